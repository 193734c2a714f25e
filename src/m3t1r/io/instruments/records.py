"""What every tracker reader returns: `TrackerRecord`, the samples of one body or marker, in SI units.

Positions are metres, orientations unit quaternions (x, y, z, w) of the body in the tracker's
frame, times seconds on the tracker's clock. Occluded samples are NaN rows. Each sample keeps
where it came from (`sources`: the file's 1-based line, or the frame number for binary formats,
`source_kind` says which) so that a gross reading found later can be traced back to the
instrument's file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m3t1r.errors import DataFileError

__all__ = ["CONVERTED_COLUMNS", "TrackerRecord", "LENGTH_SCALES", "length_scale"]

#: The columns `m3t1r convert` adds to a measurement table, which `calibrate` accepts: the tracker
#: file's line, frame or message of each pose, and the pose's position scatter [m].
CONVERTED_COLUMNS = ("source", "position_std")

#: Length units as instruments name them, in metres per unit.
LENGTH_SCALES = {
    "m": 1.0,
    "meter": 1.0,
    "meters": 1.0,
    "metre": 1.0,
    "metres": 1.0,
    "mm": 1e-3,
    "millimeter": 1e-3,
    "millimeters": 1e-3,
    "millimetre": 1e-3,
    "millimetres": 1e-3,
    "cm": 1e-2,
    "centimeter": 1e-2,
    "centimeters": 1e-2,
    "in": 0.0254,
    "inch": 0.0254,
    "inches": 0.0254,
}


def length_scale(path: Path, unit: str, line: int | None = None) -> float:
    """Metres per `unit` (as an instrument writes it, any case); DataFileError naming it otherwise."""
    try:
        return LENGTH_SCALES[unit.strip().lower()]
    except KeyError:
        raise DataFileError(path, f"unknown length unit '{unit}' (known: m, mm, cm, in)", row=line) from None


@dataclass(frozen=True, eq=False)
class TrackerRecord:
    """The samples of one tracked body or marker, read from an instrument's file.

    path, format: the file and its format name; body: the body, marker or point set read.
    positions: (N, 3) [m] in the tracker's frame, NaN rows where occluded.
    quaternions: (N, 4) unit (x, y, z, w) of the body in the tracker's frame, or None (a marker).
    times: (N,) [s] on the tracker's clock, or None (one static pose per sample).
    joints, joint_names: (N, J) readings [rad, m] recorded with the samples (a CSV holding both),
        or an empty (N, 0) block.
    sources: (N,) where each sample is in the file; source_kind: "line", "frame" or "message".
    scatter: (N,) [m] a position scatter the file states per sample (a per-pose noise figure), or None.
    points: (N, K, 3) [m] every marker of a sample, NaN where not seen, when all are kept (`--body
        all`; `positions` is then the centroid of the markers seen, which finds the still stretches),
        with `point_numbers` (K,) their numbers in the file; else None.
    """

    path: Path
    format: str
    body: str
    positions: np.ndarray
    quaternions: np.ndarray | None
    times: np.ndarray | None
    sources: np.ndarray
    source_kind: str = "line"
    joints: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    joint_names: tuple[str, ...] = ()
    scatter: np.ndarray | None = None
    points: np.ndarray | None = None
    point_numbers: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.positions)
        if self.positions.shape != (n, 3) or len(self.sources) != n:
            raise ValueError(f"positions {self.positions.shape} and sources {len(self.sources)} do not match")
        if self.joints.size == 0:
            object.__setattr__(self, "joints", np.zeros((n, 0)))
        if self.joints.shape != (n, len(self.joint_names)):
            raise ValueError(f"joints {self.joints.shape} do not match {len(self.joint_names)} names and {n} samples")
        if n == 0:
            raise DataFileError(self.path, f"no samples of {self.body} in the file")

    @property
    def n_samples(self) -> int:
        """Number of samples (frames or points)."""
        return int(len(self.positions))
