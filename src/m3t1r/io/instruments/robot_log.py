"""The robot's side of a campaign: its joint readings, as a stream or one row per stop.

A robot log CSV has joint columns by joint name and either a time column (`time`, `t`,
`timestamp`, `stamp` [s]: a stream, whose stops are found like the tracker's dwells) or
`t_start, t_end` [s] (one row per stop, its time span), or no time at all (one row per stop, paired
with the tracker's dwells by order). `;` separators with decimal commas are read like the tracker's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t1r.errors import DataFileError
from m3t1r.io.instruments.text import detect_delimiter, numbered_lines, parse_number, split_fields

__all__ = ["RobotLog", "read_robot_csv"]

_TIME = ("time", "t", "timestamp", "stamp")


@dataclass(frozen=True, eq=False)
class RobotLog:
    """Joint readings: values (M, J) [rad, m] of joint_names; times (M,) [s] of a stream, or spans
    (M, 2) [s] of stops, or neither (stops, in order); sources (M,) lines or message numbers."""

    path: Path
    joint_names: tuple[str, ...]
    values: np.ndarray
    times: np.ndarray | None
    spans: np.ndarray | None
    sources: np.ndarray


def read_robot_csv(path: Path, joints: tuple[str, ...] | None = None, joint_degrees: tuple[str, ...] = ()) -> RobotLog:
    """A robot log CSV (module docstring). joints: the joint columns (default: every column but
    the times); joint_degrees: columns in degrees ("all": every joint)."""
    lines = [(n, t) for n, t in numbered_lines(path) if t.strip() and not t.lstrip().startswith("#")]
    if len(lines) < 2:
        raise DataFileError(path, "no header and data rows")
    delimiter = detect_delimiter(lines[0][1])
    names = split_fields(lines[0][1], delimiter)
    lower = [n.lower() for n in names]
    timing = {"t_start", "t_end", *_TIME}
    chosen = list(joints) if joints is not None else [n for n, low in zip(names, lower) if low not in timing]
    missing = [j for j in chosen if j not in names]
    if missing or not chosen:
        raise DataFileError(
            path, f"no joint column {', '.join(missing)}" if missing else "no joint columns", row=lines[0][0]
        )
    rows = []
    for line, text in lines[1:]:
        fields = split_fields(text, delimiter)
        if len(fields) != len(names):
            raise DataFileError(path, f"{len(fields)} fields, but the header has {len(names)} columns", row=line)
        rows.append((line, fields))

    def column(name: str) -> np.ndarray:
        k = names.index(name)
        values = np.array([parse_number(path, line, name, fields[k], delimiter == ";") for line, fields in rows])
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise DataFileError(path, "empty field", row=rows[int(bad[0])][0], column=name)
        return values

    values = np.column_stack(
        [column(j) * (np.pi / 180.0 if j in joint_degrees or "all" in joint_degrees else 1.0) for j in chosen]
    )
    time = next((names[lower.index(t)] for t in _TIME if t in lower), None)
    spans = None
    if "t_start" in lower and "t_end" in lower:
        spans = np.column_stack([column(names[lower.index("t_start")]), column(names[lower.index("t_end")])])
    return RobotLog(
        path, tuple(chosen), values, None if time is None else column(time), spans, np.array([line for line, _ in rows])
    )
