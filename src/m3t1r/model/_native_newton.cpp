// Closed-loop FK and IK of a tree of 1-DoF joints in one compiled Newton loop on Pinocchio's C++ API
// (built by tools/build_native.py; m3t1r.model.native is its Python side).
//
// This file is the Python glue (buffers, the capsule, threads); the Newton core is _native_core.hpp.

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "_native_core.hpp"

#include <pinocchio/math.hpp>  // rpy::matrixToRpy

#include <memory>
#include <mutex>
#include <string>
#include <thread>

namespace {

// ---- Python glue: arrays by the buffer protocol, the chain in a capsule -----------------------------

struct Buffer {
  Py_buffer view{};
  bool held = false;
  ~Buffer() { if (held) PyBuffer_Release(&view); }
  bool get(PyObject * obj, bool writable, char kind, Py_ssize_t count, const char * what) {
    const int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, &view, flags) != 0) return false;
    held = true;
    const char * format = view.format ? view.format : "B";
    const bool ok_kind = (kind == 'd' && std::strcmp(format, "d") == 0 && view.itemsize == 8)
                         || (kind == 'q' && (std::strcmp(format, "q") == 0 || std::strcmp(format, "l") == 0)
                             && view.itemsize == 8)
                         || (kind == 'B' && view.itemsize == 1);
    if (!ok_kind || (count >= 0 && view.len / view.itemsize != count)) {
      PyErr_Format(PyExc_ValueError, "%s: expected %zd items of kind %c", what, count, kind);
      return false;
    }
    return true;
  }
  double * d() const { return static_cast<double *>(view.buf); }
  long long * q() const { return static_cast<long long *>(view.buf); }
  unsigned char * b() const { return static_cast<unsigned char *>(view.buf); }
  Py_ssize_t items() const { return view.len / view.itemsize; }
};

SE3 se3_from(const double * h) {
  const Eigen::Map<const Eigen::Matrix<double, 4, 4, Eigen::RowMajor>> m(h);
  return SE3(m.topLeftCorner<3, 3>(), m.topRightCorner<3, 1>());
}

pinocchio::JointModel joint_of(long long kind, const double * axis) {
  switch (kind) {
    case 0: return pinocchio::JointModelRX();
    case 1: return pinocchio::JointModelRY();
    case 2: return pinocchio::JointModelRZ();
    case 3: return pinocchio::JointModelRevoluteUnaligned(axis[0], axis[1], axis[2]);
    case 4: return pinocchio::JointModelPX();
    case 5: return pinocchio::JointModelPY();
    case 6: return pinocchio::JointModelPZ();
    default: return pinocchio::JointModelPrismaticUnaligned(axis[0], axis[1], axis[2]);
  }
}

// What the capsule owns: the chain, and a lock held by every solve on it. A batch releases the GIL
// while it runs; a single solve from another Python thread then waits for the lock instead of
// sharing the chain's buffers (it holds the GIL meanwhile, which the batch needs only after unlocking).
// `bind` gives it the warm-start arrays that every single solve reads and writes (held until the
// capsule goes): FK's tangent, labels, platform and task placements, IK's task inverse, labels and
// placements; FK's history (the sliders and passive joints its last success started from, which the
// next one's second-order predictor reads) and IK's actuators; and the model's joint limits (lower,
// upper: nq), which single solves check.
struct Handle {
  Chain chain;
  std::mutex lock;
  Buffer tangent, branch, platform, task, task_inverse, inverse_branch, inverse_platform, inverse_task, history,
      inverse_actuators, lower, upper;
  std::vector<double> start;  // FK's start, kept for `history` until the solve succeeds
  bool bound = false;
};

// A single solve's code for sliders given beyond their limits: nothing was solved or changed (the caller
// names the slider). After Newton's codes (Status), which batch rows share.
constexpr int SLIDER_BEYOND_LIMIT = 5;

// Roll and pitch [rad] of a rotation, as m3t1r.model.rotations.roll_pitch_of: Pinocchio's ZYX (yaw-pitch-roll)
// convention, pitch = atan2(-R20, |(R21, R22)|), roll = atan2(R21, R22), and its matrixToRpy near gimbal lock.
std::pair<double, double> roll_pitch(const Eigen::Matrix3d & r) {
  const double pitch = std::atan2(-r(2, 0), std::sqrt(r(2, 1) * r(2, 1) + r(2, 2) * r(2, 2)));
  if (std::abs(std::abs(pitch) - 0.5 * M_PI) < 1e-2) {
    const Eigen::Vector3d rpy = pinocchio::rpy::matrixToRpy(r);
    return {rpy[0], rpy[1]};
  }
  return {std::atan2(r(2, 1), r(2, 2)), pitch};
}

