"""Pre-processing compensation of commanded platform poses (paper section 7, Fig. 6).

A controller only knows the nominal model. To put the real platform at a commanded pose T_co:

1. inverse kinematics of the CALIBRATED model gives the slider values q^c that reach T_co on the
   machine as identified (`ClosedLoopSolver.inverse`: position and yaw, a square system);
2. forward kinematics of the NOMINAL model at q^c gives T_cp, the pose to send to the
   controller: its own (nominal) IK of T_cp returns q^c, so the machine moves to T_co.

A controller that accepts slider commands takes q^c directly ("actuators" output); one that takes
platform poses gets T_cp ("pose" output).

Only position and yaw are commandable. The roll and pitch a perturbed machine takes at a target
are set by its geometry; they are reported as `tilt` and never "compensated" (a 6D target is
over-determined for a 4-DoF machine, docs/design.md, "Conventions").

Frames and units: platform frame `Mechanism.platform_frame` in the base frame, metres and
radians; yaw is `kinematics.yaw_of` (heading of the platform x axis) everywhere. Target rows are
(x, y, z, theta); pose targets are `pin.SE3` (their yaw is `yaw_of` of their rotation).

Batches follow the target order as a path: every solve warm-starts from the previous solution,
which keeps consecutive targets on the home assembly branch and costs two or three Newton steps.
A failed warm solve is retried once from home (the reference branch), so an unreachable target
in the middle of a path costs two solves and does not derail its neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np
import pinocchio as pin

from m3t1r._lazy import lazy
from m3t1r._threads import on_one_blas_thread
from m3t1r.errors import InvalidInputError, KinematicsError, M3t1rError, OutOfWorkspaceError, real_array
from m3t1r.io.poses import pose_rows
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.design import NOMINAL, WorkspaceBox
from m3t1r.model.kinematics import ClosedLoopSolver, ForwardResult, InverseResult, roll_pitch_of, within_limits
from m3t1r.model.task import TaskSpec

__all__ = [
    "Targets",
    "TargetFailure",
    "CompensatedCommand",
    "Compensation",
    "Compensator",
    "compensate",
    "TrackingErrors",
    "CompensationAccuracy",
    "compensation_accuracy",
    "workspace_targets",
    "workspace_grid",
    "joint_limit_violation",
]

Targets = Union[np.ndarray, Sequence[pin.SE3]]
"""Commanded task-frame poses: an (N, d) array of task coordinates (`TaskSpec.columns`: rows
(x, y, z, theta) [m, m, m, rad] on the M machine, (x, y) on a planar five-bar, (qx, qy, qz, qw) on an
orientation mechanism), or a sequence of N `pin.SE3` placements of the task frame in the base frame
(components the task does not command are ignored)."""


# ------------------------------------------------------------------------------------------------
# Results
@dataclass(frozen=True)
class TargetFailure:
    """A target that could not be processed.

    index: 0-based position of the target in the batch; reason: which solve failed and the typed
    error's message (residual and iterations included); error: the typed error's class, e.g.
    `OutOfWorkspaceError` for a target out of reach or needing a slider beyond its limit.
    """

    index: int
    reason: str
    error: type[M3t1rError]


@dataclass(frozen=True)
class CompensatedCommand:
    """The compensated command for one target T_co.

    actuators: q^c, calibrated-model IK sliders [m] in `actuated_joints` order ("actuators" output);
    command_pose: T_cp, the task frame of the nominal model at q^c, by FK ("pose" output for a
    nominal-model controller, which takes task-frame targets);
    reached_pose: the calibrated model's task frame at q^c (its commanded components, e.g. position
    and yaw, equal T_co's);
    tilt: (roll, pitch) [rad] of `reached_pose` minus those of T_co (the requested ones are zero
    for an (x, y, z, theta) target): what the machine does that cannot be commanded;
    iterations: Newton steps of the calibrated IK.
    """

    actuators: np.ndarray
    command_pose: pin.SE3
    reached_pose: pin.SE3
    tilt: tuple[float, float]
    iterations: int


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array)
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class Compensation:
    """Compensated commands for a batch of N targets.

    Failed targets are EXCLUDED from the arrays, not filled: row k of every array belongs to target
    `indices[k]` of the input, and `failures` lists the others by index with the reason. Every array
    is therefore finite. M = len(indices) = N - len(failures).

    indices: (M,) int, input position of each row; actuators: (M, 4) q^c [m] ("actuators" output,
    columns `actuated_joints`); command_placements: (M, 4, 4) task-frame placements T_cp in the base
    frame [m] ("pose" output; `command_poses` the same as pin.SE3, built on first use);
    reached_placements: (M, 4, 4) task-frame placements of the calibrated model at q^c (`reached_poses`
    as pin.SE3); tilt: (M, 2) roll, pitch [rad]
    of the calibrated machine at each target minus the requested ones (reported, not compensated);
    iterations: (M,) Newton steps of the calibrated IK; failures: the excluded targets, ascending.
    """

    n_targets: int
    actuated_joints: tuple[str, ...]
    indices: np.ndarray
    actuators: np.ndarray
    command_placements: np.ndarray
    reached_placements: np.ndarray
    tilt: np.ndarray
    iterations: np.ndarray
    failures: tuple[TargetFailure, ...]
    task: TaskSpec | None = None

    @lazy
    def command_poses(self) -> tuple[pin.SE3, ...]:
        """T_cp of every row as pin.SE3 (`command_placements`)."""
        return tuple(pin.SE3(h) for h in self.command_placements)

    @lazy
    def reached_poses(self) -> tuple[pin.SE3, ...]:
        """The calibrated model's task frame at q^c of every row as pin.SE3 (`reached_placements`)."""
        return tuple(pin.SE3(h) for h in self.reached_placements)

    @property
    def complete(self) -> bool:
        """True when every target was compensated."""
        return not self.failures

    @property
    def command_targets(self) -> np.ndarray:
        """T_cp as task coordinates (M, d) (`TaskSpec.columns`, e.g. x, y, z, theta [m, rad] with
        theta = `yaw_of`): the pose output for a controller taking task targets."""
        task = self.task or TaskSpec("platform")
        return task.coordinates(self.command_placements)

    def command_pose_rows(self) -> np.ndarray:
        """T_cp as (M, 7) rows x, y, z, qx, qy, qz, qw (`io.POSE_COLUMNS`): the pose output as a file row."""
        return pose_rows(self.command_poses)

    @property
    def max_tilt(self) -> float:
        """Largest |roll| or |pitch| [rad] over the compensated targets (0 when none)."""
        return float(np.max(np.abs(self.tilt))) if self.tilt.size else 0.0


