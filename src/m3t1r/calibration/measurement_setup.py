"""Where measurements are taken: the measurement frame and the marker, apart from the machine.

A tracker or motion-capture system reports the pose (or the position) of a marker, a reflector
or a probe mounted on the platform (serial: on the tool), in its own frame:

    T_measured = frame . T_platform(q) . marker          (all SE3; T_platform in the robot base)

frame: the robot base in the measurement frame, p_measured = R p_base + t [m];
marker: the measured frame in the platform (tool) frame [m]; a single reflector gives its
position only, and the marker's orientation is then irrelevant.
points: several reflectors rigidly attached to the platform (tool), each measured by its position
alone: p_measured,k = frame . T_platform(q) . p_k, p_k [m] in the platform (tool) frame.

Both belong to the measurement setup, not to the machine: a calibration estimates them together
with the machine's geometry and reports them, and the calibrated URDF keeps the robot alone.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from m3t1r.errors import IdentificationError, InvalidInputError, require_finite_vector

__all__ = [
    "MeasurementSetup",
    "LENGTH_UNITS",
    "register_frame",
    "register_marker_rotation",
    "se3_from_report",
    "se3_to_report",
]

#: Length units a measurement file may use, in metres per unit (command-line lengths stay in m).
LENGTH_UNITS: Mapping[str, float] = {"m": 1.0, "mm": 1e-3}


def se3_to_report(placement: pin.SE3) -> dict[str, list[float]]:
    """{"translation": [x, y, z] (m), "quaternion": [qx, qy, qz, qw]} of a placement."""
    xyzquat = pin.SE3ToXYZQUAT(placement)
    return {"translation": [float(v) for v in xyzquat[:3]], "quaternion": [float(v) for v in xyzquat[3:]]}


def se3_from_report(entry: Mapping[str, object], what: str) -> pin.SE3:
    """The inverse of `se3_to_report`; raises InvalidInputError naming `what` on a malformed entry."""
    try:
        translation = np.asarray(entry["translation"], dtype=float).reshape(3)
        quaternion = np.asarray(entry["quaternion"], dtype=float).reshape(4)
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"{what}: expected translation [x, y, z] and quaternion [qx, qy, qz, qw] ({exc})"
        ) from None
    if not (np.all(np.isfinite(translation)) and np.all(np.isfinite(quaternion))):
        raise InvalidInputError(f"{what}: non-finite value")
    if abs(np.linalg.norm(quaternion) - 1.0) > 1e-6:
        raise InvalidInputError(f"{what}: quaternion norm {np.linalg.norm(quaternion):.6g} is not 1")
    return pin.XYZQUATToSE3(np.r_[translation, quaternion / np.linalg.norm(quaternion)])  # exactly orthonormal


@dataclass(frozen=True)
class MeasurementSetup:
    """The measurement frame and the marker (module docstring); identity for both by default,
    i.e. the platform frame itself measured in the robot's base frame. points: the offsets p_k (x, y,
    z) [m] in the platform (tool) frame of several measured points, when each row holds several
    (the marker is then unused); empty for one measured frame."""

    frame: pin.SE3 = field(default_factory=pin.SE3.Identity)
    marker: pin.SE3 = field(default_factory=pin.SE3.Identity)
    points: tuple[tuple[float, float, float], ...] = ()

    @staticmethod
    def from_numbers(frame_xyz_rpy: ArrayLike | None = None, marker_xyz: ArrayLike | None = None) -> MeasurementSetup:
        """The setup from command-line numbers: the frame as x, y, z [m], roll, pitch, yaw [rad]
        (Pinocchio's rpy, R = Rz(yaw) Ry(pitch) Rx(roll)), the marker as x, y, z [m] with the
        platform's orientation; identity where None."""
        frame = pin.SE3.Identity()
        if frame_xyz_rpy is not None:
            x, y, z, roll, pitch, yaw = require_finite_vector(
                frame_xyz_rpy, 6, "measurement frame x, y, z, roll, pitch, yaw"
            )
            frame = pin.SE3(pin.rpy.rpyToMatrix(roll, pitch, yaw), np.array([x, y, z]))
        marker = pin.SE3.Identity()
        if marker_xyz is not None:
            marker = pin.SE3(np.eye(3), require_finite_vector(marker_xyz, 3, "marker x, y, z"))
        return MeasurementSetup(frame, marker)

    def measured_poses(self, platform_poses: np.ndarray) -> np.ndarray:
        """frame . T_platform . marker for platform poses (N, 4, 4) in the base: (N, 4, 4)."""
        return self.frame.homogeneous @ np.asarray(platform_poses, dtype=float) @ self.marker.homogeneous

    def measured_points(self, platform_poses: np.ndarray) -> np.ndarray:
        """frame . T_platform . p_k for platform poses (N, 4, 4) in the base: (N, P, 3) [m]."""
        seen = self.frame.homogeneous @ np.asarray(platform_poses, dtype=float)
        offsets = np.array(self.points, dtype=float).reshape(-1, 3)
        return np.einsum("nij,pj->npi", seen[:, :3, :3], offsets) + seen[:, None, :3, 3]

    def to_report(self) -> dict[str, object]:
        """The report's entries for this setup (models/README.md): `measurement_frame` and `marker`
        as `se3_to_report` placements, and `points` ([x, y, z] in m, in the platform frame) when the
        setup has some; `from_report` reads them back."""
        report: dict[str, object] = {
            "measurement_frame": se3_to_report(self.frame),
            "marker": se3_to_report(self.marker),
        }
        if self.points:
            report["points"] = [list(map(float, p)) for p in self.points]
        return report

    @staticmethod
    def from_report(report: Mapping[str, object]) -> MeasurementSetup:
        """The setup a calibration report recorded (identity for a missing entry)."""

        def entry(key: str) -> pin.SE3:
            value = report.get(key)
            if value is None:
                return pin.SE3.Identity()
            if not isinstance(value, Mapping):
                raise InvalidInputError(f"report '{key}': expected an object")
            return se3_from_report(value, f"report '{key}'")

        return MeasurementSetup(entry("measurement_frame"), entry("marker"), _points_from_report(report))


def _points_from_report(report: Mapping[str, object]) -> tuple[tuple[float, float, float], ...]:
    """The `points` entry of a report (a list of [x, y, z] in m), () when absent."""
    value = report.get("points")
    if value is None:
        return ()
    try:
        points = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        points = np.zeros(0)
    if points.ndim != 2 or points.shape[1] != 3 or not len(points) or not np.all(np.isfinite(points)):
        raise InvalidInputError("report 'points': expected a list of [x, y, z] offsets (m)")
    return tuple((float(x), float(y), float(z)) for x, y, z in points)


def register_frame(model_poses: ArrayLike, measured_positions: ArrayLike) -> pin.SE3:
    """Closed-form rigid registration: the frame F minimising sum |F p_model - p_measured|^2.

    model_poses: (N, 4, 4) measured frames as the model predicts them in the robot base (their
    positions are used); measured_positions (N, 3) [m]. Any rotation is found (SVD of the
    cross-covariance, scipy's `Rotation.align_vectors`), and the translation follows from the
    centroids. Positions only, so that an unknown marker orientation cannot spoil it (see
    `register_marker_rotation`). Raises IdentificationError when the points are too few or collinear.
    """
    points = np.asarray(model_poses, dtype=float)[:, :3, 3]
    measured = np.asarray(measured_positions, dtype=float)
    centroid_model, centroid_measured = points.mean(axis=0), measured.mean(axis=0)
    a, b = measured - centroid_measured, points - centroid_model
    if len(points) < 3 or np.linalg.svd(b, compute_uv=False)[1] <= 1e-6 * max(np.abs(b).max(), 1e-300):
        raise IdentificationError("the measured positions are too few or collinear to place the measurement frame")
    rotation = Rotation.align_vectors(a, b)[0].as_matrix()
    return pin.SE3(rotation, centroid_measured - rotation @ centroid_model)


def register_marker_rotation(frame: pin.SE3, platform_poses: ArrayLike, measured_rotations: ArrayLike) -> np.ndarray:
    """Closed-form marker orientation R_M from R_measured,i = R_F R_P,i R_M: the rotation nearest
    (chordal mean, by SVD projection) to the per-pose estimates (R_F R_P,i)^T R_measured,i."""
    platform = np.asarray(platform_poses, dtype=float)[:, :3, :3]
    estimates = np.swapaxes(frame.rotation @ platform, 1, 2) @ np.asarray(measured_rotations, dtype=float)
    u, _, vt = np.linalg.svd(estimates.sum(axis=0))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
