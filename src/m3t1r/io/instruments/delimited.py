"""Plain delimited tables of tracker samples: the project's own columns with extras.

Accepted: `,`, `;` (then a comma is a decimal comma) or tab separators, `#` comment lines, and
columns recognised by name (any case):

- positions `x, y, z`, or several markers `x1, y1, z1 ... xK, yK, zK` (`--body K` picks one;
  `--body all` keeps every one, as several points of the tool, blank where not seen;
  `--body rigid` makes one rigid body of three or more: its origin the markers' centroid, its axes
  those of the tracker at the first sample seeing every marker, each sample's orientation the
  rotation that best carries the markers from that sample, by the SVD of their cross-covariance);
- an orientation `qx, qy, qz, qw`, or Euler angles `roll, pitch, yaw` / `rx, ry, rz` read with the
  convention `--euler` names (scipy's: lowercase extrinsic, uppercase intrinsic) in radians, or
  degrees with `--degrees`; or a rotation vector (axis times angle) `rvx, rvy, rvz`, or `rx, ry,
  rz` with `--rotation-vector` (a UR controller's), in radians or degrees with `--degrees`; or a
  rotation matrix `r11 ... r33` (r_ij: row i, column j), each made the nearest rotation and
  refused by line when it is not one to 1e-3;
- a time `time`, `t`, `timestamp` or `stamp` [s] (frames of a stream: still stretches are found);
- a per-sample scatter `position_std` [m] or `*_std_mm` [mm];
- joint readings: the columns `--joints` names, or else every other numeric column except
  times (`t_*`, `*time*`, `*stamp*`) and counters (`frame`, `index`, `*row*`), which are ignored
  with a note. Text columns (names, labels) are ignored.

Positions are in `units` (default metres). An empty position cell is an occluded sample.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from m3t1r.errors import DataFileError
from m3t1r.io.instruments.records import TrackerRecord, length_scale
from m3t1r.io.instruments.text import detect_delimiter, is_number, numbered_lines, parse_number, split_fields

__all__ = ["ReadOptions", "read_delimited", "looks_delimited"]

_TIME = ("time", "t", "timestamp", "stamp", "time_s")
_EULER = (("roll", "pitch", "yaw"), ("rx", "ry", "rz"))
_ROTATION_VECTOR = ("rvx", "rvy", "rvz")
_MATRIX = tuple(f"r{i}{j}" for i in "123" for j in "123")
_NOT_A_ROTATION = 1e-3  # a matrix farther from its nearest rotation (largest entry) is not one
_QUATERNION = ("qx", "qy", "qz", "qw")


@dataclass(frozen=True)
class ReadOptions:
    """What a file does not say: body: marker number, rigid-body or label to read (None: the only
    one, or the first); units: position unit when the file does not state one; euler: scipy
    convention of Euler columns; degrees: Euler angles (or a rotation vector) in degrees;
    rotation_vector: rx, ry, rz are a rotation vector, not Euler angles; joints: the joint columns
    (None: every unrecognised numeric column); joint_degrees: joint columns in degrees."""

    body: str | None = None
    units: str | None = None
    euler: str | None = None
    degrees: bool = False
    joints: tuple[str, ...] | None = None
    joint_degrees: tuple[str, ...] = ()
    rotation_vector: bool = False


def looks_delimited(lines: Sequence[tuple[int, str]]) -> bool:
    """Whether the first non-comment line is a header naming positions (x, y, z or x1, y1, z1)."""
    header = _header(lines)
    if header is None:
        return False
    names = {n.lower() for n in split_fields(header[1], detect_delimiter(header[1]))}
    return {"x", "y", "z"} <= names or {"x1", "y1", "z1"} <= names


def _header(lines: Sequence[tuple[int, str]]) -> tuple[int, str] | None:
    return next(((n, t) for n, t in lines if t.strip() and not t.lstrip().startswith("#")), None)


def read_delimited(path: Path, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """The samples of one marker or body of a delimited table (module docstring); `notes` gets
    what was chosen or ignored, in words."""
    lines = numbered_lines(path)
    header = _header(lines)
    if header is None:
        raise DataFileError(path, "no header line: the file is empty or holds only comments")
    delimiter = detect_delimiter(header[1])
    names = split_fields(header[1], delimiter)
    rows = [
        (n, split_fields(t, delimiter))
        for n, t in lines
        if n > header[0] and t.strip() and not t.lstrip().startswith("#")
    ]
    if not rows:
        raise DataFileError(path, "no data rows after the header", row=header[0])
    for line, fields in rows:
        if len(fields) != len(names):
            raise DataFileError(path, f"{len(fields)} fields, but the header has {len(names)} columns", row=line)
    lower = [n.lower() for n in names]
    columns = _Columns(path, header[0], names, lower, rows, delimiter == ";")
    scale = length_scale(path, options.units or "m")
    quaternions: np.ndarray | None  # None: position-only
    points: np.ndarray | None = None
    numbers: tuple[int, ...] = ()
    if options.body == "all":
        points, numbers = _all_markers(path, header[0], columns, lower, scale)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a sample seeing no marker: NaN, left out later
            positions = np.nanmean(points, axis=1)
        quaternions, body = None, f"markers {', '.join(map(str, numbers))} as points"
    elif options.body == "rigid":
        positions, quaternions, body = _rigid_body(path, header[0], columns, lower, scale)
    else:
        position_names, body = _position_columns(path, header[0], lower, options.body, notes)
        positions = np.column_stack([columns.values(c) for c in position_names]) * scale
        quaternions = _orientation(columns, lower, options, path, header[0])
    times = columns.values(next(n for n in _TIME if n in lower)) if any(n in lower for n in _TIME) else None
    joint_names = _joint_columns(path, header[0], names, lower, columns, options, notes)
    joints = (
        np.column_stack(
            [
                columns.values(n.lower())
                * (np.pi / 180.0 if n in options.joint_degrees or "all" in options.joint_degrees else 1.0)
                for n in joint_names
            ]
        )
        if joint_names
        else np.zeros((len(rows), 0))
    )
    if joints.size and not np.all(np.isfinite(joints)):
        row, column = (int(i) for i in np.argwhere(~np.isfinite(joints))[0])
        raise DataFileError(path, "empty joint reading", row=rows[row][0], column=joint_names[column])
    return TrackerRecord(
        path,
        "csv",
        body,
        positions,
        quaternions,
        times,
        np.array([n for n, _ in rows]),
        joints=joints,
        joint_names=tuple(joint_names),
        scatter=_scatter(columns, lower),
        points=points,
        point_numbers=numbers,
    )


class _Columns:
    """Numeric columns of the rows, parsed on demand (errors name the line and column)."""

    def __init__(
        self,
        path: Path,
        header_line: int,
        names: list[str],
        lower: list[str],
        rows: list[tuple[int, list[str]]],
        decimal_comma: bool,
    ) -> None:
        self.path, self.header_line, self.names, self.lower = path, header_line, names, lower
        self.rows, self.decimal_comma = rows, decimal_comma

    def values(self, lower_name: str) -> np.ndarray:
        k = self.lower.index(lower_name)
        return np.array(
            [parse_number(self.path, line, self.names[k], fields[k], self.decimal_comma) for line, fields in self.rows]
        )

    def numeric(self, lower_name: str) -> bool:
        k = self.lower.index(lower_name)
        return all(is_number(fields[k]) or not fields[k] for _, fields in self.rows[:50])


def _position_columns(
    path: Path, header_line: int, lower: list[str], body: str | None, notes: list[str]
) -> tuple[list[str], str]:
    markers = _marker_numbers(lower)
    if {"x", "y", "z"} <= set(lower) and body in (None, ""):
        return ["x", "y", "z"], "the point"
    if not markers:
        raise DataFileError(path, "no position columns: expected x, y, z or x1, y1, z1 ...", row=header_line)
    if body is None:
        if len(markers) > 1:
            notes.append(f"markers {', '.join(map(str, markers))} in the file: marker {markers[0]} read (--body K)")
        chosen = markers[0]
    elif body.isdigit() and int(body) in markers:
        chosen = int(body)
    else:
        raise DataFileError(
            path, f"--body {body}: the file has markers {', '.join(map(str, markers))}", row=header_line
        )
    return [f"x{chosen}", f"y{chosen}", f"z{chosen}"], f"marker {chosen}"


def _rigid_body(
    path: Path, header_line: int, columns: _Columns, lower: list[str], scale: float
) -> tuple[np.ndarray, np.ndarray, str]:
    """(centroids (N, 3) [m], quaternions (N, 4), name) of the markers as one rigid body (module
    docstring); samples missing a marker are NaN."""
    markers = _marker_numbers(lower)
    if len(markers) < 3:
        raise DataFileError(
            path,
            f"--body rigid needs three markers or more (x1, y1, z1 ...); the file has {len(markers)}",
            row=header_line,
        )
    clouds = np.stack([np.column_stack([columns.values(f"{a}{k}") for a in "xyz"]) for k in markers], axis=1) * scale
    seen = np.all(np.isfinite(clouds.reshape(len(clouds), -1)), axis=1)
    if not seen.any():
        raise DataFileError(path, "no sample sees every marker: no rigid body to build")
    reference = clouds[np.argmax(seen)] - clouds[np.argmax(seen)].mean(axis=0)
    centroids = np.full((len(clouds), 3), np.nan)
    quaternions = np.full((len(clouds), 4), np.nan)
    centroids[seen] = clouds[seen].mean(axis=1)
    moved = clouds[seen] - centroids[seen][:, None, :]
    u, _, vt = np.linalg.svd(np.swapaxes(moved, 1, 2) @ reference)
    sign = np.sign(np.linalg.det(u @ vt))
    u[:, :, -1] *= sign[:, None]
    quaternions[seen] = Rotation.from_matrix(u @ vt).as_quat()
    return centroids, quaternions, f"markers {', '.join(map(str, markers))} as one rigid body"


def _all_markers(
    path: Path, header_line: int, columns: _Columns, lower: list[str], scale: float
) -> tuple[np.ndarray, tuple[int, ...]]:
    """(points (N, K, 3) [m], NaN where not seen, marker numbers) of every marker (`--body all`)."""
    markers = _marker_numbers(lower)
    if not markers:
        raise DataFileError(path, "--body all reads markers x1, y1, z1 ...; the file has none", row=header_line)
    points = np.stack([np.column_stack([columns.values(f"{a}{k}") for a in "xyz"]) for k in markers], axis=1)
    return points * scale, tuple(markers)


def _marker_numbers(lower: list[str]) -> list[int]:
    return sorted(
        {
            int(m.group(1))
            for n in lower
            if (m := re.fullmatch(r"x(\d+)", n)) and f"y{m.group(1)}" in lower and f"z{m.group(1)}" in lower
        }
    )


def _orientation(
    columns: _Columns, lower: list[str], options: ReadOptions, path: Path, header_line: int
) -> np.ndarray | None:
    if all(q in lower for q in _QUATERNION):
        quaternions = np.column_stack([columns.values(q) for q in _QUATERNION])
        return quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)
    if all(r in lower for r in _MATRIX):
        return _matrix_quaternions(columns, path)
    vector = next(
        (
            group
            for group in (_ROTATION_VECTOR, _EULER[1])
            if all(e in lower for e in group) and (group == _ROTATION_VECTOR or options.rotation_vector)
        ),
        None,
    )
    if vector is not None:
        values = np.column_stack([columns.values(e) for e in vector])
        quaternions = np.full((len(values), 4), np.nan)
        seen = np.all(np.isfinite(values), axis=1)
        quaternions[seen] = Rotation.from_rotvec(values[seen], degrees=options.degrees).as_quat()
        return quaternions
    euler = next((group for group in _EULER if all(e in lower for e in group)), None)
    if euler is None:
        return None
    if not options.euler:
        hint = " (or --rotation-vector: a rotation vector, as a UR controller logs)" if euler == _EULER[1] else ""
        raise DataFileError(
            path,
            f"Euler angle columns {', '.join(euler)}: give their convention with --euler "
            f"(e.g. xyz extrinsic, ZYX intrinsic){hint} and --degrees if they are in degrees",
            row=header_line,
        )
    angles = np.column_stack([columns.values(e) for e in euler])
    quaternions = np.full((len(angles), 4), np.nan)
    seen = np.all(np.isfinite(angles), axis=1)
    quaternions[seen] = Rotation.from_euler(options.euler, angles[seen], degrees=options.degrees).as_quat()
    return quaternions


def _matrix_quaternions(columns: _Columns, path: Path) -> np.ndarray:
    """Quaternions (N, 4) of the rotation matrices r11 ... r33 (NaN where a cell is empty); a matrix
    that is not a rotation (beyond _NOT_A_ROTATION, or a mirror) is refused by line."""
    matrices = np.column_stack([columns.values(r) for r in _MATRIX]).reshape(-1, 3, 3)
    quaternions = np.full((len(matrices), 4), np.nan)
    seen = np.all(np.isfinite(matrices.reshape(len(matrices), -1)), axis=1)
    u, _, vt = np.linalg.svd(matrices[seen])
    nearest = u @ vt
    off = np.max(np.abs(nearest - matrices[seen]), axis=(1, 2))
    bad = np.flatnonzero((off > _NOT_A_ROTATION) | (np.linalg.det(nearest) < 0))
    if bad.size:
        line = columns.rows[int(np.flatnonzero(seen)[bad[0]])][0]
        raise DataFileError(
            path, f"r11 ... r33 are not a rotation matrix (off by {off[bad[0]]:.3g}, or a mirror)", row=line
        )
    quaternions[seen] = Rotation.from_matrix(nearest).as_quat()
    return quaternions


def _joint_columns(
    path: Path,
    header_line: int,
    names: list[str],
    lower: list[str],
    columns: _Columns,
    options: ReadOptions,
    notes: list[str],
) -> list[str]:
    if options.joints is not None:
        missing = [j for j in options.joints if j.lower() not in lower]
        if missing:
            raise DataFileError(path, f"no column {', '.join(missing)} (--joints)", row=header_line)
        return [names[lower.index(j.lower())] for j in options.joints]
    recognised = (
        set(_TIME)
        | set(_QUATERNION)
        | {e for group in _EULER for e in group}
        | {"position_std"}
        | set(_ROTATION_VECTOR)
        | set(_MATRIX)
    )
    taken, ignored = [], []
    for name, low in zip(names, lower):
        if low in recognised or re.fullmatch(r"[xyz]\d*", low) or low.endswith("_std_mm"):
            continue
        if not columns.numeric(low) or _is_meta(low):
            ignored.append(name)
        else:
            taken.append(name)
    if ignored:
        notes.append(f"columns ignored (times, counters, text): {', '.join(ignored)}")
    return taken


def _is_meta(name: str) -> bool:
    return name.startswith("t_") or "time" in name or "stamp" in name or name in ("frame", "index") or "row" in name


def _scatter(columns: _Columns, lower: list[str]) -> np.ndarray | None:
    if "position_std" in lower:
        return columns.values("position_std")
    millimetres = next((n for n in lower if n.endswith("_std_mm")), None)
    return None if millimetres is None else columns.values(millimetres) * 1e-3
