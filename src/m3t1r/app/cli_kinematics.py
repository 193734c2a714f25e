"""The kinematics verbs: `m3t1r fk`, `m3t1r ik`, `m3t1r compensate` and `m3t1r evaluate`.

`m3t1r.app.cli` imports this module only to run one of them (Pinocchio, SciPy's linear algebra and
the kinematics stack, no calibration plots, no viewer).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin

from m3t1r.app.cli_common import RowFailures, load_mechanism, pose_table_text, progress_bar, provenance, say
from m3t1r.app.datasets import read_actuators, read_targets
from m3t1r.calibration.serial_compensation import compensate_serial
from m3t1r.calibration.serial_robots import load_example_robot, load_serial_urdf, serial_chain_of
from m3t1r.calibration.validation import CalibrationReport, read_report
from m3t1r.compensation import Compensator, compensate, joint_limit_violation
from m3t1r.errors import InvalidInputError, KinematicsError
from m3t1r.io.outputs import OutputSet
from m3t1r.io.poses import POSE_COLUMNS, pose_rows
from m3t1r.io.progress import Heartbeat
from m3t1r.io.tables import read_table, table_text
from m3t1r.model.kinematics import ClosedLoopSolver, require_square_task
from m3t1r.model.poe import SerialChain, tool_poses
from m3t1r.model.workspace import workspace_actuators

__all__ = ["cmd_fk", "cmd_ik", "cmd_compensate", "cmd_evaluate"]

_FARTHEST_TARGET = 100.0  # [m] a target farther from the base is in another unit, not a place to reach


def cmd_fk(args: argparse.Namespace) -> None:
    """`m3t1r fk`: platform poses of slider sets."""

    mechanism = load_mechanism(args.model, args.closures)
    outputs = OutputSet(inputs=(args.actuators, mechanism.urdf_path, mechanism.closures_path))
    output = outputs.add(args.output, "-o")
    outputs.check()
    with Heartbeat("reading", args.actuators):
        actuators, lines = read_actuators(args.actuators, mechanism)
    comments = provenance(args) + ["platform frame pose in the base frame: m, unit quaternion"]
    text = pose_table_text(ClosedLoopSolver(mechanism), actuators, lines, Path(args.actuators), comments)
    with outputs:
        outputs.stage(output, text)
        outputs.commit()
    say(outputs, f"wrote {len(actuators)} poses to {output.name}")


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
        outputs.stage(
            output,
            table_text(
                mechanism.actuated_joints, np.array(rows), provenance(args) + ["actuator positions in m or rad"]
            ),
        )
        outputs.commit()
    # Roll and pitch are the uncommanded rotation of a yaw task only; a task without rotation has no tilt to speak of.
    tilt = "" if mechanism.task.rotation != "yaw" else f"; largest uncommandable tilt (roll/pitch) {max_tilt:.3g} rad"
    say(outputs, f"wrote {len(rows)} actuator sets to {output.name}{tilt}")


def cmd_compensate(args: argparse.Namespace) -> None:
    """`m3t1r compensate`: corrected slider commands for target poses (a serial calibration's report:
    corrected joint commands of a joint program)."""
    if args.report:
        report = read_report(args.report)
        if report.kind == "serial":
            _compensate_serial(args, report)
            return
    nominal = load_mechanism(args.model, args.closures)
    calibrated = load_mechanism(args.calibrated, args.calibrated_closures)
    outputs = OutputSet(
        inputs=(
            args.targets,
            nominal.urdf_path,
            nominal.closures_path,
            calibrated.urdf_path,
            calibrated.closures_path,
            args.report,
        )
    )
    output = outputs.add(args.output, "-o")
    outputs.check()
    targets, lines = read_targets(args.targets, calibrated.task)
    require_square_task(calibrated)
    if args.report:
        targets = _targets_in_base(targets, args.report, args.targets, calibrated)
    if args.unordered:  # every target from home, vectorised: no path order to follow
        with Heartbeat("compensate", f"{len(lines)} targets"):
            result = Compensator(nominal, calibrated).compensate_batch(targets)
    else:
        with progress_bar("compensate", len(lines)) as progress:
            result = compensate(nominal, calibrated, targets, progress=progress.update)
    if result.failures:
        raise RowFailures(Path(args.targets), [(int(lines[f.index]), f.reason) for f in result.failures])
    comments = provenance(args) + [f"calibrated model: {calibrated.urdf_path}"]
    pose_note = "poses to send to a controller that knows only the nominal model (T_cp)"
    if args.output_kind == "actuators":
        text = table_text(
            calibrated.actuated_joints, result.actuators, comments + ["corrected actuator commands [m or rad]"]
        )
    elif isinstance(targets, np.ndarray):
        text = table_text(calibrated.task.columns, result.command_targets, comments + [pose_note])
    else:
        text = table_text(POSE_COLUMNS, result.command_pose_rows(), comments + [pose_note])
    with outputs:
        outputs.stage(output, text)
        outputs.commit()
    tilt = (
        ""
        if calibrated.task.rotation != "yaw"
        else f"; largest uncommandable tilt (roll/pitch) of the calibrated machine {result.max_tilt:.3g} rad"
    )
    say(outputs, f"wrote {result.n_targets} compensated {args.output_kind} commands to {output.name}{tilt}")


def _serial_robot(source: str | None, report: CalibrationReport) -> tuple[pin.Model, SerialChain]:
    """The nominal serial robot of `compensate` (--model, else the report's) and its report chain."""
    if source is None:
        raise InvalidInputError(f"{report.path}: the report names no nominal robot; give its URDF with --model")
    path = Path(source)
    if path.is_file():
        model, urdf = load_serial_urdf(path)
        return model, serial_chain_of(model, urdf, path, report.tool or "", report.base)
    if path.suffix.lower() == ".urdf" or path.exists():
        raise InvalidInputError(
            f"nominal robot {source} ({'the report' if source == report.robot else '--model'}): "
            "no such URDF file; give the nominal URDF with --model"
        )
    model = load_example_robot(source)  # an unknown name is refused with the known ones
    return model, SerialChain.from_model(model, report.tool or "", report.base)


def _compensate_serial(args: argparse.Namespace, report: CalibrationReport) -> None:
    """`m3t1r compensate --report SERIAL.json`: the joint program (columns by joint name) compensated
    with the calibrated geometry and the report's compliance (`serial_compensation`)."""
    if args.closures or args.calibrated_closures:
        raise InvalidInputError(
            "--closures/--calibrated-closures describe a closed-loop machine; a serial "
            f"calibration ({report.path}) has none"
        )
    source = args.model or report.robot
    inputs = (args.targets, args.calibrated, args.report, source)
    outputs = OutputSet(inputs=[p for p in inputs if p and Path(p).exists()])
    output = outputs.add(args.output, "-o")
    outputs.check()
    nominal, chain = _serial_robot(source, report)
    calibrated, urdf = load_serial_urdf(Path(args.calibrated))
    if (
        serial_chain_of(calibrated, urdf, Path(args.calibrated), chain.tool_frame, chain.base_frame).joint_names
        != chain.joint_names
        or chain.joint_names != report.chain
    ):
        raise InvalidInputError(
            f"{args.calibrated}: its chain from {report.base} to {report.tool} is not the report's {list(report.chain)}"
        )
    constants = report.constant_joints  # joints the calibration's file did not log (--joint NAME=VALUE)
    table = read_table(
        args.targets,
        required=tuple(n for n in chain.joint_names if n not in constants),
        optional=(*constants, *POSE_COLUMNS),
    )
    program = np.column_stack(
        [table.column(n) if table.has_column(n) else np.full(table.n_rows, constants[n]) for n in chain.joint_names]
    )
    with Heartbeat("compensate", f"{len(program)} configurations"):
        result = compensate_serial(nominal, calibrated, chain, program, report.compliance, report.position_only)
    if result.failures:
        raise RowFailures(Path(args.targets), [(int(table.line_numbers[i]), reason) for i, reason in result.failures])
    comments = provenance(args) + [
        f"calibrated model: {args.calibrated}, compliance of {args.report}: "
        + (", ".join(f"{j} {c:.3g}" for j, c in report.compliance.items()) or "none")
    ]
    if args.output_kind == "actuators":
        text = table_text(chain.joint_names, result.commands, comments + ["compensated joint commands [rad or m]"])
    else:
        poses = pose_rows([pin.SE3(g) for g in tool_poses(chain, nominal, result.commands)])
        text = table_text(
            POSE_COLUMNS,
            poses,
            comments
            + [
                f"tool poses ({chain.tool_frame} in the base frame) to send "
                "to a controller that knows only the nominal model"
            ],
        )
    with outputs:
        outputs.stage(output, text)
        outputs.commit()
    say(outputs, f"wrote {len(program)} compensated {args.output_kind} commands to {output.name}")


def _targets_in_base(targets, report_path: str, targets_path: str, calibrated) -> np.ndarray:
    """Targets of the measured point (the reflector) in a calibration's measurement frame, to task
    coordinates of the platform frame in the calibrated base.

    The measured point is commanded in the task's components (its position axes, and its yaw or
    full rotation: the platform's composed with the marker's). Components the task leaves free
    (roll and pitch of a yaw task, every rotation of a position task) are set by the machine, so
    the platform position that puts the point on target depends on the rotation the machine takes
    there: p_platform = p_target - R_platform(q) m, solved by fixed point with the calibrated IK
    (the rotation varies slowly: 2-4 rounds to 1e-10 m).
    """
    if isinstance(targets, np.ndarray):
        raise InvalidInputError(
            f"{targets_path}: with --report the targets are poses of the measured frame in the "
            "measurement frame, and need x,y,z,qx,qy,qz,qw"
        )
    task = calibrated.task
    if task.frame != calibrated.platform_frame:
        raise InvalidInputError(
            f"{targets_path}: targets of the measured point (--report) need the task on the "
            f"measured platform frame '{calibrated.platform_frame}', not on '{task.frame}'; "
            "give task-frame targets"
        )
    setup = read_report(report_path).setup
    far = max(float(np.linalg.norm(setup.frame.actInv(target).translation)) for target in targets)
    if far > _FARTHEST_TARGET:
        raise InvalidInputError(
            f"{targets_path}: a target {far:.3g} m from the machine's base; target files are in "
            "metres, whatever unit the calibration's measurements were in: these look like "
            "millimetres (divide x, y, z by 1000)"
        )
    solver, offset = ClosedLoopSolver(calibrated), setup.marker.translation
    rows = []
    for target in targets:
        in_base = setup.frame.actInv(target)
        row = task.coordinates((in_base * setup.marker.inverse()).homogeneous)[0]
        for _ in range(10):
            try:
                platform = solver.forward(solver.inverse(row).actuators).pose
            except KinematicsError:
                break  # compensate reports this target's failure itself
            miss = platform.act(offset) - in_base.translation
            row[: len(task.position)] -= miss[task.axes]
            if np.linalg.norm(miss[task.axes]) < 1e-10:
                break
        rows.append(row)
    return np.array(rows)


def cmd_evaluate(args: argparse.Namespace) -> None:
    """`m3t1r evaluate`: nominal and calibrated machines against a (simulated) truth."""
    nominal = load_mechanism(args.model, args.closures)
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
                    errors[name].append(
                        (
                            float(np.linalg.norm(a.translation - b.translation)),
                            float(np.linalg.norm(pin.log3(a.rotation.T @ b.rotation))),
                        )
                    )
    for index, reason in failures:
        values = ", ".join(f"{v:.6g} {u}" for v, u in zip(sliders[index], nominal.joint_units()))
        print(f"m3t1r: actuator set {index} ({values}) skipped: {reason}", file=sys.stderr)
    kept = args.n - len(failures)
    if kept == 0:
        raise InvalidInputError(f"none of the {args.n} actuator sets assembles on every machine: nothing to evaluate")
    skipped = f", {len(failures)} skipped (see stderr)" if failures else ""
    print(f"held-out platform error over {kept} actuator sets in the workspace (seed {args.seed}{skipped}):")
    print(f"{'model':<12}{'position mean':>16}{'position max':>16}{'orientation mean':>19}{'orientation max':>18}")
    for name, values in errors.items():
        e = np.array(values)
        print(
            f"{name:<12}{e[:, 0].mean():>14.3e} m{e[:, 0].max():>14.3e} m"
            f"{e[:, 1].mean():>15.3e} rad{e[:, 1].max():>14.3e} rad"
        )
