"""Judging a fit: refuse what the data do not support, name the likely cause, say what is weak.

Used by `m3t1r calibrate` for closed-loop and serial machines alike:
- `check_fit` refuses a fit that did not converge, or whose residual is beyond the stated noise
  (RMS over `MAX_NOISE_RATIO` times the noise, i.e. variance factor over its square) for a cause
  `likely_causes` names; a residual beyond the noise that no cause explains (effects the geometric
  model does not hold) is not refused but reported, `unexplained_residual_warning`;
- `likely_causes` looks at the data against the nominal model for the usual mistakes: positions
  in millimetres, data in another frame, swapped reading or position columns, data of another
  machine. Each check compares the data with the model after a registration that estimates the
  measurement frame (when it is estimated) and the measured point's offset from the model's
  measured frame (an unknown marker, which any fit absorbs), so that neither is taken for a mistake;
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

__all__ = ["FitRejected", "MAX_NOISE_RATIO", "HOPELESS_RESIDUAL", "Registration", "check_fit", "check_start",
           "likely_causes", "describe_parameter", "fit_movement_notes", "coverage_notes", "noise_from_residual",
           "register_with_offset",
           "unexplained_residual_warning"]

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
              causes: Sequence[str] = (), max_noise_ratio: float = MAX_NOISE_RATIO, *,
              noise_estimated: bool = False) -> bool:
    """Raise FitRejected when LM did not converge, when the variance factor is not finite, or when
    the residual is beyond `max_noise_ratio` times the noise and `causes` names why. With the noise
    estimated from the same residual (`noise_estimated`) the variance factor tests nothing, so any
    cause refuses the fit.

    Returns whether the residual is beyond the noise with no cause named: the fit stands (the
    model's unmodelled effects, or a noise larger than stated) but the caller must say so, with
    `unexplained_residual_warning`.
    """
    if not converged:
        raise FitRejected(f"the fit did not converge ({termination} after {iterations} iterations; "
                          "--max-iterations raises the cap)", causes)
    if not np.isfinite(variance_factor):
        raise FitRejected("the residual is nan times the stated noise: the model does not explain the data",
                          list(causes) or ["a reading or measurement the model cannot evaluate"])
    if noise_estimated and causes:
        raise FitRejected("the nominal model does not fit the data for a nameable reason (with the noise "
                          "estimated from the residual, the residual alone cannot tell)", causes)
    if variance_factor <= max_noise_ratio**2:
        return False
    if causes:
        raise FitRejected(f"the residual is {np.sqrt(variance_factor):.3g} times the stated noise (accepted up to "
                          f"{max_noise_ratio:g}): the model does not explain the data", causes)
    return True


def unexplained_residual_warning(variance_factor: float, implied_noise: str, validation_error: float) -> str:
    """The warning written with a fit whose residual is beyond the stated noise for no nameable
    cause. implied_noise: the noise the residuals imply, in words with units (the stated noise
    times sqrt(variance_factor)); validation_error: the cross-validated position error [m]."""
    return (f"the residual is {np.sqrt(variance_factor):.3g} times the stated noise (variance factor "
            f"{variance_factor:.3g}) and none of the usual mistakes explains it: effects the geometric model "
            f"does not hold (compliance, thermal drift) or a noisier tracker than stated. The residuals imply a "
            f"noise of {implied_noise}; the parameters' standard deviations assume the stated noise. Judge the "
            f"result by its cross-validated error, {validation_error:.3g} m (--noise-pos auto states the noise "
            "the data show)")


@dataclass(frozen=True)
class Registration:
    """The model's predictions moved onto the measurements: measured ~ frame (g_i offset).

    frame: the measurement frame (identity when it was not estimated); offset: (3,) the measured
    point in the model's measured frame beyond the given marker [m] (zero when not estimated);
    rms: the position RMS left [m]."""

    frame: pin.SE3
    offset: np.ndarray
    rms: float


def register_with_offset(poses: np.ndarray, measured: np.ndarray, *, estimate_frame: bool = True,
                         estimate_offset: bool = True, iterations: int = 30) -> Registration:
    """Least-squares registration of the model's measured frames `poses` (N, 4, 4) onto the
    measured positions (N, 3) [m]: the frame F (any rotation, from the closed-form start
    `register_frame`) and the offset o of the measured point in the measured frame, minimising
    sum |F (R_i o + p_i) - y_i|^2 by Gauss-Newton (minimum-norm steps: an offset the poses cannot
    tell from the frame stays at zero)."""
    rotations, positions = poses[:, :3, :3], poses[:, :3, 3]
    frame = register_frame(poses, measured) if estimate_frame else pin.SE3.Identity()
    offset = np.zeros(3)
    cost = _registration_cost(frame, offset, rotations, positions, measured)
    for _ in range(iterations if estimate_offset else 0):
        step = _registration_step(frame, offset, rotations, positions, measured, estimate_frame)
        trial_frame = pin.SE3(pin.exp3(step[:3]) @ frame.rotation, frame.translation + step[3:6])
        trial_offset = offset + step[6:]
        trial = _registration_cost(trial_frame, trial_offset, rotations, positions, measured)
        if not trial < cost:
            break
        converged = cost - trial <= 1e-12 * cost
        frame, offset, cost = trial_frame, trial_offset, trial
        if converged:
            break
    return Registration(frame, offset, float(np.sqrt(cost / max(len(measured), 1))))


def _registration_cost(frame: pin.SE3, offset: np.ndarray, rotations: np.ndarray, positions: np.ndarray,
                       measured: np.ndarray) -> float:
    points = (rotations @ offset + positions) @ frame.rotation.T + frame.translation
    return float(np.sum((points - measured) ** 2))


def _registration_step(frame: pin.SE3, offset: np.ndarray, rotations: np.ndarray, positions: np.ndarray,
                       measured: np.ndarray, estimate_frame: bool) -> np.ndarray:
    """The Gauss-Newton step [d_rotation (left, rad); d_translation; d_offset] (9,), frame part zero
    when the frame is fixed."""
    in_frame = (rotations @ offset + positions) @ frame.rotation.T
    residual = (in_frame + frame.translation - measured).reshape(-1)
    n = len(measured)
    jacobian = np.zeros((n, 3, 9))
    if estimate_frame:
        jacobian[:, :, :3] = -np.array([pin.skew(p) for p in in_frame])
        jacobian[:, :, 3:6] = np.eye(3)
    jacobian[:, :, 6:] = frame.rotation @ rotations
    return np.linalg.lstsq(jacobian.reshape(3 * n, 9), -residual, rcond=1e-10)[0]


def check_start(points: np.ndarray, measured: np.ndarray, frame_estimated: bool,
                causes: Callable[[], list[str]], what: str = "machine") -> None:
    """Raise FitRejected, with `causes()`, when the nominal model's predicted points (N, 3) are
    more than HOPELESS_RESIDUAL RMS from the measured ones, after a rigid registration when the
    frame is estimated: no build error explains that, and a fit would only wander. Given the
    predicted measured frames (N, 4, 4) instead, the registration also estimates the measured
    point's offset in them (an unknown marker is no build error either)."""
    poses, offset_free = _as_poses(points)
    if frame_estimated or offset_free:
        rms = register_with_offset(poses, measured, estimate_frame=frame_estimated, estimate_offset=offset_free).rms
    else:
        rms = float(np.sqrt(np.mean(np.sum((poses[:, :3, 3] - measured) ** 2, axis=1))))
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


def _as_poses(predicted: np.ndarray) -> tuple[np.ndarray, bool]:
    """(poses (N, 4, 4), whether the point's offset in them is free): points (N, 3) become frames
    without orientation, whose offset stays fixed."""
    predicted = np.asarray(predicted, dtype=float)
    if predicted.ndim == 3:
        return predicted, True
    poses = np.tile(np.eye(4), (len(predicted), 1, 1))
    poses[:, :3, 3] = predicted
    return poses, False


def _register(poses: np.ndarray, measured: np.ndarray, offset_free: bool, frame: bool = True) -> Registration:
    return register_with_offset(poses, measured, estimate_frame=frame, estimate_offset=offset_free)


def likely_causes(predict: Callable[[np.ndarray], np.ndarray], readings: np.ndarray, measured: np.ndarray,
                  names: Sequence[str], *, frame_estimated: bool) -> list[str]:
    """The usual mistakes, tested against the nominal model, most telling first.

    predict: readings (N, k) -> the measured points (N, 3) the nominal model predicts in its base
    frame, or the measured frames (N, 4, 4) (the given marker applied), whose point's further
    offset every check then registers too (NaN rows where a reading set does not assemble);
    measured: (N, 3) [m] as read; names: the reading columns. Each check compares the data with
    the model up to a rigid registration (and that offset).
    """
    poses, offset_free = _as_poses(predict(readings))
    valid = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    if np.count_nonzero(valid) < 4:
        return ["the readings do not assemble on this machine: columns in another order or unit, or another machine"]
    poses, target = poses[valid], measured[valid]
    points = poses[:, :3, 3]
    causes = []
    spread = float(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))))
    measured_spread = float(np.sqrt(np.mean(np.sum((target - target.mean(0)) ** 2, axis=1))))
    ratio = measured_spread / max(spread, 1e-12)
    if 300.0 < ratio < 3000.0:
        causes.append(f"positions look like millimetres (spread {ratio:.0f} times the model's): use --units mm")
    elif 1 / 3000.0 < ratio < 1 / 300.0:
        causes.append(f"positions look like metres (spread 1/{1 / ratio:.0f} of the model's): drop --units mm")
    registration = _register(poses, target, offset_free)
    registered = registration.rms
    direct = _register(poses, target, offset_free, frame=False).rms
    if not frame_estimated and direct > 5.0 * registered and direct > 0.02:
        frame = registration.frame
        angle = np.degrees(np.linalg.norm(pin.log3(frame.rotation)))
        causes.append(f"the data look like they are in another frame (a rigid registration moves them "
                      f"{np.linalg.norm(frame.translation):.3g} m and {angle:.3g} deg and leaves {registered:.3g} m "
                      "RMS): use --frame estimate")
    causes += _swapped_position_columns(poses, offset_free, target, registered, direct, frame_estimated)
    causes += _swapped_columns(predict, readings, measured, names, registered)
    if not causes and registered > 0.02:
        registered_what = "registering the frame and the marker" if offset_free else "a rigid registration"
        causes.append(f"the data do not fit this machine even after {registered_what} ({registered:.3g} m RMS): "
                      "data from another machine, or the wrong model files")
    return causes


