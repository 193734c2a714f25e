"""Figures of calibration and compensation results, written as PNG files.

Figures are built on `matplotlib.figure.Figure` with an explicit Agg canvas: no pyplot, so no
global backend switch, no display, and nothing to close (a figure without pyplot's registry is
freed with its last reference). Each function takes where to write as a path or a `PlotFile`,
renders to memory and writes through `io.atomic_write_bytes`: a reader sees the old file or the
new one, never a half-written PNG, and a path in `PlotFile.protect` (an input file) is refused
before anything is written. Given `PlotFile.outputs` (an `io.OutputSet` that declares the path),
it stages the PNG there instead, to be written with the set's other outputs or not at all.

Inputs are SI (m, rad); axes show readable units chosen from the data (m/mm/um/nm,
rad/mrad/urad/nrad). Error plots use log scales, on which a zero cannot be drawn: such points are
counted in the legend rather than silently moved.
"""

from __future__ import annotations

import io as _stdio
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, cast

import numpy as np
import scipy.special
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator, LogFormatter, NullFormatter

from m3t1r.errors import InvalidInputError, OutputPathError
from m3t1r.io.outputs import OutputSet, atomic_write_bytes
from m3t1r.io.paths import StrPath, ensure_not_protected
from m3t1r.metrics import PoseErrors

__all__ = [
    "PlotFile",
    "plot_pose_errors_before_after",
    "plot_error_vs_poses",
    "plot_workspace_error_map",
    "plot_predicted_std_map",
    "plot_validation_histogram",
    "plot_normalised_qq",
    "plot_errors_over_workspace",
]

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
        raise InvalidInputError(
            f"{what}: non-finite value {array[tuple(bad[0])]} at index {tuple(int(i) for i in bad[0])}"
        )
    return array


def _nonnegative(array: np.ndarray, what: str) -> np.ndarray:
    if np.any(array < 0):
        k = int(np.flatnonzero(array < 0)[0])
        raise InvalidInputError(f"{what}: negative error {array[k]} at index {k} (errors are magnitudes)")
    return array


def _zero_note(count: int) -> str:
    return f" ({count} zero, not drawn on log scale)" if count else ""


@dataclass(frozen=True)
class PlotFile:
    """Where a figure goes: the PNG file `path`, refused when it is one of `protect` (the command's
    inputs); or, with `outputs` (an `OutputSet` that declares `path`), staged there to land with the
    set's other outputs at its commit."""

    path: StrPath
    protect: tuple[StrPath, ...] = ()
    outputs: OutputSet | None = None


def _plot_file(path: StrPath | PlotFile) -> PlotFile:
    return path if isinstance(path, PlotFile) else PlotFile(path)


def _check_output(path: StrPath | PlotFile) -> None:
    """The checks `atomic_write_bytes` makes, done before rendering (a figure takes ~0.3 s); an
    output of an OutputSet was checked with the set's other outputs (and `outputs` names it)."""
    file = _plot_file(path)
    if file.outputs is not None:
        file.outputs.output(file.path)  # KeyError for a path the set does not declare: a caller bug
        return
    target = Path(file.path)
    ensure_not_protected(target, file.protect)
    if target.is_dir():
        raise OutputPathError(target, "is a directory, expected a PNG file path")
    if not target.parent.is_dir():
        raise OutputPathError(target, f"directory {target.parent} does not exist")


def _save(figure: Figure, path: StrPath | PlotFile, description: str | None = None) -> Path:
    """Render to PNG in memory, then replace the file atomically, or stage it in the PlotFile's
    `outputs` (to land with the set's other outputs at its commit); returns the path. `description`
    goes into the PNG's Description text chunk: what the figure marks, in words, for a reader
    without the image."""
    file = _plot_file(path)
    target = Path(file.path)
    FigureCanvasAgg(figure)
    buffer = _stdio.BytesIO()
    metadata = {"Description": description} if description else None
    figure.savefig(buffer, format="png", dpi=_DPI, metadata=metadata)
    if file.outputs is not None:
        file.outputs.stage(file.path, buffer.getvalue())
    else:
        atomic_write_bytes(target, buffer.getvalue(), protect=file.protect)
    return target


