"""OptiTrack Motive CSV exports: rigid bodies and markers.

The layout, as Motive writes it: a first line of `key,value` settings (`Format Version`, `Capture
Frame Rate`, `Rotation Type`, `Length Units` ...), then header rows naming for each column the
asset type (`Rigid Body`, `Marker`, `Rigid Body Marker`), the asset name, its ID, the quantity
(`Rotation`, `Position`, `Mean Marker Error`) and, on the row that starts with `Frame,Time`,
the component (`X, Y, Z, W`). Rotations are quaternions X, Y, Z, W (the only rotation type read:
an Euler export names its order, which Motive leaves to a setting) followed by positions X, Y, Z
in the `Length Units`. An occluded frame has empty cells.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from m3t1r.errors import DataFileError
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.records import TrackerRecord, length_scale
from m3t1r.io.instruments.text import numbered_lines, parse_number, split_fields

__all__ = ["looks_motive", "read_motive"]


def looks_motive(lines: Sequence[tuple[int, str]]) -> bool:
    """Whether the file starts with Motive's settings line."""
    return bool(lines) and lines[0][1].lstrip('\ufeff"').startswith("Format Version")


def _settings(path: Path, first: str) -> dict[str, str]:
    fields = split_fields(first, ",")
    return {fields[k].strip().lower(): fields[k + 1].strip() for k in range(0, len(fields) - 1, 2)}


def read_motive(path: Path, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """One rigid body (its position and quaternion) or one marker (its position) of a Motive CSV:
    `options.body` names it; by default the only rigid body, or the only marker."""
    lines = numbered_lines(path)
    settings = _settings(path, lines[0][1])
    rotation_type = settings.get("rotation type", "Quaternion")
    scale = length_scale(path, settings.get("length units", options.units or "m"), 1)
    frame_index = next((k for k, (_, text) in enumerate(lines) if text.lower().startswith("frame,")), None)
    header = [split_fields(text, ",") for _, text in lines[1 : frame_index or 1]]
    type_row = next((k for k, row in enumerate(header) if {"Rigid Body", "Marker"} & set(row)), None)
    if frame_index is None or type_row is None or type_row + 2 > len(header) - 1:
        raise DataFileError(
            path, "no asset rows (Rigid Body, Marker) above a 'Frame,Time,...' row: not a Motive CSV export"
        )
    types, names, quantities = header[type_row], header[type_row + 1], header[-1]
    components = split_fields(lines[frame_index][1], ",")
    width = len(components)
    types, names, quantities = (row + [""] * (width - len(row)) for row in (types, names, quantities))
    bodies = sorted({n for t, n in zip(types, names) if t == "Rigid Body"})
    markers = sorted({n for t, n in zip(types, names) if t == "Marker"})
    body, is_body = _choose(path, lines[type_row + 2][0], options.body, bodies, markers)
    wanted = [("Position", c) for c in "XYZ"]
    if is_body:
        if rotation_type.lower() != "quaternion":
            raise DataFileError(
                path,
                f"rotation type '{rotation_type}': export the take with quaternions "
                "(Motive's Rotation Type: Quaternion)",
                row=1,
            )
        wanted = [("Rotation", c) for c in "XYZW"] + wanted
    kind = "Rigid Body" if is_body else "Marker"
    index = []
    for quantity, component in wanted:
        matches = [
            k
            for k in range(width)
            if types[k] == kind
            and names[k] == body
            and quantities[k] == quantity
            and components[k].upper() == component
        ]
        if not matches:
            raise DataFileError(
                path, f"{kind} '{body}' has no {quantity} {component} column", row=lines[frame_index][0]
            )
        index.append(matches[0])
    data = [(line, split_fields(text, ",")) for line, text in lines[frame_index + 1 :] if text.strip()]
    values = np.array(
        [
            [
                parse_number(path, line, f"{quantities[k]} {components[k]}", fields[k] if k < len(fields) else "")
                for k in index + [1]
            ]
            for line, fields in data
        ]
    )
    positions = values[:, -4:-1] * scale
    quaternions = values[:, :4] if is_body else None
    return TrackerRecord(
        path, "motive", body, positions, quaternions, values[:, -1], np.array([line for line, _ in data])
    )


def _choose(path: Path, line: int, wanted: str | None, bodies: list[str], markers: list[str]) -> tuple[str, bool]:
    """(asset name, whether it is a rigid body)."""
    if wanted is not None:
        if wanted in bodies:
            return wanted, True
        if wanted in markers:
            return wanted, False
        raise DataFileError(
            path,
            f"--body {wanted}: the take has rigid bodies {', '.join(bodies) or 'none'} "
            f"and markers {', '.join(markers) or 'none'}",
            row=line,
        )
    if len(bodies) == 1:
        return bodies[0], True
    if not bodies and len(markers) == 1:
        return markers[0], False
    raise DataFileError(
        path,
        f"choose the tracked asset with --body NAME: rigid bodies {', '.join(bodies) or 'none'}, "
        f"markers {', '.join(markers) or 'none'}",
        row=line,
    )
