"""The fit past the nominal's rank: where a nominal of special geometry understates what the data identify.

A nominal of special geometry (exact parallelograms, a plane) moves the platform only at second order
along some placement errors, which a machine with errors moves at first order: base parameters chosen at
the nominal are then too few to follow the curved set of machines that explain the data, and the fit
stalls at a residual of order error^2. `significant_extra_rank` says when continuing over every column
with an effect is warranted (an F test, linearised at the estimate); the pipeline then resumes
Levenberg-Marquardt there, damped in the parameters' own units, and keeps the refit only if its own drop
in chi^2 passes the same test (`significant`). Noisy data fail the test: no refit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.special

__all__ = ["GENERIC_RANK_SIGNIFICANCE", "explained", "significant"]

#: The F test's p-value below which the pipeline refits past the nominal's rank and keeps the refit: a
#: drop in chi^2 that fitting noise with that many more parameters gives once in a thousand fits.
GENERIC_RANK_SIGNIFICANCE = 1e-3


def explained(factor: np.ndarray, rotated: np.ndarray, columns: Sequence[int]) -> float:
    """The part of |r|^2 a linear fit over `columns` explains, from the triangular factor R of the whitened
    Jacobian and Q^T r (the QR of [J r]): |P Q^T r|^2, P projecting on R's chosen columns."""
    chosen = factor[:, list(columns)]
    chosen = chosen / np.linalg.norm(chosen, axis=0)
    fitted = chosen @ np.linalg.lstsq(chosen, rotated, rcond=None)[0]
    return float(fitted @ fitted)


def significant(before: float, after: float, extra: int, dof: int) -> bool:
    """Whether chi^2 dropping from `before` to `after` with `extra` more parameters is beyond what fitting
    noise gives: the F test of the drop per parameter against the residual's own variance after / dof, at
    p < GENERIC_RANK_SIGNIFICANCE."""
    if extra <= 0 or dof <= 0 or not after < before:
        return False
    ratio = (before - after) / extra / max(after / dof, 1e-300)
    return bool(scipy.special.fdtrc(extra, dof, ratio) < GENERIC_RANK_SIGNIFICANCE)
