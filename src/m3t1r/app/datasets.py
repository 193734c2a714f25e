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
from m3t1r.io.tables import Table, read_header, read_table, write_table
from m3t1r.model.description import Mechanism
from m3t1r.model.task import TaskSpec

__all__ = [
    "TARGET_COLUMNS",
    "check_joint_readings",
    "read_actuators",
    "read_targets",
    "MeasurementFile",
    "read_measurements",
    "point_numbers",
    "measured_points",
    "most_seen_point",
    "write_measurements",
    "measurement_table",
    "sha256_of",
]

TARGET_COLUMNS = TaskSpec("platform").columns  # the M machine's: platform position [m] and yaw [rad]
_QUATERNION = ("qx", "qy", "qz", "qw")


def sha256_of(path: StrPath) -> str:
    """Hex digest of a file's bytes (provenance in reports)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def check_joint_readings(
    table: Table,
    columns: Sequence[str],
    readings: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    prismatic: Sequence[bool] | np.ndarray,
    *,
    scales: Sequence[float] | np.ndarray | None = None,
    margin: float = 0.0,
) -> list[str]:
    """Refuse a joint reading beyond its joint's limits: DataFileError naming the line and column,
    with a hint when the whole column looks like millimetres or degrees. The closed-loop and the
    serial readers both check their joint columns here.

    readings: (N, k) [m or rad], column k of the table read in `columns[k]`; lower, upper: (k,)
    limits [m or rad] (a joint with lower >= upper is not checked); prismatic: which joints are
    lengths; scales: metres per file unit of each column (default 1: SI). margin: the share of a
    joint's range a reading may pass a limit by and still be kept (nominal URDF limits); returns a
    note per column with such readings.
    """
    notes = []
    for k, column in enumerate(columns):
        low, high, values = float(lower[k]), float(upper[k]), readings[:, k]
        if not low < high:
            continue
        slack = margin * (high - low) if np.isfinite(high - low) else 0.0
        outside = np.flatnonzero((values < low - slack) | (values > high + slack))
        unit = "m" if prismatic[k] else "rad"
        if outside.size:
            row = int(outside[0])
            hint = _limit_hint(
                table, values, outside.size, low, high, prismatic[k], 1.0 if scales is None else scales[k]
            )
            raise table.error(
                row,
                f"{values[row]:.6g} {unit} is beyond the joint limit [{low:.6g}, {high:.6g}] " + hint,
                column=column,
            )
        nearly = np.flatnonzero((values < low) | (values > high))
        if nearly.size:
            worst = float(np.max(np.maximum(low - values, values - high)))
            notes.append(
                f"column '{column}': {nearly.size} reading(s) up to {worst:.3g} {unit} beyond the URDF "
                f"limit [{low:.6g}, {high:.6g}] (file line {int(table.line_numbers[nearly[0]])} first), "
                f"within {margin:.0%} of its range: kept as read"
            )
    return notes


def _limit_hint(
    table: Table, values: np.ndarray, n_outside: int, lower: float, upper: float, prismatic: bool, scale: float
) -> str:
    """What a column beyond its limits most likely is: millimetres in a metre file or degrees, when
    most of the column is beyond (one bad reading is a fault, not a unit); else the SI unit it must be in."""
    within = lambda converted: bool(np.all((converted >= lower) & (converted <= upper)))
    if 2 * n_outside > len(values) and prismatic and scale == 1.0 and within(values * 1e-3):
        return "(every value of the column is within the limits in millimetres: use --units mm)"
    if 2 * n_outside > len(values) and not prismatic and within(np.radians(values)):
        return (
            "(every value of the column is within the limits in degrees: give radians; `m3t1r convert "
            f"{table.path} --joint-degrees all -o measurements.csv` rewrites the file in radians)"
        )
    return f"(SI units: {'m' if prismatic else 'rad'})"


def _check_limits(
    table: Table,
    mechanism: Mechanism,
    names: Sequence[str],
    scale: Mapping[str, float] | None = None,
    columns: Sequence[str] | None = None,
) -> None:
    """`check_joint_readings` of the joints `names` (their columns: `columns`, default the names) on
    the mechanism's limits, after `scale` (column -> metres per file unit)."""
    columns, scale = tuple(columns or names), scale or {}
    readings = np.column_stack([table.column(c) * scale.get(c, 1.0) for c in columns])
    prismatic = set(_prismatic_joints(mechanism, names))
    check_joint_readings(
        table,
        columns,
        readings,
        *mechanism.joint_limits(tuple(names)),
        [n in prismatic for n in names],
        scales=[scale.get(c, 1.0) for c in columns],
    )


def _prismatic_joints(mechanism: Mechanism, names: Iterable[str]) -> tuple[str, ...]:
    """The prismatic joints among `names`: their readings are lengths, scaled by --units."""
    model = mechanism.model
    return tuple(
        n
        for n in names
        if model.existJointName(n) and model.joints[model.getJointId(n)].shortname().startswith("JointModelP")
    )


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
    raise DataFileError(
        table.path,
        f"a target file needs the task's columns {', '.join(columns)} or a full pose "
        f"{', '.join(POSE_COLUMNS)}; missing {', '.join(missing)}",
        column=missing[0],
    )


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


