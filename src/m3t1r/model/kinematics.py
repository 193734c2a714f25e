"""Closed-loop kinematics of a `Mechanism`: closure residuals, their Jacobian, FK, IK, mobility.

Pinocchio computes the tree's placements and its WORLD-frame joint Jacobian; this module keeps
the closures satisfied by Newton's method on the enforced closure rows.

The closure rows and their Jacobian come from one place, `closures.ClosureSystem` (Pinocchio's
constraint models); calibration's row operator (each closure's derivative as a function of the
relative spatial twist of its frames) comes from there too. FK solves only the passive columns (a
square system when the sliders are independent inputs) by the one Python Newton (`model.newton`:
LU factors reused across chord steps until contraction slows). A warm-started solve (FK or IK)
starts from the last solution (`warm_start.WarmStart`) moved by a predictor built from the last
solve's factorisation: first order along the solution manifold, plus a second-order term from the
solution before it. Batches run the same Newton row by row (`solve_rows`). The same loops run
compiled on Pinocchio's C++ API when `model.native` is built (one call per solve, or per batch);
the Python ones are the reference. Branch labels: `model.branches`; the fixed bookkeeping:
`solver_layout.SolverLayout`.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import operator
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import pinocchio as pin
from scipy.linalg import blas, lapack

from m3t1r._lazy import lazy
from m3t1r.errors import (
    InvalidInputError,
    KinematicsError,
    OutOfWorkspaceError,
    require_count,
    require_finite_vector,
    require_real,
)
from m3t1r.model.batch_kinematics import SolvedRows, forward_batch, inverse_batch
from m3t1r.model.branches import BranchSignature, det_sign
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.description import Mechanism
from m3t1r.model.native import SLIDER_BEYOND_LIMIT, NativeChain
from m3t1r.model.newton import (
    CONVERGED,
    STATUS,
    Outcome,
    Signature,
    System,
    failure,
    inverse_and_rcond,
    newton,
    one_norm,
)
from m3t1r.model.newton_rules import DEFAULT_RULES, NewtonRules
from m3t1r.model.rotations import roll_pitch_of, yaw_of
from m3t1r.model.solver_layout import solver_layout
from m3t1r.model.warm_start import WarmStart

__all__ = [
    "ForwardResult",
    "InverseResult",
    "within_limits",
    "ClosedLoopSolver",
    "yaw_of",
    "roll_pitch_of",
    "rehomed",
    "require_square_task",
    "MOBILITY_RANK_TOL",
    "SINGULAR_RCOND",
    "MAX_TOLERANCE",
]

MOBILITY_RANK_TOL = 1e-9  # singular values below this fraction of the largest count as zero
SINGULAR_RCOND = DEFAULT_RULES.singular_rcond  # the default rules' singular threshold (`NewtonRules`)


_FLOAT = np.dtype(float)
_dasum = blas.dasum


class _PlacementViews:
    """`pose` and `task_pose` of a solve's result: its two 4 x 4 placements as pin.SE3, built on first use."""

    platform_placement: np.ndarray
    task_placement: np.ndarray

    @lazy
    def pose(self) -> pin.SE3:
        """The platform frame (reached) in the base frame."""
        return pin.SE3(self.platform_placement)

    @lazy
    def task_pose(self) -> pin.SE3:
        """The task frame (reached) in the base frame (`pose` itself when the task is on the platform frame)."""
        return self.pose if self.task_placement is self.platform_placement else pin.SE3(self.task_placement)


@dataclass(frozen=True)
class ForwardResult(_PlacementViews):
    """A converged forward-kinematics solve.

    q: full configuration (nq); residual: max |enforced closure row| at q [m or rad]; iterations:
    Newton steps taken; platform_placement: the platform frame in the base frame, 4 x 4 homogeneous
    [m]; task_placement: the task frame (`Mechanism.task.frame`, what IK and compensation command)
    in the base frame, the same array when the task is on the platform frame. `pose` and `task_pose`
    are those two as pin.SE3, built on first use. within_joint_limits: every coordinate of q within
    its URDF position limits (the sliders are; a passive hinge may be past its stop).
    """

    q: np.ndarray
    residual: float
    iterations: int
    platform_placement: np.ndarray
    task_placement: np.ndarray
    within_joint_limits: bool

    @property
    def yaw(self) -> float:
        return yaw_of(self.platform_placement)

    @property
    def roll_pitch(self) -> tuple[float, float]:
        return roll_pitch_of(self.platform_placement)


@dataclass(frozen=True)
class InverseResult(_PlacementViews):
    """A converged inverse-kinematics solve of position and yaw (a square system).

    actuators: slider values in `Mechanism.actuated_joints` order [m]; q: full configuration (nq);
    platform_placement: the platform frame reached, 4 x 4 homogeneous in the base frame [m];
    task_placement: the task frame reached, whose commanded components (M machine: position and yaw)
    equal the target's, roll and pitch being whatever the geometry gives (the same array when the
    task is on the platform frame); tilt: (roll, pitch) of the task frame reached minus those
    requested (zero when a 4-vector target was given) [rad]: the part of a 6D target that cannot be
    commanded. `pose` and `task_pose` are the two placements as pin.SE3, built on first use.
    within_joint_limits: every coordinate of q within its URDF position limits (the sliders always
    are: IK refuses a target that needs one beyond; a passive hinge may be past its stop).
    """

    actuators: np.ndarray
    q: np.ndarray
    residual: float
    iterations: int
    tilt: tuple[float, float]
    platform_placement: np.ndarray
    task_placement: np.ndarray
    within_joint_limits: bool


_Result = TypeVar("_Result", ForwardResult, InverseResult)


def _built(cls: type[_Result], fields: dict) -> _Result:
    """A frozen result from its fields without the dataclass __init__, which pays one object.__setattr__
    per field: about a microsecond of every warm solve (the fields are already checked and copied)."""
    result = object.__new__(cls)
    result.__dict__.update(fields)
    return result


#: The loosest Newton tolerance a solver accepts (max |closure row| [m, rad]): a micrometre, about
#: a tracker's noise; beyond it "solved" poses would be open loops.
MAX_TOLERANCE = 1e-6


def within_limits(lower: list[float], values: list[float], upper: list[float]) -> bool:
    """lower[k] <= values[k] <= upper[k] for every k (False where a value is NaN): comparisons mapped in C
    over Python floats, a fraction of numpy's cost, and of a generator's, at a few to a few tens of joints."""
    return all(map(operator.le, lower, values)) and all(map(operator.le, values, upper))


