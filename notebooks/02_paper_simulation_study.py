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
# # 02 · The paper's calibration method, step by step (simulation study)
#
# This notebook reproduces the calibration of Zhang et al. (*Symmetry* 2020) in simulation with `m3t1r.paper`,
# one section of the paper at a time:
#
# - sec. 3, eq. (6), (11): each principal chain as a serial local-POE chain, every error lumped into its initial
#   poses $T(0)$ (`paper_chains`);
# - eq. (18)-(21), (31): $y_i = \log_6(g_{meas}\, g_i(q)^{-1}) = J_i x_i$, stacked over the poses
#   (`two_chain_error_model`, `two_chain_identifiability`);
# - sec. 5, eq. (32)-(33): least squares, then $T(0) \leftarrow T(0)\exp_6(X)$, iterated until
#   $\lVert X \rVert \to 0$ (`calibrate_two_chains`);
# - sec. 4, eq. (22)-(30): the lower-crank angles $q_{i3}$ from the foot distance $\lvert A_1A_2 \rvert = a$,
#   instead of a sensor (`estimate_lower_crank_angles`);
# - sec. 6, eq. (34)-(37), Table 1, Fig. 4: preset errors $\delta t, \delta s, \delta q$; 20 poses; errors before
#   and after (`preset_errors`, `actual_chain_poses`, `paper_study`).
#
# The last section applies the same method to the full closed-chain machine, where only the sliders are
# actuated and measured, and compares it with this project's closed-loop calibration (`calibrate_closed_loop`).
#
# Units: m and rad. Poses are the platform frame in the base frame $B$. Errors are right-multiplied,
# $T(0)\exp_6(\delta t)$ with $\delta t = [v;\ \omega]$. Pose errors, as in Fig. 4, are the position distance [m] and
# the rotation angle [rad] between two poses.

# %%
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pinocchio as pin
from IPython.display import Image, display

from m3t1r import paper
from m3t1r.app.plots import plot_pose_errors_before_after
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.simulation import simulate_study
from m3t1r.errors import PoorExcitationWarning
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import poe_forward
from m3t1r.model.workspace import workspace_actuators

# calibrate_two_chains re-selects its identifiable parameters on the fitted model and keeps weakly
# conditioned combinations on purpose (see its docstring), so this conditioning warning is expected.
warnings.filterwarnings("ignore", category=PoorExcitationWarning)

# Files written by this notebook go to a fresh temporary folder, never into the repository.
OUT = Path(tempfile.mkdtemp(prefix="m3t1r-notebook-02-"))
print(f"files written by this notebook: {OUT}")
np.set_printoptions(precision=4, suppress=True, linewidth=110)

SEED, N_POSES, N_HOLDOUT = 0, 20, 50  # the paper uses 20 calibration poses
mech = Mechanism.load()


def pose_differences(poses, references) -> PoseErrors:
    """Per pose: position distance [m] and rotation angle of R_ref^T R [rad], the quantities of Fig. 4."""
    position = [np.linalg.norm(g.translation - h.translation) for g, h in zip(poses, references)]
    rotation = [np.linalg.norm(pin.log3(h.rotation.T @ g.rotation)) for g, h in zip(poses, references)]
    return PoseErrors(np.array(position), np.array(rotation))


def chain_poses(chain, model, configurations):
    """Tool poses g_i(q) of a paper chain (eq. 6) at full configurations (N, nq)."""
    return [poe_forward(chain.serial, model, qc) for qc in chain.coordinates(configurations)]


HEADER = f"{'':<46}{'pos mean [m]':>13}{'pos max [m]':>13}{'rot mean [rad]':>15}{'rot max [rad]':>14}"


def row(label, e: PoseErrors) -> str:
    return (
        f"{label:<46}{e.position.mean():13.2e}{e.position.max():13.2e}{e.rotation.mean():15.2e}{e.rotation.max():14.2e}"
    )


