"""Poses as CSV rows: `x, y, z, qx, qy, qz, qw` (m, unit quaternion), read from a `Table` and written
with a canonical quaternion sign."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import pinocchio as pin

from m3t1r.errors import DataFileError
from m3t1r.io.tables import Table

__all__ = ["POSE_COLUMNS", "JOINT_COLUMN_PREFIX", "measurement_column", "pose_rows", "poses_from_table"]

POSE_COLUMNS: tuple[str, ...] = ("x", "y", "z", "qx", "qy", "qz", "qw")
JOINT_COLUMN_PREFIX = "joint:"
"""Prefix of a measurement file's column for a joint named like a pose column (x, y, z, qx, ...)."""


def measurement_column(joint: str) -> str:
    """The measurement-file column of a joint: its name, or `joint:NAME` when the name is a pose
    column's (a joint named `x` would otherwise read as the measured x)."""
    return JOINT_COLUMN_PREFIX + joint if joint in POSE_COLUMNS else joint


"""Columns of a pose: position in m, then the unit quaternion with its scalar part last."""


def poses_from_table(table: Table, quat_tol: float = 1e-6) -> list[pin.SE3]:
    """The pose of each row of a table with the `POSE_COLUMNS`, as placements.

    Each quaternion must have unit norm within `quat_tol` (dimensionless) and is then
    normalized: a looser quaternion is a corrupted or mislabelled column, not rounding.

    Raises:
        DataFileError: a pose column is missing, or a quaternion's norm is off by more than
            `quat_tol`, naming its line.
    """
    if not (math.isfinite(quat_tol) and quat_tol > 0):
        raise ValueError(f"quat_tol must be a positive finite number, got {quat_tol}")
    missing = [name for name in POSE_COLUMNS if not table.has_column(name)]
    if missing:
        raise DataFileError(table.path, f"missing pose columns: {', '.join(missing)}", column=missing[0])
    xyzquat = np.column_stack([table.column(name) for name in POSE_COLUMNS])
    norms = np.linalg.norm(xyzquat[:, 3:], axis=1)
    off = np.flatnonzero(np.abs(norms - 1.0) > quat_tol)
    if off.size:
        row = int(off[0])
        raise table.error(row, f"quaternion (qx, qy, qz, qw) norm {norms[row]:.6g} is not 1 (tolerance {quat_tol:g})")
    xyzquat[:, 3:] /= norms[:, np.newaxis]
    return [pin.XYZQUATToSE3(row) for row in xyzquat]


def pose_rows(poses: Iterable[pin.SE3]) -> np.ndarray:
    """(n, 7) rows `x, y, z, qx, qy, qz, qw` (m, unit quaternion) of `poses`, in `POSE_COLUMNS` order.

    q and -q are the same rotation; the sign is fixed to qw > 0 (and, when qw = 0, to a
    positive first non-zero vector component) so that equal poses give equal rows, and files
    can be compared and checked for duplicates.
    """
    rows = np.array([pin.SE3ToXYZQUAT(pose) for pose in poses], dtype=float).reshape(-1, 7)
    quaternions = rows[:, 3:]
    vector = quaternions[:, :3]
    leading = vector[np.arange(len(rows)), np.argmax(vector != 0.0, axis=1)] if len(rows) else np.empty(0)
    flip = (quaternions[:, 3] < 0.0) | ((quaternions[:, 3] == 0.0) & (leading < 0.0))
    quaternions[flip] *= -1.0
    rows += 0.0  # turns -0.0 into 0.0, so files never show "-0.0"
    return rows
