"""Calibration of any serial chain of a Pinocchio model (base frame to tool frame), local POE model.

Error model (Zhang et al., Symmetry 2020, section 3.1): every kinematic error is a right-multiplied
error twist on an initial pose, T(0) <- T(0) exp6(dt) (eq. 33), for each joint placement of the
chain and the tool placement. Joint twists and joint readings are taken as exact; a joint zero
offset needs no parameter of its own (see `simulate_serial_measurements`).

Measurement model and residual, per pose i (one choice, used everywhere here): a tracker measures
the frame M = F g(q) K (`m3t1r.measurement_setup`), F the robot base {B} in the measurement frame,
g(q) the tool pose in {B}, K the measured frame (marker) in the tool frame; both F and K are
identity unless given or estimated. Optionally, joints comply under gravity: q -> q + c tau(q).
    position    r_p = p_model - p_meas          (m, in the measurement frame; {B} when F = I)
    orientation r_R = log3(R_meas^T R_model)    (rad, in the LOCAL measured frame)
with measurement noise p_meas = p + e_p, e_p ~ N(0, sigma_p^2 I) and R_meas = R exp3(e_R),
e_R ~ N(0, sigma_R^2 I) (the tracker's, `TrackerNoise`), and joint-reading noise sigma_q per joint
(`joint_noise`). Residuals are whitened by the Cholesky factor of their predicted covariance, which
includes the joint noise propagated through the joint Jacobian. Unlike the paper's spatial log6
error (eq. 18), whose linear part is the motion of the point at {B}'s origin, these rows have the
physical units of the sensor's noise, so whitening by the tracker's specification is meaningful.
Their exact Jacobians follow from the WORLD error Jacobian of `m3t1r.poe` (eq. 17): d p = v + w x p
and d r_R = Jlog3(R_meas^T R) R^T w, with every twist expressed in the measurement frame.
Position-only mode drops the orientation rows.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.identification import (
    BaseParameters,
    parameter_columns,
    triangular_factor,
)
from m3t1r.calibration.measurement_setup import MeasurementSetup, register_frame
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import (
    CalibrationOptions,
    FitSummary,
    PipelineFit,
    prior_columns,
    run_pipeline,
    summary_fields,
)
from m3t1r.calibration.serial_simulation import _checked_joint_noise, _readonly
from m3t1r.errors import IdentificationError, InvalidInputError, real_array
from m3t1r.model.poe import Placement, SerialChain, jlog3_batch, log3_batch, perturb, placement_poses, skew

__all__ = [
    "SerialCalibration",
    "SerialLayout",
    "SerialMeasurements",
    "SerialProblem",
    "SerialResidual",
    "SerialState",
    "calibrate_serial",
    "compliant_readings",
    "gravity_torques",
    "moved_mass",
    "nominal_state",
    "parse_measurements",
    "pose_whitening",
    "require_gravity_load",
    "start_state",
]


# --------------------------------------------------------------------------------------------------
# Residuals
#
# The optimiser's state (`SerialState`) holds the chain's n + 1 initial poses T(0) as one read-only
# (n + 1, 4, 4) array (`SerialChain.initial_transforms`), not a Pinocchio model: a step
# T(0) <- T(0) exp6(dx) (eq. 33) then costs n + 1 small products instead of a model copy, and forward
# kinematics of all poses is one batched pass (`placement_poses`); beside them, the measurement frame
# F and marker K (4 x 4) and the joint compliances. The calibrated model is built once, at the end.


def _placement_rows(frames: np.ndarray, orientation: bool, log_jacobians: np.ndarray | None = None) -> np.ndarray:
    """Residual rows (N, k, 6 (n + 1)) per unit placement error, from `placement_poses` frames F.

    The WORLD Jacobian block of placement j is Ad(F_j) = [[R_j, [p_j] R_j], [0, R_j]] (eq. 17). Mapped
    to this module's residual: the tool origin moves by v + w x p_P, i.e. [R_j, [p_j - p_P] R_j]
    (WORLD); the orientation rows are Jlog3 R_P^T w = Jlog3 [0, R_P^T R_j] (LOCAL), with Jlog3 = I when
    log_jacobians (N, 3, 3) is None. k = 6 with orientation, else 3. Formed from the frames directly,
    without the 6 x 6 adjoints.
    """
    n_poses, n_blocks = frames.shape[:2]
    k = 6 if orientation else 3
    rotations = np.ascontiguousarray(frames[..., :3, :3])  # (N, m, 3, 3); stacked products are slow on views
    side_by_side = rotations.transpose(0, 2, 1, 3).reshape(n_poses, 3, 3 * n_blocks)  # [R_1 ... R_m] per pose
    offsets = frames[..., :3, 3] - frames[:, -1:, :3, 3]  # p_j - p_P (N, m, 3)
    rows = np.empty((n_poses, k, n_blocks, 6))  # pose, residual row, placement, twist component
    rows[:, :3, :, :3] = side_by_side.reshape(n_poses, 3, n_blocks, 3)
    rows[:, :3, :, 3:] = (skew(offsets) @ rotations).transpose(0, 2, 1, 3)
    if orientation:
        rows[:, 3:, :, :3] = 0.0
        left = np.swapaxes(rotations[:, -1], 1, 2)  # R_P^T
        if log_jacobians is not None:
            left = log_jacobians @ left
        # One (3 x 3) @ (3 x 3m) product per pose covers every placement.
        rows[:, 3:, :, 3:] = (left @ side_by_side).reshape(n_poses, 3, n_blocks, 3)
    return rows.reshape(n_poses, k, 6 * n_blocks)


@dataclass(frozen=True)
class SerialMeasurements:
    """Checked measurements of a serial robot (`parse_measurements`): joint readings q (N, n) [rad or m]
    and measured positions [m] (N, 3), or (N, 3 P) of P points per row; rotations (N, 3, 3) of the
    measured frames, None with positions only."""

    q: np.ndarray  # (N, n)
    positions: np.ndarray  # (N, 3); (N, 3 P) with P points per row, NaN where a point was not seen
    rotations: np.ndarray | None  # (N, 3, 3), None in position-only mode (always with points)
    n_points: int = 0  # 0: one measured frame per row; P: P points per row

    @property
    def rows_per_pose(self) -> int:
        if self.n_points:
            return 3 * self.n_points
        return 3 if self.rotations is None else 6

    @functools.cached_property
    def seen(self) -> np.ndarray:
        """(N, rows_per_pose) whether each residual row was measured (False for a point not seen)."""
        if self.n_points:
            return np.isfinite(self.positions)
        return np.ones((self.q.shape[0], self.rows_per_pose), dtype=bool)


@dataclass(frozen=True)
class SerialLayout:
    """The columns of the parameter vector x, in this order: the chain's 6 (n + 1) placement errors
    (`SerialChain.parameter_names`), the measurement frame's right-multiplied error F <- F exp6(df)
    (6, m and rad), the marker's K <- K exp6(dk) (6, or its 3 translations with positions only), and
    one compliance per joint (rad/Nm, or m/N for a prismatic joint)."""

    n_joints: int
    frame: bool = False
    marker: int = 0  # 0, 3 or 6 columns; 3 P for P points (each point's offset)
    compliance: bool = False
    points: int = 0  # P points per row, whose offsets are the marker columns

    @property
    def n_chain(self) -> int:
        return 6 * (self.n_joints + 1)

    @property
    def frame_slice(self) -> slice:
        return slice(self.n_chain, self.n_chain + (6 if self.frame else 0))

    @property
    def marker_slice(self) -> slice:
        return slice(self.frame_slice.stop, self.frame_slice.stop + self.marker)

    @property
    def compliance_slice(self) -> slice:
        start = self.marker_slice.stop
        return slice(start, start + (self.n_joints if self.compliance else 0))

    @property
    def size(self) -> int:
        return self.compliance_slice.stop

    @property
    def setup_columns(self) -> np.ndarray:
        """The measurement setup's columns: the gauge, kept first by the base-parameter choice."""
        return np.arange(self.n_chain, self.marker_slice.stop)

    def names(self, chain: SerialChain) -> tuple[str, ...]:
        names = chain.parameter_names()
        names += tuple(f"measurement_frame.dt[{k}]" for k in range(6)) if self.frame else ()
        if self.points:
            names += tuple(f"marker.p{k + 1}.dt[{j}]" for k in range(self.points) for j in range(3))
        else:
            names += tuple(f"marker.dt[{k}]" for k in range(self.marker))
        return names + (tuple(f"compliance.{joint}" for joint in chain.joint_names) if self.compliance else ())


