"""Figures of calibration and compensation results, written as PNG files.

Figures are built on `matplotlib.figure.Figure` with an explicit Agg canvas: no pyplot, so no
global backend switch, no display, and nothing to close (a figure without pyplot's registry is
freed with its last reference). Each function renders to memory and writes through
`io.atomic_write_bytes`: a reader sees the old file or the new one, never a half-written PNG,
and a path in `protect` (an input file) is refused before anything is written. Given `outputs`
(an `io.OutputSet` that declares the path), it stages the PNG there instead, to be written with
the set's other outputs or not at all.

Inputs are SI (m, rad); axes show readable units chosen from the data (m/mm/um/nm,
rad/mrad/urad/nrad). Error plots use log scales, on which a zero cannot be drawn: such points are
counted in the legend rather than silently moved.
"""

from __future__ import annotations

import io as _stdio
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence, cast

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator, LogFormatter, NullFormatter

from m3t1r.errors import InvalidInputError, OutputPathError
from m3t1r.io.outputs import OutputSet, atomic_write_bytes
from m3t1r.io.paths import StrPath, ensure_not_protected
from m3t1r.metrics import PoseErrors

__all__ = ["plot_pose_errors_before_after", "plot_error_vs_poses", "plot_workspace_error_map",
           "plot_predicted_std_map"]

_DPI = 120


@dataclass(frozen=True)
class _Unit:
    """A display unit: values in SI are multiplied by `scale` and labelled `label`."""

    label: str
    scale: float


_LENGTH_UNITS = (_Unit("m", 1.0), _Unit("mm", 1e3), _Unit("µm", 1e6), _Unit("nm", 1e9))
_ANGLE_UNITS = (_Unit("rad", 1.0), _Unit("mrad", 1e3), _Unit("µrad", 1e6), _Unit("nrad", 1e9))


def _unit_for(values: np.ndarray, units: tuple[_Unit, ...]) -> _Unit:
    """The largest unit in which the geometric middle of the positive values is at least 1.

    Errors before and after calibration span three or four decades; the middle of the range,
    not its top, decides, so both ends read as small numbers.
    """
    positive = values[values > 0]
    if positive.size == 0:
        return units[0]
    middle = math.sqrt(float(positive.min()) * float(positive.max()))
    for unit in units:
        if middle * unit.scale >= 1.0:
            return unit
    return units[-1]


def _readable(value: float, units: tuple[_Unit, ...]) -> str:
    """One SI value as text in its own best unit: 0.0235 m -> '23.5 mm'."""
    unit = _unit_for(np.array([value]), units)
    return f"{value * unit.scale:.3g} {unit.label}"


class _ReadableLogFormatter(LogFormatter):
    """Log-axis tick labels in the unit that reads best at each tick: '10 µm', '1 mm', '100 mrad'.

    An error axis spans several decades, so one unit for the whole axis gives labels like
    1e+05 µrad; this keeps matplotlib's choice of WHICH ticks to label and only changes the text.
    Data are plotted in SI.
    """

    def __init__(self, units: tuple[_Unit, ...], labelOnlyBase: bool = False) -> None:
        super().__init__(labelOnlyBase=labelOnlyBase)
        self._units = units

    def _num_to_string(self, x: float, vmin: float, vmax: float) -> str:
        return _readable(x, self._units)


def _readable_log_axis(axis, units: tuple[_Unit, ...]) -> None:
    axis.set_major_formatter(_ReadableLogFormatter(units))
    axis.set_minor_formatter(_ReadableLogFormatter(units))


def _finite_array(values: object, what: str, ndim: int = 1) -> np.ndarray:
    try:
        array = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{what}: not numeric ({exc})") from None
    if array.ndim != ndim or array.shape[0] == 0:
        raise InvalidInputError(f"{what}: shape {array.shape}, expected {ndim}-D with at least one row")
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        raise InvalidInputError(f"{what}: non-finite value {array[tuple(bad[0])]} at index {tuple(int(i) for i in bad[0])}")
    return array


def _nonnegative(array: np.ndarray, what: str) -> np.ndarray:
    if np.any(array < 0):
        k = int(np.flatnonzero(array < 0)[0])
        raise InvalidInputError(f"{what}: negative error {array[k]} at index {k} (errors are magnitudes)")
    return array


def _zero_note(count: int) -> str:
    return f" ({count} zero, not drawn on log scale)" if count else ""


