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
// last factorised system. The test decides as the exact reciprocal condition would, which is computed
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
    nonzero_.assign(static_cast<size_t>(n), 0);
  }
  double & operator()(int i, int j) { return f_(i, j); }  // fill A here, then factor()

  // Factors A in place; false at a zero (or NaN) pivot.
  bool factor() {
    odd_ = false;
    double * a = f_.data();
    for (int k = 0; k < n_; ++k) {
      int p = k;
      double biggest = std::fabs(a[k * n_ + k]);
      for (int i = k + 1; i < n_; ++i) {
        const double size = std::fabs(a[i * n_ + k]);
        if (size > biggest) {
          biggest = size;
          p = i;
        }
      }
      pivot_[k] = p;
      if (!(biggest > 0.0)) return false;
      if (p != k) {
        std::swap_ranges(a + k * n_, a + (k + 1) * n_, a + p * n_);
        odd_ = !odd_;
      }
      const double * pivot_row = a + k * n_;
      int count = 0;  // the pivot row's nonzero entries right of k: the only ones an update changes
      for (int j = k + 1; j < n_; ++j)
        if (pivot_row[j] != 0.0) nonzero_[count++] = j;
      for (int i = k + 1; i < n_; ++i) {
        double * row = a + i * n_;
        if (row[k] == 0.0) continue;
        const double l = row[k] /= pivot_row[k];
        for (int c = 0; c < count; ++c) row[nonzero_[c]] -= l * pivot_row[nonzero_[c]];
      }
    }
    return true;
  }

  void solve(double * b) const {  // b := A^-1 b
    const double * a = f_.data();
    for (int k = 0; k < n_; ++k) std::swap(b[k], b[pivot_[k]]);
    // Each entry summed in a local (in the same order): written through b, every term would wait
    // for the store of the one before, b possibly aliasing the factors.
    for (int i = 1; i < n_; ++i) {
      double sum = b[i];
      for (int j = 0; j < i; ++j) sum -= a[i * n_ + j] * b[j];
      b[i] = sum;
    }
    for (int i = n_ - 1; i >= 0; --i) {
      double sum = b[i];
      for (int j = i + 1; j < n_; ++j) sum -= a[i * n_ + j] * b[j];
      b[i] = sum / a[i * n_ + i];
    }
  }

  void inverse(Matrix & out) const {  // out := A^-1, all columns at once (row operations on P I)
    out.setIdentity(n_, n_);
    const double * a = f_.data();
    double * x = out.data();
    for (int k = 0; k < n_; ++k)
      if (pivot_[k] != k) std::swap_ranges(x + k * n_, x + (k + 1) * n_, x + pivot_[k] * n_);
    for (int i = 1; i < n_; ++i)
      for (int j = 0; j < i; ++j) subtract_row(x, i, j, a[i * n_ + j]);
    for (int i = n_ - 1; i >= 0; --i) {
      for (int j = i + 1; j < n_; ++j) subtract_row(x, i, j, a[i * n_ + j]);
      for (int c = 0; c < n_; ++c) x[i * n_ + c] /= a[i * n_ + i];
    }
  }

  // An upper bound on |A^-1|_1 in O(n^2), where the inverse costs O(n^3): |A^-1| = |U^-1 L^-1 P| <=
  // M(U)^-1 M(L)^-1 entry by entry (M(T): |diagonal|, -|off-diagonal|; its inverse is nonnegative),
  // whose 1-norm is the largest entry of M(L)^-T M(U)^-T e, two triangular solves of sums of
  // nonnegative terms (no cancellation). Pessimistic by 10-2,000 on the M machine's systems.
  double inverse_one_norm_bound() const {
    const double * a = f_.data();
    bound_.assign(static_cast<size_t>(n_), 1.0);
    double * y = bound_.data();
    for (int i = 0; i < n_; ++i) {  // M(U)^T y = e: forward, U's column i above the diagonal
      double sum = 1.0;
      for (int k = 0; k < i; ++k) sum += std::fabs(a[k * n_ + i]) * y[k];
      y[i] = sum / std::fabs(a[i * n_ + i]);
    }
    double biggest = 0.0;
    for (int i = n_ - 1; i >= 0; --i) {  // M(L)^T z = y: backward, L's column i below the diagonal
      double sum = y[i];
      for (int k = i + 1; k < n_; ++k) sum += std::fabs(a[k * n_ + i]) * y[k];
      y[i] = sum;
      if (std::isnan(sum)) return sum;
      if (sum > biggest) biggest = sum;
    }
    return biggest;
  }

  bool positive_determinant() const {
    bool positive = !odd_;
    for (int k = 0; k < n_; ++k)
      if (f_(k, k) < 0.0) positive = !positive;
    return positive;
  }

 private:
  void subtract_row(double * x, int i, int j, double factor) const {  // row i of x -= factor row j
    if (factor == 0.0) return;
    for (int c = 0; c < n_; ++c) x[i * n_ + c] -= factor * x[j * n_ + c];
  }
  int n_ = 0;
  Matrix f_;  // A, then its factors: unit L strictly below the diagonal, U on and above
  std::vector<int> pivot_;  // the row swapped with row k at step k
  std::vector<int> nonzero_;  // factor's work list of columns
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
struct System {
  bool inverse = false;
  int rows = 0;
  std::vector<int> unknowns;
  Matrix inverse_matrix;
  DenseLU lu;
};

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
  std::vector<SE3> frame_placement, frame_world;
  std::vector<Closure> closures;
  std::vector<int> actuated;
  std::vector<Block> blocks;
  Task task_spec;
  System fk, ik;
  int platform = 0, task = 0, rows = 0;
  Rules rules;  // the current call's
  // Work buffers, allocated once: closure rows then task rows.
  Vector residual, step;
  Matrix jacobian;  // (rows + task rows) x nv
  std::vector<unsigned char> now;
};

