"""Closed-loop calibration from slider readings and measured poses (beyond the paper).

The error model (`m3t1r.error_model`) gives the platform pose's sensitivity to every placement
parameter. A measurement is predicted as frame . T_platform(q) . marker (`m3t1r.measurement_setup`):
the measurement frame and the marker may be estimated with the machine, and the calibrated URDF
keeps the machine alone.

The residual of one pose is e = [p_model - p_meas; log3(R_meas^T R_model)]: position in the
measurement frame [m], orientation in the measured (marker) frame [rad]; position-only data keeps
the first three. It is whitened by the tracker noise and minimised by Levenberg-Marquardt (updates
T(0) <- T(0) exp6(dX), eq. 33) over the base (identifiable) parameters, chosen once at the start
by column-pivoted QR with the setup's parameters kept first (the gauge: the base-side placements
the measurement frame makes redundant stay nominal); then outliers and model selection. Those
steps are the pipeline both fits share (`m3t1r.calibration.pipeline`); this module is the problem
(`ClosedLoopProblem`): the assembled poses, the residual and its Jacobian, the registration of the
setup and the judgement of poses that identify fewer parameters than the machine has.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import pinocchio as pin

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.error_model import ClosedLoopErrorModel, PlatformSensitivities
from m3t1r.calibration.identification import (
    BaseParameters,
    parameter_columns,
    select_base_parameters,
    triangular_factor,
    unexcited_parameters,
)
from m3t1r.calibration.measurement_setup import MeasurementSetup, register_frame, register_marker_rotation
from m3t1r.calibration.measurements import PoseMeasurements, assembled_from_home, measure
from m3t1r.calibration.pipeline import (
    CalibrationOptions,
    FitSummary,
    PipelineFit,
    fit,
    prior_columns,
    run_pipeline,
    summary_fields,
)
from m3t1r.calibration.pose_selection import reference_base
from m3t1r.calibration.repeats import CrossValidation, fold_errors, inlier_folds
from m3t1r.errors import IdentificationError, InvalidInputError
from m3t1r.metrics import PoseErrors, pose_errors_between
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver, rehomed
from m3t1r.model.poe import adjoint_matrices, jlog3_batch, log3_batch, placement_of, skew

__all__ = [
    "ClosedLoopCalibration",
    "ClosedLoopProblem",
    "ClosedLoopState",
    "calibrate_closed_loop",
    "pose_errors",
    "predicted_pose_std",
    "predicted_measurement_std",
    "setup_parameter_names",
    "CrossValidation",
    "cross_validate",
    "structural_rank",
]


def setup_parameter_names(
    estimate_frame: bool, estimate_marker: bool, position_only: bool, points: int = 0
) -> tuple[str, ...]:
    """Names of the measurement setup's parameters, right-multiplied [v; w] errors like the machine's:
    measurement_frame.dt[0..5], then marker.dt[0..5] (marker.dt[0..2] for position-only data), or with
    P points marker.p1.dt[0..2] ... marker.pP.dt[0..2] (each point's offset in the platform frame)."""
    names = tuple(f"measurement_frame.dt[{k}]" for k in range(6)) if estimate_frame else ()
    if points:
        names += tuple(f"marker.p{k + 1}.dt[{j}]" for k in range(points) for j in range(3))
    elif estimate_marker:
        names += tuple(f"marker.dt[{k}]" for k in range(3 if position_only else 6))
    return names


def _residual_rows_batch(
    poses: np.ndarray, measured_positions: np.ndarray, measured_rotations: np.ndarray | None, with_jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Residuals e = [p_model - p_meas; log3(R_meas^T R_model)] (N, k) of N model poses (N, 4, 4)
    and de/dxi (N, k, 6) for spatial twists xi of the measured frame: [I, -[p]x] and
    [0, Jlog3 R_model^T]. k = 6, or 3 when measured_rotations is None (position only)."""
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
    if rows is not None:
        rows[:, 3:, 3:] = jlog3_batch(logs, angles) @ np.swapaxes(rotation, 1, 2)
    return np.concatenate((position_error, logs), axis=1), rows


_BLOCK = 512  # poses per block of the error model's stacks (about 100 kB per pose and 216 columns)


@dataclass(eq=False)
class ClosedLoopState:
    """An LM iterate: a model and measurement setup, the assembled configuration (N, nq) and
    platform pose (N, 4, 4, base frame) of every measured pose, the parameter steps accumulated
    since the start (for priors), and, once evaluated, its whitened residual and Jacobian; `factor`,
    once `jacobian_factor` ran on it, the row weights it ran with and the triangular factor of [J r]
    over every column; `restarted`, on a state made by `restart`, the factor of the state it restarts
    (when it had one), from which its first evaluation comes."""

    model: pin.Model | None
    configurations: np.ndarray
    poses: np.ndarray
    setup: MeasurementSetup = field(default_factory=MeasurementSetup)
    accumulated: np.ndarray | None = None
    whitened: tuple[np.ndarray, np.ndarray] | None = None
    factor: tuple[np.ndarray, np.ndarray] | None = None
    restarted: tuple[np.ndarray, np.ndarray] | None = None


class ClosedLoopProblem:
    """Whitened measurement residuals over a set of parameter columns (the pipeline's
    `CalibrationProblem`). Columns index the machine's parameters, then the setup's
    (`setup_parameter_names`, as `options` estimates them); priors {column: sigma} add one row
    x_c / sigma_c per fitted column c with a prior. From `options`: the noise that whitens, what of
    the setup is estimated, the rank tolerance and the given marker of the judgement (`check_base`)."""

    def __init__(
        self,
        error_model: ClosedLoopErrorModel,
        measurements: PoseMeasurements,
        columns: np.ndarray,
        options: CalibrationOptions = CalibrationOptions(),
        priors: Mapping[int, float] | None = None,
    ) -> None:
        noise, estimate_frame, estimate_marker = options.noise, options.estimate_frame, options.estimate_marker
        self.error_model = error_model
        self.stream = options.stream_jacobian  # LM on the compressed rows (`streamed`), or on every row
        self.rank_tolerance = options.rank_tolerance
        self.reference_marker = options.start_setup.marker  # the reference set is measured through it
        self.measurements = measurements
        self.columns = columns
        self.n_machine = error_model.n_parameters
        self.n_points = measurements.n_points
        estimate_marker = estimate_marker or self.n_points > 0  # the points' offsets are always estimated
        self.names = error_model.names + setup_parameter_names(
            estimate_frame, estimate_marker, measurements.position_only, self.n_points
        )
        self.frame_slot = self.n_machine if estimate_frame else None
        self.marker_slot = self.n_machine + (6 if estimate_frame else 0) if estimate_marker else None
        self.priors = dict(priors or {})
        rows = measurements.rows_per_pose
        # 1/sigma of one pose's rows (every point seen): [position; orientation], or positions alone
        self.row_weights = np.r_[np.full(3, 1 / noise.position), np.full(3, 1 / noise.rotation)][:rows]
        if self.n_points:
            self.row_weights = np.full(rows, 1 / noise.position)
        self.seen = (
            np.ones((len(measurements), rows), dtype=bool)
            if measurements.points is None
            else np.repeat(np.isfinite(measurements.points[:, :, 0]), 3, axis=1)
        )
        self.noise_weights = np.tile(self.row_weights, len(measurements)) * self.seen.reshape(-1)
        self.active = np.ones(len(measurements), dtype=bool)
        self.on_evaluate: Callable[[], None] | None = None  # progress: called once per Jacobian evaluation
        measured = np.array([pose.homogeneous for pose in measurements.poses]).reshape(-1, 4, 4)
        self.measured_positions = measured[:, :3, 3]
        self.measured_rotations = None if measurements.position_only else measured[:, :3, :3]
        self._measured_points = (
            None
            if measurements.points is None
            else np.nan_to_num(measurements.points, nan=0.0).reshape(len(measurements), -1)
        )
        self.point_offsets = np.zeros((self.n_points, 3))  # the registered start's, for the reference rank

    @property
    def rows_per_pose(self) -> int:
        return self.measurements.rows_per_pose

    @property
    def setup_columns(self) -> np.ndarray:
        """The measurement setup's columns, after the machine's: the gauge."""
        return np.arange(self.n_machine, len(self.names))

    default_cost_tolerance = 1e-10
    default_step_significance = 0.01

    def default_iterations(self, n_parameters: int) -> int:
        return default_iterations(n_parameters)

    def reselection_bound(self) -> int:
        return 0  # a shortfall is refused (`check_base`), never left for a re-selection

    def restart(self, state: ClosedLoopState) -> ClosedLoopState:
        """`state` without its evaluation, for a fit over other columns or poses; its first evaluation
        comes from `state`'s factor (`jacobian_factor`, at the start: the base choice's) where the
        weights are the same (`streamed`)."""
        return replace(state, whitened=None, factor=None, restarted=state.factor or state.restarted)

    def accumulated(self, state: ClosedLoopState) -> np.ndarray:
        assert state.accumulated is not None, "iterates come from `assemble`"
        return state.accumulated

    def pose_blocks(self, state: ClosedLoopState) -> np.ndarray:
        return self.pose_residuals(state) * self.noise_weights.reshape(len(self.measurements), -1)

    def raw_blocks(self, state: ClosedLoopState) -> np.ndarray:
        return self.pose_residuals(state)

    def jacobian_factor(self, state: ClosedLoopState, with_residual: bool = False) -> np.ndarray:
        """The triangular factor of the whitened pose rows over every column (`evaluate`, reduce=True),
        of [J r] with_residual (flagged poses' rows are zero): a copy of the factor of [J r] that
        `state.factor` keeps for these weights (evaluated once), without its last column unless
        with_residual (R^T R = J^T J either way)."""
        weights = self.weights
        if state.factor is None or not np.array_equal(state.factor[0], weights):
            columns = np.arange(len(self.names))
            state.factor = (weights, self.evaluate(state, columns, reduce=True, with_residual=True)[1])
        augmented = state.factor[1]
        return augmented.copy() if with_residual else augmented[:, :-1].copy()

    def check_base(self, base: BaseParameters, factor: np.ndarray, fixed: Sequence[int]) -> None:
        """IdentificationError when the data identify fewer parameters than the reference pose set
        does (`_reference_base`), saying why and what would help (`_shortfall`)."""
        reference = _reference_base(self, self.reference_marker, fixed, self.rank_tolerance)
        if base.rank >= reference.rank:
            return
        missing = unexcited_parameters(factor, self.names, reference.indices, reference.rank - base.rank)
        hold = _holding_that_identifies(self, self.reference_marker, factor, fixed, self.rank_tolerance, missing)
        counts = (len(self.measurements), len(self.measurements) * self.rows_per_pose)
        raise IdentificationError(_shortfall(base, reference, missing, hold, counts, self.rank_tolerance))

    @property
    def weights(self) -> np.ndarray:
        """Per-row 1/sigma of the pose rows; zero on the rows of flagged outliers."""
        return self.noise_weights * np.repeat(self.active, self.measurements.rows_per_pose)

    def assemble(
        self,
        model: pin.Model,
        start: np.ndarray | None,
        setup: MeasurementSetup = MeasurementSetup(),
        accumulated: np.ndarray | None = None,
    ) -> ClosedLoopState:
        """Assemble every measured pose on `model` in one vectorised solve (`forward_batch`): each
        from its row of `start` (N, nq) and on that row's branch, or from home (None) on home's.
        The first pose that fails is named in an IdentificationError (InvalidInputError for a slider
        beyond its limit): no iterate is made of a partial assembly."""
        solver = ClosedLoopSolver(self.error_model.mechanism.with_model(model))
        solved = solver.forward_batch(self.measurements.actuators, q_init=start)
        if solved.failures:
            first = solved.failures[0]
            error = InvalidInputError if first.error is InvalidInputError else IdentificationError
            raise error(f"measured pose {first.index} (0-based) does not assemble: {first.reason}")
        accumulated = np.zeros(len(self.names)) if accumulated is None else accumulated
        return ClosedLoopState(model, solved.q, solved.poses, setup, accumulated)

    def measured_frames(self, state: ClosedLoopState) -> np.ndarray:
        """The model's prediction of every measured frame (N, 4, 4), in the measurement frame."""
        return state.setup.measured_poses(state.poses)

    def pose_residuals(self, state: ClosedLoopState) -> np.ndarray:
        """Unwhitened residual blocks (N, k) of every pose, outliers included (zeros where a point was not seen)."""
        if self._measured_points is not None:
            predicted = state.setup.measured_points(state.poses).reshape(len(state.poses), -1)
            return np.where(self.seen, predicted - self._measured_points, 0.0)
        residual, _ = _residual_rows_batch(
            self.measured_frames(state), self.measured_positions, self.measured_rotations, with_jacobian=False
        )
        return residual

    def prior_rows(self, state: ClosedLoopState) -> tuple[np.ndarray, np.ndarray]:
        """The prior rows x_c / sigma_c of the fitted columns with a prior, in the columns' order, and their
        Jacobian (rows, fitted columns) [1/sigma]."""
        picked = [(i, self.priors[c]) for i, c in enumerate(self.columns) if c in self.priors]
        jacobian = np.zeros((len(picked), len(self.columns)))
        values = np.zeros(len(picked))
        for row, (i, sigma) in enumerate(picked):
            assert state.accumulated is not None, "an iterate with priors carries its accumulated steps"
            jacobian[row, i] = 1.0 / sigma
            values[row] = state.accumulated[self.columns[i]] / sigma
        return values, jacobian

    def residual(self, state: ClosedLoopState) -> np.ndarray:
        """Whitened residual from the assembled poses alone (LM trial steps)."""
        if state.model is None:  # a trial that did not assemble: every row infinite, prior rows too
            return np.full(len(self.weights) + sum(1 for c in self.columns if c in self.priors), np.inf)
        return np.concatenate((self.pose_residuals(state).reshape(-1) * self.weights, self.prior_rows(state)[0]))

    def evaluate(
        self,
        state: ClosedLoopState,
        columns: np.ndarray,
        reduce: bool = False,
        extra_rows: int = 0,
        with_residual: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Whitened pose residual (6N or 3N rows, times `weights`) and its whitened Jacobian over
        `columns`, each followed by `extra_rows` rows left for the caller to fill (priors).

        Poses are processed in blocks of `_BLOCK`, so the per-pose stacks of the error model exist
        for one block at a time: memory grows with the pose count only by the Jacobian returned.
        reduce=True returns instead of the Jacobian its triangular factor R (R^T R = J^T J, same
        column norms, at most `len(columns)` rows; no extra rows): enough to choose base
        parameters, in memory independent of the pose count. With with_residual too, the factor of
        [J r] (`triangular_factor`: its last column holds Q^T r, what a linear fit can explain).
        """
        n, k = len(state.configurations), self.measurements.rows_per_pose
        residual = np.empty(n * k + extra_rows)
        jacobian = (
            np.zeros((0, len(columns) + with_residual)) if reduce else np.empty((n * k + extra_rows, len(columns)))
        )
        for block, block_residual, block_jacobian in self.whitened_blocks(state, columns):
            rows = slice(k * block.start, k * block.stop)
            residual[rows] = block_residual
            if reduce:
                jacobian = triangular_factor(block_jacobian, residual[rows] if with_residual else None, jacobian)
            else:
                jacobian[rows] = block_jacobian
        return residual, jacobian

    def whitened_blocks(
        self, state: ClosedLoopState, columns: np.ndarray
    ) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        """The poses in blocks of `_BLOCK`: (the block's poses, their whitened residual rows, their
        whitened Jacobian rows over `columns`), flagged poses' rows zero. One Jacobian evaluation
        (`on_evaluate` is called once); the error model's stacks exist for one block at a time."""
        if self.on_evaluate is not None:
            self.on_evaluate()
        solver = ClosedLoopSolver(self.error_model.mechanism.with_model(state.model))
        machine = columns[columns < self.n_machine]
        n, k = len(state.configurations), self.measurements.rows_per_pose
        weights = self.weights
        for start in range(0, n, _BLOCK):
            block = slice(start, min(start + _BLOCK, n))
            sensitivities = self.error_model.platform_sensitivities(solver, state.configurations[block], machine)
            rows = slice(k * block.start, k * block.stop)
            block_residual, block_jacobian = self._block_rows(state, block, columns, sensitivities)
            block_jacobian *= weights[rows, None]
            yield block, block_residual * weights[rows], block_jacobian

    def streamed(self, state: ClosedLoopState) -> tuple[np.ndarray, np.ndarray]:
        """The fit's least-squares problem compressed: z = [Q^T r; rho] and [R; 0] from the QR of the
        whitened pose rows [J r] accumulated block by block (`triangular_factor`), then the prior
        rows. |z|^2 = |r|^2, R^T z = J^T r and R^T R = J^T J, so Levenberg-Marquardt takes the same
        steps on them as on (r, J), in memory bounded by the parameters, not the poses. Where
        `state.restarted` holds the factor of [J r] over every column for these weights (a restart of a
        state whose factor was taken: the base choice's, at the start), the same R and z (up to the
        rotation Q) come from a QR of its columns, without evaluating the poses."""
        p = len(self.columns)
        if state.restarted is not None and np.array_equal(state.restarted[0], self.weights):
            factor = triangular_factor(state.restarted[1][:, np.r_[self.columns, len(self.names)]])
        else:
            factor = np.zeros((0, p + 1))
            for _, block_residual, block_jacobian in self.whitened_blocks(state, self.columns):
                factor = triangular_factor(block_jacobian, block_residual, previous=factor)
        prior_values, prior_jacobian = self.prior_rows(state)
        return np.concatenate((factor[:, p], prior_values)), np.vstack((factor[:, :p], prior_jacobian))

    def pose_rows(self, state: ClosedLoopState) -> tuple[np.ndarray, np.ndarray]:
        """The inlier poses' whitened residual rows and Jacobian rows over `columns` (a new
        column-major array the caller may overwrite: the selection projects it in place)."""
        k = self.rows_per_pose
        keep = np.repeat(self.active, k)
        residual = np.empty(np.count_nonzero(keep))
        jacobian = np.empty((len(residual), len(self.columns)), order="F")
        at = 0
        for block, block_residual, block_jacobian in self.whitened_blocks(state, self.columns):
            kept = keep[k * block.start : k * block.stop]
            size = np.count_nonzero(kept)
            residual[at : at + size], jacobian[at : at + size] = block_residual[kept], block_jacobian[kept]
            at += size
        return residual, jacobian

    def _block_rows(
        self, state: ClosedLoopState, block: slice, columns: np.ndarray, sensitivities: PlatformSensitivities
    ) -> tuple[np.ndarray, np.ndarray]:
        """Residual rows and Jacobian rows of the poses in `block` (measurement-frame twists)."""
        if self._measured_points is not None:
            return self._point_rows(state, block, columns, sensitivities)
        measured, twists = self.measured_frame_twists(state.setup, columns, sensitivities)
        residual, rows = _residual_rows_batch(
            measured,
            self.measured_positions[block],
            None if self.measured_rotations is None else self.measured_rotations[block],
        )
        return residual.reshape(-1), (rows @ twists).reshape(residual.size, -1)

    def _point_rows(
        self, state: ClosedLoopState, block: slice, columns: np.ndarray, sensitivities: PlatformSensitivities
    ) -> tuple[np.ndarray, np.ndarray]:
        """`_block_rows` of P points: point k at F T_platform p_k moves by v + w x p_k under the
        platform's twist (v, w) in the measurement frame, and by R_(F T_platform) along its own offset."""
        assert self._measured_points is not None and self.marker_slot is not None, "a problem of points"
        setup = replace(state.setup, marker=pin.SE3.Identity())
        platform, twists = self.measured_frame_twists(setup, columns, sensitivities)
        n, n_points = len(platform), self.n_points
        points = setup.measured_points(sensitivities.poses)  # (n, P, 3)
        rows = twists[:, None, :3] - skew(points.reshape(-1, 3)).reshape(n, n_points, 3, 3) @ twists[:, None, 3:]
        for i in np.flatnonzero(columns >= self.marker_slot):
            point, axis = divmod(int(columns[i] - self.marker_slot), 3)
            rows[:, point, :, i] = platform[:, :3, axis]
        seen = self.seen[block]
        residual = np.where(seen, points.reshape(n, -1) - self._measured_points[block], 0.0)
        return residual.reshape(-1), rows.reshape(n * 3 * n_points, -1)

    def measured_frame_twists(
        self, setup: MeasurementSetup, columns: np.ndarray, sensitivities: PlatformSensitivities
    ) -> tuple[np.ndarray, np.ndarray]:
        """The measured frames (N, 4, 4) in the measurement frame, and their spatial twists there per
        unit of each column (N, 6, len(columns)), machine columns first (`sensitivities` holds
        theirs, in base-frame twists), then the setup's in `columns` order: a frame error moves
        every measured frame by one constant twist, a marker error by its own adjoint."""
        measured = setup.measured_poses(sensitivities.poses)
        frame_adjoint = adjoint_matrices(setup.frame.homogeneous[None])[0]
        blocks = [frame_adjoint @ sensitivities.twist_jacobians]  # base-frame twists seen in the measurement frame
        for c in columns[columns >= self.n_machine]:
            if self.frame_slot is not None and self.frame_slot <= c < self.frame_slot + 6:
                blocks.append(np.broadcast_to(frame_adjoint[:, c - self.frame_slot, None], (len(measured), 6, 1)))
            elif self.n_points:  # a point's offset does not move the platform frame (`_point_rows` moves the point)
                blocks.append(np.zeros((len(measured), 6, 1)))
            else:
                blocks.append(adjoint_matrices(measured)[:, :, c - self.marker_slot, None])
        return measured, np.concatenate(blocks, axis=2)

    def residual_and_jacobian(self, state: ClosedLoopState) -> tuple[np.ndarray, np.ndarray]:
        """The whitened residual and Jacobian over `columns`: every row (pose rows, then priors), or
        with `stream` their compressed form (`streamed`), which has the same cost, gradient and
        normal equations in p + 1 rows (and the priors')."""
        if state.model is None:  # a trial step that did not assemble: reject it
            priors = sum(1 for c in self.columns if c in self.priors)
            n = len(self.columns) + 1 + priors if self.stream else len(self.residual(state))
            return np.full(n, np.inf), np.zeros((n, len(self.columns)))
        if state.whitened is None and self.stream:
            state.whitened = self.streamed(state)
        if state.whitened is None:
            prior_values, prior_jacobian = self.prior_rows(state)
            residual, jacobian = self.evaluate(state, self.columns, extra_rows=len(prior_values))
            pose_rows = len(self.weights)
            residual[pose_rows:], jacobian[pose_rows:] = prior_values, prior_jacobian
            state.whitened = (residual, jacobian)
        return state.whitened

    def release(self, state: ClosedLoopState) -> None:
        """LM hook: a superseded iterate drops its Jacobian; it keeps its model, setup and assembly."""
        state.whitened = None

    def retract(self, state: ClosedLoopState, step: np.ndarray) -> ClosedLoopState:
        assert state.accumulated is not None, "LM iterates come from `assemble`"
        vector = np.zeros(len(self.names))
        vector[self.columns] = step
        model = self.error_model.perturbed(state.model, vector[: self.n_machine])
        setup = state.setup
        if self.frame_slot is not None:
            setup = replace(setup, frame=setup.frame * pin.exp6(vector[self.frame_slot : self.frame_slot + 6]))
        if self.marker_slot is not None and self.n_points:
            moved = np.array(setup.points).reshape(-1, 3) + vector[self.marker_slot :].reshape(-1, 3)
            setup = replace(setup, points=tuple((float(x), float(y), float(z)) for x, y, z in moved))
        elif self.marker_slot is not None:
            dm = np.zeros(6)
            size = len(self.names) - self.marker_slot
            dm[:size] = vector[self.marker_slot :]
            setup = replace(setup, marker=setup.marker * pin.exp6(dm))
        try:  # from the iterate's assembly, which the batch's chord Newton corrects in a few steps
            return self.assemble(model, state.configurations, setup, state.accumulated + vector)
        except IdentificationError:  # a pose does not assemble on the trial model: LM rejects the step
            return ClosedLoopState(None, state.configurations, np.zeros((0, 4, 4)), setup, state.accumulated + vector)


@dataclass(frozen=True, kw_only=True)
class ClosedLoopCalibration(FitSummary[ClosedLoopState]):
    """Result of `calibrate_closed_loop`: the fit's `FitSummary` (base, covariance, variance factor,
    RMS before and after, outliers, LM's run and settings, the registered start; RMS orientation nan
    when position-only), and

    mechanism: the calibrated machine (nominal closures on the identified tree model, home
    re-assembled); setup: the measurement frame and marker (estimated or as given);
    parameters: identified machine error per parameter name, relative to the starting model (zero
    for the ones not fitted); std: standard deviations of every fitted parameter (machine and
    setup) from sigma^2 (J^T W J)^-1; fitted: the columns finally fitted (base, or fewer after
    model selection), whose covariance is `covariance`; problem: the fit's problem (`cross_validate`).
    """

    mechanism: Mechanism
    error_model: ClosedLoopErrorModel
    setup: MeasurementSetup
    parameters: dict[str, float]
    std: dict[str, float]
    fitted: tuple[str, ...]
    problem: ClosedLoopProblem | None = field(default=None, repr=False)


@on_one_blas_thread
def calibrate_closed_loop(
    mechanism: Mechanism,
    measurements: PoseMeasurements,
    options: CalibrationOptions = CalibrationOptions(),
    *,
    error_model: ClosedLoopErrorModel | None = None,
    progress: Callable[[], None] | None = None,
) -> ClosedLoopCalibration:
    """Identify the placement errors of every joint and closure/platform frame (module docstring),
    and the measurement setup where asked (`CalibrationOptions`: noise, setup, outliers, selection,
    fixed parameters and priors, LM's tolerances; a closed loop takes no joint noise or compliance).

    With several points per pose (`PoseMeasurements.points`) every point's offset in the platform
    frame is estimated, and only the points seen count (residual rows, degrees of freedom, outlier
    gate). error_model: the placements to identify (default: every one); progress: called once per
    Jacobian evaluation (here and in `cross_validate` of the result).

    LM stops when an accepted step lowers the whitened cost 1/2 chi^2 by less than
    step_significance * s^2, s^2 = chi^2 / (m - p) being the a-posteriori noise variance (m rows,
    p base parameters): such a step moves the estimate by at most sqrt(2 step_significance) of its
    own standard deviation (0.14 for 0.01), which the data cannot tell from noise. Being relative to
    the fit's own residual, the rule keeps noise-free data converging to rounding level. Also when
    the cost drops by less than cost_tolerance relatively or absolute_cost_tolerance absolutely.
    Raises IdentificationError when the poses identify fewer parameters than the model can (saying
    what would help), when a measured pose cannot be assembled on the starting model, or when LM
    ends on a model that does not assemble. A fit that did not converge is returned with converged
    False: `m3t1r.assessment` judges it.
    """
    if options.compliance or options.joint_noise:
        raise InvalidInputError(
            "a closed-loop fit takes no joint noise or compliance (its readings are the sliders): "
            "they are options of a serial robot's calibration"
        )
    error_model = error_model or ClosedLoopErrorModel(mechanism)
    setup = options.start_setup
    problem = ClosedLoopProblem(error_model, measurements, np.zeros(0, dtype=int), options)
    problem.columns = np.arange(len(problem.names))
    problem.on_evaluate = progress
    problem.priors = prior_columns(problem.names, options.priors)
    try:
        start = problem.assemble(mechanism.model, None, setup=setup)
    except IdentificationError as exc:
        raise IdentificationError(f"on the starting model, {exc}") from None
    start.setup = (
        _registered_points(problem, start, setup, options.estimate_frame)
        if problem.n_points
        else _registered_setup(problem, start, setup, options.estimate_frame, options.estimate_marker)
    )
    outcome = run_pipeline(problem, start, options)
    return _calibration(mechanism, problem, outcome)


def _registered_setup(
    problem: ClosedLoopProblem,
    start: ClosedLoopState,
    setup: MeasurementSetup,
    estimate_frame: bool,
    estimate_marker: bool,
) -> MeasurementSetup:
    """The setup LM starts from: the frame by rigid registration of the nominal predictions
    (positions), then, with orientation data, the marker's orientation in closed form."""
    platform = start.poses
    if estimate_frame:
        setup = replace(
            setup,
            frame=register_frame(
                MeasurementSetup(marker=setup.marker).measured_poses(platform), problem.measured_positions
            ),
        )
    if estimate_marker and problem.measured_rotations is not None:
        rotation = register_marker_rotation(setup.frame, platform, problem.measured_rotations)
        setup = replace(setup, marker=pin.SE3(rotation, setup.marker.translation))
    return setup


_POINT_REGISTRATION_ROUNDS = 5  # alternations of frame and offsets: the start LM refines


def _registered_points(
    problem: ClosedLoopProblem, start: ClosedLoopState, setup: MeasurementSetup, estimate_frame: bool
) -> MeasurementSetup:
    """The setup LM starts from with P points: alternately the frame by rigid registration of every
    point seen (with the current offsets, zero at first) and each point's offset as the mean of its
    sightings mapped into the platform frame, (F T_platform)^-1 p_measured."""
    assert problem.measurements.points is not None, "a problem of points"
    measured = problem.measurements.points
    rows, points = np.nonzero(np.isfinite(measured[:, :, 0]))
    platform = start.poses[rows]
    offsets = np.zeros((problem.n_points, 3))
    frame = setup.frame
    for _ in range(_POINT_REGISTRATION_ROUNDS if estimate_frame else 1):
        if estimate_frame:
            model_points = platform.copy()
            model_points[:, :3, 3] += np.einsum("nij,nj->ni", platform[:, :3, :3], offsets[points])
            frame = register_frame(model_points, measured[rows, points])
        seen = frame.homogeneous @ platform
        local = np.einsum("nji,nj->ni", seen[:, :3, :3], measured[rows, points] - seen[:, :3, 3])
        offsets = np.array([local[points == k].mean(axis=0) for k in range(problem.n_points)])
    problem.point_offsets = offsets
    return replace(
        setup,
        frame=frame,
        marker=pin.SE3.Identity(),
        points=tuple((float(x), float(y), float(z)) for x, y, z in offsets),
    )


def _calibration(
    mechanism: Mechanism, problem: ClosedLoopProblem, outcome: PipelineFit[ClosedLoopState]
) -> ClosedLoopCalibration:
    """The calibration a pipeline ended on: the identified machine and its parameters by name."""
    state = outcome.lm.state
    assert state.model is not None, "the pipeline ends on a model that assembles"
    std = np.zeros(len(problem.names))
    std[list(outcome.columns)] = outcome.std
    error_model = problem.error_model
    identified = _accumulated_parameters(error_model, mechanism.model, state.model)
    return ClosedLoopCalibration(
        mechanism=rehomed(mechanism.with_model(state.model)),
        error_model=error_model,
        setup=state.setup,
        parameters=dict(zip(error_model.names, identified)),
        std=dict(zip(problem.names, std)),
        fitted=tuple(problem.names[c] for c in outcome.columns),
        problem=problem,
        **summary_fields(outcome),
    )


@on_one_blas_thread
def cross_validate(
    calibration: ClosedLoopCalibration,
    folds: int = 5,
    seed: int = 0,
    refit: bool = False,
    groups: np.ndarray | None = None,
) -> CrossValidation:
    """k-fold cross-validation of a calibration on its own inlier poses (`CrossValidation`).

    By default each fold's refit is the Gauss-Newton step from the estimate without the fold's
    rows, dx_F = -(A - J_F^T J_F)^+ (J^T r - J_F^T r_F) with A = J^T J (whitened), and its
    prediction of the fold r_F + J_F dx_F: one small solve per fold. refit=True runs the full
    nonlinear fit per fold instead (the same parameters, from the same start; as slow as k
    calibrations), which the tests compare with. groups: (N,) a label per pose the calibration was
    given (`repeats.pose_groups`); poses sharing one are held out together. None: each on its own.
    """
    problem, start = calibration.problem, calibration.start
    if problem is None or start is None:
        raise InvalidInputError("cross_validate needs a calibration made by calibrate_closed_loop")
    inliers, assignment, n_groups = inlier_folds(problem.active, folds, seed, groups)
    k = problem.measurements.rows_per_pose
    residuals = np.empty((len(inliers), k))
    if refit:
        fold_problem = copy.copy(problem)
        for fold in range(folds):
            held = inliers[assignment == fold]
            fold_problem.active = problem.active.copy()
            fold_problem.active[held] = False
            assert calibration.settings is not None, "a calibration made by calibrate_closed_loop has its settings"
            result = fit(fold_problem, fold_problem.restart(start), calibration.settings)
            residuals[assignment == fold] = fold_problem.pose_residuals(result.state)[held]
    else:
        fold_of = np.full(len(problem.active), -1)
        fold_of[inliers] = assignment
        residuals[:] = _fold_predictions(problem, calibration.lm.state, fold_of, folds)[inliers]
    seen_points = problem.seen[inliers][:, ::3] if problem.n_points else None  # one error per point seen
    return CrossValidation(fold_errors(residuals, seen_points), folds, n_groups)


def _fold_predictions(
    problem: ClosedLoopProblem, state: ClosedLoopState, fold_of: np.ndarray, folds: int
) -> np.ndarray:
    """Unwhitened residual blocks (N, k) each fold's Gauss-Newton refit predicts for its poses
    (`cross_validate`; zero rows for the poses of no fold, fold -1), in two passes over the pose
    blocks: the folds' normal equations J_F^T J_F and J_F^T r_F, then the predictions r_F + J_F dx_F
    of their own rows. Memory is bounded by the parameters (and the folds), not the poses."""
    r, J = problem.residual_and_jacobian(state)  # compressed or not: the same normal equations
    information, gradient = J.T @ J, J.T @ r
    k, p = problem.rows_per_pose, len(problem.columns)
    fold_information, fold_gradient = np.zeros((folds, p, p)), np.zeros((folds, p))
    for block, block_residual, block_jacobian in problem.whitened_blocks(state, problem.columns):
        row_folds = np.repeat(fold_of[block], k)
        for fold in np.unique(row_folds[row_folds >= 0]):
            rows = row_folds == fold
            fold_information[fold] += block_jacobian[rows].T @ block_jacobian[rows]
            fold_gradient[fold] += block_jacobian[rows].T @ block_residual[rows]
    steps = np.array(
        [
            -np.linalg.lstsq(information - fold_information[f], gradient - fold_gradient[f], rcond=None)[0]
            for f in range(folds)
        ]
    )
    predicted = np.zeros((len(fold_of), k))
    weights = problem.weights.reshape(-1, k)
    for block, block_residual, block_jacobian in problem.whitened_blocks(state, problem.columns):
        poses = np.arange(block.start, block.stop)[fold_of[block] >= 0]
        local = poses - block.start
        rows = block_residual.reshape(-1, k)[local] + np.einsum(
            "nkp,np->nk", block_jacobian.reshape(-1, k, p)[local], steps[fold_of[poses]]
        )
        predicted[poses] = np.divide(rows, weights[poses], out=np.zeros_like(rows), where=weights[poses] != 0)
    return predicted


def default_iterations(n_parameters: int) -> int:
    """LM's iteration cap: 60 (ample on the M machine, which converges in under 20), or 5 per base
    parameter on bigger models, whose weak directions (condition numbers to 1e9 on orientation
    mechanisms) take LM more steps; a fit that still stops there is refused, never returned as converged."""
    return max(60, 5 * n_parameters)


def structural_rank(
    problem: ClosedLoopProblem, marker: pin.SE3, fixed_columns: Sequence[int], rank_tolerance: float
) -> int:
    """Number of identifiable parameters of the model and setup themselves, independent of the
    user's poses (`_reference_base`)."""
    return _reference_base(problem, marker, fixed_columns, rank_tolerance).rank


def _reference_base(
    problem: ClosedLoopProblem, marker: pin.SE3, fixed_columns: Sequence[int], rank_tolerance: float
) -> BaseParameters:
    """The base parameters on a fixed, seeded set of poses spread over the workspace box: what the
    model and setup can identify, whatever the user's poses. Cached (it depends on the starting
    geometry and the setup, not on the data)."""
    error_model = problem.error_model
    model = error_model.mechanism.model
    geometry = np.concatenate(
        [
            np.ravel([p.homogeneous for p in model.jointPlacements]),
            np.ravel([f.placement.homogeneous for f in model.frames]),
            np.ravel(marker.homogeneous),
            np.ravel(problem.point_offsets),
        ]
    ).tobytes()
    position_only = problem.measurements.position_only
    key = (
        geometry,
        error_model.placements,
        position_only,
        problem.names,
        tuple(sorted(fixed_columns)),
        float(problem.row_weights[0] / problem.row_weights[-1]),
        rank_tolerance,
        repr(error_model.mechanism.workspace),  # the reference poses are drawn in it
    )
    if key not in _STRUCTURAL_RANKS:
        _STRUCTURAL_RANKS[key] = _reference_selection(problem, marker, fixed_columns, rank_tolerance)
    return _STRUCTURAL_RANKS[key]


_STRUCTURAL_RANKS: dict[tuple, BaseParameters] = {}


def _reference_selection(
    problem: ClosedLoopProblem, marker: pin.SE3, fixed_columns: Sequence[int], rank_tolerance: float
) -> BaseParameters:
    """`reference_base` on the rows this problem fits: the reference poses measured exactly on the
    starting machine through `marker` (or at the start's point offsets), with the same setup estimated."""
    error_model = problem.error_model
    mechanism = error_model.mechanism
    offsets = tuple((float(x), float(y), float(z)) for x, y, z in problem.point_offsets)
    options = CalibrationOptions(
        estimate_frame=problem.frame_slot is not None, estimate_marker=problem.marker_slot is not None
    )

    def whitened_jacobian(actuators: np.ndarray) -> np.ndarray:
        reference = measure(mechanism, actuators, position_only=problem.measurements.position_only)
        if problem.n_points:  # the points at the fit's start offsets, every one seen
            platform = np.array([pose.homogeneous for pose in reference.poses])
            reference = PoseMeasurements(
                reference.actuators, reference.poses, True, MeasurementSetup(points=offsets).measured_points(platform)
            )
        else:
            reference = PoseMeasurements(
                reference.actuators, tuple(pose * marker for pose in reference.poses), reference.position_only
            )
        everything = np.arange(len(problem.names))
        twin = ClosedLoopProblem(error_model, reference, everything, options)
        twin.noise_weights = np.tile(problem.row_weights, len(reference))
        state = twin.assemble(mechanism.model, None, setup=MeasurementSetup(marker=marker, points=offsets))
        return twin.evaluate(state, everything)[1]

    forced = np.arange(error_model.n_parameters, len(problem.names))
    return reference_base(
        mechanism, whitened_jacobian, problem.names, fixed=fixed_columns, forced=forced, rank_tolerance=rank_tolerance
    )


#: A reference-set direction weaker than this many times the rank tolerance is barely identifiable
#: on any poses: its |R_ii| is within two decades of the threshold that calls it redundant.
_MARGINAL = 100.0


def _holding_that_identifies(
    problem: ClosedLoopProblem,
    marker: pin.SE3,
    factor: np.ndarray,
    fixed_columns: Sequence[int],
    rank_tolerance: float,
    missing: Sequence[str],
) -> tuple[str, ...]:
    """Parameters to hold at nominal (`fixed`) so that the data identify all the model then can:
    `missing` and, while interchangeable columns take their place, the parameters of what is still
    unexcited, checked against the reference set; () when three rounds do not get there."""
    held = list(missing)
    forced = np.arange(problem.error_model.n_parameters, len(problem.names))
    for _ in range(3):
        columns = sorted(set(fixed_columns) | set(parameter_columns(problem.names, held, "fixed parameter")))
        trial = factor.copy()
        trial[:, columns] = 0.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            base = select_base_parameters(trial, problem.names, rank_tolerance, forced=forced)
        reference = _reference_base(problem, marker, columns, rank_tolerance)
        if base.rank >= reference.rank:
            return tuple(held)
        held += [
            n
            for n in unexcited_parameters(trial, problem.names, reference.indices, reference.rank - base.rank)
            if n not in held
        ]
    return ()


def _shortfall(
    base: BaseParameters,
    reference: BaseParameters,
    missing: Sequence[str],
    hold: Sequence[str],
    counts: tuple[int, int],
    rank_tolerance: float,
) -> str:
    """Why the data identify fewer parameters than the model has (counts: poses, residual rows), and
    the advice that can help: more poses only when there are fewer rows than parameters or the
    reference set identifies the missing directions clearly; holding parameters at nominal (`hold`,
    checked to work) when even a well-spread pose set barely identifies them."""
    n_poses, n_rows = counts
    head = (
        f"{n_poses} poses give {n_rows} residual rows for {reference.rank} identifiable parameters and "
        f"identify only {base.rank}"
    )
    if n_rows < reference.rank:
        return f"{head}: add poses (each gives {n_rows // max(n_poses, 1)} rows), spread over the workspace"
    listed = ", ".join(missing[:8]) + (" ..." if len(missing) > 8 else "")
    fix = f"hold them at nominal (--fix {' '.join(hold)})" if hold else "hold the weakest at nominal (--fix)"
    marginal = int(np.count_nonzero(reference.r_diag_ratio[: reference.rank] < _MARGINAL * rank_tolerance))
    if reference.rank - base.rank <= marginal:
        return (
            f"{head}: {listed} are barely identifiable on any poses (on poses spread over the whole "
            f"workspace, within {_MARGINAL:g} times the rank tolerance), so more poses are unlikely to help: "
            f"{fix}"
        )
    return (
        f"{head}: these poses do not excite {listed}; poses that move them, over more of the workspace, would, or {fix}"
    )


def _accumulated_parameters(error_model: ClosedLoopErrorModel, start: pin.Model, end: pin.Model) -> np.ndarray:
    """dt per placement with end = start * exp6(dt): log6(start^-1 end), placement by placement."""
    blocks = [pin.log6(placement_of(start, p).actInv(placement_of(end, p))).vector for p in error_model.placements]
    return np.concatenate(blocks)


@on_one_blas_thread
def pose_errors(machine_a: Mechanism, machine_b: Mechanism, actuators: np.ndarray) -> PoseErrors:
    """Platform pose differences of two machines driven with the same actuators (rows of actuators):
    |p_a - p_b| [m] and |log3(R_a^T R_b)| [rad], each set solved from each machine's home (batch FK,
    so unrelated rows never carry a warm start across a singularity).

    Raises InvalidInputError naming the first set that does not assemble on one of the machines (and
    why): no error is reported for a pose that was not solved.
    """
    actuators = np.asarray(actuators, dtype=float)
    actuators = actuators.reshape(len(actuators), -1 if actuators.size else 0)  # no sets: (0, 0), not a reshape error
    poses = []
    for machine in (machine_a, machine_b):
        batch = ClosedLoopSolver(machine).forward_batch(actuators) if len(actuators) else None
        if batch is not None and batch.failures:
            first = batch.failures[0]
            raise InvalidInputError(
                f"pose_errors: actuator set {first.index} does not assemble on {machine.urdf_path.name}: {first.reason}"
            )
        poses.append(np.zeros((0, 4, 4)) if batch is None else batch.poses)
    return pose_errors_between(*poses)


@on_one_blas_thread
def predicted_measurement_std(calibration: ClosedLoopCalibration, actuators: np.ndarray) -> PoseErrors:
    """Predicted standard deviation of what the tracker would measure at the given sliders: the
    measured frame (frame . T_platform . marker) in the measurement frame, with the covariance of
    every fitted parameter, the measurement setup's included.

    This is the accuracy of a pose commanded in the tracker's frame, the frame the data fix. With
    the frame estimated, the platform's placement in the machine's own base is not observable
    (the base-side placements are the gauge), so `predicted_pose_std` is large there while this
    one is not. Position [m]: root of the trace of the 3x3 position block of J C J^T, J the
    sensitivity of the measured point to the fitted parameters and C their covariance;
    orientation [rad] likewise, in the measured frame's axes. Every slider set is assembled from
    home (`assembled_from_home`: InvalidInputError naming one that does not).
    """
    return _predicted_std(calibration, actuators, calibration.setup, calibration.fitted)


@on_one_blas_thread
def predicted_pose_std(calibration: ClosedLoopCalibration, actuators: np.ndarray) -> PoseErrors:
    """Predicted standard deviation of the calibrated platform pose in the base frame at the given
    sliders, from the machine block of the fitted parameters' covariance sigma^2 (J^T W J)^-1 (the
    setup's uncertainty is not the machine's): `predicted_measurement_std` with no frame and no
    marker. Position [m] and orientation [rad], the latter in the platform's axes."""
    machine = set(calibration.error_model.names)
    return _predicted_std(
        calibration, actuators, MeasurementSetup(), tuple(name for name in calibration.fitted if name in machine)
    )


def _predicted_std(
    calibration: ClosedLoopCalibration, actuators: np.ndarray, setup: MeasurementSetup, names: tuple[str, ...]
) -> PoseErrors:
    """Std of setup.frame . T_platform . setup.marker at the sliders from the covariance of the fitted
    parameters `names` (a subset of `calibration.fitted`), in blocks of `_BLOCK` poses."""
    problem = calibration.problem
    if problem is None:
        raise InvalidInputError("a predicted std needs a calibration made by calibrate_closed_loop")
    mechanism = calibration.mechanism
    error_model = ClosedLoopErrorModel(mechanism, calibration.error_model.placements)
    solver = ClosedLoopSolver(mechanism)
    fitted, index = {name: k for k, name in enumerate(calibration.fitted)}, {n: i for i, n in enumerate(problem.names)}
    picked = sorted(names, key=index.__getitem__)  # machine columns first, as the twists come
    columns = np.array([index[name] for name in picked], dtype=int)
    rows = [fitted[name] for name in picked]
    covariance = calibration.covariance[np.ix_(rows, rows)]
    machine = columns[columns < problem.n_machine]
    configurations = assembled_from_home(mechanism, actuators).q
    position, rotation = np.empty(len(configurations)), np.empty(len(configurations))
    for start in range(0, len(configurations), _BLOCK):
        block = slice(start, start + _BLOCK)
        sensitivities = error_model.platform_sensitivities(solver, configurations[block], machine)
        measured, twists = problem.measured_frame_twists(setup, columns, sensitivities)
        point = twists[:, :3] - skew(measured[:, :3, 3]) @ twists[:, 3:]  # dp = v + w x p
        angular = np.swapaxes(measured[:, :3, :3], 1, 2) @ twists[:, 3:]
        position[block] = np.sqrt(np.einsum("nip,pq,niq->n", point, covariance, point))
        rotation[block] = np.sqrt(np.einsum("nip,pq,niq->n", angular, covariance, angular))
    return PoseErrors(position, rotation)