# %% [markdown]
# ## 1. The paper's two chains
#
# The paper calibrates the machine as two serial chains, B1 → P and B3 → P, each read by sensors on every joint.
# `paper_chains` takes them from the description's `principal_chains`. Here each "equivalent" revolute joint
# $q_{i2}$, $q_{i3}$ is a parallelogram, so the chain holds six joints: slider, upper crank with its coupling, lower
# crank with its coupling, and platform hinge. Its seven initial poses $T_{0,1}(0), \dots, T_{6,P}(0)$ (eq. 6) each
# carry a 6-vector error, which gives 42 parameters per chain. Chain B3 ends at `P_II`, a copy of the platform frame
# that the 6D platform closure welds to `P_I`.

# %%
chains = paper.paper_chains(mech)
for c in chains:
    print(
        f"chain {c.name}: slider {c.slider} | upper crank {c.upper_crank} + {c.upper_coupling} | lower crank "
        f"{c.lower_crank} + {c.lower_coupling} | hinge {c.platform_hinge} | tool {c.tool_frame} "
        f"| {c.n_parameters} parameters"
    )
    assert c.n_parameters == 42  # 7 initial poses x 6

# %% [markdown]
# ## 2. Twenty poses, with the paper's "numerical forward kinematics"
#
# Slider sets are drawn by IK of platform targets spread uniformly over the workspace box. The nominal machine's
# closed-loop FK then gives every joint value at each set. The first 20 sets calibrate. The other 50 are held out
# to judge the identified model at poses it has not seen.

# %%
rng = np.random.default_rng(SEED)
actuators = workspace_actuators(mech, N_POSES + N_HOLDOUT, rng)
fk = ClosedLoopSolver(mech)
q_true = np.array([fk.forward(a, q_init=mech.home).q for a in actuators])
fit, held = slice(0, N_POSES), slice(N_POSES, None)
print(f"{'pose':>4}  {'sliders [m]':<36}chain B1 coordinates (m, rad)")
for k in range(4):
    print(f"{k:4d}  {str(np.round(actuators[k], 4)):<36}{np.round(chains[0].coordinates(q_true[k : k + 1])[0], 4)}")
print(f"... {len(actuators)} slider sets, {q_true.shape[1]} joint values each")

# %% [markdown]
# ## 3. Preset errors (the paper's Table 1)
#
# Section 6 builds each "actual" chain with three kinds of errors:
#
# - $\delta t$ on every initial pose, $T^a(0) = T(0)\exp_6(\delta t)$ (eq. 34);
# - $\delta s$ on every joint twist, re-orthonormalised so that each joint stays a pure rotation or translation
#   (eq. 35);
# - $\delta q$ on every joint variable, $q^a = q + \delta q$ (eq. 36).
#
# The printed Table 1 is missing from the paper, so `PresetErrorScale` uses the orders of magnitude its text
# implies: 1 mm, 1 mrad, $10^{-3}$ on the twists, and 1 mm or 1 mrad on the joint variables. Change `scale` to try
# others.

# %%
scale = paper.PresetErrorScale()
preset = paper.preset_errors(chains, rng, scale)
print(scale)
print(f"\n{'placement':<16}{'dt: v [mm]':<30}{'w [mrad]':<30}")
for p, dt in preset.placement.items():
    print(f"{p.name:<16}{str(np.round(dt[:3] * 1e3, 3)):<30}{str(np.round(dt[3:] * 1e3, 3)):<30}")
print(f"\n{'joint':<10}{'ds x 1e3 (v; w)':<58}{'dq [mm or mrad]':>16}")
for name, ds in preset.twist_error.items():
    print(f"{name:<10}{str(np.round(ds * 1e3, 3)):<58}{preset.joint_offset[name] * 1e3:16.3f}")

# %% [markdown]
# ## 4. The actual chains and their measured poses (eq. 37)
#
# `actual_chain_poses` evaluates each actual chain,
# $g_i = T^a_{B,1}(0) e^{\hat s^a_1 q^a_1} \cdots e^{\hat s^a_n q^a_n} T^a_{n,P}(0)$, at the true joint values. Its
# tool pose is what the tracker measures for that chain. The two actual chains carry independent errors, so their end
# poses differ. The paper's simulation does not close the loop, and neither does this step. The loop is closed in
# section 8.

