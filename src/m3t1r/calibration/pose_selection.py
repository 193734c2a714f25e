"""Choice of calibration poses that make the parameters as identifiable as possible.

Given per-candidate blocks A_i (rows x parameters) of the whitened identification Jacobian, pick
N candidates S maximising the D-optimality criterion log det M_S, M_S = sum_{i in S} A_i^T A_i,
over the base (identifiable) parameters. Maximising det M shrinks the volume of the parameter
confidence ellipsoid, sigma^2 M^-1 (whitened rows), which is what the held-out error of a
calibrated model follows once the noise dominates.

Search: greedy forward selection, then exchange (Cook and Nachtsheim's modified Fedorov
algorithm: each selected pose in turn is swapped for the candidate that raises log det the
most) until a full pass improves nothing. Both steps use the matrix determinant lemma,
    log det(M + A^T A) = log det M + log det(I_r + A M^-1 A^T),
evaluated for every candidate at once from one Cholesky factor of M.

Nothing here knows about robots except the two helpers that build blocks for the closed-loop
machine (`closed_loop_candidate_blocks`) and for a serial chain (`serial_candidate_blocks`), and
the closed-loop model's reference pose set, which `plan` and `calibrate` judge poses by (`reference_base`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
import scipy.linalg
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.identification import (
    IDENTIFIABILITY_TOLERANCE,
    REFERENCE_POSES,
    REFERENCE_SEED,
    BaseParameters,
    best_index,
    select_base_parameters,
)
from m3t1r.calibration.measurements import TrackerNoise, assembled_from_home
from m3t1r.errors import InvalidInputError
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import SerialChain, forward_and_error_jacobians
from m3t1r.model.workspace import workspace_actuators

__all__ = [
    "PoseSelection",
    "closed_loop_candidate_blocks",
    "information_log_det",
    "observability_index",
    "reference_base",
    "select_poses",
    "serial_candidate_blocks",
]

#: Ridge added to the normalised information matrix while it is still singular (fewer rows than
#: parameters during the first greedy steps). With unit-RMS columns, one pose contributes O(1) to
#: each diagonal entry, so 1e-9 only breaks ties between rank-deficient sets and is invisible in
#: log det once the set identifies everything.
_RIDGE = 1e-9
#: An exchange must raise log det by more than this [nepers] to count; rounding in the rank-r
#: update formula is far below it, so the search cannot cycle on ties.
_MIN_GAIN = 1e-9


@dataclass(frozen=True)
class PoseSelection:
    """Outcome of `select_poses`.

    indices: selected candidate indices, sorted ascending.
    log_det: log det M of the selected set [nepers], M = sum A_i^T A_i over the base columns,
        each column scaled to unit RMS over the candidate set (see `select_poses`); -inf when
        the set leaves a base parameter unidentified.
    observability_index: O1 = (s_1 ... s_m)^(1/m) / sqrt(N) of the same normalised, stacked
        Jacobian (Borm and Menq), N the number of selected poses; 0 when rank deficient.
    condition_number: s_1 / s_m of that matrix (inf when rank deficient).
    history: log det (with the tie-breaking ridge) after each greedy addition, then after each
        accepted exchange; non-decreasing from the first full-rank entry on.
    n_exchanges: accepted swaps; passes: exchange passes over the selected set (the last one
        made no swap, unless the pass limit stopped the search).
    columns: the base parameter columns of the input blocks the criterion uses.
    column_scale: the factor applied to each of those columns (inverse RMS over candidates).
    """

    indices: tuple[int, ...]
    log_det: float
    observability_index: float
    condition_number: float
    history: tuple[float, ...]
    n_exchanges: int
    passes: int
    columns: tuple[int, ...]
    column_scale: np.ndarray = field(repr=False)

    @property
    def n_poses(self) -> int:
        return len(self.indices)


def _as_blocks(blocks: ArrayLike) -> np.ndarray:
    array = np.asarray(blocks, dtype=float)
    if array.ndim == 2:  # one row per candidate
        array = array[:, None, :]
    if array.ndim != 3 or 0 in array.shape:
        raise InvalidInputError(f"candidate blocks: expected shape (n_candidates, rows, parameters), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidInputError(
            f"candidate blocks: non-finite value in candidate "
            f"{int(np.flatnonzero(~np.isfinite(array).all(axis=(1, 2)))[0])}"
        )
    return array


def _normalised(blocks: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The base columns scaled to unit RMS per candidate, and the scale factors.

    D-optimal choices do not depend on this scaling (it adds a constant to log det); it keeps the
    reported log det and O1 free of units (m versus rad) and the Cholesky factors well scaled.
    """
    kept = blocks[:, :, columns]
    rms = np.sqrt(np.einsum("irp,irp->p", kept, kept) / blocks.shape[0])
    if np.any(rms == 0.0):
        raise InvalidInputError("candidate blocks: a base column is zero over every candidate")
    return kept / rms, 1.0 / rms


