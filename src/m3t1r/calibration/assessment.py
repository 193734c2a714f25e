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
  `quaternion_order_causes`, `metres_as_millimetres_causes` and `residual_causes` name the mistakes
  only the orientations, the unit of every length or the size of what a fit left can show;
- `check_start` refuses a nominal model whose typical (median) pose is further from the data than
  any build error, after the same registration made robust to a few gross readings, which it
  returns to be left out of the fit as outliers;
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

__all__ = [
    "FitRejected",
    "MAX_NOISE_RATIO",
    "HOPELESS_RESIDUAL",
    "MAX_GROSS_SHARE",
    "SMALL_RESIDUAL",
    "Registration",
    "StartCheck",
    "check_fit",
    "check_start",
    "gross_reading_reason",
    "likely_causes",
    "residual_causes",
    "quaternion_order_causes",
    "metres_as_millimetres_causes",
    "describe_parameter",
    "fit_movement_notes",
    "coverage_notes",
    "noise_from_residual",
    "register_with_offset",
    "unexplained_residual_warning",
]

#: A fit is accepted while its whitened residual RMS is at most this many times the stated noise
#: (variance factor <= 9): a margin for small unmodelled effects, far below a wrong unit, frame,
#: column order or machine, which leave residuals of millimetres to metres.
MAX_NOISE_RATIO = 3.0
#: Beyond these a placement "moved implausibly far" for a machine built to drawing [m], [rad].
IMPLAUSIBLE_TRANSLATION, IMPLAUSIBLE_ROTATION = 0.02, 0.1
#: ... unless within this many of its own standard deviation (a weakly determined parameter's noise).
PLAUSIBLE_SIGMAS = 3.0

_COMPONENTS = (
    "translation along x",
    "translation along y",
    "translation along z",
    "rotation about x",
    "rotation about y",
    "rotation about z",
)


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


def check_fit(
    converged: bool,
    termination: str,
    iterations: int,
    variance_factor: float,
    causes: Sequence[str] = (),
    max_noise_ratio: float = MAX_NOISE_RATIO,
    *,
    noise_estimated: bool = False,
) -> bool:
    """Raise FitRejected when LM did not converge, when the variance factor is not finite, or when
    the residual is beyond `max_noise_ratio` times the noise and `causes` names why. With the noise
    estimated from the same residual (`noise_estimated`) the variance factor tests nothing, so any
    cause refuses the fit.

    Returns whether the residual is beyond the noise with no cause named: the fit stands (the
    model's unmodelled effects, or a noise larger than stated) but the caller must say so, with
    `unexplained_residual_warning`.
    """
    if not converged:
        raise FitRejected(
            f"the fit did not converge ({termination} after {iterations} iterations; --max-iterations raises the cap)",
            causes,
        )
    if not np.isfinite(variance_factor):
        raise FitRejected(
            "the residual is nan times the stated noise: the model does not explain the data",
            list(causes) or ["a reading or measurement the model cannot evaluate"],
        )
    if noise_estimated and causes:
        raise FitRejected(
            "the nominal model does not fit the data for a nameable reason (with the noise "
            "estimated from the residual, the residual alone cannot tell)",
            causes,
        )
    if variance_factor <= max_noise_ratio**2:
        return False
    if causes:
        raise FitRejected(
            f"the residual is {np.sqrt(variance_factor):.3g} times the stated noise (accepted up to "
            f"{max_noise_ratio:g}): the model does not explain the data",
            causes,
        )
    return True


def unexplained_residual_warning(variance_factor: float, implied_noise: str, validation_error: float) -> str:
    """The warning written with a fit whose residual is beyond the stated noise for no nameable
    cause. implied_noise: the noise the residuals imply, in words with units (the stated noise
    times sqrt(variance_factor)); validation_error: the cross-validated position error [m]."""
    return (
        f"the residual is {np.sqrt(variance_factor):.3g} times the stated noise (variance factor "
        f"{variance_factor:.3g}) and none of the usual mistakes explains it: effects the geometric model "
        f"does not hold (compliance, thermal drift) or a noisier tracker than stated. The residuals imply a "
        f"noise of {implied_noise}; the parameters' standard deviations assume the stated noise. Judge the "
        f"result by its cross-validated error, {validation_error:.3g} m (--noise-pos auto states the noise "
        "the data show)"
    )


