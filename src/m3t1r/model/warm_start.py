"""Where a solver's next solve continues from: its last solution and what that solve left for the
predictors, in one small object (`ClosedLoopSolver.warm`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

__all__ = ["WarmStart"]


@dataclass(slots=True)
class WarmStart:
    """The warm start of one solver, replaced field by field as solves succeed.

    q: the last solution (nq) [m, rad]. FK: tangent, d q_passive / d sliders at the last factorisation
    (None: no first-order predictor); branch, the labels at the last solution (None: taken at the next
    start); previous, (sliders, passive q) of the solution before q (the second-order predictor's
    history; with the compiled loop the two concatenated, in its `history` buffer). IK: task_inverse,
    the task-row columns of the inverse of the last IK system; inverse_previous, ((goal, goal
    rotation), q) of the IK solution before q; goal, (goal, goal rotation) of q when it is an IK
    solution; inverse_branch, the labels at the last IK solution; task, the task frame there (with
    the compiled loop its 4 x 4 buffer [m]).
    """

    q: np.ndarray
    tangent: np.ndarray | None = None
    branch: bytes | None = None
    previous: tuple[np.ndarray, np.ndarray] | np.ndarray | None = None
    task_inverse: np.ndarray | None = None
    inverse_previous: tuple | None = None
    goal: tuple | None = None
    inverse_branch: bytes | None = None
    task: pin.SE3 | np.ndarray | None = None