def _check_output(path: StrPath, protect: Iterable[StrPath], outputs: OutputSet | None = None) -> None:
    """The checks `atomic_write_bytes` makes, done before rendering (a figure takes ~0.3 s); an
    output of an OutputSet was checked with the set's other outputs (and `outputs` names it)."""
    if outputs is not None:
        outputs.output(path)  # KeyError for a path the set does not declare: a caller bug
        return
    target = Path(path)
    ensure_not_protected(target, protect)
    if target.is_dir():
        raise OutputPathError(target, "is a directory, expected a PNG file path")
    if not target.parent.is_dir():
        raise OutputPathError(target, f"directory {target.parent} does not exist")


def _save(figure: Figure, path: StrPath, protect: Iterable[StrPath], outputs: OutputSet | None = None) -> Path:
    """Render to PNG in memory, then replace `path` atomically, or stage it in `outputs` (to land
    with the set's other outputs at its commit); returns the path."""
    target = Path(path)
    protect = tuple(protect)
    FigureCanvasAgg(figure)
    buffer = _stdio.BytesIO()
    figure.savefig(buffer, format="png", dpi=_DPI)
    if outputs is not None:
        outputs.stage(path, buffer.getvalue())
    else:
        atomic_write_bytes(target, buffer.getvalue(), protect=protect)
    return target


# ------------------------------------------------------------------------------------------------
def plot_pose_errors_before_after(before: PoseErrors, after: PoseErrors, path: StrPath,
                                  title: str = "Platform pose error before and after calibration",
                                  protect: Iterable[StrPath] = (), outputs: OutputSet | None = None) -> Path:
    """Paper Fig. 4: (a) orientation error and (b) position error per pose, before and after.

    before, after: errors of the nominal and of the calibrated model against the actual machine
    at the same poses (`calibration.pose_errors`): position norm [m], rotation angle [rad]. Data
    without orientation (rotation NaN at every pose, before and after, as `measured_pose_errors`
    gives for a position-only tracker) get the position panel alone.
    Log y-scale, ticks and legend means in readable units. Returns the PNG path.
    """
    panels = []
    kinds: tuple[tuple[str, tuple[_Unit, ...], str], ...]
    kinds = (("rotation", _ANGLE_UNITS, "(a) Orientation error"), ("position", _LENGTH_UNITS, "(b) Position error"))
    if all(np.isnan(np.asarray(errors.rotation, dtype=float)).all() for errors in (before, after)):
        kinds = (("position", _LENGTH_UNITS, "Position error"),)
    for kind, units, label in kinds:
        b = _nonnegative(_finite_array(getattr(before, kind), f"before.{kind}"), f"before.{kind}")
        a = _nonnegative(_finite_array(getattr(after, kind), f"after.{kind}"), f"after.{kind}")
        if len(a) != len(b):
            raise InvalidInputError(f"before.{kind} has {len(b)} poses, after.{kind} {len(a)}: "
                                    "before and after must be at the same poses")
        panels.append((label, units, b, a))

    _check_output(path, protect, outputs)
    figure = Figure(figsize=(8.0, 6.5), layout="constrained")
    figure.suptitle(title)
    axes = np.atleast_1d(figure.subplots(len(panels), 1, sharex=True))
    for ax, (label, units, b, a) in zip(axes, panels):
        index = np.arange(1, len(b) + 1)
        for values, name, style, colour in ((b, "before", "o-", "tab:red"), (a, "after", "s-", "tab:blue")):
            ax.semilogy(index, values, style, ms=3, lw=0.8, color=colour,
                        label=f"{name}: mean {_readable(float(np.mean(values)), units)}"
                              f"{_zero_note(int(np.sum(values == 0)))}")
        _readable_log_axis(ax.yaxis, units)
        ax.set_title(label, loc="left")
        ax.set_ylabel(label.split(") ", 1)[-1].lower())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="center right", fontsize="small")
    axes[-1].set_xlabel("pose index")
    return _save(figure, path, protect, outputs)


