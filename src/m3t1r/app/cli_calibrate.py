"""`m3t1r calibrate` for the closed-loop machine: a tracker campaign from file to judged result.

Reads the measurements (in the tracker's frame and units), fits the machine with the measurement
frame and marker, flags outliers, judges the fit (refusing what the data do not support, with the
likely cause named), cross-validates it, says in plain words what the data could not determine,
and writes the calibrated pair and the report as a unit.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime as _dt
import math
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TextIO

import numpy as np
import pinocchio as pin

from m3t1r._version import __version__
from m3t1r.app.cli_common import (
    RowFailures,
    calibration_options,
    campaign_report_fields,
    checked_marker,
    held_out_entry,
    load_mechanism,
    outlier_sources,
    parse_priors,
    selection_note,
    status_stream,
)
from m3t1r.app.cli_noise import NoiseChoice, ResidualSummary, fit_with_noise, judge_fit
from m3t1r.app.cli_verbs import CALIBRATION_PLOTS, DECLARE_PLOTS, load
from m3t1r.app.datasets import MeasurementFile, read_measurements
from m3t1r.app.passive_joints import passive_joint_residuals
from m3t1r.calibration.assessment import (
    MAX_NOISE_RATIO,
    FitRejected,
    StartCheck,
    check_start,
    coverage_notes,
    describe_parameter,
    fit_movement_notes,
    gross_reading_reason,
    likely_causes,
    metres_as_millimetres_causes,
    quaternion_order_causes,
    residual_causes,
    unexplained_residual_warning,
)
from m3t1r.calibration.closed_loop import ClosedLoopCalibration, CrossValidation, calibrate_closed_loop, cross_validate
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.repeats import pose_groups
from m3t1r.errors import IdentificationError, InvalidInputError, PoorExcitationWarning
from m3t1r.io.instruments.formats import export_hint
from m3t1r.io.outputs import OutputSet
from m3t1r.io.progress import Progress
from m3t1r.metrics import PoseErrors, pose_errors_between
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import declared_workspace

__all__ = ["cmd_calibrate", "run_closed_loop_calibration", "calibration_report"]

#: A fitted parameter whose standard deviation exceeds these is "weakly determined" [m], [rad].
WEAK_TRANSLATION, WEAK_ROTATION = 1e-3, 1e-3
_DIAGNOSIS_POSES = 200  # the likely-cause checks look at this many poses at most
_MODEL_FLOOR_POSITION = 1e-6
"""[m] A fitted position residual RMS below this is below any tracker's noise: what is left is the
model's own floor (its linearisation, the parameters held at nominal), not a setup error."""


def _nominal_points(nominal: Mechanism, marker: pin.SE3) -> Callable[[np.ndarray], np.ndarray]:
    solver = ClosedLoopSolver(nominal)

    def predict(actuators: np.ndarray) -> np.ndarray:
        """Marker frames (N, 4, 4) [m] at each slider set, from home; NaN where it does not assemble
        (frames, not points: the checks register the marker's further offset, as the fit does)."""
        frames = np.full((len(actuators), 4, 4), np.nan)
        if len(actuators) == 0:
            return frames
        solved = solver.forward_batch(actuators)
        frames[solved.indices] = solved.poses @ marker.homogeneous
        return frames

    return predict


def _checked_rows(data: MeasurementFile) -> np.ndarray:
    """The rows the data checks read: every row, or with several points those seeing the most-seen one
    (the measurements' `poses`)."""
    return np.flatnonzero([np.all(np.isfinite(g.translation)) for g in data.measurements.poses])


def _checked(data: MeasurementFile) -> MeasurementFile:
    if data.measurements.points is None:
        return data
    keep = _checked_rows(data)
    return dataclasses.replace(data, measurements=data.measurements.subset(keep), lines=data.lines[keep])


