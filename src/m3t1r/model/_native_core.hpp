// The Newton core of m3t1r's compiled loop: the chain (a pinocchio::Model rebuilt from arrays, its
// closures, blocks and task), its residual and exact Jacobian, a small dense LU, and the Newton loop.
// Included by _native_newton.cpp alone (its Python glue), hence the unnamed namespace; the build
// stamps both files' sha256 into the module (tools/build_native.py).
//
// The same problems, step for step, as the Python loops they stand in for:
// m3t1r.model.kinematics.ClosedLoopSolver._newton with its predictors `_predict` and `_inverse_step`
// (single warm solves), and m3t1r.model.batch_kinematics.newton_batch (rows). FK solves the enforced
// closure rows over the passive joints; IK the closure rows and the task rows over every unlocked
// joint. Each Newton step: residual and exact Jacobian, chord steps on one LU until contraction
// slows, the largest step component capped; at convergence the 1-norm reciprocal condition test and
// the branch labels (signs of the loop blocks' determinants, plus the whole system's for IK) of the
// last factorised system. Systems are factorised in block order (`System`): the passive blocks
// first, so that their labels are read from the system's own factors, and the solves run over the
// factors' nonzeros only. No solve allocates: every buffer is the chain's, sized by `build`. The test decides as the exact reciprocal condition would, which is computed
// (from the explicit inverse) only where an O(n^2) lower bound does not clear the threshold; FK's
// tangent and IK's task columns of the inverse are solves with the last factors. Python keeps input
// checks, limits and the result objects.
//
// Residual of a closure between frames a and b (placements in the base frame):
//   "3D": R_a^T (p_b - p_a), derivative R_a^T [I, -[p_b]] (xi_b - xi_a);
//   "6D": log6(aMb),         derivative Jlog6(aMb) Ad(oMb^-1) (xi_b - xi_a);
// xi: WORLD spatial twists, the columns of computeJointJacobians' data.J masked by the supports.
// Task rows (model.task.TaskSpec): position axes p - p*, then wrap(atan2(R10, R00) - theta*) or
// log3(R*^T R), from the task frame's LOCAL_WORLD_ALIGNED Jacobian.

#pragma once

#include <pinocchio/multibody.hpp>
#include <pinocchio/spatial.hpp>
#include <pinocchio/algorithm/jacobian.hpp>
#include <pinocchio/algorithm/kinematics.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <vector>

namespace {

using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using Vector = Eigen::VectorXd;
using Model = pinocchio::Model;
using Data = pinocchio::Data;
using SE3 = pinocchio::SE3;

// Status codes shared with the Python side (batch_kinematics' row statuses).
enum Status { CONVERGED = 0, NO_ASSEMBLY = 1, NOT_CONVERGED = 2, SINGULAR = 3, BRANCH_CHANGE = 4 };

struct Closure {
  int type;                             // 3 or 6
  int frame_a, frame_b;                 // indices into Chain::frame_parent
  int first_row;                        // its first enforced row
  std::vector<int> components;          // enforced components (0..2 or 0..5)
  std::vector<std::pair<int, double>> columns;  // (velocity index, +1 or -1): joints moving b and not a, or a and not b
};

// LU with partial pivoting of a small dense matrix (LAPACK getrf's pivots: the first entry of largest
// magnitude), and what Newton takes from it: solves, the inverse, the sign of the determinant (from the
// signs of U's diagonal and the count of row swaps, as the Python loops' `_det_sign`). It replaces
// Eigen's PartialPivLU and inverse(), whose blocking and packing are made for large matrices: over 300
// warm FK solves of the M machine (callgrind, -O2) their factorisations took 6.1M instructions against
// 3.5M here, factorisations and inverses together 15.9M against 12.2M. Zero multipliers and the zeros
// of each pivot row are skipped (the same arithmetic on every entry that changes): the closure
// Jacobians are block-triangular, mostly zeros (the M machine's FK system: 64 nonzeros of 256).
class DenseLU {
 public:
  void resize(int n) {
    n_ = n;
    f_.setZero(n, n);
    pivot_.assign(static_cast<size_t>(n), 0);
    block_end_.assign(static_cast<size_t>(n), n);
    upper_.assign(static_cast<size_t>(n) * n, 0);
    lower_.assign(static_cast<size_t>(n) * n, 0);
    upper_count_.assign(static_cast<size_t>(n), 0);
    lower_count_.assign(static_cast<size_t>(n), 0);
    lower_list_.assign(static_cast<size_t>(n), 0);
    bound_.assign(static_cast<size_t>(n), 0.0);
    reciprocal_.assign(static_cast<size_t>(n), 0.0);
    pivot_values_.assign(static_cast<size_t>(n), 0.0);
  }
  double & operator()(int i, int j) { return f_(i, j); }  // fill A here, then factor()
  double * data() { return f_.data(); }  // A's entries, row by row
  void zero() { f_.setZero(); }

