"""The machine's data files: slider sets, platform poses, calibration measurements, targets.

All are CSV tables read by `m3t1r.io.tables.read_table` (header row, `#` comments, SI units), with
columns named after the machine: sliders by their actuated joint names, passive readings by their
joint names, platform poses as x, y, z [m] and a unit quaternion qx, qy, qz, qw (platform frame in
the base frame). Every check names the file, line and column at fault; models/README.md documents
the formats.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import pinocchio as pin

from m3t1r.calibration.measurement_setup import LENGTH_UNITS
from m3t1r.calibration.measurements import PoseMeasurements
from m3t1r.errors import DataFileError
from m3t1r.io.instruments.records import CONVERTED_COLUMNS
from m3t1r.io.paths import StrPath
from m3t1r.io.poses import POSE_COLUMNS, measurement_column, pose_rows, poses_from_table
from m3t1r.io.tables import Table, read_table, write_table
from m3t1r.model.description import Mechanism
from m3t1r.model.task import TaskSpec

__all__ = [
    "TARGET_COLUMNS", "read_actuators", "write_actuators", "read_poses", "write_poses", "read_targets",
    "MeasurementFile", "read_measurements", "write_measurements", "measurement_table", "sha256_of",
]

TARGET_COLUMNS = TaskSpec("platform").columns  # the M machine's: platform position [m] and yaw [rad]
_QUATERNION = ("qx", "qy", "qz", "qw")


def sha256_of(path: StrPath) -> str:
    """Hex digest of a file's bytes (provenance in reports)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _check_limits(table: Table, mechanism: Mechanism, names: Sequence[str], scale: Mapping[str, float] | None = None,
                  columns: Sequence[str] | None = None) -> None:
    """Every value within its joint's limits, after `scale` (column -> metres per file unit);
    `columns`: the joints' columns (default their names)."""
    lower, upper = mechanism.joint_limits(tuple(names))
    scale = scale or {}
    for k, (name, column) in enumerate(zip(names, columns or names)):
        values = table.column(column) * scale.get(column, 1.0)
        outside = np.flatnonzero((values < lower[k]) | (values > upper[k]))
        if outside.size:
            row = int(outside[0])
            hint = "(SI units: m for sliders, rad for hinges)"
            prismatic = name in _prismatic_joints(mechanism, names)
            if prismatic and scale.get(column, 1.0) == 1.0 and np.all((values * 1e-3 >= lower[k]) & (values * 1e-3 <= upper[k])):
                hint = "(every value of the column is within the limits in millimetres: use --units mm)"
            elif not prismatic and 2 * outside.size > len(values) \
                    and np.all((np.radians(values) >= lower[k]) & (np.radians(values) <= upper[k])):
                hint = "(every value of the column is within the limits in degrees: give radians)"
            raise table.error(row, f"{values[row]:.6g} is beyond the joint limit [{lower[k]:.6g}, {upper[k]:.6g}] "
                                   + hint, column=column)


def _prismatic_joints(mechanism: Mechanism, names: Iterable[str]) -> tuple[str, ...]:
    """The prismatic joints among `names`: their readings are lengths, scaled by --units."""
    model = mechanism.model
    return tuple(n for n in names if model.existJointName(n)
                 and model.joints[model.getJointId(n)].shortname().startswith("JointModelP"))


def _length_scale(table: Table, mechanism: Mechanism, units: str, joints: Sequence[str]) -> dict[str, float]:
    """Column -> metres per file unit for the length columns (x, y, z and the prismatic ones of `joints`)."""
    if units not in LENGTH_UNITS:
        raise DataFileError(table.path, f"unknown length unit '{units}' (one of {', '.join(LENGTH_UNITS)})")
    factor = LENGTH_UNITS[units]
    lengths = ("x", "y", "z") + tuple(measurement_column(n) for n in _prismatic_joints(mechanism, joints))
    return {name: factor for name in lengths if table.has_column(name)}


def read_actuators(path: StrPath, mechanism: Mechanism) -> tuple[np.ndarray, np.ndarray]:
    """Slider sets (n x 4) [m] in `actuated_joints` order, and each row's line number."""
    names = mechanism.actuated_joints
    table = read_table(path, required=names)
    _check_limits(table, mechanism, names)
    return np.column_stack([table.column(n) for n in names]), table.line_numbers


def write_actuators(path: StrPath, mechanism: Mechanism, actuators: np.ndarray, comments: Sequence[str] = (),
                    protect: Iterable[StrPath] = ()) -> None:
    """Write slider sets as a CSV table with the machine's actuated joint names as columns."""
    write_table(path, mechanism.actuated_joints, np.asarray(actuators, dtype=float), comments, protect)


def read_poses(path: StrPath) -> tuple[list[pin.SE3], np.ndarray]:
    """Platform poses (x, y, z, qx, qy, qz, qw per row) and line numbers; quaternions checked unit."""
    table = read_table(path, required=POSE_COLUMNS)
    return poses_from_table(table), table.line_numbers


def write_poses(path: StrPath, poses: Sequence[pin.SE3], comments: Sequence[str] = (),
                protect: Iterable[StrPath] = ()) -> None:
    """Write platform poses as a CSV table (m, unit quaternion)."""
    write_table(path, POSE_COLUMNS, pose_rows(poses), comments, protect)