def _diagnose(
    nominal: Mechanism, data: MeasurementFile, marker: pin.SE3, frame_estimated: bool, units: str
) -> list[str]:
    measurements = _checked(data).measurements
    pick = np.linspace(0, len(measurements) - 1, min(len(measurements), _DIAGNOSIS_POSES)).astype(int)
    measured = np.array([measurements.poses[i].translation for i in pick])
    model = nominal.model
    prismatic = np.array(
        [model.joints[model.getJointId(n)].shortname().startswith("JointModelP") for n in nominal.actuated_joints]
    )
    if units == "mm":
        metres = metres_as_millimetres_causes(
            _nominal_points(nominal, marker),
            measurements.actuators[pick],
            measured,
            prismatic,
            frame_estimated=frame_estimated,
        )
        if metres:
            return metres
    return likely_causes(
        _nominal_points(nominal, marker),
        measurements.actuators[pick],
        measured,
        nominal.actuated_joints,
        frame_estimated=frame_estimated,
        angular=~prismatic,
    )


def cmd_calibrate(args: argparse.Namespace) -> None:
    """`m3t1r calibrate` without --serial: a closed-loop calibration from a measurement file."""
    args.prior = parse_priors(args.prior)
    if getattr(args, "compliance", False) or getattr(args, "joint", None):
        raise InvalidInputError("--compliance and --joint apply to a serial robot (--serial) only")
    if (hint := export_hint(Path(args.measurements))) is not None:
        raise InvalidInputError(hint)
    run_closed_loop_calibration(args, load_mechanism(args.model, args.closures))


def run_closed_loop_calibration(args: argparse.Namespace, nominal: Mechanism) -> None:
    """The whole `calibrate` verb for a closed-loop machine (module docstring).

    Every output (the pair, the report, the plots) is checked before the fit and written as one
    unit after it: a failure anywhere, the plots' included, leaves every old file as it was.
    """
    held_out_path = getattr(args, "validate", None)  # --validate FILE (a namespace built in code may lack it)
    outputs = OutputSet(inputs=(args.measurements, nominal.urdf_path, nominal.closures_path, held_out_path))
    machine_output = outputs.add_machine(args.output, "-o")
    report_output = outputs.add(args.report, "--report")
    plots = load(DECLARE_PLOTS)(outputs, args.plots) if args.plots else None  # matplotlib with --plots only
    out = status_stream(outputs)  # stderr when the report goes to stdout
    with outputs:
        outputs.check()
        # Every status line, the helpers' too, goes to `out`: with `--report -` stdout is the JSON alone.
        with contextlib.redirect_stdout(out):
            data = read_measurements(args.measurements, nominal, units=args.units)
            held_out = read_measurements(held_out_path, nominal, units=args.units) if held_out_path else None
            _check_points(args, data, held_out)
            marker = MeasurementSetup.from_numbers(marker_xyz=checked_marker(args.marker)).marker
            estimate_frame = args.frame == "estimate"
            print(
                f"calibrating from {len(data.measurements)} poses"
                + (" (measurement frame estimated)" if estimate_frame else "")
                + " ...",
                file=out,
                flush=True,
            )
            start = _precheck(nominal, data, marker, estimate_frame, args.measurements, args.units)
            fitted_data = _without_gross_readings(args, data, start)
            with warnings.catch_warnings(record=True) as caught, Progress("calibrating", None) as progress:
                warnings.simplefilter("always", PoorExcitationWarning)
                calibration, choice = fit_with_noise(
                    args.noise_pos,
                    args.noise_rot,
                    TrackerNoise(actuator=args.noise_act),
                    lambda noise, gate: _fit(
                        args, nominal, fitted_data, noise, marker, estimate_frame, progress.advance, gate
                    ),
                    lambda fitted: _left(fitted, fitted_data),
                )
            noise = choice.noise
            lines = sorted(
                [int(fitted_data.lines[i]) for i in calibration.outliers] + [int(data.lines[i]) for i in start.gross]
            )
            print(choice.describe(data.measurements.position_only), file=out)
            _print_summary(calibration, lines, out)
            sources = outlier_sources(data.lines, data.sources, lines)
            if sources:
                print("outliers in the tracker's file (the source column): " + ", ".join(map(str, sources)), file=out)
            unexplained = judge_fit(
                calibration.converged,
                calibration.lm.termination,
                calibration.lm.iterations,
                calibration.variance_factor,
                choice,
                lambda: _fit_causes(args, nominal, fitted_data, marker, estimate_frame, calibration, choice),
                force=args.force,
            )
            with Progress(f"cross-validating ({args.folds} folds)", None) as progress:
                assert calibration.problem is not None, "calibrate_closed_loop keeps its problem"
                calibration.problem.on_evaluate = progress.advance
                validation = cross_validate(
                    calibration,
                    folds=args.folds,
                    groups=pose_groups(fitted_data.measurements.actuators, fitted_data.sources),
                )
            notes = explain(calibration, [str(w.message) for w in caught])
            _print_judgement(calibration, validation, notes, out)
            warned = (
                [
                    unexplained_residual_warning(
                        calibration.variance_factor, _implied_noise(calibration, noise), validation.errors.position_mean
                    )
                ]
                if unexplained
                else []
            )
            for warning in warned:
                print(f"m3t1r: warning: {warning}", file=sys.stderr)
            report = calibration_report(calibration, data, nominal, noise, args, lines, validation, notes)
            report["noise_source"], report["warnings"] = choice.report(), warned
            if data.sources is not None:
                report["outlier_sources"] = sources
            if held_out is not None:
                report["held_out"] = _score_held_out(calibration, held_out)
            if data.passive_joints:
                report["passive_joint_cross_validation"] = _idle_chain_check(nominal, calibration, data, out)
        outputs.stage_machine(machine_output, calibration.mechanism)
        outputs.stage_json(report_output, report)
        if plots is not None:
            print("rendering plots (cross-validation recalibrates on subsets) ...", file=out, flush=True)
            load(CALIBRATION_PLOTS)(
                nominal,
                calibration,
                plots,
                noise=noise,
                outputs=outputs,
                labels=[f"line {line}" for line in fitted_data.lines],
            )
        written = outputs.commit()
    print("wrote " + ", ".join(written), file=out)