def point_numbers(columns: tuple[str, ...]) -> list[int]:
    """The point numbers k of a header with x1, y1, z1 ... columns (x_k, y_k, z_k all present), sorted."""
    numbers = {int(c[1:]) for c in columns if len(c) > 1 and c[0] in "xyz" and c[1:].isdigit()}
    return sorted(k for k in numbers if all(f"{a}{k}" in columns for a in "xyz"))


def measured_points(table: Table, numbers: Sequence[int], scale: float) -> np.ndarray:
    """The points x_k, y_k, z_k of every row (N, K, 3) [m], NaN where not seen (all three blank);
    DataFileError naming the line and column of a point partly blank, a row seeing none, a point never seen."""
    columns = [f"{a}{k}" for k in numbers for a in "xyz"]
    points = np.column_stack([table.column(c) for c in columns]).reshape(table.n_rows, len(numbers), 3) * scale
    finite = np.isfinite(points)
    for row, point in np.argwhere(np.any(finite, axis=2) != np.all(finite, axis=2)):
        raise table.error(
            int(row),
            f"point {numbers[int(point)]} has some coordinates blank: give all three or none",
            column=columns[3 * point + int(np.argmin(finite[row, point]))],
        )
    for row in np.flatnonzero(~np.any(finite, axis=(1, 2))):
        raise table.error(int(row), "no point seen on this row (every x_k, y_k, z_k blank)")
    for point in np.flatnonzero(~np.any(finite[:, :, 0], axis=0)):
        raise table.error(0, f"point {numbers[int(point)]} is seen on no row", column=columns[3 * point])
    return points


def most_seen_point(points: np.ndarray) -> np.ndarray:
    """The positions (N, 3) [m] of the point seen on the most rows of `points` (N, K, 3), NaN where it
    was not seen: what stands for a row of several points where one position is read (the data
    checks, `poses`)."""
    return points[:, int(np.argmax(np.isfinite(points[:, :, 0]).sum(axis=0)))]


def read_measurements(path: StrPath, mechanism: Mechanism, units: str = "m") -> MeasurementFile:
    """Read a measurement CSV: actuator columns (named by the actuated joints), optional passive
    joint columns (named by joint), x, y, z and optionally qx, qy, qz, qw; or, for K points rigidly
    attached to the platform, x1, y1, z1 ... xK, yK, zK (blank where a point was not seen: the
    measurements' `points`, their `poses` the most-seen point, NaN where it was not seen).

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
    numbers = point_numbers(read_header(source))
    point_columns = tuple(f"{a}{k}" for k in numbers for a in "xyz")
    table = read_table(
        source,
        required=actuator_columns + (() if numbers else ("x", "y", "z")),
        optional=(*(measurement_column(n) for n in passive_names), *CONVERTED_COLUMNS),
        optional_groups=(
            tuple(point_columns[3 * k : 3 * k + 3] for k in range(len(numbers))) if numbers else (_QUATERNION,)
        ),
        reject_duplicate_rows=True,
        blank_allowed=point_columns,
    )
    scale = _length_scale(table, mechanism, units, actuated + passive_names)
    _check_limits(table, mechanism, actuated, scale, actuator_columns)
    position_only = not table.has_column("qw")
    points = measured_points(table, numbers, LENGTH_UNITS[units]) if numbers else None
    if points is not None:
        positions = most_seen_point(points)
    else:
        positions = np.column_stack([table.column(n) for n in ("x", "y", "z")]) * scale["x"]
    if position_only:
        poses = [pin.SE3(np.eye(3), row) for row in positions]
    else:
        poses = [pin.SE3(pose.rotation, position) for pose, position in zip(poses_from_table(table), positions)]
    actuators = np.column_stack([table.column(c) * scale.get(c, 1.0) for c in actuator_columns])
    present = tuple(n for n in passive_names if table.has_column(measurement_column(n)))
    passive = (
        np.column_stack([table.column(c) * scale.get(c, 1.0) for c in map(measurement_column, present)])
        if present
        else np.zeros((table.n_rows, 0))
    )
    return MeasurementFile(
        source,
        PoseMeasurements(actuators, tuple(poses), position_only, points),
        present,
        passive,
        table.line_numbers,
        sha256_of(source),
        table.column("source").astype(int) if table.has_column("source") else None,
    )


def write_measurements(
    path: StrPath,
    mechanism: Mechanism,
    measurements: PoseMeasurements,
    passive_joints: Sequence[str] = (),
    passive: np.ndarray | None = None,
    comments: Sequence[str] = (),
    protect: Iterable[StrPath] = (),
    units: str = "m",
) -> None:
    """Write measurements in the format `read_measurements` reads (atomically), lengths in `units`."""
    write_table(path, *measurement_table(mechanism, measurements, passive_joints, passive, units), comments, protect)


def measurement_table(
    mechanism: Mechanism,
    measurements: PoseMeasurements,
    passive_joints: Sequence[str] = (),
    passive: np.ndarray | None = None,
    units: str = "m",
) -> tuple[list[str], np.ndarray]:
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
