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
# # 03 · Closed-loop calibration from slider readings and tracker poses, then compensation
#
# The paper's method (notebook 02) needs a sensor on every joint of its two chains. This machine measures only its
# four sliders. Here the calibration uses what such a machine provides: the **slider readings** and the **tracker
# pose** of the platform frame `P_I` at $N$ poses.
#
# **Error model** (`ClosedLoopErrorModel`). A right-multiplied error $T(0) \leftarrow T(0)\exp_6(\delta t)$
# (eq. 33) sits on every joint placement of the tree and on every frame used by a closure or by the measurement. Each
# $\delta t = [v;\ \omega]$ [m, rad] is expressed in the placement's own frame.
#
# **Sensitivity.** With the sliders fixed, the passive joints follow the closures. Implicit differentiation of
# $r_c(q, p) = 0$ gives $\partial q_{passive}/\partial p = -J_{c,passive}^{-1}\,\partial r_c/\partial p$ (a
# 16 × 16 solve). The platform twist is then
# $\partial \xi_P/\partial p = X_P + J_{P,passive}\,\partial q_{passive}/\partial p$ (WORLD). $X_P$ comes from
# Pinocchio's kinematic regressor, the columns of eq. (17).
#
# **Residual** per pose: $e = [p_{model} - p_{meas};\ \log_3(R_{meas}^\top R_{model})]$. Position is in $B$ [m],
# orientation in the platform frame [rad]. It is whitened by the tracker noise and minimised by Levenberg-Marquardt
# over the identifiable ("base") parameters, which a column-pivoted QR selects once at the start.
#
# Then: the held-out accuracy against its predicted floor, the compensation of commands (paper section 7, Fig. 6),
# saving and reloading the calibrated machine, and a meshcat scene.

# %%
import math
import tempfile
import time
import warnings
from collections import Counter
from html import escape
from pathlib import Path

import numpy as np
from IPython.display import HTML, Image, display

from m3t1r.app.plots import plot_pose_errors_before_after
from m3t1r.app.scene import comparison_views
from m3t1r.app.static_page import write_static_html
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors, predicted_pose_std
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.simulation import simulate_study
from m3t1r.compensation import compensate, compensation_accuracy, workspace_targets
from m3t1r.errors import PoorExcitationWarning
from m3t1r.model.description import Mechanism

# Files written by this notebook go to a fresh temporary folder, never into the repository.
OUT = Path(tempfile.mkdtemp(prefix="m3t1r-notebook-03-"))
print(f"files written by this notebook: {OUT}")
np.set_printoptions(precision=4, suppress=True, linewidth=110)

SEED, N_POSES, N_HOLDOUT = 0, 50, 200
mech = Mechanism.load()

HEADER = f"{'':<40}{'pos mean [um]':>14}{'pos max [um]':>13}{'rot mean [urad]':>16}{'rot max [urad]':>15}"


def row(label, position, rotation) -> str:
    return (
        f"{label:<40}{np.mean(position) * 1e6:14.1f}{np.max(position) * 1e6:13.1f}"
        f"{np.mean(rotation) * 1e6:16.1f}{np.max(rotation) * 1e6:15.1f}"
    )


# %% [markdown]
# ## 1. A simulated machine and its measurements
#
# `simulate_study` draws the "actual" machine. It puts errors with $\sigma$ = 1 mm and 1 mrad on every placement,
# then drives it to `N_POSES` slider sets spread over the workspace and records what the instruments would read. The
# tracker gets 10 µm in position and 20 µrad in orientation (right-multiplied), and the slider encoders 1 µm
# (`TrackerNoise()`). `N_HOLDOUT` further slider sets, never used for fitting, judge the result.

# %%
noise = TrackerNoise()
study = simulate_study(mech, n_poses=N_POSES, n_holdout=N_HOLDOUT, seed=SEED, noise=noise)
measurements = study.measurements
print(noise)
print(
    f"{len(measurements)} calibration poses: slider readings {measurements.actuators.shape} [m] and "
    f"{len(measurements.poses)} tracker poses of '{mech.platform_frame}'; "
    f"{len(study.holdout_actuators)} held-out slider sets"
)
print(f"\n{'pose':>4}  {'slider readings [m]':<38}{'measured x, y, z [m]':<30}{'yaw [rad]':>10}")
for k in range(4):
    g = measurements.poses[k]
    print(
        f"{k:4d}  {str(np.round(measurements.actuators[k], 5)):<38}{str(np.round(g.translation, 5)):<30}"
        f"{math.atan2(g.rotation[1, 0], g.rotation[0, 0]):10.4f}"
    )