def _check_points(args: argparse.Namespace, data: MeasurementFile, held_out: MeasurementFile | None) -> None:
    """Refuse --marker on a file of several points (each point's offset is estimated), and a
    --validate file whose points per row differ from the measurement file's."""
    points = data.measurements.n_points
    if points and args.marker is not None:
        raise InvalidInputError(
            f"{args.measurements} holds {points} points per row, each point's offset on the "
            "platform is estimated: --marker (one point) does not apply"
        )
    if points and getattr(args, "plots", None):
        raise InvalidInputError(
            f"{args.measurements} holds {points} points per row: --plots draws one measured "
            "frame per pose; calibrate without --plots"
        )
    if held_out is not None and held_out.measurements.n_points != points:
        what = [
            f"{p} points per row" if p else "one measured frame per row"
            for p in (points, held_out.measurements.n_points)
        ]
        raise InvalidInputError(f"--validate {held_out.path}: {what[1]}, but {args.measurements} has {what[0]}")


def _idle_chain_check(
    nominal: Mechanism, calibration: ClosedLoopCalibration, data: MeasurementFile, out: TextIO = sys.stdout
) -> dict:
    """Passive-joint readings the fit did not use, predicted by the nominal and the calibrated model."""
    actuators = data.measurements.actuators
    before = passive_joint_residuals(nominal, actuators, data.passive_joints, data.passive)
    after = passive_joint_residuals(calibration.mechanism, actuators, data.passive_joints, data.passive)
    print("passive-joint readings the fit did not use (RMS after removing each encoder's zero offset):", file=out)
    for k, name in enumerate(data.passive_joints):
        print(f"  {name}: nominal {before.rms[k]:.3e}, calibrated {after.rms[k]:.3e}", file=out)
    return {
        name: {
            "nominal_rms": float(before.rms[k]),
            "calibrated_rms": float(after.rms[k]),
            "calibrated_offset": float(after.offsets[k]),
        }
        for k, name in enumerate(data.passive_joints)
    }


def _fit(
    args: argparse.Namespace,
    nominal: Mechanism,
    data: MeasurementFile,
    noise: TrackerNoise,
    marker: pin.SE3,
    estimate_frame: bool,
    progress: Callable[[], None],
    gate: bool = True,
) -> ClosedLoopCalibration:
    """The fit of the data (`_precheck` judged them first; `gate`: with the --outlier-sigma gate)."""
    groups = pose_groups(data.measurements.actuators, data.sources)
    options = calibration_options(args, noise, marker, estimate_frame, groups, gate)
    return calibrate_closed_loop(nominal, data.measurements, options, progress=progress)


