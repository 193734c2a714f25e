"""Compensation of a serial robot's joint program (`m3t1r.calibration.serial_compensation`): the
calibrated robot's tool lands on the nominal tool pose, its compliance inverted, its joint limits kept."""

from __future__ import annotations

import numpy as np
import pytest

from m3t1r.calibration import serial as S
from m3t1r.calibration.serial_compensation import compensate_serial
from m3t1r.calibration.serial_robots import load_example_robot
from m3t1r.model.poe import Placement, SerialChain, perturb, tool_poses

COMPLIANCE = {"shoulder_lift_joint": -6e-5, "elbow_joint": -9e-5}  # rad/Nm


def _robot_with_errors(name: str, tool: str):
    """(nominal model, its chain to `tool`, a copy with 1 mm / 1 mrad placement errors)."""
    model = load_example_robot(name)
    chain = SerialChain.from_model(model, tool)
    rng = np.random.default_rng(1)
    return model, chain, perturb(model, {p: rng.normal(0.0, 1e-3, 6) for p in chain.placements()})


@pytest.fixture(scope="module")
def ur10():
    return _robot_with_errors("ur10", "tool0")


@pytest.fixture(scope="module")
def panda():
    return _robot_with_errors("panda", "panda_hand_tcp")


def test_commands_put_the_compliant_calibrated_tool_on_the_nominal_pose(ur10) -> None:
    model, chain, calibrated = ur10
    program = np.random.default_rng(2).uniform([-3, -2.3, 0.6, -3, -3, -3], [3, -0.6, 2.4, 3, 3, 3], (8, 6))
    result = compensate_serial(model, calibrated, chain, program, COMPLIANCE)
    assert result.failures == ()
    moved = S.compliant_readings(calibrated, chain, result.commands, COMPLIANCE)
    reached, target = tool_poses(chain, calibrated, moved), tool_poses(chain, model, program)
    assert np.abs(reached - target).max() < 1e-9  # the Newton tolerance, 1e-12, with margin
    assert np.abs(result.commands - program).max() > 1e-3  # the millimetre errors needed correcting


def test_a_joint_at_its_limit_is_held_there_while_other_joints_can_reach(ur10) -> None:
    model, chain, calibrated = ur10
    lower, upper = chain.position_limits(model)
    program = np.array([[0.4, -1.2, 1.5, -1.0, 1.2, lower[5]]])  # wrist 3 at its stop
    held = compensate_serial(model, calibrated, chain, program, {}, position_only=True)
    assert held.failures == () and held.commands[0, 5] == lower[5]  # the least-norm step went past it
    reached = tool_poses(chain, calibrated, held.commands)[0, :3, 3]
    assert np.linalg.norm(reached - tool_poses(chain, model, program)[0, :3, 3]) < 1e-9
    # The full pose needs all six joints: a command past the stop is a failure naming the joint.
    program[0, 5] = upper[5]
    full = compensate_serial(model, calibrated, chain, program, {})
    assert len(full.failures) == 1 and "puts joint 'wrist_3_joint' at 6.28" in full.failures[0][1]
    assert np.isnan(full.commands[0]).all()


# ---------------------------------------------------------------------------------------------------
# What a row reports: the error left, a pose out of reach, the program's type


def test_each_row_reports_the_error_left_and_an_integer_program_is_read_as_angles(ur10) -> None:
    model, chain, calibrated = ur10
    integers = np.array([[0, -1, 1, 0, 1, 0], [1, -2, 2, -1, 1, 2]])
    result = compensate_serial(model, calibrated, chain, integers, COMPLIANCE)
    assert result.failures == () and result.residual.dtype == np.float64 and result.residual.shape == (2,)
    assert (result.residual <= 1e-12).all()
    floats = compensate_serial(model, calibrated, chain, integers.astype(float), COMPLIANCE)
    np.testing.assert_allclose(result.commands, floats.commands, rtol=0, atol=1e-12)


def test_a_pose_the_calibrated_arm_cannot_reach_fails_with_the_error_left(ur10) -> None:
    """The calibrated wrist 1 placed 5 cm off sideways: at the zero configuration the nominal tool pose
    is 6 mm (error norm over position and rotation) out of reach; a tolerance of 1 accepts it."""
    model, chain, _ = ur10
    offset = np.array([0.0, -0.05, 0.0, 0.0, 0.0, 0.0])
    calibrated = perturb(model, {Placement("joint", "wrist_1_joint"): offset})
    result = compensate_serial(model, calibrated, chain, np.zeros((1, 6)), {})
    left = result.residual[0]
    assert 5e-3 < left < 7e-3 and np.isnan(result.commands[0]).all()
    assert result.failures == (
        (
            0,
            "the calibrated robot does not reach the nominal tool pose near this configuration "
            f"(error {left:.3g} left)",
        ),
    )
    accepted = compensate_serial(model, calibrated, chain, np.zeros((1, 6)), {}, tolerance=1.0)
    assert accepted.failures == () and accepted.residual[0] == pytest.approx(left, rel=1e-9)


