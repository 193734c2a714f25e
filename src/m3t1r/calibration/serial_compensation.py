"""Compensation of a serial robot's joint program with its calibration: geometry and compliance.

A controller that knows only the nominal model believes that joint commands q put the tool at
g_nominal(q) (tool frame in the chain's base frame). The robot as calibrated puts it at
g_calibrated(q + c tau(q)): its identified geometry, at the readings moved by the joints'
compliance under gravity (`calibrate --serial --compliance`; tau from the calibrated model's
inertias, as `validate` predicts). For each configuration q_nominal of a joint program, the
target is g_nominal(q_nominal) and the compensated command q_c is found in two steps:

1. the joint coordinates q_a with g_calibrated(q_a) = target: Gauss-Newton on the tool's Jacobian
   (base-frame axes, [v; w]), from q_nominal, so the arm keeps the program's configuration branch;
   a redundant chain takes the least-norm step (it stays nearest the program);
2. the command q_c with q_c + c tau(q_c) = q_a: the fixed point q_c <- q_a - c tau(q_c), which
   converges because the deflection c tau changes far less than the deflection itself.

With `position_only` (a calibration from a tracker without orientation) only the tool position
is matched. A joint whose command falls beyond its limit is held at the limit while the other
joints can still match the target (a redundant arm; TIAGo's torso at its stop). A row that does
not converge, or whose command stays beyond a joint limit, is a failure (index and reason), not
a command.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from m3t1r.calibration.serial import compliant_readings
from m3t1r.model.poe import SerialChain, tool_poses

__all__ = ["SerialCompensation", "compensate_serial"]

_TOLERANCE = 1e-12  # [m, rad] tool pose error at which a solve stops
_MAX_ITERATIONS = 30


@dataclass(frozen=True)
class SerialCompensation:
    """Compensated joint commands of a program: commands (N, n) [rad, m] (NaN on a failed row),
    residual (N,) the tool pose error left [m + rad], failures (row index, reason)."""

    commands: np.ndarray
    residual: np.ndarray
    failures: tuple[tuple[int, str], ...]


def _tool_jacobian(model: pin.Model, data: pin.Data, chain: SerialChain, q: np.ndarray) -> np.ndarray:
    """(6, n) [v; w] of the tool frame per chain coordinate, in the base frame's axes."""
    full = chain.model_configuration(model, q)
    jacobian = pin.computeFrameJacobian(model, data, full, chain.tool_frame_id, pin.LOCAL_WORLD_ALIGNED)
    columns = jacobian[:, [model.joints[j].idx_v for j in chain.joint_ids]]
    if chain.base_frame_id is None:
        return columns
    # computeFrameJacobian placed the joints (data.oMi) at `full` but not the frames: place the base's.
    base = pin.updateFramePlacement(model, data, chain.base_frame_id).rotation  # its axes in the world's
    return np.vstack((base.T @ columns[:3], base.T @ columns[3:]))


def _pose_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """[p_target - p; log3(R_target R^T)] (6,), in the base frame's axes."""
    rotation = pin.log3(target[:3, :3] @ current[:3, :3].T)
    return np.concatenate((target[:3, 3] - current[:3, 3], rotation))


def _reach(
    model: pin.Model, chain: SerialChain, target: np.ndarray, start: np.ndarray, rows: slice, free: np.ndarray
) -> tuple[np.ndarray, float]:
    """q with the tool of `model` at `target` (4, 4) in the compared `rows` of the error, from `start`,
    moving the `free` joints (n,) only."""
    data = model.createData()
    q = start.copy()
    error = _pose_error(target, tool_poses(chain, model, q)[0])[rows]
    for _ in range(_MAX_ITERATIONS):
        if np.linalg.norm(error) < _TOLERANCE:
            break
        jacobian = _tool_jacobian(model, data, chain, q)[rows][:, free]
        q[free] += np.linalg.lstsq(jacobian, error, rcond=None)[0]
        error = _pose_error(target, tool_poses(chain, model, q)[0])[rows]
    return q, float(np.linalg.norm(error))


