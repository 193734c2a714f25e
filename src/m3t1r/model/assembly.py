"""Assembling a home from a rough guess: the URDF zero, the actuators' values alone, or more.

Published mechanisms rarely come with an assembled configuration: at the URDF zero the cut frames
of a loop can be centimetres apart, or a whole turn off. `assemble_home` closes the loops over the
passive joints with the actuators held at their given values, by Levenberg-Marquardt (damped
least squares) from the guess, so that it reaches the assembly the guess leads to, not whichever
one a full Newton step would jump to. A damped step is short where the closure Jacobian is poorly
conditioned (a stretched leg, a folded knee), which keeps the solve from crossing into another
assembly mode there.

The damped phase minimises a residual that is smooth everywhere: for a closure whose every row is
enforced, p_b - p_a (3D) and also R_b - R_a (6D, nine entries, scaled by a length so that they
weigh as positions): unlike log6, which the closure rows use, it has no branch cut at a half turn,
where published zeros often put a duplicated rod. The result is then polished on the enforced
rows themselves (`ClosureSystem.assemble`), moved along the motion the closures leave the passive joints
(idle spins of a rod between two spherical joints, any mobility beyond the actuators) to the point of that
set nearest the guess (`_nearest_to_guess`: a rod's spin, which moves nothing else, is wherever the
damped path left it), and revolute joints are brought back by whole turns into their limits, or into
(-pi, pi] when the URDF gives none. Of several discrete assembly modes, the one the damped path from the
guess reaches is kept, not the nearest in joint space: on a published hexapod, that nearest one has the
platform upside down.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from m3t1r.model.closures import CLOSURE_TYPES, ClosureSpec, ClosureSystem, closure_null_space

__all__ = ["HomeAssembly", "assemble_home"]

_DAMPED_ITERATIONS = 400
_SMOOTH_TOLERANCE = 1e-9  # [m] the damped phase hands over to the closure rows' own Newton below this
_POLISH_TOLERANCE = 1e-13  # [m or rad] max |enforced row| the polish aims at
_RESTARTS = 8  # offset starts tried when the solve from the guess stalls
_RESTART_ANGLE, _RESTART_LENGTH = 0.1, 0.01  # [rad], [m] their standard deviation per passive joint
_NEAREST_STEPS = 50  # projected steps toward the guess along the closures' own motion
_NEAREST_TOLERANCE = 1e-10  # [rad or m] the tangential offset from the guess at which they stop


@dataclass(frozen=True)
class HomeAssembly:
    """How `Mechanism.load` closed a home that did not close as given.

    given_residual: max |enforced closure row| at the given values [m or rad], in closure `worst`;
    residual: the same at the assembled home; moved: (joint, assembled - given) of every passive joint
    that moved by more than 1e-9 [rad or m], largest first (a whole-turn wrap not counted);
    wrapped: revolute joints brought back by whole turns into their limits, or into (-pi, pi] when the
    URDF gives none; iterations: damped steps taken.
    """

    worst: str
    given_residual: float
    residual: float
    moved: tuple[tuple[str, float], ...]
    wrapped: tuple[str, ...]
    iterations: int

    def note(self, tolerance: float) -> str:
        """One line for the user: what did not close (above `tolerance`), which assembly was chosen and
        how far each joint moved."""
        shown = ", ".join(f"{name} {change:+.3g}" for name, change in self.moved[:6])
        more = f" and {len(self.moved) - 6} more" if len(self.moved) > 6 else ""
        wraps = f"; {', '.join(self.wrapped)} wrapped by whole turns" if self.wrapped else ""
        return (
            f"home does not close: closure '{self.worst}' residual {self.given_residual:.3e} > {tolerance:g}; "
            "assembled by Newton (damped, actuators held) at the assembly nearest the given values: "
            f"passive joints moved by {shown or 'nothing'}{more} [rad or m]{wraps}. To choose another assembly "
            "mode, give approximate values of its passive joints in `home`"
        )


def assemble_home(
    model: pin.Model, closures: tuple[ClosureSpec, ...], system: ClosureSystem, guess: np.ndarray, passive: np.ndarray
) -> tuple[np.ndarray, HomeAssembly]:
    """The assembly nearest `guess` (nq) over the `passive` velocity indices, the others held.

    Returns (home, report). The caller judges `report.residual` (no assembly near the guess leaves it
    large) and the joint limits (`limits_violated`).
    """
    given_rows = np.abs(system.evaluate(guess, False)[0])
    worst = _closure_of_row(closures, int(np.argmax(np.where(np.isfinite(given_rows), given_rows, np.inf))))
    smooth = _SmoothClosures(model, closures, system)
    q, iterations = _damped(smooth, guess.copy(), passive)
    q, residual = system.assemble(q, passive, _POLISH_TOLERANCE)
    if not residual <= _SMOOTH_TOLERANCE:
        q, residual, iterations = _restarted(smooth, system, guess, passive, (q, residual, iterations))
    if residual <= _SMOOTH_TOLERANCE:
        q, residual = _nearest_to_guess(model, system, q, residual, guess, passive)
    q, wrapped = _wrapped(model, q, passive)
    names = [_joint_name(model, v) for v in passive]
    change = q[passive] - guess[passive]
    turns = np.array([_is_revolute(model, v) for v in passive])
    change = np.where(turns & np.isin(names, wrapped), _principal(change), change)
    order = np.argsort(-np.abs(change), kind="stable")
    moved = tuple((names[k], float(change[k])) for k in order if abs(change[k]) > 1e-9)
    return q, HomeAssembly(worst, float(given_rows.max(initial=0.0)), residual, moved, wrapped, iterations)


def limits_violated(model: pin.Model, q: np.ndarray, joints: np.ndarray) -> list[tuple[str, float, float, float]]:
    """(joint, value, lower, upper) of the joints (velocity indices) outside usable URDF limits
    (lower < upper; lower >= upper is how Pinocchio reads an absent limit)."""
    lower, upper = model.lowerPositionLimit, model.upperPositionLimit
    return [
        (_joint_name(model, int(v)), float(q[v]), float(lower[v]), float(upper[v]))
        for v in joints
        if lower[v] < upper[v] and not lower[v] - 1e-12 <= q[v] <= upper[v] + 1e-12
    ]


class _SmoothClosures:
    """Closure residuals without branch cuts (`ClosureType.smooth`), and their Jacobian over every
    joint (rows x nv). A closure with only some rows enforced keeps those rows, as the closure system
    has them."""

    def __init__(self, model: pin.Model, closures: tuple[ClosureSpec, ...], system: ClosureSystem) -> None:
        self.model, self.data, self.closures, self.system = model, model.createData(), closures, system
        placements = [model.jointPlacements[j].translation for j in range(1, model.njoints)]
        # The length that makes a unit of R_b - R_a weigh as much as a metre of p_b - p_a: the tree's scale.
        self.length = max(float(np.linalg.norm(placements, axis=1).sum()) / max(len(placements), 1), 1e-3)
        starts = np.cumsum([0] + [len(spec.rows) for spec in closures])
        whole = [len(spec.rows) == CLOSURE_TYPES[spec.type].rows for spec in closures]
        self.whole = [(spec, CLOSURE_TYPES[spec.type].smooth) for spec, full in zip(closures, whole) if full]
        self.partial = [np.arange(starts[k], starts[k + 1]) for k, full in enumerate(whole) if not full]

    def evaluate(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        model, data = self.model, self.data
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        rows: list[np.ndarray] = []
        jacobians: list[np.ndarray] = []
        for spec, smooth in self.whole:
            ja = pin.getFrameJacobian(model, data, spec.frame_a_id, pin.LOCAL_WORLD_ALIGNED)
            jb = pin.getFrameJacobian(model, data, spec.frame_b_id, pin.LOCAL_WORLD_ALIGNED)
            more_rows, more_jacobians = smooth(
                data.oMf[spec.frame_a_id], data.oMf[spec.frame_b_id], ja, jb, self.length
            )
            rows += more_rows
            jacobians += more_jacobians
        if self.partial:
            residual, jac = self.system.evaluate(q, True)
            for slots in self.partial:
                rows.append(residual[slots])
                jacobians.append(jac[slots])
        return np.concatenate(rows), np.concatenate(jacobians)


def _damped(smooth: _SmoothClosures, q: np.ndarray, passive: np.ndarray) -> tuple[np.ndarray, int]:
    """Levenberg-Marquardt on the smooth residual over `passive` from q (Nielsen's damping update)."""
    residual, jac = smooth.evaluate(q)
    cost = _squared(residual)
    mu, nu = None, 2.0
    for iteration in range(1, _DAMPED_ITERATIONS + 1):
        if not math.isfinite(cost) or math.sqrt(cost) <= _SMOOTH_TOLERANCE:
            return q, iteration - 1
        j = jac[:, passive]
        normal, gradient = j.T @ j, j.T @ residual
        if mu is None:
            mu = 1e-3 * max(float(np.max(np.diag(normal))), 1e-12)
        step = -np.linalg.solve(normal + mu * np.eye(len(passive)), gradient)
        trial = q.copy()
        trial[passive] += step
        trial_residual, trial_jac = smooth.evaluate(trial)
        trial_cost = _squared(trial_residual)
        predicted = float(step @ (mu * step - gradient))  # the model's decrease, > 0
        gain = (cost - trial_cost) / predicted if predicted > 0.0 else -1.0
        if gain > 0.0 and math.isfinite(trial_cost):
            q, residual, jac, cost = trial, trial_residual, trial_jac, trial_cost
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            nu = 2.0
        else:
            mu *= nu
            nu *= 2.0
            if not mu < 1e300:  # no step shortens the residual: a local minimum, not an assembly
                return q, iteration
    return q, _DAMPED_ITERATIONS


def _restarted(
    smooth: _SmoothClosures,
    system: ClosureSystem,
    guess: np.ndarray,
    passive: np.ndarray,
    first: tuple[np.ndarray, float, int],
) -> tuple[np.ndarray, float, int]:
    """(q, residual, iterations) from small fixed offsets of the guess when the solve from the guess
    itself stalled: a guess on a singularity (a linkage published stretched straight, every link on
    one line) is a stationary point of the residual, where no step shortens it. Of the starts that
    close, the assembly nearest the guess; without one, the first attempt as it was."""
    best, iterations = first, first[2]
    turns = np.array([_is_revolute(smooth.model, int(v)) for v in passive], dtype=bool)
    scale = np.where(turns, _RESTART_ANGLE, _RESTART_LENGTH)
    for seed in range(_RESTARTS):
        start = guess.copy()
        start[passive] += scale * np.random.default_rng(seed).standard_normal(len(passive))
        q, used = _damped(smooth, start, passive)
        q, residual = system.assemble(q, passive, _POLISH_TOLERANCE)
        iterations += used
        closes = residual <= _SMOOTH_TOLERANCE
        if closes and not (
            best[1] <= _SMOOTH_TOLERANCE
            and _distance(best[0], guess, passive, turns) <= _distance(q, guess, passive, turns)
        ):
            best = (q, residual, 0)
    return best[0], best[1], iterations


def _nearest_to_guess(
    model: pin.Model, system: ClosureSystem, q: np.ndarray, residual: float, guess: np.ndarray, passive: np.ndarray
) -> tuple[np.ndarray, float]:
    """(q, residual) moved from the assembly q, along the set of assemblies connected to it (actuators
    held), to the one nearest `guess` over the passive joints (revolute ones modulo whole turns): steps
    along the null space of the passive closure Jacobian toward the guess, each closed again by Newton,
    while the distance drops. Where the closures leave no motion (the usual case) q is returned as it is;
    a rod's idle spin, which Newton leaves wherever the damped phase put it, is brought back to the guess."""
    turns = np.array([_is_revolute(model, int(v)) for v in passive], dtype=bool)
    for _ in range(_NEAREST_STEPS):
        null = closure_null_space(system.evaluate(q, True)[1][:, passive])
        step = -null @ (null.T @ _offset(q, guess, passive, turns))
        if not float(np.linalg.norm(step)) > _NEAREST_TOLERANCE:
            break
        trial = q.copy()
        trial[passive] += step
        trial, trial_residual = system.assemble(trial, passive, _POLISH_TOLERANCE)
        if not (
            trial_residual <= _SMOOTH_TOLERANCE
            and _distance(trial, guess, passive, turns) < _distance(q, guess, passive, turns)
        ):
            break
        q, residual = trial, trial_residual
    return q, residual


def _distance(q: np.ndarray, guess: np.ndarray, passive: np.ndarray, turns: np.ndarray) -> float:
    """|q - guess| over the passive joints [rad or m], revolute ones (`turns`) modulo whole turns."""
    return float(np.linalg.norm(_offset(q, guess, passive, turns)))


def _offset(q: np.ndarray, guess: np.ndarray, passive: np.ndarray, turns: np.ndarray) -> np.ndarray:
    change = q[passive] - guess[passive]
    return np.where(turns, _principal(change), change)


def _squared(residual: np.ndarray) -> float:
    """|r|^2, inf (not a warning) when it overflows or r is not finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        cost = float(residual @ residual)
    return cost if math.isfinite(cost) else math.inf


def _principal(angle: np.ndarray) -> np.ndarray:
    return angle - 2.0 * np.pi * np.round(angle / (2.0 * np.pi))


def _wrapped(model: pin.Model, q: np.ndarray, passive: np.ndarray) -> tuple[np.ndarray, tuple[str, ...]]:
    """q with each passive revolute joint moved by whole turns into its limits (into (-pi, pi] without
    usable limits, or when no whole turn fits them), and the names of those that moved."""
    q = q.copy()
    lower, upper = model.lowerPositionLimit, model.upperPositionLimit
    wrapped = []
    for v in passive:
        if not _is_revolute(model, int(v)):
            continue
        value = float(_principal(np.array(q[v])))
        if lower[v] < upper[v] and not lower[v] <= value <= upper[v]:
            turns = math.ceil((lower[v] - value) / (2.0 * math.pi))
            if value + 2.0 * math.pi * turns <= upper[v]:
                value += 2.0 * math.pi * turns
        if value != q[v]:
            q[v] = value
            wrapped.append(_joint_name(model, int(v)))
    return q, tuple(wrapped)


def _is_revolute(model: pin.Model, velocity_index: int) -> bool:
    joint = next(j for j in range(1, model.njoints) if model.idx_vs[j] == velocity_index)
    return model.joints[joint].shortname().startswith(("JointModelR", "JointModelRevolute"))


def _joint_name(model: pin.Model, velocity_index: int) -> str:
    return next(model.names[j] for j in range(1, model.njoints) if model.idx_vs[j] == velocity_index)


def _closure_of_row(closures: tuple[ClosureSpec, ...], row: int) -> str:
    names = [spec.name for spec in closures for _ in spec.rows]
    return names[row] if 0 <= row < len(names) else "?"