def plot_error_vs_poses(n_poses: Sequence[int], position_errors: Sequence[float],
                        rotation_errors: Sequence[float] | None, path: StrPath,
                        predicted: tuple[Sequence[float], Sequence[float] | None] | None = None,
                        title: str = "Held-out error vs number of calibration poses",
                        protect: Iterable[StrPath] = (), outputs: OutputSet | None = None) -> Path:
    """Held-out platform error of the calibrated model against the number of calibration poses N.

    n_poses: N per study (>= 1); position_errors [m] and rotation_errors [rad] (None for
    position-only studies): the measured held-out error per N, e.g. a mean or RMS over held-out
    poses; predicted: optional (position [m], rotation [rad] or None) from the covariance
    (`calibration.predicted_pose_std`), drawn dashed. Log-log axes. Returns the PNG path.
    """
    n = _finite_array(n_poses, "n_poses")
    if np.any(n < 1):
        raise InvalidInputError(f"n_poses: every N must be >= 1, got {n.min():g}")
    series: list[tuple[str, tuple[_Unit, ...], np.ndarray, Sequence[float] | np.ndarray | None]]
    series = [("Position error", _LENGTH_UNITS, _finite_array(position_errors, "position_errors"),
               None if predicted is None else predicted[0])]
    if rotation_errors is not None:
        series.append(("Orientation error", _ANGLE_UNITS, _finite_array(rotation_errors, "rotation_errors"),
                       None if predicted is None else predicted[1]))
    checked = []
    for name, units, measured, prediction in series:
        _nonnegative(measured, name)
        if len(measured) != len(n):
            raise InvalidInputError(f"{name}: {len(measured)} values for {len(n)} values of n_poses")
        if prediction is not None:
            prediction = _nonnegative(_finite_array(prediction, f"predicted {name}"), f"predicted {name}")
            if len(prediction) != len(n):
                raise InvalidInputError(f"predicted {name}: {len(prediction)} values for {len(n)} values of n_poses")
        checked.append((name, units, measured, prediction))

    _check_output(path, protect, outputs)
    figure = Figure(figsize=(5.0 * len(checked), 4.0), layout="constrained")
    figure.suptitle(title)
    axes = np.atleast_1d(figure.subplots(1, len(checked)))
    for ax, (name, units, measured, prediction) in zip(axes, checked):
        ax.loglog(n, measured, "o-", color="tab:blue", label=f"measured (held out){_zero_note(int(np.sum(measured == 0)))}")
        if prediction is not None:
            ax.loglog(n, prediction, "--", color="tab:gray", label="predicted from covariance")
        _readable_log_axis(ax.yaxis, units)
        # The studied N are the meaningful x ticks; log-decade labels (2x10^1) would hide them.
        ax.xaxis.set_major_locator(FixedLocator(n.tolist()))
        ax.xaxis.set_major_formatter(lambda value, _: f"{value:g}")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("number of calibration poses N")
        ax.set_ylabel(name.lower())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    return _save(figure, path, protect, outputs)


def _xy(targets: object, what: str) -> np.ndarray:
    array = _finite_array(targets, what, ndim=2)
    if array.shape[1] < 2:
        raise InvalidInputError(f"{what}: shape {array.shape}, expected rows (x, y, ...) with at least 2 columns")
    return array[:, :2]


def _log_norm(values: np.ndarray) -> LogNorm:
    positive = values[values > 0]
    if positive.size == 0:  # nothing drawable; any valid range will do
        return LogNorm(vmin=1.0, vmax=10.0)
    low, high = float(positive.min()), float(positive.max())
    return LogNorm(vmin=low, vmax=high if high > low else low * 10.0)


_PLATFORM_PLANE = ("platform x [m]", "platform y [m]")


def _scatter_panels(figure: Figure, xy: np.ndarray, panels: list[tuple[str, np.ndarray]], units: tuple[_Unit, ...],
                    quantity: str, shared_scale: bool, plane: tuple[str, str] = _PLATFORM_PLANE) -> None:
    """Side-by-side scatters over a plane (axis labels `plane`) of SI magnitudes on log colour scales,
    shared or one per panel."""
    axes = np.atleast_1d(figure.subplots(1, len(panels), sharex=True, sharey=True))
    shared = _log_norm(np.concatenate([v for _, v in panels])) if shared_scale else None
    for ax, (label, v) in zip(axes, panels):
        drawn = v > 0
        mappable = ax.scatter(xy[drawn, 0], xy[drawn, 1], c=v[drawn], norm=shared or _log_norm(v), cmap="viridis",
                              s=16, edgecolors="none")
        if not drawn.all():
            ax.scatter(xy[~drawn, 0], xy[~drawn, 1], marker="x", s=16, color="k", label="exactly 0")
            ax.legend(fontsize="small")
        ax.set_title(f"{label}\nmean {_readable(float(np.mean(v)), units)}, max {_readable(float(np.max(v)), units)}",
                     fontsize="medium")
        ax.set_xlabel(plane[0])
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, alpha=0.3)
        if shared is None or ax is axes[-1]:
            colorbar = figure.colorbar(mappable, ax=ax if shared is None else list(axes), label=quantity)
            _readable_log_axis(colorbar.ax.yaxis, units)
    axes[0].set_ylabel(plane[1])


