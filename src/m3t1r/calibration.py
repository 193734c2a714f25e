"""Closed-loop calibration from slider readings and measured platform poses (beyond the paper).

Parameters: a right-multiplied 6-vector error dt = [v; w] on every joint placement of the tree
and on every frame a closure or the measurement uses (paper eq. 33: T(0) <- T(0) exp6(dt)). With
the sliders fixed, the passive joints follow the closures, so the sensitivity of the measured
platform pose to the parameters is found by implicit differentiation:

    r_c(q, p) = 0  =>  dq_passive/dp = -J_c,passive^-1 dr_c/dp        (16 x 16 square system)
    d xi_P / dp    = X_P + J_P,passive dq_passive/dp                  (spatial twist, WORLD)

where X_f (6 x P) is the spatial twist of frame f per unit parameter: Pinocchio's WORLD kinematic
regressor for the joint placements (paper eq. 17 columns, Ad(g_{0,k-1} T_{k-1,k}(0))), and
Ad(oMf) for the frame's own placement; a closure's rows see operator @ (X_b - X_a).

The measurement residual of one pose is e = [p_model - p_meas; log3(R_meas^T R_model)]: position
in WORLD [m], orientation in the platform frame [rad]; position-only data keeps the first three.
It is whitened by the tracker noise and minimised by Levenberg-Marquardt over the base
(identifiable) parameters, chosen once at the start by column-pivoted QR.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

from ._threads import on_one_blas_thread
from .description import Mechanism
from .errors import IdentificationError, InvalidInputError, KinematicsError, PoorExcitationWarning
from .identification import BaseParameters, LMResult, levenberg_marquardt, select_base_parameters
from .kinematics import ClosedLoopSolver, rehomed
from .metrics import PoseErrors  # re-exported: one pose-error type for every calibration
from .poe import Placement, adjoint_matrices, jlog3_batch, log3_batch, perturb, skew

__all__ = [
    "ClosedLoopErrorModel", "PoseMeasurements", "TrackerNoise", "ClosedLoopCalibration",
    "PlatformSensitivities", "calibrate_closed_loop", "PoseErrors", "pose_errors", "predicted_pose_std",
]


@dataclass(frozen=True)
class TrackerNoise:
    """Standard deviations of the measurements: tracker position [m] and orientation [rad],
    slider readings [m]. Used to whiten the residual and to predict the parameter covariance."""

    position: float = 10e-6
    rotation: float = 20e-6
    actuator: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("position", "rotation", "actuator"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"noise {name} must be a finite non-negative number, got {value}")
        if self.position <= 0 or self.rotation <= 0:
            raise InvalidInputError("tracker noise must be positive (it whitens the residual)")


@dataclass(frozen=True)
class PoseMeasurements:
    """N calibration poses: slider readings (N x n_act) [m] and measured platform poses in the base
    frame (orientation ignored when position_only)."""

    actuators: np.ndarray
    poses: tuple[pin.SE3, ...]
    position_only: bool = False

    def __post_init__(self) -> None:
        actuators = np.asarray(self.actuators, dtype=float)
        if actuators.ndim != 2 or actuators.shape[0] != len(self.poses):
            raise InvalidInputError(f"{actuators.shape} actuator rows for {len(self.poses)} poses")
        if not np.all(np.isfinite(actuators)):
            raise InvalidInputError("non-finite actuator reading")
        object.__setattr__(self, "actuators", actuators)

    @property
    def rows_per_pose(self) -> int:
        return 3 if self.position_only else 6

    def __len__(self) -> int:
        return len(self.poses)


class ClosedLoopErrorModel:
    """The placement parameters of a mechanism and the platform pose's sensitivity to them.

    placements: every joint of the tree (model order), then every closure frame and the platform
    frame (each once). Parameter k of placement i is named f"{name}.dt[{k}]", [v; w] order.
    """

    def __init__(self, mechanism: Mechanism, placements: tuple[Placement, ...] | None = None) -> None:
        model = mechanism.model
        if placements is None:
            joints = tuple(Placement.joint(model.names[j]) for j in range(1, model.njoints))
            frame_names: list[str] = []
            for spec in mechanism.closures:
                frame_names += [spec.frame_a, spec.frame_b]
            frame_names.append(mechanism.platform_frame)
            frames = tuple(Placement.frame(n) for n in dict.fromkeys(frame_names))
            placements = joints + frames
        self.mechanism = mechanism
        self.placements = placements
        self.names = tuple(n for p in placements for n in p.parameter_names())
        self.n_parameters = len(self.names)
        # Joint parameters: regressor column c (6 per joint, model order) -> parameter column.
        self._joint_columns = np.full(6 * (model.njoints - 1), -1)
        self._frame_block: dict[int, int] = {}
        for i, placement in enumerate(placements):
            if placement.kind == "joint":
                j = model.getJointId(placement.name)
                self._joint_columns[6 * (j - 1):6 * j] = np.arange(6 * i, 6 * i + 6)
            else:
                self._frame_block[model.getFrameId(placement.name)] = 6 * i
        self._joint_targets = np.flatnonzero(self._joint_columns >= 0)

        def support(frame_id: int) -> np.ndarray:
            mask = np.zeros(model.njoints - 1)
            mask[np.array(model.supports[model.frames[frame_id].parentJoint][1:], dtype=int) - 1] = 1.0
            return np.repeat(mask, 6)

        # Every frame's regressor is one matrix G (per-joint blocks Ad(oMi[parent] jointPlacement),
        # WORLD) masked by the frame's support; a closure sees the signed mask support(b) - support(a).
        self._closure_frames = [(spec.frame_a_id, spec.frame_b_id, len(spec.rows)) for spec in mechanism.closures]
        self._row_masks = np.vstack([np.tile(support(fb) - support(fa), (count, 1))
                                     for fa, fb, count in self._closure_frames])
        self._platform = mechanism.platform_frame_id
        self._platform_mask = support(self._platform)
        # Rows seeing their closure frames' own errors: (rows, frame slot per row, parameter
        # columns per row, sign) for the frame_b and the frame_a side.
        self._own_frame_ids = sorted(f for f in self._frame_block)
        slot_of = {f: k for k, f in enumerate(self._own_frame_ids)}
        self._own_terms = []
        for side, sign in ((1, 1.0), (0, -1.0)):
            rows, slots, columns = [], [], []
            row = 0
            for frames_and_count in self._closure_frames:
                frame_id, count = frames_and_count[side], frames_and_count[2]
                if frame_id in self._frame_block:
                    for r in range(row, row + count):
                        rows.append(r)
                        slots.append(slot_of[frame_id])
                        columns.append(np.arange(self._frame_block[frame_id], self._frame_block[frame_id] + 6))
                row += count
            if rows:
                self._own_terms.append((np.array(rows), np.array(slots), np.array(columns), sign))
        # Batched sensitivities: the parent of each joint (G's blocks are Ad(oMi[parent] jointPlacement)),
        # the platform's support per velocity column, and the frames whose own adjoints are needed.
        self._parents = np.array(model.parents[1:], dtype=int)
        self._platform_v_mask = np.zeros(model.nv)
        for j in model.supports[model.frames[self._platform].parentJoint][1:]:
            self._platform_v_mask[model.idx_vs[j]] = 1.0
        self._adjoint_frames = self._own_frame_ids + [self._platform]
        self._plans: dict[bytes, _ColumnPlan] = {}

    def deltas(self, vector: np.ndarray) -> dict[Placement, np.ndarray]:
        """{placement: dt} for a full parameter vector (placements with a zero error omitted)."""
        blocks = np.asarray(vector, dtype=float).reshape(-1, 6)
        return {p: b for p, b in zip(self.placements, blocks) if np.any(b)}

    def perturbed(self, model: pin.Model, vector: np.ndarray) -> pin.Model:
        """A copy of `model` with the parameter vector applied (eq. 33)."""
        return perturb(model, self.deltas(vector))

    def _joint_twist_matrices(self, model: pin.Model, joints: np.ndarray) -> np.ndarray:
        """G (N, 6, 6 n_joints): spatial twist (WORLD) per unit joint-placement error (eq. 17), from
        the joint placements oMi (N, njoints, 4, 4): block j = Ad(oMi[parent(j)] jointPlacements[j]),
        the columns of Pinocchio's WORLD kinematic regressor."""
        placements = np.array([placement.homogeneous for placement in model.jointPlacements.tolist()[1:]])
        blocks = adjoint_matrices(joints[:, self._parents] @ placements)  # (N, n_joints, 6, 6)
        return blocks.transpose(0, 2, 1, 3).reshape(len(joints), 6, -1)

    def platform_sensitivity(self, solver: ClosedLoopSolver, q: np.ndarray, columns: np.ndarray | None = None,
                             with_factors: bool = False):
        """Platform pose at an assembled q, d xi_P / dp (6 x P, spatial twist in WORLD) and
        dq_passive / dp (n_passive x P), for the parameter `columns` (default all).

        Sliders held fixed; the passive joints move with the parameters through the closures.
        with_factors=True also returns the LU factors of the passive closure Jacobian at q, which
        `ClosedLoopSolver.forward(..., factors=...)` can reuse on a nearby model.
        One pose of `platform_sensitivities`.
        """
        batch = self.platform_sensitivities(solver, [q], columns)
        dq_dp = -np.linalg.solve(batch.passive_jacobians[0], batch.closure_jacobians[0])
        result = (pin.SE3(batch.poses[0]), batch.twist_jacobians[0], dq_dp)
        return result + (batch.factors[0],) if with_factors else result

    def platform_sensitivities(self, solver: ClosedLoopSolver, configurations,
                               columns: np.ndarray | None = None) -> PlatformSensitivities:
        """`platform_sensitivity` at N assembled configurations at once, for the parameter `columns`.

        Only the Pinocchio passes run per pose; the algebra (eq. 17 blocks Ad(oMi[parent]
        jointPlacement), closure rows, the implicit passive solve) runs on stacks, restricted to the
        requested columns. d xi_P / dp = X_P - (J_P,pas J_c,pas^-1) dr_c/dp: the passive solve has
        6 right-hand sides, not P. Leaves solver.data at the last configuration.
        """
        model, data = solver.model, solver.data
        n = len(configurations)
        jac_q = np.empty((n, solver.n_rows, model.nv))
        operator = np.empty((n, solver.n_rows, 6))
        joint_jacobian = np.empty((n, 6, model.nv))
        joints = np.empty((n, model.njoints, 4, 4))
        frames = np.empty((n, len(self._adjoint_frames), 4, 4))
        for i, q in enumerate(configurations):
            _, jac_q[i], operator[i] = solver.closure_sensitivity(q)
            joint_jacobian[i] = data.J
            joints[i] = [placement.homogeneous for placement in data.oMi.tolist()]
            every = data.oMf.tolist()
            frames[i] = [every[f].homogeneous for f in self._adjoint_frames]
        plan = self._column_plan(np.arange(self.n_parameters) if columns is None else np.asarray(columns, dtype=int))
        G = self._joint_twist_matrices(model, joints)[:, :, plan.g_columns]
        adjoints = adjoint_matrices(frames)
        dr_dp = np.zeros((n, solver.n_rows, plan.size))
        dr_dp[:, :, plan.joint_slots] = (operator @ G) * plan.row_masks
        # Own placement errors of the closure frames: row r of a closure sees +Ad(oMb) and -Ad(oMa).
        for rows, slots, sign, pick, row_index, slot_index in plan.own_terms:
            values = np.einsum("nrk,nrkj->nrj", operator[:, rows], adjoints[:, slots])[:, pick]
            dr_dp[:, row_index, slot_index] += sign * values
        xi = np.zeros((n, 6, plan.size))
        xi[:, :, plan.joint_slots] = G * plan.platform_mask
        if plan.platform_components.size:
            xi[:, :, plan.platform_slots] = adjoints[:, -1][:, :, plan.platform_components]
        square = jac_q[:, :, solver.passive]
        one_norms = np.abs(square).sum(axis=1).max(axis=1)
        factors = tuple((*lapack.dgetrf(block)[:2], float(norm)) for block, norm in zip(square, one_norms))
        platform_jacobian = (joint_jacobian * self._platform_v_mask)[:, :, solver.passive]  # WORLD frame Jacobian
        through_passive = np.swapaxes(np.linalg.solve(np.swapaxes(square, 1, 2), np.swapaxes(platform_jacobian, 1, 2)), 1, 2)
        return PlatformSensitivities(frames[:, -1], xi - through_passive @ dr_dp, square, dr_dp, factors)

    def _column_plan(self, columns: np.ndarray) -> _ColumnPlan:
        key = columns.tobytes()
        if key not in self._plans:
            self._plans[key] = _ColumnPlan.build(self, columns)
        return self._plans[key]


