"""What a mechanism is commanded to do (its task) and where it works (its workspace).

Both come from the closures file (schema version 2, models/README.md):

    task: {frame: effector, position: [x, y], rotation: none}
    workspace: {actuators: {motor_1: [lo, hi], ...}}   or   {task: {x: [lo, hi], y: [lo, hi]}}

The task of a frame F is a set of base-frame components of its placement oMf:
- position: the chosen axes of oMf.translation [m];
- rotation "yaw": the heading of F's x axis about base z, theta = atan2(R[1,0], R[0,0]) [rad];
- rotation "full": the whole rotation, residual log3(R*^T R) [rad] (in F's axes).
Task coordinates (the rows of a targets table) are the position components, then theta for "yaw",
or the unit quaternion (qx, qy, qz, qw) for "full". The task's dimension is its number of residual
rows (position count, plus 1 for yaw, 3 for full); inverse kinematics needs it to equal the
actuator count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pinocchio as pin

from m3t1r.errors import InvalidInputError

__all__ = ["TaskSpec", "WorkspaceSpec", "POSITION_AXES", "ROTATIONS", "QUATERNION_NORM_TOLERANCE"]

POSITION_AXES = ("x", "y", "z")
ROTATIONS = ("none", "yaw", "full")
QUATERNION_NORM_TOLERANCE = 1e-6  # |q| may differ from 1 by this much in a target row (then renormalised)
_QUATERNION = ("qx", "qy", "qz", "qw")
_ROTATION_ROWS = {"none": 0, "yaw": 1, "full": 3}


@dataclass(frozen=True)
class TaskSpec:
    """The commanded components of one frame's placement in the base frame.

    frame: frame name; position: commanded base axes in x, y, z order (a subset);
    rotation: "none", "yaw" (heading about base z) or "full".
    """

    frame: str
    position: tuple[str, ...] = POSITION_AXES
    rotation: Literal["none", "yaw", "full"] = "yaw"
    _rows: slice | np.ndarray = field(init=False, repr=False, compare=False)  # set by __post_init__

    def __post_init__(self) -> None:
        if self.rotation not in ROTATIONS:
            raise InvalidInputError(f"task rotation must be one of {', '.join(ROTATIONS)}, got {self.rotation!r}")
        if len(set(self.position)) != len(self.position) or any(a not in POSITION_AXES for a in self.position):
            raise InvalidInputError(f"task position must be distinct axes among x, y, z, got {list(self.position)}")
        ordered = tuple(a for a in POSITION_AXES if a in self.position)
        object.__setattr__(self, "position", ordered)
        # The position rows as a slice when the axes are contiguous (x,y,z / x,y / y,z ...): basic
        # indexing costs a fraction of fancy indexing in the IK's inner loop.
        indices = [POSITION_AXES.index(a) for a in ordered]
        contiguous = bool(indices) and indices == list(range(indices[0], indices[0] + len(indices)))
        object.__setattr__(
            self, "_rows", slice(indices[0], indices[-1] + 1) if contiguous else np.array(indices, dtype=int)
        )
        if self.dimension == 0:
            raise InvalidInputError("task: commands nothing (no position axis and rotation none)")

    @property
    def axes(self) -> np.ndarray:
        """Indices (0, 1, 2 for x, y, z) of the commanded position axes."""
        return np.array([POSITION_AXES.index(a) for a in self.position], dtype=int)

    @property
    def dimension(self) -> int:
        """Number of residual rows: one per position axis, plus 1 (yaw) or 3 (full rotation)."""
        return len(self.position) + _ROTATION_ROWS[self.rotation]

    @property
    def columns(self) -> tuple[str, ...]:
        """Names of the task coordinates, as in a targets table: e.g. (x, y, z, theta) or (qx, qy, qz, qw)."""
        rotation = {"none": (), "yaw": ("theta",), "full": _QUATERNION}[self.rotation]
        return self.position + rotation

    @property
    def box_keys(self) -> tuple[str, ...]:
        """Names of the task-space workspace box's intervals (full rotation: roll, pitch, yaw, ZYX)."""
        rotation = {"none": (), "yaw": ("yaw",), "full": ("roll", "pitch", "yaw")}[self.rotation]
        return self.position + rotation

    def coordinates(self, poses: np.ndarray) -> np.ndarray:
        """Task coordinates (N, len(columns)) of frame placements (N, 4, 4) [m, rad]."""
        poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        parts = [poses[:, self.axes, 3]]
        if self.rotation == "yaw":
            parts.append(np.arctan2(poses[:, 1, 0], poses[:, 0, 0])[:, None])
        elif self.rotation == "full":
            parts.append(np.array([pin.Quaternion(r).coeffs() for r in poses[:, :3, :3]]).reshape(-1, 4))
        return np.hstack(parts)

    def box_coordinates(self, poses: np.ndarray) -> np.ndarray:
        """Coordinates (N, len(box_keys)) of frame placements (N, 4, 4) in a task box's terms:
        position, then yaw, or roll, pitch, yaw (ZYX, `pin.rpy.matrixToRpy`) [m, rad]."""
        poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
        if self.rotation != "full":
            return self.coordinates(poses)
        angles = np.array([pin.rpy.matrixToRpy(r) for r in poses[:, :3, :3]]).reshape(-1, 3)
        return np.hstack((poses[:, self.axes, 3], angles))

    def goals(self, coordinates: np.ndarray) -> np.ndarray:
        """Checked task coordinates (N, len(columns)); quaternions renormalised (within the tolerance).

        Raises InvalidInputError on a wrong width, a non-finite value or a quaternion whose norm is
        off by more than QUATERNION_NORM_TOLERANCE.
        """
        array = np.array(coordinates, dtype=float)
        if array.ndim == 1:
            array = array.reshape(1, -1)
        width = len(self.columns)
        if array.ndim != 2 or array.shape[1] != width:
            raise InvalidInputError(
                f"targets: shape {np.shape(coordinates)}, expected rows of {width} "
                f"task coordinates ({', '.join(self.columns)})"
            )
        bad = ~np.isfinite(array).all(axis=1)
        if bad.any():
            raise InvalidInputError(f"targets: row {int(np.flatnonzero(bad)[0])} has a non-finite value")
        if self.rotation == "full":
            norms = np.linalg.norm(array[:, -4:], axis=1)
            off = np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE
            if off.any():
                row = int(np.flatnonzero(off)[0])
                raise InvalidInputError(
                    f"targets: row {row}: quaternion (qx, qy, qz, qw) has norm {norms[row]:.9g}, "
                    f"not 1 (tolerance {QUATERNION_NORM_TOLERANCE:g})"
                )
            array[:, -4:] /= norms[:, None]
        return array

    def target_rotations(self, goals: np.ndarray) -> np.ndarray | None:
        """Rotation matrices (N, 3, 3) of checked goals with a full rotation task, else None."""
        if self.rotation != "full":
            return None
        return np.array([pin.Quaternion(*row[[3, 0, 1, 2]]).matrix() for row in goals[:, -4:]]).reshape(-1, 3, 3)

    def residual(self, placement: pin.SE3, goal: np.ndarray, goal_rotation: np.ndarray | None) -> np.ndarray:
        """Task rows at one frame placement: commanded position error [m], then wrap(theta - theta*) or
        log3(R*^T R) [rad]."""
        count = len(self.position)
        out = np.empty(self.dimension)
        out[:count] = placement.translation[self._rows]
        out[:count] -= goal[:count]
        if self.rotation == "yaw":
            rotation = placement.rotation
            out[count] = math.remainder(math.atan2(rotation[1, 0], rotation[0, 0]) - goal[count], 2 * math.pi)
        elif self.rotation == "full":
            assert goal_rotation is not None, "a full-rotation goal has its rotation"
            out[count:] = pin.log3(goal_rotation.T @ placement.rotation)
        return out

    def jacobian(self, placement: pin.SE3, frame_jacobian: np.ndarray, goal_rotation: np.ndarray | None) -> np.ndarray:
        """d(task rows)/dq from the frame's LOCAL_WORLD_ALIGNED Jacobian (6 x nv, [v; w]).

        yaw: d atan2(R10, R00) / d omega_world with dR = [omega]x R; full: Jlog3(R*^T R) R^T omega_world.
        """
        count = len(self.position)
        out = np.empty((self.dimension, frame_jacobian.shape[1]))
        out[:count] = frame_jacobian[self._rows]
        if self.rotation == "yaw":
            c0, c1, c2 = placement.rotation[:, 0].tolist()
            horizontal = c0 * c0 + c1 * c1
            out[count] = np.dot((-c0 * c2 / horizontal, -c1 * c2 / horizontal, 1.0), frame_jacobian[3:])
        elif self.rotation == "full":
            assert goal_rotation is not None, "a full-rotation goal has its rotation"
            rotation = placement.rotation
            out[count:] = pin.Jlog3(goal_rotation.T @ rotation) @ (rotation.T @ frame_jacobian[3:])
        return out