def _command(
    calibrated: pin.Model, chain: SerialChain, actual: np.ndarray, compliance: Mapping[str, float]
) -> np.ndarray:
    """q_c with q_c + c tau(q_c) = actual (module docstring, step 2)."""
    command = actual.copy()
    for _ in range(_MAX_ITERATIONS):
        deflection = compliant_readings(calibrated, chain, command, compliance)[0] - command
        updated = actual - deflection
        if np.max(np.abs(updated - command)) < _TOLERANCE:
            return updated
        command = updated
    return command


def _compensate_one(
    calibrated: pin.Model,
    chain: SerialChain,
    target: np.ndarray,
    start: np.ndarray,
    compliance: Mapping[str, float],
    rows: slice,
    limits: tuple[np.ndarray, np.ndarray],
    tolerance: float,
) -> tuple[np.ndarray, float, str]:
    """(command, residual, failure reason or "") of one configuration. A joint whose command falls
    beyond its limit is held at that limit and the others solve again, while the chain has joints
    to spare (a redundant arm, or a torso at its stop)."""
    lower, upper = limits
    free = np.ones(chain.n_joints, dtype=bool)
    start = start.copy()
    nan = np.full(chain.n_joints, np.nan)
    while True:
        actual, residual = _reach(calibrated, chain, target, start, rows, free)
        if not residual <= tolerance:
            return (
                nan,
                residual,
                (
                    "the calibrated robot does not reach the nominal tool pose near this "
                    f"configuration (error {residual:.3g} left)"
                ),
            )
        command = _command(calibrated, chain, actual, compliance)
        bounded = lower < upper
        # A held joint's command moves only with its deflection (micro-radians): clipped, not held again.
        beyond = np.flatnonzero(free & bounded & ((command < lower - _TOLERANCE) | (command > upper + _TOLERANCE)))
        if not beyond.size:
            return np.clip(command, np.where(bounded, lower, -np.inf), np.where(bounded, upper, np.inf)), residual, ""
        if np.count_nonzero(free) - beyond.size < rows.stop - rows.start:
            k = int(beyond[0])
            return (
                nan,
                residual,
                (
                    f"the compensated command puts joint '{chain.joint_names[k]}' at {command[k]:.6g}, "
                    f"beyond its limit [{lower[k]:.6g}, {upper[k]:.6g}]"
                ),
            )
        free[beyond] = False
        start = actual.copy()  # held where its command is at the limit: the deflection stays as it was
        start[beyond] = np.clip(command[beyond], lower[beyond], upper[beyond]) + actual[beyond] - command[beyond]


def compensate_serial(
    nominal: pin.Model,
    calibrated: pin.Model,
    chain: SerialChain,
    program: np.ndarray,
    compliance: Mapping[str, float],
    position_only: bool = False,
    tolerance: float = 1e-9,
) -> SerialCompensation:
    """The commands that put the calibrated robot's tool where the nominal one puts it at each
    configuration of `program` (N, n) [rad, m] (module docstring). compliance: {joint: c}
    [rad/Nm, m/N]; a row whose tool pose error stays above `tolerance` [m + rad] fails as unreachable."""
    program = np.atleast_2d(np.asarray(program, dtype=float))
    targets = tool_poses(chain, nominal, program)
    rows = slice(0, 3) if position_only else slice(0, 6)
    lower, upper = chain.position_limits(calibrated)
    commands = np.full(program.shape, np.nan)
    residual = np.full(len(program), np.nan)
    failures: list[tuple[int, str]] = []
    for i, (target, start) in enumerate(zip(targets, program)):
        commands[i], residual[i], reason = _compensate_one(
            calibrated, chain, target, start, compliance, rows, (lower, upper), tolerance
        )
        if reason:
            failures.append((i, reason))
    return SerialCompensation(commands, residual, tuple(failures))