@dataclass(frozen=True, eq=False)
class PlatformSensitivities:
    """Platform sensitivities at N assembled configurations, over P parameter columns.

    poses: platform frames (N, 4, 4) in the base frame; twist_jacobians: d xi_P / dp (N, 6, P),
    spatial twists in WORLD; passive_jacobians: J_c,passive (N, n_pas, n_pas); closure_jacobians:
    dr_c / dp (N, n_pas, P) at fixed joints; factors: getrf LU and 1-norm of each passive Jacobian.
    """

    poses: np.ndarray
    twist_jacobians: np.ndarray
    passive_jacobians: np.ndarray
    closure_jacobians: np.ndarray
    factors: tuple[tuple, ...]

    def restricted(self, columns: np.ndarray) -> PlatformSensitivities:
        """The same sensitivities over a subset of the parameter columns."""
        return dataclasses.replace(self, twist_jacobians=self.twist_jacobians[:, :, columns],
                                   closure_jacobians=self.closure_jacobians[:, :, columns])

    def passive_motion(self, step: np.ndarray) -> np.ndarray:
        """First-order passive-joint change (N, n_pas) [rad or m] for a parameter step (P,):
        dq_passive = -J_c,passive^-1 (dr_c/dp) step."""
        return -np.linalg.solve(self.passive_jacobians, (self.closure_jacobians @ step)[:, :, None])[:, :, 0]