# %% [markdown]
# ## 2. The parameters
#
# Placements: the 20 joint placements of the tree (each $T_{k-1,k}(0)$) plus the 14 frames that the 7 closures and
# the measurement use. A parameter is named `placement.dt[k]`, with $k = 0..5$ for
# $v_x, v_y, v_z, \omega_x, \omega_y, \omega_z$.

# %%
error_model = ClosedLoopErrorModel(mech)
kinds = Counter(p.kind for p in error_model.placements)
print(f"{error_model.n_parameters} parameters = 6 x ({kinds['joint']} joint placements + {kinds['frame']} frames)")
print("frames:", ", ".join(p.name for p in error_model.placements if p.kind == "frame"))
assert (error_model.n_parameters, kinds["joint"], kinds["frame"]) == (204, 20, 14)

# %% [markdown]
# ## 3. Calibration
#
# `calibrate_closed_loop(nominal, measurements, noise)` starts from the nominal machine. It first checks that the
# poses excite every parameter the model can identify, and raises `IdentificationError` otherwise. The result holds
# the calibrated `mechanism` (its home re-assembled), the identified `parameters` with their `std`, the `base`
# set, and the RMS of the measurement residual before and after.
#
# If the model fits down to the noise, the residual RMS after the fit should approach $\sqrt{3}\,\sigma$ per pose,
# shrunk by $\sqrt{1 - \text{rank}/(6N)}$ because the fit absorbs part of the noise.

# %%
t0 = time.perf_counter()
cal = calibrate_closed_loop(mech, measurements, CalibrationOptions(noise=noise))
seconds = time.perf_counter() - t0
shrink = math.sqrt(1 - cal.base.rank / (6 * len(measurements)))
print(
    f"{seconds:.2f} s; Levenberg-Marquardt: {cal.lm.iterations} iterations, stopped by its '{cal.lm.termination}' test"
)
print(
    f"identifiable (base) parameters: {cal.base.rank} of {len(cal.parameters)}, condition number "
    f"{cal.base.condition_number:.2g}; {len(cal.base.zero_columns)} parameters have no effect on the measurements"
)
print(f"residual RMS before: {cal.rms_before[0] * 1e6:9.1f} um {cal.rms_before[1] * 1e6:9.1f} urad")
print(f"residual RMS after : {cal.rms_after[0] * 1e6:9.1f} um {cal.rms_after[1] * 1e6:9.1f} urad")
print(
    f"noise floor (approx): {math.sqrt(3) * noise.position * shrink * 1e6:8.1f} um "
    f"{math.sqrt(3) * noise.rotation * shrink * 1e6:9.1f} urad"
)
# the model fits down to the noise: the residual lands near the floor, not above it
assert 0.7 < cal.rms_after[0] / (math.sqrt(3) * noise.position * shrink) < 1.5
assert 0.7 < cal.rms_after[1] / (math.sqrt(3) * noise.rotation * shrink) < 1.5

# %% [markdown]
# **Which parameters are identifiable?** Many of the 204 errors look exactly like others in the measurements, and
# some leave no trace at all. A turn about a revolute joint's own axis is just a joint offset. Consecutive placements
# can trade errors. A closure frame's error along a residual row that is not enforced changes nothing. The pivoted QR
# keeps one parameter per independent combination and leaves the others at zero. The identified values are
# therefore a *representative* of the truth, not the truth itself. They reproduce the machine's motion, which is all
# that prediction and compensation need. The table lists which components each placement keeps. The second table
# compares the largest identified values with the simulated truth. Large values of opposite sign and with large std
# on neighbouring placements are such trades, since only their combination is pinned down.

# %%
LABELS = ("vx", "vy", "vz", "wx", "wy", "wz")
kept: dict[str, list[int]] = {}
for name in cal.base.names:
    placement, component = name[:-1].split(".dt[")
    kept.setdefault(placement, []).append(int(component))
print(f"{'placement':<16}{'kind':<7}{'kept':>5}  components")
for p in error_model.placements:
    components = kept.get(p.name, [])
    print(f"{p.name:<16}{p.kind:<7}{len(components):5d}  {' '.join(LABELS[k] for k in components)}")
true_value = dict(zip(error_model.names, study.errors))  # the simulated machine's errors, same order
print(f"\n{'largest identified':<20}{'value':>9}{'std':>9}{'truth':>9}   [mm or mrad]")
for name in sorted(cal.base.names, key=lambda n: -abs(cal.parameters[n]))[:6]:
    print(f"{name:<20}{cal.parameters[name] * 1e3:+9.2f}{cal.std[name] * 1e3:9.2f}{true_value[name] * 1e3:+9.2f}")

