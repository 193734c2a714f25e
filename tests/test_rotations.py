"""Rotation helpers (`m3t1r.model.rotations`): yaw, roll and pitch, batched roll-pitch-yaw, against
Pinocchio's own conventions."""

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.model.rotations import roll_pitch_of, rpy_batch


def test_rpy_batch_matches_pinocchio():
    rng = np.random.default_rng(2)
    rpy = rng.uniform(-1.2, 1.2, (20, 3))
    rotations = np.array([pin.rpy.rpyToMatrix(*r) for r in rpy])
    np.testing.assert_allclose(rpy_batch(rotations), rpy, atol=1e-13)


def test_rpy_batch_keeps_leading_axes_and_matches_pinocchio():
    rng = np.random.default_rng(10)
    rotations = np.array([pin.rpy.rpyToMatrix(*r) for r in rng.uniform(-1.4, 1.4, (6, 3))]).reshape(2, 3, 3, 3)
    rpy = rpy_batch(rotations)
    assert rpy.shape == (2, 3, 3)
    for index in np.ndindex(2, 3):
        np.testing.assert_allclose(rpy[index], pin.rpy.matrixToRpy(rotations[index]), atol=1e-14)


@pytest.mark.parametrize("pitch", [0.0, 0.3, -1.2, 1.5607, 1.5707, -1.5708])
def test_roll_pitch_of_is_pinocchio_s_rpy(pitch):
    """Roll and pitch of a rotation or of a placement's, as Pinocchio's ZYX convention gives them,
    also next to pitch = +-pi/2 (where the heading and the roll trade places)."""
    rng = np.random.default_rng(int(1e4 * abs(pitch)))
    for _ in range(20):
        rotation = pin.rpy.rpyToMatrix(rng.uniform(-3.0, 3.0), pitch, rng.uniform(-3.0, 3.0))
        expected = pin.rpy.matrixToRpy(rotation)[:2]
        for given in (rotation, pin.SE3(rotation, np.zeros(3)).homogeneous):
            got = np.array(roll_pitch_of(given))
            wrapped = (got - expected + np.pi) % (2 * np.pi) - np.pi
            np.testing.assert_allclose(wrapped, 0.0, atol=1e-9)