# ------------------------------------------------------------------------------------------------
# Inputs
def _validated_targets(targets: Targets, task: TaskSpec) -> list[np.ndarray] | list[pin.SE3]:
    """Targets as a list of task-coordinate vectors or of SE3, every value finite; else InvalidInputError
    naming the row."""
    if isinstance(targets, pin.SE3):
        raise InvalidInputError("targets: a single pin.SE3; give a sequence of them (or use Compensator.command)")
    if not isinstance(targets, np.ndarray) and len(targets) and all(isinstance(t, pin.SE3) for t in targets):
        poses = list(targets)
        for index, pose in enumerate(poses):
            homogeneous = pose.homogeneous
            if not np.all(np.isfinite(homogeneous)):
                raise InvalidInputError(f"target {index} (0-based): non-finite value in its placement")
            rotation = homogeneous[:3, :3]
            # A non-orthonormal "rotation" has no well-defined yaw; catch corrupted input early.
            if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-9):
                raise InvalidInputError(f"target {index} (0-based): rotation matrix is not orthonormal")
        return poses
    if not isinstance(targets, np.ndarray) and any(isinstance(t, pin.SE3) for t in targets):
        raise InvalidInputError(
            f"targets: mix of pin.SE3 and other rows; give all placements or an (N, {len(task.columns)}) array"
        )
    columns = task.columns
    array = real_array(targets, "targets", f"numeric rows ({', '.join(columns)})")
    if array.ndim != 2 or array.shape[1] != len(columns):
        raise InvalidInputError(
            f"targets: shape {array.shape}, expected (N, {len(columns)}) rows ({', '.join(columns)})"
        )
    if array.shape[0] == 0:
        raise InvalidInputError("targets: no rows")
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        row, col = (int(i) for i in bad[0])
        raise InvalidInputError(f"target {row} (0-based): {columns[col]} = {array[row, col]}, not a finite number")
    return list(task.goals(array))


