"""Generate the tutorial notebooks of this folder from the cell sources below.

    .venv/bin/python notebooks/build_notebooks.py

The notebooks are written without outputs or execution counts and with fixed cell ids, so that
regenerating an unchanged source gives byte-identical files. Edit the cells here, regenerate, and
check them with `.venv/bin/python -m pytest -q tests/test_notebooks.py` (which executes them).
"""

from __future__ import annotations

import sys
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent

KERNELSPEC = {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"}

# Every notebook starts with this cell: outputs go to _out/ next to the notebook (git-ignored).
SETUP = '''\
import math
import time
import warnings
from pathlib import Path

import numpy as np
import pinocchio as pin

# Files written by this notebook go here, relative to the notebook's folder (git-ignored).
OUT = Path("_out")
OUT.mkdir(exist_ok=True)
np.set_printoptions(precision=4, suppress=True, linewidth=110)'''


def md(text: str) -> tuple[str, str]:
    return ("markdown", text.strip("\n"))


def code(text: str) -> tuple[str, str]:
    return ("code", text.strip("\n"))


# ==================================================================================================
# 01: the model and its closed-loop kinematics
# ==================================================================================================

NB01 = [
    md(r"""
# 01 · The M-shaped 3T1R machine: model and closed-loop kinematics

This notebook loads the nominal machine description and goes through its closed-loop kinematics:

1. the description: the URDF tree, its loop closures, the actuated joints and the paper's two principal chains;
2. forward kinematics (FK): platform pose from the four slider positions;
3. inverse kinematics (IK): slider positions from a platform target $(x, y, z, \theta)$;
4. mobility: the rank of the closure Jacobian;
5. a warm-started path, with its Newton iteration counts;
6. a machine with geometric errors: it still assembles, but its platform tilts (roll and pitch);
7. a meshcat scene written to a static HTML page (no server needed).

**Conventions.** SI units throughout (m, rad). The base frame $B$ sits at rail-axis height with $z$ up.
Rail I runs along $y$ at $x = 0$ and rail II at $x = b = 1$ m. The platform frame is `P_I`, at the platform
midpoint $P$. Twists and error vectors are Pinocchio's $[v;\ \omega]$, linear part first. The yaw $\theta$ is
the heading of the platform's $x$ axis, $\operatorname{atan2}(R_{10}, R_{00})$. Roll and pitch use Pinocchio's
ZYX RPY convention. Equation numbers refer to Zhang et al., *Symmetry* 2020 (the paper this project reproduces).

Every cell runs in well under a second. Change the numbers and re-run.
"""),
    code(SETUP + '''

from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver, roll_pitch_of, yaw_of'''),
    md(r"""
## 1. The description: a tree plus closures

Pinocchio only handles trees, so the machine is stored in two files. The URDF holds four open chains hanging
from `base`, one per slider. The closures file lists the frame pairs that must coincide to close the loops.
`Mechanism.load()` reads the packaged nominal pair. It also checks every name and checks that the declared
`home` configuration actually closes.
"""),
    code('''
mech = Mechanism.load()
model = mech.model
print(f"URDF      : {mech.urdf_path}")
print(f"closures  : {mech.closures_path}")
print(f"joints    : nq = nv = {model.nv} (1-DoF each), {len(mech.actuated_joints)} actuated, "
      f"{len(mech.passive_ids)} passive")
print(f"closures  : {len(mech.closures)} loops, {mech.n_constraints} enforced residual rows")
print(f"actuated  : {mech.actuated_joints}")
print(f"platform  : frame '{mech.platform_frame}'")'''),
    md(r"""
Every joint, with its Pinocchio type (`PY` = prismatic along $y$, `RX` = revolute about $x$, ...), its parent
joint, its value at the assembled home pose and its role. At a zero joint vector the machine is *not* assembled:
only `home` is.
"""),
    code('''
chain_of = {j: name for name, items in mech.principal_chains.items() for j in items[:-1]}
print(f"{'joint':<9}{'type':<6}{'parent':<10}{'home':>10}  role")
for j in range(1, model.njoints):
    name = model.names[j]
    kind = model.joints[j].shortname().replace("JointModel", "")
    unit = "m" if kind.startswith("P") else "rad"
    role = "actuated (slider)" if name in mech.actuated_joints else "passive"
    if name in chain_of:
        role += f", principal chain {chain_of[name]}"
    print(f"{name:<9}{kind:<6}{model.names[model.parents[j]]:<10}{mech.home[model.idx_qs[j]]:>9.4f} {unit:<3} {role}")'''),
    md(r"""
**Closures.** A `3D` closure asks for two frame origins to coincide. Its residual is $R_a^\top (p_b - p_a)$, in
frame $a$'s axes [m]. A `6D` closure asks for two whole frames to coincide. Its residual is
$\log_6(T_a^{-1} T_b) = [v;\ \omega]$ [m, rad]. Only the listed **rows** are enforced. In the nominal geometry the
others follow from them, so enforcing them too would make the system over-determined. Three loops close each
side: the upper and lower parallelograms, and the five-bar formed by slider B2 (B4) and the knee. A 6D weld
of `P_I` to `P_II` joins the two sides.
"""),
    code('''
LABELS = {"3D": ("x", "y", "z"), "6D": ("vx", "vy", "vz", "wx", "wy", "wz")}
print(f"{'closure':<24}{'type':<5}{'frame_a':<15}{'frame_b':<15}enforced rows")
for c in mech.closures:
    rows = ", ".join(LABELS[c.type][r] for r in c.rows)
    print(f"{c.name:<24}{c.type:<5}{c.frame_a:<15}{c.frame_b:<15}{rows}")
print(f"\\n{mech.n_constraints} enforced rows on {model.nv} joints -> {model.nv - mech.n_constraints} degrees of freedom "
      "expected (3 translations + yaw)")'''),
    md(r"""
**Principal chains.** These are the paper's chains $i = 1, 2$ (sections 3 and 6): B1 → P and B3 → P, listed as
joint names followed by the end frame. On this machine each of the paper's "equivalent" revolute joints $q_{i2}$,
$q_{i3}$ is a parallelogram. It shows up as a crank plus a coupling joint (`_pa`).
"""),
    code('''
for name, items in mech.principal_chains.items():
    print(f"{name}: {' -> '.join(items[:-1])}  ==>  frame {items[-1]}")'''),
    md(r"""
## 2. Forward kinematics

`ClosedLoopSolver.forward(sliders)` locks the four sliders [m] and solves the 16 enforced closure rows for the
16 passive joints. It uses Newton's method with the analytic closure Jacobian. The result holds `pose` (a
`pin.SE3` of `P_I` in $B$), `yaw`, `roll_pitch`, the full configuration `q`, the final `residual`, and
`iterations` (Newton steps). `q_init=mech.home` starts each solve from home and keeps it on the home assembly
branch.
"""),
    code('''
solver = ClosedLoopSolver(mech)
home_sliders = mech.home[mech.actuated_ids]
slider_sets = [home_sliders, [0.05, 0.05, 0.05, 0.05], [0.05, 0.0, 0.0, 0.05], [0.10, 0.05, 0.15, 0.12]]
print(f"{'sliders q11, q11_B2, q21, q21_B4 [m]':<38}{'x':>8}{'y':>8}{'z':>8}{'yaw':>8}"
      f"{'roll':>10}{'pitch':>10}{'iters':>6}{'residual':>10}")
for s in slider_sets:
    fk = solver.forward(np.asarray(s, dtype=float), q_init=mech.home)
    roll, pitch = fk.roll_pitch
    x, y, z = fk.pose.translation
    print(f"{str(np.round(s, 3)):<38}{x:8.4f}{y:8.4f}{z:8.4f}{fk.yaw:8.4f}{roll:10.1e}{pitch:10.1e}"
          f"{fk.iterations:6d}{fk.residual:10.1e}")'''),
    md(r"""
Moving all four sliders by the same amount translates the whole machine along the rails. The passive joints do
not change, so Newton takes 0 steps. On the nominal machine roll and pitch stay at rounding level: the
parallelograms keep the platform level.

## 3. Inverse kinematics

`inverse((x, y, z, theta))` solves one square system over all 20 joints: the 16 closure rows, plus
$p_P - p^*$ (3 rows) and $\theta_P - \theta^*$ (1 row). It returns the sliders in `actuators` [m]. Roll and pitch
cannot be commanded on a 4-DoF machine. Whatever the geometry gives is reported in `tilt`; it is zero on the nominal
machine. Each target is checked with a round trip through FK.
"""),
    code('''
targets = [(0.50, 0.525, -0.111, 0.0), (0.42, 0.30, -0.20, -0.6), (0.58, 0.80, -0.02, 0.7), (0.5, 0.6, -0.1, 0.3)]
print(f"{'target x, y, z, theta':<30}{'sliders [m]':<40}{'iters':>6}{'max |tilt| [rad]':>22}{'FK round trip [m]':>19}")
for t in targets:
    ik = solver.inverse(t, q_init=mech.home)
    fk = solver.forward(ik.actuators, q_init=mech.home)
    back = np.linalg.norm(fk.pose.translation - np.array(t[:3])) + abs(fk.yaw - t[3])
    print(f"{str(t):<30}{str(np.round(ik.actuators, 4)):<40}{ik.iterations:6d}"
          f"{max(map(abs, ik.tilt)):>22.1e}{back:19.1e}")'''),
    md(r"""
## 4. Mobility and the rank of the closure Jacobian

`closure_jacobian(q)` is $\partial r_c / \partial q$: 16 enforced rows × 20 joints, computed analytically from
Pinocchio's WORLD joint Jacobian. `mobility(q)` is $n_v - \operatorname{rank}$, with the rank taken at a relative
singular-value threshold of $10^{-9}$. With `all_rows=True` every residual component of every closure is stacked
(6 × 3 + 6 = 24 rows). In the nominal geometry the extra rows are combinations of the enforced ones, so the rank,
and hence the mobility, stays the same. The gap between the 16th and 17th singular values shows how sharp the
rank decision is.
"""),
    code('''
print(f"{'configuration':<26}{'J_c':>9}{'rank':>6}{'mobility':>9}{'J_c all rows':>14}{'rank':>6}{'mobility':>9}"
      f"{'sigma_16/sigma_1':>18}{'sigma_17/sigma_1':>18}")
for label, t in [("home", None)] + [(str(t), t) for t in targets[1:3]]:
    q = mech.home if t is None else solver.inverse(t, q_init=mech.home).q
    J = solver.closure_jacobian(q)
    J_all = solver.closure_jacobian(q, all_rows=True)
    s = np.linalg.svd(J_all, compute_uv=False)
    rank, rank_all = model.nv - solver.mobility(q), model.nv - solver.mobility(q, all_rows=True)
    print(f"{label:<26}{str(J.shape):>9}{rank:6d}{solver.mobility(q):9d}{str(J_all.shape):>14}{rank_all:6d}"
          f"{solver.mobility(q, all_rows=True):9d}{s[15] / s[0]:18.2e}{s[16] / s[0]:18.2e}")'''),
    md(r"""
## 5. A warm-started path

Without `q_init`, a solver starts from its own last solution. FK adds a first-order predictor along the solution
manifold, $\Delta q_{passive} = -J_{passive}^{-1} J_{act}\, \Delta s$. IK makes one predictor step with its last
factorisation. Newton also keeps its LU factors across steps for as long as each step still contracts the
residual (chord steps). The path below is a straight line of 41 targets across the workspace, 1.25 cm and
25 mrad apart. It compares warm solves against solves that restart from home every time. All the matrices are
tiny, so the timing runs on one BLAS thread (`threadpoolctl.threadpool_limits`): extra BLAS threads only add
wake-up latency here. The batch functions of `m3t1r` do the same internally.
"""),
    code('''
from threadpoolctl import threadpool_limits

start, end = np.array([0.45, 0.30, -0.18, -0.5]), np.array([0.55, 0.80, -0.04, 0.5])
path = [start + (end - start) * k / 40 for k in range(41)]
warm_ik, warm_fk, cold = ClosedLoopSolver(mech), ClosedLoopSolver(mech), ClosedLoopSolver(mech)
rows, clock = [], np.zeros(3)
with threadpool_limits(limits=1, user_api="blas"):
    for t in path:
        t0 = time.perf_counter(); ik = warm_ik.inverse(t)
        t1 = time.perf_counter(); ik_cold = cold.inverse(t, q_init=mech.home)
        t2 = time.perf_counter(); fk = warm_fk.forward(ik.actuators)
        t3 = time.perf_counter()
        clock += (t1 - t0, t2 - t1, t3 - t2)
        rows.append((t, ik.iterations, ik_cold.iterations, fk.iterations,
                     np.linalg.norm(fk.pose.translation - t[:3])))
print(f"{'k':>3}  {'target x, y, z, theta':<34}{'warm IK':>8}{'cold IK':>8}{'warm FK':>8}{'FK vs target [m]':>18}")
for k, (t, a, b, c, e) in enumerate(rows):
    if k % 5 == 0 or k == 1:
        print(f"{k:3d}  {str(np.round(t, 4)):<34}{a:8d}{b:8d}{c:8d}{e:18.1e}")
iterations = np.array([r[1:4] for r in rows])
print(f"mean Newton steps (targets 1..40): warm IK {iterations[1:, 0].mean():.1f}, cold IK {iterations[1:, 1].mean():.1f}, "
      f"warm FK {iterations[1:, 2].mean():.1f}")
print("mean time per solve: " + ", ".join(f"{k} {v / len(path) * 1e6:.0f} us"
                                          for k, v in zip(("warm IK", "cold IK", "warm FK"), clock)))'''),
    md(r"""
## 6. A machine with geometric errors

`simulate_study` draws an "actual" machine. Every joint placement and every closure or platform frame gets a
right-multiplied error, $T(0) \leftarrow T(0)\exp_6(\delta t)$ (eq. 33-34), with $\sigma$ = 1 mm on $v$ and 1 mrad
on $\omega$. The machine's home is then re-assembled. The simulation also measures the platform at `n_poses`
slider sets drawn over the workspace box. Here we take 5 sets, exact, with no tracker noise.

The enforced rows still close on this machine. The 6D weld, however, cannot hold in every direction once the two
sides disagree. $P_I$ and $P_{II}$ match in $x, y, z$ and yaw (the enforced rows), but their roll and pitch differ.
The platform frame $P_I$ itself tilts: this is the residual tilt below. Roll and pitch are not commandable, so it
stays whatever the geometry makes it.
"""),
    code('''
from m3t1r.calibration.simulation import simulate_study

study = simulate_study(mech, n_poses=5, n_holdout=0, seed=0)
truth = study.truth
dt = study.errors.reshape(-1, 6)
print(f"{len(dt)} placements perturbed: RMS |v| = {np.sqrt(np.mean(np.sum(dt[:, :3] ** 2, 1))) * 1e3:.2f} mm, "
      f"RMS |w| = {np.sqrt(np.mean(np.sum(dt[:, 3:] ** 2, 1))) * 1e3:.2f} mrad")

nominal_solver, truth_solver = ClosedLoopSolver(mech), ClosedLoopSolver(truth)
print(f"\\n{'sliders [m]':<38}{'|dp| [mm]':>10}{'d yaw [mrad]':>14}{'roll [mrad]':>13}{'pitch [mrad]':>14}"
      f"{'iters':>6}{'max other row':>15}")
for s in study.measurements.actuators:
    n, a = nominal_solver.forward(s, q_init=mech.home), truth_solver.forward(s, q_init=truth.home)
    roll, pitch = a.roll_pitch
    unenforced = np.abs(truth_solver.closure_residual(a.q, all_rows=True)).max()
    print(f"{str(np.round(s, 3)):<38}{np.linalg.norm(a.pose.translation - n.pose.translation) * 1e3:10.2f}"
          f"{(a.yaw - n.yaw) * 1e3:14.1f}{roll * 1e3:13.1f}{pitch * 1e3:14.1f}{a.iterations:6d}{unenforced:15.2e}")

ik = truth_solver.inverse((0.5, 0.6, -0.1, 0.3), q_init=truth.home)
print(f"\\nIK on the actual machine at (0.5, 0.6, -0.1, 0.3): sliders {np.round(ik.actuators, 4)}, "
      f"residual tilt roll/pitch = {ik.tilt[0] * 1e3:.1f} / {ik.tilt[1] * 1e3:.1f} mrad")'''),
    md(r"""
These pose errors are large for millimetre-sized geometric errors. The parallelograms amplify them: their bar
offsets are only 0.08 m (upper) and 0.06 m (lower), so a 1 mm misfit across one turns its coupling joint by an
angle of the order of 0.001 / 0.08 ≈ 12 mrad. The next cell applies one parameter at a time, at +1 mm or
+1 mrad, and lists the most influential ones at the home sliders.
Parameter `name.dt[k]` is component $k$ of $[v;\ \omega]$ on placement `name`.
"""),
    code('''
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
    effects.append((abs(fk.yaw - reference.yaw), np.linalg.norm(fk.pose.translation - reference.pose.translation), name))
effects.sort(reverse=True)
print(f"{error_model.n_parameters} parameters; largest effects of a single 1e-3 error at the home sliders:")
print(f"{'parameter':<22}{'|d yaw| [mrad]':>16}{'|dp| [mm]':>11}")
for d_yaw, d_p, name in effects[:8]:
    print(f"{name:<22}{d_yaw * 1e3:16.2f}{d_p * 1e3:11.2f}")'''),
    md(r"""
## 7. A meshcat view, as a static page

`write_static_html` records the meshcat scene offline and writes one self-contained HTML file. The viewer's
JavaScript and every draw command are inlined, so the page opens from `file://` and no server is involved.
Both machines are posed by IK at the same platform target, so the picture shows the different slider positions
each one needs. The nominal machine is drawn in its URDF colours and the actual machine in translucent magenta.
The measured platform positions appear as yellow spheres. `comparison_views(nominal, calibrated)` builds the
usual nominal/calibrated pair (notebook 03). Here the second machine is the simulated truth, so we name it
ourselves.
"""),
    code('''
from IPython.display import IFrame
from m3t1r.app.scene import CALIBRATED_COLOR, MachineView, comparison_views
from m3t1r.app.static_page import write_static_html

views = comparison_views(mech) + (MachineView("actual", truth, CALIBRATED_COLOR),)
page = write_static_html(views, OUT / "01_nominal_vs_actual.html", pose=(0.5, 0.6, -0.1, 0.3),
                         markers=study.measurements.poses)
print(f"wrote {page} ({page.stat().st_size / 1e6:.1f} MB); open it in a browser")
IFrame(src=str(page), width="100%", height=480)  # inline view in Jupyter; other front ends: open the file'''),
]


# ==================================================================================================
# 02: the paper's method, step by step
# ==================================================================================================

NB02 = [
    md(r"""
# 02 · The paper's calibration method, step by step (simulation study)

This notebook reproduces the calibration of Zhang et al. (*Symmetry* 2020) in simulation with `m3t1r.paper`,
one section of the paper at a time:

| paper | what | `m3t1r.paper` |
|---|---|---|
| sec. 3, eq. (6), (11) | each principal chain as a serial local-POE chain; every error lumped into its initial poses $T(0)$ | `paper_chains` |
| eq. (18)-(21), (31) | $y_i = \log_6(g_{meas}\, g_i(q)^{-1}) = J_i x_i$, stacked over the poses | `two_chain_error_model`, `two_chain_identifiability` |
| sec. 5, eq. (32)-(33) | least squares, then $T(0) \leftarrow T(0)\exp_6(X)$, iterated until $\lVert X \rVert \to 0$ | `calibrate_two_chains` |
| sec. 4, eq. (22)-(30) | the lower-crank angles $q_{i3}$ from the foot distance $\lvert A_1A_2 \rvert = a$, instead of a sensor | `estimate_lower_crank_angles` |
| sec. 6, eq. (34)-(37), Table 1, Fig. 4 | preset errors $\delta t, \delta s, \delta q$; 20 poses; errors before and after | `preset_errors`, `actual_chain_poses`, `paper_study` |

The last section applies the same method to the full closed-chain machine, where only the sliders are
actuated and measured, and compares it with this project's closed-loop calibration (`calibrate_closed_loop`).

Units: m and rad. Poses are the platform frame in the base frame $B$. Errors are right-multiplied,
$T(0)\exp_6(\delta t)$ with $\delta t = [v;\ \omega]$. Pose errors, as in Fig. 4, are the position distance [m] and
the rotation angle [rad] between two poses.
"""),
    code(SETUP + """

from IPython.display import Image, display

from m3t1r import paper
from m3t1r.metrics import PoseErrors
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors
from m3t1r.model.description import Mechanism
from m3t1r.errors import PoorExcitationWarning
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.app.plots import plot_pose_errors_before_after
from m3t1r.model.poe import poe_forward
from m3t1r.calibration.simulation import simulate_study
from m3t1r.model.workspace import workspace_actuators

# calibrate_two_chains re-selects its identifiable parameters on the fitted model and keeps weakly
# conditioned combinations on purpose (see its docstring), so this conditioning warning is expected.
warnings.filterwarnings("ignore", category=PoorExcitationWarning)

SEED, N_POSES, N_HOLDOUT = 0, 20, 50   # the paper uses 20 calibration poses
mech = Mechanism.load()


def pose_differences(poses, references) -> PoseErrors:
    \"\"\"Per pose: position distance [m] and rotation angle of R_ref^T R [rad], the quantities of Fig. 4.\"\"\"
    position = [np.linalg.norm(g.translation - h.translation) for g, h in zip(poses, references)]
    rotation = [np.linalg.norm(pin.log3(h.rotation.T @ g.rotation)) for g, h in zip(poses, references)]
    return PoseErrors(np.array(position), np.array(rotation))


def chain_poses(chain, model, configurations):
    \"\"\"Tool poses g_i(q) of a paper chain (eq. 6) at full configurations (N, nq).\"\"\"
    return [poe_forward(chain.serial, model, qc) for qc in chain.coordinates(configurations)]


HEADER = f"{'':<46}{'pos mean [m]':>13}{'pos max [m]':>13}{'rot mean [rad]':>15}{'rot max [rad]':>14}"


def row(label, e: PoseErrors) -> str:
    return (f"{label:<46}{e.position.mean():13.2e}{e.position.max():13.2e}"
            f"{e.rotation.mean():15.2e}{e.rotation.max():14.2e}")"""),
    md(r"""
## 1. The paper's two chains

The paper calibrates the machine as two serial chains, B1 → P and B3 → P, each read by sensors on every joint.
`paper_chains` takes them from the description's `principal_chains`. Here each "equivalent" revolute joint
$q_{i2}$, $q_{i3}$ is a parallelogram, so the chain holds six joints: slider, upper crank with its coupling, lower crank
with its coupling, and platform hinge. Its seven initial poses $T_{0,1}(0), \dots, T_{6,P}(0)$ (eq. 6) each carry a
6-vector error, which gives 42 parameters per chain. Chain B3 ends at `P_II`, a copy of the platform frame that the
6D platform closure welds to `P_I`.
"""),
    code("""
chains = paper.paper_chains(mech)
for c in chains:
    print(f"chain {c.name}: slider {c.slider} | upper crank {c.upper_crank} + {c.upper_coupling} | lower crank "
          f"{c.lower_crank} + {c.lower_coupling} | hinge {c.platform_hinge} | tool {c.tool_frame} "
          f"| {c.n_parameters} parameters")"""),
    md(r"""
## 2. Twenty poses, with the paper's "numerical forward kinematics"

Slider sets are drawn by IK of platform targets spread uniformly over the workspace box. The nominal machine's
closed-loop FK then gives every joint value at each set. The first 20 sets calibrate. The other 50 are held out
to judge the identified model at poses it has not seen.
"""),
    code("""
rng = np.random.default_rng(SEED)
actuators = workspace_actuators(mech, N_POSES + N_HOLDOUT, rng)
fk = ClosedLoopSolver(mech)
q_true = np.array([fk.forward(a, q_init=mech.home).q for a in actuators])
fit, held = slice(0, N_POSES), slice(N_POSES, None)
print(f"{'pose':>4}  {'sliders [m]':<36}chain B1 coordinates (m, rad)")
for k in range(4):
    print(f"{k:4d}  {str(np.round(actuators[k], 4)):<36}{np.round(chains[0].coordinates(q_true[k:k + 1])[0], 4)}")
print(f"... {len(actuators)} slider sets, {q_true.shape[1]} joint values each")"""),
    md(r"""
## 3. Preset errors (the paper's Table 1)

Section 6 builds each "actual" chain with three kinds of errors:

- $\delta t$ on every initial pose, $T^a(0) = T(0)\exp_6(\delta t)$ (eq. 34);
- $\delta s$ on every joint twist, re-orthonormalised so that each joint stays a pure rotation or translation (eq. 35);
- $\delta q$ on every joint variable, $q^a = q + \delta q$ (eq. 36).

The printed Table 1 is missing from the paper, so `PresetErrorScale` uses the orders of magnitude its text
implies: 1 mm, 1 mrad, $10^{-3}$ on the twists, and 1 mm or 1 mrad on the joint variables. Change `scale` to try others.
"""),
    code("""
scale = paper.PresetErrorScale()
preset = paper.preset_errors(chains, rng, scale)
print(scale)
print(f"\\n{'placement':<16}{'dt: v [mm]':<30}{'w [mrad]':<30}")
for p, dt in preset.placement.items():
    print(f"{p.name:<16}{str(np.round(dt[:3] * 1e3, 3)):<30}{str(np.round(dt[3:] * 1e3, 3)):<30}")
print(f"\\n{'joint':<10}{'ds x 1e3 (v; w)':<58}{'dq [mm or mrad]':>16}")
for name, ds in preset.twist_error.items():
    print(f"{name:<10}{str(np.round(ds * 1e3, 3)):<58}{preset.joint_offset[name] * 1e3:16.3f}")"""),
    md(r"""
## 4. The actual chains and their measured poses (eq. 37)

`actual_chain_poses` evaluates each actual chain,
$g_i = T^a_{B,1}(0) e^{\hat s^a_1 q^a_1} \cdots e^{\hat s^a_n q^a_n} T^a_{n,P}(0)$, at the true joint values. Its
tool pose is what the tracker measures for that chain. The two actual chains carry independent errors, so their end
poses differ. The paper's simulation does not close the loop, and neither does this step. The loop is closed in
section 8.
"""),
    code("""
truth = {c.name: paper.actual_chain_poses(c, mech.model, preset, q_true) for c in chains}
print(HEADER)
for c in chains:
    print(row(f"nominal chain {c.name} vs actual chain {c.name}", pose_differences(chain_poses(c, mech.model, q_true), truth[c.name])))
print(row("actual chain B1 vs actual chain B3", pose_differences(truth["B1"], truth["B3"])))"""),
    md(r"""
## 5. The error model and what the data can identify

Per pose and per chain, $y_i = \log_6(g_{meas}\, g_i(q)^{-1}) \approx J_i x_i$ (eq. 18-20). $J_i$ is the
$6 \times 42$ error Jacobian of eq. (19). Its columns are the right-multiplied errors on the chain's seven initial
poses, with rows in WORLD. `two_chain_error_model` stacks both chains over the poses as
$[y_1; y_2] = \operatorname{blockdiag}(J_1, J_2)\,[x_1; x_2]$ (eq. 31). Eq. (21) as printed sums the two chains'
predictions of one measured error, $[J_1, J_2]$ against $Y = y_1 = y_2$. The stacked form instead asks each chain
to reproduce the measurement on its own, which is the paper's objective (13). The module docstring argues the
choice.

Rank analysis (`two_chain_identifiability`, pivoted QR of the noise-weighted Jacobian):

- **24 per chain**, not the $4r + 2p + 6 = 28$ that 5 revolute and 1 prismatic joints would give. A
  parallelogram's crank and coupling joint always turn together, so the data only see a 1-DoF circular
  translation, with 6 identifiable parameters instead of 8. That gives 2 (slider) + 6 + 6 (parallelograms) +
  4 (hinge) + 6 (tool) = 24.
- **48 stacked.** Each chain keeps its own copy of the base and platform errors. The paper's bound of 34 counts the
  machine once. The literal eq. (21) has fewer independent columns, but they are sums of the two chains' errors.
"""),
    code("""
measured_fit = {c.name: truth[c.name][fit] for c in chains}
system = paper.two_chain_error_model(mech.model, chains, q_true[fit], [measured_fit[c.name] for c in chains])
print(f"y: {system.y.shape} (poses x [v1; w1; v2; w2]), J: {system.jacobian.shape}, "
      f"{len(system.parameter_names)} parameters, e.g. {system.parameter_names[:2]}")
print("first poses, |v| [m] and |w| [rad] of y_1, y_2:")
for k in range(3):
    y = system.y[k].reshape(2, 2, 3)
    print(f"  pose {k}: " + "  ".join(f"|v{i + 1}| {np.linalg.norm(y[i, 0]):.2e} |w{i + 1}| {np.linalg.norm(y[i, 1]):.2e}"
                                      for i in range(2)))

ident = paper.two_chain_identifiability(mech, q_true[fit])
print(f"\\nparameters {ident.n_parameters}; rank per chain {dict(ident.rank_per_chain)}; stacked {ident.rank_stacked}; "
      f"literal eq. (21) {ident.rank_literal_eq21}; paper's bound 4r + 2p + 6 = {ident.paper_bound}")"""),
    md(r"""
## 6. Identification (section 5)

`calibrate_two_chains` linearises at the current model and solves the weighted least squares of eq. (32) over the
identifiable parameters. It then updates every initial pose, $T(0) \leftarrow T(0)\exp_6(X)$ (eq. 33), and repeats
until $\lVert X \rVert$, or the pose change it causes, falls below the tolerance. `solver="recursive"` processes one
pose at a time, as the paper does. `"batch"` solves the whole stack at once. Both give the same update up to
rounding. Over the iterations, though, rounding can drift along combinations the data barely see: the identified
$\delta t$ may then differ while the predicted poses agree. The tracker's position and orientation noise weight
the rows at the tool point.

The parameters are selected again at the converged model, and the iteration resumes if the rank has grown. In
the nominal geometry each parallelogram's two axes are exactly parallel and read at exactly coupled angles, which
hides 4 combinations per chain. On the fitted model the axes tilt slightly and those combinations become weakly
visible, so the 48 estimated parameters become 56, and $\lVert X \rVert$ jumps once at the restart.
"""),
    code("""
cal = paper.calibrate_two_chains(mech, q_true[fit], measured_fit, solver="recursive")
print(f"{cal.iterations} iterations, converged: {cal.converged}, {cal.base.rank} parameters estimated")
print("||X|| per iteration: " + ", ".join(f"{x:.1e}" for x in cal.step_norms))
print()
print(HEADER)
for c in chains:
    print(row(f"chain {c.name}, calibration poses, before", cal.residual_before[c.name]))
    print(row(f"chain {c.name}, calibration poses, after", cal.residual_after[c.name]))
for c in chains:
    before = pose_differences(chain_poses(c, mech.model, q_true[held]), truth[c.name][held])
    after = pose_differences(cal.predict(c.name, q_true[held]), truth[c.name][held])
    print(row(f"chain {c.name}, held-out poses, before", before))
    print(row(f"chain {c.name}, held-out poses, after", after))

batch = paper.calibrate_two_chains(mech, q_true[fit], measured_fit, solver="batch")
d_dt = max(np.abs(batch.deltas[p] - cal.deltas[p]).max() for p in cal.deltas)
d_pose = max(max(e.position.max(), e.rotation.max()) for e in
             (pose_differences(batch.predict(c.name, q_true[held]), cal.predict(c.name, q_true[held])) for c in chains))
print(f"\\nbatch vs recursive solver ({batch.iterations} vs {cal.iterations} iterations): held-out poses differ by at most "
      f"{d_pose:.1e} (m or rad), the identified dt by at most {d_dt:.1e}")"""),
    md(r"""
With exact data the calibrated chains reproduce the actual ones to rounding, at the held-out poses too. The preset
twist and joint-variable errors need no parameters of their own. A tilted or shifted twist is the nominal twist
conjugated by a fixed transform, and an offset is a motion along the joint's own twist. Both merge into the
neighbouring initial poses, which is the premise of the local POE model (eq. 11).

**Fig. 4** of the paper plots the orientation and position errors per calibration pose, before and after. The
plot below is for chain B1 (log scale).
"""),
    code("""
figure = plot_pose_errors_before_after(cal.residual_before["B1"], cal.residual_after["B1"], OUT / "02_fig4_exact.png",
                                       title="Chain B1, exact data: pose error before and after calibration")
display(Image(filename=str(figure), width=640))"""),
    md(r"""
## 7. The whole simulation in one call, then with measurement noise

`paper_study` runs sections 2-6 above from one seed, drawing in the same order. Without noise it should print the
same held-out numbers as the cell above. With `SensorNoise` the tracker perturbs the measured poses (10 µm,
20 µrad) and the joint readings get encoder noise (1 µm on the sliders, 10 µrad on the other joints). The
identification then stops at the noise level, as in the paper's Fig. 4.
"""),
    code("""
exact = paper.paper_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT)
noisy = paper.paper_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT, noise=paper.SensorNoise())
print(noisy.noise)
print(HEADER)
for label, result in (("exact", exact), ("noisy", noisy)):
    if result.failure:
        print(f"{label}: calibration failed: {result.failure}")
        continue
    for name, errors in result.holdout_poses.items():
        print(row(f"{label}, chain {name}, held-out, before", errors.before))
        print(row(f"{label}, chain {name}, held-out, after", errors.after))"""),
    code("""
b1 = noisy.calibration_poses["B1"]
figure = plot_pose_errors_before_after(b1.before, b1.after, OUT / "02_fig4_noisy.png",
                                       title="Chain B1, 20 noisy poses: pose error before and after calibration")
display(Image(filename=str(figure), width=640))"""),
    md(r"""
## 8. Passive angles without sensors (section 4)

To save two encoders, the paper computes the lower-crank angles $q_{13}, q_{23}$ from the other readings. The feet
$A_1, A_2$ (eq. 22-24) must stay $a$ apart (eq. 25-26), and Newton's recursion $q \leftarrow q + J^{-1}\delta d$
(eq. 29-30) solves for them. That is one equation in two unknowns, so $J$ is $1 \times 2$ and only a
pseudo-inverse applies. The recursion then converges to *some* point of the solution curve, the one nearest the
initial guess, and not necessarily to the true angles. `estimate_lower_crank_angles` offers three methods:

- `"distance"`: the paper's recursion, with the pseudo-inverse;
- `"platform"`: Gauss-Newton on the platform weld $P_I = P_{II}$ (4 enforced rows, 2 unknowns), from the same readings;
- `"sliders"`: the full closure solve (closed-loop FK) from the slider readings alone.

Below, all three are compared with the true angles. On this nominal machine the true angles are the closure solve
itself. The second table shows what each source of $q_{i3}$ does to the calibration.
"""),
    code("""
model = mech.model
q_fit = q_true[fit]
print(f"{'method':<10}{'max |err q13| [rad]':>20}{'max |err q23| [rad]':>20}{'mean iterations':>17}{'max residual':>14}")
for method in ("distance", "platform", "sliders"):
    est = paper.estimate_lower_crank_angles(mech, q_fit, method=method)
    true = q_fit[:, [model.idx_qs[model.getJointId(j)] for j in est.joints]]
    err = np.abs(est.angles - true).max(axis=0)
    print(f"{method:<10}{err[0]:20.2e}{err[1]:20.2e}{est.iterations.mean():17.1f}{est.residual.max():14.1e}")

print()
print(HEADER)
for source in ("sensor", "distance", "platform"):
    for noise in (None, paper.SensorNoise()):
        result = paper.paper_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT, passive_from=source, noise=noise)
        label = f"q_i3 from {source}, {'noisy' if noise else 'exact'}"
        if result.failure:
            print(f"{label:<46}calibration failed: {result.failure[:60]}")
        else:
            print(row(f"{label}, B1 held-out after", result.holdout_poses["B1"].after))"""),
    md(r"""
## 9. The paper's method on the real closed-chain machine

So far each actual chain was its own serial mechanism. `closed_chain_study` instead draws one closed-chain
machine with `simulate_study`: errors on every joint placement, every parallelogram bar, the B2/B4 links and the
closure frames. The data are what a tracker and encoders would record on it. Both chains are fitted to the
measured pose of `P_I`. The held-out errors are taken against the machine's own platform at the same slider values:

| row | what is predicted |
|---|---|
| `nominal` | the uncalibrated nominal machine (closed-loop FK) |
| `sensors_before/after` | the paper's chain B1 with *every* passive joint read by a sensor, before and after calibration |
| `second_chain_before/after` | the same for chain B3. Its end `P_II` does not follow `P_I` in roll and pitch on this machine |
| `sliders_only` | the calibrated chain B1 at the passive angles the nominal closure solve gives from the sliders, so no passive sensors |
| `calibrated_tree` | chain B1's identified placements written into the tree, closed-loop FK |
| `closed_loop` | `calibrate_closed_loop` on the same slider readings and tracker poses |
"""),
    code("""
studies = {"exact": paper.closed_chain_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT),
           "noisy": paper.closed_chain_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT, noise=paper.SensorNoise())}
fields = ("nominal", "sensors_before", "sensors_after", "second_chain_before", "second_chain_after",
          "sliders_only", "calibrated_tree", "closed_loop")
print(f"{'held-out pose error, mean':<28}" + "".join(f"{k + ' pos [m]':>17}{k + ' rot [rad]':>17}" for k in studies))
for name in fields:
    cells = []
    for result in studies.values():
        e = getattr(result, name)
        cells.append(f"{'n/a':>17}{'n/a':>17}" if e is None else f"{e.position_mean:17.2e}{e.rotation_mean:17.2e}")
    print(f"{name:<28}" + "".join(cells))
for label, result in studies.items():
    cl = result.closed_loop_calibration
    print(f"{label}: both chains' calibrated placements assemble as one tree: {result.both_chains_assemble}; "
          f"closed-loop calibration identified {cl.base.rank} of {len(cl.parameters)} parameters")
print("lower-crank estimates at the held-out poses, max |error| [rad]: "
      + ", ".join(f"{m} {np.abs(e).max():.1e}" for m, e in studies["exact"].crank_error.items()))"""),
    md(r"""
The same closed-loop calibration, called directly. `simulate_study` with the same seed and size draws the same
machine and slider sets. The result therefore matches the `closed_loop` row (exact data) up to where
Levenberg-Marquardt stops: on exact data its cost test ends the fit at the 0.1-1 µm level, far below the
tracker noise that weights the residual. `calibrate_closed_loop` needs
only the slider readings and the tracker poses. It differentiates the platform pose through the closures
(implicit function theorem), so it needs no passive-joint sensor. Notebook 03 covers it in detail.
"""),
    code("""
study = simulate_study(mech, n_poses=N_POSES, n_holdout=N_HOLDOUT, seed=SEED)
closed = calibrate_closed_loop(mech, study.measurements)
print(HEADER)
print(row("nominal machine, held-out", pose_errors(mech, study.truth, study.holdout_actuators)))
print(row("calibrate_closed_loop, held-out", pose_errors(closed.mechanism, study.truth, study.holdout_actuators)))"""),
    md(r"""
**Reading the tables.** Once every passive joint is read, the paper's serial model reproduces chain B1 of the
closed machine. Its accuracy comes from the passive sensors, though, not from the model. With passive angles
computed from the sliders through the nominal closures (`sliders_only`), the calibrated chain inherits the
nominal geometry's errors and improves little on the uncalibrated machine. Writing one chain's identified
placements into the tree does not help either. This machine measures only its sliders, so it needs the
closed-loop model, which identifies the closure geometry itself.
"""),
]


# ==================================================================================================
# 03: closed-loop calibration and compensation
# ==================================================================================================

NB03 = [
    md(r"""
# 03 · Closed-loop calibration from slider readings and tracker poses, then compensation

The paper's method (notebook 02) needs a sensor on every joint of its two chains. This machine measures only its
four sliders. Here the calibration uses what such a machine provides: the **slider readings** and the **tracker
pose** of the platform frame `P_I` at $N$ poses.

**Error model** (`ClosedLoopErrorModel`). A right-multiplied error $T(0) \leftarrow T(0)\exp_6(\delta t)$
(eq. 33) sits on every joint placement of the tree and on every frame used by a closure or by the measurement. Each
$\delta t = [v;\ \omega]$ [m, rad] is expressed in the placement's own frame.

**Sensitivity.** With the sliders fixed, the passive joints follow the closures. Implicit differentiation of
$r_c(q, p) = 0$ gives $\partial q_{passive}/\partial p = -J_{c,passive}^{-1}\,\partial r_c/\partial p$ (a
16 × 16 solve). The platform twist is then $\partial \xi_P/\partial p = X_P + J_{P,passive}\,\partial q_{passive}/\partial p$
(WORLD). $X_P$ comes from Pinocchio's kinematic regressor, the columns of eq. (17).

**Residual** per pose: $e = [p_{model} - p_{meas};\ \log_3(R_{meas}^\top R_{model})]$. Position is in $B$ [m],
orientation in the platform frame [rad]. It is whitened by the tracker noise and minimised by Levenberg-Marquardt
over the identifiable ("base") parameters, which a column-pivoted QR selects once at the start.

Then: the held-out accuracy against its predicted floor, the compensation of commands (paper section 7, Fig. 6),
saving and reloading the calibrated machine, and a meshcat scene.
"""),
    code(SETUP + """

from collections import Counter

from IPython.display import IFrame, Image, display

from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors, predicted_pose_std
from m3t1r.compensation import compensate, compensation_accuracy, workspace_targets
from m3t1r.model.description import Mechanism
from m3t1r.errors import PoorExcitationWarning
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.app.plots import plot_pose_errors_before_after
from m3t1r.calibration.simulation import simulate_study
from m3t1r.app.scene import comparison_views
from m3t1r.app.static_page import write_static_html

SEED, N_POSES, N_HOLDOUT = 0, 50, 200
mech = Mechanism.load()

HEADER = f"{'':<40}{'pos mean [um]':>14}{'pos max [um]':>13}{'rot mean [urad]':>16}{'rot max [urad]':>15}"


def row(label, position, rotation) -> str:
    return (f"{label:<40}{np.mean(position) * 1e6:14.1f}{np.max(position) * 1e6:13.1f}"
            f"{np.mean(rotation) * 1e6:16.1f}{np.max(rotation) * 1e6:15.1f}")"""),
    md(r"""
## 1. A simulated machine and its measurements

`simulate_study` draws the "actual" machine. It puts errors with $\sigma$ = 1 mm and 1 mrad on every placement,
then drives it to `N_POSES` slider sets spread over the workspace and records what the instruments would read. The
tracker gets 10 µm in position and 20 µrad in orientation (right-multiplied), and the slider encoders 1 µm
(`TrackerNoise()`). `N_HOLDOUT` further slider sets, never used for fitting, judge the result.
"""),
    code("""
noise = TrackerNoise()
study = simulate_study(mech, n_poses=N_POSES, n_holdout=N_HOLDOUT, seed=SEED, noise=noise)
measurements = study.measurements
print(noise)
print(f"{len(measurements)} calibration poses: slider readings {measurements.actuators.shape} [m] and "
      f"{len(measurements.poses)} tracker poses of '{mech.platform_frame}'; {len(study.holdout_actuators)} held-out slider sets")
print(f"\\n{'pose':>4}  {'slider readings [m]':<38}{'measured x, y, z [m]':<30}{'yaw [rad]':>10}")
for k in range(4):
    g = measurements.poses[k]
    print(f"{k:4d}  {str(np.round(measurements.actuators[k], 5)):<38}{str(np.round(g.translation, 5)):<30}"
          f"{math.atan2(g.rotation[1, 0], g.rotation[0, 0]):10.4f}")"""),
    md(r"""
## 2. The parameters

Placements: the 20 joint placements of the tree (each $T_{k-1,k}(0)$) plus the 14 frames that the 7 closures and
the measurement use. A parameter is named `placement.dt[k]`, with $k = 0..5$ for $v_x, v_y, v_z, \omega_x, \omega_y, \omega_z$.
"""),
    code("""
error_model = ClosedLoopErrorModel(mech)
kinds = Counter(p.kind for p in error_model.placements)
print(f"{error_model.n_parameters} parameters = 6 x ({kinds['joint']} joint placements + {kinds['frame']} frames)")
print("frames:", ", ".join(p.name for p in error_model.placements if p.kind == "frame"))"""),
    md(r"""
## 3. Calibration

`calibrate_closed_loop(nominal, measurements, noise)` starts from the nominal machine. It first checks that the
poses excite every parameter the model can identify, and raises `IdentificationError` otherwise. The result holds
the calibrated `mechanism` (its home re-assembled), the identified `parameters` with their `std`, the `base`
set, and the RMS of the measurement residual before and after.

If the model fits down to the noise, the residual RMS after the fit should approach $\sqrt{3}\,\sigma$ per pose,
shrunk by $\sqrt{1 - \text{rank}/(6N)}$ because the fit absorbs part of the noise.
"""),
    code("""
t0 = time.perf_counter()
cal = calibrate_closed_loop(mech, measurements, noise)
seconds = time.perf_counter() - t0
shrink = math.sqrt(1 - cal.base.rank / (6 * len(measurements)))
print(f"{seconds:.2f} s; Levenberg-Marquardt: {cal.lm.iterations} iterations, stopped by its '{cal.lm.termination}' test")
print(f"identifiable (base) parameters: {cal.base.rank} of {len(cal.parameters)}, condition number "
      f"{cal.base.condition_number:.2g}; {len(cal.base.zero_columns)} parameters have no effect on the measurements")
print(f"residual RMS before: {cal.rms_before[0] * 1e6:9.1f} um {cal.rms_before[1] * 1e6:9.1f} urad")
print(f"residual RMS after : {cal.rms_after[0] * 1e6:9.1f} um {cal.rms_after[1] * 1e6:9.1f} urad")
print(f"noise floor (approx): {math.sqrt(3) * noise.position * shrink * 1e6:8.1f} um "
      f"{math.sqrt(3) * noise.rotation * shrink * 1e6:9.1f} urad")"""),
    md(r"""
**Which parameters are identifiable?** Many of the 204 errors look exactly like others in the measurements, and
some leave no trace at all. A turn about a revolute joint's own axis is just a joint offset. Consecutive placements
can trade errors. A closure frame's error along a residual row that is not enforced changes nothing. The pivoted QR
keeps one parameter per independent combination and leaves the others at zero. The identified values are
therefore a *representative* of the truth, not the truth itself. They reproduce the machine's motion, which is all
that prediction and compensation need. The table lists which components each placement keeps. The second table
compares the largest identified values with the simulated truth. Large values of opposite sign and with large std
on neighbouring placements are such trades, since only their combination is pinned down.
"""),
    code("""
LABELS = ("vx", "vy", "vz", "wx", "wy", "wz")
kept = {}
for name in cal.base.names:
    placement, k = name[:-1].split(".dt[")
    kept.setdefault(placement, []).append(int(k))
print(f"{'placement':<16}{'kind':<7}{'kept':>5}  components")
for p in error_model.placements:
    components = kept.get(p.name, [])
    print(f"{p.name:<16}{p.kind:<7}{len(components):5d}  {' '.join(LABELS[k] for k in components)}")
true_value = dict(zip(error_model.names, study.errors))  # the simulated machine's errors, same order
print(f"\\n{'largest identified':<20}{'value':>9}{'std':>9}{'truth':>9}   [mm or mrad]")
for n in sorted(cal.base.names, key=lambda n: -abs(cal.parameters[n]))[:6]:
    print(f"{n:<20}{cal.parameters[n] * 1e3:+9.2f}{cal.std[n] * 1e3:9.2f}{true_value[n] * 1e3:+9.2f}")"""),
    md(r"""
## 4. Accuracy on held-out poses, and its predicted floor

`pose_errors(a, b, sliders)` drives two machines with the same sliders and returns the per-pose position distance
[m] and rotation angle [rad] of their platforms. Held-out poses use exact slider values, so they measure the model,
not the instruments.

`predicted_pose_std(cal, sliders)` propagates the base-parameter covariance $\sigma^2 (J^\top W J)^{-1}$ through
the platform sensitivity. The square root of the trace of the $3 \times 3$ position block is the expected RMS of
the position error norm. The RMS of the actual errors should land close to it.
"""),
    code("""
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
print(f"\\nheld-out RMS, actual vs predicted: position {rms(after.position) * 1e6:.1f} vs {rms(predicted.position) * 1e6:.1f} um, "
      f"rotation {rms(after.rotation) * 1e6:.1f} vs {rms(predicted.rotation) * 1e6:.1f} urad")"""),
    code("""
figure = plot_pose_errors_before_after(rows["held-out poses, nominal model"], after, OUT / "03_holdout_before_after.png",
                                       title="Held-out poses: platform error vs the actual machine")
display(Image(filename=str(figure), width=640))"""),
    md(r"""
**How many poses?** The same calibration on the first $n$ poses. With too few poses, or poses too close together,
the kept set becomes ill-conditioned and a `PoorExcitationWarning` says so.
"""),
    code("""
print(f"{'poses':>5}{'held-out pos mean [um]':>24}{'predicted RMS [um]':>20}{'condition':>12}  warning")
for n in (20, 30, 40, N_POSES):
    subset = PoseMeasurements(measurements.actuators[:n], measurements.poses[:n])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PoorExcitationWarning)
        fitted = cal if n == N_POSES else calibrate_closed_loop(mech, subset, noise)
    e = pose_errors(fitted.mechanism, study.truth, held[:50])
    std = predicted_pose_std(fitted, held[:50])
    flagged = any(issubclass(w.category, PoorExcitationWarning) for w in caught)
    print(f"{n:5d}{e.position_mean * 1e6:24.1f}{rms(std.position) * 1e6:20.1f}{fitted.base.condition_number:12.2g}  "
          f"{'poor excitation' if flagged else ''}")"""),
    md(r"""
## 5. Compensation (paper section 7, Fig. 6)

The controller knows only the nominal model. To put the real platform at a target $T_{co}$:

1. IK of the **calibrated** model gives the sliders $q^c$ that reach $T_{co}$ on the machine as identified;
2. FK of the **nominal** model at $q^c$ gives $T_{cp}$, the pose to send. The controller's own nominal IK of
   $T_{cp}$ returns $q^c$.

A controller that takes slider commands uses `actuators` ($q^c$) directly. One that takes poses uses
`command_targets` ($T_{cp}$ as $x, y, z, \theta$). Only position and yaw can be commanded. Roll and pitch are whatever
the geometry gives, and are reported in `tilt`. The batch runs as a path, each solve warm-started from the previous
one. Targets that fail (out of reach, or a slider beyond its limit) are listed in `failures` rather than clipped.
"""),
    code("""
targets = workspace_targets(100, np.random.default_rng(SEED + 1))
commands = compensate(mech, cal.mechanism, targets)
print(f"{commands.n_targets} targets, {len(commands.indices)} compensated, {len(commands.failures)} failed; "
      f"max |tilt| {commands.max_tilt * 1e3:.1f} mrad; mean IK steps {commands.iterations.mean():.1f}")
print(f"\\n{'target T_co x, y, z, theta':<36}{'q^c sliders [m]':<40}{'T_cp x, y, z, theta':<36}{'tilt [mrad]':<16}")
for k in range(5):
    print(f"{str(np.round(targets[commands.indices[k]], 4)):<36}{str(np.round(commands.actuators[k], 4)):<40}"
          f"{str(np.round(commands.command_targets[k], 4)):<36}{str(np.round(commands.tilt[k] * 1e3, 1)):<16}")"""),
    md(r"""
`compensation_accuracy` simulates both ways of driving the actual machine to the targets. *Before*: the sliders
come from nominal IK. *After*: they are the compensated $q^c$. The errors are the actual platform's distance to
the target position, and its yaw error.
"""),
    code("""
accuracy = compensation_accuracy(mech, cal.mechanism, study.truth, targets)
print(f"{len(accuracy.indices)} of {accuracy.n_targets} targets evaluated")
print(f"{'':<24}{'pos mean [um]':>14}{'pos max [um]':>13}{'pos rms [um]':>13}{'yaw mean [urad]':>16}{'yaw max [urad]':>15}")
for label, e in (("nominal commands", accuracy.before), ("compensated commands", accuracy.after)):
    print(f"{label:<24}{e.position_mean * 1e6:14.1f}{e.position_max * 1e6:13.1f}{e.position_rms * 1e6:13.1f}"
          f"{e.yaw_mean * 1e6:16.1f}{e.yaw_max * 1e6:15.1f}")"""),
    md(r"""
## 6. Saving and reloading the calibrated machine

`Mechanism.save(urdf, closures)` writes the calibrated machine as a new URDF and closures pair. The URDF is the
source URDF with every joint `<origin>` rewritten from the identified model, so visuals, limits and names are kept.
The closures file receives the re-assembled home. `Mechanism.load` reads the pair back with full validation, and
any tool that takes a URDF plus closures file can use it. Both writes are atomic and refuse to overwrite the
packaged nominal files.
"""),
    code("""
import xml.etree.ElementTree as ET

urdf, closures = OUT / "calibrated.urdf", OUT / "calibrated.closures.yaml"
cal.mechanism.save(urdf, closures)
reloaded = Mechanism.load(urdf, closures)
check = pose_errors(cal.mechanism, reloaded, held[:50])
print(f"wrote {urdf} and {closures}")
print(f"reloaded vs in-memory calibrated model: max platform difference {check.position.max():.1e} m, "
      f"{check.rotation.max():.1e} rad")

def origin(path, joint):
    element = ET.parse(path).getroot().find(f"joint[@name='{joint}']/origin")
    return element.get("xyz"), element.get("rpy")

print(f"\\n{'joint':<8}{'file':<11}{'origin xyz [m]':<52}rpy [rad]")
for joint in ("q12", "q14"):
    for label, path in (("nominal", mech.urdf_path), ("calibrated", urdf)):
        xyz, rpy = origin(path, joint)
        print(f"{joint:<8}{label:<11}{xyz:<52}{rpy}")"""),
    md(r"""
## 7. Nominal vs calibrated, in meshcat

The scene is recorded offline and written as one self-contained HTML page (no server). Both machines are posed by
IK at the same platform target. The nominal machine is drawn in its URDF colours and the calibrated machine in
translucent magenta, so the slider differences that compensation applies are visible. The measured platform
positions appear as yellow spheres.
"""),
    code("""
page = write_static_html(comparison_views(mech, cal.mechanism), OUT / "03_nominal_vs_calibrated.html",
                         pose=(0.5, 0.6, -0.1, 0.3), markers=study.measurements.poses)
print(f"wrote {page} ({page.stat().st_size / 1e6:.1f} MB); open it in a browser")
IFrame(src=str(page), width="100%", height=480)  # inline view in Jupyter; other front ends: open the file"""),
    md(r"""
**Things to try.** Change `SEED`, `N_POSES` or the `TrackerNoise` values. Pass `position_only=True` to
`simulate_study` to simulate a tracker that sees only a point on the platform, then compare the rank and the
held-out errors. Scale the machine's errors with `sigma_position` and `sigma_rotation`. Change the compensation
targets, for instance to `compensation.workspace_grid((5, 5, 3, 3))`, a serpentine grid.
"""),
]


# ==================================================================================================
# Writing
# ==================================================================================================

NOTEBOOKS = {
    "01_model_and_kinematics.ipynb": NB01,
    "02_paper_simulation_study.ipynb": NB02,
    "03_closed_loop_calibration_and_compensation.ipynb": NB03,
}


def build(cells: list[tuple[str, str]]) -> nbformat.NotebookNode:
    """A notebook without outputs, with deterministic cell ids."""
    made = []
    for k, (kind, source) in enumerate(cells):
        cell = new_markdown_cell(source) if kind == "markdown" else new_code_cell(source)
        cell.id = f"cell-{k:02d}"
        made.append(cell)
    nb = new_notebook(cells=made, metadata={"kernelspec": KERNELSPEC, "language_info": {"name": "python"}})
    nbformat.validate(nb)
    return nb


def main() -> int:
    for name, cells in NOTEBOOKS.items():
        path = HERE / name
        nbformat.write(build(cells), path)
        print(f"wrote {path.relative_to(HERE.parent)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
