"""The POE view of Pinocchio models: forward kinematics, error Jacobian (eq. 17-20), perturbation."""

from __future__ import annotations

import warnings
from decimal import Decimal

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
from m3t1r.errors import InvalidInputError, UnknownNameError, UnsupportedJointError
from m3t1r.model.poe import (
    Placement,
    SerialChain,
    adjoint_matrices,
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
    model: pin.Model, chain: SerialChain, q_chain: np.ndarray, step: float = 1e-6
) -> np.ndarray:
    """Central differences of y = log6(g(x) g^-1) (eq. 18) through `perturb`."""
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
                twists.append(pin.log6(g * nominal.inverse()).vector)
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
        jacobian = forward_and_error_jacobians(chain, model, q_chain[None])[1][0]
        numeric = finite_difference_jacobian(model, chain, q_chain)
        assert jacobian.shape == (6, chain.n_parameters)
        assert np.linalg.norm(jacobian - numeric) <= 1e-6 * np.linalg.norm(jacobian)


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
        jacobian = forward_and_error_jacobians(chain, model, q_chain[None])[1][0]
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


# ==================================================================================================
# Rank bound, name resolution, perturbation anchors and closed forms
#
# The rank bound of the error Jacobian, exact refusals (kind, name and message of every UnknownNameError),
# which frames a perturbation anchors on and carries, check_model's every clause, the closed-form joint
# motion of a general screw, and the small-angle series of jlog3_batch.
# ==================================================================================================


def numerical_rank(matrix: np.ndarray) -> int:
    singular = np.linalg.svd(matrix, compute_uv=False)
    return int(np.count_nonzero(singular > 1e-9 * singular[0]))


# --------------------------------------------------------------------------------------------------
# rank_bound


@pytest.mark.parametrize("robot", ["ur5", "mixed"])
def test_rank_bound_is_the_rank_of_the_stacked_error_jacobian(robot: str, ur5: pin.Model) -> None:
    model, tool = (ur5, "tool0") if robot == "ur5" else (mixed_joint_model(), "tool")
    chain = SerialChain.from_model(model, tool)
    q = np.random.default_rng(0).uniform(-2.0, 2.0, size=(40, chain.n_joints))
    jacobians = forward_and_error_jacobians(chain, model, q)[1]
    # 4 r + 2 p + 6 of the paper: UR5 6 R -> 30; the mixed chain has 5 screws (RX first: an axis
    # with zero y, z components is still a rotation) and 2 prismatic joints -> 30.
    assert chain.rank_bound() == 30
    assert numerical_rank(jacobians.reshape(-1, chain.n_parameters)) == 30
    assert chain.rank_bound(position_only=True) == 27
    position_rank = numerical_rank(jacobians[:, :3].reshape(-1, chain.n_parameters))
    assert position_rank == (25 if robot == "ur5" else 27)  # a bound: UR5's parallel axes lose 2 more


# --------------------------------------------------------------------------------------------------
# Name resolution: exact refusals


def test_a_joint_frame_is_not_a_placement_nor_a_tool(ur5: pin.Model) -> None:
    expected = (
        "frame 'elbow_joint': is the JOINT frame of a joint; use Placement.joint(...) to perturb the joint placement"
    )
    for call in (
        lambda: placement_of(ur5, Placement.frame("elbow_joint")),
        lambda: perturb(ur5, {Placement.frame("elbow_joint"): np.zeros(6)}),
        lambda: SerialChain.from_model(ur5, "elbow_joint"),
    ):
        with pytest.raises(UnknownNameError) as info:
            call()
        assert (str(info.value), info.value.kind, info.value.name) == (expected, "frame", "elbow_joint")


def test_the_universe_joint_has_no_placement(ur5: pin.Model) -> None:
    with pytest.raises(UnknownNameError) as info:
        placement_of(ur5, Placement.joint("universe"))
    assert str(info.value) == "joint 'universe': the universe joint has no placement"
    assert (info.value.kind, info.value.name) == ("joint", "universe")


def test_two_frames_of_one_name_are_ambiguous(ur5: pin.Model) -> None:
    model = pin.Model(ur5)
    tool0 = model.frames[model.getFrameId("tool0")]
    model.addFrame(pin.Frame("tool0", tool0.parentJoint, tool0.placement, pin.OP_FRAME))
    kinds = f"{pin.FrameType.BODY}, {pin.FrameType.OP_FRAME}"
    with pytest.raises(UnknownNameError) as info:
        SerialChain.from_model(model, "tool0")
    assert str(info.value) == f"frame 'tool0': ambiguous: 2 frames carry this name ({kinds})"
    assert (info.value.kind, info.value.name) == ("frame", "tool0")