@dataclass(frozen=True)
class Registration:
    """The model's predictions moved onto the measurements: measured ~ frame (g_i offset).

    frame: the measurement frame (identity when it was not estimated); offset: (3,) the measured
    point in the model's measured frame beyond the given marker [m] (zero when not estimated);
    rms: the position RMS left [m]."""

    frame: pin.SE3
    offset: np.ndarray
    rms: float


def register_with_offset(
    poses: np.ndarray,
    measured: np.ndarray,
    *,
    estimate_frame: bool = True,
    estimate_offset: bool = True,
    iterations: int = 30,
) -> Registration:
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


def _registration_cost(
    frame: pin.SE3, offset: np.ndarray, rotations: np.ndarray, positions: np.ndarray, measured: np.ndarray
) -> float:
    points = (rotations @ offset + positions) @ frame.rotation.T + frame.translation
    return float(np.sum((points - measured) ** 2))


def _registration_step(
    frame: pin.SE3,
    offset: np.ndarray,
    rotations: np.ndarray,
    positions: np.ndarray,
    measured: np.ndarray,
    estimate_frame: bool,
) -> np.ndarray:
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


def check_start(
    points: np.ndarray,
    measured: np.ndarray,
    frame_estimated: bool,
    causes: Callable[[], list[str]],
    what: str = "machine",
) -> StartCheck:
    """Judge the nominal model's predictions against the measured points (N, 3) [m].

    points: the predicted measured points (N, 3), or the predicted measured frames (N, 4, 4), whose
    point's further offset in them is then registered too (an unknown marker is no build error).
    Robust to a few gross readings: the typical (median) pose decides, and a pose far beyond any
    build error is returned in `gross` rather than blamed on the model. Raises FitRejected, with
    `causes()`, when the typical pose is more than HOPELESS_RESIDUAL away, or when more than
    MAX_GROSS_SHARE of the poses are: no build error explains that, and a fit would only wander.
    """
    poses, offset_free = _as_poses(points)
    distances = _start_distances(poses, offset_free, measured, frame_estimated)
    typical = float(np.median(distances))
    gross = np.flatnonzero(distances > HOPELESS_RESIDUAL)
    if typical > HOPELESS_RESIDUAL or len(gross) > MAX_GROSS_SHARE * len(distances):
        share = "" if typical > HOPELESS_RESIDUAL else f"; {len(gross)} of {len(distances)} poses are beyond it"
        registered = " and the ".join(
            name for name, done in (("frame", frame_estimated), ("marker", offset_free)) if done
        )
        raise FitRejected(
            f"the nominal {what} is {typical:.3g} m from the measurements (median over the poses"
            + (f", after registering the {registered}" if registered else "")
            + f"), beyond any build error ({HOPELESS_RESIDUAL:g} m){share}: the fit was not attempted",
            causes(),
            forceable=False,
        )
    return StartCheck(distances, typical, tuple(int(i) for i in gross))


def gross_reading_reason(check: StartCheck, index: int) -> str:
    """Why pose `index` of `check.gross` is a gross reading, in plain words."""
    return (
        f"the measured point is {check.distances[index]:.3g} m from the nominal prediction, where the "
        f"median pose is {check.typical:.3g} m: a gross reading (beyond any build error, "
        f"{HOPELESS_RESIDUAL:g} m), not a fault of the model"
    )


def _start_distances(poses: np.ndarray, offset_free: bool, measured: np.ndarray, frame_estimated: bool) -> np.ndarray:
    """Distances [m] of the predicted points (of `poses` (N, 4, 4), see `_as_poses`) to the measured
    ones. With the frame estimated or the point's offset free, after `register_with_offset` on the
    poses within three times the median distance, repeated until that set is stable (a reading 1 m
    or 1 km off then moves the registration no more than any other pose)."""
    if not (frame_estimated or offset_free):
        return np.linalg.norm(poses[:, :3, 3] - measured, axis=1)
    keep = np.ones(len(poses), dtype=bool)
    for _ in range(10):
        registration = _register(poses[keep], measured[keep], offset_free, frame=frame_estimated)
        distances = np.linalg.norm(_registered_points(poses, registration) - measured, axis=1)
        closest = distances <= 3.0 * np.median(distances)
        if np.count_nonzero(closest) < 3 or np.array_equal(closest, keep):
            break
        keep = closest
    return distances


