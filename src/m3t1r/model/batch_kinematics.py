"""Closed-loop FK and IK for many poses at once: input checks, the predictor from home, the rows'
Newton and one result object with every failure typed.

Every row is the problem a single solve from home solves: the same closure rows
(`closures.ClosureSystem`), task rows (`TaskSpec`), Newton rules (`NewtonRules`) and branch labels.
`ClosedLoopSolver.solve_rows` runs them: the compiled loop over every row in one call (shared among
threads), or without it the single-solve Newton (`ClosedLoopSolver.newton`) row after row. A row that
does not converge, changes assembly branch or ends singular is reported with its typed error class,
never returned as a result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
import pinocchio as pin

from m3t1r.errors import InvalidInputError, M3t1rError, OutOfWorkspaceError, real_array
from m3t1r.model.native import available_cores
from m3t1r.model.newton import CONVERGED, FAILURES, reason
from m3t1r.model.newton_rules import DEFAULT_RULES
from m3t1r.model.rotations import rpy_batch

if TYPE_CHECKING:
    from m3t1r.model.description import Mechanism
    from m3t1r.model.solver_layout import SolverLayout

__all__ = [
    "RowFailure",
    "RowSolver",
    "ForwardBatch",
    "InverseBatch",
    "SolvedRows",
    "failures_of",
    "start_configurations",
]


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


_CONVERGED, _LIMIT = CONVERGED, 5  # _LIMIT: converged, but a slider is beyond its limit


@dataclass
class SolvedRows:
    """Raw outcome of a batched Newton solve: per row q, status code, residual, steps, platform pose
    (n, 4, 4), valid where the status is converged."""

    q: np.ndarray
    status: np.ndarray
    norm: np.ndarray
    iterations: np.ndarray
    platform: np.ndarray


class RowSolver(Protocol):
    """What a batch reads from its solver (`ClosedLoopSolver`): the problem, its layout and rules, the
    predictor from home and the rows' Newton."""

    mechanism: Mechanism
    model: pin.Model
    layout: SolverLayout
    passive: np.ndarray
    actuated: np.ndarray

    @property
    def singular_rcond(self) -> float: ...
    def home_reference(self) -> tuple[np.ndarray, bytes] | None: ...
    def home_derivatives(self) -> tuple[np.ndarray, np.ndarray] | None: ...
    def starts_from_home(self, sliders: np.ndarray, order: int = 3) -> np.ndarray: ...
    def check_square_task(self) -> None: ...
    def solve_rows(
        self,
        starts: np.ndarray,
        branch: bytes | None,
        steps_taken: int,
        goals: np.ndarray | None = None,
        goal_rotations: np.ndarray | None = None,
        threads: int = 1,
    ) -> SolvedRows: ...


def failures_of(
    solved: SolvedRows, offset: int, what: str, singular_rcond: float = DEFAULT_RULES.singular_rcond
) -> list[RowFailure]:
    """Typed failures of the rows of `solved` that did not converge (indices shifted by `offset`);
    singular rows name `singular_rcond`, the threshold they fell below."""
    return [
        RowFailure(
            offset + int(i),
            f"{what}: {reason(int(solved.status[i]), singular_rcond=singular_rcond)} (residual "
            f"{solved.norm[i]:.3e} after {int(solved.iterations[i])} iterations)",
            FAILURES[int(solved.status[i])],
        )
        for i in np.flatnonzero((solved.status != _CONVERGED) & (solved.status != _LIMIT))
    ]


def start_configurations(solver: RowSolver, n: int, q_init: np.ndarray | None) -> np.ndarray:
    """Start configurations (n, nq): home by default, one nq vector for every row, or one per row."""
    nq = solver.model.nq
    if q_init is None:
        return np.repeat(solver.mechanism.home[None, :], n, axis=0)
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
    finite = np.isfinite(array)
    if not finite.all():
        row, col = (int(i) for i in np.argwhere(~finite)[0])
        raise InvalidInputError(f"{what}: row {row} (0-based): {columns[col]} = {array[row, col]}, not finite")
    return array


