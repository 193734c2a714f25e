"""What every `m3t1r` verb shares: loading the machine pair, status lines, progress, provenance, row failures."""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO, cast

import numpy as np
import pinocchio as pin

from m3t1r._version import __version__
from m3t1r.calibration.assessment import describe_parameter
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.errors import InvalidInputError, M3t1rError, ModelWarning, OutputPathError
from m3t1r.io.pairing import paired_closures_path, recorded_closures_sha256
from m3t1r.io.paths import read_bounded
from m3t1r.io.poses import POSE_COLUMNS, pose_rows
from m3t1r.io.progress import Progress
from m3t1r.io.tables import table_text
from m3t1r.model.description import Mechanism
from m3t1r.model.mjcf_io import is_mjcf
from m3t1r.model.workspace import default_workspace_notes

__all__ = [
    "RowFailures",
    "load_mechanism",
    "say",
    "status_stream",
    "progress_bar",
    "provenance",
    "parse_priors",
    "parse_joint_values",
    "check_plots_folder",
    "checked_marker",
    "MAX_MARKER_DISTANCE",
]


#: A measured point farther than this from the platform (serial: tool) frame is not on it [m].
MAX_MARKER_DISTANCE = 10.0


def checked_marker(values: Sequence[float] | None) -> Sequence[float] | None:
    """--marker X Y Z [m], refused (InvalidInputError) when the point is farther than
    MAX_MARKER_DISTANCE from the frame it is fixed to: such numbers are millimetres, since --marker
    is in metres whatever --units says."""
    if values is None:
        return None
    distance = math.sqrt(sum(v * v for v in values))
    if distance > MAX_MARKER_DISTANCE:
        metres = " ".join(f"{v / 1000:g}" for v in values)
        raise InvalidInputError(
            f"--marker {' '.join(f'{v:g}' for v in values)}: a point {distance:.3g} m from the "
            f"frame it is fixed to; --marker is in metres whatever --units says (in millimetres "
            f"these are --marker {metres})"
        )
    return values


class RowFailures(M3t1rError):
    """Some input rows could not be processed; nothing was written."""

    def __init__(self, path: Path, failures: list[tuple[int, str]]) -> None:
        self.failures = failures
        lines = "\n".join(f"  {path}, line {line}: {reason}" for line, reason in failures)
        super().__init__(f"{len(failures)} row(s) failed, nothing written:\n{lines}")


