"""`make demo`: a whole tracker campaign on a simulated machine, through the real commands.

The actual machine has 1 mm / 1 mrad errors on every joint origin and frame. A laser tracker
stands 3 m away, turned 120 degrees, exports millimetres, and sees a reflector 70 mm off the
platform frame (its CAD position 0.4 mm off); two of its readings are gross errors. The demo runs
what a user runs: `m3t1r plan`, the measurements, `m3t1r calibrate --frame estimate`,
`m3t1r validate` on a fresh set, `m3t1r compensate`, and then, since this machine is simulated,
checks the calibrated model and the compensated commands against the truth.
"""

from __future__ import annotations

import contextlib
import io
import json
import shlex
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pinocchio as pin

from m3t1r._threads import on_one_blas_thread
from m3t1r._version import __version__
from m3t1r.app.datasets import read_actuators, write_measurements
from m3t1r.app.scene import comparison_views
from m3t1r.app.static_page import write_static_html
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurement_setup import MeasurementSetup, register_frame
from m3t1r.calibration.measurements import TrackerNoise, assembled_from_home, measure
from m3t1r.calibration.simulation import actual_machine, random_placement_errors, with_outliers
from m3t1r.compensation import workspace_targets
from m3t1r.errors import M3t1rError
from m3t1r.io.outputs import atomic_write_text
from m3t1r.io.poses import POSE_COLUMNS, pose_rows
from m3t1r.io.strict_json import json_text
from m3t1r.io.tables import write_table
from m3t1r.metrics import pose_errors_between
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import workspace_actuators

__all__ = ["DemoSettings", "run_demo"]

Command = Callable[[Sequence[str]], int]


@dataclass(frozen=True)
class DemoSettings:
    """What the demo simulates: truth errors [m, rad], tracker noise and setup, pose counts, seed."""

    sigma_position: float = 1e-3
    sigma_rotation: float = 1e-3
    noise: TrackerNoise = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)
    tracker_frame: tuple[float, ...] = (3.0, -1.2, 0.4, 0.0, 0.0, 2.1)  # x, y, z [m], roll, pitch, yaw [rad]
    marker: tuple[float, float, float] = (0.07, -0.02, 0.03)  # the reflector in the platform frame [m]
    marker_cad_error: tuple[float, float, float] = (0.3e-3, -0.2e-3, 0.2e-3)  # what the CAD gets wrong [m]
    n_poses: int = 60
    n_outliers: int = 2
    n_validation: int = 100
    n_holdout: int = 200
    n_targets: int = 250
    seed: int = 0


class _Steps:
    def __init__(self, steps: int, say: Callable[[str], None]) -> None:
        self.steps, self.step, self.say, self.start = steps, 0, say, time.perf_counter()

    def __call__(self, what: str) -> None:
        self.step += 1
        self.say(f"[{self.step}/{self.steps}] {what} ({time.perf_counter() - self.start:.1f} s)")


def _row(label: str, position: np.ndarray, rotation: np.ndarray) -> str:
    return (
        f"  {label:<36}{np.mean(position) * 1e6:>10.1f}{np.max(position) * 1e6:>10.1f}"
        f"{np.mean(rotation) * 1e6:>11.1f}{np.max(rotation) * 1e6:>10.1f}"
    )


_HEADER = (
    f"  {'':<36}{'pos mean':>10}{'pos max':>10}{'rot mean':>11}{'rot max':>10}\n"
    f"  {'':<36}{'[um]':>10}{'[um]':>10}{'[urad]':>11}{'[urad]':>10}"
)


def _run(
    command: Command,
    arguments: list[str],
    out_dir: Path,
    say: Callable[[str], None],
    keep: Callable[[str], bool] = lambda line: True,
) -> None:
    """Run one `m3t1r` command as a user would, show it and the lines `keep` selects; the whole
    output goes to out_dir/<verb>.log. A failing step stops the demo."""
    shown = ["m3t1r"] + [a if not a.startswith(str(out_dir)) else Path(a).name for a in arguments]
    say("  $ " + shlex.join(shown))
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(buffer):
        status = command(["-q", *arguments])
    text = buffer.getvalue().replace(str(out_dir) + "/", "")
    atomic_write_text(out_dir / f"{arguments[0]}.log", text)
    for line in text.splitlines():
        if keep(line):
            say("    " + line)
    if status != 0:
        raise M3t1rError(f"demo step `{shlex.join(shown)}` failed with status {status}")