def _check_compatible(nominal: Mechanism, calibrated: Mechanism) -> None:
    # Slider commands and platform poses only carry over between two models that name the same
    # joints and frame; anything else is a wrong file pair, not a geometry difference.
    if nominal.actuated_joints != calibrated.actuated_joints:
        raise InvalidInputError(
            f"calibrated model actuates {calibrated.actuated_joints}, "
            f"the nominal one {nominal.actuated_joints}: not the same machine"
        )
    if nominal.platform_frame != calibrated.platform_frame:
        raise InvalidInputError(
            f"calibrated platform frame '{calibrated.platform_frame}' differs from the "
            f"nominal '{nominal.platform_frame}'"
        )
    if nominal.task != calibrated.task:
        raise InvalidInputError(f"calibrated model's task {calibrated.task} differs from the nominal {nominal.task}")
    if nominal.model.nq != calibrated.model.nq:
        raise InvalidInputError(f"calibrated model has nq = {calibrated.model.nq}, nominal {nominal.model.nq}")


# ------------------------------------------------------------------------------------------------
# Warm-started path solving
class _PathSolver:
    """A `ClosedLoopSolver` that follows a path and falls back to home once per failed solve.

    The warm start (last good solution) is what makes a path fast; home is the reference branch.
    A warm solve can fail for reasons of the start alone (a jump across the workspace that Newton's
    capped steps cannot follow, or a branch check against the last solution), so one retry from
    home separates "unreachable" from "badly started"; the retry's error is the one raised. A
    failed solve leaves the solver's state alone, so the next target starts from the last good
    solution again.
    """

    def __init__(self, mechanism: Mechanism) -> None:
        self.solver = ClosedLoopSolver(mechanism)
        self._home = mechanism.home
        self._warm = False  # False while the last good solution is home itself: nothing to retry from

    def inverse(self, target: np.ndarray | pin.SE3) -> InverseResult:
        return self.solve(self.solver.inverse, target)

    def forward(self, actuators: np.ndarray) -> ForwardResult:
        return self.solve(self.solver.forward, actuators)

    def solve(self, solve, argument):
        """Warm-started solve; after a failure, once more from home (unless that was the start)."""
        try:
            result = solve(argument)
        except KinematicsError:
            if not self._warm:
                raise
            result = solve(argument, q_init=self._home)
        self._warm = True
        return result

    def reset(self) -> None:
        self.solver.reset()
        self._warm = False


class _JointLimits:
    """One model's joint limits, read once, for a check per target: at about 20 joints a loop over
    Python floats costs a fraction of numpy's comparisons and of reading the limits from the model."""

    def __init__(self, model: pin.Model) -> None:
        self._model = model
        self._lower, self._upper = model.lowerPositionLimit.tolist(), model.upperPositionLimit.tolist()

    def violation(self, q: np.ndarray) -> str | None:
        """`joint_limit_violation` of q (None when every joint is inside its limits)."""
        if within_limits(self._lower, q.tolist(), self._upper):
            return None
        return joint_limit_violation(self._model, q)  # names the joint; NaN counts as outside there too

    def check(self, result: InverseResult) -> None:
        """Raise OutOfWorkspaceError if any joint of the solved configuration is beyond its URDF limit.

        The solver keeps the sliders within their limits but not the passive hinges (models/README.md):
        a target reachable only with, say, the platform hinge past its stop is not a command to send.
        """
        if result.within_joint_limits:  # the solver's own check, against this model's limits
            return
        violation = self.violation(result.q)
        if violation is not None:
            raise OutOfWorkspaceError(violation, result.residual, result.iterations)