def _registered_points(poses: np.ndarray, registration: Registration) -> np.ndarray:
    """The measured points (N, 3) [m] the registered model predicts: F (R_i o + p_i)."""
    frame = registration.frame
    return (poses[:, :3, :3] @ registration.offset + poses[:, :3, 3]) @ frame.rotation.T + frame.translation


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


def likely_causes(
    predict: Callable[[np.ndarray], np.ndarray],
    readings: np.ndarray,
    measured: np.ndarray,
    names: Sequence[str],
    *,
    frame_estimated: bool,
    angular: Sequence[bool] | np.ndarray = (),
) -> list[str]:
    """The usual mistakes, tested against the nominal model, most telling first.

    predict: readings (N, k) -> the measured points (N, 3) the nominal model predicts in its base
    frame, or the measured frames (N, 4, 4) (the given marker applied), whose point's further
    offset every check then registers too (NaN rows where a reading set does not assemble);
    measured: (N, 3) [m] as read; names: the reading columns; angular: (k,) which of them are
    angles [rad] (revolute joints), tested for readings in degrees. Each check compares the data
    with the model up to a rigid registration (and that offset).
    """
    poses, offset_free = _as_poses(predict(readings))
    valid = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    if np.count_nonzero(valid) < 4:
        return ["the readings do not assemble on this machine: columns in another order or unit, or another machine"]
    poses, target = poses[valid], measured[valid]
    points = poses[:, :3, 3]
    spread = float(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))))
    measured_spread = float(np.sqrt(np.mean(np.sum((target - target.mean(0)) ** 2, axis=1))))
    ratio = measured_spread / max(spread, 1e-12)
    # A wrong unit is the whole story: the frame and column checks below would only misread its scale.
    if 300.0 < ratio < 3000.0:
        return [f"positions look like millimetres (spread {ratio:.0f} times the model's): use --units mm"]
    if 1 / 3000.0 < ratio < 1 / 300.0:
        return [f"positions look like metres (spread 1/{1 / ratio:.0f} of the model's): drop --units mm"]
    registration = _register(poses, target, offset_free)
    registered = registration.rms
    # Degrees are the whole story too: every other check would read the scrambled postures.
    if degrees := _degrees_causes(predict, readings, measured, names, angular, registered):
        return degrees
    causes = []
    direct = _register(poses, target, offset_free, frame=False).rms
    if not frame_estimated and direct > 5.0 * registered and direct > 0.02:
        frame = registration.frame
        angle = np.degrees(np.linalg.norm(pin.log3(frame.rotation)))
        causes.append(
            f"the data look like they are in another frame (a rigid registration moves them "
            f"{np.linalg.norm(frame.translation):.3g} m and {angle:.3g} deg and leaves {registered:.3g} m "
            "RMS): use --frame estimate"
        )
    causes += _swapped_position_columns(poses, offset_free, target, registered, direct, frame_estimated)
    causes += _swapped_columns(predict, readings, measured, names, registered)
    if not causes and registered > 0.02:
        registered_what = "registering the frame and the marker" if offset_free else "a rigid registration"
        causes.append(
            f"the data do not fit this machine even after {registered_what} ({registered:.3g} m RMS): "
            "data from another machine, or the wrong model files"
        )
    return causes


#: A fit leaving less than this RMS [m], [rad] fits the data to sub-millimetre: what is left is a
#: noise larger than stated or small unmodelled effects, not a wrong setup.
SMALL_RESIDUAL = 1e-3