_IDENTITY = np.eye(4)
_IDENTITY.flags.writeable = False


@dataclass(frozen=True, eq=False)
class SerialState:
    """One optimiser iterate (read-only arrays; caches key on identity).

    transforms: the chain's initial poses T(0) (n + 1, 4, 4) (m). frame: F, the robot base in the
    measurement frame (4, 4); marker: K, the measured frame in the tool frame (4, 4).
    compliance: c (n,) with joint coordinates q + c tau(q), or None. accumulated: the sum of the
    steps taken since the start (layout order), which priors pull toward zero; None means zero.
    points: the offsets (P, 3) [m] in the tool frame of the points measured, or None (one frame).
    """

    transforms: np.ndarray
    frame: np.ndarray = field(default_factory=lambda: _IDENTITY)
    marker: np.ndarray = field(default_factory=lambda: _IDENTITY)
    compliance: np.ndarray | None = None
    accumulated: np.ndarray | None = None
    points: np.ndarray | None = None

    @property
    def plain(self) -> bool:
        """Identity frame and marker: the tool itself measured in the robot base."""
        return self.points is None and np.array_equal(self.frame, _IDENTITY) and np.array_equal(self.marker, _IDENTITY)


class _Evaluation:
    """What one state gives, computed on demand: frames (N, n+1, 4, 4) in the robot base, the
    measured frames M = F g K (N, 4, 4) (F g with points, whose positions (N, P, 3) are `points`),
    raw residual (N, k), orientation logs and angles, whitened residual and full whitened Jacobian."""

    def __init__(self, frames: np.ndarray, measured: np.ndarray, points: np.ndarray | None = None) -> None:
        self.frames = frames
        self.measured = measured
        self.points = points
        self.residual: np.ndarray | None = None
        self.logs: np.ndarray | None = None
        self.angles: np.ndarray | None = None
        self.whitened: np.ndarray | None = None
        self.jacobian: np.ndarray | None = None