def _log_det_chol(matrix: np.ndarray) -> tuple[float, np.ndarray]:
    """log det of a symmetric positive definite matrix and its lower Cholesky factor."""
    factor = scipy.linalg.cholesky(matrix, lower=True, check_finite=False)
    return 2.0 * float(np.sum(np.log(np.diag(factor)))), factor


def _gains(factor: np.ndarray, stacked: np.ndarray, n_rows: int) -> np.ndarray:
    """log det(I + A_i M^-1 A_i^T) for every candidate, with M = L L^T (L = factor).

    stacked: all candidate rows (n_candidates * n_rows, m). B = L^-1 A^T gives
    A M^-1 A^T = B^T B per candidate; the r x r log det is taken in one batched call.
    """
    b = scipy.linalg.solve_triangular(factor, stacked.T, lower=True, check_finite=False)
    b = b.T.reshape(-1, n_rows, factor.shape[0])
    small = b @ b.transpose(0, 2, 1)
    small[:, np.arange(n_rows), np.arange(n_rows)] += 1.0
    sign, value = np.linalg.slogdet(small)
    return np.where(sign > 0, value, -np.inf)


def information_log_det(blocks: ArrayLike, indices: Sequence[int]) -> float:
    """log det(sum_{i in indices} A_i^T A_i) [nepers] of raw blocks; -inf when singular."""
    array = _as_blocks(blocks)
    stacked = array[np.asarray(indices, dtype=int)].reshape(-1, array.shape[2])
    sign, value = np.linalg.slogdet(stacked.T @ stacked)
    return float(value) if sign > 0 else -math.inf


def observability_index(jacobian: ArrayLike, n_poses: int) -> float:
    """O1 = (s_1 s_2 ... s_m)^(1/m) / sqrt(n_poses) of a stacked Jacobian (rows, m), m its columns.

    The geometric mean of the singular values, per square root of pose count so that repeating
    the same poses does not raise it. Zero when a column combination is unobserved.
    """
    matrix = np.asarray(jacobian, dtype=float)
    singular = np.linalg.svd(matrix, compute_uv=False)
    if singular.size < matrix.shape[1] or singular[-1] <= 0.0:
        return 0.0
    return float(np.exp(np.mean(np.log(singular))) / math.sqrt(n_poses))