# ---------------------------------------------------------------------------------------------------
# Joint limits: held at either stop, on a redundant arm for the full pose, and limits with no range


def test_a_compliant_joint_at_its_upper_stop_is_held_exactly_there(ur10) -> None:
    model, chain, calibrated = ur10
    lower, upper = chain.position_limits(model)
    program = np.array([[0.4, -1.2, upper[2], -1.0, 1.2, 0.3]])  # the elbow (compliant) at its stop
    held = compensate_serial(model, calibrated, chain, program, COMPLIANCE, position_only=True)
    assert held.failures == () and held.commands[0, 2] == upper[2]
    moved = S.compliant_readings(calibrated, chain, held.commands, COMPLIANCE)
    reached, target = tool_poses(chain, calibrated, moved)[0, :3, 3], tool_poses(chain, model, program)[0, :3, 3]
    assert np.linalg.norm(reached - target) < 1e-9


def test_a_redundant_arm_holds_a_joint_at_its_stop_and_still_matches_the_full_pose(panda) -> None:
    """The Panda's 7 joints for 6 pose rows: joint 1 held at its lower stop, the other 6 match the pose."""
    model, chain, calibrated = panda
    lower, _ = chain.position_limits(model)
    program = np.array([[lower[0], -0.5, 0.2, -2.0, 0.1, 1.6, 0.7]])
    held = compensate_serial(model, calibrated, chain, program, {})
    assert held.failures == () and held.commands[0, 0] == lower[0]
    reached, target = tool_poses(chain, calibrated, held.commands)[0], tool_poses(chain, model, program)[0]
    assert np.abs(reached - target).max() < 1e-9


def test_limits_that_leave_no_range_are_no_limits(ur10) -> None:
    """Wrist 3's limits both 0 (a model that states none): its command is neither held nor clipped."""
    model, chain, calibrated = ur10
    calibrated = calibrated.copy()
    index = chain.idx_q[5]
    lower, upper = calibrated.lowerPositionLimit.copy(), calibrated.upperPositionLimit.copy()
    lower[index] = upper[index] = 0.0
    calibrated.lowerPositionLimit, calibrated.upperPositionLimit = lower, upper
    program = np.array([[0.4, -1.2, 1.5, -1.0, 1.2, 1.0]])
    result = compensate_serial(model, calibrated, chain, program, {})
    assert result.failures == () and abs(result.commands[0, 5] - 1.0) < 1e-2
    reached, target = tool_poses(chain, calibrated, result.commands)[0], tool_poses(chain, model, program)[0]
    assert np.abs(reached - target).max() < 1e-9


# ---------------------------------------------------------------------------------------------------
# A chain from a base frame


def test_a_chain_from_a_turned_base_frame_puts_the_tool_on_the_nominal_pose() -> None:
    # UR10's `base` frame is turned pi about z from base_link: the tool Jacobian must be expressed in
    # its axes (its world placement, not the identity), or every Gauss-Newton step goes astray.
    model = load_example_robot("ur10")
    chain = SerialChain.from_model(model, "tool0", base_frame="base")
    rng = np.random.default_rng(3)
    calibrated = perturb(model, {p: rng.normal(0.0, 1e-3, 6) for p in chain.placements()})
    program = rng.uniform([-3, -2.3, 0.6, -3, -3, -3], [3, -0.6, 2.4, 3, 3, 3], (6, 6))
    result = compensate_serial(model, calibrated, chain, program, COMPLIANCE)
    assert result.failures == ()
    moved = S.compliant_readings(calibrated, chain, result.commands, COMPLIANCE)
    reached, target = tool_poses(chain, calibrated, moved), tool_poses(chain, model, program)
    assert np.abs(reached - target).max() < 1e-9


def test_a_compliance_too_large_to_invert_fails_the_row_by_name(ur10) -> None:
    """-0.01 rad/Nm at the shoulder and the elbow: q_c = q_a - c tau(q_c) does not converge, and a
    command from its last iterate would put the tool 0.4 m off; the row fails instead."""
    model, chain, calibrated = ur10
    program = np.array([[0.4, -1.2, 1.5, -1.0, 1.2, 0.3]])
    result = compensate_serial(model, calibrated, chain, program, {"shoulder_lift_joint": -0.01, "elbow_joint": -0.01})
    assert result.failures == (
        (
            0,
            "the commands under the compliance's deflection do not converge here (q_c = q_a - c tau(q_c): a "
            "compliance this large moves the deflection as much as the deflection itself)",
        ),
    )
    assert np.isnan(result.commands[0]).all() and result.residual[0] <= 1e-12


def test_the_nominal_robot_s_program_is_its_own_compensation_even_at_the_stops(ur10) -> None:
    """Calibrated as nominal, no compliance: every command is the program's, joints at their stops too
    (a joint exactly at its limit is not beyond it)."""
    model, chain, _ = ur10
    lower, upper = chain.position_limits(model)
    program = np.array([[lower[0], -1.2, 1.5, -1.0, 1.2, upper[5]]])
    result = compensate_serial(model, model, chain, program, {})
    assert result.failures == () and result.commands.tolist() == program.tolist()