// The first coordinate of q outside [lower, upper] (NaN counts as outside), or -1.
long first_beyond_limits(const Handle & h, const double * q, Py_ssize_t nq) {
  const double *lower = h.lower.d(), *upper = h.upper.d();
  for (Py_ssize_t k = 0; k < nq; ++k)
    if (!(lower[k] <= q[k] && q[k] <= upper[k])) return static_cast<long>(k);
  return -1;
}

void destroy(PyObject * capsule) {
  delete static_cast<Handle *>(PyCapsule_GetPointer(capsule, "m3t1r.Chain"));
}

Handle * handle_of(PyObject * capsule) {
  return static_cast<Handle *>(PyCapsule_GetPointer(capsule, "m3t1r.Chain"));
}

// build(joints (J,2) int64 [parent, kind], axes (J,3), placements (J,4,4), frame_parents (F,) int64,
//       frame_placements (F,4,4), closures (C,4) int64 [type, frame_a, frame_b, first_row],
//       components (R,) int64, column_signs (C, nv) float, passive (P,), actuated (A,) int64,
//       block_rows (P,), block_columns (P,), block_ends (B,), unknowns (U,) (IK's columns),
//       task_axes (k,), task_columns (m,) int64 (joints moving the task frame),
//       platform, task (frame indices), task_rotation (0 none, 1 yaw, 2 full): int)
PyObject * build(PyObject *, PyObject * args) {
  PyObject * o[16];
  int platform, task, task_rotation;
  if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOOOOiii", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7],
                        &o[8], &o[9], &o[10], &o[11], &o[12], &o[13], &o[14], &o[15], &platform, &task,
                        &task_rotation))
    return nullptr;
  Buffer joints, axes, placements, fparents, fplacements, closures, components, signs, passive, actuated,
      brows, bcols, bends, unknowns, taxes, tcols;
  if (!joints.get(o[0], false, 'q', -1, "joints")) return nullptr;
  const Py_ssize_t n_joints = joints.items() / 2;
  if (!axes.get(o[1], false, 'd', 3 * n_joints, "axes") || !placements.get(o[2], false, 'd', 16 * n_joints, "placements")
      || !fparents.get(o[3], false, 'q', -1, "frame_parents")
      || !fplacements.get(o[4], false, 'd', 16 * fparents.items(), "frame_placements")
      || !closures.get(o[5], false, 'q', -1, "closures") || !components.get(o[6], false, 'q', -1, "components")
      || !signs.get(o[7], false, 'd', (closures.items() / 4) * n_joints, "column_signs")
      || !passive.get(o[8], false, 'q', -1, "passive") || !actuated.get(o[9], false, 'q', -1, "actuated")
      || !brows.get(o[10], false, 'q', passive.items(), "block_rows")
      || !bcols.get(o[11], false, 'q', passive.items(), "block_columns") || !bends.get(o[12], false, 'q', -1, "block_ends")
      || !unknowns.get(o[13], false, 'q', -1, "unknowns") || !taxes.get(o[14], false, 'q', -1, "task_axes")
      || !tcols.get(o[15], false, 'q', -1, "task_columns"))
    return nullptr;
  auto handle = std::make_unique<Handle>();
  Chain * c = &handle->chain;
  for (Py_ssize_t j = 0; j < n_joints; ++j) {
    const long long parent = joints.q()[2 * j];
    if (parent < 0 || parent > j) {
      PyErr_SetString(PyExc_ValueError, "joints: parents must precede their children");
      return nullptr;
    }
    c->model.addJoint(static_cast<pinocchio::JointIndex>(parent), joint_of(joints.q()[2 * j + 1], axes.d() + 3 * j),
                      se3_from(placements.d() + 16 * j), "j" + std::to_string(j + 1));
  }
  c->data = Data(c->model);
  const int nv = c->model.nv;
  for (Py_ssize_t f = 0; f < fparents.items(); ++f) {
    c->frame_parent.push_back(static_cast<int>(fparents.q()[f]));
    c->frame_placement.push_back(se3_from(fplacements.d() + 16 * f));
  }
  c->frame_world.resize(c->frame_parent.size());
  const Py_ssize_t n_closures = closures.items() / 4;
  Py_ssize_t component = 0;
  for (Py_ssize_t k = 0; k < n_closures; ++k) {
    Closure closure;
    const long long * spec = closures.q() + 4 * k;
    closure.type = static_cast<int>(spec[0]);
    closure.frame_a = static_cast<int>(spec[1]);
    closure.frame_b = static_cast<int>(spec[2]);
    closure.first_row = static_cast<int>(spec[3]);
    const Py_ssize_t end = k + 1 < n_closures ? (closures.q() + 4 * (k + 1))[3] : components.items();
    for (; component < end; ++component) closure.components.push_back(static_cast<int>(components.q()[component]));
    for (int v = 0; v < nv; ++v)
      if (signs.d()[k * nv + v] != 0.0) closure.columns.emplace_back(v, signs.d()[k * nv + v]);
    c->closures.push_back(closure);
  }
  c->rows = static_cast<int>(components.items());
  for (Py_ssize_t j = 0; j < actuated.items(); ++j) c->actuated.push_back(static_cast<int>(actuated.q()[j]));
  long long start = 0;
  for (Py_ssize_t b = 0; b < bends.items(); ++b) {
    Block block;
    for (long long i = start; i < bends.q()[b]; ++i) {
      block.rows.push_back(static_cast<int>(brows.q()[i]));
      block.columns.push_back(static_cast<int>(bcols.q()[i]));
    }
    block.lu.resize(static_cast<int>(block.rows.size()));
    start = bends.q()[b];
    c->blocks.push_back(std::move(block));
  }
  Task & t = c->task_spec;
  for (Py_ssize_t k = 0; k < taxes.items(); ++k) t.axes.push_back(static_cast<int>(taxes.q()[k]));
  for (Py_ssize_t k = 0; k < tcols.items(); ++k) t.columns.push_back(static_cast<int>(tcols.q()[k]));
  t.rotation = task_rotation;
  t.rows = static_cast<int>(t.axes.size()) + (task_rotation == 1 ? 1 : task_rotation == 2 ? 3 : 0);
  c->fk.rows = c->rows;
  for (Py_ssize_t j = 0; j < passive.items(); ++j) c->fk.original.push_back(static_cast<int>(passive.q()[j]));
  c->ik.inverse = true;
  c->ik.rows = c->rows + t.rows;
  for (Py_ssize_t j = 0; j < unknowns.items(); ++j) c->ik.original.push_back(static_cast<int>(unknowns.q()[j]));
  std::vector<std::vector<int>> block_rows, block_columns;
  for (const Block & block : c->blocks) {
    block_rows.push_back(block.rows);
    block_columns.push_back(block.columns);
  }
  for (System * s : {&c->fk, &c->ik}) {
    if (static_cast<int>(s->original.size()) != s->rows) {
      PyErr_SetString(PyExc_ValueError, "a Newton system is not square");
      return nullptr;
    }
    order_system(*s, block_rows, block_columns);
    set_pattern(*s, c->closures, t.columns, c->rows, nv);
  }
  c->platform = platform;
  c->task = task;
  const int n_frames = static_cast<int>(c->frame_parent.size());
  const auto known = [n_frames](int f) { return 0 <= f && f < n_frames; };
  bool frames_known = known(platform) && known(task);
  for (const Closure & k : c->closures) frames_known = frames_known && known(k.frame_a) && known(k.frame_b);
  if (!frames_known) {
    PyErr_SetString(PyExc_ValueError, "a closure, platform or task frame is not among frame_parents");
    return nullptr;
  }
  // A frame only a 3D closure's frame b names needs its position alone (R_a^T (p_b - p_a)).
  c->frame_rotated.assign(c->frame_parent.size(), 0);
  c->frame_rotated[static_cast<size_t>(platform)] = c->frame_rotated[static_cast<size_t>(task)] = 1;
  for (const Closure & k : c->closures) {
    c->frame_rotated[static_cast<size_t>(k.frame_a)] = 1;
    if (k.type == 6) c->frame_rotated[static_cast<size_t>(k.frame_b)] = 1;
  }
  c->residual = Vector::Zero(c->ik.rows);
  c->jacobian = Matrix::Zero(c->ik.rows, nv);
  c->step = Vector::Zero(c->ik.rows);
  c->now.resize(c->blocks.size() + 1);
  const Eigen::Index most = std::max<Eigen::Index>(c->ik.rows, static_cast<Eigen::Index>(c->fk.original.size()));
  c->q = Vector::Zero(c->model.nq);
  c->change = Vector::Zero(static_cast<Eigen::Index>(c->actuated.size()));
  c->last_change = c->change;
  c->goal_rows = Vector::Zero(t.rows);
  c->back_rows = c->goal_rows;
  c->predicted = Vector::Zero(most);
  c->curve = c->predicted;
  return PyCapsule_New(handle.release(), "m3t1r.Chain", destroy);
}