def _checked_tolerance(value: object) -> float:
    """A solver's tolerance [m, rad], in (0, MAX_TOLERANCE], else InvalidInputError."""
    tolerance = require_real(value, "ClosedLoopSolver tolerance", minimum=0.0, inclusive=False)
    if tolerance > MAX_TOLERANCE:
        raise InvalidInputError(
            f"ClosedLoopSolver tolerance {tolerance!r}: at most {MAX_TOLERANCE:g} (m, rad "
            "of closure residual); a looser one returns open loops as solutions"
        )
    return tolerance


def _checked_max_iterations(value: object) -> int:
    """A solver's Newton cap, a whole number >= 0 (0 checks the start alone: q_init is returned only
    if it already closes), else InvalidInputError."""
    return require_count(value, "ClosedLoopSolver max_iterations", minimum=0)


@functools.cache
def _products(k: int, power: int) -> np.ndarray:
    """The products of `power` of k sliders, each set once in increasing order (i <= j <= l): (m, power)."""
    return np.array(list(itertools.combinations_with_replacement(range(k), power)), dtype=int)


@functools.cache
def _monomial_steps(k: int, degree: int) -> tuple[tuple[int, int], ...]:
    """How each monomial of k sliders of degree 2 to `degree` (in `_products` order, after the k of
    degree 1) is one multiply: (row of the monomial of its first factors, its last slider)."""
    steps: list[tuple[int, int]] = []
    rows = {(i,): i for i in range(k)}
    for power in range(2, degree + 1):
        for axes in map(tuple, _products(k, power).tolist()):
            steps.append((rows[axes[:-1]], axes[-1]))
            rows[axes] = k + len(steps) - 1
    return tuple(steps)


