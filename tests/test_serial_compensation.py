"""Compensation of a serial robot's joint program (`m3t1r.calibration.serial_compensation`): the
calibrated robot's tool lands on the nominal tool pose, its compliance inverted, its joint limits kept."""

from __future__ import annotations

import numpy as np
import pytest

from m3t1r.calibration import serial as S
from m3t1r.calibration.serial_compensation import compensate_serial
from m3t1r.calibration.serial_robots import load_example_robot
from m3t1r.model.poe import SerialChain, perturb, tool_poses

COMPLIANCE = {"shoulder_lift_joint": -6e-5, "elbow_joint": -9e-5}  # rad/Nm


@pytest.fixture(scope="module")
def ur10():
    model = load_example_robot("ur10")
    chain = SerialChain.from_model(model, "tool0")
    rng = np.random.default_rng(1)
    return model, chain, perturb(model, {p: rng.normal(0.0, 1e-3, 6) for p in chain.placements()})


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