// bind(chain, tangent (P*A,), branch (B,) uint8, platform (16,), task (16,), task_inverse (U*T,),
//      inverse_branch (B+1,) uint8, inverse_platform (16,), inverse_task (16,)): the arrays `forward` and
// `inverse` then read and write (writable, C-contiguous; kept until the chain goes), once per chain.
PyObject * bind(PyObject *, PyObject * args) {
  PyObject *capsule, *o[12];
  if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOO", &capsule, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7],
                        &o[8], &o[9], &o[10], &o[11]))
    return nullptr;
  Handle * handle = handle_of(capsule);
  if (handle == nullptr) return nullptr;
  if (handle->bound) {
    PyErr_SetString(PyExc_ValueError, "bind: the chain's arrays are bound already");
    return nullptr;
  }
  const Chain & c = handle->chain;
  const Py_ssize_t blocks = static_cast<Py_ssize_t>(c.blocks.size());
  const Py_ssize_t tangent = static_cast<Py_ssize_t>(c.fk.original.size() * c.actuated.size());
  const Py_ssize_t task_inverse = static_cast<Py_ssize_t>(c.ik.original.size()) * c.task_spec.rows;
  const Py_ssize_t n_history = static_cast<Py_ssize_t>(c.actuated.size() + c.fk.original.size());
  if (!handle->tangent.get(o[0], true, 'd', tangent, "tangent") || !handle->branch.get(o[1], true, 'B', blocks, "branch")
      || !handle->platform.get(o[2], true, 'd', 16, "platform") || !handle->task.get(o[3], true, 'd', 16, "task")
      || !handle->task_inverse.get(o[4], true, 'd', task_inverse, "task_inverse")
      || !handle->inverse_branch.get(o[5], true, 'B', blocks + 1, "inverse_branch")
      || !handle->inverse_platform.get(o[6], true, 'd', 16, "inverse_platform")
      || !handle->inverse_task.get(o[7], true, 'd', 16, "inverse_task")
      || !handle->history.get(o[8], true, 'd', n_history, "history")
      || !handle->inverse_actuators.get(o[9], true, 'd', static_cast<Py_ssize_t>(c.actuated.size()), "inverse_actuators")
      || !handle->lower.get(o[10], false, 'd', c.model.nq, "lower")
      || !handle->upper.get(o[11], false, 'd', c.model.nq, "upper"))
    return nullptr;  // the views taken so far are released with the capsule
  handle->start.resize(static_cast<size_t>(n_history));
  handle->bound = true;
  Py_RETURN_NONE;
}

