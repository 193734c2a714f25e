"""`make demo`: the main job on the embedded default, no input needed.

Simulate an actual machine (1 mm / 1 mrad errors on every joint origin and frame), measure it
with a noisy tracker, calibrate from slider readings and poses, compensate commands over the
workspace, print the before/after tables and write every artifact into one folder.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import __version__
from ._threads import on_one_blas_thread
from .calibration import TrackerNoise, calibrate_closed_loop, pose_errors
from .datasets import write_measurements
from .description import Mechanism
from .errors import PoorExcitationWarning
from .design import NOMINAL
from .io import atomic_write_text
from .kinematics import ClosedLoopSolver

__all__ = ["DemoSettings", "run_demo"]


@dataclass(frozen=True)
class DemoSettings:
    """What the demo simulates: truth errors [m, rad], tracker noise, pose counts, seed."""

    sigma_position: float = 1e-3
    sigma_rotation: float = 1e-3
    noise: TrackerNoise = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)
    n_poses: int = 50
    n_holdout: int = 200
    n_targets: int = 250
    seed: int = 0


class _Progress:
    def __init__(self, steps: int, say: Callable[[str], None]) -> None:
        self.steps, self.step, self.say, self.start = steps, 0, say, time.perf_counter()

    def __call__(self, what: str) -> None:
        self.step += 1
        self.say(f"[{self.step}/{self.steps}] {what} ({time.perf_counter() - self.start:.1f} s)")


def _row(label: str, position: np.ndarray, rotation: np.ndarray) -> str:
    return (f"  {label:<34}{np.mean(position) * 1e6:>12.1f}{np.max(position) * 1e6:>11.1f}"
            f"{np.mean(rotation) * 1e6:>13.1f}{np.max(rotation) * 1e6:>11.1f}")


_HEADER = f"  {'':<34}{'pos mean':>12}{'pos max':>11}{'rot mean':>13}{'rot max':>11}\n  {'':<34}{'[um]':>12}{'[um]':>11}{'[urad]':>13}{'[urad]':>11}"


@on_one_blas_thread
def run_demo(out_dir: Path, settings: DemoSettings = DemoSettings(), say: Callable[[str], None] = print) -> dict:
    """Run the whole job; return the summary written to out_dir/summary.json."""
    from .compensation import compensation_accuracy
    from .simulation import simulate_study

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    progress = _Progress(7, say)
    nominal = Mechanism.load()

    progress("kinematics of the nominal machine")
    solver = ClosedLoopSolver(nominal)
    say(f"  {'x':>7}{'y':>8}{'z':>8}{'theta':>8}  ->  sliders {', '.join(nominal.actuated_joints)} [m]"
        f"  ->  FK error [m]")
    for target in ([0.5, 0.525, -0.111, 0.0], [0.42, 0.3, -0.2, -0.6], [0.58, 0.8, -0.02, 0.7]):
        ik = solver.inverse(target, q_init=nominal.home)
        fk = solver.forward(ik.actuators, q_init=nominal.home)
        error = np.linalg.norm(fk.pose.translation - np.array(target[:3]))
        say(f"  {target[0]:7.3f}{target[1]:8.3f}{target[2]:8.3f}{target[3]:8.2f}  ->  "
            + " ".join(f"{v:+.4f}" for v in ik.actuators) + f"  ->  {error:.1e}")
    say(f"  mobility at home: {solver.mobility(nominal.home)} (closure Jacobian rank {nominal.model.nv - solver.mobility(nominal.home)})")

    progress(f"simulating an actual machine ({settings.sigma_position * 1e3:g} mm / {settings.sigma_rotation * 1e3:g} mrad "
             f"on every joint origin and frame) and {settings.n_poses} noisy measurements")
    study = simulate_study(nominal, settings.n_poses, settings.n_holdout, settings.seed, settings.sigma_position,
                           settings.sigma_rotation, settings.noise)
    write_measurements(out_dir / "measurements.csv", nominal, study.measurements,
                       comments=[f"m3t1r {__version__} demo, seed {settings.seed}"])
    study.truth.save(out_dir / "truth.urdf", out_dir / "truth.closures.yaml")

    progress("calibrating from slider readings and tracker poses (closed loop, implicit differentiation)")
    start = time.perf_counter()
    calibration = calibrate_closed_loop(nominal, study.measurements, settings.noise)
    seconds = time.perf_counter() - start
    calibration.mechanism.save(out_dir / "calibrated.urdf", out_dir / "calibrated.closures.yaml")
    say(f"  {calibration.base.rank} of {len(calibration.parameters)} parameters identifiable, "
        f"{calibration.lm.iterations} iterations, {seconds:.2f} s")

    progress(f"checking on {settings.n_holdout} held-out poses and compensating {settings.n_targets} targets")
    train = study.measurements.actuators
    before_train = pose_errors(nominal, study.truth, train)
    after_train = pose_errors(calibration.mechanism, study.truth, train)
    before_held = pose_errors(nominal, study.truth, study.holdout_actuators)
    after_held = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    targets = NOMINAL.workspace.sample(np.random.default_rng(settings.seed + 1), settings.n_targets)
    accuracy = compensation_accuracy(nominal, calibration.mechanism, study.truth, targets)

    progress("results")
    say("  platform error of the model vs the actual machine, at the same slider readings:")
    say(_HEADER)
    say(_row(f"calibration poses, nominal model", before_train.position, before_train.rotation))
    say(_row(f"calibration poses, calibrated", after_train.position, after_train.rotation))
    say(_row(f"held-out poses, nominal model", before_held.position, before_held.rotation))
    say(_row(f"held-out poses, calibrated", after_held.position, after_held.rotation))
    say(f"  achieved pose error when commanding {accuracy.n_targets} targets on the actual machine (yaw only for rotation):")
    say(_HEADER)
    say(_row("targets, nominal commands", accuracy.before.position, accuracy.before.yaw))
    say(_row("targets, compensated commands", accuracy.after.position, accuracy.after.yaw))
    if accuracy.failures:
        say(f"  {len(accuracy.failures)} target(s) out of reach, reported not clipped: "
            + "; ".join(f"#{f.index}: {f.reason}" for f in accuracy.failures[:3]))

    progress("writing the report, plots and the meshcat page")
    artifacts = _write_artifacts(out_dir, settings, nominal, calibration, study, before_held, after_held, accuracy, targets, say)
    summary = {
        "version": __version__, "settings": {"sigma_position_m": settings.sigma_position,
                                             "sigma_rotation_rad": settings.sigma_rotation, "n_poses": settings.n_poses,
                                             "n_holdout": settings.n_holdout, "n_targets": settings.n_targets,
                                             "seed": settings.seed},
        "identifiable": calibration.base.rank, "calibration_seconds": seconds,
        "held_out_position_mean_m": {"nominal": before_held.position_mean, "calibrated": after_held.position_mean},
        "held_out_rotation_mean_rad": {"nominal": before_held.rotation_mean, "calibrated": after_held.rotation_mean},
        "compensated_position_mean_m": {"nominal_commands": accuracy.before.position_mean,
                                        "compensated": accuracy.after.position_mean},
        "compensated_yaw_mean_rad": {"nominal_commands": accuracy.before.yaw_mean,
                                     "compensated": accuracy.after.yaw_mean},
        "artifacts": [str(p) for p in artifacts],
    }
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    progress("done")
    say(f"  artifacts in {out_dir}/:")
    for path in sorted({*artifacts, out_dir / "summary.json", out_dir / "measurements.csv", out_dir / "truth.urdf",
                        out_dir / "calibrated.urdf", out_dir / "calibrated.closures.yaml"}):
        say(f"    {path.name}")
    return summary


def _write_artifacts(out_dir: Path, settings: DemoSettings, nominal: Mechanism, calibration, study, held_before,
                     held_after, accuracy, targets: np.ndarray, say: Callable[[str], None]) -> list[Path]:
    from .calibration import PoseMeasurements, predicted_pose_std
    from .cli import _calibration_report
    from .datasets import MeasurementFile, sha256_of
    from .plots import (plot_error_vs_poses, plot_pose_errors_before_after, plot_predicted_std_map,
                        plot_workspace_error_map)
    from .viz import comparison_views, write_static_html

    artifacts = []
    reached = targets[np.asarray(accuracy.indices, dtype=int)]  # rows of the accuracy arrays
    data = MeasurementFile(out_dir / "measurements.csv", study.measurements, (), np.zeros((0, 0)),
                           np.arange(len(study.measurements)), sha256_of(out_dir / "measurements.csv"))
    report = _calibration_report(calibration, data, nominal, settings.noise)
    atomic_write_text(out_dir / "report.json", json.dumps(report, indent=2) + "\n")
    artifacts.append(out_dir / "report.json")
    artifacts.append(plot_pose_errors_before_after(held_before, held_after, out_dir / "pose_errors_before_after.png",
                                                   title="Held-out poses: platform error vs the actual machine"))
    sizes, position, rotation = [], [], []
    for k in (15, 25, 35, settings.n_poses):
        m = study.measurements
        subset = PoseMeasurements(m.actuators[:k], m.poses[:k], m.position_only)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PoorExcitationWarning)
            fitted = calibration if k == settings.n_poses else calibrate_closed_loop(nominal, subset, settings.noise)
        errors = pose_errors(fitted.mechanism, study.truth, study.holdout_actuators)
        sizes.append(k)
        position.append(errors.position_mean)
        rotation.append(errors.rotation_mean)
        note = f"  (poorly excited: condition number {fitted.base.condition_number:.2g})" if caught else ""
        say(f"  {k:3d} poses: held-out error {errors.position_mean * 1e6:7.1f} um, "
            f"{errors.rotation_mean * 1e6:7.1f} urad{note}")
    artifacts.append(plot_error_vs_poses(sizes, position, rotation, out_dir / "error_vs_poses.png",
                                         title="Held-out error vs number of calibration poses"))
    artifacts.append(plot_workspace_error_map(reached, accuracy.before.position,
                                              accuracy.after.position, out_dir / "compensation_error_map.png",
                                              title="Achieved position error over the workspace"))
    std = predicted_pose_std(calibration, accuracy.actuators_after)
    artifacts.append(plot_predicted_std_map(reached, std, out_dir / "predicted_error_map.png",
                                            title="Predicted position error after compensation (1 sigma)"))
    artifacts.append(write_static_html(comparison_views(nominal, calibration.mechanism), out_dir / "scene.html",
                                       pose=(0.5, 0.6, -0.1, 0.3), markers=study.measurements.poses))
    return artifacts


