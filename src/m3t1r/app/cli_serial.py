"""`m3t1r calibrate --serial`: a serial robot's tracker campaign from file to judged result.

Reads joint readings and measured poses (in the tracker's frame and units), fits the robot's
local-POE placement errors with the measurement frame and the marker (and, optionally, joint
compliance under gravity), flags outliers, judges the fit (refusing what the data do not support,
with the likely cause named), cross-validates it, says in plain words what the data could not
determine, and writes the calibrated URDF (the robot alone) and the report as a unit.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import sys
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pinocchio as pin

from m3t1r._version import __version__
from m3t1r.app.cli_common import (
    RowFailures,
    calibration_options,
    campaign_report_fields,
    checked_marker,
    held_out_entry,
    outlier_sources,
    parse_joint_values,
    parse_priors,
    selection_note,
    status_stream,
)
from m3t1r.app.cli_noise import NoiseChoice, ResidualSummary, fit_with_noise, judge_fit
from m3t1r.app.datasets import check_joint_readings, measured_points, most_seen_point, point_numbers
from m3t1r.calibration.assessment import (
    MAX_NOISE_RATIO,
    StartCheck,
    check_start,
    describe_parameter,
    fit_movement_notes,
    gross_reading_reason,
    likely_causes,
    quaternion_order_causes,
    residual_causes,
    unexplained_residual_warning,
)
from m3t1r.calibration.identification import parameter_columns
from m3t1r.calibration.measurement_setup import LENGTH_UNITS, MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.repeats import pose_groups
from m3t1r.calibration.serial import SerialCalibration, calibrate_serial, require_gravity_load
from m3t1r.calibration.serial_evaluation import SerialCrossValidation, cross_validate_serial, held_out_errors
from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot, load_serial_urdf, serial_chain_of
from m3t1r.errors import DataFileError, IdentificationError, InvalidInputError, PoorExcitationWarning
from m3t1r.io.instruments.formats import export_hint
from m3t1r.io.instruments.records import CONVERTED_COLUMNS
from m3t1r.io.outputs import OutputSet
from m3t1r.io.pairing import sha256_bytes
from m3t1r.io.poses import poses_from_table
from m3t1r.io.tables import read_header, read_table
from m3t1r.model.poe import SerialChain, tool_poses
from m3t1r.model.urdf_io import calibrated_urdf_bytes

__all__ = ["cmd_calibrate_serial", "run_serial_calibration", "serial_calibration_report", "SerialCampaign"]

#: A fitted parameter whose standard deviation exceeds these is "weakly determined" [m], [rad].
WEAK_TRANSLATION, WEAK_ROTATION = 1e-3, 1e-3
_EXAMPLE_ROBOTS = ("ur3", "ur5", "ur10", "panda")


@dataclass(frozen=True)
class SerialCampaign:
    """A measurement file read for a chain: readings (N, n) [rad, m], measured poses (SE3, m),
    the file's data lines (for outliers) and sha256; sources: the `source` column of a converted
    file (where each pose is in the tracker's file), or None. points: (N, P, 3) [m] of a file with P
    points per row (x1, y1, z1 ... xP, yP, zP; NaN where a point was not seen), else None; `poses`
    then hold the most-seen point (NaN where it was not seen), which the data checks read."""

    path: Path
    sha256: str
    readings: np.ndarray
    poses: list[pin.SE3]
    lines: np.ndarray
    position_only: bool
    units: str
    sources: np.ndarray | None = None
    points: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> SerialCampaign:
        """The campaign of rows `keep` (indices)."""
        return replace(
            self,
            readings=self.readings[keep],
            poses=[self.poses[i] for i in keep],
            lines=self.lines[keep],
            sources=None if self.sources is None else self.sources[keep],
            points=None if self.points is None else self.points[keep],
        )


def _robot(source: str, tool: str | None, base: str | None) -> tuple[pin.Model, SerialChain, Path | None]:
    """(model, chain, URDF path or None) of --serial: an example-robot-data name or a URDF path."""
    path = Path(source)
    if source in _EXAMPLE_ROBOTS and not path.exists():
        model = load_example_robot(source)
        return model, SerialChain.from_model(model, tool or example_tool_frame(source), base), None
    if not path.is_file():
        raise InvalidInputError(
            f"--serial {source}: neither an example robot ({', '.join(_EXAMPLE_ROBOTS)}) nor a URDF file"
        )
    if not tool:
        raise InvalidInputError(f"--serial {source}: give the measured frame with --tool FRAME")
    model, urdf = load_serial_urdf(path)
    return model, serial_chain_of(model, urdf, path, tool, base), path


def read_campaign(
    path: str,
    chain: SerialChain,
    units: str,
    model: pin.Model | None = None,
    constants: Mapping[str, float] | None = None,
) -> SerialCampaign:
    """Joint columns by joint name, x, y, z [, qx, qy, qz, qw]; lengths (x, y, z and prismatic
    joints) in `units` ("m" or "mm", `LENGTH_UNITS`), converted to m. `constants` {joint: value}
    [rad, m]: chain joints the file does not log (`--joint NAME=VALUE`: a tool changer that never
    moves), read as that value on every row. With `model`, a reading beyond its joint's URDF limits
    is a DataFileError naming its line and column."""
    if units not in LENGTH_UNITS:
        raise InvalidInputError(f"--units {units}: expected one of {', '.join(LENGTH_UNITS)}")
    names, constants = chain.joint_names, dict(constants or {})
    if unknown := sorted(set(constants) - set(names)):
        raise InvalidInputError(f"--joint {unknown[0]}: not a joint of the chain ({', '.join(names)})")
    numbers = point_numbers(read_header(path))
    point_columns = [f"{a}{k}" for k in numbers for a in "xyz"]
    try:
        table = read_table(
            path,
            required=tuple(n for n in names if n not in constants) + (() if numbers else ("x", "y", "z")),
            optional=(*constants, *CONVERTED_COLUMNS),
            optional_groups=(
                tuple(tuple(f"{a}{k}" for a in "xyz") for k in numbers) if numbers else (("qx", "qy", "qz", "qw"),)
            ),
            reject_duplicate_rows=True,
            blank_allowed=point_columns,
        )
    except DataFileError as exc:
        if exc.column in names and "missing required columns" in str(exc):
            raise DataFileError(
                path,
                f"{str(exc).partition(': ')[2]}; a chain joint that never moves and is not "
                f"logged (a tool changer) is given as --joint {exc.column}=VALUE [rad or m]",
                row=exc.row,
                column=exc.column,
            ) from None
        raise
    scale = LENGTH_UNITS[units]
    prismatic = ~np.any(chain.twists[:, 3:], axis=1)
    readings = np.column_stack(
        [
            table.column(n) * (scale if p else 1.0) if table.has_column(n) else np.full(table.n_rows, constants[n])
            for n, p in zip(names, prismatic)
        ]
    )
    if model is not None:
        # A continuous joint (cos, sin): Pinocchio's limits bound those, not the angle; not checked.
        at = [model.joints[model.getJointId(name)] for name in names]
        lower = np.array([model.lowerPositionLimit[j.idx_q] if j.nq == 1 else 0.0 for j in at])
        upper = np.array([model.upperPositionLimit[j.idx_q] if j.nq == 1 else 0.0 for j in at])
        for note in check_joint_readings(
            table, names, readings, lower, upper, prismatic, scales=np.where(prismatic, scale, 1.0), margin=LIMIT_MARGIN
        ):
            print(f"note: {note}", flush=True)
    points = measured_points(table, numbers, scale) if numbers else None
    position_only = points is not None or not table.has_column("qw")
    positions = (
        most_seen_point(points) if points is not None else np.column_stack([table.column(c) for c in "xyz"]) * scale
    )
    rotations = [np.eye(3)] * len(positions) if position_only else [g.rotation for g in poses_from_table(table)]
    return SerialCampaign(
        Path(path),
        sha256_bytes(Path(path).read_bytes()),
        readings,
        [pin.SE3(r, p) for r, p in zip(rotations, positions)],
        np.asarray(table.line_numbers),
        position_only,
        units,
        table.column("source").astype(int) if table.has_column("source") else None,
        points,
    )


#: A reading may pass its URDF limit by this share of the joint's range: a URDF's limits are nominal
#: and a real joint is read up to its stop (TIAGo's torso at 0.350181 m on a [0, 0.35] limit); such a
#: reading is kept, with a note. Beyond it, a reading is refused by line: a fault, not the machine.
LIMIT_MARGIN = 0.05


def _nominal_frames(model: pin.Model, chain: SerialChain, marker: pin.SE3) -> Callable[[np.ndarray], np.ndarray]:
    """readings (N, n) -> the measured frame (N, 4, 4) the nominal robot predicts in its base [m]
    (the given marker applied: the checks register the point's further offset, as the fit does)."""

    def predict(readings: np.ndarray) -> np.ndarray:
        return tool_poses(chain, model, readings) @ marker.homogeneous

    return predict


def _checked_rows(data: SerialCampaign) -> np.ndarray:
    """The rows the data checks read: every row, or with several points those seeing the most-seen one."""
    return np.flatnonzero([np.all(np.isfinite(g.translation)) for g in data.poses])


def _diagnose(
    model: pin.Model, chain: SerialChain, data: SerialCampaign, marker: pin.SE3, frame_estimated: bool
) -> list[str]:
    data = data.subset(_checked_rows(data)) if data.points is not None else data
    measured = np.array([g.translation for g in data.poses])
    return likely_causes(
        _nominal_frames(model, chain, marker),
        data.readings,
        measured,
        chain.joint_names,
        frame_estimated=frame_estimated,
        angular=np.any(chain.twists[:, 3:], axis=1),
    )


def _fit_causes(
    args: argparse.Namespace,
    model: pin.Model,
    chain: SerialChain,
    data: SerialCampaign,
    marker: pin.SE3,
    estimate_frame: bool,
    calibration: SerialCalibration,
    choice: NoiseChoice,
) -> list[str]:
    """Likely causes of a fit the noise does not explain (`data`: the poses it was given): quaternion
    columns in another order, else the data checks and, by the size of the residual left
    (`residual_causes`), a measured frame that is not the tool's while no marker was given."""
    if not data.position_only:
        predicted = tool_poses(chain, model, data.readings) @ marker.homogeneous
        order = quaternion_order_causes(
            predicted,
            np.array([g.translation for g in data.poses]),
            np.array([g.rotation for g in data.poses]),
            frame_estimated=estimate_frame,
        )
        if order:  # the whole story: every other check would read the scrambled orientations
            return order
    after = calibration.rms_after
    beyond_noise = not calibration.converged or not calibration.variance_factor <= MAX_NOISE_RATIO**2
    return _diagnose(model, chain, data, marker, estimate_frame) + residual_causes(
        after.position,
        after.rotation,
        beyond_noise=beyond_noise,
        marker_given=args.marker is not None or data.points is not None,
        position_only=data.position_only,
    )


def _precheck(
    model: pin.Model, chain: SerialChain, data: SerialCampaign, marker: pin.SE3, estimate_frame: bool
) -> StartCheck:
    """Refuse at once when the nominal robot is further from the data than any build error; the
    returned check's `gross` readings are left out of the fit."""
    if len(data.poses) < 3:
        raise IdentificationError(
            f"{data.path}: {len(data.poses)} pose(s) are far too few to calibrate (tens of "
            "poses spread over the joint ranges are needed; `m3t1r plan --serial` chooses them)"
        )
    rows = _checked_rows(data)
    checked = data.subset(rows) if len(rows) < len(data.poses) else data
    frames = _nominal_frames(model, chain, marker)(checked.readings)
    measured = np.array([g.translation for g in checked.poses])
    check = check_start(
        frames, measured, estimate_frame, lambda: _diagnose(model, chain, data, marker, estimate_frame), "robot"
    )
    if checked is data:
        return check
    distances = np.full(len(data.poses), np.nan)
    distances[rows] = check.distances
    return StartCheck(distances, check.typical, tuple(int(rows[i]) for i in check.gross))


def _without_gross_readings(args: argparse.Namespace, data: SerialCampaign, start: StartCheck) -> SerialCampaign:
    """The campaign without the poses the start check found gross (outliers, reported by line); with
    the outlier gate off (--outlier-sigma 0) such a pose is refused by line instead."""
    if not start.gross:
        return data
    reasons = [(int(data.lines[i]), gross_reading_reason(start, i)) for i in start.gross]
    if not args.outlier_sigma:
        raise RowFailures(
            data.path,
            [
                (
                    line,
                    reason + "; remove or re-measure the row, or let the outlier gate (--outlier-sigma) leave it out",
                )
                for line, reason in reasons
            ],
        )
    for line, reason in reasons:
        print(f"note: line {line}: {reason}; left out as an outlier", flush=True)
    return data.subset(np.setdiff1d(np.arange(len(data.poses)), start.gross))


def cmd_calibrate_serial(args: argparse.Namespace) -> None:
    """`m3t1r calibrate --serial`: a serial robot's calibration from a measurement file."""
    args.prior = parse_priors(args.prior)
    args.joint = parse_joint_values(args.joint)
    if args.compliance and not args.report:
        raise InvalidInputError(
            "--compliance: the fitted compliance is kept in the report (a URDF cannot hold it) "
            "and validate and compensate read it there: give --report JSON"
        )
    if (hint := export_hint(Path(args.measurements))) is not None:
        raise InvalidInputError(hint)
    run_serial_calibration(args)


def run_serial_calibration(args: argparse.Namespace) -> None:
    """The whole `calibrate --serial` verb (module docstring). Raises FitRejected (exit 1) when the fit
    is not supported by the data, unless args.force."""
    model, chain, urdf = _robot(args.serial, args.tool, args.base)
    if args.compliance:
        try:
            require_gravity_load(model, chain)
        except InvalidInputError as exc:
            raise InvalidInputError(f"--compliance with {args.serial}: {exc}") from None
    held_out_path = getattr(args, "validate", None)  # --validate FILE (a namespace built in code may lack it)
    outputs = OutputSet(inputs=(args.measurements, urdf, held_out_path))
    urdf_output = outputs.add(args.output, "-o") if urdf is not None else None
    report_output = outputs.add(args.report, "--report")
    with outputs:  # a failure anywhere removes every claimed temporary file
        outputs.check()
        # Status lines go to stderr when the report is stdout (`--report -`): the JSON stays parseable.
        with contextlib.redirect_stdout(status_stream(outputs)):
            if urdf is None:
                print(
                    f"{args.serial} is an example-robot-data robot: no calibrated URDF is written "
                    "(give its URDF path to --serial for one)" + (f"; -o {args.output} ignored" if args.output else "")
                )
            data, held_out = _read_inputs(args, chain, model, held_out_path)
            marker = MeasurementSetup.from_numbers(marker_xyz=checked_marker(args.marker)).marker
            estimate_frame = args.frame == "estimate"
            start = _precheck(model, chain, data, marker, estimate_frame)
            print(
                f"calibrating chain {chain.joint_names[0]} .. {chain.tool_frame} from {len(data.poses)} poses"
                + (" (measurement frame estimated)" if estimate_frame else "")
                + " ...",
                flush=True,
            )
            fitted_data = _without_gross_readings(args, data, start)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", PoorExcitationWarning)
                calibration, choice = fit_with_noise(
                    args.noise_pos,
                    args.noise_rot,
                    TrackerNoise(),
                    lambda noise, gate: _fit(args, model, chain, fitted_data, noise, marker, estimate_frame, gate),
                    lambda fitted: _left(fitted, fitted_data),
                )
            noise = choice.noise
            lines = sorted(
                [int(fitted_data.lines[i]) for i in calibration.outliers] + [int(data.lines[i]) for i in start.gross]
            )
            print(choice.describe(data.position_only))
            _print_summary(calibration, lines)
            sources = outlier_sources(data.lines, data.sources, lines)
            if sources:
                print("outliers in the tracker's file (the source column): " + ", ".join(map(str, sources)))
            unexplained = judge_fit(
                calibration.converged,
                calibration.termination,
                calibration.iterations,
                calibration.variance_factor,
                choice,
                lambda: _fit_causes(args, model, chain, fitted_data, marker, estimate_frame, calibration, choice),
                force=args.force,
            )
            validation = cross_validate_serial(
                calibration, folds=args.folds, groups=pose_groups(fitted_data.readings, fitted_data.sources)
            )
            notes = explain(calibration, [str(w.message) for w in caught], list(args.fix or ()))
            warned = (
                [
                    unexplained_residual_warning(
                        calibration.variance_factor, _implied_noise(calibration, noise), validation.errors.position_mean
                    )
                ]
                if unexplained
                else []
            )
            _print_judgement(validation, notes, calibration.setup.points)
            for warning in warned:
                print(f"m3t1r: warning: {warning}", file=sys.stderr)
            report = serial_calibration_report(calibration, data, args, noise, lines, validation, notes)
            report["noise_source"], report["warnings"] = choice.report(), warned
            if held_out is not None:
                report["held_out"] = _score_held_out(calibration, held_out)
            if data.sources is not None:
                report["outlier_sources"] = sources
        if urdf_output is not None and urdf is not None:  # one is None when the other is
            outputs.stage(urdf_output, calibrated_urdf_bytes(urdf, calibration.model))
        outputs.stage_json(report_output, report)
        written = outputs.commit()
    if written:
        print("wrote " + ", ".join(written), file=status_stream(outputs))


def _read_inputs(
    args: argparse.Namespace, chain: SerialChain, model: pin.Model, held_out_path: str | None
) -> tuple[SerialCampaign, SerialCampaign | None]:
    """The measurement file and the --validate file, read alike before any work."""
    data = read_campaign(args.measurements, chain, args.units, model, getattr(args, "joint", None))
    if data.points is not None and args.marker is not None:
        raise InvalidInputError(
            f"{args.measurements} holds {data.points.shape[1]} points per row, each "
            "point's offset on the tool is estimated: --marker (one point) does not apply"
        )
    held_out = (
        read_campaign(held_out_path, chain, args.units, model, getattr(args, "joint", None)) if held_out_path else None
    )
    if held_out is not None:
        points = [0 if d.points is None else d.points.shape[1] for d in (data, held_out)]
        if points[0] != points[1]:
            what = [f"{p} points per row" if p else "one measured frame per row" for p in points]
            raise InvalidInputError(f"--validate {held_out_path}: {what[1]}, but {args.measurements} has {what[0]}")
    return data, held_out


def _fit(
    args: argparse.Namespace,
    model: pin.Model,
    chain: SerialChain,
    data: SerialCampaign,
    noise: TrackerNoise,
    marker: pin.SE3,
    estimate_frame: bool,
    gate: bool = True,
) -> SerialCalibration:
    measured = np.array([g.translation for g in data.poses]) if data.position_only else data.poses
    if data.points is not None:
        measured = data.points
    groups = pose_groups(data.readings, data.sources)
    options = calibration_options(args, noise, marker, estimate_frame, groups, gate, bool(args.compliance))
    return calibrate_serial(model, chain, data.readings, measured, options, position_only=data.position_only)


def _left(calibration: SerialCalibration, data: SerialCampaign) -> ResidualSummary:
    """What the fit left; with several points per pose, each point seen counts as a 3-row measurement."""
    after = calibration.rms_after
    if data.points is not None:
        inliers = np.setdiff1d(np.arange(len(data.points)), calibration.outliers)
        seen = int(np.count_nonzero(np.isfinite(data.points[inliers, :, 0])))
        return ResidualSummary(after.position, after.rotation, seen, 3, len(calibration.fitted))
    return ResidualSummary(
        after.position,
        after.rotation,
        len(data.poses) - len(calibration.outliers),
        3 if calibration.position_only else 6,
        len(calibration.fitted),
    )


def _implied_noise(calibration: SerialCalibration, noise: TrackerNoise) -> str:
    """The noise the residual implies, stated noise times sqrt(variance factor), in words."""
    factor = float(np.sqrt(calibration.variance_factor))
    rotation = "" if calibration.position_only else f" and {factor * noise.rotation:.3g} rad"
    return f"{factor * noise.position:.3g} m{rotation}"


def _print_summary(calibration: SerialCalibration, outlier_lines: list[int]) -> None:
    before, after = calibration.rms_before, calibration.rms_after
    print(
        f"identified {calibration.base.rank} of {len(calibration.names)} parameters "
        f"(condition number {calibration.base.condition_number:.3g}); fitted {len(calibration.fitted)} in "
        f"{calibration.iterations} iterations ({'converged' if calibration.converged else 'NOT converged'}: "
        f"{calibration.termination})"
    )
    orientation = (
        "" if calibration.position_only else f", orientation {before.rotation:.3e} -> {after.rotation:.3e} rad"
    )
    print(
        f"residual RMS position {before.position:.3e} -> {after.position:.3e} m{orientation}; "
        f"variance factor {calibration.variance_factor:.3g}"
    )
    if calibration.compliance:
        print(
            "joint compliance under gravity: "
            + ", ".join(f"{j} {c:.3g} rad/Nm" for j, c in calibration.compliance.items())
        )
    print(
        f"outliers (left out of the fit), file lines: {', '.join(map(str, outlier_lines))}"
        if outlier_lines
        else "outliers: none"
    )


def _print_judgement(validation: SerialCrossValidation, notes: list[str], points: tuple = ()) -> None:
    errors = validation.errors
    rotation = "" if np.isnan(errors.rotation_mean) else f", {errors.rotation_mean:.3e} rad"
    rms = float(np.sqrt(np.mean(np.square(errors.position))))
    grouped = f"; {validation.groups} distinct postures, each held out whole" if validation.groups else ""
    per = f" per point ({len(points)} per pose)" if points else ""
    print(
        f"cross-validation ({validation.folds} folds{grouped}): predicting held-back measurements{per} "
        f"{errors.position_mean:.3e} m{rotation} mean, {rms:.3e} m RMS (noise included, as fresh measurements "
        "would show)"
    )
    for note in notes:
        print(f"note: {note}")


def _score_held_out(calibration: SerialCalibration, held_out: SerialCampaign) -> dict:
    """Score a held-out measurement file (`--validate`) with the calibration, print it; its report entry."""
    if held_out.points is not None:
        measured: np.ndarray = held_out.points
    else:
        measured = np.array([g.homogeneous for g in held_out.poses])
    errors = held_out_errors(calibration, held_out.readings, measured, held_out.position_only)
    return held_out_entry(
        held_out.path,
        held_out.sha256,
        len(held_out.poses),
        errors,
        held_out.position_only or calibration.position_only,
        "point" if held_out.points is not None else "pose",
    )


def _is_translation(name: str) -> bool:
    return name.rpartition(".dt[")[2] in ("0]", "1]", "2]")


def explain(calibration: SerialCalibration, warnings_seen: Sequence[str] = (), fixed: Sequence[str] = ()) -> list[str]:
    """Plain-word notes: the gauge, what selection dropped, weak parameters, what stays nominal (held
    by `fixed`, the --fix names, or not separable), how far the fit moved."""
    notes = list(warnings_seen)
    base, fitted = set(calibration.base.names), set(calibration.fitted)
    chain_names = set(calibration.chain.parameter_names())
    if any(n.startswith("measurement_frame.") for n in calibration.names):
        notes.append(
            "the measurement frame takes up the robot's base placement errors (the first joint's "
            "placement stays nominal, so the calibrated URDF's base is the robot's base)"
        )
    dropped = sorted((base - fitted) & (chain_names | {n for n in calibration.names if n.startswith("compliance.")}))
    notes += selection_note(dropped, calibration.selection)
    std = calibration.std()
    weak = [
        n
        for n in calibration.fitted
        if n in chain_names and std[n] > (WEAK_TRANSLATION if _is_translation(n) else WEAK_ROTATION)
    ]
    if weak:
        notes.append(
            "weakly determined on their own (std over 1 mm / 1 mrad; their joint effect on the tool can "
            "still be well determined): " + ", ".join(f"{describe_parameter(n)} (std {std[n]:.2g})" for n in weak[:8])
        )
    against = {joint: c for joint, c in calibration.compliance.items() if c > 0}
    if against:
        notes.append(
            "fitted compliance of the wrong sign (a joint giving way against gravity; a spring of stiffness "
            "k gives c = -1/k < 0): "
            + ", ".join(f"{j} {c:+.3g}" for j, c in against.items())
            + "; these columns stand for another effect that follows the gravity torque, not a stiffness"
        )
    held = {calibration.names[c] for c in parameter_columns(calibration.names, fixed, "--fix")} & chain_names
    notes.append(_nominal_note(calibration, chain_names, held))
    if held == chain_names:  # the machine could not move: how far it moved says nothing
        return notes
    moved = {n: float(v) for n, v in zip(calibration.names, calibration.values) if n in fitted and n in chain_names}
    marker_estimated = any(n.startswith("marker.") for n in calibration.names)
    notes += fit_movement_notes(
        moved,
        calibration.rms_before.position,
        calibration.rms_after.position,
        None if marker_estimated else calibration.chain.tool_frame,
        _along_last_axis(calibration.chain),
        std,
    )
    return notes


def _along_last_axis(chain: SerialChain) -> tuple[str, ...]:
    """The last joint's placement translations along its own axis (a revolute joint's axis through its
    origin, along a coordinate axis): they commute with the joint, so they move the tool frame as a
    translation of the tool frame would."""
    linear, angular = chain.twists[-1, :3], chain.twists[-1, 3:]
    axis = np.flatnonzero(np.abs(angular) > 1.0 - 1e-12)
    if axis.size != 1 or np.any(linear):
        return ()
    return (f"{chain.joint_names[-1]}.dt[{int(axis[0])}]",)


def _nominal_note(calibration: SerialCalibration, chain_names: set[str], held: set[str]) -> str:
    """What stays nominal among the placement components: `held` by --fix, or not separable."""
    free = chain_names - held
    if not free:
        return (
            f"every placement component ({len(chain_names)}) is held at nominal by --fix: only the measurement "
            "setup" + (" and the compliance were" if calibration.compliance else " was") + " fitted, and the "
            "calibrated URDF keeps the nominal geometry"
        )
    undetermined = len(free) - len(set(calibration.base.names) & free)
    text = f"{undetermined} of {len(free)} placement components"
    if held:
        text += f" left free ({len(held)} more are held at nominal by --fix)"
    return text + (
        " are not separable with these data (redundant with others or with the measurement setup) and stay nominal"
    )


def serial_calibration_report(
    calibration: SerialCalibration,
    data: SerialCampaign,
    args: argparse.Namespace,
    noise: TrackerNoise,
    outlier_lines: Sequence[int] = (),
    validation: SerialCrossValidation | None = None,
    notes: Sequence[str] = (),
) -> dict:
    """The JSON report of a serial calibration (strict JSON through io.json_text: NaN becomes null)."""
    chain, setup, selection = calibration.chain, calibration.setup, calibration.selection
    std, fitted = calibration.std(), set(calibration.fitted)
    robot_parameters = [n for n in calibration.names if not n.startswith(("measurement_frame.", "marker."))]
    values = dict(zip(calibration.names, calibration.values))
    before, after = calibration.rms_before, calibration.rms_after
    return {
        "tool": f"m3t1r {__version__}",
        "created": _dt.datetime.now().isoformat(timespec="seconds"),
        "kind": "serial",
        "input": {
            "path": str(data.path),
            "sha256": data.sha256,
            "poses": len(data.poses),
            "position_only": data.position_only,
            "units": data.units,
            "points": 0 if data.points is None else int(data.points.shape[1]),
        },
        "nominal_model": {
            "robot": str(args.serial),
            "base": chain.base_frame,
            "tool": chain.tool_frame,
            "chain": list(chain.joint_names),
        },
        "measured_frame": chain.tool_frame,
        **campaign_report_fields(setup, calibration.names, validation, selection, calibration.fitted, args),
        "noise_model": {"position_m": noise.position, "rotation_rad": noise.rotation, "joint_rad": 0.0},
        "converged": calibration.converged,
        "termination": calibration.termination,
        "iterations": calibration.iterations,
        "variance_factor": calibration.variance_factor,
        "outliers": list(outlier_lines),
        "identifiable": {
            "count": calibration.base.rank,
            "of": len(calibration.names),
            "condition_number": calibration.base.condition_number,
            "names": list(calibration.base.names),
        },
        "compliance": dict(calibration.compliance),
        "constant_joints": dict(getattr(args, "joint", None) or {}),
        "residual_rms": {
            "before": {"position_m": before.position, "rotation_rad": before.rotation},
            "after": {"position_m": after.position, "rotation_rad": after.rotation},
        },
        "notes": list(notes),
        "parameters": [
            {"name": n, "value": float(values[n]) if n in fitted else 0.0, "std": std.get(n), "fitted": n in fitted}
            for n in robot_parameters
        ],
    }
