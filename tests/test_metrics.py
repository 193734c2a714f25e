"""The shared pose-error type and its pose-by-pose comparison."""

from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration import closed_loop as calibration
from m3t1r.calibration import serial_evaluation
from m3t1r.errors import InvalidInputError
from m3t1r.metrics import PoseErrors, pose_errors_between, rotation_angles


def test_summaries() -> None:
    errors = PoseErrors(position=np.array([3e-6, 4e-6, 0.0]), rotation=np.array([1e-5, 2e-5, 2e-5]))
    assert errors.position_mean == pytest.approx(7e-6 / 3)
    assert errors.position_max == 4e-6
    assert errors.position_rms == pytest.approx(np.sqrt(25e-12 / 3))
    assert errors.rotation_mean == pytest.approx(5e-5 / 3)
    assert errors.rotation_max == 2e-5
    assert errors.rotation_rms == pytest.approx(np.sqrt(9e-10 / 3))
    assert all(isinstance(v, float) for v in (errors.position_mean, errors.position_max, errors.rotation_rms))


def test_missing_orientation_stays_nan_and_position_is_unaffected() -> None:
    errors = PoseErrors(np.array([1.0, 3.0]), np.full(2, np.nan))
    assert errors.position_rms == pytest.approx(np.sqrt(5.0))
    assert np.isnan(errors.rotation_mean) and np.isnan(errors.rotation_rms) and np.isnan(errors.rotation_max)


def test_construction_normalises_and_validates() -> None:
    errors = PoseErrors([1, 2], [3, 4])  # type: ignore[arg-type]
    assert errors.position.dtype == float and errors.rotation.shape == (2,)
    with pytest.raises(dataclasses.FrozenInstanceError):
        errors.position = np.zeros(2)  # type: ignore[misc]
    with pytest.raises(InvalidInputError, match="one value per pose"):
        PoseErrors(np.zeros(3), np.zeros(2))
    with pytest.raises(InvalidInputError, match="one value per pose"):
        PoseErrors(np.zeros((3, 1)), np.zeros((3, 1)))


def test_one_type_everywhere() -> None:
    # One pose-error type: both calibrations use metrics.PoseErrors, which the package exports.
    import m3t1r

    assert calibration.PoseErrors is PoseErrors
    assert serial_evaluation.PoseErrors is PoseErrors
    assert m3t1r.PoseErrors is PoseErrors and "PoseErrors" in m3t1r.__all__


def test_pose_errors_between_known_poses() -> None:
    rng = np.random.default_rng(40)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angles = np.array([0.0, 1e-9, 1e-5, 0.7, 3.0, np.pi - 1e-7, np.pi])
    shifts = rng.normal(scale=1e-3, size=(len(angles), 3))
    reference = [pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)) for _ in angles]
    moved = [
        pin.SE3(g.rotation @ pin.exp3(a * axis), g.translation + d) for g, a, d in zip(reference, angles, shifts)
    ]
    errors = pose_errors_between(moved, reference)
    np.testing.assert_allclose(errors.position, np.linalg.norm(shifts, axis=1), rtol=1e-12)
    # Down to 1e-9 rad (where the rounding of the matrices themselves is the limit) and up to pi:
    # an arccos of the trace would be off by ~1e-8 rad at any angle below that.
    np.testing.assert_allclose(errors.rotation, angles, rtol=1e-7, atol=1e-15)
    # Same answer from homogeneous arrays, and symmetric in its arguments.
    as_arrays = pose_errors_between(np.array([g.homogeneous for g in moved]), np.array([g.homogeneous for g in reference]))
    np.testing.assert_array_equal(as_arrays.position, errors.position)
    np.testing.assert_array_equal(as_arrays.rotation, errors.rotation)
    swapped = pose_errors_between(reference, moved)
    np.testing.assert_allclose(swapped.rotation, errors.rotation, rtol=1e-12, atol=1e-15)


def test_rotation_angles_equal_pinocchio_log3() -> None:
    rng = np.random.default_rng(41)
    a = np.array([pin.exp3(rng.normal(size=3)) for _ in range(50)])
    b = np.array([pin.exp3(rng.normal(size=3)) for _ in range(50)])
    expected = [np.linalg.norm(pin.log3(ra.T @ rb)) for ra, rb in zip(a, b)]
    np.testing.assert_allclose(rotation_angles(a, b), expected, rtol=1e-12)


def test_pose_errors_between_validates() -> None:
    poses = [pin.SE3.Identity()] * 3
    with pytest.raises(InvalidInputError, match="3 poses against 2"):
        pose_errors_between(poses, poses[:2])
    with pytest.raises(InvalidInputError, match="poses_b"):
        pose_errors_between(poses, np.zeros((3, 3, 3)))
    empty = pose_errors_between([], [])
    assert empty.position.shape == (0,) and empty.rotation.shape == (0,)