def _left(calibration: ClosedLoopCalibration, data: MeasurementFile) -> ResidualSummary:
    """What the fit left; with several points per pose, each point seen counts as a 3-row measurement."""
    position, rotation = calibration.rms_after
    measurements = data.measurements
    if measurements.points is not None:
        inliers = np.setdiff1d(np.arange(len(measurements)), calibration.outliers)
        seen = int(np.count_nonzero(np.isfinite(measurements.points[inliers, :, 0])))
        return ResidualSummary(position, rotation, seen, 3, len(calibration.fitted))
    return ResidualSummary(
        position,
        rotation,
        len(measurements) - len(calibration.outliers),
        measurements.rows_per_pose,
        len(calibration.fitted),
    )


def _implied_noise(calibration: ClosedLoopCalibration, noise: TrackerNoise) -> str:
    """The noise the residual implies, stated noise times sqrt(variance factor), in words."""
    factor = float(np.sqrt(calibration.variance_factor))
    assert calibration.problem is not None, "calibrate_closed_loop keeps its problem"
    rotation = "" if calibration.problem.measurements.position_only else f" and {factor * noise.rotation:.3g} rad"
    return f"{factor * noise.position:.3g} m{rotation}"


def _fit_causes(
    args: argparse.Namespace,
    nominal: Mechanism,
    data: MeasurementFile,
    marker: pin.SE3,
    estimate_frame: bool,
    calibration: ClosedLoopCalibration,
    choice: NoiseChoice,
) -> list[str]:
    """Likely causes of a fit that does not explain the data (`data`: the poses it was given): a
    stated noise below the model's floor (a residual below any tracker's noise), else quaternion
    columns in another order, else the data checks and, by the size of what the fit left
    (`residual_causes`), a measured frame whose orientation is not the platform's while no marker
    was given to absorb it."""
    measurements = data.measurements
    beyond_noise = calibration.variance_factor > MAX_NOISE_RATIO**2 or not calibration.converged
    if calibration.rms_after[0] < _MODEL_FLOOR_POSITION and beyond_noise and not choice.position_estimated:
        noise = choice.noise
        stated = f"{noise.position:g} m" + (
            "" if measurements.position_only or choice.rotation_estimated else f", {noise.rotation:g} rad"
        )
        return [
            f"the stated noise ({stated}) is below what the model can fit: the residual "
            f"({calibration.rms_after[0]:.2g} m RMS) is already below any tracker's noise, the floor of the model "
            "itself (its linearisation, the parameters held at nominal), which also flags sound rows as outliers; "
            "state the tracker's real noise with --noise-pos and --noise-rot"
        ]
    if not measurements.position_only:
        solved = ClosedLoopSolver(nominal).forward_batch(measurements.actuators)
        poses = [measurements.poses[i] for i in solved.indices]
        order = quaternion_order_causes(
            solved.poses @ marker.homogeneous,
            np.array([g.translation for g in poses]),
            np.array([g.rotation for g in poses]),
            frame_estimated=estimate_frame,
        )
        if order:  # the whole story: every other check would read the scrambled orientations
            return order
    return _diagnose(nominal, data, marker, estimate_frame, args.units) + residual_causes(
        *calibration.rms_after,
        beyond_noise=beyond_noise,
        marker_given=args.marker is not None or measurements.n_points > 0,
        position_only=measurements.position_only,
    )


