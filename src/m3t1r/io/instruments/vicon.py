"""Vicon CSV exports (Nexus and Tracker): `Objects`, `Segments` and `Trajectories` blocks.

Each block, as Vicon writes it: a line with the block's name, a line with the frame rate [Hz], a
line naming each subject or marker over the first column of its group (`Subject:Marker`), the
components (`Frame, Sub Frame, X, Y, Z` for a trajectory, `RX, RY, RZ, TX, TY, TZ` for an object
or segment), a line of units (`mm`, `deg`, `rad`), the frames, and a blank line before the next
block. Object and segment rotations RX, RY, RZ are read as a helical angle (a rotation vector), as
Vicon exports global poses; `--euler SEQ` reads them as Euler angles instead. An occluded frame
has empty cells.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from m3t1r.errors import DataFileError
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.records import TrackerRecord, length_scale
from m3t1r.io.instruments.text import numbered_lines, parse_number, split_fields

__all__ = ["BLOCKS", "looks_vicon", "read_vicon"]

BLOCKS = ("Objects", "Segments", "Trajectories")
_OTHER_BLOCKS = ("Devices", "Joints", "Model Outputs")
_ANGLE_UNITS = {"deg": np.pi / 180.0, "rad": 1.0, "": 1.0}


def looks_vicon(lines: Sequence[tuple[int, str]]) -> bool:
    """Whether the file starts with a Vicon block name."""
    first = next((split_fields(t, ",")[0] for _, t in lines if t.strip()), "")
    return first in BLOCKS + _OTHER_BLOCKS


def read_vicon(path: Path, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """One object or segment (position and orientation) or one marker trajectory: `options.body`
    names it (`Subject` or `Subject:Marker`); by default the only object, else the only marker."""
    lines = numbered_lines(path)
    blocks = _blocks(path, lines)
    bodies = [(kind, name) for kind, (names, *_rest) in blocks.items() if kind != "Trajectories" for name in names]
    markers = [("Trajectories", name) for name in blocks.get("Trajectories", ([], 0, [], [], []))[0]]
    kind, name = _choose(path, options.body, bodies, markers)
    names, rate, components, units, rows = blocks[kind]
    start = names[name]
    wanted = ["TX", "TY", "TZ", "RX", "RY", "RZ"] if kind != "Trajectories" else ["X", "Y", "Z"]
    index = []
    for component in wanted:
        k = next(
            (k for k in range(start, min(start + len(wanted), len(components))) if components[k] == component), None
        )
        if k is None:
            raise DataFileError(path, f"{kind} '{name}' has no {component} column")
        index.append(k)
    values = np.array(
        [
            [parse_number(path, line, f"{name} {components[k]}", fields[k] if k < len(fields) else "") for k in index]
            for line, fields in rows
        ]
    )
    frames = np.array([parse_number(path, line, "Frame", fields[0]) for line, fields in rows])
    sub = np.array(
        [
            parse_number(path, line, "Sub Frame", fields[1]) if len(fields) > 1 and fields[1] else 0.0
            for line, fields in rows
        ]
    )
    positions = values[:, :3] * length_scale(path, units[index[0]] or options.units or "mm")
    quaternions = None
    if kind != "Trajectories":
        angles = values[:, 3:] * _ANGLE_UNITS.get(units[index[3]].lower(), 1.0)
        quaternions = np.full((len(angles), 4), np.nan)
        seen = np.all(np.isfinite(angles), axis=1)
        rotation = (
            Rotation.from_euler(options.euler, angles[seen]) if options.euler else Rotation.from_rotvec(angles[seen])
        )
        quaternions[seen] = rotation.as_quat()
    return TrackerRecord(
        path,
        "vicon",
        name,
        positions,
        quaternions,
        (frames - frames[0] + sub) / rate,
        np.array([line for line, _ in rows]),
    )


_Block = tuple[dict[str, int], float, list[str], list[str], list[tuple[int, list[str]]]]


def _blocks(path: Path, lines: Sequence[tuple[int, str]]) -> dict[str, _Block]:
    """{block: (name -> first column, rate [Hz], components, units, data rows)} of the blocks read."""
    blocks: dict[str, _Block] = {}
    k = 0
    while k < len(lines):
        line, text = lines[k]
        kind = split_fields(text, ",")[0]
        if kind not in BLOCKS + _OTHER_BLOCKS:
            k += 1
            continue
        if k + 4 >= len(lines):
            raise DataFileError(path, f"the {kind} block ends before its header rows", row=line)
        rate = parse_number(path, lines[k + 1][0], "frame rate", split_fields(lines[k + 1][1], ",")[0])
        if not rate > 0:
            raise DataFileError(path, f"the {kind} block has no frame rate", row=lines[k + 1][0])
        names = {n.strip(): j for j, n in enumerate(split_fields(lines[k + 2][1], ",")) if n.strip()}
        components = [c.upper() for c in split_fields(lines[k + 3][1], ",")]
        units = split_fields(lines[k + 4][1], ",") + [""] * len(components)
        k += 5
        rows = []
        while k < len(lines) and lines[k][1].strip(" ,"):
            rows.append((lines[k][0], split_fields(lines[k][1], ",")))
            k += 1
        if kind in BLOCKS:
            blocks[kind] = (names, rate, components, units, rows)
    if not blocks:
        raise DataFileError(path, f"no {', '.join(BLOCKS)} block (a Vicon CSV export of poses or trajectories)")
    return blocks


def _choose(
    path: Path, wanted: str | None, bodies: list[tuple[str, str]], markers: list[tuple[str, str]]
) -> tuple[str, str]:
    every = bodies + markers
    if wanted is not None:
        found = [b for b in every if b[1] == wanted]
        if found:
            return found[0]
    elif len(bodies) == 1:
        return bodies[0]
    elif not bodies and len(markers) == 1:
        return markers[0]
    listed = ", ".join(f"{name} ({kind})" for kind, name in every)
    raise DataFileError(
        path,
        (
            f"--body {wanted}: not in the file; it has "
            if wanted
            else "choose the tracked subject or marker with --body NAME: "
        )
        + listed,
    )
