"""Static poses from streams: stationary stretches, their averages, and pairing two clocks.

A tracker records 100+ frames a second while a calibration needs one pose per posture. A frame
is *still* when the position (or the joint vector) half a window before and after it differ by
less than `speed_limit` times the window: noise barely moves that difference, a moving arm does.
Consecutive still frames lasting `min_duration` make a dwell; each dwell is averaged (positions by
their mean, orientations by the quaternion mean, the largest eigenvector of sum q q^T) and its
scatter kept as a per-pose noise figure.

Tracker dwells are paired with the robot log's stops either by order or by a clock offset: the
offset that puts the most tracker dwell midpoints inside a robot stop (every midpoint difference is
a candidate), refined as the median difference of the pairs it makes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from m3t1r.errors import InvalidInputError

__all__ = [
    "Stretch",
    "ClockPairing",
    "stationary_stretches",
    "average_positions",
    "average_quaternions",
    "pair_by_clock",
    "pair_by_order",
]


@dataclass(frozen=True)
class Stretch:
    """Samples start .. stop-1 of a stream (stop exclusive) and their time span [s]."""

    start: int
    stop: int
    t_start: float
    t_end: float

    @property
    def midpoint(self) -> float:
        """Middle of the time span [s]."""
        return 0.5 * (self.t_start + self.t_end)


@dataclass(frozen=True)
class ClockPairing:
    """Tracker dwell k paired with robot stop pairs[k] (-1: none); offset: robot clock minus
    tracker clock [s]."""

    pairs: tuple[int, ...]
    offset: float

    @property
    def paired(self) -> int:
        """Number of tracker dwells with a robot stop."""
        return sum(1 for p in self.pairs if p >= 0)


def stationary_stretches(
    times: np.ndarray, values: np.ndarray, speed_limit: float, min_duration: float, window: float = 0.5
) -> list[Stretch]:
    """The still stretches of a stream (module docstring). times (N,) [s], increasing; values (N, d)
    [m or rad], NaN rows where nothing was seen (skipped; a gap over `window` ends a stretch), or
    several markers (N, K, 3) [m], NaN where a marker was not seen: a frame is then still when every
    marker seen at both ends of its window moved less than the limit (a marker coming into view
    moves nothing); speed_limit [m/s or rad/s]; min_duration, window [s]."""
    if np.any(np.diff(times) <= 0):
        raise InvalidInputError("the sample times do not increase: cannot find still stretches")
    points = values if values.ndim == 3 else values[:, None, :]
    seen = np.flatnonzero(np.any(np.all(np.isfinite(points), axis=2), axis=1))
    if len(seen) < 2:
        return []
    t, x = times[seen], points[seen]
    lo = np.searchsorted(t, t - window / 2, side="left")
    hi = np.minimum(np.searchsorted(t, t + window / 2, side="right") - 1, len(t) - 1)
    span = np.maximum(t[hi] - t[lo], 1e-12)
    moved = np.linalg.norm(x[hi] - x[lo], axis=2)  # (M, K), NaN where a marker is missing at an end
    fastest = np.max(np.where(np.isfinite(moved), moved, -np.inf), axis=1)
    speed = np.where(np.isfinite(fastest), fastest, np.inf) / span  # no marker seen at both ends: not still
    still = (speed < speed_limit) & (hi > lo)
    stretches, k = [], 0
    while k < len(t):
        if not still[k]:
            k += 1
            continue
        end = k
        while end + 1 < len(t) and still[end + 1] and t[end + 1] - t[end] <= window:
            end += 1
        if t[end] - t[k] >= min_duration:
            stretches.append(Stretch(int(seen[k]), int(seen[end]) + 1, float(t[k]), float(t[end])))
        k = end + 1
    return stretches


def average_positions(positions: np.ndarray) -> tuple[np.ndarray, float, int]:
    """(mean (3,) [m], scatter: RMS distance of the samples from it [m], samples used) over the
    finite rows of positions (n, 3)."""
    seen = positions[np.all(np.isfinite(positions), axis=1)]
    if len(seen) == 0:
        return np.full(3, np.nan), float("nan"), 0
    mean = seen.mean(axis=0)
    return mean, float(np.sqrt(np.mean(np.sum((seen - mean) ** 2, axis=1)))), len(seen)


def average_quaternions(quaternions: np.ndarray) -> np.ndarray:
    """The mean unit quaternion (x, y, z, w) of the finite rows of quaternions (n, 4): the largest
    eigenvector of sum q q^T, which q and -q (the same rotation) weigh alike."""
    seen = quaternions[np.all(np.isfinite(quaternions), axis=1)]
    if len(seen) == 0:
        return np.full(4, np.nan)
    seen = seen / np.linalg.norm(seen, axis=1, keepdims=True)
    vector = np.linalg.eigh(seen.T @ seen)[1][:, -1]
    return vector if vector[3] >= 0 else -vector


def pair_by_order(n_tracker: int, n_robot: int) -> ClockPairing:
    """Dwell k with stop k; InvalidInputError when the counts differ (pairing by order would shift
    every pose after the first extra one)."""
    if n_tracker != n_robot:
        raise InvalidInputError(
            f"{n_tracker} tracker dwells but {n_robot} robot stops: they cannot be paired by "
            "order (give both clocks, so that convert pairs them by time, or tune --still-speed "
            "and --min-dwell)"
        )
    return ClockPairing(tuple(range(n_tracker)), 0.0)


def pair_by_clock(tracker: list[Stretch], robot: list[Stretch]) -> ClockPairing:
    """The clock offset and the pairs it makes (module docstring): InvalidInputError when no offset
    pairs half the dwells."""
    if not tracker or not robot:
        raise InvalidInputError(f"{len(tracker)} tracker dwells and {len(robot)} robot stops: nothing to pair")
    mid_t = np.array([s.midpoint for s in tracker])
    starts, ends = np.array([s.t_start for s in robot]), np.array([s.t_end for s in robot])
    mid_r = 0.5 * (starts + ends)
    best: tuple[int, float, float] | None = None
    for offset in np.unique((mid_r[None, :] - mid_t[:, None]).ravel()):
        pairs = _inside(mid_t + offset, starts, ends)
        count = int(np.count_nonzero(pairs >= 0))
        spread = float(np.sum(np.abs(mid_r[pairs[pairs >= 0]] - mid_t[pairs >= 0] - offset)))
        if best is None or count > best[0] or (count == best[0] and spread < best[1]):
            best = (count, spread, float(offset))
    assert best is not None
    pairs = _inside(mid_t + best[2], starts, ends)
    matched = pairs >= 0
    offset = float(np.median(mid_r[pairs[matched]] - mid_t[matched]))
    pairs = _inside(mid_t + offset, starts, ends)
    pairs = _unique(pairs, mid_t + offset, mid_r)
    if np.count_nonzero(pairs >= 0) < max(1, len(tracker) // 2):
        raise InvalidInputError(
            f"no clock offset pairs half of the {len(tracker)} tracker dwells with the "
            f"{len(robot)} robot stops: the logs may not be of the same session"
        )
    return ClockPairing(tuple(int(p) for p in pairs), offset)


def _inside(times: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Index of the interval [starts, ends] (sorted, disjoint) holding each time, or -1."""
    index = np.searchsorted(starts, times, side="right") - 1
    hit = (index >= 0) & (times <= ends[np.maximum(index, 0)])
    return np.where(hit, index, -1)


def _unique(pairs: np.ndarray, shifted: np.ndarray, mid_r: np.ndarray) -> np.ndarray:
    """Where two tracker dwells fall in one robot stop, keep the one nearest its middle."""
    out = pairs.copy()
    for stop in np.unique(pairs[pairs >= 0]):
        rivals = np.flatnonzero(pairs == stop)
        if len(rivals) > 1:
            keep = rivals[np.argmin(np.abs(shifted[rivals] - mid_r[stop]))]
            out[rivals[rivals != keep]] = -1
    return out