# %%
truth = {c.name: paper.actual_chain_poses(c, mech.model, preset, q_true) for c in chains}
print(HEADER)
for c in chains:
    print(
        row(
            f"nominal chain {c.name} vs actual chain {c.name}",
            pose_differences(chain_poses(c, mech.model, q_true), truth[c.name]),
        )
    )
print(row("actual chain B1 vs actual chain B3", pose_differences(truth["B1"], truth["B3"])))
assert pose_differences(truth["B1"], truth["B3"]).position.min() > 1e-4  # independent errors: the ends disagree

# %% [markdown]
# ## 5. The error model and what the data can identify
#
# Per pose and per chain, $y_i = \log_6(g_{meas}\, g_i(q)^{-1}) \approx J_i x_i$ (eq. 18-20). $J_i$ is the
# $6 \times 42$ error Jacobian of eq. (19). Its columns are the right-multiplied errors on the chain's seven initial
# poses, with rows in WORLD. `two_chain_error_model` stacks both chains over the poses as
# $[y_1; y_2] = \operatorname{blockdiag}(J_1, J_2)\,[x_1; x_2]$ (eq. 31). Eq. (21) as printed sums the two chains'
# predictions of one measured error, $[J_1, J_2]$ against $Y = y_1 = y_2$. The stacked form instead asks each chain
# to reproduce the measurement on its own, which is the paper's objective (13). The module docstring argues the
# choice.
#
# Rank analysis (`two_chain_identifiability`, pivoted QR of the noise-weighted Jacobian):
#
# - **24 per chain**, not the $4r + 2p + 6 = 28$ that 5 revolute and 1 prismatic joints would give. A
#   parallelogram's crank and coupling joint always turn together, so the data only see a 1-DoF circular
#   translation, with 6 identifiable parameters instead of 8. That gives 2 (slider) + 6 + 6 (parallelograms) +
#   4 (hinge) + 6 (tool) = 24.
# - **48 stacked.** Each chain keeps its own copy of the base and platform errors. The paper's bound of 34 counts the
#   machine once. The literal eq. (21) has fewer independent columns, but they are sums of the two chains' errors.

# %%
measured_fit = {c.name: truth[c.name][fit] for c in chains}
system = paper.two_chain_error_model(mech.model, chains, q_true[fit], [measured_fit[c.name] for c in chains])
print(
    f"y: {system.y.shape} (poses x [v1; w1; v2; w2]), J: {system.jacobian.shape}, "
    f"{len(system.parameter_names)} parameters, e.g. {system.parameter_names[:2]}"
)
print("first poses, |v| [m] and |w| [rad] of y_1, y_2:")
for k in range(3):
    y = system.y[k].reshape(2, 2, 3)
    print(
        f"  pose {k}: "
        + "  ".join(
            f"|v{i + 1}| {np.linalg.norm(y[i, 0]):.2e} |w{i + 1}| {np.linalg.norm(y[i, 1]):.2e}" for i in range(2)
        )
    )

ident = paper.two_chain_identifiability(mech, q_true[fit])
print(
    f"\nparameters {ident.n_parameters}; rank per chain {dict(ident.rank_per_chain)}; stacked {ident.rank_stacked}; "
    f"literal eq. (21) {ident.rank_literal_eq21}; paper's bound 4r + 2p + 6 = {ident.paper_bound}"
)
assert dict(ident.rank_per_chain) == {"B1": 24, "B3": 24} and ident.rank_stacked == 48 and ident.paper_bound == 34