@on_one_blas_thread
def run_demo(
    out_dir: Path, command: Command, settings: DemoSettings = DemoSettings(), say: Callable[[str], None] = print
) -> dict:
    """Run the campaign; `command` runs one `m3t1r` command line (the CLI's `main`).
    Returns the summary written to out_dir/summary.json."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    step = _Steps(7, say)
    nominal = Mechanism.load()
    rng = np.random.default_rng(settings.seed)
    setup = MeasurementSetup.from_numbers(settings.tracker_frame, settings.marker)
    file = lambda name: str(out_dir / name)  # noqa: E731

    step(f"planning {settings.n_poses} measurement poses (D-optimal, ordered for short travel)")
    _run(
        command,
        ["plan", "-n", str(settings.n_poses), "--seed", str(settings.seed), "-o", file("plan.csv")],
        out_dir,
        say,
    )

    step(
        f"measuring an actual machine ({settings.sigma_position * 1e3:g} mm / {settings.sigma_rotation * 1e3:g} mrad "
        "errors) with a tracker 3 m away, in mm, through a 70 mm reflector, with two gross errors"
    )
    error_model = ClosedLoopErrorModel(nominal)
    truth = actual_machine(
        nominal,
        random_placement_errors(error_model, rng, settings.sigma_position, settings.sigma_rotation),
        error_model,
    )
    planned, _ = read_actuators(out_dir / "plan.csv", nominal)
    campaign, spoiled = with_outliers(
        measure(truth, planned, rng, settings.noise, setup=setup), rng, settings.n_outliers
    )
    fresh = measure(truth, workspace_actuators(nominal, settings.n_validation, rng), rng, settings.noise, setup=setup)
    comments = [f"m3t1r {__version__} demo: simulated tracker, lengths in mm"]
    write_measurements(out_dir / "measurements.csv", nominal, campaign, comments=comments, units="mm")
    write_measurements(out_dir / "validation.csv", nominal, fresh, comments=comments, units="mm")
    truth.save(out_dir / "truth.urdf", out_dir / "truth.closures.yaml")
    say(
        f"  wrote measurements.csv ({len(campaign)} poses; gross errors on data rows "
        f"{', '.join(str(i + 1) for i in spoiled)}, i.e. file lines {', '.join(str(i + 3) for i in spoiled)}) "
        f"and validation.csv ({len(fresh)} fresh poses)"
    )

    step("calibrating: machine, tracker frame and reflector together; outliers flagged; the fit judged")
    cad_marker = np.array(settings.marker) + np.array(settings.marker_cad_error)
    _run(
        command,
        [
            "calibrate",
            file("measurements.csv"),
            "-o",
            file("calibrated.urdf"),
            "--report",
            file("report.json"),
            "--frame",
            "estimate",
            "--marker",
            *(f"{v:g}" for v in cad_marker),
            "--units",
            "mm",
            "--plots",
            file("plots"),
        ],
        out_dir,
        say,
        keep=lambda line: not line.startswith("wrote") or "urdf" in line,
    )

    step(f"validating on {settings.n_validation} fresh measurements")
    _run(
        command,
        [
            "validate",
            file("validation.csv"),
            "--calibrated",
            file("calibrated.urdf"),
            "--report",
            file("report.json"),
            "--predictions",
            file("predictions.csv"),
            "--plots",
            file("validation_plots"),
        ],
        out_dir,
        say,
        keep=lambda line: not (line[:1] == " " and line.split()[0].isdigit()) and not line.lstrip().startswith("line "),
    )

    step(f"compensating {settings.n_targets} targets given in the tracker's frame")
    calibrated = Mechanism.load(out_dir / "calibrated.urdf")
    estimated = MeasurementSetup.from_report(json.loads((out_dir / "report.json").read_text()))
    targets = _tracker_targets(calibrated, estimated, settings)
    write_table(
        out_dir / "targets.csv",
        POSE_COLUMNS,
        pose_rows(targets),
        ["where the tracker should see the reflector: x, y, z [m] and orientation, in the tracker's frame"],
    )
    _run(
        command,
        [
            "compensate",
            file("targets.csv"),
            "--calibrated",
            file("calibrated.urdf"),
            "--report",
            file("report.json"),
            "--output-kind",
            "actuators",
            "-o",
            file("commands.csv"),
        ],
        out_dir,
        say,
    )

    step("checking against the truth (possible only in simulation)")
    commands, _ = read_actuators(out_dir / "commands.csv", nominal)
    summary = _truth_check(nominal, calibrated, estimated, truth, setup, targets, commands, rng, settings, say)
    write_static_html(comparison_views(nominal, calibrated), out_dir / "scene.html", pose=(0.5, 0.6, -0.1, 0.3))
    report = json.loads((out_dir / "report.json").read_text())
    summary.update(
        {
            "version": __version__,
            "seed": settings.seed,
            "outlier_lines_flagged": report["outliers"],
            "outlier_lines_true": [i + 3 for i in spoiled],
            "cross_validation_position_mean_m": report["cross_validation"]["position_mean_m"],
        }
    )
    atomic_write_text(out_dir / "summary.json", json_text(summary))

    step("done")
    say(f"  artifacts in {out_dir}/: " + ", ".join(sorted(p.name for p in out_dir.iterdir())))
    return summary


def _tracker_targets(calibrated: Mechanism, estimated: MeasurementSetup, settings: DemoSettings) -> list[pin.SE3]:
    """Workspace targets as a user with a tracker writes them: where the tracker should see the
    reflector (pose in the tracker's frame); drawn as platform poses of the calibrated machine."""
    platform = workspace_targets(settings.n_targets, np.random.default_rng(settings.seed + 1))
    poses = np.array(
        [pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, theta), np.array([x, y, z])).homogeneous for x, y, z, theta in platform]
    )
    return [pin.SE3(pose) for pose in estimated.measured_poses(poses)]