// The call's Newton rules (NewtonRules.compiled(): tolerance, max_iterations, singular_rcond, max_step,
// chord_contraction, chord_below, no_assembly), the last seven arguments of every solve.
#define RULES_FORMAT "diddddd"
#define RULES_ARGS(r) &r.tolerance, &r.max_iterations, &r.singular_rcond, &r.max_step, &r.contraction, \
    &r.chord_below, &r.no_assembly

// The capsule's chain for a single solve: `lock` takes its lock for the call, and the call's rules are
// set (nullptr, with the Python error set, when the capsule holds no chain).
Handle * open_chain(PyObject * capsule, std::unique_lock<std::mutex> & lock, const Rules & rules) {
  Handle * handle = handle_of(capsule);
  if (handle == nullptr) return nullptr;
  if (!handle->bound) {
    PyErr_SetString(PyExc_ValueError, "the chain's warm-start arrays are not bound (bind)");
    return nullptr;
  }
  lock = std::unique_lock<std::mutex>(handle->lock);
  handle->chain.rules = rules;
  return handle;
}

// forward(chain, q (nq,) in/out, sliders (A,), order, previous (A+P,), has_start,
//         rules (7, RULES_FORMAT)) -> (status, residual, iterations, rcond of a singular end,
//         first coordinate of the solution beyond its joint limits or -1)
// with the bound tangent (in/out), branch (in/out), platform and task (out), history (out: q's sliders and
// passive joints, the start, on success; `previous` may be it). Sliders beyond their limits (or NaN)
// return SLIDER_BEYOND_LIMIT at once, touching nothing.
// q: the last solution; `order` 1 or 2 moves its passive joints by the predictor of
// ClosedLoopSolver._predict (tangent T of the last success; order 2 adds lam^2 (p_prev - p + T e) with
// e = a - a_prev, lam = (d . e) / (e . e), d the slider change, previous = (a_prev, p_prev)); then the
// sliders are set and Newton runs under the rules. On success tangent = -J_passive^-1 J_actuated.
PyObject * forward(PyObject *, PyObject * args) {
  PyObject *capsule, *oq, *osliders, *oprevious;
  int order, has_start;
  Rules rules;
  if (!PyArg_ParseTuple(args, "OOOiOp" RULES_FORMAT, &capsule, &oq, &osliders, &order, &oprevious, &has_start,
                        RULES_ARGS(rules)))
    return nullptr;
  std::unique_lock<std::mutex> lock;
  Handle * handle = open_chain(capsule, lock, rules);
  if (handle == nullptr) return nullptr;
  Chain * c = &handle->chain;
  const size_t n_passive = c->fk.original.size(), n_act = c->actuated.size();
  Buffer bq, bsliders, bprevious;
  if (!bq.get(oq, true, 'd', c->model.nq, "q") || !bsliders.get(osliders, false, 'd', n_act, "sliders")
      || !bprevious.get(oprevious, false, 'd', order == 2 ? static_cast<Py_ssize_t>(n_act + n_passive) : -1, "previous"))
    return nullptr;
  const Buffer &btangent = handle->tangent, &bbranch = handle->branch, &bplatform = handle->platform,
               &btask = handle->task;
  for (size_t j = 0; j < n_act; ++j) {
    const double value = bsliders.d()[j];
    if (!(handle->lower.d()[c->actuated[j]] <= value && value <= handle->upper.d()[c->actuated[j]]))
      return Py_BuildValue("(ididl)", SLIDER_BEYOND_LIMIT, 0.0, 0, 0.0, -1L);
  }
  Eigen::Map<Vector> qmap(bq.d(), c->model.nq);
  Eigen::Map<Matrix> tangent(btangent.d(), n_passive, n_act);
  Vector & q = c->q;
  q = qmap;
  for (size_t j = 0; j < n_act; ++j) handle->start[j] = q[c->actuated[j]];
  for (size_t j = 0; j < n_passive; ++j) handle->start[n_act + j] = q[c->fk.original[j]];
  if (order >= 1) {
    Vector &change = c->change, &e = c->last_change;
    for (size_t j = 0; j < n_act; ++j) change[j] = bsliders.d()[j] - q[c->actuated[j]];
    auto step = c->predicted.head(static_cast<Eigen::Index>(n_passive));
    step.noalias() = tangent * change;
    if (order == 2) {
      for (size_t j = 0; j < n_act; ++j) e[j] = q[c->actuated[j]] - bprevious.d()[j];
      const double ee = e.dot(e), lam = ee > 0.0 ? change.dot(e) / ee : 0.0;
      if (0.0 < lam && lam < 2.0) {
        auto curve = c->curve.head(static_cast<Eigen::Index>(n_passive));
        curve.noalias() = tangent * e;
        for (size_t j = 0; j < n_passive; ++j) curve[j] += bprevious.d()[n_act + j] - q[c->fk.original[j]];
        step += lam * lam * curve;
      }
    }
    for (size_t j = 0; j < n_passive; ++j) q[c->fk.original[j]] += step[j];
  }
  for (size_t j = 0; j < n_act; ++j) q[c->actuated[j]] = bsliders.d()[j];
  const Outcome out = newton(*c, c->fk, q, bbranch.b(), has_start != 0, 0);
  qmap = q;
  if (out.status == CONVERGED) {
    write_tangent(*c, btangent.d());
    std::copy(handle->start.begin(), handle->start.end(), handle->history.d());
    write_pose(c->frame_world[c->platform], bplatform.d());
    write_pose(c->frame_world[c->task], btask.d());
  }
  const long beyond = out.status == CONVERGED ? first_beyond_limits(*handle, bq.d(), c->model.nq) : -1;
  return Py_BuildValue("(ididl)", out.status, out.norm, out.iterations, out.rcond, beyond);
}

