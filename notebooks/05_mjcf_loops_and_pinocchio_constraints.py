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
# # 05 · Loops where they are published: MJCF in, Pinocchio constraint models out
#
# Simulator models often carry their loops as MJCF equality constraints: a `connect` pins a point of one body to
# another (a 3D closure), a `weld` fixes one body to another (6D). `Mechanism.load` reads such a file through
# Pinocchio's own MJCF parser: the equalities become closures, the `<actuator>` joints the actuated joints, the
# keyframe (or the reference configuration qpos0) the home. A small `NAME.closures.yaml` beside it names what the
# MJCF does not say: the platform frame, the task, the workspace.
#
# The other way round, `rigid_constraint_models` hands any machine's closures, nominal or calibrated, to
# Pinocchio as `RigidConstraintModel`s, so that its constrained algorithms (`constraintDynamics`) run on the
# calibrated geometry directly. This notebook does both on a spatial loop of seven hinges welded to the ground.

# %%
import tempfile
from pathlib import Path

import numpy as np
import pinocchio as pin

from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors
from m3t1r.calibration.simulation import PlacementErrorScale, simulate_study
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.constraint_models import constraint_residual, rigid_constraint_datas, rigid_constraint_models
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver

np.set_printoptions(precision=4, suppress=True, linewidth=110)
OUT = Path(tempfile.mkdtemp(prefix="m3t1r-notebook-05-"))
print("files written by this notebook go to", OUT)

# %% [markdown]
# ## An MJCF loop
#
# Seven hinges with skew axes; the last link is welded to the world where the reference configuration puts it
# (a `weld` without `relpose`, as in MuJoCo). One motor: 7 joints - 6 weld rows = 1 degree of freedom.

# %%
LINKS = [
    ("0 0 0.1", "0 0 0", "0 0 1"),
    ("0.2 0 0", "20 0 0", "0 1 0"),
    ("0.15 0.05 0", "0 15 30", "1 0 0.3"),
    ("0.1 0.1 0.05", "10 0 0", "0 0 1"),
    ("0 0.15 0", "0 -20 0", "0.2 1 0"),
    ("-0.1 0.1 0", "0 0 25", "1 0 0"),
    ("-0.05 0 -0.1", "15 10 0", "0 0.3 1"),
]
body = ""
for k, (pos, euler, axis) in reversed(list(enumerate(LINKS, start=1))):
    site = '<site name="platform" pos="0.02 0.03 0"/>' if k == 4 else ""
    body = (
        f'<body name="link{k}" pos="{pos}" euler="{euler}"><joint name="j{k}" axis="{axis}"/>'
        f'<geom type="sphere" size="0.02" mass="0.2"/>{site}{body}</body>'
    )
mjcf = OUT / "loop.xml"
mjcf.write_text(f"""<mujoco model="loop">
  <worldbody><body name="base">{body}</body></worldbody>
  <equality><weld name="ground" body1="link7"/></equality>
  <actuator><motor name="drive" joint="j1"/></actuator>
</mujoco>
""")
(OUT / "loop.closures.yaml").write_text(
    "platform_frame: platform\ntask: {position: [x]}\nworkspace: {actuators: {j1: [-0.3, 0.3]}}\n"
)
loop = Mechanism.load(mjcf)
print("closures:", [(c.name, c.type, c.rows) for c in loop.closures], "| actuated:", loop.actuated_joints)
assert loop.closures_document is not None  # an MJCF machine keeps the closures document it was built from
print("closure frames declared at the weld's ends:", loop.closures_document["frames"])
assert [(c.type, len(c.rows)) for c in loop.closures] == [("6D", 6)] and loop.actuated_joints == ("j1",)

# %% [markdown]
# ## Its kinematics close as Pinocchio's own MJCF constraint says
#
# Forward kinematics solves the six passive hinges; at every solution the weld as Pinocchio's parser made it
# (read independently, straight from the file) holds.

# %%
model, _, welds = pin.buildModelAndConstraintsFromMJCF(str(mjcf))
weld, data = welds[0], model.createData()
solver = ClosedLoopSolver(loop)
worst = 0.0
for angle in np.linspace(-0.3, 0.3, 13):
    q = solver.forward(np.array([angle])).q
    pin.forwardKinematics(model, data, q)
    relative = (data.oMi[weld.joint1_id] * weld.joint1_placement).actInv(
        data.oMi[weld.joint2_id] * weld.joint2_placement
    )
    worst = max(worst, float(np.abs(pin.log6(relative).vector).max()))
print(f"largest weld error of Pinocchio's MJCF constraint at 13 solutions: {worst:.1e}")
assert worst < 1e-9

# %% [markdown]
# ## Calibrate it, then hand the calibrated machine to Pinocchio
#
# A simulated campaign (0.1 mm / 0.1 mrad errors on every placement, noise-free tracker), calibrated; the
# calibrated machine's closure becomes a `RigidConstraintModel` (CONTACT_6D, both ends in Pinocchio's
# conventions) for `initConstraintDynamics` / `constraintDynamics`.

# %%
study = simulate_study(loop, n_poses=30, n_holdout=20, seed=2, errors=PlacementErrorScale(1e-4, 1e-4))
calibrated = calibrate_closed_loop(loop, study.measurements).mechanism
held_out = pose_errors(calibrated, study.truth, study.holdout_actuators)
print(f"held-out error of the calibrated machine: {held_out.position_max:.1e} m, {held_out.rotation_max:.1e} rad")
assert held_out.position_max < 1e-7

constraints = rigid_constraint_models(calibrated)
datas = rigid_constraint_datas(constraints)
print([(c.name, c.type, c.joint1_id, c.joint2_id) for c in constraints])
q = ClosedLoopSolver(calibrated).forward(np.array([0.2])).q
constraint_error = np.abs(constraint_residual(calibrated.model, constraints, q)).max()
print(f"Pinocchio's constraint error at an assembled pose: {constraint_error:.1e}")

# %% [markdown]
# ## Constrained dynamics keeps the calibrated loop closed
#
# With the loop moving (a velocity along its one motion) and some joint torques, Pinocchio's `constraintDynamics`
# gives accelerations under which the closure's second derivative vanishes: m3t1r's closure rows, differentiated
# twice along $q(t) = q + v t + a t^2 / 2$, stay at zero (a central difference, which leaves ~1e-6 of truncation;
# with $a = 0$ the same motion opens the loop at ~1 per unit time squared).

# %%
model = calibrated.model
data = model.createData()
pin.initConstraintDynamics(model, data, constraints, datas)
system = ClosureSystem(model, calibrated.closures)
v = 2.0 * np.linalg.svd(system.evaluate(q, True)[1])[2][-1]
tau = np.random.default_rng(0).normal(scale=0.05, size=model.nv)
a = pin.constraintDynamics(model, data, q, v, tau, constraints, datas)
step, now = 1e-4, system.evaluate(q, False)[0]


def closure_acceleration(acceleration: np.ndarray) -> np.ndarray:
    ahead, behind = (system.evaluate(q + s * v * step + 0.5 * acceleration * step**2, False)[0] for s in (1, -1))
    return (ahead - 2 * now + behind) / step**2


second, free = closure_acceleration(a), closure_acceleration(np.zeros(model.nv))  # free: the same motion, a = 0
print(f"closure acceleration with Pinocchio's a: {np.abs(second).max():.1e}; with a = 0: {np.abs(free).max():.1e}")
assert np.abs(second).max() < 1e-5 * np.abs(free).max()  # truncation of the difference: ~1e-6
