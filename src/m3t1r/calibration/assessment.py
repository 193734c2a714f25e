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

import numpy as np
import pinocchio as pin

from m3t1r.calibration.measurement_setup import register_frame
from m3t1r.errors import IdentificationError

__all__ = ["FitRejected", "MAX_NOISE_RATIO", "HOPELESS_RESIDUAL", "check_fit", "check_start", "likely_causes", "describe_parameter",
           "fit_movement_notes", "coverage_notes"]

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
    """The fit is not supported by the data; `causes` lists the likely reasons, most likely first."""

    def __init__(self, reason: str, causes: Sequence[str] = ()) -> None:
        self.reason = reason
        self.causes = list(causes)
        lines = [reason] + [f"  likely cause: {cause}" for cause in self.causes]
        lines.append("  nothing was written (--force writes it anyway)")
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


def check_start(points: np.ndarray, measured: np.ndarray, frame_estimated: bool,
                causes: Callable[[], list[str]], what: str = "machine") -> None:
    """Raise FitRejected, with `causes()`, when the nominal model's predicted points (N, 3) are
    more than HOPELESS_RESIDUAL RMS from the measured ones, after a rigid registration when the
    frame is estimated: no build error explains that, and a fit would only wander."""
    if frame_estimated:
        rms = _registered_rms(points, measured)[0]
    else:
        rms = float(np.sqrt(np.mean(np.sum((points - measured) ** 2, axis=1))))
    if rms > HOPELESS_RESIDUAL:
        raise FitRejected(f"the nominal {what} is {rms:.3g} m RMS from the measurements"
                          + (" after registering the frame" if frame_estimated else "")
                          + f", beyond any build error ({HOPELESS_RESIDUAL:g} m): the fit was not attempted", causes())


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
    causes = []
    spread = float(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))))
    measured_spread = float(np.sqrt(np.mean(np.sum((target - target.mean(0)) ** 2, axis=1))))
    ratio = measured_spread / max(spread, 1e-12)
    if 300.0 < ratio < 3000.0:
        causes.append(f"positions look like millimetres (spread {ratio:.0f} times the model's): use --units mm")
    elif 1 / 3000.0 < ratio < 1 / 300.0:
        causes.append(f"positions look like metres (spread 1/{1 / ratio:.0f} of the model's): drop --units mm")
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
