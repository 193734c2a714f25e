"""Closed-loop error model (`m3t1r.calibration.error_model`): sensitivities and parameter layout.

The platform sensitivities (pose, twist Jacobian, passive sensitivities, closure Jacobian) are
checked against central differences of the perturbed machine re-assembled by
`ClosedLoopSolver.forward` (perturbed with `poe.perturb` directly, independently of the module's
own parameter mapping), on the M machine along random directions over every parameter and on a
five-bar column by column; column subsets against the full computation; the parameter layout,
`deltas` / `perturbed` and `has_own_placement` on every kind of frame.
"""

import dataclasses

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.error_model import ClosedLoopErrorModel, PlatformSensitivities, has_own_placement
from m3t1r.errors import InvalidInputError
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import Placement, perturb
from m3t1r.model.workspace import workspace_actuators

STEP = 1e-6


def _passive_sensitivities(sensitivities: PlatformSensitivities) -> np.ndarray:
    """dq_passive / dp (N, n_pas, P), sliders held: -J_c,passive^-1 dr_c/dp (the module's eq.)."""
    return -np.linalg.solve(sensitivities.passive_jacobians, sensitivities.closure_jacobians)


def _perturbed(mechanism: Mechanism, placements, vector: np.ndarray) -> Mechanism:
    """The machine with error blocks `vector` (6 per placement, in order) applied by `poe.perturb`."""
    blocks = np.asarray(vector, dtype=float).reshape(-1, 6)
    return mechanism.with_model(perturb(mechanism.model, dict(zip(placements, blocks))))


def _generic(mechanism: Mechanism, seed: int) -> Mechanism:
    """A machine with every placement off by ~1 mm / 1 mrad (no symmetry left)."""
    model = ClosedLoopErrorModel(mechanism)
    rng = np.random.default_rng(seed)
    vector = rng.normal(0.0, 1e-3, model.n_parameters)
    return _perturbed(mechanism, model.placements, vector)


def _sliders(mechanism: Mechanism, q: np.ndarray) -> np.ndarray:
    model = mechanism.model
    return np.array([q[model.idx_qs[model.getJointId(name)]] for name in mechanism.actuated_joints])


def _differences(machine: Mechanism, placements, sliders, starts, direction: np.ndarray, passive):
    """Central differences along `direction`: platform twists (N, 6), passive joints (N, n_pas)."""
    results = []
    for sign in (1.0, -1.0):
        solver = ClosedLoopSolver(_perturbed(machine, placements, sign * STEP * direction))
        results.append([solver.forward(s, q_init=q) for s, q in zip(sliders, starts)])
    twists = np.array([pin.log6(plus.pose * minus.pose.inverse()).vector for plus, minus in zip(*results)]) / (2 * STEP)
    passive_q = np.array([plus.q[passive] - minus.q[passive] for plus, minus in zip(*results)]) / (2 * STEP)
    return twists, passive_q


@pytest.fixture(scope="module")
def m_machine():
    """The M machine, a generic copy of it, its solver and two assembled configurations.

    The error model and its sensitivities are built inside each test (a few ms): mutmut 3 runs for
    a mutant only the tests that call the mutated function, and a module fixture's calls count for
    the first test that uses it only.
    """
    mechanism = Mechanism.load()
    machine = _generic(mechanism, 1)
    solver = ClosedLoopSolver(machine)
    sliders = workspace_actuators(mechanism, 2, np.random.default_rng(5))
    configurations = [solver.forward(s, q_init=machine.home).q for s in sliders]
    return mechanism, machine, solver, sliders, configurations


def _full(m_machine):
    mechanism, _, solver, _, configurations = m_machine
    model = ClosedLoopErrorModel(mechanism)
    return model, model.platform_sensitivities(solver, configurations)


@pytest.fixture(scope="module")
def five_bar_files_pair(tmp_path_factory):
    return five_bar_files(tmp_path_factory.mktemp("five_bar"))