// inverse(chain, q (nq,) in/out, goal (task coordinates), goal_rotation (9,), order,
//         previous_goal (task coordinates), previous_rotation (9,), previous_q (nq,), has_start,
//         rules (7, RULES_FORMAT)) -> (status, residual, iterations, rcond of a singular end,
//         first coordinate of the solution beyond its joint limits or -1, roll, pitch of the task frame)
// with the bound task_inverse (in/out), inverse_task (in: last_task, the last success's; out),
// inverse_branch (in/out), inverse_platform and inverse_actuators (out).
// q: the last solution; `order` 1 or 2 moves its unknown joints by ClosedLoopSolver._inverse_step's
// predictor (X the task columns of the last inverse, r the new goal's task rows at last_task; order 2
// adds lam^2 (q_prev - q + X b), b the previous goal's rows, lam = -(r . b) / (b . b)). Newton under the
// rules; on success task_inverse = the task-row columns of the inverse of the last system.
PyObject * inverse(PyObject *, PyObject * args) {
  PyObject *capsule, *oq, *ogoal, *orot, *opgoal, *oprot, *opq;
  int order, has_start;
  Rules rules;
  if (!PyArg_ParseTuple(args, "OOOOiOOOp" RULES_FORMAT, &capsule, &oq, &ogoal, &orot, &order, &opgoal, &oprot, &opq,
                        &has_start, RULES_ARGS(rules)))
    return nullptr;
  std::unique_lock<std::mutex> lock;
  Handle * handle = open_chain(capsule, lock, rules);
  if (handle == nullptr) return nullptr;
  Chain * c = &handle->chain;
  Task & t = c->task_spec;
  const size_t n_unknowns = c->ik.original.size();
  const Py_ssize_t needed = static_cast<Py_ssize_t>(t.axes.size()) + (t.rotation == 1 ? 1 : 0);
  Buffer bq, bgoal, brot, bpgoal, bprot, bpq;
  if (!bq.get(oq, true, 'd', c->model.nq, "q") || !bgoal.get(ogoal, false, 'd', -1, "goal")
      || !brot.get(orot, false, 'd', 9, "goal_rotation")
      || !bpgoal.get(opgoal, false, 'd', order == 2 ? bgoal.items() : -1, "previous_goal")
      || !bprot.get(oprot, false, 'd', order == 2 ? 9 : -1, "previous_rotation")
      || !bpq.get(opq, false, 'd', order == 2 ? c->model.nq : -1, "previous_q"))
    return nullptr;
  // The last success's task frame (the predictor's), overwritten by this one's on success.
  const Buffer &binverse = handle->task_inverse, &blast = handle->inverse_task, &bbranch = handle->inverse_branch,
               &bplatform = handle->inverse_platform, &btask = handle->inverse_task;
  if (bgoal.items() < needed || bgoal.items() > 4 + static_cast<Py_ssize_t>(t.axes.size())) {
    PyErr_SetString(PyExc_ValueError, "goal: wrong number of task coordinates");
    return nullptr;
  }
  for (Py_ssize_t k = 0; k < needed; ++k) t.goal[k] = bgoal.d()[k];
  t.goal_rotation = Eigen::Map<const Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(brot.d());
  Eigen::Map<Vector> qmap(bq.d(), c->model.nq);
  Eigen::Map<Matrix> task_inverse(binverse.d(), n_unknowns, t.rows);
  Vector & q = c->q;
  q = qmap;
  if (order >= 1) {
    const SE3 last = se3_from(blast.d());
    Vector &rows = c->goal_rows, &back = c->back_rows;
    task_residual(t, last, t.goal, t.goal_rotation, rows.data());
    auto step = c->predicted.head(static_cast<Eigen::Index>(n_unknowns));
    step.noalias() = task_inverse * rows;  // negated below: -(X r) would be evaluated into a temporary
    step = -step;
    if (order == 2) {
      const Eigen::Matrix3d previous_rotation = Eigen::Map<const Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(bprot.d());
      task_residual(t, last, bpgoal.d(), previous_rotation, back.data());
      const double bb = back.dot(back), lam = bb > 0.0 ? -rows.dot(back) / bb : 0.0;
      if (0.0 < lam && lam < 2.0) {
        auto curve = c->curve.head(static_cast<Eigen::Index>(n_unknowns));
        curve.noalias() = task_inverse * back;
        for (size_t j = 0; j < n_unknowns; ++j) curve[j] += bpq.d()[c->ik.original[j]] - q[c->ik.original[j]];
        step += lam * lam * curve;
      }
    }
    for (size_t j = 0; j < n_unknowns; ++j) q[c->ik.original[j]] += step[j];
  }
  const Outcome out = newton(*c, c->ik, q, bbranch.b(), has_start != 0, 0);
  qmap = q;
  if (out.status == CONVERGED) {
    for (int k = 0; k < t.rows; ++k) {  // the task rows' columns of the inverse: solves of unit vectors
      c->step.setZero();
      c->step[c->ik.row_position[c->rows + k]] = 1.0;
      c->ik.lu.solve(c->step.data());
      for (size_t m = 0; m < n_unknowns; ++m) task_inverse(c->ik.position[m], k) = c->step[m];
    }
    for (size_t j = 0; j < c->actuated.size(); ++j) handle->inverse_actuators.d()[j] = q[c->actuated[j]];
    write_pose(c->frame_world[c->platform], bplatform.d());
    write_pose(c->frame_world[c->task], btask.d());
  }
  const long beyond = out.status == CONVERGED ? first_beyond_limits(*handle, bq.d(), c->model.nq) : -1;
  const auto [roll, pitch] = out.status == CONVERGED ? roll_pitch(c->frame_world[c->task].rotation())
                                                     : std::pair<double, double>(0.0, 0.0);
  return Py_BuildValue("(ididldd)", out.status, out.norm, out.iterations, out.rcond, beyond, roll, pitch);
}

