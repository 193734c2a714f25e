# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 04 · Another mechanism: calibrating a planar five-bar from URDF + closures
#
# Nothing in the calibration is specific to the M machine. A mechanism is a URDF of open chains plus a closures
# file that says which frames meet, which joints are actuated, what the machine is commanded to do (its **task**)
# and where it works (its **workspace**). This notebook takes the second packaged example, a planar five-bar
# (`models/five_bar.urdf`, two motors, task: the effector's $x, y$), through the same steps as notebook 03:
# load, kinematics, a simulated tracker campaign, calibration, held-out accuracy against its predicted floor, and
# compensation of commands.

# %%
import tempfile
from pathlib import Path

import numpy as np
from IPython.display import Image, display

from m3t1r.app.plots import plot_pose_errors_before_after, plot_workspace_error_map
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors, predicted_pose_std
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.simulation import PlacementErrorScale, simulate_study
from m3t1r.compensation import compensation_accuracy
from m3t1r.model.description import Mechanism, nominal_model_paths
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import workspace_actuators

np.set_printoptions(precision=4, suppress=True, linewidth=110)
OUT = Path(tempfile.mkdtemp(prefix="m3t1r-notebook-04-"))
print("files written by this notebook go to", OUT)

# %% [markdown]
# ## The description
#
# The closures file declares one 3D closure (the two distal links meet at the effector; rows $x, y$ in the plane),
# the task (`position: [x, y]`, `rotation: none`) and an actuator workspace box. `load` checks it all against the
# URDF; the task's columns name the columns of target files.

# %%
urdf = nominal_model_paths()[0].parent / "five_bar.urdf"
five_bar = Mechanism.load(urdf)
print(five_bar.closures_path.name, "| actuated:", five_bar.actuated_joints, "| task:", five_bar.task)
print("task columns:", five_bar.task.columns, "| workspace:", five_bar.workspace)
print("passive joints solved by the closures:", [five_bar.model.names[int(i) + 1] for i in five_bar.passive_ids])
assert five_bar.task.columns == ("x", "y") and five_bar.notes == ()

# %% [markdown]
# ## Kinematics
#
# Forward kinematics solves the closure rows over the passive joints; inverse kinematics solves the declared task
# (two rows for two motors). Both have batch forms that solve many poses at once.

# %%
solver = ClosedLoopSolver(five_bar)
motors = workspace_actuators(five_bar, 500, np.random.default_rng(0))
forward = solver.forward_batch(motors)
targets = five_bar.task.coordinates(forward.poses)
inverse = solver.inverse_batch(targets)
round_trip = np.abs(inverse.actuators - motors).max()
print(
    f"500 poses: effector x in [{targets[:, 0].min():.3f}, {targets[:, 0].max():.3f}] m, "
    f"y in [{targets[:, 1].min():.3f}, {targets[:, 1].max():.3f}] m; IK(FK(q)) - q: {round_trip:.1e} rad"
)
assert forward.complete and inverse.complete and round_trip < 1e-8

# %% [markdown]
# ## A simulated campaign and its calibration
#
# The truth machine has 0.1 mm / 0.1 mrad errors on every joint origin and on the closure and effector frames. A
# tracker measures the effector frame at 40 poses, with 10 µm / 20 µrad noise; the motor encoders read with 1 µrad
# noise. The fit identifies the base parameters and is judged on 300 held-out poses.

# %%
noise = TrackerNoise(position=1e-5, rotation=2e-5, actuator=1e-6)
study = simulate_study(
    five_bar,
    n_poses=40,
    n_holdout=300,
    seed=1,
    noise=noise,
    errors=PlacementErrorScale(1e-4, 1e-4),
)
calibration = calibrate_closed_loop(five_bar, study.measurements, CalibrationOptions(noise=noise))
before = pose_errors(five_bar, study.truth, study.holdout_actuators)
after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
floor = predicted_pose_std(calibration, study.holdout_actuators)
print(
    f"identified {len(calibration.base.names)} of {calibration.error_model.n_parameters} parameters, "
    f"LM {calibration.lm.termination} after {calibration.lm.iterations} iterations, "
    f"variance factor {calibration.variance_factor:.2f}"
)
print(
    f"held-out position RMS: nominal {before.position_rms * 1e6:.1f} µm -> calibrated {after.position_rms * 1e6:.2f} µm"
    f" (predicted {floor.position_rms * 1e6:.2f} µm)"
)
print(
    f"held-out rotation RMS: nominal {before.rotation_rms * 1e6:.0f} µrad -> calibrated "
    f"{after.rotation_rms * 1e6:.2f} µrad (predicted {floor.rotation_rms * 1e6:.2f} µrad)"
)
assert calibration.lm.converged and 0.5 < calibration.variance_factor < 1.5
assert after.position_rms < 0.05 * before.position_rms
assert 0.5 < after.position_rms / floor.position_rms < 2.0

# %% [markdown]
# ## Compensation
#
# Commanding the truth machine at targets through the nominal model misses by the geometric errors; through the
# calibrated model (its inverse kinematics, then the nominal forward kinematics a controller knows), by what the
# calibration left.

# %%
grid = five_bar.task.coordinates(
    solver.forward_batch(workspace_actuators(five_bar, 200, np.random.default_rng(2))).poses
)
accuracy = compensation_accuracy(five_bar, calibration.mechanism, study.truth, grid)
print(
    f"effector error at 200 targets: nominal commands {accuracy.before.position_rms * 1e6:.1f} µm RMS, "
    f"compensated {accuracy.after.position_rms * 1e6:.2f} µm RMS"
)
assert not accuracy.failures and accuracy.after.position_rms < 0.05 * accuracy.before.position_rms

# %% [markdown]
# ## The result, drawn
#
# The held-out poses, nominal model against calibrated model, pose by pose (log scale: the calibration takes the
# effector error down by more than an order of magnitude everywhere); then the 200 compensation targets over the
# plane of the task, commanded through the nominal model and through the calibrated one.

# %%
figure = plot_pose_errors_before_after(
    before,
    after,
    OUT / "04_holdout_before_after.png",
    title="Five-bar, 300 held-out poses: effector error vs the actual machine",
)
display(Image(filename=str(figure), width=640))
error_map = plot_workspace_error_map(
    grid[accuracy.indices],
    accuracy.before.position,
    accuracy.after.position,
    OUT / "04_compensation_map.png",
    title="Five-bar: effector error at the targets, without and with compensation",
)
display(Image(filename=str(error_map), width=640))
assert figure.stat().st_size > 15_000 and error_map.stat().st_size > 15_000

# %% [markdown]
# ## Saving the calibrated machine
#
# The calibrated machine is a URDF + closures pair, like the nominal one; it reloads with the same task.

# %%
saved = OUT / "five_bar_calibrated.urdf"
calibration.mechanism.save(saved)
reloaded = Mechanism.load(saved)
difference = np.abs(
    ClosedLoopSolver(reloaded).forward_batch(motors[:50]).poses
    - ClosedLoopSolver(calibration.mechanism).forward_batch(motors[:50]).poses
).max()
print(f"wrote {saved.name} and {saved.with_suffix('').name}.closures.yaml; reloaded poses differ by {difference:.1e}")
assert reloaded.task == five_bar.task and difference < 1e-9
