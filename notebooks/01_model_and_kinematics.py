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
# # 01 · The M-shaped 3T1R machine: model and closed-loop kinematics
#
# This notebook loads the nominal machine description and goes through its closed-loop kinematics:
#
# 1. the description: the URDF tree, its loop closures, the actuated joints and the paper's two principal chains;
# 2. forward kinematics (FK): platform pose from the four slider positions;
# 3. inverse kinematics (IK): slider positions from a platform target $(x, y, z, \theta)$;
# 4. mobility: the rank of the closure Jacobian;
# 5. a warm-started path, with its Newton iteration counts;
# 6. a machine with geometric errors: it still assembles, but its platform tilts (roll and pitch);
# 7. a meshcat scene written to a static HTML page (no server needed).
#
# **Conventions.** SI units throughout (m, rad). The base frame $B$ sits at rail-axis height with $z$ up.
# Rail I runs along $y$ at $x = 0$ and rail II at $x = b = 1$ m. The platform frame is `P_I`, at the platform
# midpoint $P$. Twists and error vectors are Pinocchio's $[v;\ \omega]$, linear part first. The yaw $\theta$ is
# the heading of the platform's $x$ axis, $\operatorname{atan2}(R_{10}, R_{00})$. Roll and pitch use Pinocchio's
# ZYX RPY convention. Equation numbers refer to Zhang et al., *Symmetry* 2020 (the paper this project reproduces).
#
# Every cell runs in well under a second. Change the numbers and re-run.

# %%
import tempfile
import time
from pathlib import Path

import numpy as np

from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver

# Files written by this notebook go to a fresh temporary folder, never into the repository.
OUT = Path(tempfile.mkdtemp(prefix="m3t1r-notebook-01-"))
print(f"files written by this notebook: {OUT}")
np.set_printoptions(precision=4, suppress=True, linewidth=110)

# %% [markdown]
# ## 1. The description: a tree plus closures
#
# Pinocchio only handles trees, so the machine is stored in two files. The URDF holds four open chains hanging
# from `base`, one per slider. The closures file lists the frame pairs that must coincide to close the loops.
# `Mechanism.load()` reads the packaged nominal pair. It also checks every name and checks that the declared
# `home` configuration actually closes.

# %%
mech = Mechanism.load()
model = mech.model
print(f"URDF      : {mech.urdf_path}")
print(f"closures  : {mech.closures_path}")
print(
    f"joints    : nq = nv = {model.nv} (1-DoF each), {len(mech.actuated_joints)} actuated, "
    f"{len(mech.passive_ids)} passive"
)
print(f"closures  : {len(mech.closures)} loops, {mech.n_constraints} enforced residual rows")
print(f"actuated  : {mech.actuated_joints}")
print(f"platform  : frame '{mech.platform_frame}'")
assert (model.nv, len(mech.actuated_joints), len(mech.passive_ids)) == (20, 4, 16)

# %% [markdown]
# Every joint, with its Pinocchio type (`PY` = prismatic along $y$, `RX` = revolute about $x$, ...), its parent
# joint, its value at the assembled home pose and its role. At a zero joint vector the machine is *not* assembled:
# only `home` is.

# %%
chain_of = {j: name for name, items in mech.principal_chains.items() for j in items[:-1]}
print(f"{'joint':<9}{'type':<6}{'parent':<10}{'home':>10}  role")
for j in range(1, model.njoints):
    name = model.names[j]
    kind = model.joints[j].shortname().replace("JointModel", "")
    unit = "m" if kind.startswith("P") else "rad"
    role = "actuated (slider)" if name in mech.actuated_joints else "passive"
    if name in chain_of:
        role += f", principal chain {chain_of[name]}"
    print(f"{name:<9}{kind:<6}{model.names[model.parents[j]]:<10}{mech.home[model.idx_qs[j]]:>9.4f} {unit:<3} {role}")