@on_one_blas_thread  # matrices of a few hundred entries: BLAS threads only add wake-ups
def select_poses(
    blocks: ArrayLike,
    n_poses: int,
    *,
    columns: Sequence[int] | None = None,
    initial: Sequence[int] | None = None,
    rank_tolerance: float = IDENTIFIABILITY_TOLERANCE,
    max_passes: int = 50,
) -> PoseSelection:
    """Choose `n_poses` of the candidates maximising log det of the information matrix.

    blocks: (n_candidates, rows, parameters) whitened Jacobian block of each candidate pose (rows
        per pose, e.g. 6 for a full pose); a 2-D array means one row per candidate.
    columns: the parameter columns to judge identifiability on; default: the base parameters of
        all candidates stacked (column-pivoted QR, relative tolerance `rank_tolerance`, which also
        decides whether the selected poses identify them: log det -inf otherwise).
    initial: a starting set of `n_poses` distinct candidates for the exchange search; default:
        the greedy forward selection.
    max_passes: cap on exchange passes (each tries every selected position once).

    Each candidate is used at most once. The result is a local optimum of the exchange
    neighbourhood (no single swap improves it), usually the global one for well-spread candidates.
    """
    array = _as_blocks(blocks)
    n_candidates, n_rows, n_parameters = array.shape
    if not 1 <= n_poses <= n_candidates:
        raise InvalidInputError(f"select_poses: n_poses must be in [1, {n_candidates}], got {n_poses}")
    if columns is None:
        names = [f"p{k}" for k in range(n_parameters)]
        columns = select_base_parameters(
            array.reshape(-1, n_parameters), names, rank_tolerance, max_condition=math.inf
        ).indices
    chosen_columns = np.asarray(columns, dtype=int)
    if chosen_columns.size == 0 or chosen_columns.min() < 0 or chosen_columns.max() >= n_parameters:
        raise InvalidInputError(f"select_poses: columns must index the {n_parameters} parameters")
    normalised, scale = _normalised(array, chosen_columns)
    m = chosen_columns.size
    stacked = normalised.reshape(-1, m)

    def outer(indices: int | list[int]) -> np.ndarray:
        """sum of A_i^T A_i over the given candidates (computed on demand: a stored (n, m, m)
        stack would grow to hundreds of MB for large candidate sets)."""
        rows = normalised[indices].reshape(-1, m)
        return rows.T @ rows

    ridge = _RIDGE * np.eye(m)
    history: list[float] = []

    if initial is None:
        selected: list[int] = []
        information = ridge.copy()
        for _ in range(n_poses):
            log_det, factor = _log_det_chol(information)
            gains = _gains(factor, stacked, n_rows)
            gains[selected] = -np.inf
            best = best_index(gains)  # ties (symmetric candidates) to the lower index
            selected.append(best)
            information += outer(best)
            history.append(log_det + float(gains[best]))
    else:
        selected = [int(i) for i in initial]
        if (
            len(selected) != n_poses
            or len(set(selected)) != n_poses
            or min(selected) < 0
            or max(selected) >= n_candidates
        ):
            raise InvalidInputError(f"select_poses: initial must be {n_poses} distinct candidate indices")
        information = ridge + outer(selected)
        history.append(_log_det_chol(information)[0])

    exchanges = passes = 0
    current = _log_det_chol(information)[0]
    while passes < max_passes:
        passes += 1
        swapped = False
        for position in range(n_poses):
            leaving = selected[position]
            reduced = information - outer(leaving)
            try:
                reduced_log_det, factor = _log_det_chol(reduced)
            except np.linalg.LinAlgError:
                continue  # the pose carries the only information on some direction: keep it
            gains = _gains(factor, stacked, n_rows)
            gains[selected] = -np.inf
            best = best_index(gains)  # ties (symmetric candidates) to the lower index
            candidate = reduced_log_det + float(gains[best])
            if candidate > current + _MIN_GAIN:
                selected[position] = best
                information = reduced + outer(best)
                # Recompute rather than accumulate: rank-r updates drift over many swaps.
                current = _log_det_chol(information)[0]
                history.append(current)
                exchanges += 1
                swapped = True
        if not swapped:
            break

    indices = tuple(sorted(selected))
    chosen = normalised[list(indices)].reshape(-1, m)
    singular = np.linalg.svd(chosen, compute_uv=False)
    # The selection identifies the columns by the rule calibration applies to the same rows.
    kept = select_base_parameters(chosen, [f"p{k}" for k in range(m)], rank_tolerance, max_condition=math.inf)
    full_rank = kept.rank == m
    return PoseSelection(
        indices=indices,
        log_det=float(2.0 * np.sum(np.log(singular))) if full_rank else -math.inf,
        observability_index=observability_index(chosen, n_poses) if full_rank else 0.0,
        condition_number=float(singular[0] / singular[-1]) if full_rank else math.inf,
        history=tuple(history),
        n_exchanges=exchanges,
        passes=passes,
        columns=tuple(int(c) for c in chosen_columns),
        column_scale=scale,
    )


# --------------------------------------------------------------------------------------------------
# Blocks for the two kinds of machine


def _pose_residual_rows(
    position: np.ndarray, rotation: np.ndarray, twist_rows: np.ndarray, position_only: bool
) -> np.ndarray:
    """Residual rows of the calibration (position in WORLD, orientation in the tool frame) per
    unit parameter, at a pose where model and measurement agree (Jlog3 = I there)."""
    point = twist_rows[:3] + np.cross(twist_rows[3:], position[:, None], axis=0)  # dp = v + w x p
    if position_only:
        return point
    return np.vstack((point, rotation.T @ twist_rows[3:]))


