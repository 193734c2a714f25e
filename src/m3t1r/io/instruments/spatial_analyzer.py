"""SpatialAnalyzer ASCII point exports: one measured point per line, one static pose each.

Each data line holds the point's names (collection, group, point: one to three text fields) and
then X, Y, Z, separated by commas, tabs or blanks; lines starting with `//` or `#` are comments. The
length unit comes from a comment such as `// Units: Millimeters` (or `--units`); without either
the file is refused, since SpatialAnalyzer exports in whatever unit the job uses. `--body GROUP`
keeps one group's points. The points are poses in file order: pair them with a robot log by order.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from m3t1r.errors import DataFileError
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.records import TrackerRecord, length_scale
from m3t1r.io.instruments.text import is_number, numbered_lines, parse_number

__all__ = ["looks_spatial_analyzer", "read_spatial_analyzer"]

_UNITS = re.compile(r"units?\s*[:=]\s*([A-Za-z]+)", re.IGNORECASE)


def _fields(text: str) -> list[str]:
    return [
        f.strip().strip('"')
        for f in re.split(r"[,\t]" if re.search(r"[,\t]", text) else r"\s+", text.strip())
        if f.strip()
    ]


def _data(lines: Sequence[tuple[int, str]]) -> list[tuple[int, list[str]]]:
    return [(n, _fields(t)) for n, t in lines if t.strip() and not t.lstrip().startswith(("//", "#"))]


def _is_point(fields: list[str]) -> bool:
    return (
        4 <= len(fields)
        and not is_number(fields[0])
        and all(is_number(f) for f in fields[-3:])
        and sum(1 for f in fields if not is_number(f)) <= 3
    )


def looks_spatial_analyzer(lines: Sequence[tuple[int, str]]) -> bool:
    """Whether the first data lines are names followed by three numbers."""
    rows = _data(lines)[:5]
    return bool(rows) and all(_is_point(fields) for _, fields in rows)


def read_spatial_analyzer(path: Path, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """The points of a SpatialAnalyzer ASCII export (module docstring), in metres."""
    lines = numbered_lines(path)
    stated = next(
        (m.group(1) for _, t in lines if t.lstrip().startswith(("//", "#")) and (m := _UNITS.search(t))), None
    )
    unit = stated or options.units
    if unit is None:
        raise DataFileError(path, "the export does not state its length unit (a '// Units: mm' comment): give --units")
    scale = length_scale(path, unit)
    rows = []
    for line, fields in _data(lines):
        if not _is_point(fields):
            raise DataFileError(path, "expected the point's names, then X, Y, Z", row=line)
        names = [f for f in fields if not is_number(f)]
        group = names[-2] if len(names) >= 2 else ""
        if options.body is None or group == options.body:
            rows.append((line, [parse_number(path, line, axis, fields[-3 + k]) for k, axis in enumerate("XYZ")]))
    if not rows:
        raise DataFileError(path, f"no points of group {options.body}" if options.body else "no points")
    return TrackerRecord(
        path,
        "spatial-analyzer",
        options.body or "the points",
        np.array([p for _, p in rows]) * scale,
        None,
        None,
        np.array([line for line, _ in rows]),
    )
