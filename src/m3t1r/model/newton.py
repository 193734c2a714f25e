"""The closed-loop Newton in Python: one loop for single solves and, without the compiled loop, for
every batch row; its outcome codes and failure wording, which the compiled loop (`model.native`)
shares.

`newton` solves a square system over some columns under one `NewtonRules`: the Jacobian is evaluated
at the start and after every step from a residual above `rules.chord_below`; below it, later steps
reuse the LU factors while each step still contracts the residual by `rules.chord_contraction`
(chord steps), and refresh them otherwise. Steps are capped at `rules.max_step`. At convergence the
last factorised system must have a 1-norm reciprocal condition of at least `rules.singular_rcond`
and the start's branch labels.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.linalg import blas, lapack

from m3t1r.errors import (
    BranchChangeError,
    KinematicsError,
    NotConvergedError,
    OutOfWorkspaceError,
    SingularConfigurationError,
)
from m3t1r.model.newton_rules import NewtonRules

__all__ = [
    "CONVERGED",
    "FAILURES",
    "Outcome",
    "STATUS",
    "failure",
    "newton",
    "reason",
]

#: Outcome codes of every loop (the compiled one returns them): 0 converged, then the failures.
CONVERGED, NO_ASSEMBLY, NOT_CONVERGED, SINGULAR, BRANCH_CHANGE = 0, 1, 2, 3, 4
FAILURES: dict[int, type[KinematicsError]] = {
    NO_ASSEMBLY: OutOfWorkspaceError,
    NOT_CONVERGED: NotConvergedError,
    SINGULAR: SingularConfigurationError,
    BRANCH_CHANGE: BranchChangeError,
}
STATUS = {error: status for status, error in FAILURES.items()}  # a typed failure's code
_REASONS = {
    NO_ASSEMBLY: "the closures cannot be assembled here (target out of the workspace or too far from the "
    "initial configuration's branch)",
    NOT_CONVERGED: "Newton did not reach the tolerance",
    BRANCH_CHANGE: "the solution lies on another assembly branch than the start (Newton crossed a singularity)",
}

System = Callable[[np.ndarray, bool], tuple[np.ndarray, np.ndarray | None]]
Signature = Callable[[np.ndarray, tuple], bytes]
_dasum, _idamax, _dlange = blas.dasum, blas.idamax, lapack.dlange


def reason(status: int, rcond: float | None = None, singular_rcond: float | None = None) -> str:
    """The words of a failure: a singular one names its reciprocal condition `rcond`, or (a batch row)
    the threshold `singular_rcond` it fell below."""
    if status != SINGULAR:
        return _REASONS[status]
    if rcond is not None:
        return f"singular configuration (reciprocal condition {rcond:.2e})"
    return f"singular configuration (reciprocal condition below {singular_rcond:g})"


def failure(status: int, norm: float, iterations: int, rcond: float) -> KinematicsError:
    """The typed error of a failed solve's code (compiled or Python), with its residual and steps."""
    return FAILURES[status](reason(status, rcond), norm, iterations)


class Outcome(NamedTuple):
    """A converged Newton solve: solution, residual, steps, the inverse of the last factorised system,
    last Jacobian and branch."""

    q: np.ndarray
    residual: float
    iterations: int
    inverse: np.ndarray
    jacobian: np.ndarray
    branch: bytes


def one_norm(square: np.ndarray) -> float:
    """Largest column sum of |A| (dgecon's anorm): the infinity norm of A^T, which for a C-ordered A
    LAPACK reads in place (Fortran order), without the copy that A itself would cost."""
    return float(_dlange("I", square.T))


def inverse_and_rcond(lu: tuple, norm_1: float) -> tuple[np.ndarray, float]:
    """A^-1 from getrf factors, and A's reciprocal condition number 1 / (|A|_1 |A^-1|_1), exact where
    dgecon would estimate it at about the same cost; the inverse then serves FK's tangent too.
    0 when U has a zero pivot or the inverse overflows."""
    inverse, info = lapack.dgetri(lu[0], lu[1])
    rcond = 1.0 / (norm_1 * float(_dlange("1", inverse))) if info == 0 else 0.0
    return inverse, (rcond if rcond == rcond else 0.0)  # nan (inf - inf in the inverse) counts as singular