# %% [markdown]
# ## 6. Identification (section 5)
#
# `calibrate_two_chains` linearises at the current model and solves the weighted least squares of eq. (32) over the
# identifiable parameters. It then updates every initial pose, $T(0) \leftarrow T(0)\exp_6(X)$ (eq. 33), and repeats
# until $\lVert X \rVert$, or the pose change it causes, falls below the tolerance. `solver="recursive"` processes one
# pose at a time, as the paper does. `"batch"` solves the whole stack at once. Both give the same update up to
# rounding. Over the iterations, though, rounding can drift along combinations the data barely see: the identified
# $\delta t$ may then differ while the predicted poses agree. The tracker's position and orientation noise weight
# the rows at the tool point.
#
# The parameters are selected again at the converged model, and the iteration resumes if the rank has grown. In
# the nominal geometry each parallelogram's two axes are exactly parallel and read at exactly coupled angles, which
# hides 4 combinations per chain. On the fitted model the axes tilt slightly and those combinations become weakly
# visible, so the 48 estimated parameters become 56, and $\lVert X \rVert$ jumps once at the restart.

# %%
cal = paper.calibrate_two_chains(mech, q_true[fit], measured_fit, options=paper.TwoChainOptions(solver="recursive"))
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
    assert max(after.position.max(), after.rotation.max()) < 1e-12  # exact data: reproduced to rounding
assert cal.converged and cal.base.rank == 56  # 48, plus 4 per chain visible once the axes tilt

batch = paper.calibrate_two_chains(mech, q_true[fit], measured_fit, options=paper.TwoChainOptions(solver="batch"))
d_dt = max(np.abs(batch.deltas[p] - cal.deltas[p]).max() for p in cal.deltas)
d_pose = max(
    max(e.position.max(), e.rotation.max())
    for e in (pose_differences(batch.predict(c.name, q_true[held]), cal.predict(c.name, q_true[held])) for c in chains)
)
print(
    f"\nbatch vs recursive solver ({batch.iterations} vs {cal.iterations} iterations): "
    f"held-out poses differ by at most {d_pose:.1e} (m or rad), the identified dt by at most {d_dt:.1e}"
)
assert batch.converged and d_pose < 1e-12

# %% [markdown]
# With exact data the calibrated chains reproduce the actual ones to rounding, at the held-out poses too. The preset
# twist and joint-variable errors need no parameters of their own. A tilted or shifted twist is the nominal twist
# conjugated by a fixed transform, and an offset is a motion along the joint's own twist. Both merge into the
# neighbouring initial poses, which is the premise of the local POE model (eq. 11).
#
# **Fig. 4** of the paper plots the orientation and position errors per calibration pose, before and after. The
# plot below is for chain B1 (log scale).

# %%
figure = plot_pose_errors_before_after(
    cal.residual_before["B1"],
    cal.residual_after["B1"],
    OUT / "02_fig4_exact.png",
    title="Chain B1, exact data: pose error before and after calibration",
)
display(Image(filename=str(figure), width=640))

# %% [markdown]
# ## 7. The whole simulation in one call, then with measurement noise
#
# `paper_study` runs sections 2-6 above from one seed, drawing in the same order. Without noise it should print the
# same held-out numbers as the cell above. With `noise=TrackerNoise()` the tracker perturbs the measured poses
# (10 µm, 20 µrad) and the joint readings get encoder noise: 1 µm on the sliders (`TrackerNoise.actuator`) and
# 10 µrad on the other joints (`TwoChainStudyOptions.passive_encoder_noise`, by default
# `paper.PASSIVE_ENCODER_NOISE`). The identification then stops at the noise level, as in the paper's Fig. 4.

# %%
exact = paper.paper_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT)
noisy = paper.paper_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT, noise=TrackerNoise())
print(f"{noisy.noise}, passive joints' encoders {noisy.passive_encoder_noise} rad")
print(HEADER)
for label, result in (("exact", exact), ("noisy", noisy)):
    if result.failure:
        print(f"{label}: calibration failed: {result.failure}")
        continue
    for name, errors in result.holdout_poses.items():
        assert errors.after is not None  # calibrated (no failure)
        print(row(f"{label}, chain {name}, held-out, before", errors.before))
        print(row(f"{label}, chain {name}, held-out, after", errors.after))
assert not exact.failure and not noisy.failure
for name in exact.holdout_poses:
    e, n = exact.holdout_poses[name].after, noisy.holdout_poses[name].after
    assert e is not None and n is not None
    assert max(e.position.max(), e.rotation.max()) < 1e-12  # the same as the cell above
    assert n.position_mean < 5e-5 and n.rotation_mean < 5e-5  # stops at the noise level (10 um, 20 urad)