def residual_causes(
    position_rms: float, rotation_rms: float, *, beyond_noise: bool, marker_given: bool, position_only: bool
) -> list[str]:
    """Causes of what a fit left, judged by its size: position_rms [m], rotation_rms [rad] (NaN
    with positions only); beyond_noise: the fit left more than the noise (or did not converge).

    A small residual (at most SMALL_RESIDUAL in both) names no mistake, whatever the stated noise:
    it is a noisier tracker than stated or small effects the geometric model does not hold, which
    the caller writes with `unexplained_residual_warning`. A large one with orientation data and no
    marker given is a measured frame that is not the platform's, when it is beyond the noise or its
    rotation beyond any tracker's (IMPLAUSIBLE_ROTATION / 10, which also tells with the noise
    estimated from the same residual)."""
    rotation = rotation_rms if np.isfinite(rotation_rms) else 0.0
    small = position_rms <= SMALL_RESIDUAL and rotation <= SMALL_RESIDUAL
    if marker_given or position_only or small or not (beyond_noise or rotation > IMPLAUSIBLE_ROTATION / 10):
        return []
    return [
        "the measured frame (a probe or a set of reflectors) is not the platform frame: give its position with "
        "--marker X Y Z, and its orientation is estimated with it"
    ]


def quaternion_order_causes(
    predicted_poses: np.ndarray,
    measured_positions: np.ndarray,
    measured_rotations: np.ndarray,
    *,
    frame_estimated: bool,
) -> list[str]:
    """Whether the file's quaternion columns (qx, qy, qz, qw) hold w, x, y, z instead (scalar first).

    predicted_poses (N, 4, 4): the measured frame as the nominal model puts it in its base;
    measured_positions (N, 3) [m] and measured_rotations (N, 3, 3) as read. With the measurement
    frame F (registered on the positions with the marker's offset, `register_with_offset`, when
    estimated, else the identity), R_F^T R_measured,i = R_predicted,i R_marker: the same rotation
    R_marker at every pose. Its spread over the poses is compared as read and with the four numbers
    re-ordered."""
    if len(predicted_poses) < 3:
        return []
    poses = np.asarray(predicted_poses, dtype=float)
    frame = register_with_offset(poses, measured_positions).frame.rotation if frame_estimated else np.eye(3)
    predicted = frame @ poses[:, :3, :3]

    def spread(measured: np.ndarray) -> float:
        marker = np.swapaxes(predicted, 1, 2) @ measured
        u, _, vt = np.linalg.svd(marker.sum(axis=0))
        mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        return float(np.mean([np.linalg.norm(pin.log3(mean.T @ m)) for m in marker]))

    read = np.array([pin.Quaternion(r).coeffs() for r in measured_rotations])  # the file's four numbers
    reordered = np.array([pin.Quaternion(w, x, y, z).normalized().matrix() for w, x, y, z in read])
    as_read, fixed = spread(np.asarray(measured_rotations)), spread(reordered)
    if as_read > 100 * SMALL_RESIDUAL and fixed < as_read / 5:
        return [
            f"the quaternion columns look like w, x, y, z (scalar first) under the names qx, qy, qz, qw (scalar "
            f"last): read in that order, the measured orientations follow the model's to {fixed:.2g} rad instead "
            f"of {as_read:.2g} rad (mean); reorder the columns"
        ]
    return []


def metres_as_millimetres_causes(
    predict: Callable[[np.ndarray], np.ndarray],
    readings: np.ndarray,
    measured: np.ndarray,
    length_readings: np.ndarray,
    *,
    frame_estimated: bool,
) -> list[str]:
    """Whether a file read with --units mm holds metres: `predict` as for `likely_causes` (points
    or frames, whose point's offset is registered too), the readings (N, k) and measured points
    (N, 3) [m] as read, `length_readings` (k,) the reading columns that --units scaled (prismatic
    joints). With every length scaled back by 1000, does the nominal model explain the points far
    better? (Sliders scaled too keep the spreads alike, which the spread test cannot see.)"""

    def rms(predicted: np.ndarray, target: np.ndarray) -> float:
        poses, offset_free = _as_poses(predicted)
        valid = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
        if np.count_nonzero(valid) < max(4, 0.9 * len(poses)):
            return float("inf")
        return _register(poses[valid], target[valid], offset_free, frame=frame_estimated).rms

    as_read = rms(predict(readings), measured)
    in_metres = rms(predict(readings * np.where(length_readings, 1e3, 1.0)), measured * 1e3)
    if in_metres < as_read / 5.0 and np.isfinite(in_metres):
        return [
            f"the file looks like metres: read without --units mm, the nominal model explains the positions "
            f"{as_read / max(in_metres, 1e-12):.0f} times better ({in_metres:.3g} m RMS); drop --units mm"
        ]
    return []