@dataclass(frozen=True)
class WorkspaceSpec:
    """Where a mechanism works: a box of actuator values or of task coordinates, [m or rad].

    actuators: {actuated joint: (lo, hi)}; task: {task box key (`TaskSpec.box_keys`): (lo, hi)}.
    Exactly one of the two is set.
    """

    actuators: tuple[tuple[str, float, float], ...] = ()
    task: tuple[tuple[str, float, float], ...] = ()

    def __post_init__(self) -> None:
        if bool(self.actuators) == bool(self.task):
            raise InvalidInputError("workspace: give exactly one box, 'actuators' or 'task'")
        for name, lo, hi in self.actuators + self.task:
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise InvalidInputError(
                    f"workspace: interval of '{name}' must be finite with lo <= hi, got [{lo}, {hi}]"
                )

    @property
    def kind(self) -> Literal["actuators", "task"]:
        return "actuators" if self.actuators else "task"

    def bounds(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) arrays of the box in the order of `names` (actuated joints or task box keys)."""
        box = {name: (lo, hi) for name, lo, hi in self.actuators + self.task}
        return np.array([box[n][0] for n in names]), np.array([box[n][1] for n in names])

    def task_poses(self, task: TaskSpec, rng: np.random.Generator, n: int) -> np.ndarray:
        """n task coordinates drawn uniformly in a task box (yaw and roll/pitch/yaw drawn as angles)."""
        lo, hi = self.bounds(task.box_keys)
        draws = lo + (hi - lo) * rng.random((n, len(lo)))
        if task.rotation != "full":
            return draws
        quaternions = [pin.Quaternion(pin.rpy.rpyToMatrix(*angles)).coeffs() for angles in draws[:, -3:]]
        return np.hstack((draws[:, :-3], np.array(quaternions).reshape(-1, 4)))
