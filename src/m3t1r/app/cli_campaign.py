"""Command-line verbs of a measurement campaign: `m3t1r plan` (what to measure) and `m3t1r validate`
(how well a calibrated model predicts a measurement file).

Their options are in `m3t1r.app.cli_parser`; `m3t1r.app.cli` runs `cmd_plan` and `cmd_validate`.
`add_plan_parser(verbs)` and `add_validate_parser(verbs)` add them to a parser of one's own with
`args.run` set. Errors are m3t1r errors (exit status 2 in `m3t1r.app.cli.main`); `validate
--predictions` with rows that could not be predicted raises `cli_common.RowFailures` (status 1) and
writes nothing.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from typing import TextIO

import numpy as np
import pinocchio as pin

from m3t1r.app import cli_parser
from m3t1r.app.cli_common import RowFailures, load_mechanism, provenance, say
from m3t1r.app.cli_verbs import DECLARE_VALIDATION_PLOTS, VALIDATION_PLOTS, load
from m3t1r.calibration.measurement_setup import LENGTH_UNITS
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.planning import plan_closed_loop, plan_serial
from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot, load_serial_urdf, serial_chain_of
from m3t1r.calibration.validation import validate
from m3t1r.errors import InvalidInputError, ModelWarning
from m3t1r.io.outputs import OutputSet
from m3t1r.io.pairing import paired_closures_path
from m3t1r.io.poses import POSE_COLUMNS, pose_rows
from m3t1r.io.progress import Heartbeat
from m3t1r.io.tables import table_text
from m3t1r.model.poe import SerialChain

__all__ = ["add_plan_parser", "add_validate_parser", "cmd_plan", "cmd_validate"]


# ------------------------------------------------------------------------------------------------
# plan


def add_plan_parser(verbs: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `plan` verb to argparse's subparsers object `verbs`, run by `cmd_plan` (`args.run`)."""
    parser = cli_parser.add_plan_parser(verbs)
    parser.set_defaults(run=cmd_plan)
    return parser


def _serial_robot(source: str, tool: str | None, base: str | None):
    """(model, chain) of `--serial` (an example robot name or a URDF path)."""
    path = Path(source)
    if path.suffix.lower() == ".urdf" or path.exists():
        model, urdf = load_serial_urdf(path)
        if tool is None:
            raise InvalidInputError(f"--serial {source}: give the measured frame with --tool FRAME")
        return model, serial_chain_of(model, urdf, path, tool, base)
    model = load_example_robot(source)
    return model, SerialChain.from_model(model, tool or example_tool_frame(source), base)


def _make_plan(args: argparse.Namespace):
    """The plan the arguments ask for, and the input files it read."""
    rng = np.random.default_rng(args.seed)
    if args.serial:
        if args.model or args.closures:
            raise InvalidInputError("--model/--closures describe the M machine; with --serial give the robot only")
        if args.fix:  # a serial plan is never refused for a direction at the rank tolerance
            raise InvalidInputError("--fix plans a closed-loop machine; a serial plan identifies every base parameter")
        model, chain = _serial_robot(args.serial, args.tool, args.base)
        noise = TrackerNoise(args.noise_pos, args.noise_rot)
        plan = plan_serial(
            model, chain, args.n, rng, n_candidates=args.candidates, noise=noise, position_only=args.position_only
        )
        return plan, [args.serial] if Path(args.serial).exists() else []
    if args.tool or args.base:
        raise InvalidInputError("--tool/--base apply to --serial only")

    mechanism = load_mechanism(args.model, args.closures)
    plan = plan_closed_loop(
        mechanism,
        args.n,
        rng,
        n_candidates=args.candidates,
        noise=TrackerNoise(args.noise_pos, args.noise_rot),
        position_only=args.position_only,
        fixed=args.fix,
    )
    return plan, [mechanism.urdf_path, mechanism.closures_path]