# %% [markdown]
# ## 4. Accuracy on held-out poses, and its predicted floor
#
# `pose_errors(a, b, sliders)` drives two machines with the same sliders and returns the per-pose position distance
# [m] and rotation angle [rad] of their platforms. Held-out poses use exact slider values, so they measure the model,
# not the instruments.
#
# `predicted_pose_std(cal, sliders)` propagates the base-parameter covariance $\sigma^2 (J^\top W J)^{-1}$ through
# the platform sensitivity. The square root of the trace of the $3 \times 3$ position block is the expected RMS of
# the position error norm. The RMS of the actual errors should land close to it.

# %%
held = study.holdout_actuators
rows = {
    "calibration poses, nominal model": pose_errors(mech, study.truth, measurements.actuators),
    "calibration poses, calibrated": pose_errors(cal.mechanism, study.truth, measurements.actuators),
    "held-out poses, nominal model": pose_errors(mech, study.truth, held),
    "held-out poses, calibrated": pose_errors(cal.mechanism, study.truth, held),
}
print(HEADER)
for label, e in rows.items():
    print(row(label, e.position, e.rotation))

after = rows["held-out poses, calibrated"]
predicted = predicted_pose_std(cal, held)
rms = lambda v: math.sqrt(np.mean(np.square(v)))
print(
    f"\nheld-out RMS, actual vs predicted: "
    f"position {rms(after.position) * 1e6:.1f} vs {rms(predicted.position) * 1e6:.1f} um, "
    f"rotation {rms(after.rotation) * 1e6:.1f} vs {rms(predicted.rotation) * 1e6:.1f} urad"
)
assert after.position_mean < 50e-6 and after.position_mean < rows["held-out poses, nominal model"].position_mean / 100
assert (
    0.5 < rms(after.position) / rms(predicted.position) < 2 and 0.5 < rms(after.rotation) / rms(predicted.rotation) < 2
)

# %%
figure = plot_pose_errors_before_after(
    rows["held-out poses, nominal model"],
    after,
    OUT / "03_holdout_before_after.png",
    title="Held-out poses: platform error vs the actual machine",
)
display(Image(filename=str(figure), width=640))

# %% [markdown]
# **How many poses?** The same calibration on the first $n$ poses. With too few poses, or poses too close together,
# the kept set becomes ill-conditioned and a `PoorExcitationWarning` says so.

# %%
print(f"{'poses':>5}{'held-out pos mean [um]':>24}{'predicted RMS [um]':>20}{'condition':>12}  warning")
for n in (20, 30, 40, N_POSES):
    subset = PoseMeasurements(measurements.actuators[:n], measurements.poses[:n])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PoorExcitationWarning)
        fitted = cal if n == N_POSES else calibrate_closed_loop(mech, subset, CalibrationOptions(noise=noise))
    e = pose_errors(fitted.mechanism, study.truth, held[:50])
    std = predicted_pose_std(fitted, held[:50])
    flagged = any(issubclass(w.category, PoorExcitationWarning) for w in caught)
    print(
        f"{n:5d}{e.position_mean * 1e6:24.1f}{rms(std.position) * 1e6:20.1f}{fitted.base.condition_number:12.2g}  "
        f"{'poor excitation' if flagged else ''}"
    )

# %% [markdown]
# ## 5. Compensation (paper section 7, Fig. 6)
#
# The controller knows only the nominal model. To put the real platform at a target $T_{co}$:
#
# 1. IK of the **calibrated** model gives the sliders $q^c$ that reach $T_{co}$ on the machine as identified;
# 2. FK of the **nominal** model at $q^c$ gives $T_{cp}$, the pose to send. The controller's own nominal IK of
#    $T_{cp}$ returns $q^c$.
#
# A controller that takes slider commands uses `actuators` ($q^c$) directly. One that takes poses uses
# `command_targets` ($T_{cp}$ as $x, y, z, \theta$). Only position and yaw can be commanded. Roll and pitch are whatever
# the geometry gives, and are reported in `tilt`. The batch runs as a path, each solve warm-started from the previous
# one. Targets that fail (out of reach, or a slider beyond its limit) are listed in `failures` rather than clipped.

# %%
targets = workspace_targets(100, np.random.default_rng(SEED + 1))
commands = compensate(mech, cal.mechanism, targets)
print(
    f"{commands.n_targets} targets, {len(commands.indices)} compensated, {len(commands.failures)} failed; "
    f"max |tilt| {commands.max_tilt * 1e3:.1f} mrad; mean IK steps {commands.iterations.mean():.1f}"
)
print(f"\n{'target T_co x, y, z, theta':<36}{'q^c sliders [m]':<40}{'T_cp x, y, z, theta':<36}{'tilt [mrad]':<16}")
for k in range(5):
    print(
        f"{str(np.round(targets[commands.indices[k]], 4)):<36}{str(np.round(commands.actuators[k], 4)):<40}"
        f"{str(np.round(commands.command_targets[k], 4)):<36}{str(np.round(commands.tilt[k] * 1e3, 1)):<16}"
    )
