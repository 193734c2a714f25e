"""Judging a fit: refuse what the data do not support, name the likely cause, say what is weak.

Used by `m3t1r calibrate` for closed-loop and serial machines alike:
- `check_fit` refuses a fit that did not converge or whose residual the stated noise cannot
  explain (RMS over `MAX_NOISE_RATIO` times the noise, i.e. variance factor over its square);
- `likely_causes` looks at the data against the nominal model for the usual mistakes: positions
  in millimetres, data in another frame, swapped reading columns, data of another machine;
- `weak_parameters` and `fit_movement_notes` say in plain words what the data could not
  determine and when a fit barely moved or moved implausibly far.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from m3t1r.calibration.measurement_setup import register_frame
from m3t1r.errors import IdentificationError

__all__ = ["FitRejected", "MAX_NOISE_RATIO", "HOPELESS_RESIDUAL", "MAX_GROSS_SHARE", "SMALL_RESIDUAL", "StartCheck",
           "check_fit", "check_start", "gross_reading_reason", "likely_causes", "residual_causes",
           "quaternion_order_causes", "metres_as_millimetres_causes", "describe_parameter", "fit_movement_notes",
           "coverage_notes"]

#: A fit is accepted while its whitened residual RMS is at most this many times the stated noise
#: (variance factor <= 9): a margin for small unmodelled effects, far below a wrong unit, frame,
#: column order or machine, which leave residuals of millimetres to metres.
MAX_NOISE_RATIO = 3.0
#: Beyond these a placement "moved implausibly far" for a machine built to drawing [m], [rad].
IMPLAUSIBLE_TRANSLATION, IMPLAUSIBLE_ROTATION = 0.02, 0.1

_COMPONENTS = ("translation along x", "translation along y", "translation along z",
               "rotation about x", "rotation about y", "rotation about z")


#: The nominal model this far from the data (RMS, after the frame registration when estimated) is
#: beyond any manufacturing error: the fit is not attempted [m].
HOPELESS_RESIDUAL = 0.1


class FitRejected(IdentificationError):
    """The fit is not supported by the data; `causes` lists the likely reasons, most likely first.

    forceable: whether `calibrate --force` would write something (a fit that ran and was judged);
    a fit refused before it ran (`check_start`) has nothing to write, and the message says so."""

    def __init__(self, reason: str, causes: Sequence[str] = (), forceable: bool = True) -> None:
        self.reason = reason
        self.causes = list(causes)
        self.forceable = forceable
        lines = [reason] + [f"  likely cause: {cause}" for cause in self.causes]
        lines.append("  nothing was written" + (" (--force writes it anyway)" if forceable else ""))
        super().__init__("\n".join(lines))


def check_fit(converged: bool, termination: str, iterations: int, variance_factor: float,
              causes: Sequence[str] = (), max_noise_ratio: float = MAX_NOISE_RATIO) -> None:
    """Raise FitRejected when LM did not converge or the residual is not explained by the noise."""
    if not converged:
        raise FitRejected(f"the fit did not converge ({termination} after {iterations} iterations; "
                          "--max-iterations raises the cap)", causes)
    if not np.isfinite(variance_factor) or variance_factor > max_noise_ratio**2:
        ratio = float(np.sqrt(variance_factor)) if np.isfinite(variance_factor) else float("nan")
        raise FitRejected(f"the residual is {ratio:.3g} times the stated noise (accepted up to "
                          f"{max_noise_ratio:g}): the model does not explain the data", list(causes) or [
                              "effects the geometric model does not hold (compliance, thermal drift), or a "
                              "noise smaller than the data's: state a realistic noise with --noise-pos/--noise-rot"])


#: More than this share of the poses beyond HOPELESS_RESIDUAL is no longer a few gross readings:
#: the data as a whole do not fit the model.
MAX_GROSS_SHARE = 0.25


@dataclass(frozen=True)
class StartCheck:
    """How far the nominal model starts from the data: `distances` (N,) [m] from each predicted
    point to its measured one (after a registration robust to gross readings when the frame is
    estimated), their median `typical` [m], and `gross`: the poses beyond HOPELESS_RESIDUAL, which
    no build error explains (a reading gone wrong), to be left out before the fit."""

    distances: np.ndarray
    typical: float
    gross: tuple[int, ...]


def check_start(points: np.ndarray, measured: np.ndarray, frame_estimated: bool,
                causes: Callable[[], list[str]], what: str = "machine") -> StartCheck:
    """Judge the nominal model's predicted points (N, 3) against the measured ones [m].

    Robust to a few gross readings: the typical (median) pose decides, and a pose far beyond any
    build error is returned in `gross` rather than blamed on the model. Raises FitRejected, with
    `causes()`, when the typical pose is more than HOPELESS_RESIDUAL away, or when more than
    MAX_GROSS_SHARE of the poses are: no build error explains that, and a fit would only wander.
    """
    distances = _start_distances(points, measured, frame_estimated)
    typical = float(np.median(distances))
    gross = np.flatnonzero(distances > HOPELESS_RESIDUAL)
    if typical > HOPELESS_RESIDUAL or len(gross) > MAX_GROSS_SHARE * len(distances):
        share = "" if typical > HOPELESS_RESIDUAL else f"; {len(gross)} of {len(distances)} poses are beyond it"
        raise FitRejected(f"the nominal {what} is {typical:.3g} m from the measurements (median over the poses"
                          + (", after registering the frame" if frame_estimated else "")
                          + f"), beyond any build error ({HOPELESS_RESIDUAL:g} m){share}: the fit was not attempted",
                          causes(), forceable=False)
    return StartCheck(distances, typical, tuple(int(i) for i in gross))


def gross_reading_reason(check: StartCheck, index: int) -> str:
    """Why pose `index` of `check.gross` is a gross reading, in plain words."""
    return (f"the measured point is {check.distances[index]:.3g} m from the nominal prediction, where the "
            f"median pose is {check.typical:.3g} m: a gross reading (beyond any build error, "
            f"{HOPELESS_RESIDUAL:g} m), not a fault of the model")


def _start_distances(points: np.ndarray, measured: np.ndarray, frame_estimated: bool) -> np.ndarray:
    """Distances [m] of the predicted points to the measured ones; with the frame estimated, after a
    registration on the poses within three times the median distance, repeated until that set is
    stable (a reading 1 m or 1 km off then moves the frame no more than any other pose)."""
    if not frame_estimated:
        return np.linalg.norm(points - measured, axis=1)
    keep = np.ones(len(points), dtype=bool)
    for _ in range(10):
        frame = _registered_rms(points[keep], measured[keep])[1]
        distances = np.linalg.norm(points @ frame.rotation.T + frame.translation - measured, axis=1)
        closest = distances <= 3.0 * np.median(distances)
        if np.count_nonzero(closest) < 3 or np.array_equal(closest, keep):
            break
        keep = closest
    return distances


def describe_parameter(name: str) -> str:
    """'q22.dt[3]' -> 'q22 rotation about x' (components of a right-multiplied [v; w] error)."""
    placement, _, rest = name.rpartition(".dt[")
    if not placement or not rest.endswith("]") or not rest[:-1].isdigit() or int(rest[:-1]) > 5:
        return name
    return f"{placement} {_COMPONENTS[int(rest[:-1])]}"


def _registered_rms(points: np.ndarray, measured: np.ndarray) -> tuple[float, pin.SE3]:
    homogeneous = np.tile(np.eye(4), (len(points), 1, 1))
    homogeneous[:, :3, 3] = points
    frame = register_frame(homogeneous, measured)
    moved = points @ frame.rotation.T + frame.translation
    return float(np.sqrt(np.mean(np.sum((moved - measured) ** 2, axis=1)))), frame


def likely_causes(predict: Callable[[np.ndarray], np.ndarray], readings: np.ndarray, measured: np.ndarray,
                  names: Sequence[str], *, frame_estimated: bool) -> list[str]:
    """The usual mistakes, tested against the nominal model, most telling first.

    predict: readings (N, k) -> measured points (N, 3) the nominal model predicts in its base frame
    (NaN rows where a reading set does not assemble); measured: (N, 3) [m] as read; names: the
    reading columns. Each check compares the data with the model up to a rigid registration.
    """
    points = predict(readings)
    valid = np.all(np.isfinite(points), axis=1)
    if np.count_nonzero(valid) < 4:
        return ["the readings do not assemble on this machine: columns in another order or unit, or another machine"]
    points, target = points[valid], measured[valid]
    spread = float(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))))
    measured_spread = float(np.sqrt(np.mean(np.sum((target - target.mean(0)) ** 2, axis=1))))
    ratio = measured_spread / max(spread, 1e-12)
    # A wrong unit is the whole story: the frame and column checks below would only misread its scale.
    if 300.0 < ratio < 3000.0:
        return [f"positions look like millimetres (spread {ratio:.0f} times the model's): use --units mm"]
    if 1 / 3000.0 < ratio < 1 / 300.0:
        return [f"positions look like metres (spread 1/{1 / ratio:.0f} of the model's): drop --units mm"]
    causes = []
    registered, frame = _registered_rms(points, target)
    direct = float(np.sqrt(np.mean(np.sum((points - target) ** 2, axis=1))))
    if not frame_estimated and direct > 5.0 * registered and direct > 0.02:
        angle = np.degrees(np.linalg.norm(pin.log3(frame.rotation)))
        causes.append(f"the data look like they are in another frame (a rigid registration moves them "
                      f"{np.linalg.norm(frame.translation):.3g} m and {angle:.3g} deg and leaves {registered:.3g} m "
                      "RMS): use --frame estimate")
    causes += _swapped_position_columns(points, target, registered, direct, frame_estimated)
    causes += _swapped_columns(predict, readings, measured, names, registered)
    if not causes and registered > 0.02:
        causes.append(f"the data do not fit this machine even after a rigid registration ({registered:.3g} m RMS): "
                      "data from another machine, or the wrong model files")
    return causes


#: A fit leaving less than this RMS [m], [rad] fits the data to sub-millimetre: what is left is a
#: noise larger than stated or small unmodelled effects, not a wrong setup.
SMALL_RESIDUAL = 1e-3


def residual_causes(position_rms: float, rotation_rms: float, noise_position: float, noise_rotation: float,
                    *, marker_given: bool, position_only: bool) -> list[str]:
    """Causes of a fitted residual the stated noise does not explain, judged by its size [m, rad]
    (rotation_rms NaN with positions only): a small one is the noise, stated too small; a large
    one with orientation data and no marker given is a measured frame that is not the platform's."""
    rotation_small = position_only or not np.isfinite(rotation_rms) or rotation_rms <= SMALL_RESIDUAL
    if position_rms <= SMALL_RESIDUAL and rotation_small:
        rotation = "" if position_only else f" / {rotation_rms:.2g} rad"
        stated = f"{noise_position:g} m" + ("" if position_only else f" / {noise_rotation:g} rad")
        return [f"the fit leaves {position_rms:.2g} m{rotation} RMS, close to the data but more than the stated noise "
                f"({stated}): if the tracker is that noisy, state it with --noise-pos/--noise-rot; otherwise small "
                "effects the geometric model does not hold (compliance, thermal drift)"]
    if marker_given or position_only:
        return []
    return ["the measured frame (a probe or a set of reflectors) is not the platform frame: give its position with "
            "--marker X Y Z, and its orientation is estimated with it"]


