"""Rotation helpers (`m3t1r.model.rotations`): yaw, roll and pitch, batched roll-pitch-yaw, against
Pinocchio's own conventions."""

import math
import warnings

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.model.rotations import jlog3_batch, log3_batch, roll_pitch_of, rpy_batch, skew, yaw_of


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


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_at_the_gimbal_lock_the_heading_is_moved_into_roll_as_pinocchio_does(sign):
    """Pitch exactly +-pi/2 (R20 = -+1, R21 = R22 = 0): only roll -+ yaw is defined; Pinocchio's
    convention sets the heading to 0 and puts it into roll, where atan2(R21, R22) would give 0."""
    yaw = 0.5
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[0.0, -s, sign * c], [0.0, c, sign * s], [-sign, 0.0, 0.0]])
    roll, pitch = roll_pitch_of(rotation)
    assert pitch == pytest.approx(sign * math.pi / 2, abs=1e-15)
    assert roll == pytest.approx(-sign * yaw, abs=1e-15)
    np.testing.assert_allclose(pin.rpy.rpyToMatrix(roll, pitch, 0.0), rotation, atol=1e-15)


# ---------------------------------------------------------------------------------------------------
# The platform's yaw: the heading of its x axis


@pytest.mark.parametrize("yaw", [0.0, 0.4, -2.9, 3.1])
def test_yaw_of_is_the_heading_of_the_x_axis_even_under_tilt(yaw):
    assert yaw_of(pin.rpy.rpyToMatrix(0.0, 0.0, yaw)) == pytest.approx(yaw, abs=1e-14)
    tilted = pin.rpy.rpyToMatrix(0.2, -0.1, yaw)
    assert yaw_of(tilted) == pytest.approx(np.arctan2(tilted[1, 0], tilted[0, 0]), abs=1e-15)
    assert yaw_of(tilted) == pytest.approx(yaw, abs=1e-14)  # ZYX: the heading is the last angle


# ---------------------------------------------------------------------------------------------------
# log3 and its Jacobian, batched, against Pinocchio's


def _rotations(angles, seed):
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    logs = np.asarray(angles)[:, None] * axes
    return logs, np.array([pin.exp3(w) for w in logs])


ANGLES = [0.0, 1e-9, 1e-4, 9.9e-3, 1.01e-2, 0.3, 0.9, 1.005, 1.5, 2.9, 3.0, 3.1, 3.14159]


def test_log3_batch_is_pin_log3_at_every_angle_up_to_pi():
    """Small angles, both sides of the near-pi switch (cos a = -0.99 at a = 3.0002) and next to pi."""
    logs, rotations = _rotations(ANGLES, 3)
    got, angles = log3_batch(rotations)
    for w, rotation, angle, expected in zip(got, rotations, angles, logs):
        np.testing.assert_allclose(w, pin.log3(rotation), atol=1e-9, rtol=0)
        np.testing.assert_allclose(w, expected, atol=1e-7, rtol=0)
        assert angle == pytest.approx(np.linalg.norm(expected), abs=1e-9)
    assert got[0].tolist() == [0.0, 0.0, 0.0] and angles[0] == 0.0


def test_log3_batch_near_pi_reads_the_axis_from_the_symmetric_part():
    """At a = pi - 1e-10 the antisymmetric part is 2e-10 in size: read from it alone, the axis would be
    off by 8e-7 rad; the symmetric part keeps it to 1e-9."""
    axis = np.array([2.0, -1.0, 2.0]) / 3.0
    rotation = pin.exp3((np.pi - 1e-10) * axis)
    got, angle = log3_batch(rotation[None])
    assert angle[0] == pytest.approx(np.pi, abs=1e-9)
    np.testing.assert_allclose(got[0], (np.pi - 1e-10) * axis, atol=1e-9, rtol=0)


def test_jlog3_batch_is_pin_jlog3_on_both_sides_of_the_series_switch():
    logs, rotations = _rotations(ANGLES[:-1], 5)
    angles = np.linalg.norm(logs, axis=1)
    got = jlog3_batch(logs, angles)
    assert got.shape == (len(logs), 3, 3)
    for jacobian, rotation in zip(got, rotations):
        np.testing.assert_allclose(jacobian, pin.Jlog3(rotation), atol=1e-9, rtol=0)


def test_jlog3_batch_of_no_rotation_is_the_identity_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = jlog3_batch(np.zeros((2, 3)), np.zeros(2))
        assert log3_batch(np.stack([np.eye(3)] * 2))[0].tolist() == [[0.0] * 3] * 2
    np.testing.assert_array_equal(got, np.stack([np.eye(3)] * 2))


def test_jlog3_batch_series_is_exact_to_rounding_at_small_angles():
    """b(a) = 1/12 + a^2/720 + a^4/30240 below a = 1e-2: at a = 9e-3 its last term is 2e-13 of b, and
    the closed form there loses about 1e-12 to cancellation; the series keeps pin's value to 1e-15."""
    logs = np.array([[9e-3, 0.0, 0.0], [0.0, 5e-3, 5e-3]])
    angles = np.linalg.norm(logs, axis=1)
    got = jlog3_batch(logs, angles)
    for w, angle, jacobian in zip(logs, angles, got):
        b = 1.0 / 12.0 + angle**2 / 720.0 + angle**4 / 30240.0
        wx = skew(w)
        np.testing.assert_allclose(jacobian, np.eye(3) + 0.5 * wx + b * wx @ wx, atol=1e-17, rtol=0)
        np.testing.assert_allclose(jacobian, pin.Jlog3(pin.exp3(w)), atol=1e-14, rtol=0)


# ---------------------------------------------------------------------------------------------------
# Cross-product matrices


def test_skew_is_the_cross_product_and_keeps_leading_axes():
    rng = np.random.default_rng(8)
    x, y = rng.normal(size=(2, 4, 3))
    matrices = skew(x.reshape(2, 2, 3))
    assert matrices.shape == (2, 2, 3, 3)
    np.testing.assert_allclose((matrices.reshape(4, 3, 3) @ y[:, :, None])[..., 0], np.cross(x, y), atol=1e-15)
    np.testing.assert_array_equal(matrices, -np.swapaxes(matrices, -1, -2))
    assert skew(np.array([1.0, 2.0, 3.0])).tolist() == [[0.0, -3.0, 2.0], [3.0, 0.0, -1.0], [-2.0, 1.0, 0.0]]