def joint_limit_violation(model: pin.Model, q: np.ndarray) -> str | None:
    """ "target puts joint 'NAME' at V, beyond its limit [LO, HI]" for the first joint of a configuration
    (model order) outside its URDF limits (NaN counts as outside), or None when every joint is inside."""
    lower, upper = model.lowerPositionLimit, model.upperPositionLimit
    inside = (q >= lower) & (q <= upper)
    if inside.all():  # the common case, in a servo loop: no index search
        return None
    k = int(np.argmin(inside))
    name = model.names[1 + list(model.idx_qs[1:]).index(k)]
    return f"target puts joint '{name}' at {q[k]:.6g}, beyond its limit [{lower[k]:.6g}, {upper[k]:.6g}]"


def _add_target_note(exc: Exception, index: int) -> None:
    # Python >= 3.11 shows notes in tracebacks; the typed error itself is re-raised unchanged.
    if hasattr(exc, "add_note"):
        exc.add_note(f"while compensating target {index} (0-based) of the batch")


# ------------------------------------------------------------------------------------------------
# Compensation
class Compensator:
    """Paper Fig. 6 for a stream of targets: calibrated IK, then nominal FK, warm-started.

    Keeps one solver per model, so successive calls follow a path (about 2 Newton steps each).
    Not thread-safe: one compensator per thread. A caller streaming `command` in its own loop
    should run it inside `_threads.single_blas_thread()`: the matrices are tiny and BLAS threads
    only add wake-ups (`compensate` does this itself).
    """

    def __init__(self, nominal: Mechanism, calibrated: Mechanism) -> None:
        _check_compatible(nominal, calibrated)
        self.nominal = nominal
        self.calibrated = calibrated
        self._inverse = _PathSolver(calibrated)
        self._forward = _PathSolver(nominal)
        self._limits = _JointLimits(calibrated.model)

    def reset(self) -> None:
        """Start the next target from home on both models."""
        self._inverse.reset()
        self._forward.reset()

    def command(self, target: np.ndarray | pin.SE3) -> CompensatedCommand:
        """Compensated command for one target (x, y, z, theta) [m, rad] or pin.SE3.

        Raises InvalidInputError for a malformed target, and the typed `KinematicsError` of the
        failing solve otherwise: `OutOfWorkspaceError` when the calibrated machine cannot reach the
        target or needs a slider beyond its limit (never clipped), `BranchChangeError`,
        `NotConvergedError`, `SingularConfigurationError`. InvalidInputError also when q^c is
        beyond the nominal model's slider limits (a calibrated file with other limits).
        """
        ik = self._inverse.inverse(target)
        self._limits.check(ik)
        fk = self._forward.forward(ik.actuators)
        return CompensatedCommand(ik.actuators, fk.task_pose, ik.task_pose, ik.tilt, ik.iterations)

    @on_one_blas_thread
    def compensate(self, targets: Targets, *, strict: bool = False, progress=None) -> Compensation:
        """Compensated commands for a batch of targets, in order, warm-started along the path.

        targets: (N, 4) rows (x, y, z, theta) [m, m, m, rad] or N `pin.SE3` (platform in base).
        Every target is checked first: a NaN/inf value raises InvalidInputError naming the row
        before any solve. A target that fails is reported in `Compensation.failures` (index, reason,
        error class) and excluded from the arrays; the next one restarts from the last good
        solution. With strict=True the first failure is raised instead (the typed error, with a note
        naming the target's index). A target that puts any joint of the calibrated machine beyond its
        URDF limit (a passive hinge past its stop, say) fails with OutOfWorkspaceError. `progress`, if
        given, is called with the index of each target before it is solved.
        """
        rows = _validated_targets(targets, self.calibrated.task)
        indices, commands, failures = [], [], []
        # `command`'s steps, a layer of calls fewer: a servo loop pays for each.
        calibrated, nominal, limits = self._inverse, self._forward, self._limits
        inverse, forward = calibrated.solver.inverse, nominal.solver.forward
        for index, target in enumerate(rows):
            if progress is not None:
                progress(index)
            stage = "inverse kinematics of the calibrated model"
            try:
                ik = calibrated.solve(inverse, target)
                if not ik.within_joint_limits:
                    limits.check(ik)
                stage = "forward kinematics of the nominal model at the compensated sliders"
                fk = nominal.solve(forward, ik.actuators)
            except (KinematicsError, InvalidInputError) as exc:
                # InvalidInputError here can only be q^c beyond the nominal model's slider limits.
                if strict:
                    _add_target_note(exc, index)
                    raise
                failures.append(TargetFailure(index, f"{stage}: {exc}", type(exc)))
                continue
            indices.append(index)
            commands.append((ik.actuators, fk.task_placement, ik.task_placement, ik.tilt, ik.iterations))
        actuators, command_placements, reached_placements, tilt, iterations = zip(*commands) if commands else ((),) * 5
        return Compensation(
            n_targets=len(rows),
            actuated_joints=self.calibrated.actuated_joints,
            indices=_frozen(np.array(indices, dtype=int)),
            actuators=_frozen(np.array(actuators).reshape(-1, len(self.calibrated.actuated_joints))),
            command_placements=_frozen(np.array(command_placements).reshape(-1, 4, 4)),
            reached_placements=_frozen(np.array(reached_placements).reshape(-1, 4, 4)),
            tilt=_frozen(np.array(tilt).reshape(-1, 2)),
            iterations=_frozen(np.array(iterations, dtype=int)),
            failures=tuple(failures),
            task=self.calibrated.task,
        )

    @on_one_blas_thread
    def compensate_batch(self, targets: Targets) -> Compensation:
        """Compensated commands for many targets at once: calibrated `inverse_batch`, then nominal
        `forward_batch` at q^c, every target solved from home (the reference branch), vectorised.

        Same result type and row convention as `compensate` (failed targets excluded, listed in
        `failures` with the failing stage and error class), but no path order is assumed: use it for
        maps, grids and files of unrelated targets. A target putting any joint of the calibrated machine
        beyond its URDF limit fails with OutOfWorkspaceError, as in `compensate`.
        """
        task = self.calibrated.task
        rows = _validated_targets(targets, task)
        if isinstance(rows[0], pin.SE3):
            poses = [p for p in rows if isinstance(p, pin.SE3)]  # every row: `_validated_targets` gives one kind
            wanted = np.array([roll_pitch_of(p.rotation) for p in poses])
            rows = list(task.coordinates(np.array([p.homogeneous for p in poses])))
        else:
            wanted = np.zeros((len(rows), 2))
        if task.rotation == "full":
            wanted[:] = 0.0  # the batch IK's tilt is already relative to a full-rotation goal
        ik = self._inverse.solver.inverse_batch(np.array(rows))
        failures = [
            TargetFailure(f.index, f"inverse kinematics of the calibrated model: {f.reason}", f.error)
            for f in ik.failures
        ]
        violations = [self._limits.violation(q) for q in ik.q]
        failures += [
            TargetFailure(int(index), f"inverse kinematics of the calibrated model: {violation}", OutOfWorkspaceError)
            for index, violation in zip(ik.indices, violations)
            if violation is not None
        ]
        keep = np.array([violation is None for violation in violations], dtype=bool)
        fk = self._forward.solver.forward_batch(ik.actuators[keep])
        failures += [
            TargetFailure(
                int(ik.indices[keep][f.index]),
                f"forward kinematics of the nominal model at the compensated sliders: {f.reason}",
                f.error,
            )
            for f in fk.failures
        ]
        good = np.flatnonzero(keep)[fk.indices]  # rows of `ik` with a command
        return Compensation(
            n_targets=len(rows),
            actuated_joints=self.calibrated.actuated_joints,
            indices=_frozen(ik.indices[good]),
            actuators=_frozen(ik.actuators[good]),
            command_placements=_frozen(fk.task_poses),
            reached_placements=_frozen(ik.task_poses[good]),
            tilt=_frozen(ik.tilt[good] - wanted[ik.indices[good]]),
            iterations=_frozen(ik.iterations[good]),
            failures=tuple(sorted(failures, key=lambda f: f.index)),
            task=task,
        )