def _swapped_position_columns(poses: np.ndarray, offset_free: bool, measured: np.ndarray, registered: float,
                              direct: float, frame_estimated: bool) -> list[str]:
    """x, y, z columns in another order. In the base frame the order itself is tested. Against an
    estimated frame only a mirror shows (a swap mirrors the points, which no rigid frame undoes;
    every swap is the same mirror up to a rotation, so which two columns cannot be told)."""
    if frame_estimated:
        rms = _register(poses, measured[:, [1, 0, 2]], offset_free).rms
        if rms < registered / 5.0:
            return [f"two of the x, y, z columns look swapped (the data are a mirror image of the model's; read "
                    f"mirrored, the nominal model explains them {registered / max(rms, 1e-12):.0f} times better)"]
        return []
    found = []
    for order in itertools.permutations(range(3)):
        rms = _register(poses, measured[:, list(order)], offset_free, frame=False).rms
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
        poses, offset_free = _as_poses(predict(swapped))
        valid = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
        if np.count_nonzero(valid) < max(4, 0.9 * len(poses)):
            continue
        rms = _register(poses[valid], measured[valid], offset_free).rms
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


def noise_from_residual(position_rms: float, rotation_rms: float, poses: int, rows_per_pose: int,
                        fitted: int) -> tuple[float, float]:
    """The tracker noise the fit's residual implies: (position [m], rotation [rad]) standard
    deviations per coordinate (rotation nan when orientations were not measured).

    position_rms, rotation_rms: RMS over the inlier poses of the position error norm [m] and the
    rotation angle [rad]; rows_per_pose: 3 (positions) or 6; fitted: the parameters fitted. Each
    block's mean square per coordinate (the RMS squared over 3) is scaled by m / (m - p), m the
    residual rows and p the fitted parameters: the degrees of freedom the fit used up, as in the
    unbiased variance estimate of a linear least-squares fit.
    """
    rows = poses * rows_per_pose
    if rows <= fitted:
        raise IdentificationError(f"{poses} poses give {rows} residual rows for {fitted} fitted parameters: "
                                  "too few to estimate the noise (state it with --noise-pos/--noise-rot)")
    scale = rows / (rows - fitted)
    rotation = float(np.sqrt(rotation_rms**2 / 3.0 * scale)) if rows_per_pose == 6 else float("nan")
    return float(np.sqrt(position_rms**2 / 3.0 * scale)), rotation