def quaternion_order_causes(predicted_poses: np.ndarray, measured_positions: np.ndarray,
                            measured_rotations: np.ndarray, *, frame_estimated: bool) -> list[str]:
    """Whether the file's quaternion columns (qx, qy, qz, qw) hold w, x, y, z instead (scalar first).

    predicted_poses (N, 4, 4): the measured frame as the nominal model puts it in its base;
    measured_positions (N, 3) [m] and measured_rotations (N, 3, 3) as read. With the measurement
    frame F (registered on the positions when estimated, else the identity), R_F^T R_measured,i =
    R_predicted,i R_marker: the same rotation R_marker at every pose. Its spread over the poses is
    compared as read and with the four numbers re-ordered."""
    if len(predicted_poses) < 3:
        return []
    frame = register_frame(predicted_poses, measured_positions).rotation if frame_estimated else np.eye(3)
    predicted = frame @ np.asarray(predicted_poses)[:, :3, :3]

    def spread(measured: np.ndarray) -> float:
        marker = np.swapaxes(predicted, 1, 2) @ measured
        u, _, vt = np.linalg.svd(marker.sum(axis=0))
        mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        return float(np.mean([np.linalg.norm(pin.log3(mean.T @ m)) for m in marker]))

    read = np.array([pin.Quaternion(r).coeffs() for r in measured_rotations])  # the file's four numbers
    reordered = np.array([pin.Quaternion(w, x, y, z).normalized().matrix() for w, x, y, z in read])
    as_read, fixed = spread(np.asarray(measured_rotations)), spread(reordered)
    if as_read > 100 * SMALL_RESIDUAL and fixed < as_read / 5:
        return [f"the quaternion columns look like w, x, y, z (scalar first) under the names qx, qy, qz, qw (scalar "
                f"last): read in that order, the measured orientations follow the model's to {fixed:.2g} rad instead "
                f"of {as_read:.2g} rad (mean); reorder the columns"]
    return []


