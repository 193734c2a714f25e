"""ROS 2 bags (through `rosbags`, the `m3t1r[formats]` extra): tracker poses and joint states.

Poses come from `geometry_msgs/msg/PoseStamped` or `geometry_msgs/msg/TransformStamped` topics, or
`tf2_msgs/msg/TFMessage` (`/tf`) transforms, chosen by topic name or child frame (`--body`); joint
readings from a `sensor_msgs/msg/JointState` topic. Times are the messages' header stamps [s]
(the sender's clock); sources are message numbers in the topic, counted from 1.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from m3t1r.errors import DataFileError, MissingExtraError
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.records import TrackerRecord
from m3t1r.io.instruments.robot_log import RobotLog

__all__ = ["looks_bag", "read_bag_poses", "read_bag_joints"]

_POSE, _TRANSFORM, _TF = "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped", "tf2_msgs/msg/TFMessage"
_JOINTS = "sensor_msgs/msg/JointState"


def looks_bag(path: Path) -> bool:
    """A bag directory (with metadata.yaml) or a .db3 / .mcap file."""
    return (path.is_dir() and (path / "metadata.yaml").is_file()) or path.suffix.lower() in (".db3", ".mcap")


def _messages(path: Path, msgtypes: tuple[str, ...]) -> list[tuple[str, str, Any]]:
    """(topic, msgtype, message) of every message of these types, in bag order."""
    try:
        from rosbags.highlevel import AnyReader  # the optional reader, imported only for a bag
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingExtraError("reading ROS 2 bags needs the rosbags package: pip install 'm3t1r[formats]'") from None
    bag = path.parent if path.is_file() else path
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            connections = [c for c in reader.connections if c.msgtype in msgtypes]
            return [
                (c.topic, c.msgtype, reader.deserialize(raw, c.msgtype))
                for c, _, raw in reader.messages(connections=connections)
            ]
    except Exception as exc:  # rosbags raises its own error types for every broken bag
        if isinstance(exc, MissingExtraError):
            raise
        raise DataFileError(path, f"not a readable ROS 2 bag ({exc})") from None


def _stamp(message: Any) -> float:
    return float(message.header.stamp.sec) + 1e-9 * float(message.header.stamp.nanosec)


def read_bag_poses(path: Path, options: ReadOptions, notes: list[str]) -> TrackerRecord:
    """The poses of one topic or child frame (`options.body`; by default the only one)."""
    samples: dict[str, list[tuple[float, Any, Any]]] = {}
    for topic, msgtype, message in _messages(path, (_POSE, _TRANSFORM, _TF)):
        if msgtype == _POSE:
            samples.setdefault(topic, []).append((_stamp(message), message.pose.position, message.pose.orientation))
        for transform in message.transforms if msgtype == _TF else [message] if msgtype == _TRANSFORM else []:
            key = transform.child_frame_id if msgtype == _TF else topic
            samples.setdefault(key, []).append(
                (_stamp(transform), transform.transform.translation, transform.transform.rotation)
            )
    if not samples:
        raise DataFileError(path, "no PoseStamped, TransformStamped or /tf messages in the bag")
    if options.body is None and len(samples) != 1:
        raise DataFileError(path, f"choose the tracked body with --body: {', '.join(sorted(samples))}")
    body = options.body if options.body is not None else next(iter(samples))
    if body not in samples:
        raise DataFileError(path, f"--body {body}: the bag has {', '.join(sorted(samples))}")
    chosen = samples[body]
    positions = np.array([[p.x, p.y, p.z] for _, p, _ in chosen], dtype=float)
    quaternions = np.array([[q.x, q.y, q.z, q.w] for _, _, q in chosen], dtype=float)
    return TrackerRecord(
        path,
        "rosbag",
        body,
        positions,
        quaternions,
        np.array([t for t, _, _ in chosen]),
        np.arange(1, len(chosen) + 1),
        source_kind="message",
    )


def read_bag_joints(path: Path, joints: tuple[str, ...] | None = None) -> RobotLog:
    """The joint readings of the bag's JointState topic (one topic; `joints` picks and orders them)."""
    messages = _messages(path, (_JOINTS,))
    if not messages:
        raise DataFileError(path, "no sensor_msgs/msg/JointState messages in the bag")
    topics = sorted({topic for topic, _, _ in messages})
    if len(topics) > 1:
        raise DataFileError(path, f"several JointState topics ({', '.join(topics)}): convert one bag per robot")
    names = tuple(joints) if joints is not None else tuple(messages[0][2].name)
    rows = []
    for k, (_, _, message) in enumerate(messages, start=1):
        by_name = dict(zip(message.name, message.position))
        missing = [n for n in names if n not in by_name]
        if missing:
            raise DataFileError(path, f"JointState message {k} has no {', '.join(missing)}")
        rows.append([float(by_name[n]) for n in names])
    return RobotLog(
        path,
        names,
        np.array(rows),
        np.array([_stamp(m) for _, _, m in messages]),
        None,
        np.arange(1, len(messages) + 1),
    )