class ClosedLoopSolver:
    """Newton solver for the closures of one `Mechanism` (keeps its own Pinocchio `Data`).

    tolerance: the largest closure row [m, rad] a solution may leave, in (0, MAX_TOLERANCE];
    max_iterations: Newton's cap, a whole number of at least 0. Other values raise InvalidInputError, given
    here or set later (the `tolerance` and `max_iterations` properties).

    native=True (the default): FK, IK and the batches run their Newton loops compiled
    (`m3t1r.model.native`) when the module is built and the joints allow, with the same steps and
    results as the Python loops that native=False runs (`self.native` is None then). Compiled solves
    do not move `data` to their solution. Not thread-safe: one solver per thread (a batch running in
    another thread makes single solves wait). All outputs are copies.

    branch_blocks: the diagonal blocks (closure rows, passive joint columns) of the passive closure
    Jacobian, in upper block-triangular order (`branches.diagonal_blocks`); branch labels: each
    block's determinant sign. layout: the fixed bookkeeping (`SolverLayout`) that batches and the
    compiled loop read too; warm: where the next solve continues from (`WarmStart`).
    """

    def __init__(
        self,
        mechanism: Mechanism,
        tolerance: float | None = None,
        max_iterations: int | None = None,
        native: bool = True,
        rules: NewtonRules | None = None,
    ) -> None:
        self.mechanism = mechanism
        self.model = mechanism.model
        self._closure_system = ClosureSystem(self.model, mechanism.closures)
        self.data = self._closure_system.data  # one Data: every evaluation leaves it at the q evaluated
        rules = DEFAULT_RULES if rules is None else rules
        if tolerance is not None:
            rules = dataclasses.replace(rules, tolerance=_checked_tolerance(tolerance))
        if max_iterations is not None:
            rules = dataclasses.replace(rules, max_iterations=_checked_max_iterations(max_iterations))
        self.rules = rules  # every Newton loop of this solver reads these, Python and compiled
        model = self.model
        # Every row of every closure, on the same Data (rank analysis, `closure_residual(all_rows=True)`).
        self._all_rows_system = ClosureSystem(model, mechanism.closures, all_rows=True, data=self.data)
        self.layout = layout = solver_layout(mechanism, self._closure_system)
        self.n_rows, self.passive, self.actuated = layout.n_rows, layout.passive, layout.actuated
        self.branch_blocks = layout.blocks
        self._branch = BranchSignature(layout.blocks, model.nv)
        self._limit_lists = (layout.actuator_lower.tolist(), layout.actuator_upper.tolist())
        self._joint_limit_lists = (model.lowerPositionLimit.tolist(), model.upperPositionLimit.tolist())
        # check_actuators' fast path: a float array of this shape, under finite limits (read once).
        self._fast_limits = layout.actuator_lower.shape if layout.finite_limits else None
        self._platform, self._task_frame = layout.platform_frame, layout.task_frame
        self._task_on_platform = layout.task_frame == layout.platform_frame
        self._target_name = f"target ({', '.join(mechanism.task.columns)})"  # in IK's input refusals
        self._square_task = mechanism.task.dimension == len(mechanism.actuated_joints)
        self._goal_shape = (len(mechanism.task.columns),)
        self._unknowns, self._unknown_columns = layout.unknowns, layout.unknown_columns
        # FK's and IK's Newton loops compiled (`model.native`), when built and the joints allow; None: the Python loops.
        self.native = NativeChain.of(model, mechanism.closures, layout, mechanism.task) if native else None
        self._home: tuple[np.ndarray, bytes] | None = None  # home's tangent and branch, once computed
        self._coefficients: dict[int, np.ndarray] = {}  # _moves_from_home's, by degree
        self.warm = WarmStart(mechanism.home.copy())  # where the next solve continues from (`reset`)
        self.reset()

    # One rule set, replaced whole: a solver's loops never see two versions of it.
    @property
    def rules(self) -> NewtonRules:
        """What every Newton loop of this solver obeys, Python and compiled (`NewtonRules`)."""
        return self._rules

    @rules.setter
    def rules(self, value: NewtonRules) -> None:
        # The compiled loop's argument tuple, built once per rule set rather than once per solve.
        self._rules, self._compiled_rules = value, value.compiled()

    @property
    def tolerance(self) -> float:
        """[m or rad] max |row| at convergence (`rules.tolerance`)."""
        return self.rules.tolerance

    @tolerance.setter
    def tolerance(self, value: float) -> None:
        self.rules = dataclasses.replace(self.rules, tolerance=_checked_tolerance(value))

    @property
    def max_iterations(self) -> int:
        """Newton steps allowed (`rules.max_iterations`)."""
        return self.rules.max_iterations

    @max_iterations.setter
    def max_iterations(self, value: int) -> None:
        self.rules = dataclasses.replace(self.rules, max_iterations=_checked_max_iterations(value))

    @property
    def singular_rcond(self) -> float:
        """Reciprocal condition below which a converged solve is singular (`rules.singular_rcond`)."""
        return self.rules.singular_rcond

    @singular_rcond.setter
    def singular_rcond(self, value: float) -> None:
        self.rules = dataclasses.replace(self.rules, singular_rcond=float(value))

    # ----------------------------------------------------------------------------------------
    # Residual and Jacobian
    def _system(self, q: np.ndarray, with_jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Enforced closure rows at q and, optionally, their exact Jacobian (rows x nv): the Newton
        loops' evaluation through Pinocchio's constraint models (`ClosureSystem`), about 10
        Python-level calls. Leaves `data` at q (joint placements, and the WORLD joint Jacobian when
        with_jacobian)."""
        return self._closure_system.evaluate(q, with_jacobian)

    def closure_residual(self, q: np.ndarray, all_rows: bool = False) -> np.ndarray:
        """Enforced closure rows at q (or every row of every closure) [m, rad]; leaves `data` at q with
        every frame placed."""
        q = require_finite_vector(q, self.model.nq, "configuration q")
        system = self._all_rows_system if all_rows else self._closure_system
        residual = system.evaluate(q, False)[0]
        pin.updateFramePlacements(self.model, self.data)
        return residual

    def closure_sensitivity(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(residual, Jacobian wrt q, row operator) of the enforced rows at q (`ClosureSystem.sensitivity`);
        leaves `data` at q (frames, joint placements and the WORLD joint Jacobian).

        Row r of closure c changes by operator[r] @ (xi_b - xi_a) for spatial (WORLD) twists
        xi of its two frames: that is how geometric-parameter sensitivities enter (calibration).
        """
        q = require_finite_vector(q, self.model.nq, "configuration q")
        return self._closure_system.sensitivity(q)

    def closure_operators(self, joint_placements: np.ndarray) -> np.ndarray:
        """The row operators of `closure_sensitivity` (N, rows, 6) at N configurations at once, from
        their joint placements oMi (N, njoints, 4, 4) (`ClosureSystem.operators`)."""
        return self._closure_system.operators(joint_placements)

    def closure_jacobian(self, q: np.ndarray, all_rows: bool = False) -> np.ndarray:
        """d(closure residual)/dq (rows x nv), exact (analytic), enforced rows unless all_rows; leaves
        `data` at q (joint placements and the WORLD joint Jacobian)."""
        q = require_finite_vector(q, self.model.nq, "configuration q")
        system = self._all_rows_system if all_rows else self._closure_system
        return system.evaluate(q, True)[1]

    def mobility(self, q: np.ndarray, all_rows: bool = False, rank_tolerance: float = MOBILITY_RANK_TOL) -> int:
        """nv minus the rank of the closure Jacobian at q.

        Rank counts singular values above rank_tolerance times the largest (default 1e-9). With
        all_rows=True the redundant rows are included: at the nominal geometry they are linear
        combinations of the enforced ones and the mobility is the same.
        """
        singular = np.linalg.svd(self.closure_jacobian(q, all_rows), compute_uv=False)
        return self.model.nv - int(np.sum(singular > rank_tolerance * singular[0]))

    # ----------------------------------------------------------------------------------------
    # Forward kinematics
    def check_actuators(self, actuators: np.ndarray) -> np.ndarray:
        """Validate slider values [m]: finite, right count, within the URDF limits (no clipping)."""
        if type(actuators) is np.ndarray and actuators.dtype == _FLOAT and actuators.shape == self._fast_limits:
            values = actuators.copy()
            if within_limits(self._limit_lists[0], values.tolist(), self._limit_lists[1]):
                return values
        values = require_finite_vector(actuators, len(self.actuated), "actuator values")
        names, (lower, upper) = self.mechanism.actuated_joints, self._limit_lists
        outside = (values < self.layout.actuator_lower) | (values > self.layout.actuator_upper)
        for k in np.flatnonzero(outside) if outside.any() else ():
            raise InvalidInputError(
                f"actuator '{names[k]}' = {values[k]:.6g} is beyond its joint limit "
                f"[{lower[k]:.6g}, {upper[k]:.6g}] (SI units: metres for sliders)"
            )
        return values

    def forward(self, actuators: np.ndarray, q_init: np.ndarray | None = None) -> ForwardResult:
        """Platform pose for the given slider values, on the assembly mode of the start.

        A continuation from the start, q_init or by default this solver's last solution (initially
        home, and again after `reset`): the start moved along its tangent to the slider change (plus
        a second-order term along the last step when warm), then Newton on the enforced closure rows
        over the passive joints only (sliders locked), J_c,passive dq_passive = -r_c. The solution
        must carry the start's branch labels (a new solver's first solve: home's, as `forward_batch`'s rows,
        which start from home's third-order prediction instead and agree with it to the tolerance).
        Raises InvalidInputError for bad actuators, BranchChangeError / NotConvergedError /
        OutOfWorkspaceError / SingularConfigurationError (with the final residual) otherwise.
        """
        warm, native = self.warm, self.native
        # A warm solve of a float array under finite limits: the compiled loop checks its sliders itself
        # (the refusal is still check_actuators').
        compiled_check = (
            native is not None
            and q_init is None
            and type(actuators) is np.ndarray
            and actuators.dtype == _FLOAT
            and actuators.shape == self._fast_limits
        )
        values = actuators if compiled_check else self.check_actuators(actuators)
        if q_init is None:  # a continuation from the last solution (initially home)
            q, tangent, branch, previous = warm.q.copy(), warm.tangent, warm.branch, warm.previous
        else:  # a continuation from q_init: its own tangent and branch
            q = require_finite_vector(q_init, self.model.nq, "q_init").copy()
            (tangent, branch), previous = self._continuation_from(q), None
        if native is not None:
            return self._forward_native(q, values, tangent is not None, previous, branch)
        warm.tangent = warm.previous = warm.goal = warm.inverse_previous = None  # until this succeeds
        start = q.copy()
        if tangent is not None:
            q[self.passive] += self.predict(start, values - q.take(self.actuated), tangent, previous)
        q[self.actuated] = values
        outcome = self.newton(q, self.passive, self._system, self._passive_branch, start_branch=branch)
        warm.tangent = -outcome.inverse.dot(outcome.jacobian.take(self.actuated, axis=1))
        # Where this solve continued from, for the second-order predictor of the next one.
        warm.previous = (start.take(self.actuated), start.take(self.passive))
        warm.branch, warm.q = outcome.branch, outcome.q
        platform, task = self._placements()
        within = self._within_joint_limits(outcome.q)
        return ForwardResult(outcome.q.copy(), outcome.residual, outcome.iterations, platform, task, within)

    def _within_joint_limits(self, q: np.ndarray) -> bool:
        """Every coordinate of q within its URDF limits: the Python loops' `within_joint_limits` (the
        compiled loop's check, `first_beyond_limits`, gives the same)."""
        return within_limits(self._joint_limit_lists[0], q.tolist(), self._joint_limit_lists[1])

    def _forward_native(
        self, q: np.ndarray, values: np.ndarray, predicted: bool, previous, branch: bytes | None
    ) -> ForwardResult:
        """`forward` in the compiled loop, predictor included (q: the start, solved in place; its tangent in
        `native.tangent`; values: float sliders, checked here when `forward` did not); the same bookkeeping,
        errors and result as the Python loop. `data` is not moved to the solution."""
        native, warm = self.native, self.warm
        assert native is not None, "called only with the compiled loop"
        order = (1 if previous is None else 2) if predicted else 0
        status, norm, iterations, rcond, beyond = native.forward(
            q, values, order, previous if order == 2 else None, branch, self._compiled_rules
        )
        if status == SLIDER_BEYOND_LIMIT:  # nothing solved: the warm start stays as it was
            self.check_actuators(values)  # raises InvalidInputError naming the slider
            raise InvalidInputError(f"actuator values {values.tolist()} beyond their joint limits")
        warm.goal = warm.inverse_previous = None  # this FK ends any IK path
        if status != CONVERGED:
            warm.tangent = warm.previous = None
            raise failure(status, norm, iterations, rcond)
        # The tangent and where this solve started (the next one's second-order history) stay in the
        # compiled call's arrays, overwritten only by the next success, which reads them first.
        warm.tangent, warm.previous = native.tangent, native.history
        warm.branch, warm.q = bytes(native.branch), q
        platform = native.platform.copy()
        fields = {
            "q": q.copy(),
            "residual": norm,
            "iterations": iterations,
            "platform_placement": platform,
            "task_placement": platform if self._task_on_platform else native.task.copy(),
            "within_joint_limits": beyond < 0,
        }
        return _built(ForwardResult, fields)

    def home_reference(self) -> tuple[np.ndarray, bytes] | None:
        """(T, branch) at home: T = -J_passive^-1 J_actuated (passive x actuated), d q_passive / d a,
        and home's branch labels, which define the assembly mode every solve from home keeps (None
        when home is singular). Single, fresh, reset and batch solves take their first step from these."""
        if self._home is None:
            self._home = self._reference(self.mechanism.home)
        return self._home

    def home_derivatives(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(H, G): the second and third derivatives of home's solution manifold q_passive(a),
        H[p, i, j] = d^2 q_p / da_i da_j and G[p, i, j, l] = d^3 q_p / da_i da_j da_l [rad or m per
        slider unit squared, cubed], by central differences along the manifold's first-order curves,
        no solve needed: D(f)(q)[..., j] = (f(q + h t_j) - f(q - h t_j)) / 2h with t_j = (e_j on the
        sliders, T(q) e_j on the passive joints), T the tangent (`home_reference`); H = D(T)(home) with
        h = 1e-4, G = D(D(T))(home) with an outer h = 1e-3. Each pair of points is off the manifold by
        the same O(h^2), which its difference cancels. None when home or one of the points is singular
        (batches from home then predict to first order)."""
        if self._derivatives is None:
            self._derivatives = (self._derivatives_at_home(),)
        return self._derivatives[0]

    _derivatives: tuple[tuple[np.ndarray, np.ndarray] | None] | None = None

    def _derivatives_at_home(self, inner: float = 1e-4, outer: float = 1e-3) -> tuple[np.ndarray, np.ndarray] | None:
        """`home_derivatives` computed from the tangents at 2k + 2k points around home, then at 2k points
        around each of the outer 2k (81 tangents for four sliders, in two calls of `_tangents_at`)."""
        reference = self.home_reference()
        if reference is None:
            return None
        home, k2 = self.mechanism.home, 2 * len(self.actuated)
        around = self._tangent_points(home, reference[0], inner) + self._tangent_points(home, reference[0], outer)
        first = self._tangents_at(around)
        if first is None:
            return None
        points = [
            p for point, tangent in zip(around[k2:], first[k2:]) for p in self._tangent_points(point, tangent, inner)
        ]
        second = self._tangents_at(points)
        if second is None:
            return None
        moved = [self._central_differences(second[k2 * i : k2 * (i + 1)], inner) for i in range(k2)]
        return self._central_differences(first[:k2], inner), self._central_differences(moved, outer)

    def _tangents_at(self, points: list[np.ndarray]) -> np.ndarray | None:
        """T = -J_passive^-1 J_actuated (m, passive, actuated) at each point as given (not solved), or None
        if the passive system is singular at one (its reciprocal condition below the threshold)."""
        if self.native is not None:
            tangents, regular = self.native.tangents(np.array(points), self.rules.singular_rcond)
            return tangents if regular.all() else None
        references = [self._reference(point) for point in points]
        known = [r[0] for r in references if r is not None]
        return np.array(known) if len(known) == len(points) else None

    def _tangent_points(self, q: np.ndarray, tangent: np.ndarray, h: float) -> list[np.ndarray]:
        """q + h t_j and q - h t_j for each slider j, in that order, t_j = (e_j, tangent e_j)."""
        points = []
        for j in range(len(self.actuated)):
            for sign in (1.0, -1.0):
                moved = q.copy()
                moved[self.actuated[j]] += sign * h
                moved[self.passive] += sign * h * tangent[:, j]
                points.append(moved)
        return points

    def _central_differences(self, values: Sequence[np.ndarray] | np.ndarray, h: float) -> np.ndarray:
        """(values[2 j] - values[2 j + 1]) / 2h for each slider j, along a new last axis."""
        return np.stack([(values[2 * j] - values[2 * j + 1]) / (2.0 * h) for j in range(len(self.actuated))], -1)

    def predict_from_home(self, changes: np.ndarray, order: int = 3) -> np.ndarray:
        """Passive-joint changes (n, passive) [rad or m] from home for slider changes d (n, k) from home's
        sliders, along home's solution manifold to `order` (1, 2 or 3): T d + 1/2 H[d, d] +
        1/6 G[d, d, d] (`home_reference`, `home_derivatives`; first order where those are unknown):
        one product of d's monomials up to `order`, each product of sliders once (H and G are
        symmetric), with their coefficients."""
        return self._moves_from_home(changes, order)[:, self.passive]

    def starts_from_home(self, sliders: np.ndarray, order: int = 3) -> np.ndarray:
        """The starts (n, nq) of batch rows from home for slider values (n, k) [m]: home with the
        sliders set and the passive joints moved by `predict_from_home` to `order`."""
        home = self.mechanism.home
        starts = self._moves_from_home(sliders - home[self.actuated], order)
        starts += home
        starts[:, self.actuated] = sliders
        return starts

    def _moves_from_home(self, changes: np.ndarray, order: int) -> np.ndarray:
        """`predict_from_home`'s changes in every column of q (n, nq), zero outside the passive joints."""
        degree = 1 if order < 2 or self.home_derivatives() is None else min(order, 3)
        coefficients = self._prediction_coefficients(degree)
        k = changes.shape[1]
        # Monomials as rows, each one multiply of two contiguous rows: gathering columns of the (n, k)
        # changes cost eight times as much on 2,000 rows.
        monomials = np.empty((len(coefficients), len(changes)))
        monomials[:k] = changes.T
        for row, (lower, slider) in enumerate(_monomial_steps(k, degree), start=k):
            np.multiply(monomials[lower], monomials[slider], out=monomials[row])
        return monomials.T.dot(coefficients)

    def _prediction_coefficients(self, degree: int) -> np.ndarray:
        """`_moves_from_home`'s coefficients (monomials x nq, zero outside the passive columns) to
        `degree`: T's transpose, then H / 2! and G / 3! at each product of sliders i <= j (<= l)
        times its count of orderings."""
        if degree not in self._coefficients:
            reference, derivatives = self.home_reference(), self.home_derivatives()
            assert reference is not None, "asked only where home is regular"
            rows = [reference[0].T]
            for power, tensor in zip(range(2, degree + 1), derivatives or ()):
                for axes in _products(len(self.actuated), power):
                    orderings = math.factorial(power) // math.prod(math.factorial(c) for c in Counter(axes).values())
                    rows.append(orderings / math.factorial(power) * tensor[(slice(None),) + tuple(axes)][None, :])
            passive = np.vstack(rows)
            coefficients = np.zeros((len(passive), self.model.nq))
            coefficients[:, self.passive] = passive
            self._coefficients[degree] = coefficients
        return self._coefficients[degree]

    def _reference(self, q: np.ndarray) -> tuple[np.ndarray, bytes] | None:
        """(tangent, branch labels) of the passive closure system at q, or None where it is singular."""
        _, jac = self._system(q, True)
        assert jac is not None, "asked with_jacobian"
        square = jac.take(self.passive, axis=1)
        lu = lapack.dgetrf(square)[:2]
        inverse, rcond = inverse_and_rcond(lu, one_norm(square))
        if not rcond >= self.rules.singular_rcond:
            return None
        return -inverse.dot(jac.take(self.actuated, axis=1)), self._branch(jac)

    def _continuation_from(self, q: np.ndarray) -> tuple[np.ndarray | None, bytes | None]:
        """The FK warm-start state (`warm.tangent`, `warm.branch`) of a solve continuing from q: home's cached
        reference at home, q's own elsewhere; (None, None) at a singular q (labels then at the start).
        The compiled loop reads its tangent from `native.tangent`, which this fills."""
        home = self.mechanism.home
        reference = self.home_reference() if q is home or np.array_equal(q, home) else self._reference(q)
        if reference is None:
            return None, None
        tangent, branch = reference
        if self.native is None:
            return tangent.copy(), branch
        self.native.tangent[:] = tangent
        return self.native.tangent, branch

    def predict(self, start: np.ndarray, change: np.ndarray, tangent: np.ndarray, previous) -> np.ndarray:
        """Passive-joint change [rad or m] for a slider change `change` [m] from `start` (the last
        solution, or q_init), along `tangent` (the start's) and `previous` (sliders, passive q) of the
        solution before the start (None: first order only).

        First order: T d, T = -J_pas^-1 J_act the tangent of the solution manifold. Second order along
        the previous step e (sliders s_k - s_(k-1)): the previous solution gives
        1/2 H[e, e] ~= q_(k-1) - q_k + T e, applied as lam^2 1/2 H[e, e] with lam = (d . e) / (e . e),
        only while the path keeps going the same way (0 < lam < 2). Newton corrects whatever remains.
        """
        step = tangent.dot(change)
        if previous is not None:
            last_sliders, last_passive = previous
            e = start.take(self.actuated) - last_sliders
            ee = float(e.dot(e))
            lam = float(change.dot(e)) / ee if ee > 0.0 else 0.0
            if 0.0 < lam < 2.0:
                step += lam * lam * (last_passive - start.take(self.passive) + tangent.dot(e))
        return step

    def _passive_branch(self, jac: np.ndarray, lu: tuple) -> bytes:
        """FK's branch labels: the passive blocks' determinant signs."""
        return self._branch(jac)

    def _inverse_branch(self, jac: np.ndarray, lu: tuple) -> bytes:
        """IK's branch labels: the passive blocks', then the sign of det of the whole system."""
        return self._branch(jac) + bytes([det_sign(lu)])

    def _placements(self) -> tuple[np.ndarray, np.ndarray]:
        """(platform, task frame) 4 x 4 [m] at the configuration last evaluated (copies), the task one the
        platform's array itself when they are one frame."""
        platform = self._platform_pose().homogeneous
        if self._task_frame == self._platform:
            return platform, platform
        return platform, pin.updateFramePlacement(self.model, self.data, self._task_frame).homogeneous

    def _platform_pose(self) -> pin.SE3:
        """The platform frame at the configuration last evaluated: a copy (the binding returns
        `updateFramePlacement`'s placement by value), so the solver's data may move on."""
        return pin.updateFramePlacement(self.model, self.data, self._platform)

    def newton(
        self, q: np.ndarray, unknowns: np.ndarray | None, system: System, signature: Signature, start_branch=None
    ) -> Outcome:
        """`newton.newton` under `self.rules`: the one Python Newton of single solves and batch rows."""
        return newton(q, unknowns, system, signature, self.rules, start_branch)

    # ----------------------------------------------------------------------------------------
    # Inverse kinematics
    def check_square_task(self) -> None:
        """Raise InvalidInputError unless the task commands as many coordinates as there are actuators,
        each of which the mechanism can move (`uncommandable_task_rows`)."""
        require_square_task(self.mechanism)
        self._require_commandable_task()

    def uncommandable_task_rows(self) -> tuple[str, ...]:
        """Task rows (x, y, z, theta, or rx, ry, rz for a full rotation) that no motion the closures
        allow changes, at home and near it: e.g. x for a five-bar that moves in the
        y-z plane. An IK system with such a row is singular wherever it converges: not a singularity
        of the mechanism but a task it cannot command. A row counts as unmoved when its rate along
        every unit closure-compatible motion is below 1e-9 of the largest task row's (near home: 1e-3
        along home's tangent, no solve)."""
        if self._uncommandable is None:
            home, reference = self.mechanism.home, self.home_reference()
            configurations = [home]
            for sign in (1.0, -1.0) if reference is not None else ():
                # Near home along its solution manifold (first order: within 1e-6 of an assembly).
                change = sign * 1e-3 * np.linspace(1.0, 0.5, len(self.actuated))
                q = home.copy()
                q[self.actuated] += change
                assert reference is not None, "the loop runs only with it"
                q[self.passive] += reference[0].dot(change)
                configurations.append(q)
            unmoved = None
            for q in configurations:
                rows = self._unmoved_task_rows(q)
                unmoved = rows if unmoved is None else unmoved & rows
            assert unmoved is not None, "configurations holds home"
            task = self.mechanism.task
            names = task.position + {"none": (), "yaw": ("theta",), "full": ("rx", "ry", "rz")}[task.rotation]
            self._uncommandable = tuple(name for name, dead in zip(names, unmoved) if dead)
        return self._uncommandable

    _uncommandable: tuple[str, ...] | None = None

    def _unmoved_task_rows(self, q: np.ndarray) -> np.ndarray:
        """Mask of the task rows whose rate along every unit closure-compatible motion at q (the null
        space of the closure rows over IK's unknowns) is below 1e-9 of the largest row's."""
        self._system(q, False)
        placement = pin.updateFramePlacement(self.model, self.data, self._task_frame)
        jac = self._inverse_system(np.zeros(len(self.mechanism.task.columns)), placement.rotation)(q, True)[1]
        jac = jac[:, self._unknown_columns]
        closure, task = jac[: self.n_rows], jac[self.n_rows :]
        singular, vt = np.linalg.svd(closure)[1:]
        rank = int(np.sum(singular > max(closure.shape) * np.finfo(float).eps * singular[0])) if len(singular) else 0
        rates = np.linalg.norm(task @ vt[rank:].T, axis=1)
        return rates <= 1e-9 * max(float(rates.max(initial=0.0)), 1e-300)

    def _require_commandable_task(self) -> None:
        unmoved = self.uncommandable_task_rows()
        if unmoved:
            task = self.mechanism.task
            raise InvalidInputError(
                f"{self.mechanism.closures_path}: the task's {', '.join(unmoved)} (frame '{task.frame}') cannot be "
                "commanded: no motion the closures allow changes it (at home and near it), so inverse kinematics "
                "would be singular at every target; declare a task of coordinates the mechanism moves "
                "(models/README.md)"
            )

    def inverse(self, target: pin.SE3 | np.ndarray, q_init: np.ndarray | None = None) -> InverseResult:
        """Actuator values that put the task frame at the target (the mechanism's `task`).

        target: a pin.SE3 (its uncommanded components are ignored) or the task coordinates
        (`TaskSpec.columns`: e.g. (x, y, z, theta) [m, m, m, rad] for the M machine, (x, y) for a
        planar five-bar, (qx, qy, qz, qw) for an orientation mechanism). Solves the square system
        [closure rows; task rows] = 0 over every joint but the locked ones, from q_init (default:
        this solver's last solution). Uncommanded roll and pitch are reported in `tilt`. Raises
        InvalidInputError when the task is not square, OutOfWorkspaceError when no assembly reaches
        the target or an actuator would leave its limits (never clipped).
        """
        if not self._square_task or self._uncommandable != ():
            self.check_square_task()
        goal, goal_rotation, wanted_tilt = self._goal(target)
        continuing, state = q_init is None, self.warm
        q = (state.q if continuing else require_finite_vector(q_init, self.model.nq, "q_init")).copy()
        predicted = continuing and state.task_inverse is not None and state.task is not None
        if self.native is not None:
            order = (1 if state.inverse_previous is None else 2) if predicted else 0
            return self._inverse_native(q, goal, goal_rotation, wanted_tilt, order, continuing)
        if predicted:
            assert state.task_inverse is not None and state.task is not None, "as `predicted` says"
            q[self._unknown_columns] += self.inverse_predict(
                goal, goal_rotation, state.task_inverse, state.task, state.inverse_previous
            )
        # A warm solve must stay on the previous solution's branch (assembly and working mode).
        start = state.inverse_branch if continuing else None
        state.task_inverse = state.inverse_branch = None  # dropped until this solve succeeds
        outcome = self.newton(
            q,
            self._unknowns,
            self._inverse_system(goal, goal_rotation),
            self._inverse_branch,
            start_branch=start,
        )
        q, residual, iterations, branch = outcome.q, outcome.residual, outcome.iterations, outcome.branch
        actuators = q.take(self.actuated)
        self._check_reached_actuators(actuators, residual, iterations)
        last_task = pin.updateFramePlacement(self.model, self.data, self._task_frame)  # a copy
        platform, task = self._placements()
        roll, pitch = roll_pitch_of(task)
        self._keep_inverse_solution(continuing, q, branch, outcome.inverse[:, self.n_rows :], (goal, goal_rotation))
        state.task = last_task
        tilt = (roll - wanted_tilt[0], pitch - wanted_tilt[1])
        within = self._within_joint_limits(q)
        return InverseResult(actuators, q.copy(), residual, iterations, tilt, platform, task, within)

    def _inverse_native(
        self,
        q: np.ndarray,
        goal: np.ndarray,
        goal_rotation: np.ndarray | None,
        wanted_tilt: tuple[float, float],
        order: int,
        continuing: bool,
    ) -> InverseResult:
        """`inverse` in the compiled loop, predictor of the given order included (q: the start, solved in
        place); the same checks, bookkeeping, errors and result as the Python loop. The warm start's task
        inverse and task frame stay in the compiled call's buffers, which the next warm solve reads; `data`
        is not moved to the solution."""
        native, state = self.native, self.warm
        assert native is not None, "called only with the compiled loop"
        # A warm solve must stay on the previous solution's branch (assembly and working mode).
        start = state.inverse_branch if continuing else None
        state.task_inverse = state.inverse_branch = None  # dropped until this solve succeeds
        status, residual, iterations, rcond, beyond, roll, pitch = native.inverse(
            q, goal, goal_rotation, order, state.inverse_previous, start, self._compiled_rules
        )
        if status != CONVERGED:
            raise failure(status, residual, iterations, rcond)
        actuators = native.inverse_actuators.copy()
        if beyond >= 0:  # a joint beyond its limit: refused if it is an actuator
            self._check_reached_actuators(actuators, residual, iterations)  # names the actuator
        task = native.inverse_task  # its roll and pitch came with the result (`roll_pitch_of`'s)
        self._keep_inverse_solution(
            continuing, q, bytes(native.inverse_branch), native.task_inverse, (goal, goal_rotation)
        )
        state.task = task
        platform = native.inverse_platform.copy()
        fields = {
            "actuators": actuators,
            "q": q.copy(),
            "residual": residual,
            "iterations": iterations,
            "tilt": (roll - wanted_tilt[0], pitch - wanted_tilt[1]),
            "platform_placement": platform,
            "task_placement": platform if self._task_on_platform else task.copy(),
            "within_joint_limits": beyond < 0,
        }
        return _built(InverseResult, fields)

    def _check_reached_actuators(self, actuators: np.ndarray, residual: float, iterations: int) -> None:
        """OutOfWorkspaceError naming the first actuator [m or rad] an IK solution puts beyond its limit."""
        lower, upper = self._limit_lists
        values = actuators.tolist()
        if within_limits(lower, values, upper):
            return
        names = self.mechanism.actuated_joints
        for k, value in enumerate(values):
            if not lower[k] <= value <= upper[k]:
                raise OutOfWorkspaceError(
                    f"target needs actuator '{names[k]}' = {actuators[k]:.6g} {self.mechanism.joint_units()[k]}, "
                    f"beyond its limit [{lower[k]:.6g}, {upper[k]:.6g}]",
                    residual,
                    iterations,
                )

    def _keep_inverse_solution(
        self, continuing: bool, q: np.ndarray, branch: bytes, task_inverse: np.ndarray, goal: tuple
    ) -> None:
        """The warm start after an IK success at q (its labels `branch`, the task columns of its inverse,
        its (goal, goal rotation)); the caller sets `task`."""
        state = self.warm
        # The second-order predictor's history: the solution this one started from, with its goal.
        state.inverse_previous = (state.goal, state.q) if continuing and state.goal is not None else None
        # The FK warm start now follows this solution; its predictor tangent is from elsewhere.
        state.q, state.tangent, state.branch, state.previous = q, None, branch[:-1], None
        state.task_inverse, state.inverse_branch, state.goal = task_inverse, branch, goal

    def _goal(self, target: pin.SE3 | np.ndarray) -> tuple[np.ndarray, np.ndarray | None, tuple[float, float]]:
        """(task goal, goal rotation for a full-rotation task else None, requested (roll, pitch))."""
        task = self.mechanism.task
        if (
            type(target) is np.ndarray
            and target.dtype == _FLOAT
            and target.shape == self._goal_shape
            and task.rotation != "full"
        ):
            goal = target.copy()  # kept for the next warm solve
            total = _dasum(goal)
            if total - total == 0.0:  # every entry finite (else the checks below name the bad one)
                return goal, None, (0.0, 0.0)
        if isinstance(target, pin.SE3):
            if not (np.all(np.isfinite(target.homogeneous))):
                raise InvalidInputError("target pose: non-finite value")
            goal = task.coordinates(target.homogeneous)[0]
            wanted_tilt = roll_pitch_of(target.rotation)
        else:
            vector = require_finite_vector(target, len(task.columns), self._target_name)
            # Only a quaternion goal has more to check (its norm) and to do (renormalise). A copy:
            # the goal is kept for the next warm solve, and `vector` may be the caller's array.
            goal = task.goals(vector)[0] if task.rotation == "full" else vector.copy()
            wanted_tilt = (0.0, 0.0)
        goal_rotations = task.target_rotations(goal[None, :])
        goal_rotation = None if goal_rotations is None else goal_rotations[0]
        if goal_rotation is not None and not isinstance(target, pin.SE3):
            wanted_tilt = roll_pitch_of(goal_rotation)
        return goal, goal_rotation, wanted_tilt

    def inverse_predict(
        self,
        goal: np.ndarray,
        goal_rotation: np.ndarray | None,
        task_inverse: np.ndarray,
        last_task: pin.SE3,
        previous: tuple | None,
    ) -> np.ndarray:
        """Change of the unknown joints [rad or m] from the last IK solution (`last_q`) toward a new goal.

        First order: -X [0; r], X the inverse of the last IK system (at its last Jacobian; `task_inverse`
        its task-row columns), r the task rows of the new goal at the last task pose reached, `last_task`
        (the closure rows vanish there). Second order as FK's `predict`, along the previous goal change
        (`previous`: ((goal, goal rotation), q) of the IK solution before last_q; None: first order only):
        the task rows b of the previous goal at the last pose give 1/2 H[e, e] ~= q_(k-1) - q_k + X [0; b],
        applied as lam^2 1/2 H[e, e] with lam = -(r . b) / (b . b), only while the path keeps going the same
        way (0 < lam < 2).
        """
        task = self.mechanism.task
        rows = task.residual(last_task, goal, goal_rotation)
        step = -task_inverse.dot(rows)
        if previous is not None:
            (last_goal, last_rotation), last_q = previous
            back = task.residual(last_task, last_goal, last_rotation)
            bb = float(back.dot(back))
            lam = -float(rows.dot(back)) / bb if bb > 0.0 else 0.0
            if 0.0 < lam < 2.0:
                columns = self._unknown_columns
                step += lam * lam * (last_q[columns] - self.warm.q[columns] + task_inverse.dot(back))
        return step

    def _inverse_system(self, goal: np.ndarray, goal_rotation: np.ndarray | None):
        """IK's square system for `newton`: (q, with_jacobian) -> ([closure rows; task rows], Jacobian)."""
        model, data, frame, task = self.model, self.data, self._task_frame, self.mechanism.task

        def system(qk: np.ndarray, with_jacobian: bool):
            closure, jac = self._system(qk, with_jacobian)
            placement = pin.updateFramePlacement(model, data, frame)
            residual = np.concatenate((closure, task.residual(placement, goal, goal_rotation)))
            if not with_jacobian:
                return residual, None
            assert jac is not None, "asked with_jacobian"
            frame_jac = pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED)
            return residual, np.concatenate((jac, task.jacobian(placement, frame_jac, goal_rotation)))

        return system

    # ----------------------------------------------------------------------------------------
    # Many poses at once
    def forward_batch(self, actuators: np.ndarray, q_init: np.ndarray | None = None, threads: int | None = None):
        """Forward kinematics of n slider sets (n, k) [m] at once (`batch_kinematics.forward_batch`).

        Every row is solved on home's branch (the reference), from home moved along the solution
        manifold to third order, or from q_init when given, by `solve_rows`. Where
        `forward(a, q_init=home)` converges the two agree to the tolerance; far from home the batch
        also assembles rows where plain Newton from home crosses a singularity. Returns a `ForwardBatch`: `.poses`
        (M, 4, 4), `.q`, `.iterations` of the M converged rows `.indices`; every other row is in
        `.failures` with its typed error class (never in the arrays). Leaves this solver's warm start alone.
        With the compiled loop the rows are shared among `threads` threads (None: every core this
        process may use); the results do not depend on it.
        """
        return forward_batch(self, actuators, q_init, threads)

    def inverse_batch(self, targets: np.ndarray, q_init: np.ndarray | None = None, threads: int | None = None):
        """Inverse kinematics of n targets (n, 4) rows (x, y, z, theta) [m, rad] at once; returns an
        `InverseBatch` (`.actuators`, `.poses`, `.tilt`, ... of the converged rows, `.failures`).
        Compiled loop and threads as `forward_batch`."""
        return inverse_batch(self, targets, q_init, threads)

    def solve_rows(
        self,
        starts: np.ndarray,
        branch: bytes | None,
        steps_taken: int,
        goals: np.ndarray | None = None,
        goal_rotations: np.ndarray | None = None,
        threads: int = 1,
    ) -> SolvedRows:
        """Newton from every row of `starts` (n, nq), solved in place: FK's passive system (goals None)
        or IK's toward goals[i] (task coordinates; goal_rotations[i] for a full-rotation task).

        The compiled loop takes every row in one call, shared among `threads`; without it the
        single solves' `newton` runs row after row. branch: the labels every row must end with
        (None: each row's at its start); steps_taken: iterations already spent (a predictor), counted.
        Status codes as `NativeChain`: 0 converged, 1 no assembly, 2 not converged, 3 singular,
        4 branch change. Moves `data` (the Python loop) but not the warm start.
        """
        if self.native is not None:
            labels = None if branch is None else np.frombuffer(branch, dtype=np.uint8)
            rules = self._compiled_rules
            if goals is None:
                status, norm, iterations, platform = self.native.forward_rows(
                    starts, labels, steps_taken, rules, threads
                )
            else:
                status, norm, iterations, platform = self.native.inverse_rows(
                    starts, goals, goal_rotations, labels, steps_taken, rules, threads
                )
            return SolvedRows(starts, status, norm, iterations, platform)
        return self._python_rows(starts, branch, steps_taken, goals, goal_rotations)

    def _python_rows(
        self,
        q: np.ndarray,
        branch: bytes | None,
        steps_taken: int,
        goals: np.ndarray | None,
        goal_rotations: np.ndarray | None,
    ) -> SolvedRows:
        """`solve_rows` without the compiled loop: `newton` on each row, its typed failure as a status."""
        n = len(q)
        solved = SolvedRows(q, np.zeros(n, dtype=int), np.zeros(n), np.zeros(n, dtype=int), np.zeros((n, 4, 4)))
        for i in range(n):
            unknowns: np.ndarray | None = self.passive
            if goals is None:
                system, signature = self._system, self._passive_branch
            else:
                goal_rotation = None if goal_rotations is None else goal_rotations[i]
                system, unknowns = self._inverse_system(goals[i], goal_rotation), self._unknowns
                signature = self._inverse_branch
            try:
                outcome = self.newton(q[i], unknowns, system, signature, start_branch=branch)
            except KinematicsError as error:
                solved.status[i], solved.norm[i] = STATUS[type(error)], error.residual
                solved.iterations[i] = error.iterations + steps_taken
                continue
            solved.norm[i], solved.iterations[i] = outcome.residual, outcome.iterations + steps_taken
            solved.platform[i] = self._platform_pose().homogeneous
        return solved

    @property
    def last_q(self) -> np.ndarray:
        """The last solution (nq) [m, rad], where a warm solve starts (home after `reset`)."""
        return self.warm.q

    def reset(self) -> None:
        """Forget the warm start and cached factorisations: the next solve starts from home, as a new
        solver's first and as every row of `forward_batch` (home's tangent predictor, home's branch)."""
        tangent, branch = self._continuation_from(self.mechanism.home)
        self.warm = WarmStart(self.mechanism.home.copy(), tangent, branch)


def require_square_task(mechanism: Mechanism) -> None:
    """Raise InvalidInputError unless the mechanism's task commands as many coordinates as it has
    actuators (what inverse kinematics needs; nothing else does)."""
    task, count = mechanism.task, len(mechanism.actuated_joints)
    if task.dimension != count:
        raise InvalidInputError(
            f"{mechanism.closures_path}: inverse kinematics needs as many task coordinates as actuators; "
            f"the task ({', '.join(task.columns)} of frame '{task.frame}') commands {task.dimension} for "
            f"{count} actuators (declare the task in the closures file: models/README.md)"
        )


def rehomed(mechanism: Mechanism, sliders: np.ndarray | None = None) -> Mechanism:
    """The mechanism with `home` re-assembled at `sliders` (default: the current home's sliders).

    A perturbed or calibrated tree does not close at the nominal home joint values; its closures
    file must carry its own assembled home (`Mechanism.load` checks it).
    """
    sliders = mechanism.home[mechanism.actuated_ids] if sliders is None else sliders
    return mechanism.with_home(ClosedLoopSolver(mechanism).forward(sliders, q_init=mechanism.home).q)