# %% [markdown]
# **Closures.** A `3D` closure asks for two frame origins to coincide. Its residual is $R_a^\top (p_b - p_a)$, in
# frame $a$'s axes [m]. A `6D` closure asks for two whole frames to coincide. Its residual is
# $\log_6(T_a^{-1} T_b) = [v;\ \omega]$ [m, rad]. Only the listed **rows** are enforced. In the nominal geometry the
# others follow from them, so enforcing them too would make the system over-determined. Three loops close each
# side: the upper and lower parallelograms, and the five-bar formed by slider B2 (B4) and the knee. A 6D weld
# of `P_I` to `P_II` joins the two sides.

# %%
LABELS = {"3D": ("x", "y", "z"), "6D": ("vx", "vy", "vz", "wx", "wy", "wz")}
print(f"{'closure':<24}{'type':<5}{'frame_a':<15}{'frame_b':<15}enforced rows")
for c in mech.closures:
    enforced = ", ".join(LABELS[c.type][r] for r in c.rows)
    print(f"{c.name:<24}{c.type:<5}{c.frame_a:<15}{c.frame_b:<15}{enforced}")
print(
    f"\n{mech.n_constraints} enforced rows on {model.nv} joints -> {model.nv - mech.n_constraints} degrees of freedom "
    "expected (3 translations + yaw)"
)
assert (len(mech.closures), mech.n_constraints) == (7, 16)

# %% [markdown]
# **Principal chains.** These are the paper's chains $i = 1, 2$ (sections 3 and 6): B1 → P and B3 → P, listed as
# joint names followed by the end frame. On this machine each of the paper's "equivalent" revolute joints $q_{i2}$,
# $q_{i3}$ is a parallelogram. It shows up as a crank plus a coupling joint (`_pa`).

# %%
for name, items in mech.principal_chains.items():
    print(f"{name}: {' -> '.join(items[:-1])}  ==>  frame {items[-1]}")

# %% [markdown]
# ## 2. Forward kinematics
#
# `ClosedLoopSolver.forward(sliders)` locks the four sliders [m] and solves the 16 enforced closure rows for the
# 16 passive joints. It uses Newton's method with the analytic closure Jacobian. The result holds `pose` (a
# `pin.SE3` of `P_I` in $B$), `yaw`, `roll_pitch`, the full configuration `q`, the final `residual`, and
# `iterations` (Newton steps). `q_init=mech.home` starts each solve from home and keeps it on the home assembly
# branch.

# %%
solver = ClosedLoopSolver(mech)
home_sliders = mech.home[mech.actuated_ids]
slider_sets = [home_sliders, [0.05, 0.05, 0.05, 0.05], [0.05, 0.0, 0.0, 0.05], [0.10, 0.05, 0.15, 0.12]]
print(
    f"{'sliders q11, q11_B2, q21, q21_B4 [m]':<38}{'x':>8}{'y':>8}{'z':>8}{'yaw':>8}"
    f"{'roll':>10}{'pitch':>10}{'iters':>6}{'residual':>10}"
)
for s in slider_sets:
    fk = solver.forward(np.asarray(s, dtype=float), q_init=mech.home)
    roll, pitch = fk.roll_pitch
    x, y, z = fk.pose.translation
    print(
        f"{str(np.round(s, 3)):<38}{x:8.4f}{y:8.4f}{z:8.4f}{fk.yaw:8.4f}{roll:10.1e}{pitch:10.1e}"
        f"{fk.iterations:6d}{fk.residual:10.1e}"
    )
    assert fk.residual < 1e-10 and max(abs(roll), abs(pitch)) < 1e-12  # closed, and level to rounding

# %% [markdown]
# Moving all four sliders by the same amount translates the whole machine along the rails. The passive joints do
# not change, so Newton takes 0 steps. On the nominal machine roll and pitch stay at rounding level: the
# parallelograms keep the platform level.
#
# ## 3. Inverse kinematics
#
# `inverse((x, y, z, theta))` solves one square system over all 20 joints: the 16 closure rows, plus
# $p_P - p^*$ (3 rows) and $\theta_P - \theta^*$ (1 row). It returns the sliders in `actuators` [m]. Roll and pitch
# cannot be commanded on a 4-DoF machine. Whatever the geometry gives is reported in `tilt`; it is zero on the nominal
# machine. Each target is checked with a round trip through FK.

