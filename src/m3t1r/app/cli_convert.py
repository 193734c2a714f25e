"""`m3t1r convert`: an instrument's file (and the robot's log) to the project's measurement CSV.

The format is detected from the content (or named with --format); a stream becomes one pose per
still stretch, averaged, with its scatter kept; the poses are paired with the robot log's stops by
order or by a clock offset that is estimated and printed. The output is written atomically, in
metres and radians, with a `source` column naming where each pose is in the tracker's file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from m3t1r.app.cli_common import provenance
from m3t1r.io.instruments.conversion import ConversionOptions, convert_campaign
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.formats import FORMATS
from m3t1r.io.outputs import OutputSet
from m3t1r.io.tables import table_text

__all__ = ["add_convert_parser"]


def add_convert_parser(verbs: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `convert` verb to argparse's subparsers object `verbs`."""
    p = verbs.add_parser("convert", help="a tracker's export (and the robot's log) -> measurement CSV",
                         description="Formats: " + "; ".join(f"{name}: {text}" for name, (_, text) in FORMATS.items()))
    p.add_argument("tracker", metavar="TRACKER_FILE", help="the instrument's file (a bag: its folder or .db3/.mcap)")
    p.add_argument("--robot", metavar="ROBOT_LOG", help="the robot's joint log: CSV (time or t_start,t_end, joints "
                                                        "by name) or a ROS 2 bag with JointState")
    p.add_argument("-o", "--output", required=True, metavar="MEASUREMENTS.csv", help="measurement CSV to write")
    p.add_argument("--format", choices=tuple(FORMATS), help="the tracker file's format (default: from its content)")
    p.add_argument("--body", metavar="NAME", help="the rigid body, marker, label, group or topic to read "
                                                  "(a marker number K for x1..xK columns; rigid: those markers as "
                                                  "one rigid body)")
    p.add_argument("--units", choices=("m", "mm", "cm", "in"), help="position unit when the file does not state it "
                                                                    "(default m for tables)")
    p.add_argument("--euler", metavar="SEQ", help="Euler convention of rotation columns (scipy's: xyz extrinsic, "
                                                  "XYZ intrinsic)")
    p.add_argument("--degrees", action="store_true", help="Euler angles in degrees")
    p.add_argument("--joints", nargs="+", metavar="NAME", help="the joint columns (default: every other numeric "
                                                               "column but times and counters)")
    p.add_argument("--joint-degrees", nargs="+", default=[], metavar="NAME",
                   help="joint columns in degrees ('all': every joint)")
    p.add_argument("--still-speed", type=_positive, default=5e-3, metavar="M_PER_S",
                   help="a tracker stream is still below this speed (default 5e-3 m/s)")
    p.add_argument("--robot-still-speed", type=_positive, default=2e-3, metavar="RAD_PER_S",
                   help="the robot log is still below this joint speed (default 2e-3 rad/s or m/s)")
    p.add_argument("--min-dwell", type=_positive, default=0.5, metavar="S",
                   help="shortest still stretch kept as a pose (default 0.5 s)")
    p.add_argument("--pair", choices=("auto", "order", "time"), default="auto",
                   help="pair poses with the robot's stops by clock (auto, when both have times) or by order")
    p.set_defaults(run=cmd_convert)
    return p


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"a positive number, got {text}")
    return value


def cmd_convert(args: argparse.Namespace) -> None:
    """`m3t1r convert` (module docstring)."""
    tracker = Path(args.tracker)
    robot = Path(args.robot) if args.robot else None
    outputs = OutputSet(inputs=(tracker, robot))
    output = outputs.add(args.output, "-o")
    outputs.check()
    read = ReadOptions(body=args.body, units=args.units, euler=args.euler, degrees=args.degrees,
                       joints=tuple(args.joints) if args.joints else None, joint_degrees=tuple(args.joint_degrees))
    conversion = convert_campaign(tracker, robot, ConversionOptions(
        format=args.format, read=read, still_speed=args.still_speed, robot_still_speed=args.robot_still_speed,
        min_dwell=args.min_dwell, pairing=args.pair))
    for note in conversion.notes:
        print(note)
    comments = provenance(args) + [
        f"converted from {tracker} ({conversion.format})" + (f" and {robot}" if robot else ""),
        "lengths m, angles rad; x, y, z [, qx, qy, qz, qw]: the tracked point in the tracker's frame; "
        "source: the tracker file's line, frame or message of the pose's first sample; position_std [m]: its scatter"]
    if conversion.clock_offset is not None:
        comments.append(f"clock offset: robot clock = tracker clock {conversion.clock_offset:+.6f} s")
    with outputs:
        outputs.stage(output, table_text(conversion.columns, conversion.rows, comments))
        written = outputs.commit()
    print(f"wrote {len(conversion.rows)} poses to " + ", ".join(written))
