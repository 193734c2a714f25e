"""Closed-loop FK and IK for many poses at once: numpy over stacked product-of-exponential frames.

Pinocchio's Python API computes one configuration per call. Here the tree's placements are
recomputed for n configurations at once, level by level of the kinematic tree:

    oMi[j] = oMi[parent(j)] * jMp(j) * exp(S_j q_j)

with jMp the joint placement and exp in closed form: a revolute joint about the unit axis a turns by
R = I + sin(q) [a] + (1 - cos(q)) [a]^2 (Rodrigues), a prismatic one shifts by a q. Frames are
oMf = oMi[parent] * fMp. The WORLD joint Jacobian column of joint j (spatial twist at the base
origin, [v; w], as `pin.computeJointJacobians`) is [p_j x w_j; w_j] with w_j = R_j a (revolute) or
[R_j a; 0] (prismatic). Closure residuals and their Jacobians then follow
`ClosedLoopSolver._evaluate` row for row, with batched log6 / Jlog6.

Layout: arrays are stored poses-last ((..., 3, 3, n)), so that a 3 x 3 product is a few
multiply-adds over rows of n contiguous numbers instead of n small matrix products, each of which
costs numpy about 100 ns of overhead; rows are solved in chunks of 2,048, which spreads the Python
calls of a Newton step over many rows. Only the (closure, joint) pairs where a joint moves one
closure frame and not the other are differentiated.

Newton runs on all rows together, with chord steps: a row's Jacobian is inverted (one batched
`np.linalg.inv`) where it is evaluated and reused while the residual is small and contracts well.
Rows leave the active set as they converge. A row that does not converge, changes assembly branch
or ends singular is reported with its typed error class, never returned as a result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from m3t1r.errors import (
    BranchChangeError,
    InvalidInputError,
    M3t1rError,
    NotConvergedError,
    OutOfWorkspaceError,
    SingularConfigurationError,
    UnsupportedJointError,
    real_array,
)
from m3t1r.model.description import Mechanism
from m3t1r.model.native import available_cores
from m3t1r.model.newton_rules import DEFAULT_RULES, NewtonRules
from m3t1r.model.poe import jlog3_batch, log3_batch, skew
from m3t1r.model.task import TaskSpec

__all__ = [
    "RowFailure",
    "ForwardBatch",
    "InverseBatch",
    "StackedKinematics",
    "apply_last",
    "apply_transposed_last",
    "cross_last",
    "evaluate_rows",
    "first_step_from_home",
    "jlog3_coefficients",
    "rpy_batch",
    "skew_last",
    "stack_inverses",
    "start_configurations",
    "times_last",
    "weld_rows",
    "RowFactors",
    "SolvedRows",
]

_CHUNK = 2048  # rows solved together: bounds memory (about 40 MB of arrays per chunk)


@dataclass(frozen=True)
class RowFailure:
    """A row of a batch that has no result: index (0-based input row), reason, typed error class."""

    index: int
    reason: str
    error: type[M3t1rError]


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array)
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class ForwardBatch:
    """Forward kinematics of n slider sets. Failed rows are EXCLUDED from every array.

    Row k of `poses`, `q`, `residuals`, `iterations` belongs to input row `indices[k]`; `ok` (n,) is
    True exactly at `indices`; `failures` lists the other rows with their reason and error class.
    poses: (M, 4, 4) platform frame in the base frame [m]; q: (M, nq); residuals: (M,) max |enforced
    closure row| [m or rad]; iterations: (M,) Newton steps; task_poses: (M, 4, 4) the task frame
    (what IK and compensation command) in the base frame, `poses` itself when the task is on the
    platform frame.
    """

    n: int
    indices: np.ndarray
    poses: np.ndarray
    q: np.ndarray
    residuals: np.ndarray
    iterations: np.ndarray
    failures: tuple[RowFailure, ...]
    task_poses: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        mask = np.zeros(self.n, dtype=bool)
        mask[self.indices] = True
        return mask

    @property
    def complete(self) -> bool:
        return not self.failures


@dataclass(frozen=True, eq=False)
class InverseBatch(ForwardBatch):
    """Inverse kinematics of n targets (x, y, z, theta); same row convention as `ForwardBatch`.

    actuators: (M, k) slider values [m] (`actuated_joints` order); tilt: (M, 2) roll and pitch [rad]
    of the task frame reached minus those requested (the part of a pose the machine's geometry sets,
    not the command).
    """

    actuators: np.ndarray
    tilt: np.ndarray


def rpy_batch(rotations: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) (..., 3) [rad] of rotations (..., 3, 3), ZYX convention as `pin.rpy.matrixToRpy`
    away from pitch = +-pi/2: yaw = atan2(R10, R00), pitch = atan2(-R20, hypot(R21, R22)),
    roll = atan2(R21, R22)."""
    r = rotations
    return np.stack(
        [
            np.arctan2(r[..., 2, 1], r[..., 2, 2]),
            np.arctan2(-r[..., 2, 0], np.hypot(r[..., 2, 1], r[..., 2, 2])),
            np.arctan2(r[..., 1, 0], r[..., 0, 0]),
        ],
        axis=-1,
    )


def jlog3_coefficients(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """b(a) = 1/a^2 - 1/(2 a tan(a/2)) and b'(a)/a, with their series below a = 1e-2."""
    small = angles < 1e-2
    a = np.where(small, 1.0, angles)
    sq = angles**2
    b = np.where(small, 1 / 12 + sq / 720 + sq**2 / 30240, 1 / a**2 - 1 / (2 * a * np.tan(a / 2)))
    # b'(a) = -2/a^3 + (tan(a/2) + a / (2 cos^2(a/2))) / (2 a^2 tan^2(a/2))
    t = np.tan(a / 2)
    db = -2 / a**3 + (t + a / (2 * np.cos(a / 2) ** 2)) / (2 * a**2 * t**2)
    db_over_a = np.where(small, 1 / 360 + sq / 7560, db / a)
    return b, db_over_a


_REVOLUTE_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0)}
_PRISMATIC_AXES = {"JointModelPX": (1.0, 0.0, 0.0), "JointModelPY": (0.0, 1.0, 0.0), "JointModelPZ": (0.0, 0.0, 1.0)}