# %%
targets = [(0.50, 0.525, -0.111, 0.0), (0.42, 0.30, -0.20, -0.6), (0.58, 0.80, -0.02, 0.7), (0.5, 0.6, -0.1, 0.3)]
print(f"{'target x, y, z, theta':<30}{'sliders [m]':<40}{'iters':>6}{'max |tilt| [rad]':>22}{'FK round trip [m]':>19}")
for t in targets:
    ik = solver.inverse(t, q_init=mech.home)
    fk = solver.forward(ik.actuators, q_init=mech.home)
    back = np.linalg.norm(fk.pose.translation - np.array(t[:3])) + abs(fk.yaw - t[3])
    print(
        f"{str(t):<30}{str(np.round(ik.actuators, 4)):<40}{ik.iterations:6d}{max(map(abs, ik.tilt)):>22.1e}{back:19.1e}"
    )
    assert max(map(abs, ik.tilt)) < 1e-12 and back < 1e-9

# %% [markdown]
# ## 4. Mobility and the rank of the closure Jacobian
#
# `closure_jacobian(q)` is $\partial r_c / \partial q$: 16 enforced rows × 20 joints, computed analytically from
# Pinocchio's WORLD joint Jacobian. `mobility(q)` is $n_v - \operatorname{rank}$, with the rank taken at a relative
# singular-value threshold of $10^{-9}$. With `all_rows=True` every residual component of every closure is stacked
# (6 × 3 + 6 = 24 rows). In the nominal geometry the extra rows are combinations of the enforced ones, so the rank,
# and hence the mobility, stays the same. The gap between the 16th and 17th singular values shows how sharp the
# rank decision is.

# %%
print(
    f"{'configuration':<26}{'J_c':>9}{'rank':>6}{'mobility':>9}{'J_c all rows':>14}{'rank':>6}{'mobility':>9}"
    f"{'sigma_16/sigma_1':>18}{'sigma_17/sigma_1':>18}"
)
for label, goal in [("home", None)] + [(str(t), t) for t in targets[1:3]]:
    q = mech.home if goal is None else solver.inverse(goal, q_init=mech.home).q
    J = solver.closure_jacobian(q)
    J_all = solver.closure_jacobian(q, all_rows=True)
    s = np.linalg.svd(J_all, compute_uv=False)
    rank, rank_all = model.nv - solver.mobility(q), model.nv - solver.mobility(q, all_rows=True)
    print(
        f"{label:<26}{str(J.shape):>9}{rank:6d}{solver.mobility(q):9d}{str(J_all.shape):>14}{rank_all:6d}"
        f"{solver.mobility(q, all_rows=True):9d}{s[15] / s[0]:18.2e}{s[16] / s[0]:18.2e}"
    )
    assert rank == rank_all == 16 and s[15] / s[0] > 1e-3 and s[16] / s[0] < 1e-12  # a sharp rank decision

# %% [markdown]
# ## 5. A warm-started path
#
# Without `q_init`, a solver starts from its own last solution. FK adds a first-order predictor along the solution
# manifold, $\Delta q_{passive} = -J_{passive}^{-1} J_{act}\, \Delta s$. IK makes one predictor step with its last
# factorisation. Newton also keeps its LU factors across steps for as long as each step still contracts the
# residual (chord steps). The path below is a straight line of 41 targets across the workspace, 1.25 cm and
# 25 mrad apart. It compares warm solves against solves that restart from home every time. All the matrices are
# tiny, so the timing runs on one BLAS thread (`threadpoolctl.threadpool_limits`): extra BLAS threads only add
# wake-up latency here. The batch functions of `m3t1r` do the same internally.

# %%
from threadpoolctl import threadpool_limits

start, end = np.array([0.45, 0.30, -0.18, -0.5]), np.array([0.55, 0.80, -0.04, 0.5])
path = [start + (end - start) * k / 40 for k in range(41)]
warm_ik, warm_fk, cold = ClosedLoopSolver(mech), ClosedLoopSolver(mech), ClosedLoopSolver(mech)
rows, clock = [], np.zeros(3)
with threadpool_limits(limits=1, user_api="blas"):
    for t in path:
        t0 = time.perf_counter()
        ik = warm_ik.inverse(t)
        t1 = time.perf_counter()
        ik_cold = cold.inverse(t, q_init=mech.home)
        t2 = time.perf_counter()
        fk = warm_fk.forward(ik.actuators)
        t3 = time.perf_counter()
        clock += (t1 - t0, t2 - t1, t3 - t2)
        rows.append((t, ik.iterations, ik_cold.iterations, fk.iterations, np.linalg.norm(fk.pose.translation - t[:3])))