def _swapped_position_columns(
    poses: np.ndarray, offset_free: bool, measured: np.ndarray, registered: float, direct: float, frame_estimated: bool
) -> list[str]:
    """x, y, z columns in another order. In the base frame the order itself is tested. Against an
    estimated frame only a mirror shows (a swap mirrors the points, which no rigid frame undoes;
    every swap is the same mirror up to a rotation, so which two columns cannot be told)."""
    if frame_estimated:
        rms = _register(poses, measured[:, [1, 0, 2]], offset_free).rms
        if rms < registered / 5.0:
            return [
                f"two of the x, y, z columns look swapped (the data are a mirror image of the model's; read "
                f"mirrored, the nominal model explains them {registered / max(rms, 1e-12):.0f} times better)"
            ]
        return []
    found = []
    for order in itertools.permutations(range(3)):
        rms = _register(poses, measured[:, list(order)], offset_free, frame=False).rms
        if order != (0, 1, 2) and rms < direct / 5.0:
            names = ", ".join("xyz"[k] for k in order)
            found.append(
                (
                    rms,
                    f"the position columns look like they hold {names} in that order (the nominal model "
                    f"explains the data {direct / max(rms, 1e-12):.0f} times better read that way)",
                )
            )
    return [text for _, text in sorted(found)[:1]]


def _degrees_causes(
    predict: Callable[[np.ndarray], np.ndarray],
    readings: np.ndarray,
    measured: np.ndarray,
    names: Sequence[str],
    angular: Sequence[bool] | np.ndarray,
    registered: float,
) -> list[str]:
    """Angle columns logged in degrees: read as degrees (times pi / 180), does the nominal model explain
    the data far better (up to the same registration)?"""
    angles = np.asarray(angular, dtype=bool)
    if not angles.any() or registered <= SMALL_RESIDUAL:
        return []
    converted = readings.copy()
    converted[:, angles] = np.radians(converted[:, angles])
    poses, offset_free = _as_poses(predict(converted))
    valid = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    if np.count_nonzero(valid) < max(4, 0.9 * len(poses)):
        return []
    rms = _register(poses[valid], measured[valid], offset_free).rms
    if rms >= registered / 5.0:
        return []
    columns = ", ".join(f"'{n}'" for n, a in zip(names, angles) if a)
    return [
        f"the joint readings look like degrees (columns {columns}): read as degrees, the nominal model explains "
        f"the data {registered / max(rms, 1e-12):.0f} times better ({rms:.3g} m RMS against {registered:.3g} m); "
        "give radians (`m3t1r convert FILE --joint-degrees all -o measurements.csv` rewrites the file in radians)"
    ]


def _swapped_columns(
    predict: Callable[[np.ndarray], np.ndarray],
    readings: np.ndarray,
    measured: np.ndarray,
    names: Sequence[str],
    registered: float,
) -> list[str]:
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
            found.append(
                (
                    rms,
                    f"columns '{names[a]}' and '{names[b]}' look swapped (with them exchanged the "
                    f"nominal model explains the data {registered / max(rms, 1e-12):.0f} times better)",
                )
            )
    return [text for _, text in sorted(found)]


