"""Workspace sampling: actuator sets drawn in the mechanism's declared workspace (closures file)."""

from __future__ import annotations

import numpy as np

from m3t1r._threads import on_one_blas_thread
from m3t1r.errors import InvalidInputError, ModelFileError
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.task import WorkspaceSpec

__all__ = ["workspace_actuators", "declared_workspace"]


def declared_workspace(mechanism: Mechanism) -> WorkspaceSpec:
    """The mechanism's workspace; without one (schema 1 files), the actuators' URDF limits as a box.

    Raises InvalidInputError when there is neither a workspace nor finite actuator limits.
    """
    if mechanism.workspace is not None:
        return mechanism.workspace
    lower, upper = mechanism.joint_limits()
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower < upper)):
        raise InvalidInputError(f"{mechanism.closures_path}: no workspace declared and the actuators have no finite "
                                "limits to sample between; add a `workspace:` box (models/README.md)")
    return WorkspaceSpec(actuators=tuple((name, float(lo), float(hi)) for name, lo, hi in
                                         zip(mechanism.actuated_joints, lower, upper)))


@on_one_blas_thread
def workspace_actuators(nominal: Mechanism, n: int, rng: np.random.Generator) -> np.ndarray:
    """n actuator sets (n x k) [m or rad] drawn uniformly in the declared workspace, each assembled
    from home (so every one is on the home branch).

    A task box is drawn in task coordinates and mapped by inverse kinematics; an actuator box is
    drawn directly and checked by forward kinematics. Raises ModelFileError (naming the closures
    file and a draw) when the machine cannot reach a draw: the declared box is wrong for it.
    """
    workspace = declared_workspace(nominal)
    if n == 0:
        return np.zeros((0, len(nominal.actuated_joints)))
    solver = ClosedLoopSolver(nominal)
    if workspace.kind == "task":
        batch = solver.inverse_batch(workspace.task_poses(nominal.task, rng, n))
        actuators = batch.actuators
    else:
        lo, hi = workspace.bounds(nominal.actuated_joints)
        actuators = lo + (hi - lo) * rng.random((n, len(lo)))
        batch = solver.forward_batch(actuators)
    if batch.failures:
        first = batch.failures[0]
        where = (f"declared {workspace.kind} workspace box" if nominal.workspace is not None else
                 "actuators' URDF limits (no workspace declared: add a `workspace:` box, models/README.md)")
        raise ModelFileError(nominal.closures_path, f"{len(batch.failures)} of {n} draws in the {where} cannot be "
                                                    f"assembled from home; first, draw {first.index}: {first.reason}")
    return np.array(actuators).reshape(n, len(nominal.actuated_joints))