// Where a row batch reads and writes: q (n, nq) in/out, optional labels every row must end with, per-row
// goals (IK: n x goal_width task coordinates and n x 9 rotations), and per-row outputs.
struct Rows {
  double * q;
  const unsigned char * given;
  const double * goals = nullptr;
  const double * rotations = nullptr;
  Py_ssize_t goal_width = 0;
  int steps_taken;
  long long * status;
  double * norms;
  long long * iterations;
  double * platform;
};

// Rows [begin, end) on one chain (its own Data and buffers: one per thread).
void solve_rows(Chain & c, bool inverse, const Rows & r, Py_ssize_t begin, Py_ssize_t end) {
  System & s = inverse ? c.ik : c.fk;
  const size_t n_labels = c.blocks.size() + (inverse ? 1 : 0);
  std::vector<unsigned char> branch(n_labels);
  Vector q(c.model.nq);
  Task & t = c.task_spec;
  const Py_ssize_t needed = static_cast<Py_ssize_t>(t.axes.size()) + (t.rotation == 1 ? 1 : 0);
  for (Py_ssize_t i = begin; i < end; ++i) {
    if (r.given != nullptr) std::memcpy(branch.data(), r.given, n_labels);
    if (inverse) {
      for (Py_ssize_t k = 0; k < needed; ++k) t.goal[k] = r.goals[i * r.goal_width + k];
      t.goal_rotation = Eigen::Map<const Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(r.rotations + 9 * i);
    }
    Eigen::Map<Vector> row(r.q + i * c.model.nq, c.model.nq);
    q = row;
    const Outcome out = newton(c, s, q, branch.data(), r.given != nullptr, r.steps_taken);
    row = q;
    r.status[i] = out.status;
    r.norms[i] = out.norm;
    r.iterations[i] = out.iterations;
    if (out.status == CONVERGED) write_pose(c.frame_world[c.platform], r.platform + 16 * i);
  }
}

