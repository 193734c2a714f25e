"""io tests that kill mutants the behaviour tests let through (docs/mutation.md): the quaternion
norm tolerance at its boundary, from both sides."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from m3t1r.errors import DataFileError
from m3t1r.io.poses import POSE_COLUMNS, poses_from_table
from m3t1r.io.tables import Table


def _table(tmp_path: Path, norm_error: float) -> Table:
    quaternion = np.array([0.0, 0.0, 0.6, 0.8]) * (1.0 + norm_error)
    data = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0, *quaternion]])
    return Table(path=tmp_path / "poses.csv", columns=POSE_COLUMNS, data=data, line_numbers=[2, 7])


@pytest.mark.parametrize("norm_error", [1e-4, 1e-5, 2e-6, -2e-6])
def test_default_quaternion_tolerance_refuses_just_beyond_1e_6(tmp_path, norm_error):
    with pytest.raises(DataFileError, match=r"norm .* is not 1 \(tolerance 1e-06\)") as caught:
        poses_from_table(_table(tmp_path, norm_error))
    assert caught.value.row == 7


@pytest.mark.parametrize("norm_error", [5e-7, -5e-7, 0.0])
def test_default_quaternion_tolerance_accepts_within_1e_6_and_normalizes(tmp_path, norm_error):
    poses = poses_from_table(_table(tmp_path, norm_error))
    rotation = poses[1].rotation
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(rotation[:2, :2], [[1 - 2 * 0.36, -2 * 0.48], [2 * 0.48, 1 - 2 * 0.36]], atol=1e-12)
    np.testing.assert_array_equal(poses[1].translation, [1.0, 2.0, 3.0])


def test_explicit_quaternion_tolerance_is_used_at_its_boundary(tmp_path):
    table = _table(tmp_path, 2e-3)
    assert len(poses_from_table(table, quat_tol=3e-3)) == 2
    with pytest.raises(DataFileError, match=r"tolerance 0.001\)"):
        poses_from_table(table, quat_tol=1e-3)