def _precheck(
    nominal: Mechanism, data: MeasurementFile, marker: pin.SE3, estimate_frame: bool, path: str, units: str = "m"
) -> StartCheck:
    """Refuse at once when the nominal model is further from the data than any build error, and
    name every line whose slider readings do not assemble on it (one batch solve of every row).
    Returns the start check of every pose: its `gross` readings are left out of the fit."""
    measurements = data.measurements
    if len(measurements) < 3:
        raise IdentificationError(
            f"{path}: {len(measurements)} pose(s) are far too few to calibrate (tens of poses "
            "spread over the workspace are needed; `m3t1r plan` chooses them)"
        )
    if units == "mm":
        _refuse_metres_read_as_millimetres(nominal, data, path)
    points = _nominal_points(nominal, marker)(measurements.actuators)
    assembled = np.all(np.isfinite(points.reshape(len(points), -1)), axis=1)
    pick = np.linspace(0, len(measurements) - 1, min(len(measurements), _DIAGNOSIS_POSES)).astype(int)
    valid = assembled[pick]
    if np.count_nonzero(valid) < 3:
        raise FitRejected(
            "the slider readings do not assemble on the nominal machine",
            _diagnose(nominal, data, marker, estimate_frame, units),
            forceable=False,
        )
    failed = np.flatnonzero(~assembled)
    if failed.size:
        raise RowFailures(
            Path(path),
            [
                (
                    int(data.lines[i]),
                    "the slider readings do not assemble on the nominal machine (from its home, on its branch)",
                )
                for i in failed
            ],
        )
    rows = _checked_rows(data)
    measured = np.array([measurements.poses[i].translation for i in rows])
    check = check_start(
        points[rows], measured, estimate_frame, lambda: _diagnose(nominal, data, marker, estimate_frame, units)
    )
    if len(rows) == len(measurements):
        return check
    distances = np.full(len(measurements), np.nan)
    distances[rows] = check.distances
    return StartCheck(distances, check.typical, tuple(int(rows[i]) for i in check.gross))


def _refuse_metres_read_as_millimetres(nominal: Mechanism, data: MeasurementFile, path: str) -> None:
    """Sliders of a metre file read with --units mm sit within a thousandth of their stroke around
    zero, where the machine barely moves: a fit would only report unidentifiable parameters."""
    model = nominal.model
    lower, upper = nominal.joint_limits()
    sliders = [
        k
        for k, name in enumerate(nominal.actuated_joints)
        if model.joints[model.getJointId(name)].shortname().startswith("JointModelP")
    ]
    if not sliders:
        return
    for k in sliders:
        values, stroke = data.measurements.actuators[:, k], upper[k] - lower[k]
        if not np.isfinite(stroke) or np.ptp(values) >= 0.01 * stroke:
            return
        if not np.all((values * 1e3 >= lower[k]) & (values * 1e3 <= upper[k])):
            return
    raise InvalidInputError(
        f"{path}: read with --units mm, every slider spans under 1 % of its stroke, and in "
        "metres every value is within its limits: the file looks like metres; drop --units mm"
    )