// The rows on `threads` threads (at least 64 rows each): the first on the chain itself, the others on
// copies of it. Rows are independent: the results do not depend on the thread count. Call without the
// GIL, holding the chain's lock.
void solve_rows_threaded(Chain & c, bool inverse, const Rows & r, Py_ssize_t n, int threads) {
  const Py_ssize_t workers = std::max<Py_ssize_t>(1, std::min<Py_ssize_t>(threads, n / 64));
  const Py_ssize_t share = (n + workers - 1) / workers;
  std::vector<Chain> copies(static_cast<size_t>(workers - 1), c);
  std::vector<std::thread> pool;
  for (Py_ssize_t w = 1; w < workers; ++w)
    pool.emplace_back(solve_rows, std::ref(copies[w - 1]), inverse, std::cref(r), w * share,
                      std::min(n, (w + 1) * share));
  solve_rows(c, inverse, r, 0, std::min(n, share));
  for (std::thread & thread : pool) thread.join();
}

// rows(chain, inverse, q (n, nq) in/out, branch (B or B+1,) uint8 or empty (labels at each row's start),
//      goals (n, g) and rotations (n, 9) (IK; empty for FK), steps_taken, status (n,) int64 out,
//      residual (n,) out, iterations (n,) int64 out, platform (n, 16) out,
//      rules (7, RULES_FORMAT), threads):
//   FK or IK Newton row by row, without predictor (the caller sets each start), tangent or inverse
//   (the task frame's placements, where it is not the platform, come from the rows' q).
PyObject * rows(PyObject *, PyObject * args) {
  PyObject *capsule, *oq, *obranch, *ogoals, *orots, *ostatus, *onorm, *oiter, *oplatform;
  int inverse, steps_taken, threads;
  Rules rules;
  if (!PyArg_ParseTuple(args, "OpOOOOiOOOO" RULES_FORMAT "i", &capsule, &inverse, &oq, &obranch, &ogoals, &orots,
                        &steps_taken, &ostatus, &onorm, &oiter, &oplatform, RULES_ARGS(rules), &threads))
    return nullptr;
  Handle * handle = handle_of(capsule);
  if (handle == nullptr) return nullptr;
  Chain * c = &handle->chain;
  Buffer bq, bbranch, bgoals, brots, bstatus, bnorm, biter, bplatform;
  if (!bq.get(oq, true, 'd', -1, "q") || !bbranch.get(obranch, false, 'B', -1, "branch")
      || !bgoals.get(ogoals, false, 'd', -1, "goals") || !brots.get(orots, false, 'd', -1, "rotations"))
    return nullptr;
  const Py_ssize_t n = bq.items() / c->model.nq;
  const Py_ssize_t labels = static_cast<Py_ssize_t>(c->blocks.size()) + (inverse ? 1 : 0);
  const Py_ssize_t width = n > 0 ? bgoals.items() / n : 0;
  const Task & t = c->task_spec;
  const bool goals_ok = !inverse || (bgoals.items() == n * width && brots.items() == 9 * n
                                     && (n == 0 || (width >= static_cast<Py_ssize_t>(t.axes.size()) + (t.rotation == 1)
                                                    && width <= static_cast<Py_ssize_t>(t.axes.size()) + 4)));
  if (bq.items() != n * c->model.nq || (bbranch.items() > 0 && bbranch.items() != labels) || !goals_ok
      || (inverse && t.rows == 0) || !bstatus.get(ostatus, true, 'q', n, "status")
      || !bnorm.get(onorm, true, 'd', n, "residual") || !biter.get(oiter, true, 'q', n, "iterations")
      || !bplatform.get(oplatform, true, 'd', 16 * n, "platform")) {
    if (!PyErr_Occurred()) PyErr_SetString(PyExc_ValueError, "q, branch or goals: wrong size (or no square IK)");
    return nullptr;
  }
  Rows r{bq.d(), bbranch.items() > 0 ? bbranch.b() : nullptr, bgoals.d(), brots.d(), width, steps_taken,
         bstatus.q(), bnorm.d(), biter.q(), bplatform.d()};
  Py_BEGIN_ALLOW_THREADS
  {
    const std::lock_guard<std::mutex> guard(handle->lock);  // released before the GIL is taken back
    c->rules = rules;
    solve_rows_threaded(*c, inverse != 0, r, n, threads);
  }
  Py_END_ALLOW_THREADS
  return PyLong_FromSsize_t(n);
}