print(f"{'k':>3}  {'target x, y, z, theta':<34}{'warm IK':>8}{'cold IK':>8}{'warm FK':>8}{'FK vs target [m]':>18}")
for k, (t, warm_ik_steps, cold_ik_steps, warm_fk_steps, gap) in enumerate(rows):
    if k % 5 == 0 or k == 1:
        print(f"{k:3d}  {str(np.round(t, 4)):<34}{warm_ik_steps:8d}{cold_ik_steps:8d}{warm_fk_steps:8d}{gap:18.1e}")
iterations = np.array([r[1:4] for r in rows])
print(
    f"mean Newton steps (targets 1..40): warm IK {iterations[1:, 0].mean():.1f}, "
    f"cold IK {iterations[1:, 1].mean():.1f}, warm FK {iterations[1:, 2].mean():.1f}"
)
print(
    "mean time per solve: "
    + ", ".join(f"{k} {v / len(path) * 1e6:.0f} us" for k, v in zip(("warm IK", "cold IK", "warm FK"), clock))
)
assert max(r[4] for r in rows) < 1e-9  # every warm FK lands on its target
assert iterations[1:, 0].mean() < iterations[1:, 1].mean()  # warm IK takes fewer Newton steps than cold IK

# %% [markdown]
# ## 6. A machine with geometric errors
#
# `simulate_study` draws an "actual" machine. Every joint placement and every closure or platform frame gets a
# right-multiplied error, $T(0) \leftarrow T(0)\exp_6(\delta t)$ (eq. 33-34), with $\sigma$ = 1 mm on $v$ and 1 mrad
# on $\omega$. The machine's home is then re-assembled. The simulation also measures the platform at `n_poses`
# slider sets drawn over the workspace box. Here we take 5 sets, exact, with no tracker noise.
#
# The enforced rows still close on this machine. The 6D weld, however, cannot hold in every direction once the two
# sides disagree. $P_I$ and $P_{II}$ match in $x, y, z$ and yaw (the enforced rows), but their roll and pitch differ.
# The platform frame $P_I$ itself tilts: this is the residual tilt below. Roll and pitch are not commandable, so it
# stays whatever the geometry makes it.

# %%
from m3t1r.calibration.simulation import simulate_study

study = simulate_study(mech, n_poses=5, n_holdout=0, seed=0)
truth = study.truth
dt = study.errors.reshape(-1, 6)
rms_v, rms_w = np.sqrt(np.mean(np.sum(dt[:, :3] ** 2, 1))), np.sqrt(np.mean(np.sum(dt[:, 3:] ** 2, 1)))
print(f"{len(dt)} placements perturbed: RMS |v| = {rms_v * 1e3:.2f} mm, RMS |w| = {rms_w * 1e3:.2f} mrad")
assert 1e-3 < rms_v < 2.5e-3 and 1e-3 < rms_w < 2.5e-3  # sqrt(3) x 1 mm (1 mrad), give or take the draw

nominal_solver, truth_solver = ClosedLoopSolver(mech), ClosedLoopSolver(truth)
print(
    f"\n{'sliders [m]':<38}{'|dp| [mm]':>10}{'d yaw [mrad]':>14}{'roll [mrad]':>13}{'pitch [mrad]':>14}"
    f"{'iters':>6}{'max other row':>15}"
)
for s in study.measurements.actuators:
    n, a = nominal_solver.forward(s, q_init=mech.home), truth_solver.forward(s, q_init=truth.home)
    roll, pitch = a.roll_pitch
    unenforced = np.abs(truth_solver.closure_residual(a.q, all_rows=True)).max()
    print(
        f"{str(np.round(s, 3)):<38}{np.linalg.norm(a.pose.translation - n.pose.translation) * 1e3:10.2f}"
        f"{(a.yaw - n.yaw) * 1e3:14.1f}{roll * 1e3:13.1f}{pitch * 1e3:14.1f}{a.iterations:6d}{unenforced:15.2e}"
    )
    # the enforced rows close; the platform tilts and the other rows stay open
    assert a.residual < 1e-10 and max(abs(roll), abs(pitch)) > 1e-3 and unenforced > 1e-3