def fit_movement_notes(
    moved: dict[str, float],
    rms_before: float,
    rms_after: float,
    measured_frame: str | None = None,
    same_as_frame: Sequence[str] = (),
    std: dict[str, float] | None = None,
) -> list[str]:
    """Plain-word notes on how far the fit moved: implausibly far, or barely.

    moved: identified error per parameter name ([m] for translations, [rad] for rotations);
    rms_before / rms_after: position residual RMS [m] at the start and the end; measured_frame:
    the model frame the data measure, when no marker was estimated (its translating far means a
    reflector off that frame was taken for the machine's geometry); same_as_frame: other parameters
    that move the measured frame alike (a translation along the last joint's axis commutes with
    the joint: the fit may share the reflector's offset with it); std: the parameters' standard
    deviations (same units): a move within PLAUSIBLE_SIGMAS of its own std is what the noise allows
    a weakly determined parameter, not a sign of wrong data, and is not called implausible.
    """
    notes: list[str] = []
    far: list[tuple[float, str, str]] = []
    std = {} if std is None else std
    for name, value in moved.items():
        translation = name.rpartition(".dt[")[2] in ("0]", "1]", "2]")
        limit = IMPLAUSIBLE_TRANSLATION if translation else IMPLAUSIBLE_ROTATION
        if abs(value) > limit and not abs(value) <= PLAUSIBLE_SIGMAS * std.get(name, 0.0):
            unit = "m" if translation else "rad"
            far.append((abs(value) / limit, name, f"{describe_parameter(name)} {value:+.3g} {unit}"))
    if not far:
        return notes + _barely_moved(rms_before, rms_after)
    # The measured frame translating far is a reflector off it, taken for the machine's geometry: its
    # own placement moves (translation and rotation), which says nothing of units or frames.
    absorbed = bool(measured_frame) and any(n.startswith(f"{measured_frame}.dt[") and n[-2] in "012" for _, n, _ in far)
    others = [
        entry
        for entry in far
        if not (absorbed and (entry[1].startswith(f"{measured_frame}.") or entry[1] in same_as_frame))
    ]
    listed = ", ".join(text for _, _, text in sorted(far, reverse=True)[:3])
    if others:
        cause = "check the units, the measurement frame, the reading columns and that the model is this machine's" + (
            f" (the moves of {measured_frame} itself are the reflector below)" if absorbed else ""
        )
    else:
        alike = (
            ""
            if len(far) == sum(e[1].startswith(f"{measured_frame}.") for e in far)
            else " (with translations along the last joint's axis, which move it alike)"
        )
        cause = (
            f"only the measured frame {measured_frame} moved{alike}, by a reflector's offset: the units, the "
            "frame and the rest of the machine are not in question"
        )
    notes.append(f"the fit moved implausibly far for a machine built to drawing ({listed}): {cause}")
    if absorbed:
        notes.append(
            f"the measured frame {measured_frame} itself moved: the measured point is probably a "
            "reflector off it, now baked into the machine; give its position with --marker X Y Z"
        )
    return notes + _barely_moved(rms_before, rms_after)


def _barely_moved(rms_before: float, rms_after: float) -> list[str]:
    notes = []
    if rms_before > 0 and rms_after > 0.8 * rms_before:
        notes.append(
            f"the fit barely moved (residual RMS {rms_before:.3g} -> {rms_after:.3g} m): the nominal "
            "model already explains the data, or the poses do not excite the errors"
        )
    return notes


def coverage_notes(values: np.ndarray, bounds: dict[str, tuple[float, float]], threshold: float = 0.5) -> list[str]:
    """Which task coordinates the poses cover poorly: values (N, len(bounds)) of the coordinates
    named by `bounds` (name -> (low, high) of the workspace); a coordinate whose measured range is
    below `threshold` of the workspace's is named with both ranges."""
    notes = []
    for k, (name, (low, high)) in enumerate(bounds.items()):
        span = float(np.ptp(values[:, k]))
        if high > low and span < threshold * (high - low):
            notes.append(
                f"{name} spans {values[:, k].min():.3g} .. {values[:, k].max():.3g} "
                f"({100 * span / (high - low):.0f} % of the workspace's {low:.3g} .. {high:.3g})"
            )
    return notes


def noise_from_residual(
    position_rms: float, rotation_rms: float, poses: int, rows_per_pose: int, fitted: int
) -> tuple[float, float]:
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
        raise IdentificationError(
            f"{poses} poses give {rows} residual rows for {fitted} fitted parameters: "
            "too few to estimate the noise (state it with --noise-pos/--noise-rot)"
        )
    scale = rows / (rows - fitted)
    rotation = float(np.sqrt(rotation_rms**2 / 3.0 * scale)) if rows_per_pose == 6 else float("nan")
    return float(np.sqrt(position_rms**2 / 3.0 * scale)), rotation