def _five_bar(files, variant: str):
    """A five-bar variant, its error model, a generic copy's solver, sliders and configurations.

    "base": the base frame's placement is a parameter too (it moves the whole machine, both sides of
    the closure alike); "swapped": the elbows drive and the motors follow (the platform's first
    supporting joint is passive); "platform_on_base": the measured frame is the base frame itself.
    """
    mechanism = Mechanism.load(*files)
    if variant == "swapped":
        mechanism = dataclasses.replace(mechanism, actuated_joints=("elbow_1", "elbow_2"))
    elif variant == "platform_on_base":
        mechanism = dataclasses.replace(mechanism, platform_frame="base")
    placements = ClosedLoopErrorModel(mechanism).placements
    if variant == "base":
        placements += (Placement.frame("base"),)
    model = ClosedLoopErrorModel(mechanism, placements)
    machine = _perturbed(mechanism, placements, np.random.default_rng(2).normal(0.0, 1e-3, model.n_parameters))
    solver = ClosedLoopSolver(machine)
    home = _sliders(mechanism, mechanism.home)
    sliders = np.array([home + [0.05, -0.04], home + [-0.03, 0.06]])
    configurations = [solver.forward(s, q_init=machine.home).q for s in sliders]
    return mechanism, machine, model, solver, sliders, configurations


# ---------------------------------------------------------------------------------------------
# Layout


def test_m_machine_parameter_layout(m_machine):
    mechanism = m_machine[0]
    model = ClosedLoopErrorModel(mechanism)
    frames = [
        "upper_tip_I",
        "upper_pt_I",
        "fivebar_tip_I",
        "D_I",
        "lower_tip_I",
        "lower_pt_I",
        "upper_tip_II",
        "upper_pt_II",
        "fivebar_tip_II",
        "D_II",
        "lower_tip_II",
        "lower_pt_II",
        "P_I",
        "P_II",
    ]
    joints = [mechanism.model.names[j] for j in range(1, mechanism.model.njoints)]
    assert model.placements == tuple(Placement.joint(n) for n in joints) + tuple(Placement.frame(n) for n in frames)
    assert model.n_parameters == 204 == len(model.names)
    assert model.names[:7] == (
        "q11.dt[0]",
        "q11.dt[1]",
        "q11.dt[2]",
        "q11.dt[3]",
        "q11.dt[4]",
        "q11.dt[5]",
        "q12.dt[0]",
    )
    assert model.names[-1] == "P_II.dt[5]" and model.mechanism is mechanism


def test_five_bar_parameter_layout(five_bar_files_pair):
    mechanism = Mechanism.load(*five_bar_files_pair)
    model = ClosedLoopErrorModel(mechanism)
    assert model.placements == (
        Placement.joint("motor_1"),
        Placement.joint("elbow_1"),
        Placement.joint("motor_2"),
        Placement.joint("elbow_2"),
        Placement.frame("effector"),
        Placement.frame("tip_2"),
    )
    assert model.n_parameters == 36


def test_has_own_placement_on_every_kind_of_frame(m_machine):
    model = m_machine[0].model
    kinds = {
        "q11": False,
        "slider_B1": False,
        "platform": False,
        "D_I_fixed": True,
        "D_I": True,
        "P_I": True,
        "universe": True,
        "base": True,
        "q14": False,
    }
    for name, expected in kinds.items():
        assert has_own_placement(model, model.getFrameId(name)) is expected, name
    extra = model.copy()
    under_joint = extra.addFrame(
        pin.Frame("tool_on_joint", 6, extra.getFrameId("q14"), pin.SE3.Identity(), pin.FrameType.OP_FRAME)
    )
    under_body = extra.addFrame(
        pin.Frame("tool_on_body", 6, extra.getFrameId("platform"), pin.SE3.Identity(), pin.FrameType.OP_FRAME)
    )
    body_under_fixed = extra.addFrame(
        pin.Frame("link_on_fixed", 6, extra.getFrameId("P_I_fixed"), pin.SE3.Identity(), pin.FrameType.BODY)
    )
    body_under_body = extra.addFrame(
        pin.Frame("link_on_body", 6, extra.getFrameId("platform"), pin.SE3.Identity(), pin.FrameType.BODY)
    )
    assert has_own_placement(extra, under_joint) and has_own_placement(extra, under_body)
    assert has_own_placement(extra, body_under_fixed) and has_own_placement(extra, body_under_body)