def forward_batch(
    solver: RowSolver, sliders: np.ndarray, q_init: np.ndarray | None = None, threads: int | None = None
) -> ForwardBatch:
    """Platform poses for n slider sets (n, k) [m], each solved from q_init.

    Default (q_init None): every row starts from home moved along home's solution manifold to third
    order (`ClosedLoopSolver.starts_from_home`, counted as one iteration) and must end on
    home's assembly branch (the branch labels at home). Far from home this assembles rows where plain
    Newton from home's passive joints crosses a singularity (`forward(a, q_init=home)` then raises
    BranchChangeError or OutOfWorkspaceError); where both succeed they agree to the tolerance.
    Given q_init (nq,) or (n, nq), each row starts there, branch labels taken at its start.
    A row with a slider beyond its URDF limit fails with InvalidInputError (reported, not raised);
    non-finite values or a wrong shape raise InvalidInputError for the whole batch. threads: how many
    threads share the rows in the compiled loop (None: every core this process may use; the Python
    loop ignores it); the results do not depend on it.
    """
    workers = _thread_count(threads)
    names = solver.mechanism.actuated_joints
    values = _rows(sliders, len(names), "actuator values", names)
    lower, upper = solver.layout.actuator_lower, solver.layout.actuator_upper
    outside = (values < lower) | (values > upper)
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
    reference = solver.home_reference() if q_init is None else None
    if reference is None:  # from q_init, or from a singular home: labels at each start
        start = start_configurations(solver, len(values), q_init)
        start[:, solver.actuated] = values
        inside = start if len(rows) == len(start) else start[rows]  # the rows' own array, solved in place
        parts = [(rows, solver.solve_rows(inside, None, 0, threads=workers))]
    else:
        parts = _rows_from_home(solver, values[rows], rows, reference[1], workers)
    last_rows, last = parts[-1]
    failures += [
        RowFailure(int(last_rows[f.index]), f.reason, f.error)
        for f in failures_of(last, 0, "forward kinematics", solver.singular_rcond)
    ]
    return _forward_result(solver, len(values), parts, failures)


def _rows_from_home(
    solver: RowSolver, sliders: np.ndarray, rows: np.ndarray, branch: bytes, workers: int
) -> list[tuple[np.ndarray, SolvedRows]]:
    """Rows `rows` of slider values `sliders` solved from home's third-order prediction
    (`starts_from_home`), then the rows it loses from the first-order one: [(rows, solved)] and, if
    any was lost, [(lost rows, solved again)], whose failures are the batch's.

    Far from home the higher-order terms can carry a start past a singularity that the first-order
    start stays clear of (five-bar sliders 1.5 rad from home): retried, such a row ends as it
    did with the first-order start, so the batch converges wherever that start converges.
    """
    solved = solver.solve_rows(solver.starts_from_home(sliders), branch, 1, threads=workers)
    lost = np.flatnonzero(solved.status != _CONVERGED)
    if not len(lost) or solver.home_derivatives() is None:
        return [(rows, solved)]
    again = solver.starts_from_home(sliders[lost], order=1)
    return [(rows, solved), (rows[lost], solver.solve_rows(again, branch, 1, threads=workers))]


def _thread_count(threads: int | None) -> int:
    """The thread count asked for (an int >= 1), or every available core for None."""
    if threads is None:
        return available_cores()
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InvalidInputError(f"threads: expected an integer >= 1 or None, got {threads!r}")
    return int(threads)


def _task_poses(solver: RowSolver, q: np.ndarray) -> np.ndarray:
    """Task frame placements (n, 4, 4) in the base frame at configurations q (n, nq)."""
    model, data, frame = solver.model, solver.mechanism.model.createData(), solver.layout.task_frame
    poses = np.empty((len(q), 4, 4))
    for i, configuration in enumerate(q):
        pin.forwardKinematics(model, data, configuration)
        poses[i] = pin.updateFramePlacement(model, data, frame).homogeneous
    return poses