def compensate(
    nominal: Mechanism, calibrated: Mechanism, targets: Targets, *, strict: bool = False, progress=None
) -> Compensation:
    """Compensated commands (paper section 7, Fig. 6) for a batch of targets; see `Compensator.compensate`.

    The first target starts from home on both models, each next one from the previous solution.
    """
    return Compensator(nominal, calibrated).compensate(targets, strict=strict, progress=progress)


# ------------------------------------------------------------------------------------------------
# Accuracy in simulation
@dataclass(frozen=True, eq=False)
class TrackingErrors(PoseErrors):
    """How far a machine ends up from the commanded targets, per target.

    position: |p_achieved - p_target| over the task's commanded axes [m]; rotation: the commanded
    rotation error [rad]: |yaw_achieved - theta_target| wrapped to [0, pi] (yaw by `yaw_of`) for a
    yaw task, the log3 angle for a full rotation, 0 for none. Uncommanded components (roll and pitch
    of the M machine) are not counted here.
    """


@dataclass(frozen=True, eq=False)
class CompensationAccuracy:
    """Errors of the truth machine at the targets, driven without and with compensation.

    n_targets: N, targets given; indices: (M,) those where all four solves succeeded (nominal IK,
    calibrated IK, truth FK at both slider sets), the rows of every array here; before: truth
    errors at the nominal-IK sliders (a controller that trusts the nominal model); after: truth
    errors at the calibrated-IK sliders q^c; actuators_before / actuators_after: (M, 4) those
    sliders [m]; failures: the other targets, by index and reason.
    """

    n_targets: int
    indices: np.ndarray
    before: TrackingErrors
    after: TrackingErrors
    actuators_before: np.ndarray
    actuators_after: np.ndarray
    failures: tuple[TargetFailure, ...]


