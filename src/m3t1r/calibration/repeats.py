"""Repeats of one pose: rows that measure the same posture, held out together in cross-validation.

A campaign often measures a posture more than once (a tracker's frames of one dwell kept as rows,
a posture revisited). Such rows share their error from unmodelled effects, so a row held out while
its repeat stays in training is predicted too well: cross-validation would be optimistic. Rows
form one group when they have the same `source` (the tracker file's line, frame or message that
`m3t1r convert` writes) or joint readings that agree within `REPEAT_TOLERANCE` in every joint
(transitively). Folds are then drawn over groups, so that a group is held out whole.

The closed-loop and serial cross-validations (`closed_loop.cross_validate`,
`serial_evaluation.cross_validate_serial`) split their inlier poses here (`inlier_folds`) and
report one record (`CrossValidation`, errors from `fold_errors`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from m3t1r.errors import InvalidInputError, require_count
from m3t1r.metrics import PoseErrors

__all__ = [
    "MAX_PADDING",
    "REPEAT_TOLERANCE",
    "CrossValidation",
    "InlierFolds",
    "fold_errors",
    "grouped_blocks",
    "grouped_folds",
    "inlier_folds",
    "pose_groups",
]

#: Joint readings within this of each other in every joint [rad or m] are one posture: a robot's
#: repeatability is well above it, and distinct postures of a calibration are far more than it apart.
REPEAT_TOLERANCE = 1e-4


def _first_seen_labels(keys: np.ndarray) -> np.ndarray:
    """(N,) labels 0, 1, ... of the distinct rows of keys (N, d), numbered in order of first appearance."""
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return np.argsort(np.argsort(first))[inverse.reshape(-1)]


def pose_groups(
    readings: ArrayLike, sources: ArrayLike | None = None, tolerance: float = REPEAT_TOLERANCE
) -> np.ndarray:
    """(N,) group label of each row (module docstring), numbered 0, 1, ... in order of first appearance.

    readings: (N, n) joint readings [rad or m]; sources: (N,) the rows' `source` values, or None.
    Readings are compared on a grid of `tolerance`: two rows within it in every joint and in the
    same grid cell share a group.
    """
    q = np.asarray(readings, dtype=float)
    if q.ndim != 2 or not np.all(np.isfinite(q)):
        raise InvalidInputError(f"pose_groups: expected finite (N, n) readings, got shape {q.shape}")
    if not tolerance > 0:
        raise InvalidInputError(f"pose_groups: tolerance must be positive, got {tolerance}")
    labels = _first_seen_labels(np.round(q / tolerance).astype(np.int64))
    if sources is None:
        return labels
    by_source = _first_seen_labels(np.asarray(sources).reshape(-1, 1))
    # Union of the two partitions: each source label joins the reading groups of its rows.
    parent = np.arange(len(q))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    for partition in (labels, by_source):
        first_of: dict[int, int] = {}
        for i, label in enumerate(partition.tolist()):
            j = first_of.setdefault(label, i)
            parent[root(i)] = root(j)
    return _first_seen_labels(np.array([root(i) for i in range(len(q))]).reshape(-1, 1))


def grouped_folds(groups: ArrayLike, folds: int, rng: np.random.Generator) -> np.ndarray:
    """(N,) fold of each row, whole groups to a fold: the groups (labels of `pose_groups`, renumbered
    by first appearance) are permuted by `rng` and dealt round the folds. With every row its own
    group this is `rng.permutation(N) % folds`."""
    labels = _first_seen_labels(np.asarray(groups).reshape(-1, 1))
    n_groups = int(labels.max()) + 1 if len(labels) else 0
    if n_groups < folds:
        raise InvalidInputError(
            f"cross-validation: {folds} folds need at least {folds} distinct poses "
            f"(repeats of a pose count once), got {n_groups}"
        )
    return (rng.permutation(n_groups) % folds)[labels]


class InlierFolds(NamedTuple):
    """The k-fold split of a calibration's inlier poses: inliers (M,) their indices among the N poses,
    fold (M,) the fold of each, groups the number of groups of repeats they form."""

    inliers: np.ndarray
    fold: np.ndarray
    groups: int


def inlier_folds(active: np.ndarray, folds: int, seed: int, groups: ArrayLike | None = None) -> InlierFolds:
    """Deal the poses `active` (N,) keeps to `folds` folds, whole groups of `groups` (N,) labels
    (`pose_groups`; None: every pose its own) to a fold, by `grouped_folds` with seed `seed`.
    InvalidInputError for fewer than 2 folds, fewer than 2 inlier poses per fold, labels of another
    length, or fewer distinct poses than folds."""
    inliers = np.flatnonzero(active)
    if folds < 2 or len(inliers) < 2 * folds:
        raise InvalidInputError(f"cross-validation: {folds} folds need at least {2 * folds} inlier poses")
    labels = np.arange(len(active)) if groups is None else np.asarray(groups)
    if labels.shape != active.shape:
        raise InvalidInputError(f"cross-validation: {labels.shape} group labels for {len(active)} poses")
    fold = grouped_folds(labels[inliers], folds, np.random.default_rng(require_count(seed, "seed", minimum=0)))
    return InlierFolds(inliers, fold, len(np.unique(labels[inliers])))


@dataclass(frozen=True)
class CrossValidation:
    """k-fold prediction of held-back measurements (outliers excluded), of a closed-loop or a serial
    calibration: each fold is refitted on the others (same parameters, same setup estimation, from the
    same start) and predicts its poses' measurements in the measurement frame. The errors include the
    measurement noise, as a fresh validation set of the same quality does. errors: per inlier pose,
    position [m] and rotation [rad] (nan when position-only); with several points per pose, per point
    seen on an inlier pose (position only). groups: how many groups of repeats the inlier poses form,
    each held out whole; the number of inlier poses when no groups were given."""

    errors: PoseErrors
    folds: int
    groups: int = 0


def fold_errors(residuals: np.ndarray, seen_points: np.ndarray | None = None) -> PoseErrors:
    """The `CrossValidation` errors of held-out residual blocks (M, k) [m, rad], k = 6 or 3 (position
    only): per pose, the position error's norm and the rotation error's angle (nan when k = 3); with
    seen_points (M, P), which of P points per pose were seen (k = 3 P), per point seen, position only."""
    if seen_points is not None:
        position = np.linalg.norm(residuals.reshape(len(residuals), -1, 3), axis=2)[seen_points]
        return PoseErrors(position, np.full(len(position), np.nan))
    position = np.linalg.norm(residuals[:, :3], axis=1)
    rotation = np.linalg.norm(residuals[:, 3:], axis=1) if residuals.shape[1] == 6 else np.full(len(position), np.nan)
    return PoseErrors(position, rotation)


#: Grouped rows may grow by padding to at most this multiple of the rows; beyond, poses are left
#: out one at a time (a campaign with one posture repeated hundreds of times among single ones).
MAX_PADDING = 2.0


def grouped_blocks(
    jacobian: np.ndarray, residual: np.ndarray, rows_per_pose: int, groups: ArrayLike | None
) -> tuple[np.ndarray, np.ndarray, int]:
    """The rows of N poses (N k rows of `jacobian` and `residual`, pose after pose) rearranged so that
    each group of `groups` (N,) is one block, padded with zero rows to the largest group's size:
    (jacobian, residual, rows per block) for a leave-one-block-out score (`forward_selection`),
    which then leaves each group out whole. A zero row changes no fit and no leave-out residual.
    The inputs are returned as they are when every pose is its own group, when `groups` is None, or
    when padding would exceed MAX_PADDING times the rows."""
    k = int(rows_per_pose)
    if groups is None:
        return jacobian, residual, k
    labels = _first_seen_labels(np.asarray(groups).reshape(-1, 1))
    counts = np.bincount(labels)
    if counts.max() == 1 or len(counts) * counts.max() > MAX_PADDING * len(labels):
        return jacobian, residual, k
    size = int(counts.max())
    order = np.argsort(labels, kind="stable")
    slot = np.arange(len(labels)) - np.repeat(np.cumsum(counts) - counts, counts)  # position within its group
    rows = (k * (labels[order] * size + slot))[:, None] + np.arange(k)
    source = (k * order)[:, None] + np.arange(k)
    out_j = np.zeros((len(counts) * size * k, jacobian.shape[1]))
    out_r = np.zeros(len(counts) * size * k)
    out_j[rows.reshape(-1)] = jacobian[source.reshape(-1)]
    out_r[rows.reshape(-1)] = residual[source.reshape(-1)]
    return out_j, out_r, size * k
