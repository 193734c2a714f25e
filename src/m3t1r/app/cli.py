"""The `m3t1r` command line: kinematics, simulation, calibration, compensation, viewing, demo.

Every verb reads validated files, computes, and only then writes its outputs atomically; it never
writes onto an input or the nominal model. Errors print `m3t1r: error: ...` naming the file, line,
column or joint at fault, and exit with status 2 (1 when some rows failed, or a fit was refused as
not supported by the data, and nothing was written).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import pinocchio as pin

from m3t1r._threads import single_blas_thread
from m3t1r._version import __version__
from m3t1r.app.cli_calibrate import add_campaign_options, parse_priors, run_closed_loop_calibration
from m3t1r.app.cli_campaign import add_plan_parser, add_validate_parser
from m3t1r.app.cli_common import (
    RowFailures,
    count_number,
    finite_number,
    load_mechanism,
    nonnegative_number,
    positive_number,
    progress_bar,
    provenance,
    say,
    seed_number,
    zero_or_count,
)
from m3t1r.app.cli_serial import run_serial_calibration
from m3t1r.app.datasets import TARGET_COLUMNS, measurement_table, read_actuators, read_measurements, read_targets
from m3t1r.app.demo import run_demo
from m3t1r.app.live_viewer import open_viewer
from m3t1r.app.reporting import IDLE_CHAIN_JOINTS
from m3t1r.app.scene import comparison_views
from m3t1r.app.static_page import build_scene, scene_html
from m3t1r.calibration.assessment import FitRejected
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.simulation import simulate_study
from m3t1r.calibration.validation import read_report
from m3t1r.compensation import Compensator, compensate, joint_limit_violation
from m3t1r.errors import InvalidInputError, KinematicsError, M3t1rError
from m3t1r.io.outputs import OutputSet
from m3t1r.io.poses import POSE_COLUMNS, pose_rows
from m3t1r.io.progress import set_quiet
from m3t1r.io.signals import Terminated, termination_as_exception
from m3t1r.io.tables import table_text
from m3t1r.model.kinematics import ClosedLoopSolver, require_square_task, yaw_of
from m3t1r.model.workspace import workspace_actuators
from m3t1r.paper.closed_chain import closed_chain_study
from m3t1r.paper.study import paper_study

EXIT_ERROR, EXIT_ROWS_FAILED = 2, 1
_FARTHEST_TARGET = 100.0  # [m] a target farther from the base is in another unit, not a place to reach


# ------------------------------------------------------------------------------------------------
def cmd_fk(args: argparse.Namespace) -> None:
    """`m3t1r fk`: platform poses of slider sets."""

    mechanism = load_mechanism(args.model, args.closures)
    outputs = OutputSet(inputs=(args.actuators, mechanism.urdf_path, mechanism.closures_path))
    output = outputs.add(args.output, "-o")
    outputs.check()
    actuators, lines = read_actuators(args.actuators, mechanism)
    with progress_bar("fk", 1) as progress:  # one vectorised solve, every row from home
        batch = ClosedLoopSolver(mechanism).forward_batch(actuators)
        progress.advance()
    if batch.failures:
        raise RowFailures(Path(args.actuators), [(int(lines[f.index]), f.reason) for f in batch.failures])
    poses = [pin.SE3(pose) for pose in batch.poses]
    comments = provenance(args) + ["platform frame pose in the base frame: m, unit quaternion"]
    with outputs:
        outputs.stage(output, table_text(POSE_COLUMNS, pose_rows(poses), comments))
        outputs.commit()
    say(outputs, f"wrote {len(poses)} poses to {output.name}")


def cmd_ik(args: argparse.Namespace) -> None:
    """`m3t1r ik`: slider sets of platform poses."""
    mechanism = load_mechanism(args.model, args.closures)
    outputs = OutputSet(inputs=(args.poses, mechanism.urdf_path, mechanism.closures_path))
    output = outputs.add(args.output, "-o")
    outputs.check()
    targets, lines = read_targets(args.poses, mechanism.task)
    solver = ClosedLoopSolver(mechanism)
    solver.check_square_task()
    if not isinstance(targets, np.ndarray):
        targets = mechanism.task.coordinates(np.array([pose.homogeneous for pose in targets]))
    with progress_bar("ik", 1) as progress:  # one vectorised solve, every row from home
        batch = solver.inverse_batch(targets)
        progress.advance()
    failures = [(int(lines[f.index]), f.reason) for f in batch.failures]
    for k, q in zip(batch.indices, batch.q):
        violation = joint_limit_violation(mechanism.model, q)
        if violation is not None:
            failures.append((int(lines[k]), violation))
    if failures:
        raise RowFailures(Path(args.poses), sorted(failures))
    rows = batch.actuators
    max_tilt = float(np.abs(batch.tilt).max(initial=0.0))
    with outputs:
        outputs.stage(output, table_text(mechanism.actuated_joints, np.array(rows),
                                         provenance(args) + ["actuator positions in m or rad"]))
        outputs.commit()
    tilt = "" if mechanism.task.rotation == "full" else f"; largest uncommandable tilt (roll/pitch) {max_tilt:.3g} rad"
    say(outputs, f"wrote {len(rows)} actuator sets to {output.name}{tilt}")


def cmd_simulate(args: argparse.Namespace) -> None:
    """`m3t1r simulate`: a perturbed machine and noisy measurements of it."""
    nominal = load_mechanism(args.model, args.closures)
    outputs = OutputSet(inputs=(nominal.urdf_path, nominal.closures_path))
    measurement_output = outputs.add(args.output, "-o")
    truth_output = outputs.add_machine(args.truth_urdf, "--truth-urdf")
    outputs.check()
    noise = None if args.noise_free else TrackerNoise(args.noise_pos, args.noise_rot, args.noise_act)
    passive = IDLE_CHAIN_JOINTS if args.with_passive else ()
    setup = MeasurementSetup.from_numbers(args.tracker_frame, args.marker)
    study = simulate_study(nominal, args.n, 0, args.seed, args.sigma_pos, args.sigma_rot, noise, args.position_only,
                           passive_joints=passive, setup=setup, outliers=args.outliers)
    comments = provenance(args) + [
        f"truth: {args.sigma_pos:g} m / {args.sigma_rot:g} rad errors on every joint placement and closure/platform frame, seed {args.seed}",
        "noise: none" if noise is None else f"noise: tracker {noise.position:g} m / {noise.rotation:g} rad, sliders {noise.actuator:g} m",
        f"lengths in {args.units}; measured: tracker frame . platform . marker",
    ]
    if study.outliers:
        comments.append(f"gross outliers (3-5 mm) on data rows {', '.join(str(i + 1) for i in study.outliers)}")
    columns, rows = measurement_table(nominal, study.measurements, passive, study.passive_readings, args.units)
    with outputs:
        outputs.stage(measurement_output, table_text(columns, rows, comments))
        if truth_output is not None:
            outputs.stage_machine(truth_output, study.truth)
        outputs.commit()
    say(outputs, f"wrote {args.n} {'position-only ' if args.position_only else ''}measurements to "
                  f"{measurement_output.name}")
    if truth_output is not None:
        say(outputs, f"wrote the truth machine to {truth_output.name} and {truth_output.closures.name}")


def cmd_calibrate(args: argparse.Namespace) -> None:
    """`m3t1r calibrate`: closed-loop or serial calibration from a measurement file."""
    args.prior = parse_priors(args.prior)
    if args.serial:
        return run_serial_calibration(args)
    run_closed_loop_calibration(args, load_mechanism(args.model, args.closures))


def cmd_compensate(args: argparse.Namespace) -> None:
    """`m3t1r compensate`: corrected slider commands for target poses."""
    nominal = load_mechanism(args.model, args.closures)
    calibrated = load_mechanism(args.calibrated, args.calibrated_closures)
    outputs = OutputSet(inputs=(args.targets, nominal.urdf_path, nominal.closures_path, calibrated.urdf_path,
                                calibrated.closures_path, args.report))
    output = outputs.add(args.output, "-o")
    outputs.check()
    targets, lines = read_targets(args.targets, calibrated.task)
    require_square_task(calibrated)
    if args.report:
        targets = _targets_in_base(targets, args.report, args.targets, calibrated)
    if args.unordered:  # every target from home, vectorised: no path order to follow
        result = Compensator(nominal, calibrated).compensate_batch(targets)
    else:
        with progress_bar("compensate", len(lines)) as progress:
            result = compensate(nominal, calibrated, targets, progress=progress.update)
    if result.failures:
        raise RowFailures(Path(args.targets), [(int(lines[f.index]), f.reason) for f in result.failures])
    comments = provenance(args) + [f"calibrated model: {calibrated.urdf_path}"]
    pose_note = "poses to send to a controller that knows only the nominal model (T_cp)"
    if args.output_kind == "actuators":
        text = table_text(calibrated.actuated_joints, result.actuators, comments + ["corrected actuator commands [m or rad]"])
    elif isinstance(targets, np.ndarray):
        text = table_text(calibrated.task.columns, result.command_targets, comments + [pose_note])
    else:
        text = table_text(POSE_COLUMNS, result.command_pose_rows, comments + [pose_note])
    with outputs:
        outputs.stage(output, text)
        outputs.commit()
    tilt = ("" if calibrated.task.rotation == "full" else
            f"; largest uncommandable tilt (roll/pitch) of the calibrated machine {result.max_tilt:.3g} rad")
    say(outputs, f"wrote {result.n_targets} compensated {args.output_kind} commands to {output.name}{tilt}")


def _targets_in_base(targets, report_path: str, targets_path: str, calibrated) -> np.ndarray:
    """Targets of the measured point (the reflector) in a calibration's measurement frame, to
    platform targets (x, y, z, theta) in the calibrated base.

    The measured point is commanded in position and heading (its yaw in the base, the platform's
    plus the marker's); the platform's roll and pitch are not commandable, so the platform
    position that puts the point on target depends on the tilt the machine takes there:
    p_platform = p_target - R_platform(q) m, solved by fixed point with the calibrated IK
    (the tilt varies slowly: 2-4 rounds to 1e-10 m).
    """
    if isinstance(targets, np.ndarray):
        raise InvalidInputError(f"{targets_path}: with --report the targets are poses of the measured frame in the "
                                "measurement frame, and need x,y,z,qx,qy,qz,qw")
    if calibrated.task.columns != TARGET_COLUMNS or calibrated.task.frame != calibrated.platform_frame:
        raise InvalidInputError(f"{targets_path}: targets of the measured point (--report) need a task commanding "
                                "x, y, z and yaw of the platform frame (the M machine's); give task-frame targets")
    setup = read_report(report_path).setup
    far = max(float(np.linalg.norm(setup.frame.actInv(target).translation)) for target in targets)
    if far > _FARTHEST_TARGET:
        raise InvalidInputError(f"{targets_path}: a target {far:.3g} m from the machine's base; target files are in "
                                "metres, whatever unit the calibration's measurements were in: these look like "
                                "millimetres (divide x, y, z by 1000)")
    solver, offset = ClosedLoopSolver(calibrated), setup.marker.translation
    rows = []
    for target in targets:
        in_base = setup.frame.actInv(target)
        row = np.r_[(in_base * setup.marker.inverse()).translation, yaw_of((in_base * setup.marker.inverse()).rotation)]
        for _ in range(10):
            try:
                platform = solver.forward(solver.inverse(row).actuators).pose
            except KinematicsError:
                break  # compensate reports this target's failure itself
            miss = platform.act(offset) - in_base.translation
            row[:3] -= miss
            if np.linalg.norm(miss) < 1e-10:
                break
        rows.append(row)
    return np.array(rows)


def cmd_view(args: argparse.Namespace) -> None:
    """`m3t1r view`: the nominal and calibrated machines in meshcat."""
    nominal = load_mechanism(args.nominal, args.closures)
    calibrated = load_mechanism(args.calibrated, args.calibrated_closures) if args.calibrated else None
    outputs = OutputSet(inputs=(nominal.urdf_path, nominal.closures_path, args.measurements,
                                *((calibrated.urdf_path, calibrated.closures_path) if calibrated else ())))
    output = outputs.add(args.html, "--html")
    outputs.check()
    views = comparison_views(nominal, calibrated)
    markers = None
    if args.measurements:
        markers = read_measurements(args.measurements, nominal).measurements.poses
    if output is not None:
        with outputs:
            outputs.stage(output, scene_html(build_scene(views, pose=args.pose, markers=markers)))
            outputs.commit()
        say(outputs, f"wrote {output.name} (self-contained: open it in any browser, no network needed)")
        return
    with open_viewer(views, pose=args.pose, markers=markers) as viewer:
        print(f"meshcat viewer at {viewer.url} (Ctrl-C to stop)", flush=True)
        viewer.wait()


def cmd_demo(args: argparse.Namespace) -> None:
    """`m3t1r demo`: the end-to-end simulated calibration."""
    run_demo(Path(args.out), main)


def cmd_paper(args: argparse.Namespace) -> None:
    """`m3t1r paper`: the paper's simulation study, or its method on the closed chain."""
    if args.closed and args.passive_from is not None:
        raise InvalidInputError("--closed runs every variant (passive joints read, sliders alone, closed loop); "
                                "--passive-from applies to the two-chain study only")
    passive_from = args.passive_from or "sensor"
    noise = TrackerNoise() if args.noise else None
    label = "with noise (tracker 10 um / 20 urad, encoders 10 urad)" if args.noise else "noise-free"

    def row(name, errors) -> str:
        return (f"{name:<46}{errors.position_mean:>14.3e}{errors.position.max():>14.3e}"
                f"{errors.rotation_mean:>16.3e}{errors.rotation.max():>15.3e}")

    header = f"{'':<46}{'pos mean [m]':>14}{'pos max [m]':>14}{'rot mean [rad]':>16}{'rot max [rad]':>15}"
    if args.closed:
        print(f"the paper's two-chain method on the closed-chain machine, seed {args.seed}, {label}:", flush=True)
        result = closed_chain_study(args.seed, noise=noise)
        print(header)
        print(row("nominal model", result.nominal))
        print(row("chain B1, every passive joint read: before", result.sensors_before))
        print(row("chain B1, every passive joint read: after", result.sensors_after))
        print(row("chain B3 fitted to P_I: after", result.second_chain_after))
        print(row("chain B1 from the sliders alone", result.sliders_only))
        if result.closed_loop is not None:
            print(row("closed-loop calibration (m3t1r.calibration)", result.closed_loop))
        return
    print(f"the paper's simulation study (two serial chains, Table-1-like dt, ds, dq), seed {args.seed}, "
          f"lower cranks from {passive_from}, {label}:", flush=True)
    result = paper_study(args.seed, noise=noise, passive_from=passive_from)
    ident = result.identifiability
    print(f"identifiable: {ident.rank_per_chain} per chain, {ident.rank_stacked} stacked "
          f"(the paper's bound for the whole machine: {ident.paper_bound})")
    if result.failure:
        print(f"identification failed: {result.failure}")
    print(header)
    for chain, errors in result.holdout_poses.items():
        print(row(f"held-out poses, chain {chain}: before", errors.before))
        if errors.after is not None:
            print(row(f"held-out poses, chain {chain}: after", errors.after))


def cmd_evaluate(args: argparse.Namespace) -> None:
    """`m3t1r evaluate`: nominal and calibrated machines against a (simulated) truth."""
    import pinocchio as pin


    nominal = load_mechanism(args.nominal, args.nominal_closures)
    truth = load_mechanism(args.truth, None)
    calibrated = load_mechanism(args.calibrated, None)
    sliders = workspace_actuators(nominal, args.n, np.random.default_rng(args.seed))
    machines = {"truth": truth, "nominal": nominal, "calibrated": calibrated}
    solvers = {name: ClosedLoopSolver(machine) for name, machine in machines.items()}
    errors: dict[str, list[tuple[float, float]]] = {"nominal": [], "calibrated": []}
    failures: list[tuple[int, str]] = []
    # One slider set that does not assemble on some machine is reported and skipped, not fatal.
    with progress_bar("evaluate", len(sliders)) as progress:
        for index, values in enumerate(sliders):
            progress.advance()
            poses = {}
            for name, solver in solvers.items():
                try:
                    poses[name] = solver.forward(values).pose
                except (KinematicsError, InvalidInputError) as exc:
                    failures.append((index, f"{name} machine: {exc}"))
                    solver.reset()
                    break
            else:
                for name in errors:
                    a, b = poses[name], poses["truth"]
                    errors[name].append((float(np.linalg.norm(a.translation - b.translation)),
                                         float(np.linalg.norm(pin.log3(a.rotation.T @ b.rotation)))))
    for index, reason in failures:
        print(f"m3t1r: slider set {index} ({', '.join(f'{v:.6g}' for v in sliders[index])} m) skipped: {reason}",
              file=sys.stderr)
    kept = args.n - len(failures)
    if kept == 0:
        raise InvalidInputError(f"none of the {args.n} slider sets assembles on every machine: nothing to evaluate")
    skipped = f", {len(failures)} skipped (see stderr)" if failures else ""
    print(f"held-out platform error over {kept} slider sets in the workspace (seed {args.seed}{skipped}):")
    print(f"{'model':<12}{'position mean':>16}{'position max':>16}{'orientation mean':>19}{'orientation max':>18}")
    for name, values in errors.items():
        e = np.array(values)
        print(f"{name:<12}{e[:, 0].mean():>14.3e} m{e[:, 0].max():>14.3e} m"
              f"{e[:, 1].mean():>15.3e} rad{e[:, 1].max():>14.3e} rad")


# ------------------------------------------------------------------------------------------------
def _add_model_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", metavar="URDF", help="machine URDF (default: the packaged nominal model)")
    parser.add_argument("--closures", metavar="YAML", help="its closures file (default: URDF stem + .closures.yaml)")


def _add_noise_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--noise-pos", type=positive_number, default=10e-6, metavar="M", help="tracker position noise [m]")
    parser.add_argument("--noise-rot", type=positive_number, default=20e-6, metavar="RAD", help="tracker rotation noise [rad]")
    parser.add_argument("--noise-act", type=nonnegative_number, default=1e-6, metavar="M", help="slider reading noise [m]")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every verb."""
    parser = argparse.ArgumentParser(prog="m3t1r", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"m3t1r {__version__}")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")

    p = verbs.add_parser("fk", help="forward kinematics: slider sets -> platform poses")
    p.add_argument("actuators", help="CSV with one column per actuated joint [m]")
    p.add_argument("-o", "--output", required=True, help="poses CSV (x,y,z,qx,qy,qz,qw)")
    _add_model_options(p)
    p.set_defaults(run=cmd_fk)

    p = verbs.add_parser("ik", help="inverse kinematics: task-frame poses -> actuator sets (the closures file's task)")
    p.add_argument("poses", help="CSV with the task's columns (M machine: x,y,z,theta) or x,y,z,qx,qy,qz,qw")
    p.add_argument("-o", "--output", required=True, help="slider CSV (columns named by actuated joint)")
    _add_model_options(p)
    p.set_defaults(run=cmd_ik)

    p = verbs.add_parser("simulate", help="simulate an actual machine and its calibration measurements")
    p.add_argument("-n", type=count_number, default=20, help="number of poses (default 20)")
    p.add_argument("--seed", type=seed_number, default=0)
    p.add_argument("--sigma-pos", type=nonnegative_number, default=1e-3, metavar="M", help="placement error std, translation [m]")
    p.add_argument("--sigma-rot", type=nonnegative_number, default=1e-3, metavar="RAD", help="placement error std, rotation [rad]")
    _add_noise_options(p)
    p.add_argument("--noise-free", action="store_true", help="exact measurements")
    p.add_argument("--position-only", action="store_true", help="a tracker without orientation")
    p.add_argument("--tracker-frame", nargs=6, type=finite_number, metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                   help="the robot base in the tracker's frame [m, rad] (default: measured in the base frame)")
    p.add_argument("--marker", nargs=3, type=finite_number, metavar=("X", "Y", "Z"),
                   help="the reflector in the platform frame [m] (default: the platform frame's origin)")
    p.add_argument("--units", choices=("m", "mm"), default="m", help="length unit of the written file")
    p.add_argument("--outliers", type=zero_or_count, default=0, metavar="K", help="spoil K measurements with 3-5 mm gross errors")
    p.add_argument("--with-passive", action="store_true",
                   help="also record encoders on the idle chains' hinges (q12_B2, q22_B4) for cross-validation")
    p.add_argument("-o", "--output", required=True, help="measurement CSV")
    p.add_argument("--truth-urdf", metavar="URDF", help="also write the actual machine (and its closures file)")
    _add_model_options(p)
    p.set_defaults(run=cmd_simulate)

    p = verbs.add_parser("calibrate", help="identify the geometry from measurements; write a calibrated URDF")
    p.add_argument("measurements", help="measurement CSV (sliders by joint name, x,y,z[,qx,qy,qz,qw])")
    p.add_argument("-o", "--output", required=True, help="calibrated URDF (a .closures.yaml is written beside it)")
    p.add_argument("--report", metavar="JSON", help="identified parameters, std, rank, RMS, input sha256")
    p.add_argument("--plots", metavar="DIR", help="write error plots (PNG) into DIR")
    p.add_argument("--serial", metavar="ROBOT_OR_URDF", help="calibrate a serial chain instead (ur5, ur10, panda or a URDF)")
    p.add_argument("--base", metavar="FRAME", help="with --serial: base frame (default the model root)")
    p.add_argument("--tool", metavar="FRAME", help="with --serial: the measured tool frame")
    p.add_argument("--compliance", action="store_true",
                   help="with --serial: joint compliance under gravity as candidate parameters")
    add_campaign_options(p)
    _add_noise_options(p)
    _add_model_options(p)
    p.set_defaults(run=cmd_calibrate)

    p = verbs.add_parser("compensate", help="corrected commands for targets, from a calibrated model (paper sec. 7)")
    p.add_argument("targets", help="CSV with the task's columns (M machine: x,y,z,theta) or x,y,z,qx,qy,qz,qw")
    p.add_argument("--calibrated", required=True, metavar="URDF", help="calibrated URDF")
    p.add_argument("--calibrated-closures", metavar="YAML", help="its closures (default: beside the URDF)")
    p.add_argument("--report", metavar="JSON", help="targets are poses of the measured frame (the marker) in this "
                                                    "calibration's measurement frame (the tracker's), not the base's")
    p.add_argument("--output-kind", choices=("pose", "actuators"), default="pose",
                   help="pose: T_cp for a controller with the nominal model; actuators: slider commands")
    p.add_argument("--unordered", action="store_true",
                   help="the targets are not a path (a grid, a map, unrelated poses): solve each from home, "
                        "all at once, instead of warm-starting from the previous target")
    p.add_argument("-o", "--output", required=True, help="commands CSV")
    _add_model_options(p)
    p.set_defaults(run=cmd_compensate)

    p = verbs.add_parser("view", help="meshcat scene of the nominal and calibrated machines")
    p.add_argument("--nominal", metavar="URDF", help="nominal URDF (default: packaged)")
    p.add_argument("--closures", metavar="YAML", help="nominal closures")
    p.add_argument("--calibrated", metavar="URDF")
    p.add_argument("--calibrated-closures", metavar="YAML")
    p.add_argument("--pose", nargs="+", type=finite_number, metavar="VALUE",
                   help="command both machines to these task coordinates (the task's columns; M machine: "
                        "x y z theta [m, m, m, rad]; default: home)")
    p.add_argument("--measurements", metavar="CSV", help="show measured platform positions as markers")
    p.add_argument("--html", metavar="PATH", help="write a self-contained static page instead of serving")
    p.set_defaults(run=cmd_view)

    p = verbs.add_parser("demo", help="the main job: a simulated tracker campaign, plan to compensation (no input needed)")
    p.add_argument("--out", default="demo_out", help="artifact folder (default demo_out)")
    p.set_defaults(run=cmd_demo)

    p = verbs.add_parser("paper", help="the paper's two-chain method: its simulation study, or on the closed chain")
    p.add_argument("--seed", type=seed_number, default=3)
    p.add_argument("--noise", action="store_true", help="tracker, encoder and slider noise")
    p.add_argument("--passive-from", choices=("sensor", "distance", "platform", "sliders"), default=None,
                   help="lower cranks q13, q23: read (default), the paper's recursion (eq. 30), or a closure solve; "
                        "not with --closed")
    p.add_argument("--closed", action="store_true", help="run the method on the full closed-chain machine instead")
    p.set_defaults(run=cmd_paper)

    p = verbs.add_parser("evaluate", help="compare nominal and calibrated machines against a (simulated) truth")
    p.add_argument("--truth", required=True, metavar="URDF")
    p.add_argument("--calibrated", required=True, metavar="URDF")
    p.add_argument("--nominal", metavar="URDF")
    p.add_argument("--nominal-closures", metavar="YAML")
    p.add_argument("-n", type=count_number, default=200)
    p.add_argument("--seed", type=seed_number, default=1)
    p.set_defaults(run=cmd_evaluate)

    add_plan_parser(verbs)
    add_validate_parser(verbs)
    # --quiet before or after the verb; the verb's copy must not reset the global one.
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress display on stderr")
    for sub in verbs.choices.values():
        sub.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                         help="no progress display on stderr")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)
    set_quiet(getattr(args, "quiet", False))
    try:
        # SIGTERM/SIGHUP unwind like Ctrl-C, so every OutputSet removes its temporary files.
        with termination_as_exception(), single_blas_thread():
            args.run(args)
    except (RowFailures, FitRejected) as exc:
        print(f"m3t1r: error: {exc}", file=sys.stderr)
        return EXIT_ROWS_FAILED
    except (M3t1rError, OSError) as exc:
        print(f"m3t1r: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("m3t1r: interrupted; outputs not yet in place were not written", file=sys.stderr)
        return 130
    except Terminated as exc:
        print(f"m3t1r: {exc}; outputs not yet in place were not written", file=sys.stderr)
        return 128 + exc.signum
    finally:
        set_quiet(False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