def max_abs(vector: np.ndarray) -> float:
    """max |v_i| as numpy's abs().max() gives it (nan if any entry is nan), by two BLAS calls: a
    fraction of a numpy reduction's overhead on vectors this short. dasum is nan exactly when an
    entry is (a sum of absolute values never makes nan from finite or infinite terms)."""
    total = _dasum(vector)
    return abs(float(vector[_idamax(vector)])) if total == total else math.nan


def newton(
    q: np.ndarray,
    unknowns: np.ndarray | None,
    system: System,
    signature: Signature,
    rules: NewtonRules,
    start_branch: bytes | None = None,
) -> Outcome:
    """Newton on the square system `system(q, with_jacobian) -> (rows, Jacobian (rows x nv) or None)`
    over the columns `unknowns` (None: every column), from q (solved in place), under `rules`.

    `signature(jac, lu)` labels the branch: its value at the last Jacobian must equal `start_branch`
    (default: its value at the first Jacobian). Raises OutOfWorkspaceError (residual above
    rules.no_assembly or not finite), NotConvergedError, SingularConfigurationError (a zero pivot, or
    a converged system below rules.singular_rcond) or BranchChangeError, each with its residual and
    iteration.
    """
    tolerance, contraction, max_step = rules.tolerance, rules.chord_contraction, rules.max_step
    residual, jac = system(q, True)
    previous = norm = math.inf
    last_jac = square = label = lu = None  # label: the signature of last_jac, once computed
    for iteration in range(rules.max_iterations + 1):
        norm = max_abs(residual)
        if not math.isfinite(norm):
            break
        if jac is None and norm > contraction * previous and norm > tolerance:
            residual, jac = system(q, True)
        if jac is not None:
            square = jac if unknowns is None else jac.take(unknowns, axis=1)
            factors = lapack.dgetrf(square)
            lu = factors[:2]
            if factors[2] > 0:  # a zero pivot: no step exists (the compiled loop's `factor` says the same)
                raise failure(SINGULAR, norm, iteration, 0.0)
            label = None
            if start_branch is None:
                start_branch = label = signature(jac, lu)
            last_jac, jac = jac, None
        if norm <= tolerance:
            assert lu is not None and square is not None and last_jac is not None, "the first pass sets them"
            return _verdict(q, norm, iteration, rules, (square, lu, last_jac, label), signature, start_branch)
        if iteration == rules.max_iterations:
            break
        assert lu is not None, "the first iteration factorises"
        step = lapack.dgetrs(lu[0], lu[1], residual)[0]
        biggest = abs(float(step[_idamax(step)]))  # nan entries make q nan: the next residual stops
        if biggest > max_step:
            step *= max_step / biggest
        if unknowns is None:
            q -= step
        else:
            q[unknowns] -= step
        previous = norm
        residual, jac = system(q, previous > rules.chord_below)
    raise failure(
        NO_ASSEMBLY if norm > rules.no_assembly or not math.isfinite(norm) else NOT_CONVERGED, norm, iteration, 0.0
    )


def _verdict(
    q: np.ndarray,
    norm: float,
    iteration: int,
    rules: NewtonRules,
    factored: tuple,
    signature: Signature,
    start_branch: bytes | None,
) -> Outcome:
    """A converged solve judged at its last Jacobian only: conditioning, then branch."""
    square, lu, last_jac, label = factored
    inverse, rcond = inverse_and_rcond(lu, one_norm(square))
    if rcond < rules.singular_rcond:
        raise failure(SINGULAR, norm, iteration, rcond)
    branch = label if label is not None else signature(last_jac, lu)
    if branch != start_branch:
        raise failure(BRANCH_CHANGE, norm, iteration, 0.0)
    return Outcome(q, norm, iteration, inverse, last_jac, branch)
