"""The tracker formats `m3t1r convert` reads, by name, with a line each: no reader imported.

The command line builds `convert --help` and its `--format` choices from this table at start-up;
`formats.FORMATS` pairs each name with its reader.
"""

from __future__ import annotations

__all__ = ["FORMAT_DESCRIPTIONS"]

FORMAT_DESCRIPTIONS: dict[str, str] = {
    "csv": "delimited table: x,y,z or x1,y1,z1 ..., optional time, quaternion, joints",
    "motive": "OptiTrack Motive CSV export (rigid body or marker)",
    "vicon": "Vicon CSV export (Objects, Segments or Trajectories block)",
    "c3d": "C3D file (needs m3t1r[formats])",
    "spatial-analyzer": "SpatialAnalyzer ASCII point export",
    "rosbag": "ROS 2 bag: PoseStamped, TransformStamped or /tf (needs m3t1r[formats])",
}