def test_explicit_placements_map_to_the_same_columns(m_machine):
    mechanism, _, solver, _, configurations = m_machine
    model, full = _full(m_machine)
    chosen = (
        Placement.frame("P_I"),
        Placement.joint("q12"),
        Placement.frame("upper_tip_I"),
        Placement.joint("q11"),
        Placement.frame("D_II"),
    )
    small = ClosedLoopErrorModel(mechanism, chosen)
    assert small.placements == chosen and small.n_parameters == 30
    assert small.names[:2] == ("P_I.dt[0]", "P_I.dt[1]") and small.names[6] == "q12.dt[0]"
    index = {p: i for i, p in enumerate(model.placements)}
    columns = np.concatenate([np.arange(6 * index[p], 6 * index[p] + 6) for p in chosen])
    part = small.platform_sensitivities(solver, configurations)
    np.testing.assert_allclose(part.twist_jacobians, full.twist_jacobians[:, :, columns], atol=1e-12)
    np.testing.assert_allclose(part.closure_jacobians, full.closure_jacobians[:, :, columns], atol=1e-12)


def test_deltas_and_perturbed_round_trip(m_machine):
    mechanism = m_machine[0]
    model = ClosedLoopErrorModel(mechanism)
    vector = np.zeros(model.n_parameters)
    vector[6 * 3 + 2] = 1e-3  # the fourth joint's placement
    vector[-6:] = [1e-3, -2e-3, 3e-3, 1e-2, 0.0, -1e-2]
    vector[-7] = 5e-4
    deltas = model.deltas(vector)
    assert list(deltas) == [model.placements[3], model.placements[-2], model.placements[-1]]
    np.testing.assert_array_equal(deltas[model.placements[-1]], vector[-6:])
    np.testing.assert_array_equal(deltas[model.placements[-2]], vector[-12:-6])
    np.testing.assert_array_equal(deltas[model.placements[3]], vector[18:24])
    assert model.deltas(np.zeros(model.n_parameters)) == {}
    assert list(model.deltas(list(vector))) == list(deltas)
    assert all(block.dtype == float for block in model.deltas(np.arange(204)).values())
    moved = model.perturbed(mechanism.model, vector)
    expected = perturb(mechanism.model, deltas)
    for j in range(1, moved.njoints):
        assert moved.jointPlacements[j].isApprox(expected.jointPlacements[j], 1e-15)
    for a, b in zip(moved.frames, expected.frames):
        assert a.placement.isApprox(b.placement, 1e-15)
    joint = mechanism.model.getJointId(model.placements[3].name)
    assert not moved.jointPlacements[joint].isApprox(mechanism.model.jointPlacements[joint], 1e-9)
    assert mechanism.model.jointPlacements[joint].isApprox(pin.Model(mechanism.model).jointPlacements[joint])
    with pytest.raises(ValueError):
        model.deltas(np.zeros(203))


# ---------------------------------------------------------------------------------------------
# Sensitivities against central differences