def _forward_result(solver: RowSolver, n: int, parts: list, failures: list) -> ForwardBatch:
    """Gather the converged rows of every part (in input order) into a frozen ForwardBatch (q: (M, nq),
    also when no row converged), with the task frame's placements. A single part's rows are in input
    order already (every caller's: `np.flatnonzero` or `np.arange`)."""
    columns: list[list[np.ndarray]] = [[], [], [], [], []]  # rows, poses, q, residuals, iterations
    for chunk, solved in parts:
        good = solved.status == _CONVERGED
        kept = slice(None) if good.all() else good  # the usual batch: its arrays as they are
        for column, array in zip(columns, (chunk, solved.platform, solved.q, solved.norm, solved.iterations)):
            column.append(array[kept])
    widths = ((), (4, 4), (solver.model.nq,), (), ())
    if len(parts) == 1:
        index, platform, q, norms, steps = (column[0] for column in columns)
    else:
        index, platform, q, norms, steps = (
            np.concatenate(column) if column else np.zeros((0, *width)) for column, width in zip(columns, widths)
        )
        order = np.argsort(index, kind="stable")
        index, platform, q, norms, steps = index[order], platform[order], q[order], norms[order], steps[order]
    platform, q = _frozen(platform), _frozen(q)
    layout = solver.layout
    task = platform if layout.task_frame == layout.platform_frame else _frozen(_task_poses(solver, q))
    return ForwardBatch(
        n=n,
        indices=_frozen(index.astype(int)),
        poses=platform,
        q=q,
        residuals=_frozen(norms),
        iterations=_frozen(steps.astype(int)),
        failures=tuple(sorted(failures, key=lambda f: f.index)),
        task_poses=task,
    )


def inverse_batch(
    solver: RowSolver, targets: np.ndarray, q_init: np.ndarray | None = None, threads: int | None = None
) -> InverseBatch:
    """Slider values for n targets, rows of task coordinates (`TaskSpec.columns`, e.g. x, y, z, theta)
    [m, rad], each from q_init (default home).

    Row system as `ClosedLoopSolver.inverse`: [closure rows; task rows] = 0 over every joint but the
    locked ones; branch labels = closure blocks plus the sign of det of the whole system, taken at
    the row's start. A converged row needing a slider beyond its limit fails with OutOfWorkspaceError
    naming the slider. threads: as `forward_batch`.
    """
    workers = _thread_count(threads)
    task = solver.mechanism.task
    solver.check_square_task()
    goal = task.goals(_rows(targets, len(task.columns), "targets", task.columns))
    goal_rot = task.target_rotations(goal)
    start = start_configurations(solver, len(goal), q_init)
    parts, failures = [], []
    if len(goal):
        rows = np.arange(len(goal))
        solved = solver.solve_rows(start, None, 0, goal, goal_rot, threads=workers)
        failures += _beyond_limits(solver, solved, rows)
        failures += [
            RowFailure(int(rows[f.index]), f.reason, f.error)
            for f in failures_of(solved, 0, "inverse kinematics", solver.singular_rcond)
        ]
        parts.append((rows, solved))
    fk = _forward_result(solver, len(goal), parts, failures)
    wanted = np.zeros(2) if goal_rot is None else rpy_batch(goal_rot[fk.indices])[:, :2]
    return InverseBatch(
        **{
            f: getattr(fk, f)
            for f in ("n", "indices", "poses", "q", "residuals", "iterations", "failures", "task_poses")
        },
        actuators=_frozen(fk.q[:, solver.actuated]),
        tilt=_frozen(rpy_batch(fk.task_poses[:, :3, :3])[:, :2] - wanted),
    )


def _beyond_limits(solver: RowSolver, solved: SolvedRows, rows: np.ndarray) -> list[RowFailure]:
    """Converged IK rows that need a slider beyond its limit, marked _LIMIT in `solved`, as failures."""
    names, units = solver.mechanism.actuated_joints, solver.mechanism.joint_units()
    lower, upper = solver.layout.actuator_lower, solver.layout.actuator_upper
    sliders = solved.q[:, solver.actuated]
    outside = ((sliders < lower) | (sliders > upper)) & (solved.status == _CONVERGED)[:, None]
    failures = []
    for i in np.flatnonzero(outside.any(axis=1)):
        k = int(np.argmax(outside[i]))
        solved.status[i] = _LIMIT
        failures.append(
            RowFailure(
                int(rows[i]),
                f"inverse kinematics: target needs actuator '{names[k]}' = "
                f"{sliders[i, k]:.6g} {units[k]}, beyond its limit "
                f"[{lower[k]:.6g}, {upper[k]:.6g}]",
                OutOfWorkspaceError,
            )
        )
    return failures