def test_a_base_frame_may_be_a_joint_frame_but_must_support_the_tool(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0", base_frame="shoulder_lift_joint")
    assert chain.joint_names == ("elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
    model = pin.Model(ur5)
    elbow = model.getJointId("elbow_joint")
    model.addFrame(pin.Frame("side", elbow, pin.SE3.Identity(), pin.OP_FRAME))
    with pytest.raises(UnknownNameError) as info:
        SerialChain.from_model(model, "upper_arm_link", base_frame="side")
    assert str(info.value) == (
        "frame 'side': is on joint 'elbow_joint', which does not support tool frame 'upper_arm_link'"
    )
    assert (info.value.kind, info.value.name) == ("frame", "side")
    with pytest.raises(InvalidInputError) as plain:
        SerialChain.from_model(ur5, "tool0", base_frame="wrist_3_link")
    assert str(plain.value) == "no joint moves tool frame 'tool0' relative to the base"


def test_multi_dof_joints_are_refused_with_their_shape() -> None:
    model = pin.Model()
    ball = model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    model.addFrame(pin.Frame("tool", ball, pin.SE3.Identity(), pin.OP_FRAME))
    with pytest.raises(UnsupportedJointError) as info:
        SerialChain.from_model(model, "tool")
    assert str(info.value) == "joint 'ball': JointModelSpherical has nq=4, nv=3; a serial POE chain needs 1-DoF joints"
    # Two DoF in two coordinates (nq within (1, 2), nv = 2) is refused as well.
    model = pin.Model()
    composite = pin.JointModelComposite(pin.JointModelRX())
    composite.addJoint(pin.JointModelRY())
    pair = model.addJoint(0, composite, pin.SE3.Identity(), "pair")
    model.addFrame(pin.Frame("tool", pair, pin.SE3.Identity(), pin.OP_FRAME))
    with pytest.raises(UnsupportedJointError, match="nq=2, nv=2") as info:
        SerialChain.from_model(model, "tool")
    assert info.value.joint == "pair"


def test_a_twist_that_is_not_the_joint_motion_is_refused_by_name(ur5: pin.Model, monkeypatch) -> None:
    right = SerialChain.joint_twists

    def off_by_one_percent(chain: SerialChain, model: pin.Model) -> np.ndarray:
        wrong = right(chain, model)
        wrong[2] *= 1.01  # far beyond the 1e-12 of the check
        return wrong

    monkeypatch.setattr(SerialChain, "joint_twists", off_by_one_percent)
    with pytest.raises(UnsupportedJointError) as info:
        SerialChain.from_model(ur5, "tool0")
    assert str(info.value) == (
        "joint 'elbow_joint': JointModelRY does not move as exp6(S q); it cannot be a POE factor"
    )


def test_the_chain_twists_are_read_only(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0")
    assert not chain.twists.flags.writeable
    with pytest.raises(ValueError):
        chain.twists[0, 0] = 1.0


# --------------------------------------------------------------------------------------------------
# Placement and perturb


def test_placement_refusals_are_exact() -> None:
    with pytest.raises(InvalidInputError) as info:
        Placement("link", "tool0")  # type: ignore[arg-type]
    assert str(info.value) == "Placement kind must be 'joint' or 'frame', got 'link'"
    for name in ("", 5):
        with pytest.raises(InvalidInputError) as info:
            Placement("joint", name)  # type: ignore[arg-type]
        assert str(info.value) == f"Placement name must be a non-empty string, got {name!r}"


def test_perturb_refusals_are_exact(ur5: pin.Model) -> None:
    with pytest.raises(InvalidInputError) as info:
        perturb(ur5, {"elbow_joint": np.zeros(6)})  # type: ignore[dict-item]
    assert str(info.value) == "perturb: keys must be Placement objects, got 'elbow_joint'"
    with pytest.raises(InvalidInputError) as info:
        perturb(ur5, {Placement.joint("elbow_joint"): np.zeros(5)})
    assert str(info.value) == "error twist of joint 'elbow_joint': expected 6 values, got 5"
    with pytest.raises(InvalidInputError) as info:
        perturb(
            ur5, {Placement.frame("tool0"): np.zeros(6), Placement.frame("wrist_3_link-tool0_fixed_joint"): np.zeros(6)}
        )
    assert str(info.value) == (
        "perturb: frame 'wrist_3_link-tool0_fixed_joint' and frame 'tool0' name the same physical placement"
    )


def test_a_link_after_a_moving_joint_anchors_itself(ur5: pin.Model) -> None:
    """forearm_link's parent frame is the JOINT frame of elbow_joint with the same (identity)
    placement, but only a FIXED_JOINT parent carries a link: the JOINT frame must not move."""
    dt = np.array([1e-3, 2e-3, -1e-3, 2e-3, 1e-3, -3e-3])
    moved = perturb(ur5, {Placement.frame("forearm_link"): dt})
    link, joint = ur5.getFrameId("forearm_link"), ur5.getFrameId("elbow_joint", pin.JOINT)
    assert moved.frames[joint].placement == ur5.frames[joint].placement
    assert moved.frames[link].placement.isApprox(ur5.frames[link].placement * pin.exp6(dt), 1e-15)


def test_a_non_body_frame_on_a_fixed_joint_anchors_itself(ur5: pin.Model) -> None:
    """An OP_FRAME hanging from a FIXED_JOINT frame at the same placement is its own placement."""
    model = pin.Model(ur5)
    fixed = model.getFrameId("wrist_3_link-tool0_fixed_joint")
    marker = model.addFrame(
        pin.Frame("marker", model.frames[fixed].parentJoint, fixed, model.frames[fixed].placement, pin.OP_FRAME)
    )
    dt = np.array([1e-3, 0.0, 2e-3, 0.0, 1e-3, 0.0])
    moved = perturb(model, {Placement.frame("marker"): dt})
    assert moved.frames[marker].placement.isApprox(model.frames[marker].placement * pin.exp6(dt), 1e-15)
    assert moved.frames[fixed].placement == model.frames[fixed].placement
    perturb(model, {Placement.frame("marker"): dt, Placement.frame("tool0"): -dt})  # two placements, no clash


def test_everything_on_the_link_moves_whatever_the_frame_order() -> None:
    """Frames and joints below a perturbed link, visited in any order: a frame of another joint
    hanging from the link and the next joint's JOINT frame must not stop the walk."""
    model = pin.Model()
    j1 = model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "j1")
    jf1 = model.addJointFrame(j1, 0)
    offset = pin.SE3(pin.exp3(np.array([0.1, 0.2, 0.3])), np.array([0.1, 0.0, 0.2]))
    link = model.addFrame(pin.Frame("link", j1, jf1, offset, pin.BODY))
    late = model.addFrame(pin.Frame("late", j1, link, offset * offset, pin.OP_FRAME))
    j2 = model.addJoint(j1, pin.JointModelRY(), offset * pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.3])), "j2")
    model.addJointFrame(j2, link)
    model.addFrame(pin.Frame("odd", j2, link, pin.SE3.Identity(), pin.OP_FRAME))  # on j2, below link
    dt = np.array([1e-3, -2e-3, 1e-3, 3e-3, 1e-3, -2e-3])
    moved = perturb(model, {Placement.frame("link"): dt})
    to_new = offset * pin.exp6(dt) * offset.inverse()
    assert moved.frames[late].placement.isApprox(to_new * model.frames[late].placement, 1e-15)
    assert moved.jointPlacements[j2].isApprox(to_new * model.jointPlacements[j2], 1e-15)
    assert not moved.frames[late].placement.isApprox(model.frames[late].placement, 1e-6)