def test_m_machine_sensitivities_along_random_directions(m_machine):
    mechanism, machine, solver, sliders, configurations = m_machine
    model, full = _full(m_machine)
    assert isinstance(full, PlatformSensitivities)
    n_pas = len(solver.passive)
    assert full.poses.shape == (2, 4, 4) and full.twist_jacobians.shape == (2, 6, 204)
    assert full.passive_jacobians.shape == (2, n_pas, n_pas) and full.closure_jacobians.shape == (2, n_pas, 204)
    for q, pose in zip(configurations, full.poses):
        np.testing.assert_allclose(pose, solver.forward(_sliders(mechanism, q), q_init=q).pose.homogeneous, atol=1e-14)
    rng = np.random.default_rng(11)
    passive = _passive_sensitivities(full)
    for _ in range(2):
        direction = rng.normal(size=model.n_parameters)
        twists, passive_q = _differences(machine, model.placements, sliders, configurations, direction, solver.passive)
        np.testing.assert_allclose(full.twist_jacobians @ direction, twists, atol=2e-7)
        np.testing.assert_allclose(passive @ direction, passive_q, atol=2e-7)
        # dr_c/dp at fixed joints: the perturbed closures at the same q.
        plus = ClosedLoopSolver(_perturbed(machine, model.placements, STEP * direction))
        minus = ClosedLoopSolver(_perturbed(machine, model.placements, -STEP * direction))
        for i, q in enumerate(configurations):
            fd = (plus.closure_residual(q) - minus.closure_residual(q)) / (2 * STEP)
            np.testing.assert_allclose(full.closure_jacobians[i] @ direction, fd, atol=2e-7)


@pytest.mark.parametrize("variant", ["nominal", "base", "swapped", "platform_on_base"])
def test_five_bar_sensitivities_column_by_column(five_bar_files_pair, variant):
    _, machine, model, solver, sliders, configurations = _five_bar(five_bar_files_pair, variant)
    full = model.platform_sensitivities(solver, configurations)
    passive = _passive_sensitivities(full)
    for k in range(model.n_parameters):
        direction = np.zeros(model.n_parameters)
        direction[k] = 1.0
        twists, passive_q = _differences(machine, model.placements, sliders, configurations, direction, solver.passive)
        np.testing.assert_allclose(full.twist_jacobians[:, :, k], twists, atol=1e-7, err_msg=model.names[k])
        np.testing.assert_allclose(passive[:, :, k], passive_q, atol=1e-7, err_msg=model.names[k])


def test_passive_and_closure_jacobians(m_machine):
    _, _, solver, _, configurations = m_machine
    model, full = _full(m_machine)
    for i, q in enumerate(configurations):
        square = solver.closure_jacobian(q)[:, solver.passive]
        np.testing.assert_allclose(full.passive_jacobians[i], square, atol=1e-13)
        expected = -np.linalg.solve(square, full.closure_jacobians[i])
        np.testing.assert_allclose(_passive_sensitivities(full)[i], expected, atol=1e-10)
    solver.closure_sensitivity(configurations[-1])
    last = [m.homogeneous.copy() for m in solver.data.oMf.tolist()]
    solver.closure_sensitivity(configurations[0])
    full_again = model.platform_sensitivities(solver, configurations)
    assert np.allclose(full_again.poses, full.poses, atol=0)
    np.testing.assert_array_equal([m.homogeneous for m in solver.data.oMf.tolist()], last)


def test_invalid_configuration_is_refused(m_machine):
    mechanism, _, solver, _, configurations = m_machine
    model = ClosedLoopErrorModel(mechanism)
    with pytest.raises(InvalidInputError):
        model.platform_sensitivities(solver, [configurations[0][:-1]])
    with pytest.raises(InvalidInputError):
        model.platform_sensitivities(solver, [np.full_like(configurations[0], np.nan)])


def test_columns_are_read_as_integers(m_machine):
    _, _, solver, _, configurations = m_machine
    model, full = _full(m_machine)
    floats = model.platform_sensitivities(solver, configurations, np.array([198.0, 5.0, 2.0]))
    np.testing.assert_allclose(floats.twist_jacobians, full.twist_jacobians[:, :, [198, 5, 2]], atol=1e-12)
    np.testing.assert_allclose(floats.closure_jacobians, full.closure_jacobians[:, :, [198, 5, 2]], atol=1e-12)