@dataclass(frozen=True, eq=False)
class _ColumnPlan:
    """Where each requested parameter column comes from in `platform_sensitivities`."""

    size: int
    joint_slots: np.ndarray  # output columns that are joint-placement parameters
    g_columns: np.ndarray  # their columns in G
    row_masks: np.ndarray  # (n_rows, len(joint_slots)) signed closure supports
    platform_mask: np.ndarray  # (len(joint_slots),) platform support
    own_terms: tuple  # (rows, slots, sign, pick (R, 6) mask, row index, output slot) per closure side
    platform_slots: np.ndarray  # output columns of the platform frame's own parameters
    platform_components: np.ndarray  # and their twist components

    @staticmethod
    def build(model: ClosedLoopErrorModel, columns: np.ndarray) -> _ColumnPlan:
        slot_of = np.full(model.n_parameters, -1)
        slot_of[columns] = np.arange(len(columns))
        g_column_of = np.full(model.n_parameters, -1)
        g_column_of[model._joint_columns[model._joint_targets]] = model._joint_targets
        joint_slots = np.flatnonzero(g_column_of[columns] >= 0)
        g_columns = g_column_of[columns[joint_slots]]
        own_terms = []
        for rows, slots, blocks, sign in model._own_terms:
            pick = slot_of[blocks] >= 0  # (R, 6)
            if pick.any():
                row_index = np.broadcast_to(rows[:, None], blocks.shape)[pick]
                own_terms.append((rows, slots, sign, pick, row_index, slot_of[blocks][pick]))
        own = model._frame_block.get(model._platform)
        platform_slots = np.array([], dtype=int)
        platform_components = np.array([], dtype=int)
        if own is not None:
            wanted = slot_of[own:own + 6] >= 0
            platform_slots = slot_of[own:own + 6][wanted]
            platform_components = np.flatnonzero(wanted)
        return _ColumnPlan(len(columns), joint_slots, g_columns, model._row_masks[:, g_columns],
                           model._platform_mask[g_columns], tuple(own_terms), platform_slots, platform_components)