def plot_workspace_error_map(targets: object, errors_before: Sequence[float], errors_after: Sequence[float],
                             path: StrPath, kind: str = "position", shared_scale: bool = False,
                             title: str = "Error of the actual platform over the workspace",
                             protect: Iterable[StrPath] = (), outputs: OutputSet | None = None) -> Path:
    """Error of the actual platform at each target, without and with compensation, over x-y.

    targets: (N, >= 2) rows (x, y, ...) [m] (rows x, y, z, theta accepted; z and theta are
    projected out); errors_before, errors_after: (N,) error magnitudes at those targets, [m] for
    kind="position" or [rad] for kind="yaw" (e.g. `CompensationAccuracy.before.position` with
    `targets[accuracy.indices]`). Log colour scales, one per panel by default: before and after
    differ by three decades, and one shared scale paints each panel in a single colour
    (shared_scale=True draws it anyway, for a side-by-side magnitude comparison). Returns the path.
    """
    if kind not in ("position", "yaw"):
        raise InvalidInputError(f"kind must be 'position' or 'yaw', got {kind!r}")
    xy = _xy(targets, "targets")
    before = _nonnegative(_finite_array(errors_before, "errors_before"), "errors_before")
    after = _nonnegative(_finite_array(errors_after, "errors_after"), "errors_after")
    if not len(before) == len(after) == len(xy):
        raise InvalidInputError(f"{len(xy)} targets, {len(before)} errors before, {len(after)} after: "
                                "one error of each per target")
    _check_output(path, protect, outputs)
    figure = Figure(figsize=(8.5, 6.0), layout="constrained")
    figure.suptitle(f"{title}\n({len(xy)} targets; z and theta projected onto x-y)")
    _scatter_panels(figure, xy, [("uncompensated", before), ("compensated", after)],
                    _LENGTH_UNITS if kind == "position" else _ANGLE_UNITS, f"{kind} error", shared_scale)
    return _save(figure, path, protect, outputs)


def plot_predicted_std_map(targets: object, std: PoseErrors, path: StrPath,
                           title: str = "Predicted standard deviation of the calibrated platform pose",
                           protect: Iterable[StrPath] = (), plane: tuple[str, str] = _PLATFORM_PLANE,
                           outputs: OutputSet | None = None) -> Path:
    """Predicted pose uncertainty of the calibrated model over the workspace, drawn over a plane.

    targets: (N, >= 2) rows whose first two columns place each pose in the plane (default x, y [m];
    `plane` names the two axes); std: from `calibration.predicted_measurement_std` or
    `predicted_pose_std` at the same poses: position [m] (root of the trace of the 3x3 position
    covariance) and orientation [rad]. Two panels, position and orientation, each with its own log
    colour scale; the other coordinates are projected onto the plane. Returns the PNG path.
    """
    xy = _xy(targets, "targets")
    position = _nonnegative(_finite_array(std.position, "std.position"), "std.position")
    rotation = _nonnegative(_finite_array(std.rotation, "std.rotation"), "std.rotation")
    if not len(position) == len(rotation) == len(xy):
        raise InvalidInputError(f"{len(xy)} targets, {len(position)} position std, {len(rotation)} orientation std")
    _check_output(path, protect, outputs)
    figure = Figure(figsize=(8.5, 6.0), layout="constrained")
    figure.suptitle(f"{title}\n({len(xy)} poses; the other coordinates projected onto this plane)")
    left, right = cast(np.ndarray, figure.subfigures(1, 2))  # an array for more than one subfigure
    _scatter_panels(left, xy, [("position", position)], _LENGTH_UNITS, "predicted position std", False, plane)
    _scatter_panels(right, xy, [("orientation", rotation)], _ANGLE_UNITS, "predicted orientation std", False, plane)
    return _save(figure, path, protect, outputs)