def _tracking_errors(
    task: TaskSpec, target: np.ndarray | pin.SE3, poses: Sequence[pin.SE3]
) -> list[tuple[float, float]]:
    """(|commanded position error| [m], |commanded rotation error| [rad]) of each reached pose: the
    norms of the position rows and of the rotation rows (wrapped yaw, or log3 angle) of the task."""
    goal = task.coordinates(target.homogeneous)[0] if isinstance(target, pin.SE3) else np.asarray(target)
    rotations = task.target_rotations(goal[None, :])
    count = len(task.position)
    errors = []
    for pose in poses:
        rows = task.residual(pose, goal, None if rotations is None else rotations[0])
        errors.append((float(np.linalg.norm(rows[:count])), float(np.linalg.norm(rows[count:]))))
    return errors


@on_one_blas_thread
def compensation_accuracy(
    nominal: Mechanism, calibrated: Mechanism, truth: Mechanism, targets: Targets
) -> CompensationAccuracy:
    """Simulate commanding `truth` at the targets with nominal-IK and with calibrated-IK sliders.

    With compensation the truth's error at a target equals the calibrated model's own error at
    q^c (the calibrated model reaches the target's position and yaw exactly), so `after` should
    match `pose_errors(calibrated, truth, actuators_after)`; `before` is the raw effect of the
    geometric errors. Targets that fail any of the four solves are reported, not evaluated.
    """
    _check_compatible(nominal, calibrated)
    _check_compatible(nominal, truth)
    task = nominal.task
    rows = _validated_targets(targets, task)
    # Two command streams, each with its own IK solver and its own truth FK solver, so that both
    # warm-start along the target path.
    streams = (
        ("uncompensated", _PathSolver(nominal), "nominal", _PathSolver(truth)),
        ("compensated", _PathSolver(calibrated), "calibrated", _PathSolver(truth)),
    )
    indices, sliders, achieved, failures = [], [], [], []
    for index, target in enumerate(rows):
        commands, poses, stage = [], [], ""
        try:
            for label, ik_solver, model_name, truth_solver in streams:
                stage = f"{model_name}-model inverse kinematics ({label} command)"
                commands.append(ik_solver.inverse(target).actuators)
                stage = f"truth forward kinematics at the {label} sliders"
                poses.append(truth_solver.forward(commands[-1]).task_pose)
        except (KinematicsError, InvalidInputError) as exc:
            failures.append(TargetFailure(index, f"{stage}: {exc}", type(exc)))
            continue
        indices.append(index)
        sliders.append(commands)
        achieved.append(_tracking_errors(task, target, poses))

    def errors(stream: int) -> TrackingErrors:
        pairs = np.array([both[stream] for both in achieved], dtype=float).reshape(-1, 2)
        return TrackingErrors(_frozen(pairs[:, 0]), _frozen(pairs[:, 1]))

    stacked = np.array(sliders, dtype=float).reshape(-1, 2, len(nominal.actuated_joints))
    return CompensationAccuracy(
        len(rows),
        _frozen(np.array(indices, dtype=int)),
        errors(0),
        errors(1),
        _frozen(stacked[:, 0]),
        _frozen(stacked[:, 1]),
        tuple(failures),
    )