def _plan_summary(plan, args: argparse.Namespace) -> list[str]:
    """Lines describing a plan: what was chosen, its travel and predicted accuracy (also the CSV comments)."""
    what = "actuator sets" if plan.kind == "closed_loop" else "joint configurations"
    unit = "/".join(sorted(set(plan.column_units)))
    std = plan.accuracy.std
    lines = [
        f"{plan.n_poses} {what} chosen D-optimally among {plan.n_candidates} candidates (seed {args.seed}): "
        f"log det {plan.log_det:.6g}, condition number {plan.selection.condition_number:.3g}, "
        f"{len(plan.selection.columns)} identifiable parameters",
        f"travel (largest joint stroke per move, from home): {plan.travel:.4g} {unit} in this order, "
        f"{plan.travel_selection_order:.4g} {unit} in selection order",
        f"predicted accuracy after calibrating on this plan (tracker noise {plan.noise[0]:g} m / {plan.noise[1]:g} rad"
        f"{', position only' if plan.position_only else ''}), std at {plan.accuracy.n} workspace poses:",
        f"  position     mean {std.position_mean:.3e} m    max {std.position_max:.3e} m",
    ]
    if not plan.position_only:
        lines.append(f"  orientation  mean {std.rotation_mean:.3e} rad  max {std.rotation_max:.3e} rad")
    return lines


def cmd_plan(args: argparse.Namespace) -> None:
    """`m3t1r plan`: write the plan CSV (columns by joint name, SI units) and print its summary."""
    outputs = OutputSet(inputs=[p for p in (args.model, args.closures, args.serial) if p and Path(p).exists()])
    output = outputs.add(args.output, "-o")
    outputs.check()
    print("planning ...", file=sys.stderr if output.path is None else sys.stdout, flush=True)
    with Heartbeat("planning", f"choosing {args.n} poses"):  # the selection reports no count
        plan, inputs = _make_plan(args)
    for path in inputs:
        outputs.add_input(path)
    outputs.check()
    summary = _plan_summary(plan, args)
    unit = ", ".join(f"{name} [{u}]" for name, u in zip(plan.columns, plan.column_units))
    comments = provenance(args) + [
        "measurement plan: " + summary[0],
        summary[1],
        *summary[2:],
        f"columns {unit}; one row per pose, in measuring order",
    ]
    with outputs:
        outputs.stage(output, table_text(plan.columns, plan.configurations, comments))
        outputs.commit()
    for line in summary:
        say(outputs, line)
    say(outputs, f"wrote {plan.n_poses} rows to {output.name}")


# ------------------------------------------------------------------------------------------------
# validate


