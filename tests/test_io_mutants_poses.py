"""io.poses tests that kill mutants the behaviour tests let through (docs/mutation.md): the quat_tol
argument check on both sides, the tolerance at its exact value, normalization of every quaternion
component, the missing-column error, and the canonical sign of half-turn quaternions (qw = 0)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.errors import DataFileError
from m3t1r.io.poses import POSE_COLUMNS, pose_rows, poses_from_table
from m3t1r.io.tables import Table


def _table(tmp_path: Path, quaternion, columns=POSE_COLUMNS) -> Table:
    row = [1.0, 2.0, 3.0, *quaternion][: len(columns)]
    return Table(path=tmp_path / "poses.csv", columns=columns, data=[row], line_numbers=[3])


@pytest.mark.parametrize("quat_tol", [0.0, -1e-6, math.inf, -math.inf, math.nan])
def test_quat_tol_must_be_positive_and_finite(tmp_path, quat_tol):
    with pytest.raises(ValueError, match=rf"^quat_tol must be a positive finite number, got {quat_tol}$"):
        poses_from_table(_table(tmp_path, (0.0, 0.0, 0.0, 1.0)), quat_tol=quat_tol)


def test_norm_off_by_exactly_the_tolerance_is_accepted(tmp_path):
    table = _table(tmp_path, (0.0, 0.0, 0.0, 1.5))  # norm 1.5: off by exactly 0.5
    np.testing.assert_array_equal(poses_from_table(table, quat_tol=0.5)[0].rotation, np.eye(3))
    with pytest.raises(DataFileError, match=r"norm 1.5 is not 1 \(tolerance 0.4999"):
        poses_from_table(table, quat_tol=0.49999)


def test_every_quaternion_component_is_normalized(tmp_path):
    scaled = np.array([0.5, 0.5, 0.5, 0.5]) * 1.001
    pose = poses_from_table(_table(tmp_path, scaled), quat_tol=0.01)[0]
    # q = (1, 1, 1, 1) / 2 is the rotation by 120 degrees about (1, 1, 1): x -> y -> z -> x.
    np.testing.assert_allclose(pose.rotation, [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_array_equal(pose.translation, [1.0, 2.0, 3.0])


def test_missing_pose_column_names_the_file_and_the_first_missing(tmp_path):
    columns = ("x", "y", "z", "qx", "qy", "qz")
    with pytest.raises(DataFileError) as caught:
        poses_from_table(_table(tmp_path, (0.0, 0.0, 0.0), columns=columns))
    error = caught.value
    assert (error.path, error.row, error.column) == (str(tmp_path / "poses.csv"), None, "qw")
    assert str(error) == f"{tmp_path / 'poses.csv'}, column 'qw': missing pose columns: qw"
    with pytest.raises(DataFileError) as caught:
        poses_from_table(_table(tmp_path, (0.0,), columns=("x", "y", "z", "qx")))
    assert caught.value.column == "qy"
    assert str(caught.value).endswith("missing pose columns: qy, qz, qw")


@pytest.mark.parametrize(("quaternion", "canonical"), [
    ((0.6, 0.8, 0.0, 0.0), (0.6, 0.8, 0.0, 0.0)),
    ((-0.6, 0.8, 0.0, 0.0), (0.6, -0.8, 0.0, 0.0)),
    ((0.0, -0.6, 0.8, 0.0), (0.0, 0.6, -0.8, 0.0)),
    ((0.0, 0.0, 0.6, 0.0), (0.0, 0.0, 1.0, 0.0)),
])
def test_half_turn_sign_is_fixed_by_the_first_non_zero_component(quaternion, canonical):
    x, y, z, w = quaternion
    rotation = pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()
    rows = pose_rows([pin.SE3(rotation, np.array([0.1, -0.2, 0.3]))])
    assert rows.shape == (1, 7)
    np.testing.assert_allclose(rows[0, 3:], canonical, atol=1e-15)
    assert rows[0, 6] == 0.0
