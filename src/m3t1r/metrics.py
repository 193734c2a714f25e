"""Per-pose accuracy figures shared by the serial and the closed-loop calibrations.

One shape serves both the errors of a model against a reference (position distance and rotation
angle per pose, the quantities of the paper's Fig. 4) and the predicted standard deviations of a
calibrated model (root of the trace of the position and orientation covariance blocks per pose):
a position array in m and a rotation array in rad, one entry per pose.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r.errors import InvalidInputError

__all__ = ["PoseErrors", "pose_errors_between", "rotation_angles"]


@dataclass(frozen=True, eq=False)
class PoseErrors:
    """Per-pose position [m] and rotation [rad] figures, (M,) each.

    Errors: position = |p_a - p_b|, rotation = |log3(R_a^T R_b)| (see `pose_errors_between`).
    Predicted standard deviations: sqrt(trace Cov(dp)) and sqrt(trace Cov(dr)), i.e. the RMS of the
    position error norm and of the rotation angle to expect. Rotation may be NaN where orientation
    is not available (position-only data), and then so are its summaries.
    eq=False: equality of array fields is element-wise, so objects compare by identity.
    """

    position: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        position = np.asarray(self.position, dtype=float)
        rotation = np.asarray(self.rotation, dtype=float)
        if position.ndim != 1 or rotation.shape != position.shape:
            raise InvalidInputError(
                f"PoseErrors: position and rotation must be 1-D arrays of one value per pose, "
                f"got shapes {position.shape} and {rotation.shape}"
            )
        object.__setattr__(self, "position", position)  # frozen: normalise once, at construction
        object.__setattr__(self, "rotation", rotation)

    @property
    def position_mean(self) -> float:
        """Mean over poses (m)."""
        return float(np.mean(self.position))

    @property
    def position_max(self) -> float:
        """Largest value over poses (m)."""
        return float(np.max(self.position))

    @property
    def position_rms(self) -> float:
        """Root mean square over poses (m); compares an error with a predicted standard deviation."""
        return float(np.sqrt(np.mean(self.position**2)))

    @property
    def rotation_mean(self) -> float:
        """Mean over poses (rad)."""
        return float(np.mean(self.rotation))

    @property
    def rotation_max(self) -> float:
        """Largest value over poses (rad)."""
        return float(np.max(self.rotation))

    @property
    def rotation_rms(self) -> float:
        """Root mean square over poses (rad)."""
        return float(np.sqrt(np.mean(self.rotation**2)))


def rotation_angles(rotations_a: ArrayLike, rotations_b: ArrayLike) -> np.ndarray:
    """Angles |log3(R_a^T R_b)| (M,) in [0, pi] (rad) of rotation matrices (M, 3, 3), batched.

    atan2(|sin|, cos) rather than arccos of the trace: arccos loses half the digits near 0, where
    calibrated models live (1e-5 rad would come out at 1e-8 relative accuracy).
    """
    relative = np.swapaxes(np.asarray(rotations_a, dtype=float), -1, -2) @ np.asarray(rotations_b, dtype=float)
    # R - R^T = 2 sin(angle) [axis]: its off-diagonal entries give |sin|, the trace gives cos.
    sine_axis = np.stack(
        [
            relative[..., 2, 1] - relative[..., 1, 2],
            relative[..., 0, 2] - relative[..., 2, 0],
            relative[..., 1, 0] - relative[..., 0, 1],
        ],
        axis=-1,
    )
    cosine = np.trace(relative, axis1=-2, axis2=-1) - 1.0
    return np.arctan2(np.linalg.norm(sine_axis, axis=-1), cosine)  # both scaled by 2: same angle


def _as_homogeneous(poses: Sequence[pin.SE3] | ArrayLike, what: str) -> np.ndarray:
    if isinstance(poses, np.ndarray):
        array = np.asarray(poses, dtype=float)
    else:
        rows = (
            [g.homogeneous if isinstance(g, pin.SE3) else np.asarray(g, dtype=float) for g in poses]
            if isinstance(poses, Iterable)
            else [np.asarray(poses, dtype=float)]
        )  # a scalar: refused below
        array = np.array(rows) if rows else np.empty((0, 4, 4))
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise InvalidInputError(
            f"{what}: expected pinocchio.SE3 objects or (M, 4, 4) homogeneous matrices, got shape {array.shape}"
        )
    return array


def pose_errors_between(poses_a: Sequence[pin.SE3] | ArrayLike, poses_b: Sequence[pin.SE3] | ArrayLike) -> PoseErrors:
    """Pose by pose: position distance |p_a - p_b| (m) and rotation angle |log3(R_a^T R_b)| (rad).

    poses_a, poses_b: M poses each, as pinocchio.SE3 objects or (M, 4, 4) homogeneous matrices,
    expressed in the same frame. Symmetric in a and b.
    """
    a = _as_homogeneous(poses_a, "poses_a")
    b = _as_homogeneous(poses_b, "poses_b")
    if a.shape != b.shape:
        raise InvalidInputError(f"pose_errors_between: {a.shape[0]} poses against {b.shape[0]}")
    position = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    return PoseErrors(position=position, rotation=rotation_angles(a[:, :3, :3], b[:, :3, :3]))