ik = truth_solver.inverse((0.5, 0.6, -0.1, 0.3), q_init=truth.home)
print(
    f"\nIK on the actual machine at (0.5, 0.6, -0.1, 0.3): sliders {np.round(ik.actuators, 4)}, "
    f"residual tilt roll/pitch = {ik.tilt[0] * 1e3:.1f} / {ik.tilt[1] * 1e3:.1f} mrad"
)
assert max(map(abs, ik.tilt)) > 1e-3

# %% [markdown]
# These pose errors are large for millimetre-sized geometric errors. The parallelograms amplify them: their bar
# offsets are only 0.08 m (upper) and 0.06 m (lower), so a 1 mm misfit across one turns its coupling joint by an
# angle of the order of 0.001 / 0.08 ≈ 12 mrad. The next cell applies one parameter at a time, at +1 mm or
# +1 mrad, and lists the most influential ones at the home sliders.
# Parameter `name.dt[k]` is component $k$ of $[v;\ \omega]$ on placement `name`.

# %%
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.simulation import actual_machine

error_model = ClosedLoopErrorModel(mech)
reference = nominal_solver.forward(home_sliders, q_init=mech.home)
effects = []
for k, name in enumerate(error_model.names):
    vector = np.zeros(error_model.n_parameters)
    vector[k] = 1e-3
    one = actual_machine(mech, vector, error_model)
    fk = ClosedLoopSolver(one).forward(home_sliders, q_init=one.home)
    effects.append(
        (abs(fk.yaw - reference.yaw), np.linalg.norm(fk.pose.translation - reference.pose.translation), name)
    )
effects.sort(reverse=True)
print(f"{error_model.n_parameters} parameters; largest effects of a single 1e-3 error at the home sliders:")
print(f"{'parameter':<22}{'|d yaw| [mrad]':>16}{'|dp| [mm]':>11}")
for d_yaw, d_p, name in effects[:8]:
    print(f"{name:<22}{d_yaw * 1e3:16.2f}{d_p * 1e3:11.2f}")
assert effects[0][0] > 5e-3  # amplified: 1 mm or 1 mrad turns the platform by several mrad

# %% [markdown]
# ## 7. A meshcat view, as a static page
#
# `write_static_html` records the meshcat scene offline and writes one self-contained HTML file. The viewer's
# JavaScript and every draw command are inlined, so the page opens from `file://` and no server is involved.
# Both machines are posed by IK at the same platform target, so the picture shows the different slider positions
# each one needs. The nominal machine is drawn in its URDF colours and the actual machine in translucent magenta.
# The measured platform positions appear as yellow spheres. `comparison_views(nominal, calibrated)` builds the
# usual nominal/calibrated pair (notebook 03). Here the second machine is the simulated truth, so we name it
# ourselves.

# %%
from html import escape

from IPython.display import HTML

from m3t1r.app.scene import CALIBRATED_COLOR, MachineView, comparison_views
from m3t1r.app.static_page import write_static_html

views = comparison_views(mech) + (MachineView("actual", truth, CALIBRATED_COLOR),)
page = write_static_html(
    views, OUT / "01_nominal_vs_actual.html", pose=(0.5, 0.6, -0.1, 0.3), markers=study.measurements.poses
)
print(f"wrote {page} ({page.stat().st_size / 1e6:.1f} MB); open it in a browser")
assert page.stat().st_size > 100_000  # the viewer's JavaScript is inlined
# inline view in Jupyter: the page itself, embedded (the temporary folder is not served)
HTML(
    f'<iframe srcdoc="{escape(page.read_text(encoding="utf-8"))}" width="100%" height="480" style="border: 0"></iframe>'
)
