"""Which reader a file needs: detected from its content, or named with `--format`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from m3t1r.errors import DataFileError, InvalidInputError
from m3t1r.io.instruments.c3d import looks_c3d, read_c3d
from m3t1r.io.instruments.delimited import ReadOptions, looks_delimited, read_delimited
from m3t1r.io.instruments.names import FORMAT_DESCRIPTIONS
from m3t1r.io.instruments.optitrack import looks_motive, read_motive
from m3t1r.io.instruments.records import TrackerRecord
from m3t1r.io.instruments.robot_log import RobotLog, read_robot_csv
from m3t1r.io.instruments.rosbag import looks_bag, read_bag_joints, read_bag_poses
from m3t1r.io.instruments.spatial_analyzer import looks_spatial_analyzer, read_spatial_analyzer
from m3t1r.io.instruments.text import numbered_lines
from m3t1r.io.instruments.vicon import looks_vicon, read_vicon

__all__ = ["FORMATS", "detect_format", "export_hint", "read_tracker", "read_robot_log"]

Reader = Callable[[Path, ReadOptions, list[str]], TrackerRecord]

#: Format name -> reader (the descriptions: `names.FORMAT_DESCRIPTIONS`).
_READERS: dict[str, Reader] = {
    "csv": read_delimited,
    "motive": read_motive,
    "vicon": read_vicon,
    "c3d": read_c3d,
    "spatial-analyzer": read_spatial_analyzer,
    "rosbag": read_bag_poses,
}
#: Format name -> (reader, description).
FORMATS: dict[str, tuple[Reader, str]] = {name: (_READERS[name], FORMAT_DESCRIPTIONS[name]) for name in _READERS}


def detect_format(path: Path) -> str:
    """The format name of `path` from its content; DataFileError naming what it looks like otherwise."""
    if not path.exists():
        raise DataFileError(path, "no such file or directory")
    if looks_bag(path):
        return "rosbag"
    if looks_c3d(path):
        return "c3d"
    lines = numbered_lines(path)
    for name, looks in (
        ("motive", looks_motive),
        ("vicon", looks_vicon),
        ("csv", looks_delimited),
        ("spatial-analyzer", looks_spatial_analyzer),
    ):
        if looks(lines):
            return name
    first = next((t.strip() for _, t in lines if t.strip()), "")
    raise DataFileError(
        path, f"not a tracker export convert knows (first line '{first[:60]}'): give --format ({', '.join(FORMATS)})"
    )


def read_tracker(path: Path, format_name: str | None, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """The record of one body or marker, in the format named or detected."""
    name = format_name or detect_format(path)
    if name not in FORMATS:
        raise InvalidInputError(f"--format {name}: expected one of {', '.join(FORMATS)}")
    return FORMATS[name][0](path, options, notes)


def read_robot_log(path: Path, joints: tuple[str, ...] | None, joint_degrees: tuple[str, ...]) -> RobotLog:
    """The robot's joint log: a ROS 2 bag's JointState, or a CSV (`robot_log`)."""
    if looks_bag(path):
        return read_bag_joints(path, joints)
    return read_robot_csv(path, joints, joint_degrees)


def _is_raw(column: str) -> bool:
    """A column a measurement table never has, but a tracker's table does (times, counters, scatter in mm)."""
    return (
        "time" in column
        or "stamp" in column
        or column.startswith("t_")
        or column.endswith("_std_mm")
        or "row" in column
        or column in ("t", "frame", "index")
    )


def export_hint(path: Path) -> str | None:
    """When `path` is an instrument's export rather than a measurement table, the sentence saying
    which and how to convert it; None for a measurement table (or a file no reader knows)."""
    try:
        name = detect_format(path)
    except (DataFileError, InvalidInputError):
        return None
    if name == "csv":
        header = next((t for _, t in numbered_lines(path) if t.strip() and not t.lstrip().startswith("#")), "")
        names = {n.strip().lower() for n in header.replace(";", ",").replace("\t", ",").split(",")}
        if ";" not in header and "\t" not in header and {"x", "y", "z"} <= names and not names & {"time", "x1"}:
            return None
        if ";" not in header and "\t" not in header and {"x1", "y1", "z1"} <= names and not any(map(_is_raw, names)):
            return None  # several points per row, as `convert --body all` writes them
    what = (
        "table of tracker samples (several markers, a time column or ';' separators)"
        if name == "csv"
        else FORMATS[name][1].split(" (")[0].split(":")[0]
    )
    return (
        f"{path} is an instrument's export ({what}), not a measurement table: convert it first, "
        f"`m3t1r convert {path} [--robot ROBOT_LOG] -o measurements.csv`"
    )
