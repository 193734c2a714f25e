"""C3D files (through `ezc3d`, the `m3t1r[formats]` extra): one labelled point's trajectory.

The points are read by label (`POINT:LABELS`), in the unit `POINT:UNITS` names, at the rate of the
header; a sample whose residual is negative (the C3D mark of an invalid point) or that ezc3d reads
as NaN is occluded. The samples' sources are frame numbers (the header's first frame counted).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from m3t1r.errors import DataFileError, MissingExtraError
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.records import TrackerRecord, length_scale

__all__ = ["looks_c3d", "read_c3d"]


def looks_c3d(path: Path) -> bool:
    """Whether the file starts like a C3D file (its second byte is 0x50) or is named .c3d."""
    if path.suffix.lower() == ".c3d":
        return True
    try:
        with path.open("rb") as stream:
            head = stream.read(2)
    except OSError:
        return False
    return len(head) == 2 and head[1] == 0x50


def _ezc3d() -> Any:
    try:
        import ezc3d  # the optional reader, imported only when a C3D file is read
    except ImportError:
        raise MissingExtraError("reading C3D files needs the ezc3d package: pip install 'm3t1r[formats]'") from None
    return ezc3d


def read_c3d(path: Path, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """The point `options.body` names (by default the only one) of a C3D file."""
    ezc3d = _ezc3d()
    try:
        c3d = ezc3d.c3d(str(path))
    except (RuntimeError, OSError, ValueError) as exc:
        raise DataFileError(path, f"not a readable C3D file ({exc})") from None
    parameters = c3d["parameters"]["POINT"]
    labels = [str(label).strip() for label in parameters["LABELS"]["value"]]
    if options.body is None and len(labels) != 1:
        raise DataFileError(path, f"choose the point with --body LABEL: {', '.join(labels)}")
    label = options.body if options.body is not None else labels[0]
    if label not in labels:
        raise DataFileError(path, f"--body {label}: the points are {', '.join(labels)}")
    unit = (
        (list(parameters["UNITS"]["value"]) or [options.units or "mm"])[0]
        if "UNITS" in parameters
        else options.units or "mm"
    )
    k = labels.index(label)
    points = np.array(c3d["data"]["points"][:3, k, :], dtype=float).T * length_scale(path, str(unit))
    residuals = c3d["data"]["meta_points"].get("residuals")
    if residuals is not None and residuals.size:
        points[np.asarray(residuals)[0, k, :] < 0] = np.nan
    rate = float(c3d["header"]["points"]["frame_rate"])
    if not rate > 0:
        raise DataFileError(path, "the header has no point rate")
    frames = np.arange(points.shape[0]) + int(c3d["header"]["points"]["first_frame"]) + 1
    return TrackerRecord(path, "c3d", label, points, None, (frames - frames[0]) / rate, frames, source_kind="frame")