assert len(commands.indices) == commands.n_targets and not commands.failures

# %% [markdown]
# `compensation_accuracy` simulates both ways of driving the actual machine to the targets. *Before*: the sliders
# come from nominal IK. *After*: they are the compensated $q^c$. The errors are the actual platform's distance to
# the target position, and its yaw error.

# %%
accuracy = compensation_accuracy(mech, cal.mechanism, study.truth, targets)
print(f"{len(accuracy.indices)} of {accuracy.n_targets} targets evaluated")
print(
    f"{'':<24}{'pos mean [um]':>14}{'pos max [um]':>13}{'pos rms [um]':>13}"
    f"{'yaw mean [urad]':>16}{'yaw max [urad]':>15}"
)
for label, e in (("nominal commands", accuracy.before), ("compensated commands", accuracy.after)):
    print(
        f"{label:<24}{e.position_mean * 1e6:14.1f}{e.position_max * 1e6:13.1f}{e.position_rms * 1e6:13.1f}"
        f"{e.rotation_mean * 1e6:16.1f}{e.rotation_max * 1e6:15.1f}"
    )
assert accuracy.after.position_mean < 50e-6 and accuracy.after.position_mean < accuracy.before.position_mean / 100
assert accuracy.after.rotation_mean < 50e-6 and accuracy.after.rotation_mean < accuracy.before.rotation_mean / 100

# %% [markdown]
# ## 6. Saving and reloading the calibrated machine
#
# `Mechanism.save(urdf, closures)` writes the calibrated machine as a new URDF and closures pair. The URDF is the
# source URDF with every joint `<origin>` rewritten from the identified model, so visuals, limits and names are kept.
# The closures file receives the re-assembled home. `Mechanism.load` reads the pair back with full validation, and
# any tool that takes a URDF plus closures file can use it. Both writes are atomic and refuse to overwrite the
# packaged nominal files.

# %%
import xml.etree.ElementTree as ET

urdf, closures = OUT / "calibrated.urdf", OUT / "calibrated.closures.yaml"
cal.mechanism.save(urdf, closures)
reloaded = Mechanism.load(urdf, closures)
check = pose_errors(cal.mechanism, reloaded, held[:50])
print(f"wrote {urdf} and {closures}")
print(
    f"reloaded vs in-memory calibrated model: max platform difference {check.position.max():.1e} m, "
    f"{check.rotation.max():.1e} rad"
)
assert check.position.max() < 1e-9 and check.rotation.max() < 1e-9  # the files hold the calibrated machine


def origin(path, joint):
    element = ET.parse(path).getroot().find(f"joint[@name='{joint}']/origin")
    return element.get("xyz"), element.get("rpy")


print(f"\n{'joint':<8}{'file':<11}{'origin xyz [m]':<52}rpy [rad]")
for joint in ("q12", "q14"):
    for label, path in (("nominal", mech.urdf_path), ("calibrated", urdf)):
        xyz, rpy = origin(path, joint)
        print(f"{joint:<8}{label:<11}{xyz:<52}{rpy}")

# %% [markdown]
# ## 7. Nominal vs calibrated, in meshcat
#
# The scene is recorded offline and written as one self-contained HTML page (no server). Both machines are posed by
# IK at the same platform target. The nominal machine is drawn in its URDF colours and the calibrated machine in
# translucent magenta, so the slider differences that compensation applies are visible. The measured platform
# positions appear as yellow spheres.

# %%
page = write_static_html(
    comparison_views(mech, cal.mechanism),
    OUT / "03_nominal_vs_calibrated.html",
    pose=(0.5, 0.6, -0.1, 0.3),
    markers=study.measurements.poses,
)
print(f"wrote {page} ({page.stat().st_size / 1e6:.1f} MB); open it in a browser")
assert page.stat().st_size > 100_000  # the viewer's JavaScript is inlined
# inline view in Jupyter: the page itself, embedded (the temporary folder is not served)
HTML(
    f'<iframe srcdoc="{escape(page.read_text(encoding="utf-8"))}" width="100%" height="480" style="border: 0"></iframe>'
)

# %% [markdown]
# **Things to try.** Change `SEED`, `N_POSES` or the `TrackerNoise` values. Pass
# `options=StudyOptions(position_only=True)` to `simulate_study` to simulate a tracker that sees only a point on the
# platform, then compare the rank and the held-out errors. Scale the machine's errors with
# `errors=PlacementErrorScale(position, rotation)`. Change the compensation
# targets, for instance to `compensation.workspace_grid((5, 5, 3, 3))`, a serpentine grid.
