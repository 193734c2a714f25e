"""What a closures file may leave out, derived from the mechanism itself: the task and its sensitivity.

A first-time user's file (schema 1) names the actuators, the loops and a platform frame, and nothing
about what the machine is for. The default task is the set of the platform frame's base-frame
coordinates that the actuators command at home: the first candidate, in the order below, whose
actuator-to-task Jacobian has full rank there. Position comes before rotation, since a frame's
position is what people measure and command:

1. position and yaw (x, y, z, theta: the schema 1 task), when there are four actuators;
2. position axes only, the best-conditioned choice of as many axes as actuators;
3. position axes and yaw; 4. position axes and the full rotation.

The default workspace (`m3t1r.model.workspace`) is judged by the same Jacobian's conditioning.
"""

from __future__ import annotations

import itertools
from typing import Literal

import numpy as np
import pinocchio as pin

from m3t1r.model.closures import ClosureSystem
from m3t1r.model.task import POSITION_AXES, TaskSpec

__all__ = ["SCHEMA_1_TASK_ROTATION", "actuator_task_jacobian", "default_task", "task_entry", "task_words"]

SCHEMA_1_TASK_ROTATION: Literal["none", "yaw", "full"] = (
    "yaw"  # with all three position axes: the M machine's task, schema 1's default
)
FULL_RANK = 1e-6  # smallest/largest singular value of the actuator-to-task Jacobian for a task to be taken


def actuator_task_jacobian(
    system: ClosureSystem, q: np.ndarray, actuated: np.ndarray, passive: np.ndarray, task: TaskSpec
) -> np.ndarray | None:
    """d(task rows)/d(actuators) at an assembled q (task.dimension x actuators) [m or rad per m or rad],
    the passive joints (velocity indices `passive`; the locked ones left out) following the closures:
    J_t,act - J_t,pas J_c,pas^-1 J_c,act. None where the passive closure block is singular (the
    actuators do not fix the passive joints there)."""
    _, closure = system.evaluate(q, True)
    model = system.model
    passive_block = closure[:, passive]
    singular = np.linalg.svd(passive_block, compute_uv=False) if passive_block.size else np.ones(1)
    if len(singular) and not singular[-1] > 1e-12 * singular[0]:
        return None
    frame = model.getFrameId(task.frame)
    placement = pin.updateFramePlacement(model, system.data, frame)
    frame_jac = pin.getFrameJacobian(model, system.data, frame, pin.LOCAL_WORLD_ALIGNED)
    rows = task.jacobian(placement, frame_jac, placement.rotation if task.rotation == "full" else None)
    if not passive_block.size:
        return rows[:, actuated]
    follow = -np.linalg.solve(passive_block, closure[:, actuated])
    return rows[:, actuated] + rows[:, passive] @ follow


def _candidates(frame: str, count: int) -> list[list[TaskSpec]]:
    """Candidate tasks of `count` rows in preference groups (module docstring's order)."""
    groups: list[list[TaskSpec]] = []
    if count == 4:
        groups.append([TaskSpec(frame, POSITION_AXES, SCHEMA_1_TASK_ROTATION)])
    for rotation, rows in (("none", 0), ("yaw", 1), ("full", 3)):
        size = count - rows
        if 0 <= size <= 3 and count > 0:
            groups.append(
                [
                    TaskSpec(frame, axes, rotation)  # type: ignore[arg-type]
                    for axes in itertools.combinations(POSITION_AXES, size)
                ]
            )
    return groups


def _conditioning(jacobian: np.ndarray | None) -> float:
    if jacobian is None or not np.all(np.isfinite(jacobian)):
        return 0.0
    singular = np.linalg.svd(jacobian, compute_uv=False)
    return float(singular[-1] / singular[0]) if singular[0] > 0.0 else 0.0


def default_task(
    system: ClosureSystem, home: np.ndarray, actuated: np.ndarray, passive: np.ndarray, platform_frame: str
) -> TaskSpec | None:
    """The task of the platform frame that the actuators (velocity indices `actuated`) command at an
    assembled home (module docstring), or None when no candidate has full rank there (or the
    passive joints are not fixed at home)."""
    for group in _candidates(platform_frame, len(actuated)):
        scored = [
            (_conditioning(actuator_task_jacobian(system, home, actuated, passive, task)), k, task)
            for k, task in enumerate(group)
        ]
        best, _, task = max(scored, key=lambda item: (item[0], -item[1]))
        if best > FULL_RANK:
            return task
    return None


def task_entry(task: TaskSpec) -> dict:
    """The closures file's `task:` mapping of a task (what `save` records when the task was derived)."""
    return {"frame": task.frame, "position": list(task.position), "rotation": task.rotation}


def task_words(task: TaskSpec) -> str:
    """A task in words, e.g. "y, z of frame 'effector'" (for notes and messages)."""
    return f"{', '.join(task.columns)} of frame '{task.frame}'"
