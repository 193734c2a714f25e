"""Serial robots to calibrate: the example-robot-data arms (UR3/5/10, Panda), their tool frames."""

from __future__ import annotations

import functools
import importlib.metadata
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Literal

import pinocchio as pin

from m3t1r.errors import InvalidInputError, ModelFileError
from m3t1r.io.paths import read_bounded, size_refusal
from m3t1r.model.poe import SerialChain
from m3t1r.model.urdf_io import refuse_mimic_joints

__all__ = [
    "RobotName",
    "example_robot_data_dir",
    "example_tool_frame",
    "load_example_robot",
    "load_serial_urdf",
    "serial_chain_of",
]


RobotName = Literal["ur3", "ur5", "ur10", "panda"]


@dataclass(frozen=True)
class _ExampleRobot:
    urdf: tuple[str, ...]  # path under example-robot-data's robots/ directory
    tool_frame: str
    locked_joints: tuple[str, ...] = ()


_EXAMPLE_ROBOTS: Mapping[str, _ExampleRobot] = MappingProxyType(
    {
        "ur3": _ExampleRobot(("ur_description", "urdf", "ur3_robot.urdf"), "tool0"),
        "ur5": _ExampleRobot(("ur_description", "urdf", "ur5_robot.urdf"), "tool0"),
        "ur10": _ExampleRobot(("ur_description", "urdf", "ur10_robot.urdf"), "tool0"),
        # The fingers are a separate branch; the calibrated chain ends at the hand's TCP frame.
        "panda": _ExampleRobot(
            ("panda_description", "urdf", "panda.urdf"),
            "panda_hand_tcp",
            ("panda_finger_joint1", "panda_finger_joint2"),
        ),
    }
)


def _example_robot(name: str) -> _ExampleRobot:
    try:
        return _EXAMPLE_ROBOTS[name]
    except KeyError:
        known = ", ".join(sorted(_EXAMPLE_ROBOTS))
        raise InvalidInputError(f"unknown example robot '{name}' (known: {known})") from None


@functools.cache
def example_robot_data_dir() -> Path:
    """The installed `robots/` directory of the example-robot-data distribution.

    Version 6 ships data files only (under its cmeel prefix, no Python module), so the directory
    is located through the distribution's file list rather than an import.
    """
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        raise ModelFileError("example-robot-data", "distribution not installed") from None
    marker = ("share", "example-robot-data", "robots")
    for file in dist.files or ():
        parts = file.parts
        for i in range(len(parts) - len(marker)):
            if parts[i : i + len(marker)] == marker:
                return Path(str(dist.locate_file(Path(*parts[: i + len(marker)]))))
    raise ModelFileError("example-robot-data", "no share/example-robot-data/robots directory in the distribution")


def example_tool_frame(name: RobotName | str) -> str:
    """The tool frame used for example robot `name` (e.g. 'tool0' for UR, 'panda_hand_tcp')."""
    return _example_robot(name).tool_frame


def load_example_robot(name: RobotName | str) -> pin.Model:
    """Kinematic model of an example-robot-data arm, offline, without geometry.

    Panda's two finger joints are locked at their neutral value (`pin.buildReducedModel`), leaving
    the 7 arm joints; its tool frame 'panda_hand_tcp' then hangs from panda_joint7.
    """
    spec = _example_robot(name)
    path = example_robot_data_dir().joinpath(*spec.urdf)
    if not path.is_file():
        raise ModelFileError(path, f"URDF of example robot '{name}' is missing")
    model = pin.buildModelFromUrdf(str(path))
    if spec.locked_joints:
        for joint in spec.locked_joints:
            if not model.existJointName(joint):
                raise ModelFileError(path, f"joint '{joint}' to lock is not in the model")
        ids = [model.getJointId(joint) for joint in spec.locked_joints]
        model = pin.buildReducedModel(model, ids, pin.neutral(model))
    return model


def load_serial_urdf(path: Path) -> tuple[pin.Model, bytes]:
    """A robot's URDF file as a Pinocchio model, and its bytes. ModelFileError naming the file when
    it is missing, too large or not a URDF Pinocchio reads (any XML, or none at all)."""
    if not path.is_file():
        raise ModelFileError(path, "file not found" if not path.exists() else "not a regular file")
    try:
        data = read_bounded(path)
    except OSError as exc:
        raise ModelFileError(path, f"cannot read: {exc.strerror or exc}") from None
    if data is None:
        raise ModelFileError(path, size_refusal())
    try:
        return pin.buildModelFromUrdf(str(path)), data
    except Exception as exc:  # Pinocchio raises bare RuntimeError/ValueError (or worse) for a bad file
        raise ModelFileError(path, f"Pinocchio cannot read this URDF: {exc}") from None


def serial_chain_of(
    model: pin.Model, urdf: bytes | None, path: Path | None, tool: str, base: str | None
) -> SerialChain:
    """The chain from `base` to `tool`, refused by joint name (ModelFileError) when the URDF makes a
    joint of it a `<mimic>` of another (it would be fitted as independent)."""
    chain = SerialChain.from_model(model, tool, base)
    if urdf is not None and path is not None:
        refuse_mimic_joints(path, urdf, chain.joint_names)
    return chain