def read_targets(path: StrPath, task: TaskSpec | None = None) -> tuple[list[pin.SE3] | np.ndarray, np.ndarray]:
    """Commanded poses of the task frame, and the file's line numbers.

    Either the task's own columns (`TaskSpec.columns`: x, y, z, theta on the M machine, x, y on a
    planar five-bar, qx, qy, qz, qw on an orientation mechanism), returned as an (n, d) array, or a
    full pose x, y, z, qx, qy, qz, qw, returned as SE3 (the task ignores what it does not command).
    task: default the M machine's (x, y, z, theta of the platform).
    """
    task = task or TaskSpec("platform")
    columns = task.columns
    optional = tuple(dict.fromkeys(c for c in columns + POSE_COLUMNS if c not in _QUATERNION))
    groups = (_QUATERNION,)
    table = read_table(path, required=(), optional=optional, optional_groups=groups)
    full_pose = all(table.has_column(c) for c in POSE_COLUMNS)
    own = all(table.has_column(c) for c in columns)
    if task.rotation == "yaw" and full_pose and table.has_column("theta"):
        raise DataFileError(table.path, "a target file needs either a 'theta' column or qx, qy, qz, qw, not both")
    if own and not (full_pose and task.rotation != "yaw"):
        return np.column_stack([table.column(n) for n in columns]), table.line_numbers
    if full_pose:
        return poses_from_table(table), table.line_numbers
    missing = [c for c in columns if not table.has_column(c)]
    raise DataFileError(table.path, f"a target file needs the task's columns {', '.join(columns)} or a full pose "
                                    f"{', '.join(POSE_COLUMNS)}; missing {', '.join(missing)}", column=missing[0])


@dataclass(frozen=True)
class MeasurementFile:
    """A calibration measurement file, read and checked against a mechanism.

    measurements: slider readings and measured platform poses (position-only when the file has no
    quaternion columns); passive: optional passive-joint readings (n x k) [rad or m] named by
    `passive_joints` (paper section 4: encoders on passive joints); lines: file line per pose;
    sources: the `source` column of a converted file (where each pose is in the tracker's file), or None.
    """

    path: Path
    measurements: PoseMeasurements
    passive_joints: tuple[str, ...]
    passive: np.ndarray
    lines: np.ndarray
    sha256: str
    sources: np.ndarray | None = None


def read_measurements(path: StrPath, mechanism: Mechanism, units: str = "m") -> MeasurementFile:
    """Read a measurement CSV: actuator columns (named by the actuated joints), optional passive
    joint columns (named by joint), x, y, z and optionally qx, qy, qz, qw.

    units: the length unit of the file's length columns (x, y, z and prismatic joints), "m" or
    "mm"; everything returned is in SI units. Raises DataFileError naming file, line and column
    for: missing/extra/unknown columns (a file of another model), NaN, duplicate rows, non-unit
    quaternions, slider values beyond limits (saying so when they look like millimetres).
    """
    source = Path(path)
    model = mechanism.model
    actuated = mechanism.actuated_joints
    passive_names = tuple(model.names[j] for j in range(1, model.njoints) if model.names[j] not in actuated)
    actuator_columns = tuple(measurement_column(n) for n in actuated)
    table = read_table(source, required=actuator_columns + ("x", "y", "z"),
                       optional=(*(measurement_column(n) for n in passive_names), *CONVERTED_COLUMNS),
                       optional_groups=(_QUATERNION,), reject_duplicate_rows=True)
    scale = _length_scale(table, mechanism, units, actuated + passive_names)
    _check_limits(table, mechanism, actuated, scale, actuator_columns)
    position_only = not table.has_column("qw")
    positions = np.column_stack([table.column(n) for n in ("x", "y", "z")]) * scale["x"]
    if position_only:
        poses = [pin.SE3(np.eye(3), row) for row in positions]
    else:
        poses = [pin.SE3(pose.rotation, position) for pose, position in zip(poses_from_table(table), positions)]
    actuators = np.column_stack([table.column(c) * scale.get(c, 1.0) for c in actuator_columns])
    present = tuple(n for n in passive_names if table.has_column(measurement_column(n)))
    passive = (np.column_stack([table.column(c) * scale.get(c, 1.0) for c in map(measurement_column, present)])
               if present else np.zeros((table.n_rows, 0)))
    return MeasurementFile(source, PoseMeasurements(actuators, tuple(poses), position_only), present, passive,
                           table.line_numbers, sha256_of(source),
                           table.column("source").astype(int) if table.has_column("source") else None)


def write_measurements(path: StrPath, mechanism: Mechanism, measurements: PoseMeasurements,
                       passive_joints: Sequence[str] = (), passive: np.ndarray | None = None,
                       comments: Sequence[str] = (), protect: Iterable[StrPath] = (), units: str = "m") -> None:
    """Write measurements in the format `read_measurements` reads (atomically), lengths in `units`."""
    write_table(path, *measurement_table(mechanism, measurements, passive_joints, passive, units), comments, protect)


def measurement_table(mechanism: Mechanism, measurements: PoseMeasurements, passive_joints: Sequence[str] = (),
                      passive: np.ndarray | None = None, units: str = "m") -> tuple[list[str], np.ndarray]:
    """Columns and rows of a measurement file, lengths (x, y, z, prismatic joints) in `units`."""
    if units not in LENGTH_UNITS:
        raise DataFileError("-", f"unknown length unit '{units}' (one of {', '.join(LENGTH_UNITS)})")
    joints = list(mechanism.actuated_joints) + list(passive_joints)
    columns = [measurement_column(n) for n in joints]
    blocks = [measurements.actuators]
    if passive_joints:
        blocks.append(np.asarray(passive, dtype=float))
    rows = pose_rows(measurements.poses)
    if measurements.position_only:
        columns += ["x", "y", "z"]
        blocks.append(rows[:, :3])
    else:
        columns += list(POSE_COLUMNS)
        blocks.append(rows)
    table = np.hstack(blocks)
    lengths = {measurement_column(n) for n in _prismatic_joints(mechanism, joints)} | {"x", "y", "z"}
    divide = np.array([LENGTH_UNITS[units] if c in lengths else 1.0 for c in columns])
    return columns, table / divide