@on_one_blas_thread
def closed_loop_candidate_blocks(
    mechanism: Mechanism,
    actuators: ArrayLike,
    noise: TrackerNoise | None = None,
    *,
    position_only: bool = False,
    error_model: ClosedLoopErrorModel | None = None,
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Whitened identification blocks (n, rows, P) of the closed-loop machine at slider sets (n, 4) [m].

    Rows are those `calibrate_closed_loop` fits (position [m] then orientation [rad], each divided
    by the tracker noise of `noise`; default `TrackerNoise()`), evaluated on
    `mechanism` (the nominal model: the truth is unknown when poses are chosen). Each slider set
    is assembled from home, so all candidates lie on the home branch. Returns blocks and the
    parameter names of the error model.
    """
    noise = noise or TrackerNoise()
    error_model = error_model or ClosedLoopErrorModel(mechanism)
    solver = ClosedLoopSolver(mechanism)
    weights = np.r_[np.full(3, 1.0 / noise.position), np.full(3, 1.0 / noise.rotation)]
    rows = 3 if position_only else 6
    sliders = np.atleast_2d(np.asarray(actuators, dtype=float))
    configurations = list(assembled_from_home(mechanism, sliders).q)
    sensitivities = error_model.platform_sensitivities(solver, configurations)
    blocks = np.array(
        [
            _pose_residual_rows(pose[:3, 3], pose[:3, :3], dxi, position_only)
            for pose, dxi in zip(sensitivities.poses, sensitivities.twist_jacobians)
        ]
    )
    return blocks * weights[:rows, None], error_model.names


def reference_base(
    mechanism: Mechanism,
    whitened_jacobian: Callable[[np.ndarray], np.ndarray],
    names: Sequence[str],
    *,
    fixed: Sequence[int] = (),
    forced: Sequence[int] | np.ndarray = (),
    rank_tolerance: float = IDENTIFIABILITY_TOLERANCE,
) -> BaseParameters:
    """What a closed-loop model can identify whatever the user's poses: the one measure by which
    `plan` chooses poses and `calibrate` judges them. The base parameters of `whitened_jacobian(actuators)`
    (the whitened rows of every pose stacked, one column per name of `names`) at the reference pose
    set, `REFERENCE_POSES` slider sets [m or rad] of seed `REFERENCE_SEED` drawn in the workspace box
    (`workspace_actuators`), with the `fixed` columns zeroed and the `forced` ones (the measurement
    setup's, the gauge) kept first. A direction barely above `rank_tolerance` is identified on more
    rows and not on fewer, so plan and calibrate must measure on this same set. The reference set's
    own weak directions are what it measures: no PoorExcitationWarning."""
    actuators = workspace_actuators(mechanism, REFERENCE_POSES, np.random.default_rng(REFERENCE_SEED))
    jacobian = whitened_jacobian(actuators)
    jacobian[:, list(fixed)] = 0.0
    return select_base_parameters(jacobian, names, rank_tolerance, max_condition=math.inf, forced=forced)


def serial_candidate_blocks(
    model: pin.Model,
    chain: SerialChain,
    q_chain: ArrayLike,
    noise: TrackerNoise | None = None,
    *,
    position_only: bool = False,
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Whitened identification blocks (n, rows, 6(joints+1)) of a serial chain at configurations (n, joints).

    Same rows as `calibrate_serial` with exact joint readings: tool position [m] in the base frame
    and orientation [rad] in the tool frame, divided by the tracker noise of `noise` (default
    `TrackerNoise()`).
    Returns blocks and `chain.parameter_names()`.
    """
    noise = noise or TrackerNoise()
    poses, jacobians = forward_and_error_jacobians(chain, model, q_chain)
    weights = np.r_[np.full(3, 1.0 / noise.position), np.full(3, 1.0 / noise.rotation)]
    rows = 3 if position_only else 6
    blocks = np.array(
        [_pose_residual_rows(g.translation, g.rotation, j, position_only) for g, j in zip(poses, jacobians)]
    )
    return blocks * weights[:rows, None], chain.parameter_names()