  // Leading diagonal blocks [start, end) of the rows and columns (ends: their end positions, in order):
  // a pivot of a block's column is then taken among its own rows unless a row below the blocks holds
  // an entry more than 1 / kBlockPivot = 100 times larger (threshold partial pivoting), so that the factors
  // of the blocks are the blocks' own LU (their determinants' signs: `block_positive`). Rows of later
  // blocks must hold zeros in earlier blocks' columns (an upper block-triangular order); without blocks,
  // or where the block's rows hold the column's largest entry, the pivot is partial pivoting's.
  void set_blocks(const std::vector<int> & ends) {
    int start = 0;
    for (const int end : ends) {
      for (int k = start; k < end; ++k) block_end_[static_cast<size_t>(k)] = end;
      start = end;
    }
  }

  // Factors A in place; false at a zero (or NaN) pivot. Keeps, row by row, the nonzero columns of L
  // (strictly below the diagonal) and of U (strictly above): the terms the solves add.
  bool factor() {
    odd_ = false;
    double * a = f_.data();
    for (int i = 0; i < n_; ++i) {
      lower_list_[i] = i;
      lower_count_[i] = 0;
    }
    for (int k = 0; k < n_; ++k) {
      const int p = pivot_row_of(k);
      pivot_[k] = p;
      if (!(std::fabs(a[p * n_ + k]) > 0.0)) return false;
      if (p != k) {
        std::swap_ranges(a + k * n_, a + (k + 1) * n_, a + p * n_);
        std::swap(lower_list_[k], lower_list_[p]);
        odd_ = !odd_;
      }
      const double * pivot_row = a + k * n_;
      // The pivot's reciprocal, as LAPACK's dgetf2 scales by it (a multiply where a division would be on
      // every elimination's and back-substitution's critical path), unless the pivot is subnormal.
      reciprocal_[k] = std::fabs(pivot_row[k]) >= std::numeric_limits<double>::min() ? 1.0 / pivot_row[k] : 0.0;
      int * nonzero = upper_.data() + k * n_;  // the pivot row's nonzero entries right of k: U's row k,
      int count = 0;                           // and the only entries an update changes
      for (int j = k + 1; j < n_; ++j) {
        nonzero[count] = j;
        count += pivot_row[j] != 0.0;
      }
      upper_count_[k] = count;
      // The pivot row's entries and the reciprocal in locals: stores into the rows below could alias
      // them for all the compiler knows, which would reload them for every row and every entry.
      double * values = pivot_values_.data();
      for (int c = 0; c < count; ++c) values[c] = pivot_row[nonzero[c]];
      const double inverse = reciprocal_[k], pivot = pivot_row[k];
      for (int i = k + 1; i < n_; ++i) {
        double * row = a + i * n_;
        if (row[k] == 0.0) continue;
        const int list = lower_list_[i];
        lower_[list * n_ + lower_count_[list]++] = k;
        const double l = row[k] = inverse != 0.0 ? row[k] * inverse : row[k] / pivot;
        for (int c = 0; c < count; ++c) row[nonzero[c]] -= l * values[c];
      }
    }
    return true;
  }

  void solve(double * b) const {  // b := A^-1 b
    const double * a = f_.data();
    for (int k = 0; k < n_; ++k) std::swap(b[k], b[pivot_[k]]);
    int first = 0;  // L's rows down to b's first nonzero leave b as it is (a unit vector: most of them)
    while (first < n_ && b[first] == 0.0) ++first;
    // Each entry summed in a local, over the factors' nonzeros in increasing column order (the terms
    // a dense loop adds, less its zero products): written through b, every term would wait for the
    // store of the one before, b possibly aliasing the factors.
    for (int i = first + 1; i < n_; ++i) {
      const int * columns = lower_.data() + lower_list_[i] * n_;
      const double * row = a + i * n_;
      double sum = b[i];
      for (int e = 0, count = lower_count_[lower_list_[i]]; e < count; ++e) sum -= row[columns[e]] * b[columns[e]];
      b[i] = sum;
    }
    for (int i = n_ - 1; i >= 0; --i) {
      const int * columns = upper_.data() + i * n_;
      const double * row = a + i * n_;
      double sum = b[i];
      for (int e = 0; e < upper_count_[i]; ++e) sum -= row[columns[e]] * b[columns[e]];
      b[i] = over_pivot(sum, i);
    }
  }

