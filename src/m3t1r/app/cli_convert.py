"""`m3t1r convert`: an instrument's file (and the robot's log) to the project's measurement CSV.

The format is detected from the content (or named with --format); a stream becomes one pose per
still stretch, averaged, with its scatter kept; the poses are paired with the robot log's stops by
order or by a clock offset that is estimated and printed. The output is written atomically, in
metres and radians, with a `source` column naming where each pose is in the tracker's file.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from m3t1r.app.cli_common import provenance
from m3t1r.io.instruments.conversion import ConversionOptions, convert_campaign
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.outputs import OutputSet
from m3t1r.io.tables import table_text

__all__ = ["cmd_convert"]


def cmd_convert(args: argparse.Namespace) -> None:
    """`m3t1r convert` (module docstring)."""
    tracker = Path(args.tracker)
    robot = Path(args.robot) if args.robot else None
    outputs = OutputSet(inputs=(tracker, robot))
    output = outputs.add(args.output, "-o")
    outputs.check()
    read = ReadOptions(
        body=args.body,
        units=args.units,
        euler=args.euler,
        degrees=args.degrees,
        joints=tuple(args.joints) if args.joints else None,
        joint_degrees=tuple(args.joint_degrees),
        rotation_vector=args.rotation_vector,
    )
    conversion = convert_campaign(
        tracker,
        robot,
        ConversionOptions(
            format=args.format,
            read=read,
            still_speed=args.still_speed,
            robot_still_speed=args.robot_still_speed,
            min_dwell=args.min_dwell,
            pairing=args.pair,
        ),
    )
    for note in conversion.notes:
        print(note)
    comments = provenance(args) + [
        f"converted from {tracker} ({conversion.format})" + (f" and {robot}" if robot else ""),
        "lengths m, angles rad; x, y, z [, qx, qy, qz, qw]: the tracked point in the tracker's frame; "
        "source: the tracker file's line, frame or message of the pose's first sample; position_std [m]: its scatter",
    ]
    if conversion.clock_offset is not None:
        comments.append(f"clock offset: robot clock = tracker clock {conversion.clock_offset:+.6f} s")
    points = [c for c in conversion.columns if re.fullmatch(r"[xyz]\d+", c)]
    if points:
        comments.append("x1, y1, z1 ...: each marker's position, blank where the tracker did not see it")
    with outputs:
        outputs.stage(output, table_text(conversion.columns, conversion.rows, comments, blank_allowed=points))
        written = outputs.commit()
    print(f"wrote {len(conversion.rows)} poses to " + ", ".join(written))
