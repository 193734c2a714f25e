"""Calibration plots from measurements alone (`m3t1r calibrate --plots DIR`), and the plots of a
validation (`m3t1r validate --plots DIR`, `write_validation_plots`).

Without a known truth, each plot uses what the data can show honestly:
- per-pose error before/after (paper Fig. 4): the model's platform pose against the measured one
  at the calibration poses (a fit residual, not an accuracy), the outliers the fit left out circled
  and named;
- error vs number of poses: cross-validation: calibrate on the first k of a shuffled pose set and
  measure the error on poses kept out of every fit;
- workspace map: the standard deviation of what the tracker would measure, in its frame, predicted
  from the covariance of every fitted parameter (the setup's included): the expected error of a
  pose commanded in that frame after compensation (`predicted_measurement_std`).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from m3t1r.app.cli_common import check_plots_folder
from m3t1r.app.passive_joints import PassiveJointResiduals, passive_joint_residuals
from m3t1r.app.plots import (
    PlotFile,
    plot_error_vs_poses,
    plot_errors_over_workspace,
    plot_normalised_qq,
    plot_pose_errors_before_after,
    plot_predicted_std_map,
    plot_validation_histogram,
)
from m3t1r.calibration.closed_loop import ClosedLoopCalibration, calibrate_closed_loop, predicted_measurement_std
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise, assembled_from_home
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.errors import IdentificationError, InvalidInputError, KinematicsError, PoorExcitationWarning
from m3t1r.io.outputs import OutputSet
from m3t1r.metrics import PoseErrors, rotation_angles
from m3t1r.model.description import Mechanism
from m3t1r.model.design import IDLE_CHAIN_JOINTS
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import declared_workspace

if TYPE_CHECKING:
    from m3t1r.calibration.validation import Validation

__all__ = [
    "measured_pose_errors",
    "cross_validation_curve",
    "write_calibration_plots",
    "check_plots_folder",
    "declare_plot_outputs",
    "PLOT_NAMES",
    "VALIDATION_PLOT_NAMES",
    "declare_validation_plot_outputs",
    "write_validation_plots",
    "row_labels",
    "PassiveJointResiduals",
    "passive_joint_residuals",
    "IDLE_CHAIN_JOINTS",
]
# check_plots_folder, the passive-joint residuals and IDLE_CHAIN_JOINTS live in modules without
# matplotlib (`calibrate` imports this module only for --plots); they are named here too, as before.


def measured_pose_errors(
    machine: Mechanism, measurements: PoseMeasurements, setup: MeasurementSetup = MeasurementSetup()
) -> PoseErrors:
    """Model prediction (setup.frame . platform . setup.marker) vs measured pose at the measured
    sliders: position norm [m], rotation angle [rad] (NaN rotation for position-only data)."""
    predicted = setup.measured_poses(assembled_from_home(machine, measurements.actuators).poses)
    measured = np.array([pose.homogeneous for pose in measurements.poses]).reshape(-1, 4, 4)
    position = np.linalg.norm(predicted[:, :3, 3] - measured[:, :3, 3], axis=1)
    rotation = (
        np.full(len(position), np.nan)
        if measurements.position_only
        else rotation_angles(measured[:, :3, :3], predicted[:, :3, :3])
    )
    return PoseErrors(position, rotation)


def _subset(measurements: PoseMeasurements, indices: np.ndarray) -> PoseMeasurements:
    return PoseMeasurements(
        measurements.actuators[indices], tuple(measurements.poses[i] for i in indices), measurements.position_only
    )


def cross_validation_curve(
    nominal: Mechanism,
    measurements: PoseMeasurements,
    options: CalibrationOptions,
    seed: int = 0,
    test_fraction: float = 0.2,
) -> tuple[list[int], list[float], list[float]]:
    """(training sizes, mean position error [m], mean rotation error [rad]) on held-back poses.

    options go to `calibrate_closed_loop` (the noise, the measurement setup to estimate). Sizes too
    small to identify every parameter are skipped (calibrate_closed_loop refuses them).
    """
    order = np.random.default_rng(seed).permutation(len(measurements))
    n_test = max(5, int(round(test_fraction * len(measurements))))
    test, train = order[:n_test], order[n_test:]
    sizes = sorted({int(k) for k in np.linspace(min(15, len(train)), len(train), 4)})
    kept, position, rotation = [], [], []
    for k in sizes:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PoorExcitationWarning)  # small subsets are poor by design
                fitted = calibrate_closed_loop(nominal, _subset(measurements, train[:k]), options)
        except (IdentificationError, KinematicsError):
            continue
        errors = measured_pose_errors(fitted.mechanism, _subset(measurements, test), fitted.setup)
        kept.append(k)
        position.append(errors.position_mean)
        rotation.append(float(np.nanmean(errors.rotation)) if not measurements.position_only else float("nan"))
    return kept, position, rotation


#: The files `write_calibration_plots` writes into its folder.
PLOT_NAMES = ("pose_errors_before_after.png", "error_vs_poses.png", "predicted_error_map.png")


def declare_plot_outputs(outputs: OutputSet, folder: str | Path) -> Path:
    """Declare the calibration plots in `folder` as outputs of `outputs` (`--plots DIR`), so that
    they are checked with the set's other outputs before any work (collisions, writability, other
    writers) and written with them or not at all; a missing folder is created by the set's check.
    Returns the folder."""
    folder = check_plots_folder(folder)
    for name in PLOT_NAMES:
        outputs.add(folder / name, "--plots", create_folder=True)
    return folder


def write_calibration_plots(
    nominal: Mechanism,
    calibration: ClosedLoopCalibration,
    out_dir: Path,
    protect: Iterable[Path] = (),
    noise: TrackerNoise = TrackerNoise(),
    seed: int = 0,
    outputs: OutputSet | None = None,
    labels: Sequence[str] | None = None,
) -> list[Path]:
    """Write the calibration plots (module docstring) into out_dir as a unit; return their paths.

    The calibration's own inlier measurements and measurement setup are used throughout, but for
    the per-pose plot, which shows its outliers too, named by `labels` (one per pose the calibration
    was given, e.g. "line 12"; default the pose number). With
    `outputs` (where `declare_plot_outputs(outputs, out_dir)` declared them) the plots are only
    staged there, to be committed with the set's other outputs. A plot the data cannot give (the
    error-vs-poses curve when no subset can be calibrated) is withdrawn and not written.
    """
    own = outputs is None
    if outputs is None:
        outputs = OutputSet(inputs=protect)
        declare_plot_outputs(outputs, out_dir)
    with outputs:
        if own:
            outputs.check()
        written = _stage_calibration_plots(nominal, calibration, Path(out_dir), noise, seed, outputs, labels)
        for path in [Path(out_dir) / name for name in PLOT_NAMES]:
            if not outputs.output(path).staged:
                outputs.drop(path)
        written = [path for path in written if path in (o.path for o in outputs.outputs)]
        if own:
            outputs.commit()
    return written


def _stage_calibration_plots(
    nominal: Mechanism,
    calibration: ClosedLoopCalibration,
    out_dir: Path,
    noise: TrackerNoise,
    seed: int,
    outputs: OutputSet,
    labels: Sequence[str] | None,
) -> list[Path]:
    problem, start = calibration.problem, calibration.start
    if problem is None or start is None:
        raise InvalidInputError("write_calibration_plots needs a calibration made by calibrate_closed_loop")
    measurements = _subset(problem.measurements, np.flatnonzero(problem.active))
    written = [
        plot_pose_errors_before_after(
            measured_pose_errors(nominal, problem.measurements, start.setup),
            measured_pose_errors(calibration.mechanism, problem.measurements, calibration.setup),
            PlotFile(out_dir / PLOT_NAMES[0], outputs=outputs),
            title="Calibration poses: model vs measured pose",
            outliers=np.flatnonzero(~problem.active),
            labels=labels,
        )
    ]
    options = CalibrationOptions(
        noise=noise,
        setup=MeasurementSetup(marker=start.setup.marker),
        estimate_frame=problem.frame_slot is not None,
        estimate_marker=problem.marker_slot is not None,
    )
    sizes, position, rotation = cross_validation_curve(nominal, measurements, options, seed)
    if sizes:
        written.append(
            plot_error_vs_poses(
                sizes,
                position,
                None if measurements.position_only else rotation,
                PlotFile(out_dir / PLOT_NAMES[1], outputs=outputs),
                title="Cross-validated error vs number of calibration poses",
            )
        )
    sliders, where, plane = map_poses(calibration.mechanism, 300, np.random.default_rng(seed))
    # What the tracker would measure, in its own frame, with the setup's uncertainty: with an estimated
    # frame the platform's place in the machine's base is not observable (`predicted_measurement_std`),
    # so a map of the platform in the base would show the gauge, not the accuracy of a command.
    std = predicted_measurement_std(calibration, sliders)
    plain = (
        calibration.setup.frame.isIdentity()
        and calibration.setup.marker.isIdentity()
        and problem.frame_slot is None
        and problem.marker_slot is None
    )
    title = (
        "Predicted error after compensation (1 sigma)"
        if plain
        else "Predicted error of the measured point in the measurement frame (1 sigma),\n"
        "for poses commanded in that frame after calibration"
    )
    written.append(
        plot_predicted_std_map(
            where,
            std,
            PlotFile(out_dir / PLOT_NAMES[2], outputs=outputs),
            title=title,
            plane=plane,
        )
    )
    return written


def map_poses(
    mechanism: Mechanism, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, tuple[str, str]]:
    """Slider sets (M, k) drawn in the mechanism's declared workspace box (task or actuators) that
    assemble from home, their place in a plane (M, 2) and the plane's axis labels: the task frame's
    first two box coordinates (M machine and five-bar: x, y [m]; an orientation task: roll, pitch
    [rad]). Draws that do not assemble (a box corner beyond a calibrated machine's reach) are left out."""
    workspace, solver, task = declared_workspace(mechanism), ClosedLoopSolver(mechanism), mechanism.task
    if workspace.kind == "task":
        batch = solver.inverse_batch(workspace.task_poses(task, rng, count))
    else:
        lower, upper = workspace.bounds(mechanism.actuated_joints)
        batch = solver.forward_batch(lower + (upper - lower) * rng.random((count, len(lower))))
    sliders = batch.q[:, mechanism.actuated_ids]
    if len(task.box_keys) < 2:  # a one-coordinate task: the platform's x-y instead
        return sliders, batch.poses[:, :2, 3], ("platform x [m]", "platform y [m]")
    where = task.box_coordinates(batch.task_poses)[:, :2]
    units = ["m" if key in task.position else "rad" for key in task.box_keys[:2]]
    return (
        sliders,
        where,
        (f"{task.frame} {task.box_keys[0]} [{units[0]}]", f"{task.frame} {task.box_keys[1]} [{units[1]}]"),
    )


#: The files `write_validation_plots` writes into its folder.
VALIDATION_PLOT_NAMES = ("error_histogram.png", "normalised_errors_qq.png", "errors_over_workspace.png")


def declare_validation_plot_outputs(outputs: OutputSet, folder: str | Path) -> Path:
    """Declare the validation plots in `folder` as outputs of `outputs` (`validate --plots DIR`),
    checked with the set's other outputs before any work and written with them; returns the folder."""
    folder = check_plots_folder(folder)
    for name in VALIDATION_PLOT_NAMES:
        outputs.add(folder / name, "--plots", create_folder=True)
    return folder


def row_labels(result: Validation) -> list[str]:
    """How each predicted row is named on the plots: by its `source` in the instrument's file when the
    measurement file has that column (`m3t1r convert` writes it), with its line in the file."""
    lines = result.lines[result.rows]
    if result.sources is None:
        return [f"line {int(line)}" for line in lines]
    return [f"source {source:g} (line {int(line)})" for source, line in zip(result.sources[result.rows], lines)]


def write_validation_plots(result: Validation, out_dir: Path, outputs: OutputSet) -> list[Path]:
    """Stage the validation plots in `outputs` (where `declare_validation_plot_outputs` declared them):
    the error histograms against the noise model, the normal QQ plot of the normalised residuals and
    the errors over the measured positions, the rows beyond the gate named by `row_labels`."""
    if result.residuals is None or result.noise is None:
        raise InvalidInputError("write_validation_plots needs a validation made by `validate`")
    flagged = np.isin(result.lines[result.rows], result.flagged)
    labels = row_labels(result)
    predicted = f"{len(result.rows)} of {len(result.lines)} rows of {result.path.name}"
    folder = Path(out_dir)
    rotation = None if result.position_only else result.errors.rotation
    return [
        plot_validation_histogram(
            result.errors.position,
            rotation,
            result.noise,
            result.scale,
            flagged,
            labels,
            PlotFile(folder / VALIDATION_PLOT_NAMES[0], outputs=outputs),
            title=f"Prediction errors of the calibrated model\n{predicted}",
        ),
        plot_normalised_qq(
            result.residuals,
            result.scale,
            flagged,
            labels,
            PlotFile(folder / VALIDATION_PLOT_NAMES[1], outputs=outputs),
            title=f"Residuals over the report's noise model\n{predicted}",
        ),
        plot_errors_over_workspace(
            result.measured[result.rows, :3, 3],
            result.errors.position,
            flagged,
            labels,
            PlotFile(folder / VALIDATION_PLOT_NAMES[2], outputs=outputs),
        ),
    ]
