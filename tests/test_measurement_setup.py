"""The measurement setup (`m3t1r.calibration.measurement_setup`): tracker frame and marker.

Exact refusals, the quaternion-norm tolerance from both sides, the collinearity threshold from both
sides, reports round trips, and the registrations in closed form, including reflections and a marker
turned by more than pi/2.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.measurement_setup import (
    LENGTH_UNITS,
    MeasurementSetup,
    register_frame,
    register_marker_rotation,
    se3_from_report,
    se3_to_report,
)
from m3t1r.errors import IdentificationError, InvalidInputError

FRAME = pin.SE3(pin.exp3(np.array([0.4, -2.5, 1.0])), np.array([3.0, -1.5, 0.8]))
MARKER = pin.SE3(pin.exp3(np.array([0.0, 2.9, 0.3])), np.array([0.07, 0.0, 0.02]))


def _message(call, error=InvalidInputError) -> str:
    with pytest.raises(error) as raised:
        call()
    return str(raised.value)


def test_report_entry_is_translation_then_xyzw_quaternion_as_floats():
    report = se3_to_report(pin.SE3(np.eye(3), np.array([1.0, 2.0, 3.0])))
    assert report == {"translation": [1.0, 2.0, 3.0], "quaternion": [0.0, 0.0, 0.0, 1.0]}
    assert all(type(v) is float for v in report["translation"] + report["quaternion"])
    back = se3_from_report(se3_to_report(FRAME), "frame")
    np.testing.assert_allclose(back.homogeneous, FRAME.homogeneous, atol=1e-15)
    # Integers and lists are read as floats.
    np.testing.assert_allclose(
        se3_from_report({"translation": [1, 2, 3], "quaternion": [0, 0, 0, 1]}, "x").translation, [1.0, 2.0, 3.0]
    )


@pytest.mark.parametrize(
    "entry, detail",
    [
        ({"quaternion": [0, 0, 0, 1]}, "('translation')"),
        ({"translation": [1, 2, 3]}, "('quaternion')"),
        ({"translation": [1, 2], "quaternion": [0, 0, 0, 1]}, "(cannot reshape array of size 2 into shape (3,))"),
        ({"translation": [1, 2, 3], "quaternion": [0, 0, 1]}, "(cannot reshape array of size 3 into shape (4,))"),
        ({"translation": ["a", 2, 3], "quaternion": [0, 0, 0, 1]}, "(could not convert string to float: 'a')"),
        ({"translation": [1, 2, 3], "quaternion": [0, 0, "a", 1]}, "(could not convert string to float: 'a')"),
        ({"translation": [1, 2, 3], "quaternion": None}, "(cannot reshape array of size 1 into shape (4,))"),
        (
            {"translation": object(), "quaternion": [0, 0, 0, 1]},
            "(float() argument must be a string or a real number, not 'object')",
        ),
    ],
)
def test_malformed_entry_is_refused_naming_what_and_why(entry, detail):
    assert _message(lambda: se3_from_report(entry, "report 'marker'")) == (
        "report 'marker': expected translation [x, y, z] and quaternion [qx, qy, qz, qw] " + detail
    )


@pytest.mark.parametrize("key, index", [("translation", 0), ("translation", 2), ("quaternion", 1), ("quaternion", 3)])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_entry_is_refused(key, index, value):
    entry = se3_to_report(pin.SE3.Identity())
    entry[key][index] = value
    assert _message(lambda: se3_from_report(entry, "frame")) == "frame: non-finite value"


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_quaternion_norm_tolerance_is_1e_6_from_both_sides(sign):
    quaternion = np.array([0.1, -0.2, 0.3, 0.9])
    quaternion /= np.linalg.norm(quaternion)
    inside = {"translation": [0, 0, 0], "quaternion": list(quaternion * (1 + sign * 0.9e-6))}
    rotation = se3_from_report(inside, "marker").rotation
    # Accepted and renormalised: the rotation is orthonormal to rounding (compensation checks 1e-9).
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    outside = {"translation": [0, 0, 0], "quaternion": list(quaternion * (1 + sign * 1.1e-6))}
    assert _message(lambda: se3_from_report(outside, "marker")) == (
        f"marker: quaternion norm {1 + sign * 1.1e-6:.6g} is not 1"
    )


def test_measured_poses_compose_frame_platform_marker_in_that_order():
    rng = np.random.default_rng(0)
    platform = np.array([pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)).homogeneous for _ in range(4)])
    setup = MeasurementSetup(FRAME, MARKER)
    expected = np.array([(FRAME * pin.SE3(p) * MARKER).homogeneous for p in platform])
    np.testing.assert_allclose(setup.measured_poses(platform), expected, atol=1e-12)
    np.testing.assert_allclose(setup.measured_poses(platform.tolist()), expected, atol=1e-12)
    default = MeasurementSetup()
    np.testing.assert_array_equal(default.frame.homogeneous, np.eye(4))
    np.testing.assert_array_equal(default.marker.homogeneous, np.eye(4))
    np.testing.assert_allclose(default.measured_poses(platform), platform)


def test_setup_report_keys_round_trip_and_refusals():
    setup = MeasurementSetup(FRAME, MARKER)
    report = setup.to_report()
    assert report == {"measurement_frame": se3_to_report(FRAME), "marker": se3_to_report(MARKER)}
    again = MeasurementSetup.from_report(report)
    np.testing.assert_allclose(again.frame.homogeneous, FRAME.homogeneous, atol=1e-15)
    np.testing.assert_allclose(again.marker.homogeneous, MARKER.homogeneous, atol=1e-15)
    only_marker = MeasurementSetup.from_report({"marker": se3_to_report(MARKER), "measurement_frame": None})
    np.testing.assert_array_equal(only_marker.frame.homogeneous, np.eye(4))
    np.testing.assert_allclose(only_marker.marker.homogeneous, MARKER.homogeneous, atol=1e-15)
    assert (
        _message(lambda: MeasurementSetup.from_report({"marker": [1, 2, 3]})) == "report 'marker': expected an object"
    )
    assert _message(lambda: MeasurementSetup.from_report({"measurement_frame": "identity"})) == (
        "report 'measurement_frame': expected an object"
    )
    bad = {"measurement_frame": {"translation": [0, 0, np.nan], "quaternion": [0, 0, 0, 1]}}
    assert _message(lambda: MeasurementSetup.from_report(bad)) == "report 'measurement_frame': non-finite value"


def test_length_units():
    assert dict(LENGTH_UNITS) == {"m": 1.0, "mm": 1e-3}


def _points(n: int, seed: int = 1) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 3))
    return poses


def test_registration_is_exact_for_a_rotation_beyond_pi_over_2_and_least_squares_with_noise():
    poses = _points(20)
    measured = (FRAME.homogeneous @ poses)[:, :3, 3]
    found = register_frame(poses, measured)
    np.testing.assert_allclose(found.homogeneous, FRAME.homogeneous, atol=1e-12)
    found = register_frame(poses.tolist(), measured.tolist())
    np.testing.assert_allclose(found.homogeneous, FRAME.homogeneous, atol=1e-12)
    # Three non-collinear points are enough.
    np.testing.assert_allclose(register_frame(poses[:3], measured[:3]).homogeneous, FRAME.homogeneous, atol=1e-10)
    noisy = measured + np.random.default_rng(2).normal(0.0, 1e-4, measured.shape)
    fitted = register_frame(poses, noisy)
    cost = lambda frame: np.sum(((frame.homogeneous @ poses)[:, :3, 3] - noisy) ** 2)  # noqa: E731
    for xi in np.eye(6) * 1e-5:
        assert cost(fitted) < cost(fitted * pin.exp6(xi)) and cost(fitted) < cost(fitted * pin.exp6(-xi))


def test_registration_refuses_two_points_and_collinear_ones_at_the_documented_threshold():
    poses = _points(3)
    message = "the measured positions are too few or collinear to place the measurement frame"
    assert _message(lambda: register_frame(poses[:2], poses[:2, :3, 3]), IdentificationError) == message
    line = np.tile(np.eye(4), (5, 1, 1))
    line[:, 0, 3] = np.linspace(-1.0, 1.0, 5)  # spread 1 m
    near = line.copy()
    near[2, 1, 3] = 1.2e-6  # second singular value of the centred points just above 1e-6
    register_frame(near, near[:, :3, 3])
    near[2, 1, 3] = 1.0e-6  # just below
    assert _message(lambda: register_frame(near, near[:, :3, 3]), IdentificationError) == message
    # The threshold is relative to the spread: the same shape 1000x smaller is as collinear.
    small = line.copy()
    small[:, :3, 3] *= 1e-3
    small[2, 1, 3] = 1.2e-9
    register_frame(small, small[:, :3, 3])
    small[2, 1, 3] = 1.0e-9
    assert _message(lambda: register_frame(small, small[:, :3, 3]), IdentificationError) == message


def test_marker_rotation_beyond_pi_over_2_and_the_nearest_rotation_with_noise():
    rng = np.random.default_rng(3)
    platform = np.array(
        [
            pin.SE3(pin.exp3(np.array([0.2 * t, 0, t])), rng.normal(size=3)).homogeneous
            for t in np.linspace(-2.5, 2.5, 9)
        ]
    )
    measured = FRAME.rotation @ platform[:, :3, :3] @ MARKER.rotation
    np.testing.assert_allclose(register_marker_rotation(FRAME, platform, measured), MARKER.rotation, atol=1e-12)
    np.testing.assert_allclose(
        register_marker_rotation(FRAME, platform.tolist(), measured.tolist()), MARKER.rotation, atol=1e-12
    )
    # Noisy estimates: a proper rotation (det +1, not a reflection) close to the truth.
    noisy = np.array([m @ pin.exp3(rng.normal(0.0, 0.05, 3)) for m in measured])
    found = register_marker_rotation(FRAME, platform, noisy)
    np.testing.assert_allclose(found @ found.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(found) == pytest.approx(1.0)
    assert np.linalg.norm(pin.log3(found.T @ MARKER.rotation)) < 0.05
    # Estimates that average to a reflection-like sum still give a rotation (the det correction).
    flips = np.array([np.diag([1.0, 1.0, 1.0]), np.diag([-1.0, -1.0, 1.0]), np.diag([1.0, -1.0, -1.0])])
    result = register_marker_rotation(pin.SE3.Identity(), np.tile(np.eye(4), (3, 1, 1)), flips)
    assert np.linalg.det(result) == pytest.approx(1.0)


def test_setup_from_command_line_numbers():
    """Frame from x, y, z, roll, pitch, yaw (R = Rz(yaw) Ry(pitch) Rx(roll)); marker from x, y, z with the
    platform's orientation; identity for what is not given."""
    from m3t1r.calibration.measurement_setup import MeasurementSetup as Setup

    setup = Setup.from_numbers([1.0, -2.0, 0.5, 0.1, -0.2, 0.3], (0.07, -0.02, 0.03))
    rz, ry, rx = (
        pin.AngleAxis(a, axis).matrix()
        for a, axis in (
            (0.3, np.array([0.0, 0.0, 1.0])),
            (-0.2, np.array([0.0, 1.0, 0.0])),
            (0.1, np.array([1.0, 0.0, 0.0])),
        )
    )
    np.testing.assert_allclose(setup.frame.rotation, rz @ ry @ rx, atol=1e-15)
    np.testing.assert_array_equal(setup.frame.translation, [1.0, -2.0, 0.5])
    np.testing.assert_array_equal(setup.marker.rotation, np.eye(3))
    np.testing.assert_array_equal(setup.marker.translation, [0.07, -0.02, 0.03])
    only_marker = Setup.from_numbers(marker_xyz=np.array([[1, 2, 3]]))
    assert only_marker.frame.isIdentity() and only_marker.marker.translation.dtype == float
    np.testing.assert_array_equal(only_marker.marker.translation, [1.0, 2.0, 3.0])
    only_frame = Setup.from_numbers(np.array([[0, 0, 1, 0, 0, np.pi / 2]]))
    assert only_frame.marker.isIdentity()
    np.testing.assert_allclose(only_frame.frame.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    assert Setup.from_numbers().frame.isIdentity() and Setup.from_numbers().marker.isIdentity()
    as_text = Setup.from_numbers(["1", "-2", "0.5", "0.1", "-0.2", "0.3"], ["0.07", "-0.02", "0.03"])  # argv strings
    assert as_text.frame.isApprox(setup.frame, 1e-15) and as_text.marker.isApprox(setup.marker, 1e-15)


@pytest.mark.parametrize(
    "frame, marker, message",
    [
        ([1.0, 2.0, 3.0], None, "measurement frame x, y, z, roll, pitch, yaw: expected 6 values, got 3"),
        (
            [0.0, 0.0, 0.0, 0.0, 0.0, np.nan],
            None,
            "measurement frame x, y, z, roll, pitch, yaw: non-finite value nan at index 5",
        ),
        (None, [1.0, 2.0], "marker x, y, z: expected 3 values, got 2"),
    ],
)
def test_setup_numbers_are_refused_naming_what_they_are(frame, marker, message):
    """A wrong count or a non-finite value of the command-line numbers is refused naming the numbers."""
    with pytest.raises(InvalidInputError) as caught:
        MeasurementSetup.from_numbers(frame, marker)
    assert str(caught.value) == message