# %%
b1 = noisy.calibration_poses["B1"]
assert b1.after is not None
figure = plot_pose_errors_before_after(
    b1.before,
    b1.after,
    OUT / "02_fig4_noisy.png",
    title="Chain B1, 20 noisy poses: pose error before and after calibration",
)
display(Image(filename=str(figure), width=640))

# %% [markdown]
# ## 8. Passive angles without sensors (section 4)
#
# To save two encoders, the paper computes the lower-crank angles $q_{13}, q_{23}$ from the other readings. The feet
# $A_1, A_2$ (eq. 22-24) must stay $a$ apart (eq. 25-26), and Newton's recursion $q \leftarrow q + J^{-1}\delta d$
# (eq. 29-30) solves for them. That is one equation in two unknowns, so $J$ is $1 \times 2$ and only a
# pseudo-inverse applies. The recursion then converges to *some* point of the solution curve, the one nearest the
# initial guess, and not necessarily to the true angles. `estimate_lower_crank_angles` offers three methods:
#
# - `"distance"`: the paper's recursion, with the pseudo-inverse;
# - `"platform"`: Gauss-Newton on the platform weld $P_I = P_{II}$ (4 enforced rows, 2 unknowns), from the same
#   readings;
# - `"sliders"`: the full closure solve (closed-loop FK) from the slider readings alone.
#
# Below, all three are compared with the true angles. On this nominal machine the true angles are the closure solve
# itself. The second table shows what each source of $q_{i3}$ does to the calibration.

# %%
model = mech.model
q_fit = q_true[fit]
print(
    f"{'method':<10}{'max |err q13| [rad]':>20}{'max |err q23| [rad]':>20}{'mean iterations':>17}{'max residual':>14}"
)
for method in ("distance", "platform", "sliders"):
    est = paper.estimate_lower_crank_angles(mech, q_fit, method=method)
    true = q_fit[:, [model.idx_qs[model.getJointId(j)] for j in est.joints]]
    err = np.abs(est.angles - true).max(axis=0)
    print(f"{method:<10}{err[0]:20.2e}{err[1]:20.2e}{est.iterations.mean():17.1f}{est.residual.max():14.1e}")
    # the distance recursion lands elsewhere on the solution curve; the other two find the true angles
    assert err.max() > 1e-2 if method == "distance" else err.max() < 1e-9

print()
print(HEADER)
after_by_source = {}
for source in ("sensor", "distance", "platform"):
    for noise in (None, TrackerNoise()):
        result = paper.paper_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT, passive_from=source, noise=noise)
        label = f"q_i3 from {source}, {'noisy' if noise else 'exact'}"
        if result.failure:
            print(f"{label:<46}calibration failed: {result.failure[:60]}")
        else:
            b1_after = result.holdout_poses["B1"].after
            assert b1_after is not None  # calibrated (no failure)
            print(row(f"{label}, B1 held-out after", b1_after))
            after_by_source[source, noise is not None] = b1_after
for (source, noisy_data), e in after_by_source.items():
    if source == "distance":
        assert e.position_mean > 1e-3  # wrong crank angles spoil the calibration
    else:
        assert e.position_mean < (5e-5 if noisy_data else 1e-9)

# %% [markdown]
# ## 9. The paper's method on the real closed-chain machine
#
# So far each actual chain was its own serial mechanism. `closed_chain_study` instead draws one closed-chain
# machine with `simulate_study`: errors on every joint placement, every parallelogram bar, the B2/B4 links and the
# closure frames. The data are what a tracker and encoders would record on it. Both chains are fitted to the
# measured pose of `P_I`. The held-out errors are taken against the machine's own platform at the same slider values:
#
# | row | what is predicted |
# |---|---|
# | `nominal` | the uncalibrated nominal machine (closed-loop FK) |
# | `sensors_before/after` | the paper's chain B1, *every* passive joint read by a sensor, before and after |
# | `second_chain_before/after` | the same for chain B3 (its end `P_II` does not follow `P_I` in roll and pitch) |
# | `sliders_only` | calibrated B1 at the passive angles the nominal closure solve gives from the sliders |
# | `calibrated_tree` | chain B1's identified placements written into the tree, closed-loop FK |
# | `closed_loop` | `calibrate_closed_loop` on the same slider readings and tracker poses |