void evaluate_closures(Chain & c, bool with_jacobian) {
  Eigen::Matrix<double, 6, 1> full;
  Eigen::Matrix<double, 6, 6> op;
  for (const Closure & k : c.closures) {
    const SE3 & a = c.frame_world[k.frame_a];
    const SE3 & b = c.frame_world[k.frame_b];
    if (k.type == 3) {
      full.head<3>() = a.rotation().transpose() * (b.translation() - a.translation());
      if (with_jacobian) {
        op.topLeftCorner<3, 3>() = a.rotation().transpose();
        op.topRightCorner<3, 3>() = -a.rotation().transpose() * pinocchio::skew(b.translation());
      }
    } else {
      const SE3 aMb = a.actInv(b);
      full = pinocchio::log6(aMb).toVector();
      if (with_jacobian) op = pinocchio::Jlog6(aMb) * b.inverse().toActionMatrix();
    }
    for (size_t r = 0; r < k.components.size(); ++r) {
      const int row = k.first_row + static_cast<int>(r);
      c.residual[row] = full[k.components[r]];
      if (!with_jacobian) continue;
      for (const auto & col : k.columns)
        c.jacobian(row, col.first) = col.second * op.row(k.components[r]).dot(c.data.J.col(col.first));
    }
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
  for (int k = 0; k < t.rows; ++k) c.jacobian.row(row + k).setZero();
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
  for (size_t f = 0; f < c.frame_parent.size(); ++f)
    c.frame_world[f] = c.data.oMi[c.frame_parent[f]] * c.frame_placement[f];
  if (with_jacobian) c.jacobian.topRows(c.rows).setZero();
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

// Branch labels at the current Jacobian: sign of each diagonal block's determinant of the passive
// closure system (true: > 0), then for IK the sign of the whole system's determinant.
void labels(Chain & c, const System & s, unsigned char * out) {
  for (size_t b = 0; b < c.blocks.size(); ++b) {
    Block & block = c.blocks[b];
    for (size_t i = 0; i < block.rows.size(); ++i)
      for (size_t j = 0; j < block.columns.size(); ++j)
        block.lu(static_cast<int>(i), static_cast<int>(j)) = c.jacobian(block.rows[i], block.columns[j]);
    out[b] = block.lu.factor() && block.lu.positive_determinant() ? 1 : 0;
  }
  if (s.inverse) out[c.blocks.size()] = s.lu.positive_determinant() ? 1 : 0;
}

// |A|_1 (the largest column sum of |A|) of the system at the last Jacobian, which the buffer still holds
// after chord steps (residual-only evaluations leave it alone): needed at convergence only.
double one_norm(const Chain & c, const System & s) {
  double biggest = 0.0;
  for (size_t j = 0; j < s.unknowns.size(); ++j) {
    double sum = 0.0;
    for (int i = 0; i < s.rows; ++i) sum += std::fabs(c.jacobian(i, s.unknowns[j]));
    if (std::isnan(sum)) return sum;
    if (sum > biggest) biggest = sum;
  }
  return biggest;
}

bool factor(Chain & c, System & s) {
  for (int i = 0; i < s.rows; ++i)
    for (size_t j = 0; j < s.unknowns.size(); ++j) s.lu(i, static_cast<int>(j)) = c.jacobian(i, s.unknowns[j]);
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
      // The exact reciprocal condition decides only where its lower bound from
      // inverse_one_norm_bound does not already clear the threshold (with a margin for rounding).
      const double norm_a = one_norm(c, s);
      const double lower = 1.0 / (norm_a * s.lu.inverse_one_norm_bound() * (1.0 + 1e-9));
      if (!(lower >= rules.singular_rcond)) {
        s.lu.inverse(s.inverse_matrix);
        const double rcond = 1.0 / (norm_a * s.inverse_matrix.cwiseAbs().colwise().sum().maxCoeff());
        if (!(rcond >= rules.singular_rcond)) return {SINGULAR, iteration, norm, rcond == rcond ? rcond : 0.0};
      }
      labels(c, s, c.now.data());
      if (std::memcmp(c.now.data(), branch, n_labels) != 0) return {BRANCH_CHANGE, iteration, norm};
      return {CONVERGED, iteration, norm};
    }
    if (iteration == rules.max_iterations + steps_taken) break;
    c.step.head(s.rows) = c.residual.head(s.rows);
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