// tangents(chain, q (m, nq), out (m, P*A) out, ok (m,) uint8 out, singular_rcond) -> m:
//   T = -J_passive^-1 J_actuated of FK's passive system at each row's q as given (not solved:
//   ClosedLoopSolver.home_derivatives' points, off the solution manifold), laid out as the bound
//   tangent (P x A, the passive joints in the caller's order); ok[i] = 0 where the system is singular
//   there (a zero pivot, or a reciprocal condition below singular_rcond: `reciprocal_condition`).
PyObject * tangents(PyObject *, PyObject * args) {
  PyObject *capsule, *oq, *oout, *ook;
  double threshold;
  if (!PyArg_ParseTuple(args, "OOOOd", &capsule, &oq, &oout, &ook, &threshold)) return nullptr;
  Handle * handle = handle_of(capsule);
  if (handle == nullptr) return nullptr;
  Chain * c = &handle->chain;
  const Py_ssize_t nq = c->model.nq, n_passive = static_cast<Py_ssize_t>(c->fk.original.size()),
                   n_act = static_cast<Py_ssize_t>(c->actuated.size());
  Buffer bq, bout, bok;
  if (!bq.get(oq, false, 'd', -1, "q")) return nullptr;
  const Py_ssize_t m = bq.items() / nq;
  if (bq.items() != m * nq) {
    PyErr_SetString(PyExc_ValueError, "q: not rows of nq");
    return nullptr;
  }
  if (!bout.get(oout, true, 'd', m * n_passive * n_act, "out") || !bok.get(ook, true, 'B', m, "ok")) return nullptr;
  const std::lock_guard<std::mutex> guard(handle->lock);
  System & s = c->fk;
  for (Py_ssize_t i = 0; i < m; ++i) {
    c->q = Eigen::Map<const Vector>(bq.d() + i * nq, nq);
    evaluate(*c, s, c->q, true);
    const bool regular = factor(*c, s) && reciprocal_condition(*c, s, threshold) >= threshold;
    bok.b()[i] = regular ? 1 : 0;
    if (regular) write_tangent(*c, bout.d() + i * n_passive * n_act);
  }
  return PyLong_FromSsize_t(m);
}

PyMethodDef methods[] = {
    {"build", build, METH_VARARGS, "A closed chain from arrays (see the source)."},
    {"bind", bind, METH_VARARGS, "Binds a chain's warm-start arrays (see the source)."},
    {"forward", forward, METH_VARARGS, "One Newton solve of the passive joints, in place."},
    {"inverse", inverse, METH_VARARGS, "One Newton solve of closure and task rows, in place."},
    {"rows", rows, METH_VARARGS, "FK or IK Newton solves of many rows, in place."},
    {"tangents", tangents, METH_VARARGS, "FK's tangents at many configurations, unsolved."},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module = {PyModuleDef_HEAD_INIT, "_native_newton",
                      "Compiled Newton loops of closed-loop FK and IK (Pinocchio C++).", -1, methods,
                      nullptr, nullptr, nullptr, nullptr};

}  // namespace

#ifndef M3T1R_SOURCE_SHA256
#define M3T1R_SOURCE_SHA256 "unknown"
#endif

PyMODINIT_FUNC PyInit__native_newton(void) {
  PyObject * m = PyModule_Create(&module);
  // The sha256 of this file when it was compiled: m3t1r.model.native uses the module only if it matches.
  if (m != nullptr && PyModule_AddStringConstant(m, "source_sha256", M3T1R_SOURCE_SHA256) != 0) {
    Py_DECREF(m);
    return nullptr;
  }
  return m;
}
