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
    moved = [pin.SE3(g.rotation @ pin.exp3(a * axis), g.translation + d) for g, a, d in zip(reference, angles, shifts)]
    errors = pose_errors_between(moved, reference)
    np.testing.assert_allclose(errors.position, np.linalg.norm(shifts, axis=1), rtol=1e-12)
    # Down to 1e-9 rad (where the rounding of the matrices themselves is the limit) and up to pi:
    # an arccos of the trace would be off by ~1e-8 rad at any angle below that.
    np.testing.assert_allclose(errors.rotation, angles, rtol=1e-7, atol=1e-15)
    # Same answer from homogeneous arrays, and symmetric in its arguments.
    as_arrays = pose_errors_between(
        np.array([g.homogeneous for g in moved]), np.array([g.homogeneous for g in reference])
    )
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


# ==================================================================================================
# Inputs as lists or arrays, batches of any shape, exact refusals
#
# Inputs as lists of SE3 or of arrays, batches of any leading shape, exact refusal messages naming the
# argument.
# ==================================================================================================


rng = np.random.default_rng(0)
A = [pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(3)]
B = [pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(3)]
EXPECTED_ROTATION = [np.linalg.norm(pin.log3(a.rotation.T @ b.rotation)) for a, b in zip(A, B)]
EXPECTED_POSITION = [np.linalg.norm(a.translation - b.translation) for a, b in zip(A, B)]


@pytest.mark.parametrize(
    "as_input",
    [
        lambda poses: poses,  # list of SE3
        lambda poses: [g.homogeneous for g in poses],  # list of arrays
        lambda poses: [g.homogeneous.tolist() for g in poses],  # list of nested lists
        lambda poses: np.array([g.homogeneous for g in poses]),
    ],
)
def test_every_documented_input_form_gives_the_same_errors(as_input):
    errors = pose_errors_between(as_input(A), as_input(B))
    np.testing.assert_allclose(errors.rotation, EXPECTED_ROTATION, atol=1e-12)
    np.testing.assert_allclose(errors.position, EXPECTED_POSITION, atol=1e-12)
    mixed = pose_errors_between(A, [g.homogeneous for g in B])
    np.testing.assert_allclose(mixed.rotation, EXPECTED_ROTATION, atol=1e-12)


def test_refusals_name_the_argument():
    good = np.array([g.homogeneous for g in A])
    with pytest.raises(InvalidInputError) as error:
        pose_errors_between(good[:, :3, :3], good)
    assert str(error.value) == (
        "poses_a: expected pinocchio.SE3 objects or (M, 4, 4) homogeneous matrices, got shape (3, 3, 3)"
    )
    with pytest.raises(InvalidInputError) as error:
        pose_errors_between(good, [np.eye(3)])
    assert str(error.value) == (
        "poses_b: expected pinocchio.SE3 objects or (M, 4, 4) homogeneous matrices, got shape (1, 3, 3)"
    )
    with pytest.raises(InvalidInputError) as error:
        pose_errors_between(good, good[:2])
    assert str(error.value) == "pose_errors_between: 3 poses against 2"
    assert pose_errors_between([], []).position.shape == (0,)


def test_rotation_angles_of_one_pair_and_of_a_two_level_batch():
    ra = np.array([g.rotation for g in A])
    rb = np.array([g.rotation for g in B])
    assert rotation_angles(ra[0], rb[0]) == pytest.approx(EXPECTED_ROTATION[0], abs=1e-12)
    grid = rotation_angles(np.stack([ra, rb]), np.stack([rb, ra]))
    assert grid.shape == (2, 3)
    np.testing.assert_allclose(grid, [EXPECTED_ROTATION, EXPECTED_ROTATION], atol=1e-12)
    # Angles beyond pi/2 and at pi.
    assert rotation_angles(np.eye(3), pin.exp3(np.array([0.0, 0.0, 3.0]))) == pytest.approx(3.0, abs=1e-12)
    assert rotation_angles(np.eye(3), np.diag([1.0, -1.0, -1.0])) == pytest.approx(np.pi, abs=1e-15)
    assert rotation_angles(np.eye(3), pin.exp3(np.array([0.0, 0.0, 4.0]))) == pytest.approx(2 * np.pi - 4.0)


def test_pose_errors_store_floats():
    errors = PoseErrors(position=[1, 2], rotation=[0, 1])
    assert errors.position.dtype == np.float64 and errors.rotation.dtype == np.float64