def metres_as_millimetres_causes(predict: Callable[[np.ndarray], np.ndarray], readings: np.ndarray,
                                  measured: np.ndarray, length_readings: np.ndarray, *, frame_estimated: bool
                                  ) -> list[str]:
    """Whether a file read with --units mm holds metres: the readings (N, k) and measured points
    (N, 3) [m] as read, `length_readings` (k,) the reading columns that --units scaled (prismatic
    joints). With every length scaled back by 1000, does the nominal model explain the points far
    better? (Sliders scaled too keep the spreads alike, which the spread test cannot see.)"""
    def rms(points: np.ndarray, target: np.ndarray) -> float:
        valid = np.all(np.isfinite(points), axis=1)
        if np.count_nonzero(valid) < max(4, 0.9 * len(points)):
            return float("inf")
        if frame_estimated:
            return _registered_rms(points[valid], target[valid])[0]
        return float(np.sqrt(np.mean(np.sum((points[valid] - target[valid]) ** 2, axis=1))))

    as_read = rms(predict(readings), measured)
    in_metres = rms(predict(readings * np.where(length_readings, 1e3, 1.0)), measured * 1e3)
    if in_metres < as_read / 5.0 and np.isfinite(in_metres):
        return [f"the file looks like metres: read without --units mm, the nominal model explains the positions "
                f"{as_read / max(in_metres, 1e-12):.0f} times better ({in_metres:.3g} m RMS); drop --units mm"]
    return []