# --------------------------------------------------------------------------------------------------
# SerialChain helpers


def test_chain_configuration_refusals_are_exact(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0")
    for q in (np.zeros(5), np.zeros((2, 6))):
        with pytest.raises(InvalidInputError) as info:
            chain.chain_configuration(q)
        assert str(info.value) == f"configuration: expected a vector of >= 6 values, got shape {q.shape}"


def test_model_configuration_keeps_the_reference_off_the_chain(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0", base_frame="shoulder_lift_joint")  # the last 4 joints
    reference = np.array([0.01, 0.02, 0.0, 0.0, 0.0, 0.0])
    q = chain.model_configuration(ur5, np.full(4, 0.3), reference)
    np.testing.assert_array_equal(q, [0.01, 0.02, 0.3, 0.3, 0.3, 0.3])
    with pytest.raises(InvalidInputError) as info:
        chain.model_configuration(ur5, np.zeros(3))
    assert str(info.value) == "chain configuration: expected 4 values, got 3"
    with pytest.raises(InvalidInputError) as info:
        chain.model_configuration(ur5, np.zeros(4), np.zeros(3))
    assert str(info.value) == "reference: expected 6 values, got 3"


def test_position_limits_of_an_unbounded_joint_are_plus_minus_pi() -> None:
    model = mixed_joint_model()
    model.lowerPositionLimit[:] = -0.5
    model.upperPositionLimit[:] = 0.25
    chain = SerialChain.from_model(model, "tool")
    lower, upper = chain.position_limits(model)
    np.testing.assert_array_equal(lower, [-0.5] * 5 + [-np.pi, -0.5])
    np.testing.assert_array_equal(upper, [0.25] * 5 + [np.pi, 0.25])


def test_chain_configurations_accept_any_real_numbers(ur5: pin.Model) -> None:
    """Decimal values (e.g. from an exact reader) are numbers: converted to float, not refused."""
    chain = SerialChain.from_model(ur5, "tool0")
    q = np.array([0.1, -0.4, 0.7, 0.2, -0.3, 0.5])
    exact = [[Decimal(str(v)) for v in q]]
    np.testing.assert_array_equal(tool_poses(chain, ur5, exact), tool_poses(chain, ur5, q))
    transforms = [[[Decimal(str(v)) for v in row] for row in t] for t in chain.initial_transforms(ur5)]
    np.testing.assert_allclose(placement_poses(chain, transforms, q)[0, -1], tool_poses(chain, ur5, q)[0], atol=1e-15)
    mixed = mixed_joint_model()
    mixed_chain = SerialChain.from_model(mixed, "tool")
    full = mixed_chain.model_configuration(mixed, np.linspace(-1.0, 1.0, 7))
    np.testing.assert_array_equal(
        mixed_chain.chain_configuration([Decimal(str(v)) for v in full]), mixed_chain.chain_configuration(full)
    )


def test_poe_forward_names_the_chain_configuration(ur5: pin.Model) -> None:
    chain = SerialChain.from_model(ur5, "tool0")
    with pytest.raises(InvalidInputError) as info:
        poe_forward(chain, ur5, np.zeros(5))
    assert str(info.value) == "chain configuration: expected 6 values, got 5"


def renamed(model: pin.Model, joint: str | None = None, frame: str | None = None) -> pin.Model:
    out = pin.Model(model)
    if joint is not None:
        out.names[out.getJointId(joint)] = joint + "_renamed"
    if frame is not None:
        out.frames[out.getFrameId(frame)].name = frame + "_renamed"
    return out


def test_check_model_checks_every_joint_and_frame(ur5: pin.Model) -> None:
    model = pin.Model(ur5)
    model.addFrame(pin.Frame("table", 0, pin.SE3.Identity(), pin.OP_FRAME))  # the last frame id
    chain = SerialChain.from_model(model, "tool0", base_frame="table")
    message = (
        f"model '{ur5.name}' does not match the serial chain to 'tool0' "
        "(build the chain from this model or from the model it was perturbed from)"
    )
    fewer_joints = pin.buildReducedModel(model, [model.getJointId("wrist_3_joint")], pin.neutral(model))
    few_frames = pin.Model()
    for j in range(1, model.njoints):
        few_frames.addJoint(model.parents[j], model.joints[j], model.jointPlacements[j], model.names[j])
    while few_frames.nframes < chain.tool_frame_id:
        few_frames.addFrame(pin.Frame(f"f{few_frames.nframes}", 0, pin.SE3.Identity(), pin.OP_FRAME))
    candidates = [
        ur5,  # no frame at the base frame's id
        renamed(model, joint="elbow_joint"),
        renamed(model, frame="tool0"),
        renamed(model, frame="table"),
        fewer_joints,
        few_frames,
    ]
    for candidate in candidates:
        candidate.name = ur5.name
        with pytest.raises(InvalidInputError) as info:
            chain.check_model(candidate)
        assert str(info.value) == message
    chain.check_model(model)


# --------------------------------------------------------------------------------------------------
# Closed forms


def test_joint_motions_of_a_general_screw_equal_exp6(ur5: pin.Model) -> None:
    """The closed form holds for any twist, also one whose linear part is off the axis (the
    [u] v and [u]^2 v terms) and a pure translation."""
    rng = np.random.default_rng(5)
    twists = np.vstack([rng.normal(size=(3, 6)), [[0.3, -0.2, 0.9, 0.0, 0.0, 0.0]]])
    template = SerialChain.from_model(ur5, "tool0")
    chain = SerialChain(
        joint_ids=template.joint_ids[:4],
        joint_names=template.joint_names[:4],
        tool_frame_id=template.tool_frame_id,
        tool_frame=template.tool_frame,
        base_frame_id=None,
        base_frame=None,
        idx_q=template.idx_q[:4],
        nq_per_joint=(1, 1, 1, 1),
        twists=twists,
    )
    q = rng.uniform(-2.0, 2.0, size=(5, 4))
    motions = chain.joint_motions(q)
    for k in range(4):
        for i in range(5):
            np.testing.assert_allclose(motions[k, i], pin.exp6(twists[k] * q[i, k]).homogeneous, atol=1e-13)


def test_jlog3_small_angle_series_is_exact_to_rounding() -> None:
    """b(a) = 1/a^2 - 1/(2 a tan(a/2)) = 1/12 + a^2/720 + a^4/30240 + a^6/1209600 + ...; read back
    from the off-diagonal entry J[0, 1] = b a^2 / 2 of log = a (1, 1, 0)/sqrt(2), which is exact."""
    angles = np.array([1e-3, 4e-3, 7e-3, 9.99e-3])
    logs = angles[:, None] * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    jacobians = jlog3_batch(logs, angles)
    squared = angles**2
    reference = squared**3 / 1209600.0 + squared**2 / 30240.0 + squared / 720.0 + 1.0 / 12.0
    np.testing.assert_allclose(2.0 * jacobians[:, 0, 1] / squared, reference, rtol=4e-15, atol=0.0)


def test_log3_and_jlog3_of_zero_rotations_raise_no_warning() -> None:
    """Exact zero rotations (a noise-free residual) take the guarded branches without a floating
    point warning and give exact zeros, whatever the memory numpy hands out."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for n in (1, 2, 4, 7):
            for _ in range(5):
                poison = [np.full(n, np.nan) for _ in range(16)]
                del poison
                logs, angles = log3_batch(np.repeat(np.eye(3)[None], n, axis=0))
                assert np.all(logs == 0.0) and np.all(angles == 0.0)
                np.testing.assert_array_equal(jlog3_batch(logs, angles), np.repeat(np.eye(3)[None], n, axis=0))


def test_prismatic_joint_motions_are_exact_whatever_the_memory() -> None:
    """Chains of prismatic joints only (no rotation rate to divide by) move by exactly exp6 of their
    twists, without a floating point warning, whatever the memory numpy hands out."""
    for n in (1, 3):
        model = pin.Model()
        parent = 0
        for k in range(n):
            parent = model.addJoint(
                parent, (pin.JointModelPX(), pin.JointModelPY(), pin.JointModelPZ())[k], pin.SE3.Identity(), f"p{k}"
            )
        model.addFrame(pin.Frame("tool", parent, pin.SE3.Identity(), pin.OP_FRAME))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            for _ in range(5):
                poison = [np.full(n, np.nan) for _ in range(16)]
                del poison
                chain = SerialChain.from_model(model, "tool")  # a new chain: its motion terms computed anew
                q = np.linspace(-0.3, 0.4, 2 * n).reshape(2, n)
                motions = chain.joint_motions(q)
                assert np.all(np.isfinite(motions))
                for k in range(n):
                    for i in range(2):
                        expected = pin.exp6(chain.twists[k] * q[i, k]).homogeneous
                        np.testing.assert_allclose(motions[k, i], expected, atol=1e-15)


def test_frames_moved_by_a_frame_error_are_the_frames_perturb_moves() -> None:
    """For frames on the base (parent joint 0), mid-chain and at the platform of the M machine, the set
    returned is exactly the set of frames whose world placement changes when `perturb` applies an
    error to that frame, at a generic configuration; the anchor carries the error. World placements
    are oMi[parent] * placement: Pinocchio never updates oMf[0], the universe frame a base error moves."""
    from m3t1r.model.description import Mechanism
    from m3t1r.model.poe import Placement, frames_moved_by_frame_error, perturb

    model = Mechanism.load().model
    q = np.random.default_rng(3).uniform(-0.3, 0.3, model.nq)

    def world_frames(machine: pin.Model) -> list[pin.SE3]:
        data = machine.createData()
        pin.forwardKinematics(machine, data, q)
        return [data.oMi[frame.parentJoint] * frame.placement for frame in machine.frames]

    before = world_frames(model)
    names = [f.name for f in model.frames if f.type != pin.FrameType.JOINT]
    base = next(
        f.name for f in model.frames if f.parentJoint == 0 and f.type == pin.FrameType.BODY and f.name != "universe"
    )
    chosen = {base, "P_I", "slider_B1", names[len(names) // 2]}
    for name in chosen:
        frame_id = model.getFrameId(name)
        anchor, moved = frames_moved_by_frame_error(model, frame_id)
        perturbed = perturb(model, {Placement("frame", name): np.full(6, 1e-3)})
        after = world_frames(perturbed)
        changed = {
            i for i in range(model.nframes) if np.linalg.norm(pin.log6(before[i].actInv(after[i])).vector) > 1e-12
        }
        assert moved == changed, name
        assert anchor in moved and frame_id in moved