def _joint_axis(joint, joint_name: str) -> tuple[np.ndarray, bool]:
    """(unit axis in the joint frame, is_revolute) of a 1-DoF joint; UnsupportedJointError otherwise."""
    name = joint.shortname()
    if name in _REVOLUTE_AXES:
        return np.array(_REVOLUTE_AXES[name]), True
    if name in _PRISMATIC_AXES:
        return np.array(_PRISMATIC_AXES[name]), False
    if name in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
        axis = np.array(joint.extract().axis, dtype=float)
        return axis / np.linalg.norm(axis), name.startswith("JointModelRevolute")
    raise UnsupportedJointError(
        joint_name,
        f"joint type {name} is not supported by the batched kinematics (1-DoF revolute or prismatic joints only)",
    )


def times_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Products of 3 x 3 matrices stored poses-last, (..., 3, 3, n) @ (..., 3, 3, n or 1)."""
    return np.einsum("...ijn,...jkn->...ikn", a, b)


def apply_last(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """a v for 3 x 3 matrices (..., 3, 3, n) and vectors (..., 3, n or 1) stored poses-last."""
    return a[..., :, 0, :] * v[..., 0:1, :] + a[..., :, 1, :] * v[..., 1:2, :] + a[..., :, 2, :] * v[..., 2:3, :]


def apply_transposed_last(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """a^T v for 3 x 3 matrices (..., 3, 3, n) and vectors (..., 3, n) stored poses-last."""
    return a[..., 0, :, :] * v[..., 0:1, :] + a[..., 1, :, :] * v[..., 1:2, :] + a[..., 2, :, :] * v[..., 2:3, :]


def cross_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for vectors (..., 3, n) stored poses-last."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0, :] = a[..., 1, :] * b[..., 2, :] - a[..., 2, :] * b[..., 1, :]
    out[..., 1, :] = a[..., 2, :] * b[..., 0, :] - a[..., 0, :] * b[..., 2, :]
    out[..., 2, :] = a[..., 0, :] * b[..., 1, :] - a[..., 1, :] * b[..., 0, :]
    return out


def skew_last(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v] (3, 3, n) of vectors (3, n) stored poses-last."""
    out = np.zeros((3, 3) + v.shape[1:])
    out[0, 1], out[0, 2], out[1, 2] = -v[2], v[1], -v[0]
    out[1, 0], out[2, 0], out[2, 1] = v[2], -v[1], v[0]
    return out