class SerialResidual:
    """The whitened residual of every parameter of `layout`, as a function of the state (`SerialState`).

    Pose i is predicted as M_i = F g(q_i + c tau_i) K (module docstring); its residual is
    [p_M - p_meas (m, measurement frame); log3(R_meas^T R_M) (rad, measured frame)].
    The last state's evaluation is kept (keyed by identity): the optimiser asks for a trial's
    residual and, once accepted, for its Jacobian at the same state.
    """

    def __init__(
        self,
        chain: SerialChain,
        data: SerialMeasurements,
        whitening: np.ndarray,
        layout: SerialLayout | None = None,
        torques: np.ndarray | None = None,
    ) -> None:
        self.chain = chain
        self.data = data
        self.whitening = whitening  # (N, k, k): inverse Cholesky factor of each pose's covariance
        self.layout = layout or SerialLayout(chain.n_joints)
        self.torques = torques  # (N, n) gravity torques tau(q) (Nm or N), for the compliance columns
        self._state: SerialState | None = None
        self._evaluation: _Evaluation | None = None

    def joint_coordinates(self, state: SerialState) -> np.ndarray:
        """q + c tau(q) (N, n): the readings moved by the joints' compliance under gravity."""
        if state.compliance is None or self.torques is None:
            return self.data.q
        return self.data.q + state.compliance * self.torques

    def _evaluate(self, state: SerialState) -> _Evaluation:
        if state is not self._state or self._evaluation is None:
            frames = placement_poses(self.chain, state.transforms, self.joint_coordinates(state))
            if state.points is not None:
                tool = state.frame @ frames[:, -1]
                points = np.einsum("nij,pj->npi", tool[:, :3, :3], state.points) + tool[:, None, :3, 3]
                self._evaluation = _Evaluation(frames, tool, points)
            else:
                measured = frames[:, -1] if state.plain else state.frame @ frames[:, -1] @ state.marker
                self._evaluation = _Evaluation(frames, measured)
            self._state = state
        return self._evaluation

    def raw_residual(self, state: SerialState) -> np.ndarray:
        """(N, k): p_model - p_meas (m, measurement frame) [, log3(R_meas^T R_model) (rad, measured frame)]."""
        e = self._evaluate(state)
        if e.residual is None:
            if e.points is not None:
                # A point not seen gives a zero row (its whitening row is zero too).
                seen = self.data.seen
                measured = np.where(seen, self.data.positions, 0.0)
                e.residual = np.where(seen, e.points.reshape(seen.shape) - measured, 0.0)
            elif self.data.rotations is None:
                position = e.measured[:, :3, 3] - self.data.positions
                e.residual = position
            else:
                position = e.measured[:, :3, 3] - self.data.positions
                e.logs, e.angles = log3_batch(np.swapaxes(self.data.rotations, 1, 2) @ e.measured[:, :3, :3])
                e.residual = np.concatenate([position, e.logs], axis=1)
            e.residual.flags.writeable = False  # cached: callers share it
        return e.residual

    def residual(self, state: SerialState) -> np.ndarray:
        """Whitened residual (N k,), no Jacobian: what a trial step needs."""
        e = self._evaluate(state)
        if e.whitened is None:
            e.whitened = (self.whitening @ self.raw_residual(state)[:, :, None]).reshape(-1)
            e.whitened.flags.writeable = False
        return e.whitened

    def residual_and_jacobian(self, state: SerialState) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residual (N k,) and its Jacobian (N k, layout.size) over every parameter."""
        r = self.residual(state)
        e = self._evaluate(state)
        if e.jacobian is None:
            log_jacobians = None if e.logs is None or e.angles is None else jlog3_batch(e.logs, e.angles)
            e.jacobian = (self.whitening @ self._rows(state, e, log_jacobians)).reshape(r.size, -1)
            e.jacobian.flags.writeable = False
        return r, e.jacobian

    def _rows(self, state: SerialState, e: _Evaluation, log_jacobians: np.ndarray | None) -> np.ndarray:
        """Unwhitened residual rows (N, k, layout.size).

        Each error acts as a right-multiplied twist on a frame known in the measurement frame: F
        (the frame's error), F F_j (placement j, `placement_poses`) and M = F g K (the marker's); so
        `_placement_rows` of the stack [F, F F_1 .. F F_P, M] with M as endpoint gives them all. A
        compliance column is d r / d q_j tau_j, with d r / d q_j = (placement j's rows) S_j because
        F_j exp6(S_j q_j) moves like F_j exp6(S_j dq) at fixed q_j (the twists commute).
        """
        if state.points is not None:
            return self._point_rows(state, e)
        layout, n_poses, n = self.layout, e.frames.shape[0], self.chain.n_joints
        orientation = self.data.rotations is not None
        k = 6 if orientation else 3
        if state.plain and not (layout.frame or layout.marker):
            placement = _placement_rows(e.frames, orientation, log_jacobians).reshape(n_poses, k, n + 1, 6)
            frame_rows = marker_rows = None
        else:
            stack = np.concatenate(
                [np.broadcast_to(state.frame, (n_poses, 1, 4, 4)), state.frame @ e.frames, e.measured[:, None]], axis=1
            )
            rows = _placement_rows(stack, orientation, log_jacobians).reshape(n_poses, k, n + 3, 6)
            placement, frame_rows, marker_rows = rows[:, :, 1 : n + 2], rows[:, :, 0], rows[:, :, -1]
        if layout.size == layout.n_chain:
            return placement.reshape(n_poses, k, -1)
        out = np.empty((n_poses, k, layout.size))
        out[:, :, : layout.n_chain] = placement.reshape(n_poses, k, -1)
        if layout.frame:
            assert frame_rows is not None, "the stacked branch runs with a frame"
            out[:, :, layout.frame_slice] = frame_rows
        if layout.marker:
            assert marker_rows is not None, "the stacked branch runs with a marker"
            out[:, :, layout.marker_slice] = marker_rows[:, :, : layout.marker]
        if layout.compliance:
            assert self.torques is not None, "a compliance layout has its gravity torques"
            joint_rows = np.einsum("nikj,kj->nik", placement[:, :, :n], self.chain.twists)
            out[:, :, layout.compliance_slice] = joint_rows * self.torques[:, None, :]
        return out

    def _point_rows(self, state: SerialState, e: _Evaluation) -> np.ndarray:
        """Unwhitened rows (N, 3 P, layout.size) of P points: point k is the endpoint F g T(p_k) of the
        stack [F, F F_1 .. F F_P] as in `_rows`, and its own offset's columns are its translation rows."""
        assert e.points is not None and state.points is not None
        layout, n_poses, n = self.layout, e.frames.shape[0], self.chain.n_joints
        out = np.zeros((n_poses, 3 * len(state.points), layout.size))
        stack = np.concatenate(
            [np.broadcast_to(state.frame, (n_poses, 1, 4, 4)), state.frame @ e.frames, e.measured[:, None]], axis=1
        )
        for k in range(len(state.points)):
            stack[:, -1, :3, 3] = e.points[:, k]
            rows = _placement_rows(stack, False).reshape(n_poses, 3, n + 3, 6)
            block = slice(3 * k, 3 * k + 3)
            out[:, block, : layout.n_chain] = rows[:, :, 1 : n + 2].reshape(n_poses, 3, -1)
            if layout.frame:
                out[:, block, layout.frame_slice] = rows[:, :, 0]
            if layout.marker:
                start = layout.marker_slice.start + 3 * k
                out[:, block, start : start + 3] = rows[:, :, -1, :3]
            if layout.compliance:
                assert self.torques is not None, "compliance columns are laid out only with the gravity torques"
                joint_rows = np.einsum("nikj,kj->nik", rows[:, :, 1 : n + 1], self.chain.twists)
                out[:, block, layout.compliance_slice] = joint_rows * self.torques[:, None, :]
        return out

    def retract(self, state: SerialState, step: np.ndarray) -> SerialState:
        """T_j(0) <- T_j(0) exp6(dt_j) per placement (eq. 33), F <- F exp6(df), K <- K exp6(dk),
        c <- c + dc, for step = x in layout order."""
        layout = self.layout
        out = state.transforms.copy()
        for j in range(out.shape[0]):
            twist = step[6 * j : 6 * j + 6]
            if np.any(twist):
                out[j] = out[j] @ pin.exp6(twist).homogeneous
        out.flags.writeable = False
        frame, marker, compliance, points = state.frame, state.marker, state.compliance, state.points
        if layout.frame:
            frame = _readonly(frame @ pin.exp6(step[layout.frame_slice]).homogeneous)
        if layout.marker and points is not None:
            points = _readonly(points + step[layout.marker_slice].reshape(points.shape))
        elif layout.marker:
            twist = np.zeros(6)
            twist[: layout.marker] = step[layout.marker_slice]
            marker = _readonly(marker @ pin.exp6(twist).homogeneous)
        if layout.compliance:
            compliance = _readonly((0.0 if compliance is None else compliance) + step[layout.compliance_slice])
        accumulated = _readonly(step if state.accumulated is None else state.accumulated + step)
        return SerialState(out, frame, marker, compliance, accumulated, points)


class SerialProblem:
    """The whitened calibration residual over some columns, for the pipeline (`CalibrationProblem`).

    active: (N,) poses that count (flagged outliers are zero rows); priors: {column: sigma} add a
    row x_c / sigma (Tikhonov, toward the start) per column with a prior, sigma in m, rad or rad/Nm.
    """

    default_cost_tolerance = 1e-12
    default_step_significance = 0.0

    def __init__(
        self, residual: SerialResidual, columns: Sequence[int] | np.ndarray, priors: Mapping[int, float] | None = None
    ) -> None:
        self._residual = residual
        self.names = residual.layout.names(residual.chain)
        self.columns = np.asarray(columns, dtype=int)
        self.priors = dict(priors or {})
        self.active = np.ones(residual.data.q.shape[0], dtype=bool)

    @property
    def model(self) -> SerialResidual:
        return self._residual

    @property
    def rows_per_pose(self) -> int:
        return self._residual.data.rows_per_pose

    @property
    def seen(self) -> np.ndarray:
        return self._residual.data.seen

    @property
    def n_points(self) -> int:
        return self._residual.data.n_points

    @property
    def setup_columns(self) -> np.ndarray:
        return self._residual.layout.setup_columns

    def default_iterations(self, n_parameters: int) -> int:
        return 30

    def reselection_bound(self) -> int:
        """The structural bound 4 r + 2 p + 6 (+ 3 with positions only, section 3.2; + n with compliance)."""
        layout = self._residual.layout
        bound = self._residual.chain.rank_bound(self._residual.data.rotations is None)
        return bound + (layout.n_joints if layout.compliance else 0)

    def check_base(self, base: BaseParameters, factor: np.ndarray, fixed: Sequence[int]) -> None:
        """Nothing is refused here: a rank below the bound is chosen again at the estimate."""

    def release(self, state: SerialState) -> None:
        """Nothing to drop: the residual's cache keys on the last state evaluated."""

    def restart(self, state: SerialState) -> SerialState:
        return state  # read-only: its evaluations do not depend on the columns or the poses kept

    def accumulated(self, state: SerialState) -> np.ndarray:
        return np.zeros(len(self.names)) if state.accumulated is None else state.accumulated

    def pose_blocks(self, state: SerialState) -> np.ndarray:
        return self._residual.residual(state).reshape(-1, self.rows_per_pose)

    def raw_blocks(self, state: SerialState) -> np.ndarray:
        return self._residual.raw_residual(state)

    def pose_rows(self, state: SerialState) -> tuple[np.ndarray, np.ndarray]:
        r, J = self._residual.residual_and_jacobian(state)
        keep = np.repeat(self.active, self.rows_per_pose)
        return r[keep], np.asfortranarray(J[keep][:, self.columns])

    def jacobian_factor(self, state: SerialState, with_residual: bool = False) -> np.ndarray:
        """The whitened Jacobian of every pose row over every column (a copy); with_residual, the
        triangular factor of the inliers' [J r] instead."""
        r, J = self._residual.residual_and_jacobian(state)
        if not with_residual:
            return J.copy()
        keep = np.repeat(self.active, self.rows_per_pose)
        return triangular_factor(J[keep], r[keep])

    def _mask(self) -> np.ndarray | None:
        return None if self.active.all() else np.repeat(self.active, self._residual.data.rows_per_pose)

    def _prior_rows(self, state: SerialState) -> tuple[np.ndarray, np.ndarray]:
        picked = [(i, self.priors[c]) for i, c in enumerate(self.columns) if c in self.priors]
        values, jacobian = np.zeros(len(picked)), np.zeros((len(picked), len(self.columns)))
        for row, (i, sigma) in enumerate(picked):
            jacobian[row, i] = 1.0 / sigma
            values[row] = 0.0 if state.accumulated is None else state.accumulated[self.columns[i]] / sigma
        return values, jacobian

    def residual(self, state: SerialState) -> np.ndarray:
        r = self._residual.residual(state)
        mask = self._mask()
        if mask is None and not self.priors:
            return r
        r = r if mask is None else r * mask
        return np.concatenate((r, self._prior_rows(state)[0]))

    def residual_and_jacobian(self, state: SerialState) -> tuple[np.ndarray, np.ndarray]:
        r, J = self._residual.residual_and_jacobian(state)
        J = J[:, self.columns]
        mask = self._mask()
        if mask is None and not self.priors:
            return r, J
        if mask is not None:
            r, J = r * mask, J * mask[:, None]
        values, rows = self._prior_rows(state)
        return np.concatenate((r, values)), np.vstack((J, rows))

    def retract(self, state: SerialState, step: np.ndarray) -> SerialState:
        full = np.zeros(self._residual.layout.size)
        full[self.columns] = step
        return self._residual.retract(state, full)


def nominal_state(chain: SerialChain, model: pin.Model, setup: MeasurementSetup | None = None) -> SerialState:
    """The starting state: `model`'s initial poses, and the setup's frame and marker (default identity)."""
    transforms = chain.initial_transforms(model)
    transforms.flags.writeable = False
    if setup is None:
        return SerialState(transforms)
    return SerialState(transforms, _readonly(setup.frame.homogeneous), _readonly(setup.marker.homogeneous))


def pose_whitening(
    chain: SerialChain, state: SerialState, data: SerialMeasurements, noise: TrackerNoise, joint_noise: float
) -> np.ndarray:
    """Inverse Cholesky factors (N, k, k) of the residual covariance of each pose.

    Cov = diag(sigma_p^2 I3 [, sigma_R^2 I3]) + J_q sigma_q^2 J_q^T, with sigma_p, sigma_R the
    tracker's `noise`, sigma_q = `joint_noise` and J_q the residual's Jacobian with respect to the
    joint readings. Computed once at the starting state so that the
    cost function does not change under the optimiser's feet; the joint Jacobian barely moves over
    millimetre-size corrections.
    """
    n_poses = data.q.shape[0]
    k = data.rows_per_pose
    sigmas = np.full(k, noise.position)
    if data.rotations is not None:
        sigmas[3:] = noise.rotation
    seen = data.seen
    if joint_noise == 0.0:
        return np.diag(1.0 / sigmas)[None] * seen[:, :, None]
    unit = SerialResidual(chain, data, np.broadcast_to(np.eye(k), (n_poses, k, k)))
    rows = unit.residual_and_jacobian(state)[1].reshape(n_poses, k, -1)
    n = chain.n_joints
    # Column k of the joint Jacobian is block k of the error Jacobian applied to S_k:
    # Ad(g_{B,k-1} T_{k-1,k}(0)) S_k = Ad(g_{B,k}) S_k because Ad(exp(S_k q_k)) S_k = S_k.
    joint_rows = np.einsum("nikj,kj->nik", rows[:, :, : 6 * n].reshape(n_poses, k, n, 6), chain.twists)
    covariance = np.diag(sigmas**2) + joint_noise**2 * joint_rows @ np.swapaxes(joint_rows, 1, 2)
    # A point not seen is decoupled (unit variance, no covariance): the factor of the rows seen is then
    # the one of their own covariance, and the unseen rows are zeroed.
    pair = seen[:, :, None] & seen[:, None, :]
    covariance = np.where(pair, covariance, np.eye(k)[None])
    return np.linalg.inv(np.linalg.cholesky(covariance)) * seen[:, :, None]


def gravity_torques(model: pin.Model, chain: SerialChain, q_chain: ArrayLike) -> np.ndarray:
    """Generalized gravity tau(q) (N, n) on the chain's joints (Nm, or N for prismatic joints).

    tau = pinocchio.computeGeneralizedGravity at each configuration (the chain's coordinates set,
    every other joint at neutral), with the model's inertias (the URDF's <inertial>): the torque
    each joint must deliver to hold the arm still. A joint of torsional stiffness k then deflects
    by -tau / k: the compliance model q -> q + c tau has c = -1/k (rad/Nm).
    """
    q_chain = np.atleast_2d(np.asarray(q_chain, dtype=float))
    data = model.createData()
    velocity_index = [model.joints[j].idx_v for j in chain.joint_ids]
    out = np.empty(q_chain.shape)
    for i, row in enumerate(q_chain):
        tau = pin.computeGeneralizedGravity(model, data, chain.model_configuration(model, row))
        out[i] = tau[velocity_index]
    return out


def moved_mass(model: pin.Model, chain: SerialChain) -> float:
    """The mass [kg] of the bodies the chain's first joint moves (the URDF's <inertial> masses)."""
    return float(sum(model.inertias[j].mass for j in model.subtrees[chain.joint_ids[0]]))


def require_gravity_load(model: pin.Model, chain: SerialChain) -> None:
    """InvalidInputError when the chain moves no mass: gravity torques are then zero everywhere, and a
    compliance under gravity can neither be fitted nor applied."""
    if moved_mass(model, chain) <= 0.0:
        raise InvalidInputError(
            f"the links that joints {chain.joint_names[0]} .. {chain.joint_names[-1]} move have no mass (the URDF "
            "gives them no <inertial>): the gravity torques are zero in every posture, so joint compliance under "
            "gravity cannot be fitted or applied; use a URDF with the links' inertial elements, or leave "
            "out --compliance"
        )


def compliant_readings(
    model: pin.Model, chain: SerialChain, q_chain: ArrayLike, compliance: Mapping[str, float]
) -> np.ndarray:
    """q + c tau(q) (N, n): joint readings (N, n) [rad, m] moved by the compliances {joint: c}
    [rad/Nm, m/N] under gravity, tau from `model`'s inertias (`gravity_torques`); q itself without
    any. InvalidInputError (`require_gravity_load`) when the chain moves no mass."""
    q = np.atleast_2d(np.asarray(q_chain, dtype=float))
    if not compliance:
        return q
    require_gravity_load(model, chain)
    c = np.array([compliance.get(joint, 0.0) for joint in chain.joint_names])
    return q + c * gravity_torques(model, chain, q)


# --------------------------------------------------------------------------------------------------
# Calibration


def _parse_points(q: np.ndarray, measured_points: ArrayLike) -> SerialMeasurements:
    """(N, P, 3) positions of P points per row [m], NaN where a point was not seen; refused as
    `real_array` refuses complex or non-numeric values, and copied (the caller's array stays theirs)."""
    points = real_array(measured_points, "measured points").copy()
    if points.shape[2] != 3 or points.shape[1] < 1:
        raise InvalidInputError(f"measured points: expected shape (N, P, 3), got {points.shape}")
    if points.shape[0] != q.shape[0]:
        raise InvalidInputError(f"{q.shape[0]} joint readings but {points.shape[0]} rows of measured points")
    finite = np.isfinite(points)
    partial = np.flatnonzero(np.any(np.any(finite, axis=2) != np.all(finite, axis=2), axis=1))
    if partial.size:
        raise InvalidInputError(f"measured points: row {int(partial[0])} has a point with some coordinates missing")
    blind = np.flatnonzero(~np.any(finite, axis=(1, 2)))
    if blind.size:
        raise InvalidInputError(f"measured points: row {int(blind[0])} sees no point")
    unseen = np.flatnonzero(~np.any(finite[:, :, 0], axis=0))
    if unseen.size:
        raise InvalidInputError(f"measured points: point {int(unseen[0]) + 1} is seen in no row")
    return SerialMeasurements(q=q, positions=points.reshape(len(points), -1), rotations=None, n_points=points.shape[1])


def parse_measurements(
    chain: SerialChain, q_readings: ArrayLike, measured_poses: Sequence[pin.SE3] | ArrayLike, position_only: bool
) -> SerialMeasurements:
    """The checked measurements: joint readings (N, n) [rad or m] and SE3 poses, (N, 7) [x, y, z, qx, qy, qz, qw]
    rows [m], (N, 3) positions [m] (with `position_only`) or (N, P, 3) points; InvalidInputError names the row."""
    q = real_array(q_readings, "q_readings")
    if q.ndim != 2 or q.shape[1] != chain.n_joints:
        raise InvalidInputError(f"q_readings: expected shape (N, {chain.n_joints}), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"q_readings: non-finite value in row {int(np.flatnonzero(~np.isfinite(q).all(1))[0])}")
    if isinstance(measured_poses, np.ndarray) and measured_poses.ndim == 3 and measured_poses.shape[1:] != (4, 4):
        return _parse_points(q, measured_poses)
    if isinstance(measured_poses, Sequence) and any(isinstance(g, pin.SE3) for g in measured_poses):
        not_se3 = [i for i, g in enumerate(measured_poses) if not isinstance(g, pin.SE3)]
        if not_se3:
            raise InvalidInputError(f"measured_poses: row {not_se3[0]} is not an SE3 like the others")
        homogeneous = np.array([g.homogeneous for g in measured_poses if isinstance(g, pin.SE3)])  # all, as checked
        positions = homogeneous[:, :3, 3].copy()
        rotations = np.ascontiguousarray(homogeneous[:, :3, :3])
    else:
        array = real_array(measured_poses, "measured_poses")
        if array.ndim != 2 or array.shape[1] not in (3, 7):
            raise InvalidInputError(
                f"measured_poses: expected SE3 objects, (N, 7) [x, y, z, qx, qy, qz, qw] or (N, 3) positions, "
                f"got shape {array.shape}"
            )
        if not np.all(np.isfinite(array)):
            raise InvalidInputError(
                f"measured_poses: non-finite value in row {int(np.flatnonzero(~np.isfinite(array).all(1))[0])}"
            )
        if array.shape[1] == 3 and not position_only:
            raise InvalidInputError("measured_poses: positions only (N, 3) need position_only=True")
        positions = array[:, :3].copy()
        rotations = None
        if array.shape[1] == 7:
            norms = np.linalg.norm(array[:, 3:], axis=1)
            bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-6)
            if bad.size:
                raise InvalidInputError(f"measured_poses: quaternion of row {bad[0]} has norm {norms[bad[0]]:.6g}")
            rotations = np.array([pin.XYZQUATToSE3(row).rotation for row in array])
    if positions.shape[0] != q.shape[0]:
        raise InvalidInputError(f"{q.shape[0]} joint readings but {positions.shape[0]} measured poses")
    return SerialMeasurements(q=q, positions=positions, rotations=None if position_only else rotations)


@dataclass(frozen=True, kw_only=True)
class SerialCalibration(FitSummary[SerialState]):
    """Result of `calibrate_serial`: the fit's `FitSummary` (base, covariance, variance factor with
    the priors, RMS before and after at the nominal robot and the calibrated model, outliers, LM's run
    and settings, the start), and

    model: calibrated copy of the input model, T_c(0) = T(0) exp6(dt) per placement (eq. 33): the
        robot alone (the measurement frame and the marker are in `setup`, the compliance apart).
    deltas: identified dt = log6(T(0)^-1 T_c(0)) per placement of `chain.placements()` ([v; w], m, rad).
    setup: the measurement frame and marker, estimated or as given.
    compliance: {joint: c} (rad/Nm, m/N) of the joints whose compliance was fitted; q -> q + c tau(q).
    names: every candidate parameter (`SerialLayout`: placements, setup, compliance); values: each one's
        identified change from the start (zero where not fitted).
    fitted: the names finally fitted (base, or fewer after model selection), fitted_indices their
        columns, the covariance's order; parameter_std: sqrt(diag(covariance)).
    problem: the fit's problem (`cross_validate_serial`).
    """

    model: pin.Model
    chain: SerialChain
    deltas: Mapping[Placement, np.ndarray]
    parameter_std: np.ndarray
    position_only: bool
    setup: MeasurementSetup = field(default_factory=MeasurementSetup)
    fitted: tuple[str, ...] = ()
    fitted_indices: tuple[int, ...] = ()
    names: tuple[str, ...] = ()
    values: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    compliance: Mapping[str, float] = field(default_factory=dict)
    problem: SerialProblem | None = field(default=None, repr=False)

    def std(self) -> dict[str, float]:
        """Standard deviation per fitted parameter name (m, rad, rad/Nm)."""
        return dict(zip(self.fitted, map(float, self.parameter_std)))


def start_state(
    chain: SerialChain,
    model: pin.Model,
    data: SerialMeasurements,
    setup: MeasurementSetup,
    estimate_frame: bool,
    estimate_marker: bool,
    compliance: bool,
) -> SerialState:
    """The nominal robot with the given setup, and closed-form starts for what is estimated.

    estimate_frame: F from the rigid registration of the nominal predictions g(q) K to the measured
    positions (`register_frame`: any rotation, any distance). estimate_marker with orientations:
    K's rotation from R_meas,i = R_F R_g,i R_K, the rotation nearest (chordal mean, SVD
    projection) to sum_i (R_F R_g,i)^T R_meas,i, so that a marker given by its position alone
    (unknown axes) starts right too.
    """
    state = nominal_state(chain, model, setup)
    tool = placement_poses(chain, state.transforms, data.q)[:, -1]
    if data.n_points:
        return _point_start(state, tool, data, estimate_frame, compliance)
    if estimate_frame:
        frame = register_frame(tool @ state.marker, data.positions)
        state = replace(state, frame=_readonly(frame.homogeneous))
    if estimate_marker and data.rotations is not None:
        u, _, vt = np.linalg.svd(np.sum(np.swapaxes(state.frame[:3, :3] @ tool[:, :3, :3], 1, 2) @ data.rotations, 0))
        marker = state.marker.copy()
        marker[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        state = replace(state, marker=_readonly(marker))
    if compliance:
        state = replace(state, compliance=_readonly(np.zeros(chain.n_joints)))
    return state


# Alternations of the closed-form frame registration and point offsets that start a fit of points.
_POINT_START_ROUNDS = 4


def _point_start(
    state: SerialState, tool: np.ndarray, data: SerialMeasurements, estimate_frame: bool, compliance: bool
) -> SerialState:
    """The start of a fit of P points: alternately F by `register_frame` of every point seen (at its
    current offset) and each offset p_k in closed form given F, the mean over its rows of
    R_g^T (F^-1 p_meas - t_g) (least squares, R_g orthonormal); from zero offsets."""
    measured = data.positions.reshape(len(tool), data.n_points, 3)
    rows, points = np.nonzero(data.seen[:, ::3])
    offsets = np.zeros((data.n_points, 3))
    frame = pin.SE3(state.frame)
    for _ in range(_POINT_START_ROUNDS if estimate_frame else 1):
        if estimate_frame:
            model_points = tool[rows].copy()
            model_points[:, :3, 3] += np.einsum("nij,nj->ni", tool[rows, :3, :3], offsets[points])
            frame = register_frame(model_points, measured[rows, points])
        in_base = (measured[rows, points] - frame.translation) @ frame.rotation  # F^-1 p, row by row
        local = np.einsum("nji,nj->ni", tool[rows, :3, :3], in_base - tool[rows, :3, 3])
        offsets = np.array([local[points == k].mean(axis=0) for k in range(data.n_points)])
    state = replace(state, frame=_readonly(frame.homogeneous), points=_readonly(offsets))
    if compliance:
        state = replace(state, compliance=_readonly(np.zeros(data.q.shape[1])))
    return state


@on_one_blas_thread  # tiny matrices: BLAS threads only add wake-up latency
def calibrate_serial(
    model: pin.Model,
    chain: SerialChain,
    q_readings: ArrayLike,
    measured_poses: Sequence[pin.SE3] | ArrayLike,
    options: CalibrationOptions = CalibrationOptions(),
    *,
    position_only: bool = False,
) -> SerialCalibration:
    """Identify the placement errors of `chain` (and the measurement setup, compliance) from measurements.

    Measurement model: M_i = F g(q_i + c tau(q_i)) K (measurement_setup module), F = setup.frame
    (robot base in the measurement frame), K = setup.marker (measured frame in the tool frame).
    q_readings: (N, n) chain coordinates (rad or m) as read by the robot.
    measured_poses: measured frames M_i in the measurement frame: SE3 objects, or an (N, 7) array
        [x, y, z, qx, qy, qz, qw] (m), or (N, 3) positions (m) with position_only=True.
    position_only: use the position rows only (3 per pose; the marker's orientation is irrelevant).
    options (`CalibrationOptions`): noise whitens the residuals (its `actuator` is not used);
        joint_noise (rad or m, every joint) is propagated into the whitening through the joint
        Jacobian (0 takes the readings as exact); estimate_frame starts F by `register_frame` of
        the nominal predictions to the measurements, estimate_marker K's rotation in closed form.
        The setup's columns are kept first in the base-parameter choice, so the placements it makes
        redundant (the first placement for F, the tool placement for K) are the ones left nominal:
        the calibrated URDF's base stays the robot's base and its tool frame the tool. compliance
        adds candidates c_j (rad/Nm) with q_j -> q_j + c_j tau_j(q), tau from `gravity_torques`
        (the model's inertias), chosen like the other parameters.

    Method (`m3t1r.calibration.pipeline`): base parameters by pivoted QR of the whitened Jacobian at
    the start; LM over them with T(0) <- T(0) exp6(dx) (eq. 33); re-selection at the estimate while
    the rank is below the structural bound 4 r + 2 p + 6 (+ 3 with positions only, section 3.2; + n
    with compliance); then outliers, then selection. A fit that did not converge is returned with
    converged False.
    """
    chain.check_model(model)
    data = parse_measurements(chain, q_readings, measured_poses, position_only)
    if data.n_points:
        layout = SerialLayout(
            chain.n_joints, options.estimate_frame, 3 * data.n_points, options.compliance, data.n_points
        )
    else:
        marker = (3 if position_only else 6) if options.estimate_marker else 0
        layout = SerialLayout(chain.n_joints, options.estimate_frame, marker, options.compliance)
    names = layout.names(chain)
    if len(set(parameter_columns(names, options.fixed, "fixed parameter"))) == layout.size:
        raise IdentificationError(
            f"all {layout.size} candidate parameters are held fixed: nothing is left to fit "
            "(estimate the measurement frame, a marker or compliance, or fix fewer)"
        )
    start = start_state(
        chain, model, data, options.start_setup, options.estimate_frame, options.estimate_marker, options.compliance
    )
    if options.compliance:
        require_gravity_load(model, chain)
    torques = gravity_torques(model, chain, data.q) if options.compliance else None
    whitening = pose_whitening(chain, start, data, options.noise, _checked_joint_noise(options.joint_noise))
    residual = SerialResidual(chain, data, whitening, layout, torques)
    problem = SerialProblem(residual, np.arange(layout.size), prior_columns(names, options.priors))
    return _result(model, problem, run_pipeline(problem, start, options))


def _result(model: pin.Model, problem: SerialProblem, outcome: PipelineFit[SerialState]) -> SerialCalibration:
    """The calibration a pipeline ended on: the calibrated model, the deltas and the compliance."""
    residual, state, start = problem.model, outcome.lm.state, outcome.start
    chain, layout = residual.chain, residual.layout
    # dt_j = log6(T_j(0)^-1 T_j,c(0)) per placement (for j = 1 with a base frame, the inverse base
    # placement cancels); the calibrated model is the nominal one perturbed by exactly these.
    deltas = {
        p: _readonly(pin.log6(pin.SE3(start.transforms[j]).actInv(pin.SE3(state.transforms[j]))).vector)
        for j, p in enumerate(chain.placements())
    }
    values = np.zeros(layout.size) if state.accumulated is None else state.accumulated.copy()
    values[: layout.n_chain] = np.concatenate(list(deltas.values()))
    fitted = outcome.columns
    compliance = {}
    if layout.compliance and state.compliance is not None:
        compliance = {
            joint: float(state.compliance[k])
            for k, joint in enumerate(chain.joint_names)
            if layout.compliance_slice.start + k in fitted
        }
    return SerialCalibration(
        model=perturb(model, deltas),
        chain=chain,
        deltas=MappingProxyType(deltas),
        parameter_std=outcome.std,
        position_only=residual.data.rotations is None,
        setup=_fitted_setup(state),
        fitted=tuple(problem.names[c] for c in fitted),
        fitted_indices=fitted,
        names=problem.names,
        values=_readonly(values),
        compliance=MappingProxyType(compliance),
        problem=problem,
        **summary_fields(outcome),
    )


def _fitted_setup(state: SerialState) -> MeasurementSetup:
    """The measurement setup of a state: F and K, or F and the points' offsets."""
    if state.points is None:
        return MeasurementSetup(pin.SE3(state.frame), pin.SE3(state.marker))
    points = tuple((float(x), float(y), float(z)) for x, y, z in state.points)
    return MeasurementSetup(pin.SE3(state.frame), pin.SE3.Identity(), points)
