"""Plausibility screening of a measurement file before a calibration, naming the row and the cause.

A calibration accepts any numbers its reader accepts and fits them as well as it can: a file
with two pose columns swapped, or in millimetres, still "converges", to a meaningless machine.
Manufacturing errors move the platform by millimetres to centimetres, so a measured pose far
from the nominal model's pose at the same slider readings is a data error, not geometry. This
module finds those rows and, when a whole file is off, tests the usual causes (swapped position
columns, millimetres) so the error message can name them.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .description import Mechanism
from .errors import DataFileError, KinematicsError, InvalidInputError

__all__ = ["POSITION_TOLERANCE", "ROTATION_TOLERANCE", "Implausible", "implausible_rows", "screen_measurements"]

POSITION_TOLERANCE = 0.1
"""m. A measured platform position farther than this from the nominal model's is not a geometric error."""
ROTATION_TOLERANCE = 1.0
"""rad. Likewise for the orientation."""

_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Implausible:
    """One implausible row: its index, file line, and how far it is from the nominal model."""

    index: int
    line: int
    position: float
    rotation: float | None


def _nominal_poses(nominal: Mechanism, actuators: np.ndarray) -> list[pin.SE3 | None]:
    from .kinematics import ClosedLoopSolver

    solver = ClosedLoopSolver(nominal)
    poses: list[pin.SE3 | None] = []
    for sliders in actuators:
        try:
            poses.append(solver.forward(sliders).pose)
        except (KinematicsError, InvalidInputError):
            solver.reset()
            poses.append(None)  # does not assemble nominally: not judged here
    return poses


def implausible_rows(nominal: Mechanism, data, position_tolerance: float = POSITION_TOLERANCE,
                     rotation_tolerance: float = ROTATION_TOLERANCE) -> list[Implausible]:
    """Rows of a `MeasurementFile` whose measured pose is implausibly far from the nominal model's."""
    measurements = data.measurements
    found = []
    for index, (pose, measured) in enumerate(zip(_nominal_poses(nominal, measurements.actuators), measurements.poses)):
        if pose is None:
            continue
        position = float(np.linalg.norm(measured.translation - pose.translation))
        rotation = None if measurements.position_only else float(
            np.linalg.norm(pin.log3(pose.rotation.T @ measured.rotation)))
        if position > position_tolerance or (rotation is not None and rotation > rotation_tolerance):
            found.append(Implausible(index, int(data.lines[index]), position, rotation))
    return found


def screen_measurements(nominal: Mechanism, data, position_tolerance: float = POSITION_TOLERANCE,
                        rotation_tolerance: float = ROTATION_TOLERANCE, max_listed: int = 5) -> None:
    """Raise DataFileError if a row's measured pose is implausible for this machine, naming lines and cause.

    Every row is compared with the nominal model's platform pose at its slider readings. If rows
    are off, the usual file-wide causes are tried in turn: two position columns swapped (x, y, z
    permuted) and millimetres instead of metres; the message names the one that makes every row
    plausible, or lists the first offending lines otherwise.
    """
    bad = implausible_rows(nominal, data, position_tolerance, rotation_tolerance)
    if not bad:
        return
    path = data.path
    measurements = data.measurements
    positions = np.array([p.translation for p in measurements.poses])
    nominal_positions = [p for p in _nominal_poses(nominal, measurements.actuators)]
    judged = [k for k, p in enumerate(nominal_positions) if p is not None]
    reference = np.array([nominal_positions[k].translation for k in judged])

    def fits(candidate: np.ndarray) -> bool:
        return bool(np.all(np.linalg.norm(candidate[judged] - reference, axis=1) <= position_tolerance))

    cause = None
    for order in itertools.permutations(range(3)):
        if order != (0, 1, 2) and fits(positions[:, order]):
            moved = [(_AXES[k], _AXES[order[k]]) for k in range(3) if order[k] != k]
            cause = ("columns " + " and ".join(sorted({f"'{a}'" for a, _ in moved}))
                     + " look swapped: with them exchanged every row fits the machine")
            break
    if cause is None and fits(positions / 1000.0):
        cause = "positions look like millimetres: the file must be in metres (SI units)"
    first = bad[0]
    listed = "; ".join(
        f"line {b.line}: {b.position:.3g} m" + ("" if b.rotation is None else f", {b.rotation:.3g} rad")
        for b in bad[:max_listed])
    more = f" (and {len(bad) - max_listed} more)" if len(bad) > max_listed else ""
    message = (f"{len(bad)} of {len(measurements.actuators)} measured poses are implausibly far from the machine's "
               f"pose at their slider readings (more than {position_tolerance:g} m or {rotation_tolerance:g} rad, "
               f"far beyond manufacturing errors): {listed}{more}")
    if cause:
        message += f". Cause: {cause}"
    raise DataFileError(path, message, row=first.line)