# %%
studies = {
    "exact": paper.closed_chain_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT),
    "noisy": paper.closed_chain_study(SEED, n_poses=N_POSES, n_holdout=N_HOLDOUT, noise=TrackerNoise()),
}
fields = (
    "nominal",
    "sensors_before",
    "sensors_after",
    "second_chain_before",
    "second_chain_after",
    "sliders_only",
    "calibrated_tree",
    "closed_loop",
)
print(f"{'held-out pose error, mean':<28}" + "".join(f"{k + ' pos [m]':>17}{k + ' rot [rad]':>17}" for k in studies))
for name in fields:
    cells = []
    for chain_study in studies.values():
        e = getattr(chain_study, name)
        cells.append(f"{'n/a':>17}{'n/a':>17}" if e is None else f"{e.position_mean:17.2e}{e.rotation_mean:17.2e}")
    print(f"{name:<28}" + "".join(cells))
for label, chain_study in studies.items():
    cl = chain_study.closed_loop_calibration
    assert cl is not None
    print(
        f"{label}: both chains' calibrated placements assemble as one tree: {chain_study.both_chains_assemble}; "
        f"closed-loop calibration identified {cl.base.rank} of {len(cl.parameters)} parameters"
    )
print(
    "lower-crank estimates at the held-out poses, max |error| [rad]: "
    + ", ".join(f"{m} {np.abs(e).max():.1e}" for m, e in studies["exact"].crank_error.items())
)
for label, chain_study in studies.items():
    nominal = chain_study.nominal.position_mean
    assert chain_study.calibrated_tree is not None and chain_study.closed_loop is not None
    assert chain_study.sensors_after.position_mean < (5e-5 if label == "noisy" else 1e-12)  # every passive joint read
    assert chain_study.sliders_only.position_mean > nominal / 2  # improves little on the nominal machine
    assert chain_study.calibrated_tree.position_mean > nominal / 2  # does not help either
    assert chain_study.closed_loop.position_mean < (1e-4 if label == "noisy" else 1e-5)  # the closed-loop model

# %% [markdown]
# The same closed-loop calibration, called directly. `simulate_study` with the same seed and size draws the same
# machine and slider sets. The result therefore matches the `closed_loop` row (exact data) up to where
# Levenberg-Marquardt stops: on exact data its cost test ends the fit at the 0.1-1 µm level, far below the
# tracker noise that weights the residual. `calibrate_closed_loop` needs
# only the slider readings and the tracker poses. It differentiates the platform pose through the closures
# (implicit function theorem), so it needs no passive-joint sensor. Notebook 03 covers it in detail.

# %%
study = simulate_study(mech, n_poses=N_POSES, n_holdout=N_HOLDOUT, seed=SEED)
closed = calibrate_closed_loop(mech, study.measurements)
print(HEADER)
closed_errors = pose_errors(closed.mechanism, study.truth, study.holdout_actuators)
print(row("nominal machine, held-out", pose_errors(mech, study.truth, study.holdout_actuators)))
print(row("calibrate_closed_loop, held-out", closed_errors))
exact_closed_loop = studies["exact"].closed_loop
assert exact_closed_loop is not None
assert abs(closed_errors.position_mean - exact_closed_loop.position_mean) < 1e-6  # the same fit

# %% [markdown]
# **Reading the tables.** Once every passive joint is read, the paper's serial model reproduces chain B1 of the
# closed machine. Its accuracy comes from the passive sensors, though, not from the model. With passive angles
# computed from the sliders through the nominal closures (`sliders_only`), the calibrated chain inherits the
# nominal geometry's errors and improves little on the uncalibrated machine. Writing one chain's identified
# placements into the tree does not help either. This machine measures only its sliders, so it needs the
# closed-loop model, which identifies the closure geometry itself.