def _swapped_position_columns(points: np.ndarray, measured: np.ndarray, registered: float, direct: float,
                              frame_estimated: bool) -> list[str]:
    """x, y, z columns in another order. In the base frame the order itself is tested. Against an
    estimated frame only a mirror shows (a swap mirrors the points, which no rigid frame undoes;
    every swap is the same mirror up to a rotation, so which two columns cannot be told)."""
    if frame_estimated:
        rms = _registered_rms(points, measured[:, [1, 0, 2]])[0]
        if rms < registered / 5.0:
            return [f"two of the x, y, z columns look swapped (the data are a mirror image of the model's; read "
                    f"mirrored, the nominal model explains them {registered / max(rms, 1e-12):.0f} times better)"]
        return []
    found = []
    for order in itertools.permutations(range(3)):
        rms = float(np.sqrt(np.mean(np.sum((points - measured[:, list(order)]) ** 2, axis=1))))
        if order != (0, 1, 2) and rms < direct / 5.0:
            names = ", ".join("xyz"[k] for k in order)
            found.append((rms, f"the position columns look like they hold {names} in that order (the nominal model "
                               f"explains the data {direct / max(rms, 1e-12):.0f} times better read that way)"))
    return [text for _, text in sorted(found)[:1]]


def _swapped_columns(predict: Callable[[np.ndarray], np.ndarray], readings: np.ndarray, measured: np.ndarray,
                     names: Sequence[str], registered: float) -> list[str]:
    found = []
    for a, b in itertools.combinations(range(readings.shape[1]), 2):
        swapped = readings.copy()
        swapped[:, [a, b]] = swapped[:, [b, a]]
        points = predict(swapped)
        valid = np.all(np.isfinite(points), axis=1)
        if np.count_nonzero(valid) < max(4, 0.9 * len(points)):
            continue
        rms, _ = _registered_rms(points[valid], measured[valid])
        if rms < registered / 5.0:
            found.append((rms, f"columns '{names[a]}' and '{names[b]}' look swapped (with them exchanged the "
                               f"nominal model explains the data {registered / max(rms, 1e-12):.0f} times better)"))
    return [text for _, text in sorted(found)]


