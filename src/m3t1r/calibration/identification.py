"""Model-agnostic parameter identification: base parameters, linear and nonlinear least squares.

Nothing here knows about robots. The calibration model of Zhang et al. (Symmetry 2020) is the
stacked linear system Y = A X of eq. (31), solved in the least-squares sense (eq. 32), recursively
(section 5), or iterated with multiplicative updates of the initial poses (eq. 33); these are the
three solvers below, plus the choice of an identifiable (base) parameter subset that makes them
well posed, since the 6 (n + 1) placement errors of a chain are redundant (section 3.2).

Conventions: a Jacobian has one row per scalar measurement and one column per parameter; weights
are per-row inverse standard deviations (1/sigma, in the inverse units of the row).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, Literal, Protocol, TypeVar, cast

import numpy as np
import scipy.linalg
import scipy.special
from numpy.typing import ArrayLike

from m3t1r.errors import IdentificationError, InvalidInputError, PoorExcitationWarning, require_real

__all__ = [
    "BaseParameters",
    "IDENTIFIABILITY_TOLERANCE",
    "REFERENCE_POSES",
    "REFERENCE_SEED",
    "TIE_TOLERANCE",
    "best_index",
    "pivoted_qr",
    "project_out",
    "LMResult",
    "LMSettings",
    "OUTLIER_SIGMA",
    "outlier_gate",
    "ParameterSelection",
    "forward_selection",
    "outlier_poses",
    "checked_outlier_sigma",
    "parameter_columns",
    "LeastSquaresProblem",
    "LinearFit",
    "RecursiveLeastSquares",
    "batch_least_squares",
    "levenberg_marquardt",
    "select_base_parameters",
    "triangular_factor",
    "unexcited_parameters",
    "without_column",
]

#: Above this condition number of the kept, column-normalised Jacobian, a relative perturbation of
#: 1e-6 in the data (a micrometre on a metre) can reach the parameters at order one.
POOR_EXCITATION_CONDITION = 1e6


def _as_matrix(values: ArrayLike, what: str) -> np.ndarray:
    matrix = np.asarray(values, dtype=float)
    if matrix.ndim != 2:
        raise InvalidInputError(f"{what}: expected a 2-D array, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        row, col = np.argwhere(~np.isfinite(matrix))[0]
        raise InvalidInputError(f"{what}: non-finite value at row {row}, column {col}")
    return matrix


def _as_rows(values: ArrayLike, n_rows: int, what: str) -> np.ndarray:
    vector = np.asarray(values, dtype=float).reshape(-1)
    if vector.size != n_rows:
        raise InvalidInputError(f"{what}: expected {n_rows} values, got {vector.size}")
    if not np.all(np.isfinite(vector)):
        raise InvalidInputError(f"{what}: non-finite value at index {int(np.flatnonzero(~np.isfinite(vector))[0])}")
    return vector


def _as_weights(values: ArrayLike | None, n_rows: int, what: str) -> np.ndarray | None:
    if values is None:
        return None
    weights = _as_rows(values, n_rows, what)
    if np.any(weights <= 0.0):
        raise InvalidInputError(f"{what}: must be positive inverse standard deviations")
    return weights


# Rows per QR in `triangular_factor`: a block of 4,096 rows by 57 columns is 1.9 MB.
_FACTOR_ROWS = 4096


def triangular_factor(
    matrix: np.ndarray, vector: np.ndarray | None = None, previous: np.ndarray | None = None
) -> np.ndarray:
    """Upper-triangular R with R^T R = P^T P + M^T M for M = [matrix, vector] (the vector, when
    given, as a last column) and P = `previous`: the R of a QR of [P; M], taken over blocks of rows.

    Memory is R plus one block, never a copy of M. With a vector, R = [R_J, Q^T r; 0, rho]: the
    factor of the matrix alone, the vector rotated by the same Q, and rho^2 the part of |r|^2
    outside the matrix's range. Rows: min(rows of [P; M], columns).
    """
    width = matrix.shape[1] + (vector is not None)
    factor = np.zeros((0, width)) if previous is None else previous
    for start in range(0, matrix.shape[0], _FACTOR_ROWS):
        block = matrix[start : start + _FACTOR_ROWS]
        if vector is not None:
            block = np.column_stack((block, vector[start : start + _FACTOR_ROWS]))
        factor = cast(np.ndarray, np.linalg.qr(np.vstack((factor, block)), mode="r"))  # numpy's stub: QRResult
    return factor


# --------------------------------------------------------------------------------------------------
# Base parameters


@dataclass(frozen=True)
class BaseParameters:
    """An identifiable subset of parameters, chosen by column-pivoted QR.

    All quantities are computed on the column-normalised Jacobian (every non-zero column scaled to
    unit 2-norm), so that the choice does not depend on the parameters' units (m versus rad).

    indices: kept columns, sorted in the original column order; names: their names.
    rank: number of kept columns.
    singular_values: of the whole column-normalised Jacobian (zero columns stay zero), descending.
    condition_number: ratio of extreme singular values of the kept normalised columns.
    r_diag_ratio: |R_ii| / |R_00| along the pivot order, for the kept columns and the first dropped
        one if any; the drop from the last to the next entry shows how clear the rank decision is.
    zero_columns: names of columns whose norm is below rank_tolerance times the largest column norm
        (parameters with no effect at all on the measurements).
    """

    indices: tuple[int, ...]
    names: tuple[str, ...]
    rank: int
    singular_values: np.ndarray
    condition_number: float
    r_diag_ratio: np.ndarray
    zero_columns: tuple[str, ...]


#: Two candidates of a rank-revealing choice (a pivot column, a pose, a parameter to add) whose scores
#: agree to this relative tolerance are a tie, and the lower index wins. Interchangeable columns of a
#: symmetric mechanism differ only by rounding (1e-16 relative, up to 1e-12 after the projections of
#: a pivoted QR), which BLAS kernels do differently; genuine differences are far above 1e-9.
TIE_TOLERANCE = 1e-9

#: The one identifiability decision of `plan`, `calibrate` and the diagnosis: a parameter column is
#: identifiable while |R_ii| > IDENTIFIABILITY_TOLERANCE |R_00| in the tie-ruled pivoted QR of the
#: column-normalised whitened Jacobian. Redundant columns sit at 1e-13 and below; O(error^2) effects
#: (1e-6 of a 1 mm error) and genuine weak directions at 1e-7 and above.
IDENTIFIABILITY_TOLERANCE = 1e-8

#: What a closed-loop model can identify is measured on one pose set, spread over the workspace box:
#: REFERENCE_POSES draws of seed REFERENCE_SEED (`workspace_actuators`). `calibrate` requires its
#: data to identify that many parameters, and `plan` its poses; a direction barely above the
#: tolerance is identified on more rows and not on fewer, so both must measure on the same set.
REFERENCE_POSES = 40
REFERENCE_SEED = 2020


def best_index(scores: ArrayLike, *, largest: bool = True) -> int:
    """Index of the best score (the largest, or the smallest with largest=False), the lower index
    among those within TIE_TOLERANCE (relative to the best's magnitude) of it; -inf/inf never wins
    over a finite score."""
    values = np.asarray(scores, dtype=float)
    if not largest:
        values = -values
    best = float(np.max(values))
    if not math.isfinite(best):
        return int(np.argmax(values))
    return int(np.flatnonzero(values >= best - TIE_TOLERANCE * max(abs(best), 1e-300))[0])


def pivoted_qr(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R and pivots of A P = Q R (Householder, column pivoting on the largest remaining 2-norm).

    Unlike LAPACK's dgeqp3, whose downdated column norms carry errors up to 1e-8 relative, every
    remaining norm is recomputed at each step, and a tie (TIE_TOLERANCE) goes to the lower original
    column: the same columns are chosen on any processor. O(p^3) for p columns: meant for the small
    triangular factor of a tall matrix (`select_base_parameters`).
    """
    work = np.array(matrix, dtype=float)
    rows, cols = work.shape
    pivots = np.arange(cols)
    for k in range(min(rows, cols)):
        norms = np.sqrt(np.einsum("ij,ij->j", work[k:, k:], work[k:, k:]))
        ties = np.flatnonzero(norms >= (1.0 - TIE_TOLERANCE) * norms.max())
        j = k + int(ties[np.argmin(pivots[k + ties])])
        work[:, [k, j]] = work[:, [j, k]]
        pivots[[k, j]] = pivots[[j, k]]
        column = work[k:, k].copy()
        length = float(np.linalg.norm(column))
        if length == 0.0:
            continue
        alpha = -length if column[0] >= 0.0 else length
        column[0] -= alpha
        column /= np.linalg.norm(column)
        work[k:, k:] -= 2.0 * np.outer(column, column @ work[k:, k:])
        work[k + 1 :, k] = 0.0
        work[k, k] = alpha
    return np.triu(work[: min(rows, cols)]), pivots


def select_base_parameters(
    jacobian: ArrayLike,
    names: Sequence[str],
    rank_tolerance: float = IDENTIFIABILITY_TOLERANCE,
    *,
    max_condition: float = POOR_EXCITATION_CONDITION,
    forced: Sequence[int] | np.ndarray = (),
) -> BaseParameters:
    """Choose a maximal set of linearly independent columns of the stacked Jacobian (m, p).

    A column is kept while |R_ii| > rank_tolerance |R_00| in the pivoted QR of the column-normalised
    matrix. Exactly redundant parameters (e.g. a placement error along its own joint axis, which
    commutes with the joint motion) give |R_ii| at rounding level; rank_tolerance must sit between that
    and the weakest genuine direction. Emits PoorExcitationWarning when the kept set's condition
    number exceeds `max_condition`: the pose set is then too poor to pin down every kept parameter.

    forced: columns kept first, whatever their norm (the gauge: e.g. a measurement frame whose 6
    parameters are redundant with base-side placements keeps them, and the placements it makes
    redundant are the ones dropped). They are taken in the given order, and one that the earlier
    ones explain is dropped; the rest is chosen on the remainder after projecting them out.
    """
    if len(forced):
        return _select_with_forced(
            _as_matrix(jacobian, "jacobian"), tuple(names), rank_tolerance, max_condition, np.asarray(forced, dtype=int)
        )
    matrix = _as_matrix(jacobian, "jacobian")
    names = tuple(names)
    norms, nonzero = _column_norms(matrix, names, rank_tolerance)
    candidates = np.flatnonzero(nonzero)
    # An unpivoted QR of the tall matrix first: pivoting decisions depend only on column norms of
    # trailing blocks, which are invariant under the orthogonal factor, so pivoting its small
    # triangular factor picks the same columns at a fraction of the cost. Every spectrum below
    # then comes from triangular factors too (A P = Q R: equal singular values).
    # Symmetric mechanisms give columns of equal norm at a pivot step; which of them wins would then
    # depend on rounding: `pivoted_qr` gives such ties to the lower column, on any processor.
    r0 = cast(np.ndarray, np.linalg.qr(matrix[:, candidates] / norms[candidates], mode="r"))  # the stub: QRResult
    r, pivots = pivoted_qr(r0)
    diag = np.abs(np.diag(r))
    ratio = diag / diag[0]
    rank = int(np.count_nonzero(ratio > rank_tolerance))
    kept = np.sort(candidates[pivots[:rank]])
    singular_values = np.zeros(min(matrix.shape))
    spectrum = np.linalg.svd(r, compute_uv=False)
    singular_values[: spectrum.size] = spectrum
    kept_singular = np.linalg.svd(r[:rank, :rank], compute_uv=False)
    condition = float(kept_singular[0] / kept_singular[-1])
    if condition > max_condition:
        warnings.warn(
            PoorExcitationWarning(
                f"kept {rank} parameters with condition number {condition:.3g} > {max_condition:.3g}: "
                "add or spread out poses"
            ),
            stacklevel=2,
        )
    return BaseParameters(
        indices=tuple(int(i) for i in kept),
        names=tuple(names[i] for i in kept),
        rank=rank,
        singular_values=singular_values,
        condition_number=condition,
        r_diag_ratio=ratio[: min(rank + 1, ratio.size)],
        zero_columns=tuple(names[i] for i in np.flatnonzero(~nonzero)),
    )


def _column_norms(matrix: np.ndarray, names: tuple[str, ...], rank_tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Column norms and the mask of columns above rank_tolerance of the largest (the others have no effect)."""
    if len(names) != matrix.shape[1]:
        raise InvalidInputError(f"select_base_parameters: {matrix.shape[1]} columns but {len(names)} names")
    if not 0.0 < rank_tolerance < 1.0:
        raise InvalidInputError(f"select_base_parameters: rank_tolerance must be in (0, 1), got {rank_tolerance}")
    norms = np.linalg.norm(matrix, axis=0)
    largest = norms.max(initial=0.0)
    if largest == 0.0:
        raise IdentificationError("select_base_parameters: the Jacobian is identically zero")
    return norms, norms > rank_tolerance * largest


def _select_with_forced(
    matrix: np.ndarray, names: tuple[str, ...], rank_tolerance: float, max_condition: float, forced: np.ndarray
) -> BaseParameters:
    norms, nonzero = _column_norms(matrix, names, rank_tolerance)
    normalised = matrix[:, nonzero] / norms[nonzero]
    position = np.full(matrix.shape[1], -1)
    position[np.flatnonzero(nonzero)] = np.arange(np.count_nonzero(nonzero))
    # Forced columns in their given order, unpivoted: one that the earlier ones explain is dropped.
    q_forced = np.zeros((matrix.shape[0], 0))
    kept_forced, forced_diag = [], []
    for column in forced[nonzero[forced]]:
        vector = normalised[:, position[column]]
        vector = vector - q_forced @ (q_forced.T @ vector)
        length = float(np.linalg.norm(vector))
        if length > rank_tolerance:
            q_forced = np.column_stack((q_forced, vector / length))
            kept_forced.append(int(column))
            forced_diag.append(length)
    forced = np.array(kept_forced, dtype=int)
    rest = np.setdiff1d(np.flatnonzero(nonzero), forced)
    remainder = normalised[:, position[rest]]
    remainder = remainder - q_forced @ (q_forced.T @ remainder)
    r0 = cast(np.ndarray, np.linalg.qr(remainder, mode="r"))  # mode "r" returns R; numpy's stub says QRResult
    r, pivots = pivoted_qr(r0)
    diag = np.abs(np.diag(r))
    rank_rest = int(np.count_nonzero(diag > rank_tolerance))
    kept = np.sort(np.concatenate((forced, rest[pivots[:rank_rest]])))
    r_kept = np.linalg.qr(normalised[:, position[kept]], mode="r")
    kept_singular = np.linalg.svd(r_kept, compute_uv=False)
    condition = float(kept_singular[0] / kept_singular[-1])
    if condition > max_condition:
        warnings.warn(
            PoorExcitationWarning(
                f"kept {kept.size} parameters with condition number {condition:.3g} > {max_condition:.3g}: "
                "add or spread out poses"
            ),
            stacklevel=3,
        )
    singular_values = np.zeros(min(matrix.shape))
    spectrum = np.linalg.svd(np.linalg.qr(normalised, mode="r"), compute_uv=False)
    singular_values[: spectrum.size] = spectrum
    return BaseParameters(
        indices=tuple(int(i) for i in kept),
        names=tuple(names[i] for i in kept),
        rank=int(kept.size),
        singular_values=singular_values,
        condition_number=condition,
        r_diag_ratio=np.concatenate((forced_diag, diag[: min(rank_rest + 1, diag.size)])),
        zero_columns=tuple(names[i] for i in np.flatnonzero(~nonzero)),
    )


def unexcited_parameters(
    jacobian: ArrayLike, names: Sequence[str], columns: Sequence[int], count: int
) -> tuple[str, ...]:
    """The parameters among `columns` that make up the `count` least excited directions of the
    column-normalised `jacobian` (rows, parameters): for each of its `count` smallest right singular
    vectors over those columns, the parameters weighing at least half its largest component, the
    largest first (each direction is a combination; these are its main parts). What a rank
    shortfall of `count` leaves unidentified."""
    matrix = _as_matrix(jacobian, "jacobian")[:, list(columns)]
    norms = _column_norms_of(matrix)
    factor = triangular_factor(matrix / np.where(norms > 0.0, norms, 1.0))
    vt = np.linalg.svd(factor, full_matrices=True)[2]
    found: list[str] = []
    for direction in np.abs(vt[vt.shape[0] - count :][::-1]):
        weight = np.round(direction / direction.max(), 9)  # equal weights (twins) in column order, on any processor
        for position in np.argsort(-weight, kind="stable"):
            if weight[position] < 0.5:
                break
            if names[columns[position]] not in found:
                found.append(names[columns[position]])
    return tuple(found)


def parameter_columns(names: Sequence[str], wanted: Sequence[str], what: str) -> list[int]:
    """Columns named by `wanted`: a parameter name (`q12.dt[3]`, `compliance.elbow_joint`) or a
    placement's name (`q12`: every column named `q12.dt[k]`). InvalidInputError naming `what` and
    the unknown name otherwise, with an example taken from `names`."""
    # A bare string would be read letter by letter ("q12" -> 'q', '1', '2').
    if isinstance(wanted, (str, bytes)) or not all(isinstance(name, str) for name in wanted):
        raise InvalidInputError(f"{what}: expected a list of names such as ['q12'], got {wanted!r}")
    index = {name: i for i, name in enumerate(names)}
    columns: list[int] = []
    for name in wanted:
        if name in index:
            columns.append(index[name])
            continue
        group = [i for i, n in enumerate(names) if n.rsplit(".dt[", 1)[0] == name]
        if not group:
            example = names[0] if names else "q12.dt[3]"
            raise InvalidInputError(
                f"{what}: '{name}' is neither a parameter (e.g. {example}) nor a placement "
                f"(e.g. {example.rsplit('.dt[', 1)[0]}: all its components)"
            )
        columns += group
    return columns


# --------------------------------------------------------------------------------------------------
# Outliers and model selection by leave-one-pose-out prediction

#: A pose is an outlier when its whitened residual is as unlikely under the noise model as a
#: 5-sigma deviation of one normal variable (two-sided tail probability 5.7e-7).
OUTLIER_SIGMA = 5.0


def outlier_gate(sigma: float, dof: int) -> float:
    """The chi^2_dof quantile whose upper tail has the two-sided normal tail probability of `sigma`.

    scipy.special's chdtri and ndtr are the functions scipy.stats' chi2.isf and norm.sf call, without
    importing scipy.stats (a second of start-up for every command).
    """
    return float(scipy.special.chdtri(dof, 2.0 * scipy.special.ndtr(-sigma)))


def checked_outlier_sigma(sigma: object) -> float | None:
    """The outlier gate of a calibration call: None (or 0) keeps every pose; otherwise a finite
    number of sigmas from 1 to 1000. Anything else (negative, NaN, 0.5: a gate that flags good
    poses or none) raises InvalidInputError."""
    if sigma is None:
        return None
    value = require_real(sigma, "outlier_sigma")
    if value == 0.0:
        return None
    if not 1.0 <= value <= 1e3:
        raise InvalidInputError(
            f"outlier_sigma: None or 0 (keep every pose) or a gate of 1 to 1000 noise sigmas, got {sigma!r}"
        )
    return value


def outlier_poses(
    whitened: ArrayLike, sigma: float = OUTLIER_SIGMA, measured_rows: ArrayLike | None = None
) -> tuple[np.ndarray, float]:
    """Flag poses whose whitened residual block (N, k) is beyond `sigma` noise sigmas.

    A pose's statistic d^2 = ||r_i||^2 is chi^2 with k degrees of freedom under the noise model; it
    is flagged when d^2 / s^2 exceeds the chi^2_k quantile with the two-sided normal tail
    probability of `sigma`. s^2 = max(1, median(d^2) / median(chi^2_k)) is a robust variance
    factor: unmodelled effects larger than the stated noise widen the gate instead of flagging
    every pose, and the outliers themselves cannot widen it. measured_rows (N,): the rows of each
    block that were measured (the others zero: a point not seen), its chi^2 degrees of freedom
    (then s^2 = max(1, median(d^2 / median(chi^2_k_i)))); default k. Returns (mask (N,), s).
    """
    blocks = np.asarray(whitened, dtype=float)
    if blocks.ndim != 2 or blocks.shape[0] == 0:
        raise InvalidInputError(f"outlier_poses: expected an (N, k) residual, got shape {blocks.shape}")
    if not np.all(np.isfinite(blocks)):
        raise InvalidInputError("outlier_poses: non-finite residual")
    k = blocks.shape[1]
    d2 = np.sum(blocks**2, axis=1)
    if measured_rows is None:
        chi2_median = 2.0 * float(scipy.special.gammaincinv(k / 2.0, 0.5))
        scale2 = max(1.0, float(np.median(d2)) / chi2_median)
        return d2 / scale2 > outlier_gate(sigma, k), float(np.sqrt(scale2))
    dof = np.asarray(measured_rows, dtype=int)
    medians = 2.0 * scipy.special.gammaincinv(dof / 2.0, 0.5)
    scale2 = max(1.0, float(np.median(d2 / medians)))
    gates = np.array([outlier_gate(sigma, int(d)) for d in dof])
    return d2 / scale2 > gates, float(np.sqrt(scale2))


@dataclass(frozen=True)
class ParameterSelection:
    """Columns chosen by forward selection scored by leave-one-pose-out prediction (PRESS).

    indices: chosen columns, sorted (forced ones included). press: sum over poses of the squared
    whitened leave-one-pose-out prediction error of that choice; press_all: the same with every
    candidate column; order / path: the columns in the order they were added and PRESS after each.
    tied: how many other set sizes on the path score within one standard error of the best (the
    paired per-pose differences): CV on few poses cannot separate them, and the report says so.
    """

    indices: tuple[int, ...]
    press: float
    press_all: float
    order: tuple[int, ...]
    path: tuple[float, ...]
    tied: int


def _loo_system(leverage: np.ndarray) -> np.ndarray:
    """I - H_ii for each k x k leverage block (..., N, k, k), kept off singular by 1e-12 I."""
    eye = np.eye(leverage.shape[-1])
    return eye - leverage + 1e-12 * eye


def _loo_press(residual: np.ndarray, leverage: np.ndarray) -> np.ndarray:
    """Per-pose squared LOO residuals (..., N): e_loo_i = (I - H_ii)^-1 e_i for each k-row block."""
    loo = np.linalg.solve(_loo_system(leverage), residual[..., None])[..., 0]
    return np.sum(loo**2, axis=-1)


def _candidate_press(inverse: np.ndarray, loo: np.ndarray, fitted: np.ndarray, units: np.ndarray) -> np.ndarray:
    """PRESS of the current fit with each candidate direction added, without a solve per candidate.

    inverse (N, k, k): M_i = (I - H_ii)^-1 of the current fit (`_loo_system`); loo (N, k): its LOO
    residuals w_i = M_i e_i; fitted (N, k): its residual blocks e_i; units (N, k, c): the candidates'
    unit directions, orthogonal to the fitted columns. Adding u lowers every residual block by
    g u_i (g = u . e over every row) and raises H_ii by u_i u_i^T, a rank-one change of each block,
    so by Sherman-Morrison the new LOO residual is w_i + v_i (u_i . w_i - g) / (1 - u_i . v_i) with
    v_i = M_i u_i: one k x k product per pose and candidate instead of a k x k solve. Returns (c,).
    """
    v = inverse @ units
    along = np.einsum("nkc,nkc->nc", units, v)
    onto_loo = np.einsum("nkc,nk->nc", units, loo)
    g = np.einsum("nkc,nk->c", units, fitted)
    shift = (onto_loo - g) / np.maximum(1.0 - along, 1e-12)  # 1 - u.v > 0 while I - H_ii - u u^T is regular
    trial = loo[..., None] + v * shift[:, None, :]
    return np.einsum("nkc,nkc->c", trial, trial)


# Columns per in-place update of `forward_selection`'s projected Jacobian (temporaries of this width).
_UPDATE_COLUMNS = 8


def _column_norms_of(matrix: np.ndarray) -> np.ndarray:
    """2-norm of every column, without the (m, p) temporary of np.linalg.norm(axis=0)."""
    return np.sqrt(np.einsum("ij,ij->j", matrix, matrix))


def project_out(matrix: np.ndarray, basis: np.ndarray) -> None:
    """matrix -= basis basis^T matrix, in place, a few columns at a time (orthonormal basis columns)."""
    if basis.shape[1] == 0:
        return
    for start in range(0, matrix.shape[1], _UPDATE_COLUMNS):
        block = matrix[:, start : start + _UPDATE_COLUMNS]
        block -= basis @ (basis.T @ block)


def without_column(matrix: np.ndarray, column: int) -> np.ndarray:
    """`matrix` without `column`: the later columns shifted left in place, a few at a time, and a view
    of the first p - 1 returned (np.delete would copy the whole matrix)."""
    for start in range(column, matrix.shape[1] - 1, _UPDATE_COLUMNS):
        stop = min(start + _UPDATE_COLUMNS, matrix.shape[1] - 1)
        matrix[:, start:stop] = matrix[:, start + 1 : stop + 1].copy()
    return matrix[:, :-1]


def forward_selection(
    jacobian: ArrayLike,
    residual: ArrayLike,
    rows_per_pose: int,
    candidates: Sequence[int],
    forced: Sequence[int] | np.ndarray = (),
    *,
    rank_tolerance: float = 1e-9,
    overwrite: bool = False,
) -> ParameterSelection:
    """Greedy forward selection of columns of the whitened linear model r + J dx (m = N k rows).

    Starting from `forced`, each step adds the candidate column whose least-squares fit has the
    smallest leave-one-pose-out PRESS; the hat matrix gives every LOO residual without a refit
    (e_loo_i = (I - H_ii)^-1 e_i, H_ii the pose's k x k block), and a candidate changes each
    block by rank one, so it is scored from the current (I - H_ii)^-1 without a solve
    (`_candidate_press`); the path's PRESS is solved afresh at each step. The whole path is scored and the
    set with the lowest PRESS is chosen: a parameter enters only where it predicts left-out poses
    better, not merely fits the training set better.

    overwrite=True lets a column-major float64 `jacobian` be the projected copy itself (its columns
    are overwritten): the selection then holds no second matrix of every row.
    """
    J = _as_matrix(jacobian, "jacobian")
    r = _as_rows(residual, J.shape[0], "residual")
    k = int(rows_per_pose)
    n = J.shape[0] // k
    if n * k != J.shape[0]:
        raise InvalidInputError(f"forward_selection: {J.shape[0]} rows are not a multiple of {k} per pose")
    chosen = [int(c) for c in forced]
    basis = np.linalg.qr(J[:, chosen])[0] if chosen else np.zeros((J.shape[0], 0))
    fitted = r - basis @ (basis.T @ r)
    leverage = np.einsum("nia,nja->nij", basis.reshape(n, k, -1), basis.reshape(n, k, -1))
    per_pose = [_loo_press(fitted.reshape(n, k), leverage)]
    remaining = [int(c) for c in candidates if int(c) not in chosen]
    # The one copy of the Jacobian, column-major so that the in-place updates below run on contiguous columns.
    in_place = overwrite and J.flags.f_contiguous and remaining == [c for c in range(J.shape[1]) if c not in chosen]
    if in_place:
        projected = J
        for column in sorted(chosen, reverse=True):  # the forced columns out, the others kept in order
            projected = without_column(projected, column)
    else:
        projected = np.empty((J.shape[0], len(remaining)), order="F")
        for position, column in enumerate(remaining):
            projected[:, position] = J[:, column]
    norms = np.zeros(J.shape[1])
    norms[remaining] = _column_norms_of(projected)  # as the lengths below: a column is never longer than itself
    project_out(projected, basis)
    chunk = max(1, int(5e5 // max(1, n * k)))  # candidates per batch: about 4 MB per (N, k, c) stack
    while remaining:
        lengths = _column_norms_of(projected)
        alive = lengths > rank_tolerance * np.maximum(norms[remaining], 1e-300)
        if not alive.any():
            break
        inverse = np.linalg.inv(_loo_system(leverage))
        loo = (inverse @ fitted.reshape(n, k, 1))[..., 0]
        scores = np.full(len(remaining), np.inf)
        for start in range(0, len(remaining), chunk):
            block = np.arange(start, min(start + chunk, len(remaining)))
            block = block[alive[block]]
            if not block.size:
                continue
            units = (projected[:, block] / lengths[block]).reshape(n, k, block.size)
            scores[block] = _candidate_press(inverse, loo, fitted.reshape(n, k), units)
        best = best_index(scores, largest=False)
        u = projected[:, best] / lengths[best]
        fitted = fitted - u * (u @ fitted)
        leverage = leverage + np.einsum("ni,nj->nij", u.reshape(n, k), u.reshape(n, k))
        per_pose.append(_loo_press(fitted.reshape(n, k), leverage))
        chosen.append(remaining.pop(best))
        projected = without_column(projected, best)
        project_out(projected, u[:, None])
    path = np.array([p.sum() for p in per_pose])
    best_size = int(np.argmin(path))
    differences = np.array(per_pose) - per_pose[best_size]
    standard_error = differences.std(axis=1, ddof=1) * np.sqrt(n) if n > 1 else np.zeros(len(path))
    tied = int(np.count_nonzero(path - path[best_size] <= standard_error)) - 1
    added = tuple(chosen[len(forced) :])
    return ParameterSelection(
        indices=tuple(sorted(chosen[: len(forced) + best_size])),
        press=float(path[best_size]),
        press_all=float(path[-1]),
        order=added,
        path=tuple(float(v) for v in path),
        tied=tied,
    )


# --------------------------------------------------------------------------------------------------
# Linear least squares


@dataclass(frozen=True)
class LinearFit:
    """Result of a (weighted) linear least-squares fit y ~ A x.

    x: minimum-norm solution (parameter units).
    residual_rms: RMS of the unweighted residual y - A x (units of y).
    variance_factor: chi^2 / (m - rank) of the weighted residual; about 1 when the weights are the
        true inverse noise standard deviations (the a-posteriori check of the noise model).
    covariance: (p, p) parameter covariance, see `batch_least_squares`; std: sqrt of its diagonal.
    rank: numerical rank of the weighted A.
    """

    x: np.ndarray
    residual_rms: float
    variance_factor: float
    covariance: np.ndarray
    std: np.ndarray
    rank: int


def batch_least_squares(
    A: ArrayLike,
    y: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    rcond: float = 1e-12,
    covariance_from: Literal["noise_model", "residuals"] | None = None,
) -> LinearFit:
    """Solve min || W (A x - y) || (paper eq. 32) by SVD of W A, never forming A^T A.

    weights: per-row 1/sigma (W = diag(weights)); None means unit weights.
    rcond: singular values below rcond * s_max are treated as zero, which yields the minimum-norm
        solution when A is rank deficient (the unobservable combination is left at zero).
    covariance_from: "noise_model" gives (A^T W^2 A)^+, exact when the weights are the true
        inverse standard deviations; "residuals" scales it by the variance factor s^2 estimated
        from the residuals. Default: "noise_model" when weights are given, else "residuals".
    """
    A = _as_matrix(A, "A")
    m, p = A.shape
    y = _as_rows(y, m, "y")
    w = _as_weights(weights, m, "weights")
    if covariance_from is None:
        covariance_from = "noise_model" if w is not None else "residuals"
    A_w = A if w is None else A * w[:, None]
    y_w = y if w is None else y * w
    u, s, vt = np.linalg.svd(A_w, full_matrices=False)
    if s.size == 0 or s[0] == 0.0:
        raise IdentificationError("batch_least_squares: A is identically zero")
    rank = int(np.count_nonzero(s > rcond * s[0]))
    v_r = vt[:rank].T
    x = v_r @ ((u[:, :rank].T @ y_w) / s[:rank])
    residual = A @ x - y
    weighted = residual if w is None else residual * w
    dof = m - rank
    variance_factor = float(weighted @ weighted / dof) if dof > 0 else float("nan")
    covariance = (v_r / s[:rank] ** 2) @ v_r.T
    if covariance_from == "residuals":
        if dof <= 0:
            raise IdentificationError("batch_least_squares: no redundancy to estimate the noise from residuals")
        covariance = covariance * variance_factor
    return LinearFit(
        x=x,
        residual_rms=float(np.sqrt(residual @ residual / m)),
        variance_factor=variance_factor,
        covariance=covariance,
        std=np.sqrt(np.diag(covariance)),
        rank=rank,
    )


class RecursiveLeastSquares:
    """Streaming least squares, one block of rows (e.g. one pose) at a time (paper section 5).

    Kept in square-root information form: an upper-triangular R and vector z with
    R^T R = sum_k lambda^(K-k) A_k^T W_k^2 A_k and R^T z the matching right-hand side, updated by a
    QR of [sqrt(lambda) R, sqrt(lambda) z; W A_k, W y_k]. This is algebraically the classic
    covariance-form RLS (P = (R^T R)^-1, gain K = P A^T ...) without its loss of symmetry and
    positivity in floating point, and without a large made-up initial covariance: with no prior
    the estimate after K blocks equals the batch solution of all K blocks (minimum-norm while the
    data are still rank deficient).

    forgetting_factor lambda in (0, 1] discounts old blocks geometrically; the default 1 keeps all.
    prior_mean / prior_std optionally add x ~ N(prior_mean, diag(prior_std^2)) as initial information.
    """

    def __init__(
        self,
        n_parameters: int,
        *,
        forgetting_factor: float = 1.0,
        prior_mean: ArrayLike | None = None,
        prior_std: ArrayLike | None = None,
        rcond: float = 1e-12,
    ) -> None:
        if n_parameters < 1:
            raise InvalidInputError(f"RecursiveLeastSquares: n_parameters must be >= 1, got {n_parameters}")
        if not 0.0 < forgetting_factor <= 1.0:
            raise InvalidInputError(f"RecursiveLeastSquares: forgetting_factor {forgetting_factor} not in (0, 1]")
        self._n = n_parameters
        self._sqrt_lambda = float(np.sqrt(forgetting_factor))
        self._rcond = rcond
        # Augmented factor [R z; 0 rho]: rho^2 accumulates the weighted residual sum of squares.
        self._factor = np.zeros((n_parameters + 1, n_parameters + 1))
        self._rows = 0
        if prior_std is not None:
            std = np.broadcast_to(np.asarray(prior_std, dtype=float), (n_parameters,))
            if np.any(std <= 0.0) or not np.all(np.isfinite(std)):
                raise InvalidInputError("RecursiveLeastSquares: prior_std must be positive and finite")
            mean = np.zeros(n_parameters) if prior_mean is None else _as_rows(prior_mean, n_parameters, "prior_mean")
            self._factor[:n_parameters, :n_parameters] = np.diag(1.0 / std)
            self._factor[:n_parameters, n_parameters] = mean / std
        elif prior_mean is not None:
            raise InvalidInputError("RecursiveLeastSquares: prior_mean needs prior_std")
        self._x = self._solve()  # before any row: the prior mean, or zero (minimum norm) without a prior

    @property
    def n_rows(self) -> int:
        """Number of measurement rows absorbed so far."""
        return self._rows

    @property
    def estimate(self) -> np.ndarray:
        """Current (minimum-norm) least-squares estimate, a copy."""
        return self._x.copy()

    @property
    def information_factor(self) -> np.ndarray:
        """Upper-triangular R with R^T R the (weighted, discounted) information matrix, a copy."""
        return self._factor[: self._n, : self._n].copy()

    @property
    def covariance(self) -> np.ndarray:
        """(R^T R)^+: the parameter covariance under the weights' noise model."""
        r = self._factor[: self._n, : self._n]
        r_pinv = np.linalg.pinv(r, rcond=self._rcond)
        return r_pinv @ r_pinv.T

    @property
    def weighted_residual_sum_of_squares(self) -> float:
        """sum over absorbed rows of (w (a x - y))^2 at the current estimate (exact, not approximated)."""
        return float(self._factor[self._n, self._n] ** 2)

    def update(self, A_k: ArrayLike, y_k: ArrayLike, weights_k: ArrayLike | None = None) -> np.ndarray:
        """Absorb a block of rows A_k x ~ y_k (weights_k: per-row 1/sigma); return the new estimate."""
        A_k = _as_matrix(np.atleast_2d(A_k), "A_k")
        if A_k.shape[1] != self._n:
            raise InvalidInputError(f"A_k: expected {self._n} columns, got {A_k.shape[1]}")
        y_k = _as_rows(y_k, A_k.shape[0], "y_k")
        w = _as_weights(weights_k, A_k.shape[0], "weights_k")
        block = np.hstack([A_k, y_k[:, None]])
        if w is not None:
            block = block * w[:, None]
        stacked = np.vstack([self._sqrt_lambda * self._factor, block])
        r = scipy.linalg.qr(stacked, mode="r", check_finite=False)[0]
        size = min(r.shape[0], self._n + 1)
        self._factor = np.zeros((self._n + 1, self._n + 1))
        self._factor[:size] = r[:size]
        self._rows += A_k.shape[0]
        self._x = self._solve()
        return self._x.copy()

    def _solve(self) -> np.ndarray:
        r = self._factor[: self._n, : self._n]
        z = self._factor[: self._n, self._n]
        diag = np.abs(np.diag(r))
        if diag.min() > self._rcond * diag.max():
            return scipy.linalg.solve_triangular(r, z, check_finite=False)
        return np.linalg.lstsq(r, z, rcond=self._rcond)[0]


# --------------------------------------------------------------------------------------------------
# Levenberg-Marquardt on a manifold

State = TypeVar("State")


class LeastSquaresProblem(Protocol[State]):
    """A nonlinear least-squares problem min 1/2 ||r(state)||^2 over a manifold of states.

    residual_and_jacobian: whitened residual r (m,) and its Jacobian (m, p) with respect to a
        tangent step dx at `state`, i.e. r(retract(state, dx)) = r + J dx + O(dx^2).
    A problem may also define `residual(state) -> r` (same r, no Jacobian): trial steps then use
    it, and the Jacobian is only computed for accepted steps; and `release(state)`, called on an
    iterate once a step from it is accepted, to drop what it cached for that step.
    retract: the state moved by the tangent step dx (p,), e.g. T(0) <- T(0) exp6(dx) (eq. 33).
    """

    def residual_and_jacobian(self, state: State) -> tuple[np.ndarray, np.ndarray]: ...

    def retract(self, state: State, step: np.ndarray) -> State: ...


@dataclass(frozen=True)
class LMResult(Generic[State]):
    """Outcome of `levenberg_marquardt`.

    cost_history: 1/2 ||r||^2 at the start and after every accepted step.
    termination: which test stopped the iteration: "gradient", "step", "cost" (converged), or
        "max_iterations", "stalled" (no damping value lowers the cost; not converged).
    converged: one of the first three tests was met.
    step_norm: 2-norm of the last computed step (parameter units).
    """

    state: State
    iterations: int
    cost: float
    cost_history: tuple[float, ...]
    converged: bool
    termination: str
    step_norm: float


@dataclass(frozen=True)
class LMSettings:
    """The settings of `levenberg_marquardt` (its docstring gives each test): a calibration keeps its
    own with its result, so that cross-validation refits each fold the same way."""

    max_iterations: int = 50
    cost_tolerance: float = 1e-12
    absolute_cost_tolerance: float = 0.0
    initial_damping: float = 1e-3
    unit_damping: bool = False
    step_tolerance: float = 1e-12
    gradient_tolerance: float = 1e-12


def levenberg_marquardt(
    problem: LeastSquaresProblem[State],
    x0: State,
    settings: LMSettings = LMSettings(),
) -> LMResult[State]:
    """Minimise 1/2 ||r||^2 with Levenberg-Marquardt steps applied through `problem.retract`; the
    names below are the fields of `settings`.

    Step: argmin ||r + J dx||^2 + mu ||D dx||^2 with D^2 = diag(J^T J) (Marquardt's scaling, so mu
    is unit free), or with unit_damping D = max_j ||J_j|| I: damped in the parameters' own units, so
    that among nearly equivalent directions the step is the shortest, and a direction the data
    barely see is not scaled up and driven far (along a curved set of equivalent models). Solved
    through a QR of J and a small QR of [R; sqrt(mu) D] per damping value.
    Damping follows Nielsen: on acceptance (actual decrease > 0) mu *= max(1/3, 1 - (2 rho - 1)^3),
    on rejection mu *= nu and nu doubles, rho being actual over predicted decrease.
    Stops when ||J^T r||_inf <= gradient_tolerance, when a step has ||dx|| <= step_tolerance
    (parameter units), or when an accepted step lowers the cost by less than cost_tolerance times
    the cost or by less than absolute_cost_tolerance (for a whitened residual, in units of noise
    variance: a decrease far below one cannot be told from noise). An iteration is one accepted step,
    however many damping trials it took, and one Jacobian evaluation, at its start; a run that stops
    on the cost test returns before evaluating the Jacobian at its last iterate, which decides nothing
    here (a problem with `residual` leaves it to a later caller).
    """
    state = x0
    # Optional cheaper residual for trial steps (rejected steps then cost no Jacobian), and an
    # optional hook dropping a superseded iterate's caches (the caller may still hold x0).
    residual_only = getattr(problem, "residual", None)
    release = getattr(problem, "release", None)
    r, J = problem.residual_and_jacobian(state)
    cost = 0.5 * float(r @ r)
    history = [cost]
    mu = settings.initial_damping
    nu = 2.0
    step_norm = float("nan")
    for iteration in range(1, settings.max_iterations + 1):
        gradient = J.T @ r
        if not np.all(np.isfinite(gradient)):
            raise IdentificationError(f"levenberg_marquardt: non-finite gradient at iteration {iteration}")
        if np.max(np.abs(gradient), initial=0.0) <= settings.gradient_tolerance:
            return LMResult(state, iteration - 1, cost, tuple(history), True, "gradient", step_norm)
        # R and Q^T r from a QR of [J r] in row blocks: the memory of J's Q is never needed.
        augmented_factor = triangular_factor(J, r)
        size = min(augmented_factor.shape[0], J.shape[1])
        rj, qtr = augmented_factor[:size, :-1], augmented_factor[:size, -1]
        scale = _column_norms_of(J)
        scale = np.maximum(scale, 1e-12 * max(scale.max(), 1e-300))
        if settings.unit_damping:
            scale = np.full_like(scale, scale.max())
        p = J.shape[1]
        while True:
            augmented = np.vstack([rj, np.sqrt(mu) * np.diag(scale)])
            rhs = np.concatenate([-qtr, np.zeros(p)])
            dx = np.linalg.lstsq(augmented, rhs, rcond=None)[0]
            step_norm = float(np.linalg.norm(dx))
            if step_norm <= settings.step_tolerance:
                return LMResult(state, iteration, cost, tuple(history), True, "step", step_norm)
            j_dx = rj @ dx
            predicted = -float(qtr @ j_dx) - 0.5 * float(j_dx @ j_dx)
            trial = problem.retract(state, dx)
            if residual_only is not None:  # the Jacobian only if the step is accepted
                r_trial, J_trial = residual_only(trial), None
            else:
                r_trial, J_trial = problem.residual_and_jacobian(trial)
            cost_trial = 0.5 * float(r_trial @ r_trial)
            decrease = cost - cost_trial
            if decrease > 0.0 and np.isfinite(cost_trial):
                rho = decrease / predicted if predicted > 0.0 else 0.0
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                if release is not None:
                    release(state)
                del J  # the superseded iterate's Jacobian, before the next one is built
                state, cost = trial, cost_trial
                history.append(cost)
                if decrease <= max(settings.cost_tolerance * (cost + decrease), settings.absolute_cost_tolerance):
                    # Decided by the cost alone: the new iterate's Jacobian (when not yet evaluated) is
                    # left to whoever needs it.
                    return LMResult(state, iteration, cost, tuple(history), True, "cost", step_norm)
                r, J = (r_trial, J_trial) if J_trial is not None else problem.residual_and_jacobian(trial)
                break
            mu *= nu
            nu *= 2.0
            if mu > 1e30:
                # No step along the descent direction lowers the cost although the gradient test
                # failed: the Jacobian is inconsistent with the residual, or rounding dominates.
                return LMResult(state, iteration, cost, tuple(history), False, "stalled", step_norm)
    return LMResult(state, settings.max_iterations, cost, tuple(history), False, "max_iterations", step_norm)
