"""The POE view of Pinocchio models: forward kinematics, error Jacobian (eq. 17-20), perturbation."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
from m3t1r.errors import InvalidInputError, UnknownNameError, UnsupportedJointError
from m3t1r.model.poe import (
    Placement,
    SerialChain,
    adjoint_matrices,
    error_jacobian_world,
    express_error_jacobian,
    forward_and_error_jacobians,
    jlog3_batch,
    log3_batch,
    perturb,
    placement_of,
    placement_poses,
    poe_forward,
    skew,
    tool_poses,
)


@pytest.fixture(scope="module")
def ur5() -> pin.Model:
    return load_example_robot("ur5")


@pytest.fixture(scope="module")
def panda() -> pin.Model:
    return load_example_robot("panda")


def mixed_joint_model() -> pin.Model:
    """Every 1-DoF joint flavour the chain accepts, with arbitrary placements and an OP tool frame."""
    rng = np.random.default_rng(7)
    axis = rng.normal(size=3)
    joints = [
        pin.JointModelRX(),
        pin.JointModelPY(),
        pin.JointModelRevoluteUnaligned(axis / np.linalg.norm(axis)),
        pin.JointModelHZ(0.05),
        pin.JointModelPrismaticUnaligned(np.array([0.6, 0.0, 0.8])),
        pin.JointModelRUBZ(),
        pin.JointModelRY(),
    ]
    model = pin.Model()
    parent = 0
    for k, joint in enumerate(joints):
        placement = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(scale=0.3, size=3))
        parent = model.addJoint(parent, joint, placement, f"j{k}")
    model.addFrame(pin.Frame("tool", parent, pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)), pin.OP_FRAME))
    return model


def pinocchio_tool_pose(model: pin.Model, chain: SerialChain, q: np.ndarray) -> pin.SE3:
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    pose = data.oMf[chain.tool_frame_id]
    if chain.base_frame_id is not None:
        pose = data.oMf[chain.base_frame_id].actInv(pose)
    return pose


def random_chain_configurations(model: pin.Model, chain: SerialChain, n: int, seed: int) -> np.ndarray:
    lower, upper = chain.position_limits(model)
    lower, upper = np.maximum(lower, -3.0), np.minimum(upper, 3.0)
    return np.random.default_rng(seed).uniform(lower, upper, size=(n, chain.n_joints))


def se3_distance(a: pin.SE3, b: pin.SE3) -> float:
    return float(np.linalg.norm(pin.log6(a.actInv(b)).vector))


# --------------------------------------------------------------------------------------------------
# Forward kinematics


@pytest.mark.parametrize("robot", ["ur5", "panda"])
def test_poe_forward_equals_pinocchio(robot: str, request: pytest.FixtureRequest) -> None:
    model = request.getfixturevalue(robot)
    chain = SerialChain.from_model(model, example_tool_frame(robot))
    for q_chain in random_chain_configurations(model, chain, 25, seed=1):
        q = chain.model_configuration(model, q_chain)
        assert se3_distance(poe_forward(chain, model, q_chain), pinocchio_tool_pose(model, chain, q)) < 1e-12


def test_poe_forward_with_base_frames(ur5: pin.Model) -> None:
    # 'base' is a rotated fixed frame on the universe; 'upper_arm_link' starts a sub-chain at joint 3.
    for base, n_joints in (("base", 6), ("upper_arm_link", 4)):
        chain = SerialChain.from_model(ur5, "tool0", base_frame=base)
        assert chain.n_joints == n_joints
        for q_chain in random_chain_configurations(ur5, chain, 10, seed=2):
            q = chain.model_configuration(ur5, q_chain, reference=pin.randomConfiguration(ur5))
            assert se3_distance(poe_forward(chain, ur5, q_chain), pinocchio_tool_pose(ur5, chain, q)) < 1e-12


def test_every_one_dof_joint_flavour() -> None:
    model = mixed_joint_model()
    chain = SerialChain.from_model(model, "tool")
    assert chain.nq_per_joint == (1, 1, 1, 1, 1, 2, 1)
    np.testing.assert_array_equal(chain.twists[0], [0, 0, 0, 1, 0, 0])
    np.testing.assert_array_equal(chain.twists[1], [0, 1, 0, 0, 0, 0])
    np.testing.assert_allclose(chain.twists[3], [0, 0, 0.05, 0, 0, 1])  # helical: pitch along z
    for q_chain in random_chain_configurations(model, chain, 10, seed=3):
        q = chain.model_configuration(model, q_chain)
        np.testing.assert_allclose(chain.chain_configuration(q), q_chain, atol=1e-15)
        assert se3_distance(poe_forward(chain, model, q_chain), pinocchio_tool_pose(model, chain, q)) < 1e-12


def test_multi_dof_joint_is_rejected_by_name() -> None:
    model = pin.Model()
    ball = model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    wrist = model.addJoint(ball, pin.JointModelRZ(), pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.3])), "wrist")
    model.addFrame(pin.Frame("tool", wrist, pin.SE3.Identity(), pin.OP_FRAME))
    with pytest.raises(UnsupportedJointError, match="ball") as info:
        SerialChain.from_model(model, "tool")
    assert info.value.joint == "ball"


def test_initial_poses_and_placements(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0")
    poses = chain.initial_poses(ur5)
    assert len(poses) == 7
    assert poses[2] == ur5.jointPlacements[ur5.getJointId("elbow_joint")]
    assert chain.placements()[-1] == Placement.frame("tool0")
    assert chain.placements()[0] == Placement.joint("shoulder_pan_joint")
    assert chain.parameter_names()[:2] == ("shoulder_pan_joint.dt[0]", "shoulder_pan_joint.dt[1]")
    assert len(chain.parameter_names()) == chain.n_parameters == 42
    # POE product of the initial poses at q = 0 is the tool pose at q = 0.
    product = pin.SE3.Identity()
    for pose in poses:
        product = product * pose
    assert se3_distance(product, poe_forward(chain, ur5, np.zeros(6))) < 1e-14


# --------------------------------------------------------------------------------------------------
# Error Jacobian


def finite_difference_jacobian(
    model: pin.Model, chain: SerialChain, q_chain: np.ndarray, step: float = 1e-6, frame: str = "world"
) -> np.ndarray:
    """Central differences of y = log6(g(x) g^-1) (eq. 18) or log6(g^-1 g(x)) through `perturb`."""
    nominal = poe_forward(chain, model, q_chain)
    placements = chain.placements()
    columns = []
    for k, placement in enumerate(placements):
        for i in range(6):
            twists = []
            for sign in (1.0, -1.0):
                dt = np.zeros(6)
                dt[i] = sign * step
                g = poe_forward(chain, perturb(model, {placement: dt}), q_chain)
                error = g * nominal.inverse() if frame == "world" else nominal.inverse() * g
                twists.append(pin.log6(error).vector)
            columns.append((twists[0] - twists[1]) / (2 * step))
    return np.array(columns).T


@pytest.mark.parametrize("robot", ["ur5", "panda", "mixed"])
def test_error_jacobian_matches_finite_differences(robot: str, request: pytest.FixtureRequest) -> None:
    if robot == "mixed":
        model, tool = mixed_joint_model(), "tool"
    else:
        model, tool = request.getfixturevalue(robot), example_tool_frame(robot)
    chain = SerialChain.from_model(model, tool)
    for q_chain in random_chain_configurations(model, chain, 3, seed=4):
        jacobian = error_jacobian_world(chain, model, q_chain)
        numeric = finite_difference_jacobian(model, chain, q_chain)
        assert jacobian.shape == (6, chain.n_parameters)
        assert np.linalg.norm(jacobian - numeric) <= 1e-6 * np.linalg.norm(jacobian)


def test_local_error_jacobian_matches_finite_differences(panda: pin.Model) -> None:
    chain = SerialChain.from_model(panda, "panda_hand_tcp")
    q_chain = random_chain_configurations(panda, chain, 1, seed=5)[0]
    poses, jacobians = forward_and_error_jacobians(chain, panda, q_chain[None])
    local = express_error_jacobian(jacobians[0], poses[0], pin.LOCAL)
    numeric = finite_difference_jacobian(panda, chain, q_chain, frame="local")
    assert np.linalg.norm(local - numeric) <= 1e-6 * np.linalg.norm(local)
    # LOCAL_WORLD_ALIGNED linear rows are the tool origin displacement in WORLD.
    aligned = express_error_jacobian(jacobians[0], poses[0], pin.LOCAL_WORLD_ALIGNED)
    np.testing.assert_allclose(aligned[:3], poses[0].rotation @ local[:3], atol=1e-12)


@pytest.mark.parametrize("robot", ["ur5", "panda"])
def test_error_jacobian_matches_pinocchio_regressor(robot: str, request: pytest.FixtureRequest) -> None:
    model = request.getfixturevalue(robot)
    chain = SerialChain.from_model(model, example_tool_frame(robot))
    data = model.createData()
    for q_chain in random_chain_configurations(model, chain, 5, seed=6):
        q = chain.model_configuration(model, q_chain)
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacements(model, data)
        regressor = pin.computeFrameKinematicRegressor(model, data, chain.tool_frame_id, pin.WORLD)
        jacobian = error_jacobian_world(chain, model, q_chain)
        for k, j in enumerate(chain.joint_ids):
            np.testing.assert_allclose(jacobian[:, 6 * k : 6 * k + 6], regressor[:, 6 * (j - 1) : 6 * j], atol=1e-12)
        np.testing.assert_allclose(jacobian[:, -6:], data.oMf[chain.tool_frame_id].action, atol=1e-12)


# --------------------------------------------------------------------------------------------------
# Batched evaluation


def chain_and_model(name: str, request: pytest.FixtureRequest) -> tuple[pin.Model, SerialChain]:
    if name == "mixed":
        model = mixed_joint_model()
        return model, SerialChain.from_model(model, "tool")
    if name == "ur5-sub":
        model = request.getfixturevalue("ur5")
        return model, SerialChain.from_model(model, "tool0", base_frame="upper_arm_link")
    model = request.getfixturevalue(name)
    return model, SerialChain.from_model(model, example_tool_frame(name))


@pytest.mark.parametrize("name", ["ur5", "panda", "mixed", "ur5-sub"])
def test_joint_motions_equal_exp6(name: str, request: pytest.FixtureRequest) -> None:
    _, chain = chain_and_model(name, request)
    q = np.random.default_rng(20).uniform(-3.0, 3.0, size=(12, chain.n_joints))
    q[0] = 0.0
    q[1] = 1e-9  # the closed form has no 1/angle term: nothing special near zero
    motions = chain.joint_motions(q)
    assert motions.shape == (chain.n_joints, len(q), 4, 4)
    for i, row in enumerate(q):
        for k, value in enumerate(row):
            np.testing.assert_allclose(motions[k, i], pin.exp6(chain.twists[k] * value).homogeneous, atol=1e-15)


@pytest.mark.parametrize("name", ["ur5", "panda", "mixed", "ur5-sub"])
def test_placement_poses_equal_pinocchio(name: str, request: pytest.FixtureRequest) -> None:
    model, chain = chain_and_model(name, request)
    data = model.createData()
    q_chain = random_chain_configurations(model, chain, 20, seed=21)
    frames = placement_poses(chain, chain.initial_transforms(model), q_chain)
    assert frames.shape == (20, chain.n_joints + 1, 4, 4)
    np.testing.assert_array_equal(tool_poses(chain, model, q_chain), frames[:, -1])
    for q_c, poses in zip(q_chain, frames):
        q = chain.model_configuration(model, q_c)
        pin.framesForwardKinematics(model, data, q)
        base = pin.SE3.Identity() if chain.base_frame_id is None else data.oMf[chain.base_frame_id]
        # F_k: joint k's placement frame before its motion, oMi[parent] T(0); the tool frame last.
        expected = [base.actInv(data.oMi[model.parents[j]] * model.jointPlacements[j]) for j in chain.joint_ids]
        expected.append(base.actInv(data.oMf[chain.tool_frame_id]))
        for frame, pose in zip(poses, expected):
            np.testing.assert_allclose(frame, pose.homogeneous, atol=1e-12)


@pytest.mark.parametrize("name", ["ur5", "panda", "mixed", "ur5-sub"])
def test_batched_jacobians_equal_the_pose_by_pose_product(name: str, request: pytest.FixtureRequest) -> None:
    # The former implementation, one Pinocchio SE3 product per link and pose, is the reference.
    model, chain = chain_and_model(name, request)
    q_chain = random_chain_configurations(model, chain, 15, seed=22)
    poses, jacobians = forward_and_error_jacobians(chain, model, q_chain)
    initial = chain.initial_poses(model)
    for q, pose, jacobian in zip(q_chain, poses, jacobians):
        g = pin.SE3.Identity()
        for k in range(chain.n_joints):
            g = g * initial[k]
            np.testing.assert_allclose(jacobian[:, 6 * k : 6 * k + 6], g.action, atol=1e-12)
            g = g * pin.exp6(chain.twists[k] * q[k])
        g = g * initial[-1]
        np.testing.assert_allclose(jacobian[:, -6:], g.action, atol=1e-12)
        assert se3_distance(pose, g) < 1e-12
        assert se3_distance(pose, poe_forward(chain, model, q)) < 1e-12


def test_adjoint_and_skew_match_pinocchio() -> None:
    rng = np.random.default_rng(23)
    poses = [pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(4)]
    adjoints = adjoint_matrices(np.array([g.homogeneous for g in poses]))
    for g, ad in zip(poses, adjoints):
        np.testing.assert_allclose(ad, g.action, atol=1e-15)
    vectors = rng.normal(size=(5, 3))
    for v, m in zip(vectors, skew(vectors)):
        np.testing.assert_array_equal(m, pin.skew(v))


def test_batched_inputs_are_validated(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0")
    transforms = chain.initial_transforms(ur5)
    with pytest.raises(InvalidInputError, match=r"expected shape \(7, 4, 4\)"):
        placement_poses(chain, transforms[:-1], np.zeros((2, 6)))
    with pytest.raises(InvalidInputError, match=r"expected shape \(N, 6\)"):
        placement_poses(chain, transforms, np.zeros((2, 5)))
    bad = np.zeros((3, 6))
    bad[2, 1] = np.nan
    with pytest.raises(InvalidInputError, match="row 2"):
        tool_poses(chain, ur5, bad)
    # A single configuration is a batch of one.
    assert tool_poses(chain, ur5, np.zeros(6)).shape == (1, 4, 4)


# --------------------------------------------------------------------------------------------------
# Perturbation


def snapshot(model: pin.Model) -> list[pin.SE3]:
    return [model.jointPlacements[j].copy() for j in range(model.njoints)] + [f.placement.copy() for f in model.frames]


def test_perturb_returns_a_copy_and_applies_right_multiplied_errors(ur5: pin.Model) -> None:
    before = snapshot(ur5)
    dt = np.array([1e-3, -2e-3, 3e-3, 1e-2, 2e-2, -1e-2])
    perturbed = perturb(ur5, {Placement.joint("elbow_joint"): dt, Placement.frame("tool0"): -dt})
    assert all(a == b for a, b in zip(before, snapshot(ur5)))
    elbow = Placement.joint("elbow_joint")
    expected = placement_of(ur5, elbow) * pin.exp6(dt)
    assert se3_distance(placement_of(perturbed, elbow), expected) < 1e-15
    tool = Placement.frame("tool0")
    assert se3_distance(placement_of(perturbed, tool), placement_of(ur5, tool) * pin.exp6(-dt)) < 1e-15
    # placement_of hands out copies.
    copy = placement_of(perturbed, elbow)
    copy.translation = np.zeros(3)
    assert se3_distance(placement_of(perturbed, elbow), expected) < 1e-15


def test_perturbing_a_link_moves_what_hangs_below_it(ur5: pin.Model) -> None:
    dt = np.array([2e-3, 1e-3, -1e-3, 3e-3, -2e-3, 1e-3])
    model = pin.Model(ur5)
    tool0 = model.getFrameId("tool0")
    offset = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.1]))
    tcp = model.addFrame(
        pin.Frame("tcp", model.frames[tool0].parentJoint, tool0, model.frames[tool0].placement * offset, pin.OP_FRAME)
    )
    by_link = perturb(model, {Placement.frame("tool0"): dt})
    by_fixed_joint = perturb(model, {Placement.frame("wrist_3_link-tool0_fixed_joint"): dt})
    assert all(a == b for a, b in zip(snapshot(by_link), snapshot(by_fixed_joint)))
    fixed = model.getFrameId("wrist_3_link-tool0_fixed_joint")
    for frame_id in (fixed, tool0):
        expected = model.frames[frame_id].placement * pin.exp6(dt)
        assert se3_distance(by_link.frames[frame_id].placement, expected) < 1e-15
    # The descendant keeps its pose relative to tool0; the sibling ee_link does not move.
    relative = model.frames[tool0].placement.actInv(model.frames[tcp].placement)
    assert se3_distance(by_link.frames[tool0].placement.actInv(by_link.frames[tcp].placement), relative) < 1e-15
    assert se3_distance(by_link.frames[tcp].placement, model.frames[tcp].placement) > 1e-3
    ee_link = model.getFrameId("ee_link")
    assert by_link.frames[ee_link].placement == model.frames[ee_link].placement
    with pytest.raises(InvalidInputError, match="same physical placement"):
        perturb(model, {Placement.frame("tool0"): dt, Placement.frame("wrist_3_link-tool0_fixed_joint"): dt})


def test_perturbing_the_base_link_moves_the_whole_arm(ur5: pin.Model) -> None:
    dt = np.array([1e-3, 0.0, 0.0, 0.0, 0.0, 2e-3])
    moved = perturb(ur5, {Placement.frame("base_link"): dt})
    chain = SerialChain.from_model(ur5, "tool0")
    q_chain = random_chain_configurations(ur5, chain, 1, seed=8)[0]
    # base_link sits at the world origin, so the whole arm is displaced by exp6(dt) in WORLD.
    expected = pin.exp6(dt) * poe_forward(chain, ur5, q_chain)
    assert se3_distance(poe_forward(chain, moved, q_chain), expected) < 1e-14


def test_unknown_names_raise_typed_errors(ur5: pin.Model) -> None:
    with pytest.raises(UnknownNameError, match="'elbow'") as info:
        perturb(ur5, {Placement.joint("elbow"): np.zeros(6)})
    assert (info.value.kind, info.value.name) == ("joint", "elbow")
    with pytest.raises(UnknownNameError, match="'tool'") as info:
        perturb(ur5, {Placement.frame("tool"): np.zeros(6)})
    assert (info.value.kind, info.value.name) == ("frame", "tool")
    with pytest.raises(UnknownNameError, match="'flange'"):
        SerialChain.from_model(ur5, "flange")
    with pytest.raises(UnknownNameError, match="'table'"):
        SerialChain.from_model(ur5, "tool0", base_frame="table")
    with pytest.raises(UnknownNameError, match="JOINT frame"):
        placement_of(ur5, Placement.frame("elbow_joint"))
    with pytest.raises(UnknownNameError, match="universe"):
        placement_of(ur5, Placement.joint("universe"))
    with pytest.raises(InvalidInputError, match="expected 6 values"):
        perturb(ur5, {Placement.joint("elbow_joint"): np.zeros(5)})
    with pytest.raises(InvalidInputError):
        Placement("link", "tool0")  # type: ignore[arg-type]


def test_chain_rejects_a_different_model(ur5: pin.Model, panda: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0")
    with pytest.raises(InvalidInputError, match="does not match"):
        poe_forward(chain, panda, np.zeros(6))


def test_batched_log3_and_jlog3_equal_pinocchio() -> None:
    rng = np.random.default_rng(30)
    angles = [0.0, 1e-12, 1e-7, 1e-5, 9.9e-3, 1.01e-2, 0.3, 1.5, 2.9, 3.1, np.pi - 1e-6, np.pi]
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rotations = np.array([pin.exp3(a * u) for a, u in zip(angles, axes)])
    logs, measured_angles = log3_batch(rotations)
    jacobians = jlog3_batch(logs, measured_angles)
    for rotation, log, angle, jacobian in zip(rotations, logs, measured_angles, jacobians):
        np.testing.assert_allclose(log, pin.log3(rotation), rtol=1e-12, atol=1e-15)
        assert angle == pytest.approx(np.linalg.norm(pin.log3(rotation)), rel=1e-12, abs=1e-15)
        if angle < np.pi - 1e-3:  # Jlog3 is singular at pi
            np.testing.assert_allclose(jacobian, pin.Jlog3(rotation), rtol=1e-12, atol=1e-12)