def fit_movement_notes(moved: dict[str, float], rms_before: float, rms_after: float,
                       measured_frame: str | None = None) -> list[str]:
    """Plain-word notes on how far the fit moved: implausibly far, or barely.

    moved: identified error per parameter name ([m] for translations, [rad] for rotations);
    rms_before / rms_after: position residual RMS [m] at the start and the end; measured_frame:
    the model frame the data measure, when no marker was estimated (its translating far means a
    reflector off that frame was taken for the machine's geometry).
    """
    notes, far = [], []
    for name, value in moved.items():
        translation = name.rpartition(".dt[")[2] in ("0]", "1]", "2]")
        limit = IMPLAUSIBLE_TRANSLATION if translation else IMPLAUSIBLE_ROTATION
        if abs(value) > limit:
            far.append((abs(value) / limit, f"{describe_parameter(name)} {value:+.3g} {'m' if translation else 'rad'}"))
    if far:
        listed = ", ".join(text for _, text in sorted(far, reverse=True)[:3])
        notes.append(f"the fit moved implausibly far for a machine built to drawing ({listed}): check the "
                     "units, the measurement frame, the reading columns and that the model is this machine's")
        frame_moved = [n for n, v in moved.items() if measured_frame and n.startswith(f"{measured_frame}.dt[")
                       and n[-2] in "012" and abs(v) > IMPLAUSIBLE_TRANSLATION]
        if frame_moved:
            notes.append(f"the measured frame {measured_frame} itself moved: the measured point is probably a "
                         "reflector off it, now baked into the machine; give its position with --marker X Y Z")
    if rms_before > 0 and rms_after > 0.8 * rms_before:
        notes.append(f"the fit barely moved (residual RMS {rms_before:.3g} -> {rms_after:.3g} m): the nominal "
                     "model already explains the data, or the poses do not excite the errors")
    return notes


def coverage_notes(values: np.ndarray, bounds: dict[str, tuple[float, float]], threshold: float = 0.5) -> list[str]:
    """Which task coordinates the poses cover poorly: values (N, len(bounds)) of the coordinates
    named by `bounds` (name -> (low, high) of the workspace); a coordinate whose measured range is
    below `threshold` of the workspace's is named with both ranges."""
    notes = []
    for k, (name, (low, high)) in enumerate(bounds.items()):
        span = float(np.ptp(values[:, k]))
        if high > low and span < threshold * (high - low):
            notes.append(f"{name} spans {values[:, k].min():.3g} .. {values[:, k].max():.3g} "
                         f"({100 * span / (high - low):.0f} % of the workspace's {low:.3g} .. {high:.3g})")
    return notes