  void inverse(Matrix & out) const {  // out := A^-1, all columns at once (row operations on P I)
    out.setIdentity(n_, n_);
    const double * a = f_.data();
    double * x = out.data();
    for (int k = 0; k < n_; ++k)
      if (pivot_[k] != k) std::swap_ranges(x + k * n_, x + (k + 1) * n_, x + pivot_[k] * n_);
    for (int i = 1; i < n_; ++i) {
      const int * columns = lower_.data() + lower_list_[i] * n_;
      for (int e = 0, count = lower_count_[lower_list_[i]]; e < count; ++e)
        subtract_row(x, i, columns[e], a[i * n_ + columns[e]]);
    }
    for (int i = n_ - 1; i >= 0; --i) {
      const int * columns = upper_.data() + i * n_;
      for (int e = 0; e < upper_count_[i]; ++e) subtract_row(x, i, columns[e], a[i * n_ + columns[e]]);
      for (int c = 0; c < n_; ++c) x[i * n_ + c] = over_pivot(x[i * n_ + c], i);
    }
  }

  // An upper bound on |A^-1|_1 in O(n^2), where the inverse costs O(n^3): |A^-1| = |U^-1 L^-1 P| <=
  // M(U)^-1 M(L)^-1 entry by entry (M(T): |diagonal|, -|off-diagonal|; its inverse is nonnegative),
  // whose 1-norm is the largest entry of M(L)^-T M(U)^-T e, two triangular solves of sums of
  // nonnegative terms (no cancellation). Pessimistic by 10-2,000 on the M machine's systems.
  double inverse_one_norm_bound() const {
    const double * a = f_.data();
    double * y = bound_.data();
    // Both solves over the factors' nonzeros, each row's terms scattered once it is final: M(U)^T y = e
    // forward (y[j] gains |U[k, j]| y[k] in increasing k, the order of a dense loop), then M(L)^T z = y
    // backward (z[i] gains |L[k, i]| z[k], k decreasing).
    std::fill(bound_.begin(), bound_.end(), 1.0);
    for (int k = 0; k < n_; ++k) {
      y[k] /= std::fabs(a[k * n_ + k]);
      const int * columns = upper_.data() + k * n_;
      for (int e = 0; e < upper_count_[k]; ++e) y[columns[e]] += std::fabs(a[k * n_ + columns[e]]) * y[k];
    }
    for (int k = n_ - 1; k > 0; --k) {
      const int * columns = lower_.data() + lower_list_[k] * n_;
      for (int e = 0, count = lower_count_[lower_list_[k]]; e < count; ++e)
        y[columns[e]] += std::fabs(a[k * n_ + columns[e]]) * y[k];
    }
    double biggest = 0.0;
    for (int i = 0; i < n_; ++i) {
      if (std::isnan(y[i])) return y[i];
      if (y[i] > biggest) biggest = y[i];
    }
    return biggest;
  }

  // Whether the leading diagonal block [start, end) of a block upper-triangular A has det > 0, read
  // from the factors: its pivots all from its own rows (else false in `inside`, and nothing known).
  bool block_positive(int start, int end, bool & inside) const {
    bool positive = true;
    inside = true;
    for (int k = start; k < end; ++k) {
      if (pivot_[k] >= end) {
        inside = false;
        return false;
      }
      if ((f_(k, k) < 0.0) != (pivot_[k] != k)) positive = !positive;
    }
    return positive;
  }

  bool positive_determinant() const {
    bool positive = !odd_;
    for (int k = 0; k < n_; ++k)
      if (f_(k, k) < 0.0) positive = !positive;
    return positive;
  }

 private:
  double over_pivot(double x, int k) const {  // x / U[k, k]
    return reciprocal_[k] != 0.0 ? x * reciprocal_[k] : x / f_(k, k);
  }

  // The threshold of threshold partial pivoting (0.01, as sparse LU codes take): each such step's
  // multipliers are at most 100 in magnitude. On the M machine's IK systems along the path and over its
  // workspace the blocks' own largest entry is 0.04-0.05 times a task row's in one column (metres
  // against radians), which 0.1 would refuse.
  static constexpr double kBlockPivot = 0.01;

