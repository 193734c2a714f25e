"""What is measured on the closed-loop machine: tracker noise, pose measurements, and simulated ones.

The tracker sees a frame on the platform in its own frame (`MeasurementSetup`); the slider
encoders read the actuators. `measure` simulates both on a known machine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.errors import InvalidInputError, real_array
from m3t1r.model.batch_kinematics import ForwardBatch
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver

__all__ = ["TrackerNoise", "PoseMeasurements", "measure", "assembled_from_home"]


@dataclass(frozen=True)
class TrackerNoise:
    """Standard deviations of the measurements: tracker position [m] and orientation [rad],
    slider readings [m]. Used to whiten the residual and to predict the parameter covariance."""

    position: float = 10e-6
    rotation: float = 20e-6
    actuator: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("position", "rotation", "actuator"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"noise {name} must be a finite non-negative number, got {value}")
        if self.position <= 0 or self.rotation <= 0:
            raise InvalidInputError("tracker noise must be positive (it whitens the residual)")


@dataclass(frozen=True)
class PoseMeasurements:
    """N calibration poses: slider readings (N x n_act) [m] and measured platform poses in the base
    frame (orientation ignored when position_only). points: (N, P, 3) [m] positions of P points rigidly
    attached to the platform, NaN where a point was not seen (position-only; `poses` then holds one
    seen point per row, for the data checks), or None: one measured frame per row."""

    actuators: np.ndarray
    poses: tuple[pin.SE3, ...]
    position_only: bool = False
    points: np.ndarray | None = None

    def __post_init__(self) -> None:
        actuators = real_array(self.actuators, "actuator readings")
        if actuators.ndim != 2 or actuators.shape[0] != len(self.poses):
            raise InvalidInputError(f"{actuators.shape} actuator rows for {len(self.poses)} poses")
        if not np.all(np.isfinite(actuators)):
            raise InvalidInputError("non-finite actuator reading")
        object.__setattr__(self, "actuators", actuators)
        if self.points is not None:
            points = np.asarray(self.points, dtype=float)
            if points.ndim != 3 or points.shape[0] != len(self.poses) or points.shape[2] != 3 or not self.position_only:
                raise InvalidInputError(
                    f"measured points: expected position-only (N, P, 3) points for "
                    f"{len(self.poses)} poses, got shape {points.shape}"
                )
            seen = np.isfinite(points)
            if np.any(np.any(seen, axis=2) != np.all(seen, axis=2)) or not np.all(np.any(seen[:, :, 0], axis=1)):
                raise InvalidInputError("measured points: a point with some coordinates missing, or a row seeing none")
            object.__setattr__(self, "points", points)

    @property
    def n_points(self) -> int:
        """P points per row, 0 for one measured frame per row."""
        return 0 if self.points is None else int(self.points.shape[1])

    @property
    def rows_per_pose(self) -> int:
        """Residual rows per pose: 6, 3 (position only) or 3 P (P points; a point not seen gives zeros)."""
        if self.points is not None:
            return 3 * self.n_points
        return 3 if self.position_only else 6

    def subset(self, keep: np.ndarray) -> PoseMeasurements:
        """The poses at the indices `keep`, in that order."""
        return PoseMeasurements(
            self.actuators[keep],
            tuple(self.poses[i] for i in keep),
            self.position_only,
            None if self.points is None else self.points[keep],
        )

    def __len__(self) -> int:
        return len(self.poses)


@on_one_blas_thread
def measure(
    machine: Mechanism,
    actuators: np.ndarray,
    rng: np.random.Generator | None = None,
    noise: TrackerNoise | None = None,
    position_only: bool = False,
    setup: MeasurementSetup | None = None,
) -> PoseMeasurements:
    """What a tracker sees on `machine` driven at `actuators`, and what the slider encoders read.

    The tracker sees setup.frame . T_platform . setup.marker (default: the platform frame in the
    base frame). With `noise`, the recorded poses get Gaussian position [m] and rotation
    (right-multiplied, [rad]) noise and the recorded slider readings Gaussian noise; without,
    both are exact.
    """
    platform = assembled_from_home(machine, actuators).poses
    seen = (setup or MeasurementSetup()).measured_poses(platform)
    poses = [pin.SE3(pose) for pose in seen]
    readings = np.array(actuators, dtype=float)
    if noise is not None:
        if rng is None:
            raise InvalidInputError("measure: noise needs a random generator")
        poses = [
            pin.SE3(
                p.rotation @ pin.exp3(rng.normal(0.0, noise.rotation, 3)),
                p.translation + rng.normal(0.0, noise.position, 3),
            )
            for p in poses
        ]
        readings = readings + rng.normal(0.0, noise.actuator, readings.shape)
    return PoseMeasurements(readings, tuple(poses), position_only)


def assembled_from_home(machine: Mechanism, actuators: np.ndarray) -> ForwardBatch:
    """Forward kinematics of every slider set (n, k) on `machine`, each from home, in one vectorised
    solve (`ClosedLoopSolver.forward_batch`); InvalidInputError naming the first set that does not
    assemble. From home, not warm-started: a start carried from one unrelated set to the next can
    cross a singularity onto another branch (a five-bar's elbows)."""
    values = np.asarray(actuators, dtype=float)
    if len(values) == 0:
        empty = np.zeros(0)
        return ForwardBatch(
            0,
            empty.astype(int),
            np.zeros((0, 4, 4)),
            np.zeros((0, machine.model.nq)),
            empty,
            empty.astype(int),
            (),
            np.zeros((0, 4, 4)),
        )
    solved = ClosedLoopSolver(machine).forward_batch(values.reshape(len(values), -1))
    if solved.failures:
        first = solved.failures[0]
        raise InvalidInputError(
            f"slider set {first.index} ({values[first.index]}) does not assemble on the machine "
            f"from its home: {first.reason}"
        )
    return solved