def _without_gross_readings(args: argparse.Namespace, data: MeasurementFile, start: StartCheck) -> MeasurementFile:
    """The data without the poses the start check found gross (they are outliers, reported by line);
    with the outlier gate off (--outlier-sigma 0) such a pose is refused by line instead."""
    if not start.gross:
        return data
    reasons = [(int(data.lines[i]), gross_reading_reason(start, i)) for i in start.gross]
    if not args.outlier_sigma:
        raise RowFailures(
            Path(args.measurements),
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
    keep = np.setdiff1d(np.arange(len(data.measurements)), start.gross)
    return dataclasses.replace(
        data,
        measurements=data.measurements.subset(keep),
        passive=data.passive[keep],
        lines=data.lines[keep],
        sources=None if data.sources is None else data.sources[keep],
    )


def _score_held_out(calibration: ClosedLoopCalibration, held_out: MeasurementFile) -> dict:
    """Score a held-out measurement file (`--validate`): each row assembled from home on the calibrated
    machine, seen through the fitted measurement frame and marker; rows that do not assemble are listed."""
    measurements = held_out.measurements
    solved = ClosedLoopSolver(calibration.mechanism).forward_batch(measurements.actuators)
    if not len(solved.indices):
        raise InvalidInputError(f"--validate {held_out.path}: no row assembles on the calibrated machine")
    failed = sorted(int(held_out.lines[f.index]) for f in solved.failures)
    if measurements.points is not None:  # one error per point seen
        difference = calibration.setup.measured_points(solved.poses) - measurements.points[solved.indices]
        position = np.linalg.norm(difference, axis=2)
        position = position[np.isfinite(position)]
        return held_out_entry(
            held_out.path,
            held_out.sha256,
            len(measurements),
            PoseErrors(position, np.full(len(position), np.nan)),
            True,
            "point",
            failed,
        )
    measured = np.array([measurements.poses[i].homogeneous for i in solved.indices]).reshape(-1, 4, 4)
    errors = pose_errors_between(calibration.setup.measured_poses(solved.poses), measured)
    assert calibration.problem is not None, "a calibration made by calibrate_closed_loop keeps its problem"
    position_only = measurements.position_only or calibration.problem.measurements.position_only
    return held_out_entry(held_out.path, held_out.sha256, len(measurements), errors, position_only, failed_lines=failed)


def _print_summary(calibration: ClosedLoopCalibration, outlier_lines: list[int], out: TextIO = sys.stdout) -> None:
    before, after = calibration.rms_before, calibration.rms_after
    fitted = len(calibration.fitted)
    print(
        f"identified {calibration.base.rank} of {len(calibration.std)} parameters "
        f"(condition number {calibration.base.condition_number:.3g}); fitted {fitted} "
        f"in {calibration.lm.iterations} iterations ({'converged' if calibration.converged else 'NOT converged'})",
        file=out,
    )
    if fitted > calibration.base.rank:
        print(
            f"note: fitted more than the {calibration.base.rank} parameters the nominal identifies: the estimate "
            "identifies more (the nominal is a special geometry, e.g. planar or with exact parallelograms), "
            "and the data determine them",
            file=out,
        )
    orientation = (
        ""
        if not (math.isfinite(before[1]) and math.isfinite(after[1]))
        # position-only data
        else f", orientation {before[1]:.3e} -> {after[1]:.3e} rad"
    )
    print(
        f"residual RMS position {before[0]:.3e} -> {after[0]:.3e} m{orientation}; "
        f"variance factor {calibration.variance_factor:.3g}",
        file=out,
    )
    if outlier_lines:
        print(f"outliers (left out of the fit), file lines: {', '.join(map(str, outlier_lines))}", file=out)
    else:
        print("outliers: none", file=out)


def _print_judgement(
    calibration: ClosedLoopCalibration, validation: CrossValidation, notes: list[str], out: TextIO = sys.stdout
) -> None:
    errors = validation.errors
    rotation = "" if np.isnan(errors.rotation_mean) else f", {errors.rotation_mean:.3e} rad"
    rms = float(np.sqrt(np.mean(np.square(errors.position))))
    grouped = f"; {validation.groups} distinct poses, each held out whole" if validation.groups else ""
    print(
        f"cross-validation ({validation.folds} folds{grouped}): predicting held-back measurements "
        f"{errors.position_mean:.3e} m{rotation} mean, {rms:.3e} m RMS (noise included: what `m3t1r validate` will "
        "show on fresh measurements of the same quality)",
        file=out,
    )
    for note in notes:
        print(f"note: {note}", file=out)


def explain(calibration: ClosedLoopCalibration, warnings_seen: Sequence[str] = ()) -> list[str]:
    """Plain-word notes: what the data could not determine, and how far the fit moved."""
    notes = list(warnings_seen)
    base, fitted = set(calibration.base.names), set(calibration.fitted)
    setup_names = [n for n in calibration.std if n.startswith(("measurement_frame.", "marker."))]
    gauge = [n for n in setup_names if n not in base]
    if gauge:
        notes.append(
            "not separable from the machine or the measurement frame with these data, kept at the given "
            "value: "
            + ", ".join(describe_parameter(n) for n in gauge)
            + " (a marker offset along the platform z axis is the frame's height while the platform never tilts)"
        )
    notes += selection_note(sorted(base - fitted), calibration.selection)
    weak = [
        n
        for n in calibration.fitted
        if n in calibration.parameters
        and calibration.std[n] > (WEAK_TRANSLATION if n.rpartition(".dt[")[2] in ("0]", "1]", "2]") else WEAK_ROTATION)
    ]
    if weak:
        notes.append(
            "weakly determined on their own (std over 1 mm / 1 mrad; their joint effect on the "
            "platform can still be well determined): "
            + ", ".join(f"{describe_parameter(n)} (std {calibration.std[n]:.2g})" for n in weak[:8])
        )
    notes += _coverage(calibration, bool(weak))
    machine = {n: v for n, v in calibration.parameters.items() if n in fitted}
    marker_estimated = any(n.startswith("marker.") for n in calibration.std)
    notes += fit_movement_notes(
        machine,
        calibration.rms_before[0],
        calibration.rms_after[0],
        None if marker_estimated else calibration.mechanism.platform_frame,
        std=calibration.std,
    )
    if calibration.variance_factor < 0.05:
        notes.append(
            f"the residual is {np.sqrt(calibration.variance_factor):.2g} times the stated noise: the "
            "measurements are more precise than stated, so the standard deviations above are pessimistic "
            "(--noise-pos, --noise-rot)"
        )
    return notes


def _coverage(calibration: ClosedLoopCalibration, weak: bool) -> list[str]:
    problem = calibration.problem
    if problem is None or not weak:
        return []
    mechanism = calibration.mechanism
    actuators = problem.measurements.actuators[problem.active]
    workspace = declared_workspace(mechanism)
    if workspace.kind == "actuators":
        names, values = mechanism.actuated_joints, actuators
    else:
        names = mechanism.task.box_keys
        values = mechanism.task.box_coordinates(ClosedLoopSolver(mechanism).forward_batch(actuators).task_poses)
    lo, hi = workspace.bounds(names)
    spans = coverage_notes(np.array(values), {name: (a, b) for name, a, b in zip(names, lo, hi)})
    if not spans:
        return ["the poses cover the workspace box; more poses would tighten the weak parameters"]
    return ["poses spread over more of the workspace would excite them: " + "; ".join(spans)]


def calibration_report(
    calibration: ClosedLoopCalibration,
    data: MeasurementFile,
    nominal: Mechanism,
    noise: TrackerNoise,
    args: argparse.Namespace | None = None,
    outlier_lines: Sequence[int] = (),
    validation: CrossValidation | None = None,
    notes: Sequence[str] = (),
) -> dict:
    """The JSON report of a closed-loop calibration (models/README.md documents every field)."""
    base, fitted = set(calibration.base.names), set(calibration.fitted)
    setup, selection = calibration.setup, calibration.selection
    return {
        "tool": f"m3t1r {__version__}",
        "created": _dt.datetime.now().isoformat(timespec="seconds"),
        "kind": "closed_loop",
        "input": {
            "path": str(data.path),
            "sha256": data.sha256,
            "poses": len(data.measurements),
            "position_only": data.measurements.position_only,
            "units": getattr(args, "units", "m"),
            "points": data.measurements.n_points,
        },
        "nominal_model": {"urdf": str(nominal.urdf_path), "closures": str(nominal.closures_path)},
        "measured_frame": nominal.platform_frame,
        **campaign_report_fields(setup, list(calibration.std), validation, selection, calibration.fitted, args),
        "noise_model": {"position_m": noise.position, "rotation_rad": noise.rotation, "actuator_m": noise.actuator},
        "converged": calibration.converged,
        "variance_factor": calibration.variance_factor,
        "outliers": list(outlier_lines),
        "identifiable": {
            "count": calibration.base.rank,
            "of": len(calibration.std),
            "condition_number": calibration.base.condition_number,
            "names": list(calibration.base.names),
        },
        "residual_rms": {
            "before": {"position_m": calibration.rms_before[0], "rotation_rad": calibration.rms_before[1]},
            "after": {"position_m": calibration.rms_after[0], "rotation_rad": calibration.rms_after[1]},
        },
        "solver": {
            "iterations": calibration.lm.iterations,
            "converged": calibration.converged,
            "termination": calibration.lm.termination,
        },
        "notes": list(notes),
        "parameters": [
            {
                "name": name,
                "value": calibration.parameters.get(name, 0.0),
                "std": std,
                "identifiable": name in base,
                "fitted": name in fitted,
            }
            for name, std in calibration.std.items()
            if name in calibration.parameters
        ],
    }
