"""Metrics tests that kill mutants the behaviour tests let through (docs/mutation.md): inputs as
lists of SE3 or of arrays, batches of any leading shape, exact refusal messages naming the argument."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.errors import InvalidInputError
from m3t1r.metrics import PoseErrors, pose_errors_between, rotation_angles

rng = np.random.default_rng(0)
A = [pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(3)]
B = [pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(3)]
EXPECTED_ROTATION = [np.linalg.norm(pin.log3(a.rotation.T @ b.rotation)) for a, b in zip(A, B)]
EXPECTED_POSITION = [np.linalg.norm(a.translation - b.translation) for a, b in zip(A, B)]


@pytest.mark.parametrize("as_input", [
    lambda poses: poses,                                   # list of SE3
    lambda poses: [g.homogeneous for g in poses],          # list of arrays
    lambda poses: [g.homogeneous.tolist() for g in poses],  # list of nested lists
    lambda poses: np.array([g.homogeneous for g in poses]),
])
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
    assert str(error.value) == ("poses_a: expected pinocchio.SE3 objects or (M, 4, 4) homogeneous matrices, "
                                "got shape (3, 3, 3)")
    with pytest.raises(InvalidInputError) as error:
        pose_errors_between(good, [np.eye(3)])
    assert str(error.value) == ("poses_b: expected pinocchio.SE3 objects or (M, 4, 4) homogeneous matrices, "
                                "got shape (1, 3, 3)")
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
