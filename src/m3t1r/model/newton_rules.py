"""The rules every closed-loop Newton loop obeys, in one frozen object.

The Python Newton (`ClosedLoopSolver.newton`, which single solves and, without the compiled loop,
every batch row run) and the compiled loop (`model.native`, passed `NewtonRules.compiled()` with
every call) read one `NewtonRules`: where they once kept their own copies of these numbers, one of
them could (and did) drift from the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from m3t1r.errors import InvalidInputError

__all__ = ["NewtonRules", "DEFAULT_RULES"]


@dataclass(frozen=True)
class NewtonRules:
    """How a closure Newton solve steps, converges and fails.

    tolerance: max |row| [m or rad] at which a solve has converged.
    max_iterations: Newton steps allowed (a batch row counts its predicted start as one).
    singular_rcond: 1-norm reciprocal condition number of the square system (rows and unknowns
        scaled to unit length, `kinematics` module) below which a converged solve is refused as
        singular.
    max_step: [m or rad] cap on the largest component of a step, which keeps a far start on its branch.
    chord_contraction: a reused factorisation is kept while each step shrinks the residual by at
        least this factor; the Jacobian is re-evaluated otherwise.
    chord_below: [m or rad] chord steps only from residuals at or below this; above it Newton's
        quadratic rate is worth a fresh Jacobian at every step.
    no_assembly: [m or rad] a solve out of iterations with a residual above this has no assembly
        there (OutOfWorkspaceError); at or below it, it merely did not converge (NotConvergedError).
    """

    tolerance: float = 1e-12
    max_iterations: int = 60
    singular_rcond: float = 1e-10
    max_step: float = 0.3
    chord_contraction: float = 0.05
    chord_below: float = 1e-4
    no_assembly: float = 1e-6

    def __post_init__(self) -> None:
        positive = {
            "tolerance": self.tolerance,
            "max_step": self.max_step,
            "chord_below": self.chord_below,
            "no_assembly": self.no_assembly,
        }
        for name, value in positive.items():
            if not (isinstance(value, (int, float)) and value > 0.0) or math.isnan(value):
                raise InvalidInputError(f"Newton rules: {name} must be a number > 0, got {value!r}")
        if not (isinstance(self.singular_rcond, (int, float)) and self.singular_rcond >= 0.0):
            raise InvalidInputError(f"Newton rules: singular_rcond must be a number >= 0, got {self.singular_rcond!r}")
        if not 0.0 < self.chord_contraction < 1.0:
            raise InvalidInputError(
                f"Newton rules: chord_contraction must be in (0, 1), got {self.chord_contraction!r}"
            )
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) or self.max_iterations < 0:
            raise InvalidInputError(
                f"Newton rules: max_iterations must be an integer >= 0, got {self.max_iterations!r}"
            )

    def compiled(self) -> tuple[float, int, float, float, float, float, float]:
        """The rules in the order the compiled loop takes them (`_native_newton`'s `rules` arguments)."""
        return (
            float(self.tolerance),
            int(self.max_iterations),
            float(self.singular_rcond),
            float(self.max_step),
            float(self.chord_contraction),
            float(self.chord_below),
            float(self.no_assembly),
        )


DEFAULT_RULES = NewtonRules()
