"""The compiled Newton loop of closed-loop FK (`_native_newton`, C++ on Pinocchio), when it is built.

`tools/build_native.py` (run by `make`) compiles it in place. It solves the problem of
`ClosedLoopSolver.newton` (single solves, and batch rows without the compiled loop), step for step:
the same residual and exact Jacobian of the enforced rows, and the same `NewtonRules` (passed with
every call: chord steps, step cap, convergence test, singular threshold, no-assembly threshold), the
1-norm reciprocal condition and branch labels (signs of the diagonal blocks' determinants). It holds
its own `pinocchio::Model`, rebuilt from the Python model's joints and placements, so a calibrated
copy of a machine gets its own. Trees of 1-DoF revolute and prismatic joints only; anything else
(and an interpreter without the module) keeps the pure-Python loop: `NativeChain.of` returns None.
Without the module the first solver of a run warns (RuntimeWarning: four to six times slower),
unless M3T1R_PURE_PYTHON is set; `status()` says in one line which loop runs and why.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from m3t1r.model.closures import ROW_COUNT, frame_support, relative_supports
from m3t1r.model.native_status import STALE, load_compiled

_native_newton, _WHY_NOT = load_compiled()  # _WHY_NOT: why the Python loops run ("": they do not)
# The variable that asks for the pure-Python package (tools/build_native.py, hatch_build.py): set, a
# run without the compiled loop is what the user chose and goes without the warning.
PURE_PYTHON_VARIABLE = "M3T1R_PURE_PYTHON"
if _WHY_NOT == STALE:
    # Compiled from another version of the source (edited since, or an old build): its calls may not
    # match this module's. The Python loops run until `make native` rebuilds it.
    warnings.warn(
        "_native_newton: the compiled Newton loop is older than its source; using "
        "the Python loop (rebuild: make native, or python tools/build_native.py)",
        RuntimeWarning,
        stacklevel=2,
    )
_warned = _WHY_NOT == STALE  # that case has had its warning, above

if TYPE_CHECKING:
    import pinocchio as pin

    from m3t1r.model.closures import ClosureSpec
    from m3t1r.model.solver_layout import SolverLayout
    from m3t1r.model.task import TaskSpec

__all__ = ["AVAILABLE", "NativeChain", "CONVERGED", "PURE_PYTHON_VARIABLE", "available_cores", "status"]

AVAILABLE = _native_newton is not None
_EMPTY = np.zeros(0)
CONVERGED = 0  # status codes 1-4 as `newton`: no assembly, not converged, singular, branch change
SLIDER_BEYOND_LIMIT = 5  # a single FK's sliders beyond their limits (or NaN): nothing solved

# Joint types the compiled model rebuilds, by Pinocchio's short name: the code `joint_of` reads.
_ROTATION_CODES = {"none": 0, "yaw": 1, "full": 2}
_KINDS = {
    "JointModelRX": 0,
    "JointModelRY": 1,
    "JointModelRZ": 2,
    "JointModelRevoluteUnaligned": 3,
    "JointModelPX": 4,
    "JointModelPY": 5,
    "JointModelPZ": 6,
    "JointModelPrismaticUnaligned": 7,
}


class NativeChain:
    """One mechanism's closures, passive and actuated joints and branch blocks, compiled.

    `forward` solves one configuration in place, `forward_rows` many; both return status codes
    (0 converged; 1 no assembly, 2 not converged, 3 singular, 4 branch change) that the callers turn
    into their typed errors.
    """

    def __init__(
        self,
        handle: object,
        counts: tuple[int, int, int, int, int],
        limits: tuple[np.ndarray, np.ndarray],
    ) -> None:
        """counts: (branch blocks, passive joints, actuated joints, IK unknowns, task rows); limits: the
        model's (lower, upper) position limits (nq), which single solves check."""
        n_blocks, n_passive, n_actuated, n_unknowns, task_rows = counts
        assert _native_newton is not None, "built by `of` only when the module is"
        self._handle, self.n_blocks, self._module = handle, n_blocks, _native_newton
        self.tangent = np.zeros((n_passive, n_actuated))  # FK: -J_passive^-1 J_actuated at the last success
        self.task_inverse = np.zeros((n_unknowns, task_rows))  # IK: task-row columns of the last inverse
        self.platform, self.task = np.eye(4), np.eye(4)  # FK: their placements at the last success [m]
        self.inverse_platform, self.inverse_task = np.eye(4), np.eye(4)  # IK's
        self.branch = bytearray(n_blocks)  # FK's labels at the last success
        self.inverse_branch = bytearray(n_blocks + 1)  # IK's: the blocks', then sign(det) of the whole system
        # FK's history: the sliders and passive joints its last success started from (the second-order
        # predictor's `previous`); IK's actuators at its last success [m or rad].
        self.history, self.inverse_actuators = np.zeros(n_actuated + n_passive), np.zeros(n_actuated)
        self._identity = np.eye(3)
        self._lower, self._upper = (np.array(limit, dtype=float) for limit in limits)
        # The compiled chain reads and writes these arrays in place (bound once: every solve then passes
        # only its own inputs), so they are never rebound: fill them with `[:] =`.
        self._module.bind(
            handle,
            self.tangent,
            self.branch,
            self.platform,
            self.task,
            self.task_inverse,
            self.inverse_branch,
            self.inverse_platform,
            self.inverse_task,
            self.history,
            self.inverse_actuators,
            self._lower,
            self._upper,
        )

    @classmethod
    def of(
        cls, model: pin.Model, closures: tuple[ClosureSpec, ...], layout: SolverLayout, task: TaskSpec
    ) -> NativeChain | None:
        """The compiled chain, or None when the module is not built or a joint is not 1-DoF revolute/prismatic.

        layout: the solver's (`SolverLayout`: FK's and IK's columns, branch blocks, platform and task
        frames); IK is square only when the task's dimension equals the actuator count (else only FK
        may be called).
        """
        if _native_newton is None:
            _warn_once_without_module()
            return None
        names = [model.joints[j].shortname() for j in range(1, model.njoints)]
        if any(name not in _KINDS for name in names):
            return None
        joints = np.array([[model.parents[j], _KINDS[names[j - 1]]] for j in range(1, model.njoints)], dtype=np.int64)
        axes = np.array([_axis(model.joints[j]) for j in range(1, model.njoints)])
        placements = np.array([model.jointPlacements[j].homogeneous for j in range(1, model.njoints)])
        passive, actuated, blocks = layout.passive, layout.actuated, layout.blocks
        unknowns = np.arange(model.nv) if layout.unknowns is None else layout.unknowns
        # Each frame once: the platform and the task frame are often a closure's frame too.
        named = {layout.platform_frame, layout.task_frame}
        frame_ids = sorted({c.frame_a_id for c in closures} | {c.frame_b_id for c in closures} | named)
        where = {f: k for k, f in enumerate(frame_ids)}
        rows = np.cumsum([0] + [len(c.rows) for c in closures])
        spec = np.array(
            [[ROW_COUNT[c.type], where[c.frame_a_id], where[c.frame_b_id], rows[k]] for k, c in enumerate(closures)],
            dtype=np.int64,
        ).reshape(-1, 4)
        components = np.array([r for c in closures for r in c.rows], dtype=np.int64)
        square = int(rows[-1]) + task.dimension == len(unknowns)
        ik_columns = np.asarray(unknowns if square else passive, dtype=np.int64)  # FK only: a square stand-in
        ik_axes = task.axes if square else np.zeros(0, dtype=int)
        handle = _native_newton.build(
            joints,
            np.ascontiguousarray(axes, dtype=float),
            np.ascontiguousarray(placements),
            np.array([model.frames[f].parentJoint for f in frame_ids], dtype=np.int64),
            np.array([model.frames[f].placement.homogeneous for f in frame_ids]),
            spec,
            components,
            np.ascontiguousarray(relative_supports(model, closures), dtype=float),
            np.asarray(passive, dtype=np.int64),
            np.asarray(actuated, dtype=np.int64),
            np.concatenate([r for r, _ in blocks]).astype(np.int64),
            np.concatenate([c for _, c in blocks]).astype(np.int64),
            np.cumsum([len(r) for r, _ in blocks]).astype(np.int64),
            ik_columns,
            ik_axes.astype(np.int64),
            np.flatnonzero(frame_support(model, layout.task_frame)).astype(np.int64),
            where[layout.platform_frame],
            where[layout.task_frame],
            _ROTATION_CODES[task.rotation] if square else 0,
        )
        counts = (len(blocks), len(passive), len(actuated), len(ik_columns), task.dimension if square else 0)
        return cls(handle, counts, (model.lowerPositionLimit, model.upperPositionLimit))

    def forward(
        self,
        q: np.ndarray,
        sliders: np.ndarray,
        order: int,
        previous: np.ndarray | None,
        start_branch: bytes | None,
        rules: tuple,
    ) -> tuple[int, float, int, float, int]:
        """FK from the last solution q (nq, float64, solved in place) to `sliders` (float64).

        order: 0 no predictor, 1 first order along `tangent` (the last success's), 2 also second order
        with previous = (sliders, passive joints) of the solution before q, concatenated
        (`ClosedLoopSolver.predict`). start_branch: the labels the solution must have (None: those at
        its start); rules: `NewtonRules.compiled()`, what every loop obeys. On success
        `tangent`, `platform`, `task` and `branch` hold the solution's, and `history` this solve's
        start (its sliders, then passive joints: the next solve's `previous`, which may be `history`
        itself). Returns (status, max |row|, iterations, reciprocal condition of a singular end (0 for
        a zero pivot) or 0, the first coordinate of a solution beyond its joint limits or -1); status
        SLIDER_BEYOND_LIMIT when a slider is beyond its limit or NaN, before anything is solved or
        changed.
        """
        if start_branch is not None:  # labels are 0 or 1: a label of another length cannot be met
            self.branch[:] = start_branch if len(start_branch) == self.n_blocks else b"\xff" * self.n_blocks
        return self._module.forward(
            self._handle, q, sliders, order, _EMPTY if previous is None else previous, start_branch is not None, *rules
        )

    def inverse(
        self,
        q: np.ndarray,
        goal: np.ndarray,
        goal_rotation: np.ndarray | None,
        order: int,
        previous: tuple | None,
        start_branch: bytes | None,
        rules: tuple,
    ) -> tuple[int, float, int, float, int, float, float]:
        """IK from the last solution q (solved in place) on [closure rows; task rows] with `goal` (task
        coordinates) and `goal_rotation` (3 x 3, a full-rotation task).

        order: 0 no predictor, 1 first order from `task_inverse` and `inverse_task` (the last IK
        success's), 2 also second order with previous = ((goal, goal rotation), q) of the IK solution
        before (`ClosedLoopSolver.inverse_predict`). On success `task_inverse`, `inverse_platform`,
        `inverse_task`, `inverse_branch` and `inverse_actuators` hold the solution's; returns as
        `forward`, then the roll and pitch [rad] of the task frame reached (`roll_pitch_of`; zeros
        after a failure).
        """
        if start_branch is not None:
            count = self.n_blocks + 1
            self.inverse_branch[:] = start_branch if len(start_branch) == count else b"\xff" * count
        (last_goal, last_rotation), last_q = previous if previous is not None else ((_EMPTY, None), _EMPTY)
        return self._module.inverse(
            self._handle,
            q,
            goal,
            self._identity if goal_rotation is None else goal_rotation,
            order,
            last_goal,
            self._identity if last_rotation is None else last_rotation,
            last_q,
            start_branch is not None,
            *rules,
        )

    def tangents(self, q: np.ndarray, singular_rcond: float) -> tuple[np.ndarray, np.ndarray]:
        """FK's tangents T = -J_passive^-1 J_actuated (m, P, A) at configurations q (m, nq) as given (not
        solved), and whether each is regular there (m,) bool: no zero pivot, a reciprocal condition of
        at least singular_rcond (the tangent of an irregular row is left unset)."""
        q = np.ascontiguousarray(q, dtype=float)
        tangents = np.zeros((len(q), *self.tangent.shape))
        regular = np.zeros(len(q), dtype=np.uint8)
        self._module.tangents(self._handle, q, tangents, regular, float(singular_rcond))
        return tangents, regular.astype(bool)

    def forward_rows(
        self, q: np.ndarray, start_branch: np.ndarray | None, steps_taken: int, rules: tuple, threads: int = 1
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """FK's Newton for every row of q (n, nq) (solved in place, no predictor) under `rules`
        (`NewtonRules.compiled()`), iterations counted from `steps_taken`, rows shared among
        `threads` threads (at least 64 rows each; the results do not depend on it). start_branch: the
        labels every row must end with (None: each row's at its start). Returns per row (status,
        max |row|, iterations, platform (n, 4, 4)); poses are valid where status is 0."""
        return self._rows(False, q, start_branch, _EMPTY, _EMPTY, steps_taken, rules, threads)

    def inverse_rows(
        self,
        q: np.ndarray,
        goals: np.ndarray,
        rotations: np.ndarray | None,
        start_branch: np.ndarray | None,
        steps_taken: int,
        rules: tuple,
        threads: int = 1,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """IK's Newton for every row of q (n, nq), row i toward goals[i] (task coordinates) and
        rotations[i] (3 x 3, a full-rotation task; None otherwise); as `forward_rows` otherwise, the
        labels being the blocks' then sign(det) of the whole system."""
        n = len(q)
        turns = np.broadcast_to(self._identity, (n, 3, 3)) if rotations is None else rotations
        return self._rows(
            True,
            q,
            start_branch,
            np.ascontiguousarray(goals, dtype=float),
            np.ascontiguousarray(turns, dtype=float),
            steps_taken,
            rules,
            threads,
        )

    def _rows(
        self,
        inverse: bool,
        q: np.ndarray,
        start_branch: np.ndarray | None,
        goals: np.ndarray,
        rotations: np.ndarray,
        steps_taken: int,
        rules: tuple,
        threads: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        n = len(q)
        status, norm, iterations = np.zeros(n, dtype=np.int64), np.zeros(n), np.zeros(n, dtype=np.int64)
        platform = np.zeros((n, 4, 4))
        branch = b"" if start_branch is None else np.asarray(start_branch, dtype=np.uint8).tobytes()
        self._module.rows(
            self._handle,
            inverse,
            q,
            branch,
            goals,
            rotations,
            int(steps_taken),
            status,
            norm,
            iterations,
            platform,
            *rules,
            int(threads),
        )
        return status, norm, iterations, platform


def status() -> str:
    """One line saying whether the solvers run the compiled Newton loop, and if not why (for
    `m3t1r --version`). Cheap: it reads what this module found at import and imports nothing."""
    if _native_newton is not None:
        return f"compiled Newton loop ({Path(str(_native_newton.__file__)).name})"
    chosen = f", as {PURE_PYTHON_VARIABLE} asks" if _pure_python_chosen() else ""
    return f"pure-Python Newton loop: the compiled one is {_WHY_NOT}{chosen} (4-6x slower; {_HOW_TO_BUILD})"


_HOW_TO_BUILD = "build it: make native, or reinstall with a C++ compiler, e.g. pip install --force-reinstall ."


def _pure_python_chosen() -> bool:
    return os.environ.get(PURE_PYTHON_VARIABLE, "").strip().lower() in ("1", "yes", "true", "on")


def _warn_once_without_module() -> None:
    """The first solver of a run without the compiled loop says so, unless the user chose it."""
    global _warned
    if _warned or _pure_python_chosen():
        return
    _warned = True
    warnings.warn(
        f"m3t1r: the compiled Newton loop is {_WHY_NOT}: the solvers run their pure-Python loop, "
        f"four to six times slower ({_HOW_TO_BUILD}; {PURE_PYTHON_VARIABLE}=1 silences this)",
        RuntimeWarning,
        stacklevel=4,
    )  # at the code that made the solver


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform tells, else the CPU count)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity is not None else (os.cpu_count() or 1)


def _axis(joint: pin.JointModel) -> np.ndarray:
    name = joint.shortname()
    if name.endswith("Unaligned"):
        axis = np.array(joint.extract().axis, dtype=float)
        return axis / np.linalg.norm(axis)
    return np.zeros(3)