def weld_rows(
    rotation_a: np.ndarray, position_a: np.ndarray, rotation_b: np.ndarray, position_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 6D closure between frames a and b (poses last): residual log6(aMb) = [v; w] (6, n) and the
    operator Jlog6(aMb) Ad(oMb^-1) = [[A, B]; [0, A]] on WORLD twists, as A, B (3, 3, n).

    With (R, p) = aMb, w = log3(R), a = |w|, Jl = Jlog3 = I + [w]/2 + b(a) [w]^2, v = Jl^T p and
    X = d v / d w = 1/2 [p] + (b'(a)/a) ([w]^2 p) w^T - b(a) ([w x p] + [w][p]):
    A = Jl R_b^T, B = X A - A [p_b].
    """
    rotation = times_last(rotation_a.transpose(1, 0, 2), rotation_b)
    p = apply_transposed_last(rotation_a, position_b - position_a)
    logs, angles = log3_batch(rotation.transpose(2, 0, 1))
    w = logs.T
    b, db_over_a = jlog3_coefficients(angles)
    w_skew, p_skew = skew_last(w), skew_last(p)
    w_skew2 = times_last(w_skew, w_skew)
    jlog3 = np.eye(3)[..., None] + 0.5 * w_skew + b * w_skew2
    v = apply_transposed_last(jlog3, p)
    x = (
        0.5 * p_skew
        + db_over_a * apply_last(w_skew2, p)[:, None, :] * w[None, :, :]
        - b * (skew_last(cross_last(w, p)) + times_last(w_skew, p_skew))
    )
    a = times_last(jlog3, rotation_b.transpose(1, 0, 2))
    return np.concatenate((v, w)), a, times_last(x, a) - times_last(a, skew_last(position_b))


class StackedTree:
    """Placements of a Pinocchio tree of 1-DoF joints for n configurations at once (numpy).

    Arrays are stored poses-last ((..., 3, 3, n) rotations, (..., 3, n) vectors): every 3 x 3
    product is then a few multiply-adds over contiguous rows of n numbers, where a stack of n small
    matrix products pays numpy's per-matrix overhead (about 100 ns against 10-25 ns per pose).
    Joint j's local motion is jMp(j) exp(S_j q): R = R0 + sin(q) R0[a] + (1 - cos q) R0[a]^2 for a
    revolute joint (R0[a], R0[a]^2 precomputed), p = p0 + R0 a q for a prismatic one. Joints are
    composed one tree level at a time (all joints of a level in one product).
    """

    def __init__(self, model: pin.Model) -> None:
        n_joints = model.njoints - 1
        # `_joint_axis` admits 1-DoF joints only (nq = nv = 1 each), so q and v share the joints' order.
        axes, revolute = zip(*(_joint_axis(model.joints[j], model.names[j]) for j in range(1, model.njoints)))
        self.axes, self.revolute = np.array(axes), np.array(revolute)
        self.q_index = np.array([model.idx_qs[j] for j in range(1, model.njoints)])
        self.parent = np.array([model.parents[j] for j in range(1, model.njoints)])
        r0 = np.array([model.jointPlacements[j].rotation for j in range(1, model.njoints)])
        k = skew(self.axes)
        # Constant factors poses-last, shaped to broadcast against (joints, 3, 3, n).
        self.r0, self.r0k, self.r0k2 = r0[..., None], (r0 @ k)[..., None], (r0 @ k @ k)[..., None]
        self.p0 = np.array([model.jointPlacements[j].translation for j in range(1, model.njoints)])[..., None]
        self.r0a = (np.einsum("jik,jk->ji", r0, self.axes) * (~self.revolute)[:, None])[..., None]
        self.axes_last = self.axes[..., None]
        depth = np.zeros(model.njoints, dtype=int)
        for j in range(1, model.njoints):
            depth[j] = depth[model.parents[j]] + 1
        self.levels = [np.flatnonzero(depth[1:] == d) + 1 for d in range(1, depth.max() + 1)]
        self.n_joints = n_joints

    def joints(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (J+1, 3, 3, n) and positions (J+1, 3, n) of every joint frame (0 = universe)
        for configurations q (n, nq): poses last."""
        n = len(q)
        value = q[:, self.q_index].T  # (J, n)
        angle = value * self.revolute[:, None]
        s, c1 = np.sin(angle)[:, None, None, :], (1.0 - np.cos(angle))[:, None, None, :]
        local_r = self.r0 + s * self.r0k + c1 * self.r0k2
        local_p = self.p0 + value[:, None, :] * self.r0a
        rot = np.empty((self.n_joints + 1, 3, 3, n))
        pos = np.empty((self.n_joints + 1, 3, n))
        rot[0], pos[0] = np.eye(3)[..., None], 0.0
        for level in self.levels:
            parent = self.parent[level - 1]
            parent_r = rot[parent]
            rot[level] = times_last(parent_r, local_r[level - 1])
            pos[level] = pos[parent] + apply_last(parent_r, local_p[level - 1])
        return rot, pos

    def twists(self, rot: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Columns of the WORLD joint Jacobian (`pin.computeJointJacobians`), poses last: linear
        (nv, 3, n) and angular (nv, 3, n) parts. Joint j's column is [p_j x w_j; w_j] (revolute) or
        [w_j; 0] (prismatic), w_j = R_j a_j."""
        w = apply_last(rot[1:], self.axes_last)
        linear, angular = np.empty_like(w), np.zeros_like(w)
        linear[self.q_index] = np.where(self.revolute[:, None, None], cross_last(pos[1:], w), w)
        angular[self.q_index[self.revolute]] = w[self.revolute]
        return linear, angular

    def world_jacobian(self, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """WORLD joint Jacobian (n, 6, nv), as `pin.computeJointJacobians` per configuration."""
        linear, angular = self.twists(rot, pos)
        return np.concatenate((linear, angular), axis=1).transpose(2, 1, 0)


class StackedKinematics:
    """Closure residuals, Jacobians and Newton solves of one `ClosedLoopSolver`'s mechanism, batched.

    Built from the solver (its row layout, tolerance, block structure and slider limits) so that a
    batch solve and a single solve are the same problem, row for row.
    """

    def __init__(self, solver) -> None:
        mechanism: Mechanism = solver.mechanism
        model = mechanism.model
        self.solver, self.tree = solver, StackedTree(model)
        frame_ids = sorted({c.frame_a_id for c in mechanism.closures} | {c.frame_b_id for c in mechanism.closures})
        frame_ids.append(mechanism.platform_frame_id)
        task_frame = model.getFrameId(mechanism.task.frame)
        # The task frame last (-1); the platform frame before it when they differ (else both -1).
        frame_ids.append(task_frame)
        self.platform_index = -1 if task_frame == mechanism.platform_frame_id else -2
        where = {f: k for k, f in enumerate(frame_ids)}
        self.frame_parent = np.array([model.frames[f].parentJoint for f in frame_ids])
        self.frame_r = np.array([model.frames[f].placement.rotation for f in frame_ids])
        self.frame_p = np.array([model.frames[f].placement.translation for f in frame_ids])
        point_a: list[int] = []
        point_b: list[int] = []
        self.point_slot, self.weld = [], []
        start = 0
        for c in mechanism.closures:
            if c.type == "3D":
                point_a.append(where[c.frame_a_id])
                point_b.append(where[c.frame_b_id])
                self.point_slot.append(start)
                start += 3
            else:
                self.weld.append((start, where[c.frame_a_id], where[c.frame_b_id]))
                start += 6
        self.point_rows = (np.array(self.point_slot, dtype=int)[:, None] + np.arange(3)).reshape(-1)
        self.point_a, self.point_b = np.array(point_a, dtype=int), np.array(point_b, dtype=int)
        self.enforced = solver._enforced
        self.n_full = start
        # The 3D closures' Jacobian entries, one (closure, column) pair at a time: the columns of the
        # joints that move frame b but not frame a (sign +1) or a but not b (-1); every other entry is 0.
        full_mask = solver._row_masks[True]
        pairs = [
            (k, v, full_mask[slot, v])
            for k, slot in enumerate(self.point_slot)
            for v in np.flatnonzero(full_mask[slot])
        ]
        self.pair_point = np.array([k for k, _, _ in pairs], dtype=int)
        self.pair_column = np.array([v for _, v, _ in pairs], dtype=int)
        self.pair_sign = np.array([sign for _, _, sign in pairs], dtype=float)[:, None, None]
        self.pair_rows = np.array([self.point_slot[k] for k, _, _ in pairs], dtype=int)[:, None] + np.arange(3)
        # The same for each 6D closure: (columns (K,), signs (K, 1, 1), rows (K, 6)).
        self.weld_pairs = []
        for slot, _, _ in self.weld:
            columns = np.flatnonzero(full_mask[slot])
            self.weld_pairs.append(
                (columns, full_mask[slot, columns][:, None, None], slot + np.arange(6)[None, :] + 0 * columns[:, None])
            )
        self.passive, self.actuated = solver.passive, solver.actuated
        self.blocks = [(np.asarray(r), np.asarray(c)) for r, c in solver.branch_blocks]
        support = np.zeros(model.nv)
        for j in model.supports[model.frames[task_frame].parentJoint][1:]:
            support[model.idx_vs[j]] = 1.0
        self.task_support = support  # columns of the joints that move the task frame
        self.unknowns = np.sort(np.concatenate((self.passive, self.actuated)))  # every joint but the locked ones

    def task_poses(self, q: np.ndarray) -> np.ndarray:
        """Task frame placements (n, 4, 4) in the base frame at configurations q (n, nq)."""
        rot, pos = self.tree.joints(q)
        parent = self.frame_parent[-1]
        poses = np.zeros((len(q), 4, 4))
        poses[:, :3, :3] = np.einsum("ijn,jk->nik", rot[parent], self.frame_r[-1])
        poses[:, :3, 3] = pos[parent].T + np.einsum("ijn,j->ni", rot[parent], self.frame_p[-1])
        poses[:, 3, 3] = 1.0
        return poses

    def frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closure, platform and task frame rotations (F, 3, 3, n) and positions (F, 3, n), and the WORLD
        Jacobian columns, linear (nv, 3, n) and angular (nv, 3, n): all poses last."""
        rot, pos = self.tree.joints(q)
        parent_r = rot[self.frame_parent]
        frot = times_last(parent_r, self.frame_r[..., None])
        fpos = pos[self.frame_parent] + apply_last(parent_r, self.frame_p[..., None])
        return (frot, fpos) + self.tree.twists(rot, pos)

    def closures(self, q: np.ndarray, with_jacobian: bool = True) -> tuple:
        """Enforced closure rows (n, rows) at q (n, nq), their Jacobian (n, rows, nv), the frames
        (n, F, 3, 3) and (n, F, 3) and the WORLD joint Jacobian (n, 6, nv).

        3D: r = R_a^T (p_b - p_a); the column of joint j is +-R_a^T (v_j - p_b x w_j), [v_j; w_j] its
        WORLD twist (`ClosedLoopSolver._evaluate`'s R_a^T [I, -[p_b]] operator, column by column).
        6D: r = log6(aMb); the column is +-Jlog6(aMb) Ad(oMb^-1) [v_j; w_j]. Only the (closure, joint)
        pairs where a joint moves one frame and not the other are computed; the rest are zero.
        """
        frot, fpos, linear, angular = self.frames(q)
        n = len(q)
        full = np.empty((self.n_full, n))
        ra, pb = frot[self.point_a], fpos[self.point_b]
        full[self.point_rows] = apply_transposed_last(ra, pb - fpos[self.point_a]).reshape(-1, n)
        jac = np.zeros((self.n_full, len(linear), n)) if with_jacobian else None
        if jac is not None and len(self.pair_point):
            column = self.pair_column
            moved = linear[column] - cross_last(pb[self.pair_point], angular[column])
            jac[self.pair_rows, column[:, None]] = self.pair_sign * apply_transposed_last(ra[self.pair_point], moved)
        for (slot, ia, ib), (columns, sign, rows) in zip(self.weld, self.weld_pairs):
            full[slot : slot + 6], a, b = weld_rows(frot[ia], fpos[ia], frot[ib], fpos[ib])
            if jac is not None:
                v, w = linear[columns], angular[columns]
                moved_rows = (apply_last(a, v) + apply_last(b, w), apply_last(a, w))
                jac[rows, columns[:, None]] = sign * np.concatenate(moved_rows, axis=1)
        world = np.concatenate((linear, angular), axis=1).transpose(2, 1, 0)  # (n, 6, nv), a view
        frames = frot.transpose(3, 0, 1, 2), fpos.transpose(2, 0, 1)  # (n, F, 3, 3), (n, F, 3) views
        residual = full[self.enforced].T
        if jac is None:
            return (residual, None) + frames + (world,)
        return (residual, jac[self.enforced].transpose(2, 0, 1)) + frames + (world,)

    def home_reference(self) -> tuple[np.ndarray, np.ndarray] | None:
        """At home: T = -J_passive^-1 J_actuated (passive x actuated), d q_passive / d a, and the branch
        labels (blocks,) of the passive closure system (FK from home must end on that branch): the
        solver's own (`ClosedLoopSolver.home_reference`), so that a batch row and a fresh single solve
        take one first step. None when home is singular."""
        if self._home is None:
            reference = self.solver.home_reference()
            if reference is None:
                return None
            tangent, branch = reference
            self._home = tangent, np.frombuffer(branch, dtype=np.uint8).astype(bool)
        return self._home

    _home: tuple[np.ndarray, np.ndarray] | None = None

    def signatures(self, jac: np.ndarray) -> np.ndarray:
        """Signs (m, blocks) of the determinants of the diagonal blocks of the passive closure system
        (as `ClosedLoopSolver`'s branch signature): True where det > 0."""
        signs = []
        for rows, cols in self.blocks:
            block = jac[:, rows[:, None], cols[None, :]]
            if len(rows) == 1:
                signs.append(block[:, 0, 0] > 0)
            elif len(rows) == 2:
                signs.append(block[:, 0, 0] * block[:, 1, 1] - block[:, 0, 1] * block[:, 1, 0] > 0)
            else:
                signs.append(np.linalg.slogdet(block)[0] > 0)
        return np.stack(signs, axis=1)


_CONVERGED, _ACTIVE, _LIMIT = 0, -1, 5  # _LIMIT: converged, but a slider is beyond its limit
_FAILURES = {1: OutOfWorkspaceError, 2: NotConvergedError, 3: SingularConfigurationError, 4: BranchChangeError}
_REASONS = {
    1: "the closures cannot be assembled here (target out of the workspace or too far from the "
    "initial configuration's branch)",
    2: "Newton did not reach the tolerance",
    3: "singular configuration (reciprocal condition below 1e-10)",
    4: "the solution lies on another assembly branch than the start (Newton crossed a singularity)",
}


def stack_inverses(square: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses (m, k, k) of a stack and a mask of the exactly singular matrices (inverse left zero):
    one singular row must not fail the whole stack."""
    try:
        return np.linalg.inv(square), np.zeros(len(square), dtype=bool)
    except np.linalg.LinAlgError:
        out, bad = np.zeros_like(square), np.zeros(len(square), dtype=bool)
        for i, matrix in enumerate(square):
            try:
                out[i] = np.linalg.inv(matrix)
            except np.linalg.LinAlgError:
                bad[i] = True
        return out, bad


@dataclass
class SolvedRows:
    """Raw outcome of a batched Newton solve: per row q, status code, residual, steps, platform pose."""

    q: np.ndarray
    status: np.ndarray
    norm: np.ndarray
    iterations: np.ndarray
    rotation: np.ndarray
    position: np.ndarray


class RowFactors:
    """Per-row inverse Jacobians (chord steps reuse them), their 1-norm reciprocal condition and
    branch labels at the last Jacobian, and the labels at the first one."""

    def __init__(self, n: int, k: int) -> None:
        self.inverse, self.rcond = np.zeros((n, k, k)), np.zeros(n)
        self.labels: np.ndarray | None = None
        self.start: np.ndarray | None = None

    def refresh(self, rows: np.ndarray, jac: np.ndarray, unknowns: np.ndarray, signature) -> np.ndarray:
        """Factor the Jacobians of `rows` (ids); returns the mask of exactly singular ones."""
        square = jac[:, :, unknowns]
        inverse, singular = stack_inverses(square)
        labels = signature(jac, square)
        if self.labels is None:
            self.labels = np.zeros((len(self.rcond), labels.shape[1]), dtype=bool)
            self.start = np.zeros_like(self.labels)
            self.start[rows] = labels
        self.inverse[rows], self.labels[rows] = inverse, labels
        norms = np.abs(square).sum(axis=1).max(axis=1) * np.abs(inverse).sum(axis=1).max(axis=1)
        self.rcond[rows] = np.where(singular, 0.0, 1.0 / np.where(singular, 1.0, norms))
        return singular


def evaluate_rows(
    q: np.ndarray,
    active: np.ndarray,
    previous: np.ndarray,
    rules: NewtonRules,
    system,
    factors: RowFactors,
    unknowns: np.ndarray,
    signature,
) -> tuple:
    """Residual, platform pose and singular mask of the `active` rows after a step. Rows whose last
    residual was above `rules.chord_below` get a Jacobian (Newton); the others get the residual alone
    (chord), and a Jacobian too when that step contracted by less than `rules.chord_contraction`."""
    m = len(active)
    rot, pos, singular = np.empty((m, 3, 3)), np.empty((m, 3)), np.zeros(m, dtype=bool)
    residual: np.ndarray | None = None
    stale = previous > rules.chord_below
    near = np.flatnonzero(~stale)
    if len(near):
        near_residual, _, rot[near], pos[near] = system(q[active[near]], active[near], False)
        residual = np.empty((m, near_residual.shape[1]))
        residual[near] = near_residual
        norm = np.abs(near_residual).max(axis=1)
        stale[near] = (norm > rules.chord_contraction * previous[near]) & (norm > rules.tolerance) & np.isfinite(norm)
    if stale.any():
        rows = active[stale]
        stale_residual, jac, rot[stale], pos[stale] = system(q[rows], rows, True)
        if residual is None:
            residual = np.empty((m, stale_residual.shape[1]))
        residual[stale] = stale_residual
        singular[stale] = factors.refresh(rows, jac, unknowns, signature)
    return residual, rot, pos, singular


def newton_batch(
    q: np.ndarray,
    unknowns: np.ndarray,
    system,
    signature,
    rules: NewtonRules,
    steps_taken: int = 0,
    branch: np.ndarray | None = None,
) -> SolvedRows:
    """Chord Newton on n independent square systems at once; rows leave the active set as they finish.

    system(q_rows, rows, with_jacobian) -> (residual (m, r), Jacobian (m, r, nv) or None, platform
    rotation (m, 3, 3), position (m, 3)); signature(jac, square) -> (m, s) bool branch labels. Under
    `rules`, as `ClosedLoopSolver.newton`: a step solves J[:, unknowns] dx = -r with the inverse of the
    row's last Jacobian, the largest component capped at rules.max_step; the Jacobian is evaluated at
    the start, after steps from residuals above rules.chord_below, and for rows whose residual
    contracted by less than rules.chord_contraction. A row converges when max|r| <= rules.tolerance;
    it then fails if its last Jacobian has reciprocal 1-norm condition < rules.singular_rcond
    (singular) or branch labels other than at its first Jacobian (branch change). Status codes:
    0 converged, 1 out of workspace (no assembly: residual > rules.no_assembly or non-finite),
    2 not converged, 3 singular, 4 branch change. `steps_taken`: steps already taken
    (a predictor), counted in the iterations; `branch`: (s,) labels every row must end with, instead
    of those at its first Jacobian (a predicted start is not a reference).
    """
    n = len(q)
    q = q.copy()
    out = SolvedRows(
        q, np.full(n, _ACTIVE), np.full(n, np.inf), np.zeros(n, dtype=int), np.zeros((n, 3, 3)), np.zeros((n, 3))
    )
    factors, previous = RowFactors(n, len(unknowns)), np.full(n, np.inf)
    active = np.arange(n)
    residual, jac, rot, pos = system(q, active, True)
    singular = factors.refresh(active, jac, unknowns, signature)
    assert factors.labels is not None and factors.start is not None, "the first refresh sets them"
    if branch is not None:
        factors.start[:] = branch
    tolerance, max_iterations = rules.tolerance, rules.max_iterations
    for iteration in range(steps_taken, max_iterations + steps_taken + 1):
        norm = np.abs(residual).max(axis=1)
        out.norm[active], out.iterations[active] = norm, iteration
        bad = ~np.isfinite(norm)
        done = (norm <= tolerance) & ~bad
        if done.any():
            rows = active[done]
            out.rotation[rows], out.position[rows] = rot[done], pos[done]
            out.status[rows] = np.where(
                factors.rcond[rows] < rules.singular_rcond,
                3,
                np.where((factors.labels[rows] != factors.start[rows]).any(axis=1), 4, _CONVERGED),
            )
        out.status[active[bad]] = 1
        out.status[active[singular & ~done & ~bad]] = 3
        keep = ~(done | bad | singular)
        if iteration == max_iterations + steps_taken or not keep.any():
            break
        previous[active[keep]] = norm[keep]
        active, residual = active[keep], residual[keep]
        step = np.einsum("nij,nj->ni", factors.inverse[active], residual)
        biggest = np.abs(step).max(axis=1)
        step *= np.minimum(1.0, rules.max_step / np.maximum(biggest, 1e-300))[:, None]
        q[active[:, None], unknowns[None, :]] -= step
        residual, rot, pos, singular = evaluate_rows(
            q, active, previous[active], rules, system, factors, unknowns, signature
        )
    left = out.status == _ACTIVE
    out.status[left] = np.where(out.norm[left] > rules.no_assembly, 1, 2)
    return out


def failures_of(
    solved: SolvedRows, offset: int, what: str, singular_rcond: float = DEFAULT_RULES.singular_rcond
) -> list[RowFailure]:
    """Typed failures of the rows of `solved` that did not converge (indices shifted by `offset`);
    singular rows name `singular_rcond`, the threshold they fell below."""
    reasons = _REASONS | {3: f"singular configuration (reciprocal condition below {singular_rcond:g})"}
    return [
        RowFailure(
            offset + int(i),
            f"{what}: {reasons[int(solved.status[i])]} (residual "
            f"{solved.norm[i]:.3e} after {int(solved.iterations[i])} iterations)",
            _FAILURES[int(solved.status[i])],
        )
        for i in np.flatnonzero((solved.status != _CONVERGED) & (solved.status != _LIMIT))
    ]


def start_configurations(kin: StackedKinematics, n: int, q_init: np.ndarray | None) -> np.ndarray:
    """Start configurations (n, nq): home by default, one nq vector for every row, or one per row."""
    nq = kin.solver.model.nq
    if q_init is None:
        return np.repeat(kin.solver.mechanism.home[None, :], n, axis=0)
    start = real_array(q_init, "q_init")
    if start.shape == (nq,):
        start = np.repeat(start[None, :], n, axis=0)
    if start.shape != (n, nq) or not np.all(np.isfinite(start)):
        raise InvalidInputError(f"q_init: expected finite ({nq},) or ({n}, {nq}) values, got shape {start.shape}")
    return start.copy()


def _rows(values: object, width: int, what: str, columns: tuple[str, ...]) -> np.ndarray:
    """An (n, width) finite float array (n may be 0), or InvalidInputError naming the first bad row and column."""
    array = real_array(values, what, "numeric rows")
    if array.ndim != 2 or array.shape[1] != width:
        raise InvalidInputError(f"{what}: shape {array.shape}, expected (n, {width}) rows {columns}")
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        row, col = (int(i) for i in bad[0])
        raise InvalidInputError(f"{what}: row {row} (0-based): {columns[col]} = {array[row, col]}, not finite")
    return array


def forward_batch(
    kin: StackedKinematics, sliders: np.ndarray, q_init: np.ndarray | None = None, threads: int | None = None
) -> ForwardBatch:
    """Platform poses for n slider sets (n, k) [m], each solved from q_init, in chunks.

    Default (q_init None): every row starts from home moved along home's solution manifold to first
    order (dq_passive = T (a - a_home), T = -J_passive^-1 J_actuated at home) and must end on home's
    assembly branch (the branch labels at home). Far from home this assembles rows where plain
    Newton from home's passive joints crosses a singularity (`forward(a, q_init=home)` then raises
    BranchChangeError or OutOfWorkspaceError); where both succeed they agree to the tolerance.
    Given q_init (nq,) or (n, nq), each row starts there, branch labels taken at its start.
    A row with a slider beyond its URDF limit fails with InvalidInputError (reported, not raised);
    non-finite values or a wrong shape raise InvalidInputError for the whole batch. threads: how many
    threads share the rows in the compiled loop (None: every core this process may use; the numpy
    loop ignores it); the results do not depend on it.
    """
    solver = kin.solver
    workers = _thread_count(threads)
    names = solver.mechanism.actuated_joints
    values = _rows(sliders, len(names), "actuator values", names)
    start = start_configurations(kin, len(values), q_init)
    outside = (values < solver._act_lower) | (values > solver._act_upper)
    failures = [
        RowFailure(
            int(i),
            f"actuator '{names[int(np.argmax(outside[i]))]}' = "
            f"{values[i, np.argmax(outside[i])]:.6g} is beyond its joint limit",
            InvalidInputError,
        )
        for i in np.flatnonzero(outside.any(axis=1))
    ]
    rows = np.flatnonzero(~outside.any(axis=1))
    reference = kin.home_reference() if q_init is None else None
    predicted = reference is not None
    if reference is not None:  # first-order predictor along home's solution manifold: dq_passive = T (a - a_home)
        tangent, branch = reference
        start[:, kin.passive] += (values - start[:, kin.actuated]) @ tangent.T
    start[:, kin.actuated] = values

    def system(q: np.ndarray, active: np.ndarray, with_jacobian: bool):
        residual, jac, frot, fpos, _ = kin.closures(q, with_jacobian)
        return residual, jac, frot[:, kin.platform_index], fpos[:, kin.platform_index]

    parts = []
    # The compiled loop takes every row at once (row by row, on `workers` threads); numpy, chunks of rows.
    size = max(len(rows), 1) if solver.native is not None else _CHUNK
    for chunk in np.array_split(rows, max(1, -(-len(rows) // size))) if len(rows) else []:
        if solver.native is not None:
            q = start[chunk]
            solved = _native_solved(
                q,
                solver.native.forward_rows(
                    q, branch if predicted else None, int(predicted), solver.rules.compiled(), workers
                ),
            )
        else:
            solved = newton_batch(
                start[chunk],
                kin.passive,
                system,
                lambda jac, sq: kin.signatures(jac),
                solver.rules,
                int(predicted),
                branch if predicted else None,
            )
        failures += [
            RowFailure(int(chunk[f.index]), f.reason, f.error)
            for f in failures_of(solved, 0, "forward kinematics", solver.singular_rcond)
        ]
        parts.append((chunk, solved))
    return _forward_result(kin, len(values), parts, failures)


def _native_solved(q: np.ndarray, outcome: tuple) -> SolvedRows:
    """A compiled row solve of q (`NativeChain.forward_rows` / `inverse_rows`) as `newton_batch`'s result."""
    status, norm, iterations, platform = outcome
    return SolvedRows(q, status, norm, iterations, platform[:, :3, :3], platform[:, :3, 3])


def _thread_count(threads: int | None) -> int:
    """The thread count asked for (an int >= 1), or every available core for None."""
    if threads is None:
        return available_cores()
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InvalidInputError(f"threads: expected an integer >= 1 or None, got {threads!r}")
    return int(threads)


def _forward_result(kin: StackedKinematics, n: int, parts: list, failures: list) -> ForwardBatch:
    """Gather the converged rows of every chunk (in input order) into a frozen ForwardBatch (q: (M, nq),
    also when no row converged), with the task frame's placements."""
    indices, poses, qs, norms, steps = [], [], [], [], []
    for chunk, solved in parts:
        good = solved.status == _CONVERGED
        pose = np.zeros((int(good.sum()), 4, 4))
        pose[:, :3, :3], pose[:, :3, 3], pose[:, 3, 3] = solved.rotation[good], solved.position[good], 1.0
        indices.append(chunk[good])
        poses.append(pose)
        qs.append(solved.q[good])
        norms.append(solved.norm[good])
        steps.append(solved.iterations[good])
    cat = lambda arrays, shape: np.concatenate(arrays) if arrays else np.zeros(shape)
    index = cat(indices, (0,)).astype(int)
    order = np.argsort(index, kind="stable")
    platform, q = _frozen(cat(poses, (0, 4, 4))[order]), _frozen(cat(qs, (0, kin.solver.model.nq))[order])
    task = platform if kin.platform_index == -1 else _frozen(kin.task_poses(q) if len(q) else np.zeros((0, 4, 4)))
    return ForwardBatch(
        n=n,
        indices=_frozen(index[order]),
        poses=platform,
        q=q,
        residuals=_frozen(cat(norms, (0,))[order]),
        iterations=_frozen(cat(steps, (0,)).astype(int)[order]),
        failures=tuple(sorted(failures, key=lambda f: f.index)),
        task_poses=task,
    )


def task_rows(
    task: TaskSpec, rot: np.ndarray, pos: np.ndarray, twist: np.ndarray, goal: np.ndarray, goal_rot: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Task residual rows (n, d) and their Jacobian (n, d, nv), batched as `TaskSpec.residual`/`jacobian`.

    rot, pos: the task frame (n, 3, 3), (n, 3); twist: the WORLD Jacobian columns that move it
    (n, 6, nv); goal: (n, len(task.columns)) task coordinates; goal_rot: (n, 3, 3) for a full rotation.
    """
    axes, count = task.axes, len(task.position)
    origin = twist[:, :3] - skew(pos) @ twist[:, 3:]  # origin velocity v + w x p, WORLD axes
    residual, jacobian = [pos[:, axes] - goal[:, :count]], [origin[:, axes]]
    if task.rotation == "yaw":
        yaw = np.arctan2(rot[:, 1, 0], rot[:, 0, 0]) - goal[:, count]
        residual.append((yaw - 2 * np.pi * np.round(yaw / (2 * np.pi)))[:, None])
        c = rot[:, :, 0]
        horizontal = c[:, 0] ** 2 + c[:, 1] ** 2
        row = np.stack([-c[:, 0] * c[:, 2], -c[:, 1] * c[:, 2], horizontal], axis=1) / horizontal[:, None]
        jacobian.append(np.einsum("nk,nkv->nv", row, twist[:, 3:])[:, None])
    elif task.rotation == "full":
        assert goal_rot is not None, "a full-rotation goal has its rotations"
        logs, angles = log3_batch(goal_rot.transpose(0, 2, 1) @ rot)
        residual.append(logs)
        jacobian.append(jlog3_batch(logs, angles) @ rot.transpose(0, 2, 1) @ twist[:, 3:])
    return np.concatenate(residual, axis=1), np.concatenate(jacobian, axis=1)


def first_step_from_home(
    kin: StackedKinematics, start: np.ndarray, rows: np.ndarray, goal: np.ndarray, signature
) -> np.ndarray | None:
    """Newton's first IK step from home for `rows` at once, in place on `start` (n, nq); returns the
    branch labels at home (the rows' reference), or None (start untouched) if home is singular.

    At home the system's Jacobian is the same for every row when the task rows do not depend on the
    goal (position and yaw tasks), and the closure rows are those of home: one factorisation serves
    all rows, dq = -J_home^-1 [r_closure(home); task(home) - goal], capped as every step.
    """
    home = kin.solver.mechanism.home
    closure, jac, frot, fpos, world = kin.closures(home[None, :])
    n = len(rows)
    task_residual, task_jac = task_rows(
        kin.solver.mechanism.task,
        np.broadcast_to(frot[:, -1], (n, 3, 3)),
        np.broadcast_to(fpos[:, -1], (n, 3)),
        np.broadcast_to(world * kin.task_support, (n,) + world.shape[1:]),
        goal[rows],
        None,
    )
    full_jac = np.concatenate((jac, task_jac[:1]), axis=1)
    square = full_jac[:, :, kin.unknowns]
    inverse, singular = stack_inverses(square)
    if (
        singular[0]
        or 1.0 / (np.abs(square).sum(axis=1).max() * np.abs(inverse).sum(axis=1).max()) < kin.solver.singular_rcond
    ):
        return None
    residual = np.concatenate((np.broadcast_to(closure, (n, closure.shape[1])), task_residual), axis=1)
    step = residual @ inverse[0].T
    step *= np.minimum(1.0, kin.solver.rules.max_step / np.maximum(np.abs(step).max(axis=1), 1e-300))[:, None]
    start[rows[:, None], kin.unknowns[None, :]] -= step
    return signature(full_jac, square)[0]


def inverse_batch(
    kin: StackedKinematics, targets: np.ndarray, q_init: np.ndarray | None = None, threads: int | None = None
) -> InverseBatch:
    """Slider values for n targets, rows of task coordinates (`TaskSpec.columns`, e.g. x, y, z, theta)
    [m, rad], each from q_init (default home).

    Row system as `ClosedLoopSolver.inverse`: [closure rows; task rows] = 0 over every joint but the
    locked ones; branch labels = closure blocks plus the sign of det of the whole system. A converged
    row needing a slider beyond its limit fails with OutOfWorkspaceError naming the slider. threads:
    as `forward_batch`.
    """
    solver = kin.solver
    workers = _thread_count(threads)
    task = solver.mechanism.task
    solver.check_square_task()
    goal = task.goals(_rows(targets, len(task.columns), "targets", task.columns))
    goal_rot = task.target_rotations(goal)
    start = start_configurations(kin, len(goal), q_init)
    every = kin.unknowns

    def system(q: np.ndarray, active: np.ndarray, with_jacobian: bool):
        closure, jac, frot, fpos, world = kin.closures(q, with_jacobian)
        rot, pos = frot[:, -1], fpos[:, -1]
        rows, rows_jac = task_rows(
            task, rot, pos, world * kin.task_support, goal[active], None if goal_rot is None else goal_rot[active]
        )
        return (
            np.concatenate((closure, rows), axis=1),
            np.concatenate((jac, rows_jac), axis=1) if with_jacobian else None,
            frot[:, kin.platform_index],
            fpos[:, kin.platform_index],
        )

    def signature(jac: np.ndarray, square: np.ndarray) -> np.ndarray:
        return np.concatenate((kin.signatures(jac), (np.linalg.slogdet(square)[0] > 0)[:, None]), axis=1)

    parts, failures = [], []
    names = solver.mechanism.actuated_joints
    # The compiled loop takes every row at once (row by row, on `workers` threads); numpy, chunks of rows.
    size = max(len(goal), 1) if solver.native is not None else _CHUNK
    for chunk in np.array_split(np.arange(len(goal)), max(1, -(-len(goal) // size))) if len(goal) else []:
        branch = None
        if q_init is None and task.rotation != "full":
            branch = first_step_from_home(kin, start, chunk, goal, signature)
        if solver.native is not None:
            q = start[chunk]
            solved = _native_solved(
                q,
                solver.native.inverse_rows(
                    q,
                    goal[chunk],
                    None if goal_rot is None else goal_rot[chunk],
                    branch,
                    int(branch is not None),
                    solver.rules.compiled(),
                    workers,
                ),
            )
        else:
            solved = newton_batch(
                start[chunk],
                every,
                lambda q, a, jacobian: system(q, chunk[a], jacobian),
                signature,
                solver.rules,
                int(branch is not None),
                branch,
            )
        sliders = solved.q[:, kin.actuated]
        outside = ((sliders < solver._act_lower) | (sliders > solver._act_upper)) & (solved.status == _CONVERGED)[
            :, None
        ]
        for i in np.flatnonzero(outside.any(axis=1)):
            k = int(np.argmax(outside[i]))
            solved.status[i] = _LIMIT
            failures.append(
                RowFailure(
                    int(chunk[i]),
                    f"inverse kinematics: target needs actuator '{names[k]}' = "
                    f"{sliders[i, k]:.6g} {solver.mechanism.joint_units()[k]}, beyond its limit "
                    f"[{solver._act_lower[k]:.6g}, {solver._act_upper[k]:.6g}]",
                    OutOfWorkspaceError,
                )
            )
        failures += [
            RowFailure(int(chunk[f.index]), f.reason, f.error)
            for f in failures_of(solved, 0, "inverse kinematics", solver.singular_rcond)
        ]
        parts.append((chunk, solved))
    fk = _forward_result(kin, len(goal), parts, failures)
    wanted = np.zeros(2) if goal_rot is None else rpy_batch(goal_rot[fk.indices])[:, :2]
    return InverseBatch(
        **{
            f: getattr(fk, f)
            for f in ("n", "indices", "poses", "q", "residuals", "iterations", "failures", "task_poses")
        },
        actuators=_frozen(fk.q[:, kin.actuated]),
        tilt=_frozen(rpy_batch(fk.task_poses[:, :3, :3])[:, :2] - wanted),
    )