  // Step k's pivot row: the first entry of largest magnitude in column k at or below the diagonal
  // (LAPACK getrf's), unless k is in a leading block whose rows hold one at least kBlockPivot times it.
  int pivot_row_of(int k) const {
    const double * a = f_.data();
    const int end = block_end_[k];
    int p = k;
    double biggest = std::fabs(a[k * n_ + k]);
    for (int i = k + 1; i < end; ++i) {
      const double size = std::fabs(a[i * n_ + k]);
      if (size > biggest) {
        biggest = size;
        p = i;
      }
    }
    int below = p;
    double largest = biggest;
    for (int i = end; i < n_; ++i) {
      const double size = std::fabs(a[i * n_ + k]);
      if (size > largest) {
        largest = size;
        below = i;
      }
    }
    return biggest >= kBlockPivot * largest || end == n_ ? p : below;
  }

  void subtract_row(double * x, int i, int j, double factor) const {  // row i of x -= factor row j
    for (int c = 0; c < n_; ++c) x[i * n_ + c] -= factor * x[j * n_ + c];
  }
  int n_ = 0;
  Matrix f_;  // A, then its factors: unit L strictly below the diagonal, U on and above
  std::vector<int> pivot_;  // the row swapped with row k at step k
  std::vector<int> block_end_;  // the end of position k's leading block (n: none)
  std::vector<int> upper_, upper_count_;  // U's row k: its nonzero columns right of k, upper_[k n ...]
  std::vector<int> lower_, lower_count_;  // L's nonzero columns, by list; a list moves with its row's swaps
  std::vector<int> lower_list_;  // row i's list of L columns: lower_[lower_list_[i] n ...]
  std::vector<double> reciprocal_;  // 1 / U[k, k] (0: a subnormal pivot, divided by)
  std::vector<double> pivot_values_;  // factor's copy of the pivot row's nonzero entries
  mutable std::vector<double> bound_;  // inverse_one_norm_bound's work vector
  bool odd_ = false;  // an odd count of swaps
};

struct Block {
  std::vector<int> rows, columns;  // enforced rows, velocity indices
  DenseLU lu;
};

// The commanded components of the task frame (model.task.TaskSpec): position axes, then "yaw"
// (wrap(atan2(R10, R00) - theta*)) or "full" (log3(R*^T R)); the goal is set per IK call.
struct Task {
  std::vector<int> axes;
  int rotation = 0;  // 0 none, 1 yaw, 2 full
  int rows = 0;
  std::vector<int> columns;  // velocity indices of the joints that move the task frame
  double goal[4] = {0, 0, 0, 0};
  Eigen::Matrix3d goal_rotation = Eigen::Matrix3d::Identity();
};

// One square Newton system: FK (closure rows over the passive joints) or IK (closure and task rows
// over every unlocked joint), with its own factorisation buffers.
//
// The system is factorised in block order: the passive blocks' rows and columns first, in `Chain::blocks`'
// (upper block-triangular) order, then the other rows (IK's task rows) and unknowns (IK's actuated
// joints). Partial pivoting then takes each block column's pivot among its own block's rows, unless a
// task row's entry is larger, so the LU is that of the diagonal blocks (whose determinants' signs are
// the branch labels, read from the factors) plus a border, with no fill-in between blocks.
struct System {
  bool inverse = false;
  int rows = 0;
  std::vector<int> original;   // the unknowns (velocity indices) in the caller's order (tangent, task_inverse)
  std::vector<int> unknowns;   // the same in block order: column k of the factorised system
  std::vector<int> position;   // unknowns[k] == original[position[k]]
  std::vector<int> row_order;  // row i of the factorised system is row row_order[i] of the residual
  std::vector<int> row_position;  // row_order[row_position[r]] == r
  bool blocks_lead = false;  // the blocks are the system's leading diagonal blocks (labels from its factors)
  bool odd_order = false;    // the two orderings' permutations have, together, an odd parity
  // The entries the evaluations can make nonzero (a closure row's columns, a task row's), rows in the
  // residual's order: where each sits in the factorised system (row-major, block order) and in the
  // Jacobian (row-major), and its column there. `factor` copies only these (the M machine's FK system:
  // 64 of 256).
  struct Entry {
    int system, jacobian, column;
  };
  std::vector<Entry> pattern;
  std::vector<double> column_sums;  // one_norm's work vector, by column (block order)
  Matrix inverse_matrix;
  DenseLU lu;
};

// Parity of a permutation (true: odd), by counting its cycles.
inline bool odd_permutation(const std::vector<int> & p) {
  std::vector<unsigned char> seen(p.size(), 0);
  size_t cycles = 0;
  for (size_t i = 0; i < p.size(); ++i) {
    if (seen[i]) continue;
    ++cycles;
    for (size_t j = i; !seen[j]; j = static_cast<size_t>(p[j])) seen[j] = 1;
  }
  return (p.size() - cycles) % 2 == 1;
}

// Sets s.unknowns, s.position, s.row_order, s.row_position, s.blocks_lead and s.odd_order from
// s.original and s.rows: block order where every block's rows and columns are among the system's, else
// the caller's order.
inline void order_system(System & s, const std::vector<std::vector<int>> & block_rows,
                         const std::vector<std::vector<int>> & block_columns) {
  const size_t n = s.original.size();
  std::vector<int> rows, positions;
  std::vector<unsigned char> row_used(static_cast<size_t>(s.rows), 0), column_used(n, 0);
  bool lead = true;
  for (size_t b = 0; b < block_rows.size() && lead; ++b)
    for (size_t i = 0; i < block_rows[b].size() && lead; ++i) {
      const int r = block_rows[b][i];
      const auto found = std::find(s.original.begin(), s.original.end(), block_columns[b][i]);
      if (r < 0 || r >= s.rows || row_used[static_cast<size_t>(r)] || found == s.original.end()
          || column_used[static_cast<size_t>(found - s.original.begin())]) {
        lead = false;
        break;
      }
      row_used[static_cast<size_t>(r)] = 1;
      column_used[static_cast<size_t>(found - s.original.begin())] = 1;
      rows.push_back(r);
      positions.push_back(static_cast<int>(found - s.original.begin()));
    }
  if (!lead) {
    rows.clear();
    positions.clear();
    std::fill(row_used.begin(), row_used.end(), 0);
    std::fill(column_used.begin(), column_used.end(), 0);
  }
  for (int r = 0; r < s.rows; ++r)
    if (!row_used[static_cast<size_t>(r)]) rows.push_back(r);
  for (size_t j = 0; j < n; ++j)
    if (!column_used[j]) positions.push_back(static_cast<int>(j));
  s.blocks_lead = lead;
  s.row_order = rows;
  s.position = positions;
  s.row_position.assign(static_cast<size_t>(s.rows), 0);
  for (int i = 0; i < s.rows; ++i) s.row_position[static_cast<size_t>(rows[i])] = i;
  s.unknowns.resize(n);
  for (size_t k = 0; k < n; ++k) s.unknowns[k] = s.original[static_cast<size_t>(positions[k])];
  s.odd_order = odd_permutation(rows) != odd_permutation(positions);
  s.column_sums.assign(n, 0.0);
  s.lu.resize(s.rows);
  if (lead) {
    std::vector<int> ends;
    for (const std::vector<int> & block : block_rows) ends.push_back((ends.empty() ? 0 : ends.back()) + static_cast<int>(block.size()));
    s.lu.set_blocks(ends);
  }
}

// s.pattern from the closures' and the task's columns (velocity indices) over a Jacobian of `nv` columns,
// after order_system: row r of the residual is closure row r below `closure_rows`, task row after.
inline void set_pattern(System & s, const std::vector<Closure> & closures, const std::vector<int> & task_columns,
                        int closure_rows, int nv) {
  std::vector<int> column_of(static_cast<size_t>(nv), -1);
  const int n = static_cast<int>(s.unknowns.size());
  for (int k = 0; k < n; ++k) column_of[static_cast<size_t>(s.unknowns[k])] = k;
  s.pattern.clear();
  const auto add = [&](int r, int velocity) {
    const int j = column_of[static_cast<size_t>(velocity)];
    if (j >= 0) s.pattern.push_back({s.row_position[r] * n + j, r * nv + velocity, j});
  };
  for (const Closure & k : closures)
    for (int r = k.first_row; r < k.first_row + static_cast<int>(k.components.size()) && r < s.rows; ++r)
      for (const auto & col : k.columns) add(r, col.first);
  for (int r = closure_rows; r < s.rows; ++r)
    for (const int col : task_columns) add(r, col);
  // In the residual's row order: one_norm's sums then add the terms the dense loop added.
  std::stable_sort(s.pattern.begin(), s.pattern.end(),
                   [nv](const System::Entry & a, const System::Entry & b) { return a.jacobian / nv < b.jacobian / nv; });
}

// NewtonRules (m3t1r.model.newton_rules), passed with every call.
struct Rules {
  double tolerance = 0.0;
  int max_iterations = 0;
  double singular_rcond = 0.0, max_step = 0.0, contraction = 0.0, chord_below = 0.0, no_assembly = 0.0;
};

struct Chain {
  Model model;
  Data data;
  std::vector<int> frame_parent;
  std::vector<SE3> frame_placement, frame_world;  // frame_world: positions only where not frame_rotated
  std::vector<unsigned char> frame_rotated;
  std::vector<Closure> closures;
  std::vector<int> actuated;
  std::vector<Block> blocks;
  Task task_spec;
  System fk, ik;
  int platform = 0, task = 0, rows = 0;
  Rules rules;  // the current call's
  // Work buffers, allocated once: closure rows then task rows. The Jacobian's entries outside the
  // closures' and the task's columns are never written: zero from `build` on.
  Vector residual, step;
  Matrix jacobian;  // (rows + task rows) x nv
  std::vector<unsigned char> now;
  // The single solves' predictor buffers, allocated once: q, slider change and last step (FK), task
  // rows of the goal and of the previous goal (IK), the predicted step and its curvature term.
  Vector q, change, last_change, goal_rows, back_rows, predicted, curve;
};

void evaluate_closures(Chain & c, bool with_jacobian) {
  Eigen::Matrix<double, 6, 1> full;
  Eigen::Matrix<double, 6, 6, Eigen::RowMajor> op;  // its rows dotted with the Jacobian's columns: both contiguous
  for (const Closure & k : c.closures) {
    const SE3 & a = c.frame_world[k.frame_a];
    const SE3 & b = c.frame_world[k.frame_b];
    const int components = static_cast<int>(k.components.size());
    if (k.type == 3) {
      // R_a^T [I, -[p_b]] xi = R_a^T (v + w x p_b): the velocity of the point p_b, in frame a's axes
      const Eigen::Matrix3d & rotation = a.rotation();
      const Eigen::Vector3d & point = b.translation();
      full.head<3>() = rotation.transpose() * (point - a.translation());
      for (int r = 0; r < components; ++r) c.residual[k.first_row + r] = full[k.components[r]];
      if (!with_jacobian) continue;
      for (const auto & col : k.columns) {
        const auto twist = c.data.J.col(col.first);
        const Eigen::Vector3d velocity = twist.head<3>() + twist.tail<3>().cross(point);
        for (int r = 0; r < components; ++r)
          c.jacobian(k.first_row + r, col.first) = col.second * rotation.col(k.components[r]).dot(velocity);
      }
      continue;
    }
    const SE3 aMb = a.actInv(b);
    // log6 from the rotation's quaternion: the same twist, with one atan2 where the rotation
    // matrix's log3 takes four (3 % of forward_batch's instructions on the M machine).
    full = pinocchio::log6(Eigen::Quaterniond(aMb.rotation()), aMb.translation()).toVector();
    for (int r = 0; r < components; ++r) c.residual[k.first_row + r] = full[k.components[r]];
    if (!with_jacobian) continue;
    op = pinocchio::Jlog6(aMb) * b.inverse().toActionMatrix();
    for (int r = 0; r < components; ++r)
      for (const auto & col : k.columns)
        c.jacobian(k.first_row + r, col.first) = col.second * op.row(k.components[r]).dot(c.data.J.col(col.first));
  }
}

// Task rows of a placement for a goal (position axes, then theta or a rotation): TaskSpec.residual.
void task_residual(const Task & t, const SE3 & frame, const double * goal, const Eigen::Matrix3d & goal_rotation,
                   double * out) {
  const int count = static_cast<int>(t.axes.size());
  for (int k = 0; k < count; ++k) out[k] = frame.translation()[t.axes[k]] - goal[k];
  const Eigen::Matrix3d & rotation = frame.rotation();
  if (t.rotation == 1) {
    out[count] = std::remainder(std::atan2(rotation(1, 0), rotation(0, 0)) - goal[count], 2.0 * M_PI);
  } else if (t.rotation == 2) {
    Eigen::Map<Eigen::Vector3d>(out + count) = pinocchio::log3(goal_rotation.transpose() * rotation);
  }
}

// Task rows after the closure rows; Jacobian from the WORLD joint Jacobian: the task frame's
// LOCAL_WORLD_ALIGNED column is [v + w x p; w] for its supporting joints.
void evaluate_task(Chain & c, bool with_jacobian) {
  const Task & t = c.task_spec;
  const SE3 & frame = c.frame_world[c.task];
  const int row = c.rows, count = static_cast<int>(t.axes.size());
  task_residual(t, frame, t.goal, t.goal_rotation, c.residual.data() + row);
  if (!with_jacobian) return;
  const Eigen::Vector3d p = frame.translation();
  const Eigen::Matrix3d & rotation = frame.rotation();
  Eigen::Matrix3d jlog;
  Eigen::Vector3d yaw_row;
  if (t.rotation == 1) {
    const double c0 = rotation(0, 0), c1 = rotation(1, 0), c2 = rotation(2, 0), horizontal = c0 * c0 + c1 * c1;
    yaw_row << -c0 * c2 / horizontal, -c1 * c2 / horizontal, 1.0;
  } else if (t.rotation == 2) {
    pinocchio::Jlog3(Eigen::Matrix3d(t.goal_rotation.transpose() * rotation), jlog);
    jlog = jlog * rotation.transpose();
  }
  for (const int col : t.columns) {
    const Eigen::Vector3d v = c.data.J.col(col).head<3>(), w = c.data.J.col(col).tail<3>();
    const Eigen::Vector3d linear = v + w.cross(p);
    for (int k = 0; k < count; ++k) c.jacobian(row + k, col) = linear[t.axes[k]];
    if (t.rotation == 1) c.jacobian(row + count, col) = yaw_row.dot(w);
    if (t.rotation == 2) c.jacobian.block<3, 1>(row + count, col) = jlog * w;
  }
}

void evaluate(Chain & c, const System & s, const Vector & q, bool with_jacobian) {
  if (with_jacobian)
    pinocchio::computeJointJacobians(c.model, c.data, q);
  else
    pinocchio::forwardKinematics(c.model, c.data, q);
  for (size_t f = 0; f < c.frame_parent.size(); ++f) {
    const SE3 & joint = c.data.oMi[c.frame_parent[f]];
    if (c.frame_rotated[f])
      c.frame_world[f] = joint * c.frame_placement[f];
    else
      c.frame_world[f].translation() = joint.act(c.frame_placement[f].translation());
  }
  evaluate_closures(c, with_jacobian);
  if (s.inverse) evaluate_task(c, with_jacobian);
}

double max_abs(const Vector & v, int n) {
  double m = 0.0;
  for (int i = 0; i < n; ++i) {
    const double a = std::fabs(v[i]);
    if (std::isnan(a)) return a;
    if (a > m) m = a;
  }
  return m;
}

// Branch labels at the current Jacobian, whose system `s.lu` holds factorised: sign of each diagonal
// block's determinant of the passive closure system (true: > 0), read from s.lu's factors where the
// blocks lead the system and their pivots stayed in them (else each block factorised on its own), then
// for IK the sign of the whole system's determinant (in the caller's row and column order).
void labels(Chain & c, const System & s, unsigned char * out) {
  bool inside = s.blocks_lead;
  for (int b = 0, start = 0; inside && b < static_cast<int>(c.blocks.size()); ++b) {
    const int end = start + static_cast<int>(c.blocks[b].rows.size());
    out[b] = s.lu.block_positive(start, end, inside) ? 1 : 0;
    start = end;
  }
  for (size_t b = 0; !inside && b < c.blocks.size(); ++b) {
    Block & block = c.blocks[b];
    for (size_t i = 0; i < block.rows.size(); ++i)
      for (size_t j = 0; j < block.columns.size(); ++j)
        block.lu(static_cast<int>(i), static_cast<int>(j)) = c.jacobian(block.rows[i], block.columns[j]);
    out[b] = block.lu.factor() && block.lu.positive_determinant() ? 1 : 0;
  }
  if (s.inverse) out[c.blocks.size()] = s.lu.positive_determinant() != s.odd_order ? 1 : 0;
}

// |A|_1 (the largest column sum of |A|, summed in the residual's row order) of the system last
// factorised, from the last Jacobian (which the buffer still holds after chord steps: residual-only
// evaluations leave it alone): needed at convergence only.
double one_norm(const Chain & c, System & s) {
  std::fill(s.column_sums.begin(), s.column_sums.end(), 0.0);
  const double * jacobian = c.jacobian.data();
  for (const System::Entry & e : s.pattern) s.column_sums[e.column] += std::fabs(jacobian[e.jacobian]);
  double biggest = 0.0;
  for (const double sum : s.column_sums) {
    if (std::isnan(sum)) return sum;
    if (sum > biggest) biggest = sum;
  }
  return biggest;
}

// The 1-norm reciprocal condition of the system last factorised where it is below `threshold` (exact,
// from the inverse; NaN where the inverse overflows), else a lower bound at or above it: the exact
// value decides only where the bound from inverse_one_norm_bound does not already clear the threshold
// (with a margin for rounding).
double reciprocal_condition(const Chain & c, System & s, double threshold) {
  const double norm_a = one_norm(c, s);
  const double lower = 1.0 / (norm_a * s.lu.inverse_one_norm_bound() * (1.0 + 1e-9));
  if (lower >= threshold) return lower;
  s.lu.inverse(s.inverse_matrix);
  return 1.0 / (norm_a * s.inverse_matrix.cwiseAbs().colwise().sum().maxCoeff());
}

// T = -J_passive^-1 J_actuated (P x A, row-major, the passive joints in the caller's order) into `out`,
// by solves with FK's last factors at the Jacobian still in the buffer.
void write_tangent(Chain & c, double * out) {
  System & s = c.fk;
  const size_t n_passive = s.original.size(), n_act = c.actuated.size();
  Eigen::Map<Matrix> tangent(out, static_cast<Eigen::Index>(n_passive), static_cast<Eigen::Index>(n_act));
  for (size_t j = 0; j < n_act; ++j) {
    for (int i = 0; i < c.rows; ++i) c.step[i] = -c.jacobian(s.row_order[i], c.actuated[j]);
    s.lu.solve(c.step.data());
    for (size_t k = 0; k < n_passive; ++k) tangent(s.position[k], static_cast<Eigen::Index>(j)) = c.step[k];
  }
}

// Factors the system at the current Jacobian (in block order): its pattern's entries into zeros.
bool factor(Chain & c, System & s) {
  s.lu.zero();
  double * system = s.lu.data();
  const double * jacobian = c.jacobian.data();
  for (const System::Entry & e : s.pattern) system[e.system] = jacobian[e.jacobian];
  return s.lu.factor();
}

struct Outcome {
  int status, iterations;
  double norm, rcond = 0.0;  // rcond: the reciprocal condition of a singular outcome (0: a zero pivot)
};

// Newton from q over the system's unknowns, under c.rules. `branch` holds the labels the solution must
// have when `has_start`, else receives those at the first Jacobian. Chord steps only from residuals at
// or below rules.chord_below. On convergence the system's `lu` holds the factors of the last
// factorised system.
Outcome newton(Chain & c, System & s, Vector & q, unsigned char * branch, bool has_start, int steps_taken) {
  const Rules & rules = c.rules;
  evaluate(c, s, q, true);
  bool fresh = true;
  double previous = std::numeric_limits<double>::infinity(), norm = previous;
  int iteration = steps_taken;
  const size_t n_labels = c.blocks.size() + (s.inverse ? 1 : 0);
  for (; iteration <= rules.max_iterations + steps_taken; ++iteration) {
    norm = max_abs(c.residual, s.rows);
    if (!std::isfinite(norm)) return {NO_ASSEMBLY, iteration, norm};
    if (!fresh && norm > rules.contraction * previous && norm > rules.tolerance) {
      evaluate(c, s, q, true);
      fresh = true;
    }
    if (fresh) {
      if (!factor(c, s)) return {SINGULAR, iteration, norm};
      if (!has_start) {
        labels(c, s, branch);
        has_start = true;
      }
      fresh = false;
    }
    if (norm <= rules.tolerance) {
      const double rcond = reciprocal_condition(c, s, rules.singular_rcond);
      if (!(rcond >= rules.singular_rcond)) return {SINGULAR, iteration, norm, rcond == rcond ? rcond : 0.0};
      labels(c, s, c.now.data());
      if (std::memcmp(c.now.data(), branch, n_labels) != 0) return {BRANCH_CHANGE, iteration, norm};
      return {CONVERGED, iteration, norm};
    }
    if (iteration == rules.max_iterations + steps_taken) break;
    for (int i = 0; i < s.rows; ++i) c.step[i] = c.residual[s.row_order[i]];
    s.lu.solve(c.step.data());
    const double biggest = c.step.head(s.rows).cwiseAbs().maxCoeff();
    if (biggest > rules.max_step) c.step.head(s.rows) *= rules.max_step / biggest;
    for (size_t j = 0; j < s.unknowns.size(); ++j) q[s.unknowns[j]] -= c.step[j];
    previous = norm;
    fresh = previous > rules.chord_below;
    evaluate(c, s, q, fresh);
  }
  return {norm > rules.no_assembly || !std::isfinite(norm) ? NO_ASSEMBLY : NOT_CONVERGED, iteration, norm};
}

void write_pose(const SE3 & m, double * out) {
  Eigen::Map<Eigen::Matrix<double, 4, 4, Eigen::RowMajor>> pose(out);
  pose = m.toHomogeneousMatrix();
}

}  // namespace