def load_mechanism(urdf: str | None, closures: str | None):
    """Load a machine; a URDF without --closures loads with its pair NAME.closures.yaml (sha256-checked)."""
    if urdf is not None and closures is None and not _is_mjcf_file(urdf):  # an MJCF holds its own closures
        sibling = paired_closures_path(urdf)
        try:
            recorded = recorded_closures_sha256(read_bounded(urdf) or b"")
        except (OSError, M3t1rError):
            recorded = None  # Mechanism.load names the problem with the URDF
        if recorded is None and not sibling.is_file() and Path(urdf).is_file():
            raise InvalidInputError(f"--closures is required with {urdf} (no {sibling.name} beside it)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)  # printed below as notes, once, without a traceback line
        mechanism = Mechanism.load(urdf, closures)
    for note in mechanism.notes + tuple(default_workspace_notes(mechanism)):
        print(f"note: {mechanism.closures_path.name}: {note}", file=sys.stderr)
    return mechanism


def _is_mjcf_file(path: str) -> bool:
    try:
        return is_mjcf(read_bounded(path) or b"")
    except OSError:
        return False  # Mechanism.load names the problem


def status_stream(outputs) -> TextIO:
    """Where status lines go: stdout, or stderr when an output of the command is stdout (`-o -`,
    `--report -`), so that the output stays machine-readable."""
    to_stdout = outputs is None or all(o.path is not None for o in outputs.outputs)
    return sys.stdout if to_stdout else sys.stderr


def say(outputs, message: str) -> None:
    """A status line on `status_stream(outputs)`."""
    print(message, file=status_stream(outputs), flush=True)


#: Rows per call of a batch solver in the long verbs: a progress step, and a moment for a signal
#: (Ctrl-C, SIGTERM) to act, every fraction of a second.
BATCH_ROWS = 5000


def table_chunk_text(columns: Sequence[str], rows, comments: Sequence[str] | None) -> str:
    """`table_text` of one chunk of a table's rows: the whole head (comments, header) with the first
    chunk (`comments` given, possibly empty), the data lines alone with a later one (None)."""
    text = table_text(columns, rows, comments or ())
    return text if comments is not None else text.split("\n", 1)[1]


def pose_table_text(solver, actuators: np.ndarray, lines: np.ndarray, path: Path, comments: Sequence[str]) -> str:
    """The poses table of `m3t1r fk`: each slider set's platform pose from home (`solver`, a
    `ClosedLoopSolver`), solved `BATCH_ROWS` at a time with a progress display, which changes no
    result since every row starts from home. Raises RowFailures naming every row that failed."""
    pieces: list[str] = []
    failures: list[tuple[int, str]] = []
    with progress_bar("fk", len(actuators)) as progress:
        for start in range(0, len(actuators), BATCH_ROWS):
            batch = solver.forward_batch(actuators[start : start + BATCH_ROWS])
            failures += [(int(lines[start + f.index]), f.reason) for f in batch.failures]
            if not failures:
                rows = pose_rows([pin.SE3(pose) for pose in batch.poses])
                pieces.append(table_chunk_text(POSE_COLUMNS, rows, None if pieces else comments))
            progress.update(min(start + BATCH_ROWS, len(actuators)))
    if failures:
        raise RowFailures(path, failures)
    return "".join(pieces)


def progress_bar(label: str, total: int):
    """A progress display on stderr for `total` rows."""
    return Progress(label, total)


def provenance(args: argparse.Namespace) -> list[str]:
    """Comment lines naming the version, the time and the command that wrote a file."""
    return [
        f"written by m3t1r {__version__} on {_dt.datetime.now().isoformat(timespec='seconds')}",
        "command: m3t1r " + " ".join(sys.argv[1:]) if sys.argv[1:] else "command: m3t1r (API)",
    ]


def parse_priors(entries: list[str]) -> dict[str, float]:
    """["q12=1e-3", ...] -> {"q12": 0.001}; InvalidInputError naming the entry otherwise."""
    priors = {}
    for entry in entries:
        name, _, value = entry.partition("=")
        try:
            sigma = float(value)
        except ValueError:
            sigma = float("nan")
        if not name or not (math.isfinite(sigma) and sigma > 0):
            raise InvalidInputError(f"--prior {entry}: expected NAME=SIGMA with SIGMA > 0 [m or rad]")
        priors[name] = sigma
    return priors


def parse_joint_values(entries: list[str] | None) -> dict[str, float]:
    """--joint ["tool_changer=0.5", ...] -> {"tool_changer": 0.5} [rad or m]; InvalidInputError naming
    the entry otherwise."""
    values: dict[str, float] = {}
    for entry in entries or ():
        name, _, text = entry.partition("=")
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not name or not math.isfinite(value):
            raise InvalidInputError(f"--joint {entry}: expected NAME=VALUE, the joint's constant value [rad or m]")
        if name in values:
            raise InvalidInputError(f"--joint {name}: given twice")
        values[name] = value
    return values


def check_plots_folder(path: str | Path) -> Path:
    """The plots' folder as a Path; OutputPathError naming it when it exists and is not a folder
    (checked before any work, so that a file there is refused and left alone)."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise OutputPathError(folder, "exists and is not a folder (the plots go into a folder)")
    return folder


def campaign_report_fields(
    setup: MeasurementSetup,
    estimated: Sequence[str],
    validation,
    selection,
    fitted: Sequence[str],
    args: argparse.Namespace | None,
) -> dict:
    """The report fields closed-loop and serial calibrations share (models/README.md): the
    measurement frame and marker (`estimated`: the setup parameter names that were estimated),
    the cross-validation, the selection, and the --fix / --prior / --force choices."""
    errors = None if validation is None else validation.errors
    placements = cast("dict[str, dict]", setup.to_report())
    return {
        **placements,  # measurement_frame, marker, and the points when the setup has some
        "measurement_frame": {
            **placements["measurement_frame"],
            "estimated": any(n.startswith("measurement_frame.") for n in estimated),
        },
        "marker": {**placements["marker"], "estimated": any(n.startswith("marker.") for n in estimated)},
        "cross_validation": None
        if errors is None
        else {
            "position_mean_m": errors.position_mean,
            "rotation_mean_rad": errors.rotation_mean,
            "position_rms_m": float(np.sqrt(np.mean(np.square(errors.position)))),
            "rotation_rms_rad": None
            if np.all(np.isnan(errors.rotation))
            else float(np.sqrt(np.mean(np.square(errors.rotation)))),
            "folds": validation.folds,
            "groups": getattr(validation, "groups", None) or None,
        },
        "selection": {
            "method": "forward_loo" if selection else "none",
            "kept": list(fitted),
            "press": selection.press if selection else None,
            "press_all": selection.press_all if selection else None,
            "tied": selection.tied if selection else None,
        },
        "fixed": list(getattr(args, "fix", None) or []),
        "priors": dict(getattr(args, "prior", None) or {}),
        "forced": bool(getattr(args, "force", False)),
    }


def held_out_entry(
    path: Path,
    sha256: str,
    poses: int,
    errors,
    position_only: bool,
    per: str = "pose",
    failed_lines: Sequence[int] = (),
) -> dict:
    """Print the score of a held-out measurement file (`calibrate --validate`) and return its report
    entry: position error mean, RMS and max [m], rotation mean and RMS [rad] unless position_only, per
    pose (or per point); failed_lines: rows the calibrated model could not predict (not scored)."""
    position = np.asarray(errors.position, dtype=float)
    rms = float(np.sqrt(np.mean(np.square(position))))
    rotation_rms = None if position_only else float(np.sqrt(np.mean(np.square(errors.rotation))))
    rotation = (
        "" if rotation_rms is None else f"; rotation {errors.rotation_mean:.3e} rad mean, {rotation_rms:.3e} rad RMS"
    )
    failed = (
        f"; {len(failed_lines)} rows not predicted (lines {', '.join(map(str, failed_lines[:10]))})"
        if failed_lines
        else ""
    )
    print(
        f"held-out file {path} ({poses} poses): position error per {per} {errors.position_mean:.3e} m mean, "
        f"{rms:.3e} m RMS, {float(np.max(position)):.3e} m max{rotation}{failed}"
    )
    return {
        "path": str(path),
        "sha256": sha256,
        "poses": poses,
        "per": per,
        "position_mean_m": float(errors.position_mean),
        "position_rms_m": rms,
        "position_max_m": float(np.max(position)),
        "rotation_mean_rad": None if rotation_rms is None else float(errors.rotation_mean),
        "rotation_rms_rad": rotation_rms,
        "failed_lines": [int(line) for line in failed_lines],
    }


def outlier_sources(
    lines: Sequence[int] | np.ndarray, sources: Sequence[int] | np.ndarray | None, outlier_lines: Sequence[int]
) -> list[int]:
    """The `source` value (the pose in the tracker's file) of each outlier's file line; none without
    a `source` column."""
    if sources is None:
        return []
    source_of_line = {int(line): int(source) for line, source in zip(lines, sources)}
    return [source_of_line[line] for line in outlier_lines]


def selection_note(dropped: Sequence[str], selection) -> list[str]:
    """The plain-word note on identifiable parameters that model selection held at nominal."""
    if not dropped:
        return []
    tied = f"; {selection.tied} other set sizes score within one standard error" if selection else ""
    return [
        f"{len(dropped)} identifiable parameters held at nominal because they did not predict left-out poses "
        f"better (leave-one-pose-out{tied}): "
        + ", ".join(describe_parameter(n) for n in dropped[:8])
        + (" ..." if len(dropped) > 8 else "")
    ]


def calibration_options(
    args: argparse.Namespace,
    noise: TrackerNoise,
    marker: pin.SE3,
    estimate_frame: bool,
    groups: np.ndarray,
    gate: bool = True,
    compliance: bool = False,
) -> CalibrationOptions:
    """The settings `calibrate`'s flags give either fit (`--marker`, `--outlier-sigma` unless not `gate`,
    `--select`, `--fix`, `--prior`, `--max-iterations`); groups: the poses' repeat labels."""
    return CalibrationOptions(
        noise=noise,
        setup=MeasurementSetup(marker=marker),
        estimate_frame=estimate_frame,
        estimate_marker=args.marker is not None,
        outlier_sigma=(args.outlier_sigma or None) if gate else None,
        select=args.select == "loo",
        compliance=compliance,
        fixed=list(args.fix or ()),
        priors=dict(args.prior or {}),
        groups=groups,
        max_iterations=args.max_iterations,
    )
