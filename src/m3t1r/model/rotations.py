"""Rotation helpers, single and batched: the platform's yaw and tilt, ZYX roll-pitch-yaw, log3 and its
Jacobian, cross-product matrices. Angles in rad; rotations are 3 x 3 (or stacks (..., 3, 3)) in the
frame they are given in.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

__all__ = ["jlog3_batch", "log3_batch", "roll_pitch_of", "rpy_batch", "skew", "yaw_of"]


def yaw_of(rotation: np.ndarray) -> float:
    """Heading of the frame's x axis in the base frame: atan2(R[1,0], R[0,0]) [rad].

    Used everywhere as the platform's yaw theta. Under residual tilt it differs by about
    roll*pitch/2 from the z component of log3 (docs/design.md, "Conventions"); this is the one we command.
    """
    return math.atan2(rotation[1, 0], rotation[0, 0])


def roll_pitch_of(rotation: np.ndarray) -> tuple[float, float]:
    """Roll and pitch [rad] of a rotation (3 x 3, or a 4 x 4 placement's), from Pinocchio's ZYX
    (yaw-pitch-roll) RPY convention: pitch = atan2(-R20, |(R21, R22)|), roll = atan2(R21, R22)."""
    r20, r21, r22 = rotation[2, :3].tolist()
    pitch = math.atan2(-r20, math.sqrt(r21 * r21 + r22 * r22))
    if abs(abs(pitch) - 0.5 * math.pi) < 1e-2:  # near gimbal lock Pinocchio moves the heading into roll
        rpy = pin.rpy.matrixToRpy(np.asarray(rotation)[:3, :3])
        return float(rpy[0]), float(rpy[1])
    return math.atan2(r21, r22), pitch


def rpy_batch(rotations: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) (..., 3) [rad] of rotations (..., 3, 3), ZYX convention as `pin.rpy.matrixToRpy`
    away from pitch = +-pi/2: yaw = atan2(R10, R00), pitch = atan2(-R20, hypot(R21, R22)),
    roll = atan2(R21, R22)."""
    r = rotations
    return np.stack(
        [
            np.arctan2(r[..., 2, 1], r[..., 2, 2]),
            np.arctan2(-r[..., 2, 0], np.hypot(r[..., 2, 1], r[..., 2, 2])),
            np.arctan2(r[..., 1, 0], r[..., 0, 0]),
        ],
        axis=-1,
    )


# Above this rotation angle the axis is read from the symmetric part of R (pin.log3) instead of from
# R - R^T, whose size, 2 sin(angle), vanishes at pi; cos(angle) < -0.99 is beyond 171.9 deg.
_NEAR_PI_COSINE = -0.99


def log3_batch(rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """log3 (N, 3) of rotation matrices (N, 3, 3) and the angles (N,) (rad): pin.log3, batched.

    With R - R^T = 2 sin(a) [u] and trace R = 1 + 2 cos(a): a = atan2(|sin|, cos), log = a u. Angles
    near pi fall back to pin.log3, which recovers the axis from R + R^T (rare in calibration
    residuals, which are small rotations).
    """
    sine_axis = 0.5 * np.stack(
        [
            rotations[:, 2, 1] - rotations[:, 1, 2],
            rotations[:, 0, 2] - rotations[:, 2, 0],
            rotations[:, 1, 0] - rotations[:, 0, 1],
        ],
        axis=1,
    )
    sine = np.linalg.norm(sine_axis, axis=1)
    cosine = 0.5 * (np.trace(rotations, axis1=1, axis2=2) - 1.0)
    angle = np.arctan2(sine, cosine)
    # a / sin(a) is well conditioned everywhere below pi; at a = 0 exactly, sine_axis is zero anyway.
    ratio = np.divide(angle, sine, out=np.ones_like(angle), where=sine > 0.0)
    logs = ratio[:, None] * sine_axis
    for i in np.flatnonzero(cosine < _NEAR_PI_COSINE):
        logs[i] = pin.log3(rotations[i])
    return logs, angle


def jlog3_batch(logs: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """pin.Jlog3 (N, 3, 3) at rotations exp3(logs), logs (N, 3), angles = |logs| (rad).

    Jlog3 = I + [w]/2 + b(a) [w]^2 with b(a) = 1/a^2 - 1 / (2 a tan(a/2)) (the inverse right Jacobian
    of SO(3)). b cancels catastrophically at small a, where calibration residuals live, so its
    series 1/12 + a^2/720 + a^4/30240 (error below 1e-18 for a < 1e-2) is used there.
    """
    small = angles < 1e-2
    safe = np.where(small, 1.0, angles)
    squared = angles**2
    b = np.where(
        small,
        1.0 / 12.0 + squared / 720.0 + squared**2 / 30240.0,
        1.0 / safe**2 - 1.0 / (2.0 * safe * np.tan(0.5 * safe)),
    )
    w = skew(logs)
    return np.eye(3) + 0.5 * w + b[:, None, None] * (w @ w)


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices [x] (..., 3, 3) of vectors (..., 3): [x] y = x cross y."""
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out = np.zeros(vectors.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -z, y, -x
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = z, -y, x
    return out