# ------------------------------------------------------------------------------------------------
# Targets over the workspace
def workspace_targets(n: int, rng: np.random.Generator, box: WorkspaceBox = NOMINAL.workspace) -> np.ndarray:
    """n targets (n, 4) rows (x, y, z, theta) [m, m, m, rad], uniform in the workspace box."""
    if n < 1:
        raise InvalidInputError(f"workspace_targets: n must be >= 1, got {n}")
    return box.sample(rng, n)


def workspace_grid(counts: Sequence[int], box: WorkspaceBox = NOMINAL.workspace) -> np.ndarray:
    """A regular grid over the workspace box, as a path: (prod(counts), 4) rows (x, y, z, theta).

    counts: points per axis (x, y, z, theta), each >= 1 (1 puts the axis at the box centre).
    Rows are in serpentine (boustrophedon) order, theta fastest: consecutive rows differ by one
    grid step along one axis, so a warm-started batch never jumps across the box.
    """
    counts = tuple(int(c) for c in counts)
    if len(counts) != 4 or min(counts) < 1:
        raise InvalidInputError(f"workspace_grid: counts must be 4 integers >= 1, got {counts}")
    axes = []
    for count, (lo, hi) in zip(counts, (box.x, box.y, box.z, box.theta)):
        axes.append(np.array([(lo + hi) / 2.0]) if count == 1 else np.linspace(lo, hi, count))
    # Serpentine order built from the fastest axis outwards: the inner block is reversed on every
    # other step of the next-slower axis, so block ends meet at the same inner point.
    order = np.arange(counts[3])[:, None]
    for axis in (2, 1, 0):
        blocks = [
            np.column_stack((np.full(len(order), i), order if i % 2 == 0 else order[::-1])) for i in range(counts[axis])
        ]
        order = np.concatenate(blocks)
    return np.column_stack([axes[k][order[:, k]] for k in range(4)])