def add_validate_parser(verbs: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `validate` verb to argparse's subparsers object `verbs`, run by `cmd_validate` (`args.run`)."""
    parser = cli_parser.add_validate_parser(verbs)
    parser.set_defaults(run=cmd_validate)
    return parser


def _row_table(result, out: TextIO) -> None:
    """Per-row errors, in the file's length unit."""
    scale = 1.0 / _unit_scale(result.units)
    heading = result.heading is not None
    header = f"{'line':>6}  {'position [' + result.units + ']':>15}"
    if not result.position_only:
        header += f"  {'rotation [rad]':>15}" + (f"  {'heading [rad]':>15}" if heading else "")
    print(header + f"  {'sigmas':>7}", file=out)
    flagged = set(result.flagged)
    for k, row in enumerate(result.rows):
        line = int(result.lines[row])
        text = f"{line:>6}  {result.errors.position[k] * scale:>15.4e}"
        if not result.position_only:
            text += f"  {result.errors.rotation[k]:>15.4e}" + (f"  {result.heading[k]:>+15.4e}" if heading else "")
        print(text + f"  {result.sigmas[k]:>7.2f}" + ("  FLAGGED" if line in flagged else ""), file=out)


def _unit_scale(units: str) -> float:
    return LENGTH_UNITS[units]


def _summary(result, out: TextIO) -> None:
    """Mean, RMS and max of each error, the flag count and the failed rows."""
    scale = 1.0 / _unit_scale(result.units)
    e = result.errors
    print(
        f"{len(result.rows)} of {len(result.lines)} rows predicted; errors:{'':>10}mean{'':>10}RMS{'':>10}max", file=out
    )
    print(
        f"  position [{result.units}]{'':<{12 - len(result.units)}}{e.position_mean * scale:>12.4e}"
        f"{e.position_rms * scale:>13.4e}{e.position_max * scale:>13.4e}",
        file=out,
    )
    if not result.position_only:
        print(
            f"  rotation [rad]{'':<9}{e.rotation_mean:>12.4e}{e.rotation_rms:>13.4e}{e.rotation_max:>13.4e}", file=out
        )
    if result.heading is not None:
        h = np.abs(result.heading)
        print(f"  heading |yaw| [rad]{'':<4}{h.mean():>12.4e}{np.sqrt(np.mean(h**2)):>13.4e}{h.max():>13.4e}", file=out)
    flags = ", ".join(map(str, result.flagged)) or "none"
    print(
        f"rows beyond 5 sigma (chi-square gate on the report's noise model x {result.scale:.3g}, the square root "
        f"of its variance factor): {flags}",
        file=out,
    )
    for line, reason in result.failures:
        print(f"  {result.path}, line {line} not predicted: {reason}", file=out)


def _prediction_rows(result) -> np.ndarray:
    """(N, 3 or 7) rows x, y, z [file unit][, qx, qy, qz, qw] of the predictions."""
    rows = pose_rows([pin.SE3(p) for p in result.predictions])
    rows[:, :3] /= _unit_scale(result.units)
    return rows[:, :3] if result.position_only else rows


def cmd_validate(args: argparse.Namespace) -> None:
    """`m3t1r validate`: per-row errors and summary on stdout; PRED.csv only when every row was predicted;
    the plots of `--plots DIR` with it, as a unit."""
    outputs = OutputSet(inputs=(args.measurements, args.calibrated, paired_closures_path(args.calibrated), args.report))
    output = outputs.add(args.predictions, "--predictions")
    plots = load(DECLARE_VALIDATION_PLOTS)(outputs, args.plots) if args.plots else None  # matplotlib with --plots only
    outputs.check()
    out = sys.stderr if output is not None and output.path is None else sys.stdout
    # Its batch prediction reports rows only at the end: a heartbeat shows it is alive.
    with Heartbeat("validate", args.measurements), warnings.catch_warnings(record=True) as notes:
        warnings.simplefilter("always", ModelWarning)  # the calibrated machine's load notes, printed as notes
        result = validate(args.measurements, args.calibrated, args.report, args.units)
    for note in dict.fromkeys(str(w.message) for w in notes if issubclass(w.category, ModelWarning)):
        print(f"note: {note}", file=sys.stderr)
    _row_table(result, out)
    _summary(result, out)
    if output is None and plots is None:
        return
    with outputs:  # leaving it by an error removes what `check` reserved
        if output is not None and result.failures:
            raise RowFailures(result.path, list(result.failures))
        if output is not None:
            outputs.stage(output, table_text(*_prediction_table(args, result)))
        if plots is not None:
            load(VALIDATION_PLOTS)(result, plots, outputs)
        written = outputs.commit()
    if output is not None:
        print(f"wrote {len(result.lines)} predicted measurements to {output.name}", file=out)
    if plots is not None:
        print(f"wrote {', '.join(name for name in written if output is None or name != output.name)}", file=out)


def _prediction_table(args: argparse.Namespace, result) -> tuple[tuple[str, ...], np.ndarray, list[str]]:
    """Columns, rows and comments of the predictions file."""
    columns = POSE_COLUMNS[:3] if result.position_only else POSE_COLUMNS
    comments = provenance(args) + [
        f"predicted measurements of {args.measurements} by {args.calibrated}, with the measurement frame and "
        f"marker of {args.report}",
        f"position in {result.units}"
        + ("" if result.position_only else ", unit quaternion")
        + ", in the measurement file's frame; one row per input row, same order",
    ]
    return tuple(columns), _prediction_rows(result), comments