def _residual_rows_batch(poses: np.ndarray, measured_positions: np.ndarray, measured_rotations: np.ndarray | None,
                         with_jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals e = [p_model - p_meas; log3(R_meas^T R_model)] (N, k) of N model poses (N, 4, 4)
    and de/dxi (N, k, 6) for spatial twists xi (WORLD): [I, -[p]x] and [0, Jlog3 R_model^T].
    k = 6, or 3 when measured_rotations is None (position only)."""
    p, rotation = poses[:, :3, 3], poses[:, :3, :3]
    position_error = p - measured_positions
    rows = None
    if with_jacobian:
        rows = np.zeros((len(poses), 3 if measured_rotations is None else 6, 6))
        rows[:, :3, :3] = np.eye(3)
        rows[:, :3, 3:] = -skew(p)  # dp = v + w x p
    if measured_rotations is None:
        return position_error, rows
    logs, angles = log3_batch(np.swapaxes(measured_rotations, 1, 2) @ rotation)
    if with_jacobian:
        rows[:, 3:, 3:] = jlog3_batch(logs, angles) @ np.swapaxes(rotation, 1, 2)
    return np.concatenate((position_error, logs), axis=1), rows


@dataclass(eq=False)
class _State:
    """An LM iterate: a model, the assembled configuration of every measured pose on it, and
    (once its Jacobian is known) its sensitivities, whose passive motion per step predicts the
    configurations of the next trial model."""

    model: pin.Model | None
    configurations: tuple[np.ndarray, ...]
    poses: tuple[pin.SE3, ...] = ()
    tangents: PlatformSensitivities | None = None
    factors: tuple[tuple, ...] | None = None
    whitened: tuple[np.ndarray, np.ndarray] | None = None


class _ClosedLoopProblem:
    """Whitened pose residuals over the base parameters (the LeastSquaresProblem protocol)."""

    def __init__(self, error_model: ClosedLoopErrorModel, measurements: PoseMeasurements, noise: TrackerNoise,
                 columns: np.ndarray) -> None:
        self.error_model = error_model
        self.measurements = measurements
        self.columns = columns
        rows = measurements.rows_per_pose
        weights = np.r_[np.full(3, 1 / noise.position), np.full(3, 1 / noise.rotation)][:rows]
        self.weights = np.tile(weights, len(measurements))
        measured = np.array([pose.homogeneous for pose in measurements.poses]).reshape(-1, 4, 4)
        self._measured_positions = measured[:, :3, 3]
        self._measured_rotations = None if measurements.position_only else measured[:, :3, :3]

    def assemble(self, model: pin.Model, start: tuple[np.ndarray, ...], factors: tuple | None = None) -> _State:
        """Assemble every measured pose on `model`, from `start`; with `factors` (each pose's
        passive-Jacobian LU on a nearby model) Newton takes chord steps without a new Jacobian."""
        solver = ClosedLoopSolver(self.error_model.mechanism.with_model(model))
        factors = factors or (None,) * len(start)
        solutions = [solver.forward(a, q_init=q0, factors=lu)
                     for a, q0, lu in zip(self.measurements.actuators, start, factors)]
        return _State(model, tuple(s.q for s in solutions), tuple(s.pose for s in solutions))

    def residual(self, state: _State) -> np.ndarray:
        """Whitened residual from the assembled poses alone (LM trial steps)."""
        if state.model is None:
            return np.full(len(self.weights), np.inf)
        poses = np.array([pose.homogeneous for pose in state.poses])
        residual, _ = _residual_rows_batch(poses, self._measured_positions, self._measured_rotations,
                                           with_jacobian=False)
        return residual.reshape(-1) * self.weights

    def evaluate(self, state: _State, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray, PlatformSensitivities]:
        """Unwhitened residual (6N or 3N), its Jacobian over `columns`, and the sensitivities behind it."""
        solver = ClosedLoopSolver(self.error_model.mechanism.with_model(state.model))
        sensitivities = self.error_model.platform_sensitivities(solver, state.configurations, columns)
        state.factors = sensitivities.factors
        residual, rows = _residual_rows_batch(sensitivities.poses, self._measured_positions, self._measured_rotations)
        return residual.reshape(-1), (rows @ sensitivities.twist_jacobians).reshape(residual.size, -1), sensitivities

    def residual_and_jacobian(self, state: _State) -> tuple[np.ndarray, np.ndarray]:
        if state.model is None:  # a trial step that did not assemble: reject it
            n = len(self.weights)
            return np.full(n, np.inf), np.zeros((n, len(self.columns)))
        if state.whitened is None:
            residual, jacobian, state.tangents = self.evaluate(state, self.columns)
            state.whitened = (residual * self.weights, jacobian * self.weights[:, None])
        return state.whitened

    def retract(self, state: _State, step: np.ndarray) -> _State:
        vector = np.zeros(self.error_model.n_parameters)
        vector[self.columns] = step
        model = self.error_model.perturbed(state.model, vector)
        start = state.configurations
        if state.tangents is not None:
            # First-order prediction of the new assembly: q_passive + dq_passive/dp step.
            passive = self.error_model.mechanism.passive_ids
            start = tuple(_shifted(q, passive, d) for q, d in zip(start, state.tangents.passive_motion(step)))
        try:
            return self.assemble(model, start, state.factors)
        except KinematicsError:
            return _State(None, state.configurations)


def _shifted(q: np.ndarray, indices: np.ndarray, delta: np.ndarray) -> np.ndarray:
    out = q.copy()
    out[indices] += delta
    return out


@dataclass(frozen=True)
class ClosedLoopCalibration:
    """Result of `calibrate_closed_loop`.

    mechanism: the calibrated machine (nominal closures on the identified tree model, home
    re-assembled); parameters: identified error per parameter name, relative to the starting model
    (zero for non-identifiable ones); std: their standard deviations from sigma^2 (J^T W J)^-1 over
    the base parameters (zero elsewhere); base: the identifiable set; rms_before/rms_after:
    position [m] and orientation [rad] RMS of the measurement residual (orientation nan when
    position-only); lm: the solver's record.
    """

    mechanism: Mechanism
    error_model: ClosedLoopErrorModel
    parameters: dict[str, float]
    std: dict[str, float]
    base: BaseParameters
    rms_before: tuple[float, float]
    rms_after: tuple[float, float]
    covariance: np.ndarray = field(repr=False)
    lm: LMResult = field(repr=False)


def _rms(residual: np.ndarray, rows: int) -> tuple[float, float]:
    per_pose = residual.reshape(-1, rows)
    position = float(np.sqrt(np.mean(np.sum(per_pose[:, :3] ** 2, axis=1))))
    rotation = float(np.sqrt(np.mean(np.sum(per_pose[:, 3:] ** 2, axis=1)))) if rows == 6 else float("nan")
    return position, rotation


@on_one_blas_thread
def calibrate_closed_loop(mechanism: Mechanism, measurements: PoseMeasurements, noise: TrackerNoise = TrackerNoise(),
                          *, rank_tolerance: float = 1e-8, max_iterations: int = 60, cost_tolerance: float = 1e-10,
                          absolute_cost_tolerance: float = 1e-6, step_significance: float = 0.01,
                          refine: bool = False,
                          refine_rank_tolerance: float = 1e-7, refine_iterations: int = 400,
                          error_model: ClosedLoopErrorModel | None = None) -> ClosedLoopCalibration:
    """Identify the placement errors of every joint and closure/platform frame (module docstring).

    LM stops when an accepted step lowers the whitened cost 1/2 chi^2 by less than
    step_significance * s^2, s^2 = chi^2 / (m - p) being the a-posteriori noise variance (m rows,
    p base parameters): such a step moves the estimate by at most sqrt(2 step_significance) of its
    own standard deviation (0.14 for 0.01), which the data cannot tell from noise. Being relative to
    the fit's own residual, the rule keeps noise-free data converging to rounding level. Also when
    the cost drops by less than cost_tolerance relatively or absolute_cost_tolerance absolutely
    (1e-6 of the assumed noise variance). On noisy data the LM tail beyond this rule creeps along
    the weakest directions for 5-15 more iterations without changing the held-out error.
    Base parameters are selected once, at the starting model, by column-pivoted QR of the whitened
    Jacobian (relative tolerance `rank_tolerance`); re-selecting during the iterations oscillates.
    refine=True (exact data only, e.g. simulation studies): after convergence, re-select the
    base parameters at the estimate, where some of the 148 directions unidentifiable at the
    nominal geometry have become weakly identifiable (O(error^2) effects), and continue with
    damped LM for up to `refine_iterations`. Noise-free 1 mm / 1 mrad: 0.4 um -> 0.04 um
    held-out in ~15 s. With noisy data it fits noise along those weak directions: leave it off.
    Raises IdentificationError when there are fewer measurement rows than base parameters, when a
    measured pose cannot be assembled on the starting model, or when LM fails.
    """
    error_model = error_model or ClosedLoopErrorModel(mechanism)
    everything = np.arange(error_model.n_parameters)
    problem = _ClosedLoopProblem(error_model, measurements, noise, everything)
    try:
        state = problem.assemble(mechanism.model, (mechanism.home,) * len(measurements))
    except KinematicsError as exc:
        raise IdentificationError(f"a measured pose does not assemble on the starting model: {exc}") from None
    residual, jacobian, sensitivities = problem.evaluate(state, everything)
    whitened = jacobian * problem.weights[:, None]
    base = select_base_parameters(whitened, error_model.names, rel_tol=rank_tolerance)
    identifiable = _structural_rank(error_model, measurements.position_only, noise, rank_tolerance)
    if base.rank < identifiable:
        raise IdentificationError(
            f"{len(measurements)} poses give {len(residual)} residual rows for {identifiable} identifiable "
            f"parameters and identify only {base.rank}: add poses spread over the workspace")
    problem.columns = np.array(base.indices)
    # LM starts here: its first residual and Jacobian are these, restricted to the base columns.
    state.whitened = (residual * problem.weights, whitened[:, problem.columns])
    state.tangents = sensitivities.restricted(problem.columns)
    # Damping starts low: 1e-3 over-damps the weak directions (about twice the iterations).
    degrees_of_freedom = max(len(residual) - base.rank, 1)
    relative_tolerance = max(cost_tolerance, 2.0 * step_significance / degrees_of_freedom)
    result = levenberg_marquardt(problem, state, max_iterations=max_iterations, initial_damping=1e-6,
                                 cost_tolerance=relative_tolerance, absolute_cost_tolerance=absolute_cost_tolerance)
    if result.state.model is None:
        raise IdentificationError("calibration ended on a model that does not assemble")
    if refine:
        _, jacobian, _ = problem.evaluate(result.state, everything)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)  # weak by construction
            refined = select_base_parameters(jacobian * problem.weights[:, None], error_model.names,
                                             rel_tol=refine_rank_tolerance)
        if refined.rank > base.rank:
            base = refined
            problem.columns = np.array(base.indices)
            state = problem.assemble(result.state.model, result.state.configurations)
            result = levenberg_marquardt(problem, state, max_iterations=refine_iterations, initial_damping=1e-9,
                                         cost_tolerance=1e-14)
    final_residual, final_jacobian = problem.residual_and_jacobian(result.state)
    rows = measurements.rows_per_pose
    # Covariance of the base parameters from the noise model: (J^T W J)^-1 with whitened J.
    # From the SVD of J rather than pinv(J^T J): squaring the condition number of a weakly
    # excited set can make the diagonal slightly negative.
    _, singular, vt = np.linalg.svd(final_jacobian, full_matrices=False)
    kept = singular > 1e-12 * singular[0]
    covariance = (vt[kept].T / singular[kept] ** 2) @ vt[kept]
    std = np.zeros(error_model.n_parameters)
    std[problem.columns] = np.sqrt(np.sum((vt[kept] / singular[kept, None]) ** 2, axis=0))
    identified = _accumulated_parameters(error_model, mechanism.model, result.state.model)
    calibrated = rehomed(mechanism.with_model(result.state.model))
    return ClosedLoopCalibration(
        mechanism=calibrated,
        error_model=error_model,
        parameters=dict(zip(error_model.names, identified)),
        std=dict(zip(error_model.names, std)),
        base=base,
        rms_before=_rms(residual, rows),
        rms_after=_rms(final_residual / problem.weights, rows),
        covariance=covariance,
        lm=result,
    )


_REFERENCE_POSES = 40  # a well-spread pose set on which the model's identifiable count is measured


def _structural_rank(error_model: ClosedLoopErrorModel, position_only: bool, noise: TrackerNoise,
                     rank_tolerance: float) -> int:
    """Number of identifiable parameters of the model itself, independent of the user's poses:
    the base-parameter count on a fixed, seeded set of poses spread over the workspace box.
    Cached on the error model (it depends on the starting geometry, not on the data)."""
    model = error_model.mechanism.model
    geometry = np.concatenate([np.ravel([p.homogeneous for p in model.jointPlacements]),
                               np.ravel([f.placement.homogeneous for f in model.frames])]).tobytes()
    key = (geometry, error_model.placements, position_only, noise.position / noise.rotation, rank_tolerance)
    if key not in _STRUCTURAL_RANKS:
        _STRUCTURAL_RANKS[key] = _count_identifiable(error_model, position_only, noise, rank_tolerance)
    return _STRUCTURAL_RANKS[key]


_STRUCTURAL_RANKS: dict[tuple, int] = {}


def _count_identifiable(error_model: ClosedLoopErrorModel, position_only: bool, noise: TrackerNoise,
                        rank_tolerance: float) -> int:
    from .simulation import measure, workspace_actuators

    mechanism = error_model.mechanism
    actuators = workspace_actuators(mechanism, _REFERENCE_POSES, np.random.default_rng(2020))
    reference = measure(mechanism, actuators, position_only=position_only)
    problem = _ClosedLoopProblem(error_model, reference, noise, np.arange(error_model.n_parameters))
    state = problem.assemble(mechanism.model, (mechanism.home,) * len(reference))
    _, jacobian, _ = problem.evaluate(state, problem.columns)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return select_base_parameters(jacobian * problem.weights[:, None], error_model.names, rank_tolerance).rank


def _accumulated_parameters(error_model: ClosedLoopErrorModel, start: pin.Model, end: pin.Model) -> np.ndarray:
    """dt per placement with end = start * exp6(dt): log6(start^-1 end), placement by placement."""
    from .poe import placement_of

    blocks = [pin.log6(placement_of(start, p).actInv(placement_of(end, p))).vector for p in error_model.placements]
    return np.concatenate(blocks)


@on_one_blas_thread
def pose_errors(machine_a: Mechanism, machine_b: Mechanism, actuators: np.ndarray) -> PoseErrors:
    """Platform pose differences of two machines driven with the same sliders (rows of actuators)."""
    solver_a, solver_b = ClosedLoopSolver(machine_a), ClosedLoopSolver(machine_b)
    position, rotation = [], []
    for sliders in np.asarray(actuators, dtype=float):
        pa, pb = solver_a.forward(sliders).pose, solver_b.forward(sliders).pose
        position.append(np.linalg.norm(pa.translation - pb.translation))
        rotation.append(np.linalg.norm(pin.log3(pa.rotation.T @ pb.rotation)))
    return PoseErrors(np.array(position), np.array(rotation))


@on_one_blas_thread
def predicted_pose_std(calibration: ClosedLoopCalibration, actuators: np.ndarray) -> PoseErrors:
    """Predicted standard deviation of the calibrated platform pose at the given sliders.

    Propagates the base-parameter covariance sigma^2 (J^T W J)^-1 through the pose sensitivity:
    position [m] = sqrt(trace of the 3x3 position block), orientation [rad] likewise.
    """
    mechanism = calibration.mechanism
    error_model = ClosedLoopErrorModel(mechanism, calibration.error_model.placements)
    solver = ClosedLoopSolver(mechanism)
    columns = np.array(calibration.base.indices)
    configurations = [solver.forward(sliders).q for sliders in np.asarray(actuators, dtype=float)]
    sensitivities = error_model.platform_sensitivities(solver, configurations, columns)
    position, rotation = [], []
    for pose, dxi in zip(sensitivities.poses, sensitivities.twist_jacobians):
        # Position of P and local orientation, per unit base parameter.
        point = np.hstack((np.eye(3), -pin.skew(pose[:3, 3]))) @ dxi
        angular = pose[:3, :3].T @ dxi[3:]
        position.append(math.sqrt(np.trace(point @ calibration.covariance @ point.T)))
        rotation.append(math.sqrt(np.trace(angular @ calibration.covariance @ angular.T)))
    return PoseErrors(np.array(position), np.array(rotation))