# ------------------------------------------------------------------------------------------------
def plot_pose_errors_before_after(
    before: PoseErrors,
    after: PoseErrors,
    path: StrPath | PlotFile,
    title: str = "Platform pose error before and after calibration",
    outliers: Sequence[int] | np.ndarray = (),
    labels: Sequence[str] | None = None,
) -> Path:
    """Paper Fig. 4: (a) orientation error and (b) position error per pose, before and after.

    before, after: errors of the nominal and of the calibrated model against the actual machine
    at the same poses (`calibration.pose_errors`): position norm [m], rotation angle [rad]. Data
    without orientation (rotation NaN at every pose, before and after, as `measured_pose_errors`
    gives for a position-only tracker) get the position panel alone.
    outliers: indices of the poses the fit left out, circled on both curves and named by `labels`
    (one per pose, e.g. "line 12"; default the pose index); the legend means are over the others.
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
            raise InvalidInputError(
                f"before.{kind} has {len(b)} poses, after.{kind} {len(a)}: before and after must be at the same poses"
            )
        panels.append((label, units, b, a))
    left_out, names = _outlier_labels(outliers, labels, len(panels[0][2]))

    _check_output(path)
    figure = Figure(figsize=(8.0, 6.5), layout="constrained")
    figure.suptitle(title)
    axes = np.atleast_1d(figure.subplots(len(panels), 1, sharex=True))
    kept = np.setdiff1d(np.arange(len(panels[0][2])), left_out)
    for ax, (label, units, b, a) in zip(axes, panels):
        index = np.arange(1, len(b) + 1)
        over = f" of {len(kept)} fitted poses" if len(left_out) else ""
        for values, name, style, colour in ((b, "before", "o-", "tab:red"), (a, "after", "s-", "tab:blue")):
            ax.semilogy(
                index,
                values,
                style,
                ms=3,
                lw=0.8,
                color=colour,
                label=f"{name}: mean {_readable(float(np.mean(values[kept])), units)}{over}"
                f"{_zero_note(int(np.sum(values == 0)))}",
            )
        if len(left_out):
            _mark_outliers(ax, index[left_out], np.vstack([b[left_out], a[left_out]]), names)
        _readable_log_axis(ax.yaxis, units)
        ax.set_title(label, loc="left")
        ax.set_ylabel(label.split(") ", 1)[-1].lower())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel("pose index")
    return _save(figure, path, _outlier_description(names))


_MAX_LABELS = 12  # more names than this cover the curves; the PNG's description lists them all


def _outlier_labels(
    outliers: Sequence[int] | np.ndarray, labels: Sequence[str] | None, count: int
) -> tuple[np.ndarray, list[str]]:
    """(sorted indices, their names) of the outliers among `count` poses, checked."""
    index = np.unique(np.asarray(outliers, dtype=int))
    if index.size and (index[0] < 0 or index[-1] >= count):
        raise InvalidInputError(
            f"outliers: pose index {index[0] if index[0] < 0 else index[-1]} out of range for {count} poses"
        )
    if labels is not None and len(labels) != count:
        raise InvalidInputError(f"labels: {len(labels)} for {count} poses, one per pose")
    return index, [str(labels[i]) if labels is not None else f"pose {i + 1}" for i in index]


def _mark_outliers(ax, x: np.ndarray, values: np.ndarray, names: Sequence[str]) -> None:
    """Circle each outlier on every curve (rows of `values`) and name it beside its highest point."""
    for row in values:
        shown = row > 0
        ax.plot(x[shown], row[shown], "o", ms=9, mfc="none", mec="black", mew=1.2)
    ax.plot([], [], "o", ms=9, mfc="none", mec="black", mew=1.2, label=f"outlier, left out of the fit ({len(x)})")
    top = values.max(axis=0)
    for k in range(min(len(x), _MAX_LABELS)):
        if top[k] > 0:
            ax.annotate(names[k], (x[k], top[k]), xytext=(4, 6), textcoords="offset points", fontsize="x-small")


def _outlier_description(names: Sequence[str]) -> str:
    return "outliers: " + (", ".join(names) if names else "none")


def plot_error_vs_poses(
    n_poses: Sequence[int],
    position_errors: Sequence[float],
    rotation_errors: Sequence[float] | None,
    path: StrPath | PlotFile,
    predicted: tuple[Sequence[float], Sequence[float] | None] | None = None,
    title: str = "Held-out error vs number of calibration poses",
) -> Path:
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
    series = [
        (
            "Position error",
            _LENGTH_UNITS,
            _finite_array(position_errors, "position_errors"),
            None if predicted is None else predicted[0],
        )
    ]
    if rotation_errors is not None:
        series.append(
            (
                "Orientation error",
                _ANGLE_UNITS,
                _finite_array(rotation_errors, "rotation_errors"),
                None if predicted is None else predicted[1],
            )
        )
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

    _check_output(path)
    figure = Figure(figsize=(5.0 * len(checked), 4.0), layout="constrained")
    figure.suptitle(title)
    axes = np.atleast_1d(figure.subplots(1, len(checked)))
    for ax, (name, units, measured, prediction) in zip(axes, checked):
        ax.loglog(
            n, measured, "o-", color="tab:blue", label=f"measured (held out){_zero_note(int(np.sum(measured == 0)))}"
        )
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
    return _save(figure, path)


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


def _scatter_panels(
    figure: Figure,
    xy: np.ndarray,
    panels: list[tuple[str, np.ndarray]],
    units: tuple[_Unit, ...],
    quantity: str,
    shared_scale: bool,
    plane: tuple[str, str] = _PLATFORM_PLANE,
) -> None:
    """Side-by-side scatters over a plane (axis labels `plane`) of SI magnitudes on log colour scales,
    shared or one per panel."""
    axes = np.atleast_1d(figure.subplots(1, len(panels), sharex=True, sharey=True))
    shared = _log_norm(np.concatenate([v for _, v in panels])) if shared_scale else None
    for ax, (label, v) in zip(axes, panels):
        drawn = v > 0
        mappable = ax.scatter(
            xy[drawn, 0], xy[drawn, 1], c=v[drawn], norm=shared or _log_norm(v), cmap="viridis", s=16, edgecolors="none"
        )
        if not drawn.all():
            ax.scatter(xy[~drawn, 0], xy[~drawn, 1], marker="x", s=16, color="k", label="exactly 0")
            ax.legend(fontsize="small")
        ax.set_title(
            f"{label}\nmean {_readable(float(np.mean(v)), units)}, max {_readable(float(np.max(v)), units)}",
            fontsize="medium",
        )
        ax.set_xlabel(plane[0])
        ax.set_aspect("equal", adjustable="box")
        ax.grid(True, alpha=0.3)
        if shared is None or ax is axes[-1]:
            colorbar = figure.colorbar(mappable, ax=ax if shared is None else list(axes), label=quantity)
            _readable_log_axis(colorbar.ax.yaxis, units)
    axes[0].set_ylabel(plane[1])


def plot_workspace_error_map(
    targets: object,
    errors_before: Sequence[float] | np.ndarray,
    errors_after: Sequence[float] | np.ndarray,
    path: StrPath | PlotFile,
    kind: str = "position",
    shared_scale: bool = False,
    title: str = "Error of the actual platform over the workspace",
) -> Path:
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
        raise InvalidInputError(
            f"{len(xy)} targets, {len(before)} errors before, {len(after)} after: one error of each per target"
        )
    _check_output(path)
    figure = Figure(figsize=(8.5, 6.0), layout="constrained")
    planar = _finite_array(targets, "targets", ndim=2).shape[1] == 2  # the five-bar's x, y: nothing projected
    figure.suptitle(f"{title}\n({len(xy)} targets{'' if planar else '; z and theta projected onto x-y'})")
    _scatter_panels(
        figure,
        xy,
        [("uncompensated", before), ("compensated", after)],
        _LENGTH_UNITS if kind == "position" else _ANGLE_UNITS,
        f"{kind} error",
        shared_scale,
    )
    return _save(figure, path)


def plot_predicted_std_map(
    targets: object,
    std: PoseErrors,
    path: StrPath | PlotFile,
    title: str = "Predicted standard deviation of the calibrated platform pose",
    plane: tuple[str, str] = _PLATFORM_PLANE,
) -> Path:
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
    _check_output(path)
    figure = Figure(figsize=(8.5, 6.0), layout="constrained")
    figure.suptitle(f"{title}\n({len(xy)} poses; the other coordinates projected onto this plane)")
    left, right = cast(np.ndarray, figure.subfigures(1, 2))  # an array for more than one subfigure
    _scatter_panels(left, xy, [("position", position)], _LENGTH_UNITS, "predicted position std", False, plane)
    _scatter_panels(right, xy, [("orientation", rotation)], _ANGLE_UNITS, "predicted orientation std", False, plane)
    return _save(figure, path)


# ------------------------------------------------------------------------------------------------
# Validation of a calibrated model on a measurement file


def _validation_rows(
    errors: object, flagged: object, labels: Sequence[str], what: str
) -> tuple[np.ndarray, np.ndarray]:
    """(errors, flagged mask) checked against each other and the labels, one per predicted row."""
    values = _nonnegative(_finite_array(errors, what), what)
    mask = np.asarray(flagged, dtype=bool).reshape(-1)
    if not len(mask) == len(labels) == len(values):
        raise InvalidInputError(f"{len(values)} {what}, {len(mask)} flags, {len(labels)} labels: one of each per row")
    return values, mask


def _flag_description(mask: np.ndarray, labels: Sequence[str]) -> str:
    return "flagged: " + (", ".join(labels[int(i)] for i in np.flatnonzero(mask)) or "none")


def _name_flagged(ax, x: np.ndarray, y: np.ndarray, mask: np.ndarray, labels: Sequence[str]) -> None:
    """Circle the flagged points in red and name the first `_MAX_LABELS` of them."""
    ax.scatter(
        x[mask],
        y[mask],
        s=70,
        facecolors="none",
        edgecolors="tab:red",
        linewidths=1.2,
        label=f"beyond the 5-sigma gate ({int(mask.sum())})",
    )
    for k in np.flatnonzero(mask)[:_MAX_LABELS]:
        ax.annotate(
            labels[k], (x[k], y[k]), xytext=(4, 4), textcoords="offset points", fontsize="x-small", color="tab:red"
        )


def _chi3_cdf(radius: np.ndarray, sigma: float) -> np.ndarray:
    """P(|e| <= radius) for a 3-D error with independent N(0, sigma^2) coordinates (Maxwell)."""
    return scipy.special.gammainc(1.5, np.square(radius / sigma) / 2.0)


def plot_validation_histogram(
    position: object,
    rotation: object | None,
    noise: tuple[float, float],
    scale: float,
    flagged: object,
    labels: Sequence[str],
    path: StrPath | PlotFile,
    title: str = "Prediction errors of the calibrated model",
) -> Path:
    """Histograms of the position [m] (and rotation [rad], or None) errors of validated rows, the rows
    beyond the gate stacked in red, against the counts the noise model expects: a 3-D error of
    independent N(0, sigma^2) coordinates, sigma = noise (sigma_p [m], sigma_r [rad]) times `scale`
    (s, from the calibration's variance factor; the stated noise dashed when s > 1). Log-spaced bins
    on a log axis: gross rows sit decades beyond the rest. flagged, labels: per row (the PNG's
    description names the flagged rows). Returns the PNG path."""
    series = [("position error", _LENGTH_UNITS, position, noise[0])]
    if rotation is not None:
        series.append(("rotation error", _ANGLE_UNITS, rotation, noise[1]))
    checked = [
        (name, units, *_validation_rows(values, flagged, labels, name), sigma) for name, units, values, sigma in series
    ]
    if not (math.isfinite(scale) and scale >= 1.0) or min(noise) <= 0:
        raise InvalidInputError(f"noise {noise} and scale {scale}: positive noise and a scale of at least 1")
    _check_output(path)
    figure = Figure(figsize=(max(6.5, 5.0 * len(checked)), 4.2), layout="constrained")
    figure.suptitle(title)
    axes = np.atleast_1d(figure.subplots(1, len(checked)))
    for ax, (name, units, values, mask, sigma) in zip(axes, checked):
        low = min(float(values[values > 0].min(initial=sigma * scale)), 0.1 * sigma)
        high = max(float(values.max()), 5 * sigma * scale)
        edges = np.geomspace(low, high * 1.001, 31)
        ax.hist(
            [values[~mask], values[mask]],
            bins=edges,
            stacked=True,
            color=["tab:blue", "tab:red"],
            label=[f"rows within the gate ({int((~mask).sum())})", f"beyond the gate ({int(mask.sum())})"],
        )
        curves = [(1.0, "--", "noise as stated")]
        if scale > 1.0:
            curves.append((scale, "-", f"noise x s = {scale:.3g}"))
        for factor, style, text in curves:
            expected = len(values) * np.diff(_chi3_cdf(edges, sigma * factor))
            ax.stairs(
                expected,
                edges,
                color="black",
                linestyle=style,
                label=f"{text} ({_readable(sigma * factor, units)} per axis)",
            )
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(_ReadableLogFormatter(units))
        ax.xaxis.set_minor_formatter(_two_and_five(units))  # every minor label would collide on this axis
        ax.set_xlabel(
            f"{name} (mean {_readable(float(values.mean()), units)}, "
            f"RMS {_readable(float(np.sqrt(np.mean(values**2))), units)})"
        )
        ax.set_ylabel("rows")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    return _save(figure, path, _flag_description(checked[0][3], labels))


def _two_and_five(units: tuple[_Unit, ...]):
    """Tick labels of a log axis at 2 and 5 times a power of ten only."""

    def label(value: float, _: object) -> str:
        mantissa = round(value / 10.0 ** math.floor(math.log10(value)), 6) if value > 0 else 0.0
        return _readable(value, units) if mantissa in (2.0, 5.0) else ""

    return label


def _normal_quantiles(count: int) -> np.ndarray:
    """Expected order statistics of `count` standard normal draws (Blom's plotting positions)."""
    return scipy.special.ndtri((np.arange(1, count + 1) - 0.375) / (count + 0.25))


def plot_normalised_qq(
    residuals: object,
    scale: float,
    flagged: object,
    labels: Sequence[str],
    path: StrPath | PlotFile,
    title: str = "Normalised residuals against the noise model",
) -> Path:
    """Normal QQ plot of every residual coordinate divided by its stated noise: residuals (M, 3) or
    (M, 6), [dp / sigma_p, dr / sigma_r] per validated row (`Validation.residuals`), one panel for
    position and one for orientation. Under the noise model the points lie on y = x; on y = s x when
    the noise is s times the stated (`scale`, drawn when above 1). Each flagged row's farthest
    coordinate is circled and named by its label. Symmetric-log y axis: linear within a few sigmas.
    Returns the PNG path."""
    z = _finite_array(residuals, "residuals", ndim=2)
    if z.shape[1] not in (3, 6):
        raise InvalidInputError(f"residuals: shape {z.shape}, expected (rows, 3) or (rows, 6)")
    _, mask = _validation_rows(np.zeros(len(z)), flagged, labels, "residual rows")
    _check_output(path)
    panels = [("position", z[:, :3])] + ([("orientation", z[:, 3:])] if z.shape[1] == 6 else [])
    figure = Figure(figsize=(max(6.5, 5.0 * len(panels)), 4.5), layout="constrained")
    figure.suptitle(title)
    axes = np.atleast_1d(figure.subplots(1, len(panels)))
    for ax, (name, block) in zip(axes, panels):
        values, rows = block.reshape(-1), np.repeat(np.arange(len(block)), block.shape[1])
        order = np.argsort(values)
        theory, values, rows = _normal_quantiles(len(values)), values[order], rows[order]
        ax.plot(theory, values, ".", ms=3, color="tab:blue", label=f"{name} coordinates ({len(values)})")
        span = np.array([theory[0], theory[-1]])
        ax.plot(span, span, "--", color="black", lw=0.9, label="noise as stated")
        if scale > 1.0:
            ax.plot(span, scale * span, "-", color="black", lw=0.9, label=f"noise x s = {scale:.3g}")
        farthest = np.zeros(len(values), dtype=bool)
        for row in np.flatnonzero(mask):
            at = np.flatnonzero(rows == row)
            farthest[at[np.argmax(np.abs(values[at]))]] = True
        _name_flagged(ax, theory, values, farthest, [labels[int(r)] for r in rows])
        linear = max(3.0, 3.0 * scale)
        if np.abs(values).max() > 10 * linear:  # gross rows: linear within a few sigmas, logarithmic beyond
            ax.set_yscale("symlog", linthresh=linear)
            ax.yaxis.set_major_formatter(lambda value, _: f"{value:g}")
        ax.set_xlabel("standard normal quantile")
        ax.set_ylabel(f"{name} residual / stated noise")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small", loc="upper left")
    return _save(figure, path, _flag_description(mask, labels))


def plot_errors_over_workspace(
    positions: object,
    errors: object,
    flagged: object,
    labels: Sequence[str],
    path: StrPath | PlotFile,
    frame: str = "measurement frame",
    title: str = "Position error of the calibrated model where each row was measured",
) -> Path:
    """The measured positions (M, 3) [m] in `frame`, over x-y and x-z, coloured by each row's
    position error [m] (log colour scale), the flagged rows circled and named by their label.
    Returns the PNG path."""
    xyz = _finite_array(positions, "positions", ndim=2)
    if xyz.shape[1] != 3:
        raise InvalidInputError(f"positions: shape {xyz.shape}, expected (rows, 3)")
    values, mask = _validation_rows(errors, flagged, labels, "errors")
    if len(values) != len(xyz):
        raise InvalidInputError(f"{len(xyz)} positions for {len(values)} errors")
    _check_output(path)
    figure = Figure(figsize=(10.0, 4.8), layout="constrained")
    figure.suptitle(
        f"{title}\n(mean {_readable(float(values.mean()), _LENGTH_UNITS)}, "
        f"max {_readable(float(values.max()), _LENGTH_UNITS)})"
    )
    axes = figure.subplots(1, 2)
    norm = _log_norm(values)
    drawn = values > 0
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2))):
        mappable = ax.scatter(
            xyz[drawn, i], xyz[drawn, j], c=values[drawn], norm=norm, cmap="viridis", s=18, edgecolors="none"
        )
        _name_flagged(ax, xyz[:, i], xyz[:, j], mask, labels)
        ax.set_xlabel(f"{frame} {'xyz'[i]} [m]")
        ax.set_ylabel(f"{frame} {'xyz'[j]} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize="small")
    colorbar = figure.colorbar(mappable, ax=list(axes), label="position error")
    _readable_log_axis(colorbar.ax.yaxis, _LENGTH_UNITS)
    return _save(figure, path, _flag_description(mask, labels))