def _truth_check(
    nominal: Mechanism,
    calibrated: Mechanism,
    estimated: MeasurementSetup,
    truth: Mechanism,
    setup: MeasurementSetup,
    targets: list[pin.SE3],
    commands: np.ndarray,
    rng: np.random.Generator,
    settings: DemoSettings,
    say: Callable[[str], None],
) -> dict:
    """What the tracker would see, predicted by each model, against the truth: at held-out slider
    sets, and when the truth is driven with nominal and with compensated commands to the targets.

    Everything is compared where the tracker sees it (the reflector in the tracker's frame): the
    robot's base and the platform frame's origin are gauges that a tracker cannot observe. The
    nominal model is given the best it can have without calibration: the frame registered to the
    calibration data and the CAD reflector.
    """
    holdout = workspace_actuators(nominal, settings.n_holdout, rng)
    seen = setup.measured_poses(_platform_poses(truth, holdout))
    cad = MeasurementSetup.from_numbers(marker_xyz=np.add(settings.marker, settings.marker_cad_error))
    registered = replace(
        cad, frame=register_frame(cad.measured_poses(_platform_poses(nominal, holdout)), seen[:, :3, 3])
    )
    say(
        "  the reflector as the tracker sees it vs the models' prediction, "
        f"at {settings.n_holdout} held-out slider sets:"
    )
    say(_HEADER)
    summary = {}
    for name, model, model_setup in (
        ("nominal model", nominal, registered),
        ("calibrated model", calibrated, estimated),
    ):
        errors = pose_errors_between(model_setup.measured_poses(_platform_poses(model, holdout)), seen)
        say(_row(name, errors.position, errors.rotation))
        summary[name] = {"position_mean_m": errors.position_mean, "rotation_mean_rad": errors.rotation_mean}
    nominal_commands = np.array(
        [
            ClosedLoopSolver(nominal).inverse(registered.frame.actInv(t) * cad.marker.inverse()).actuators
            for t in targets
        ]
    )
    say(
        f"  where the tracker sees the reflector when the machine is commanded to {len(targets)} targets "
        "(rotation: heading):"
    )
    say(_HEADER)
    for name, sliders in (("nominal commands", nominal_commands), ("compensated commands", commands)):
        reached = setup.measured_poses(_platform_poses(truth, sliders))
        position = np.linalg.norm(reached[:, :3, 3] - np.array([t.translation for t in targets]), axis=1)
        heading = _heading(estimated, reached) - _heading(estimated, np.array([t.homogeneous for t in targets]))
        say(_row(name, position, heading))
        heading = np.abs(np.angle(np.exp(1j * heading)))
        summary[name] = {"position_mean_m": float(position.mean()), "heading_mean_rad": float(heading.mean())}
    return summary


def _heading(setup: MeasurementSetup, measured: np.ndarray) -> np.ndarray:
    """Platform heading [rad] implied by measured frames (N, 4, 4) in the tracker's frame, under a
    setup's conventions: yaw of frame^-1 . T . marker^-1 (what the IK commands; tilt is not)."""
    platform = setup.frame.inverse().homogeneous @ measured @ setup.marker.inverse().homogeneous
    return np.arctan2(platform[:, 1, 0], platform[:, 0, 0])


def _platform_poses(machine: Mechanism, actuators: np.ndarray) -> np.ndarray:
    return np.array(assembled_from_home(machine, actuators).poses)
