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
_UNSETTLED = (
    "the commands under the compliance's deflection do not converge here (q_c = q_a - c tau(q_c): a "
    "compliance this large moves the deflection as much as the deflection itself)"
)


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
) -> np.ndarray | None:
    """q_c with q_c + c tau(q_c) = actual (module docstring, step 2), or None when the fixed point does
    not converge in _MAX_ITERATIONS (a compliance so large that the deflection changes as much as itself)."""
    command = actual.copy()
    for _ in range(_MAX_ITERATIONS):
        deflection = compliant_readings(calibrated, chain, command, compliance)[0] - command
        updated = actual - deflection
        if np.max(np.abs(updated - command)) < _TOLERANCE:
            return updated
        command = updated
    return None


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
    beyond its limit is held with its command at that limit and the others solve again, while the
    chain has joints to spare (a redundant arm, or a torso at its stop). A held joint's reading is its
    limit plus its deflection, which moves as the other joints do: the solve is repeated from the
    readings it leads to until the held commands are at their limits (within _TOLERANCE)."""
    lower, upper = limits
    bounded = lower < upper
    free = np.ones(chain.n_joints, dtype=bool)
    held_at = np.full(chain.n_joints, np.nan)  # the limit each held joint's command is held at
    start = start.copy()
    nan = np.full(chain.n_joints, np.nan)
    for _ in range(_MAX_ITERATIONS):
        actual, residual = _reach(calibrated, chain, target, start, rows, free)
        if not residual <= tolerance:
            return nan, residual, _unreachable(residual)
        command = _command(calibrated, chain, actual, compliance)
        if command is None:
            return nan, residual, _UNSETTLED
        # A held joint is settled once its command is at its limit; a free one is beyond past _TOLERANCE.
        beyond = np.flatnonzero(free & bounded & ((command < lower - _TOLERANCE) | (command > upper + _TOLERANCE)))
        drift = np.abs(command[~free] - held_at[~free])
        if not beyond.size and not np.any(drift > _TOLERANCE):
            command = np.clip(command, np.where(bounded, lower, -np.inf), np.where(bounded, upper, np.inf))
            command[~free] = held_at[~free]  # within _TOLERANCE of it
            return command, residual, ""
        if np.count_nonzero(free) - beyond.size < rows.stop - rows.start:
            return nan, residual, _beyond_limit(chain, int(beyond[0]), command, limits)
        free[beyond] = False
        held_at[beyond] = np.clip(command[beyond], lower[beyond], upper[beyond])
        start = actual.copy()  # held joints read their limit plus their deflection at the current command
        start[~free] = held_at[~free] + actual[~free] - command[~free]
    return nan, residual, "the held joints' deflections do not settle (their commands keep leaving the limits)"


def _unreachable(residual: float) -> str:
    return (
        f"the calibrated robot does not reach the nominal tool pose near this configuration (error {residual:.3g} left)"
    )


def _beyond_limit(chain: SerialChain, k: int, command: np.ndarray, limits: tuple[np.ndarray, np.ndarray]) -> str:
    lower, upper = limits
    return (
        f"the compensated command puts joint '{chain.joint_names[k]}' at {command[k]:.6g}, "
        f"beyond its limit [{lower[k]:.6g}, {upper[k]:.6g}]"
    )


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
