"""Workspace sampling: slider sets that reach poses drawn in the design's workspace box."""

from __future__ import annotations

import numpy as np

from m3t1r._threads import on_one_blas_thread
from m3t1r.model.description import Mechanism
from m3t1r.model.design import NOMINAL
from m3t1r.model.kinematics import ClosedLoopSolver

__all__ = ["workspace_actuators"]


@on_one_blas_thread
def workspace_actuators(nominal: Mechanism, n: int, rng: np.random.Generator) -> np.ndarray:
    """n slider sets (n x 4) [m]: platform poses drawn uniformly in the design's workspace box,
    through the nominal model's IK (each from home, so every pose is on the home branch)."""
    solver = ClosedLoopSolver(nominal)
    rows = []
    for pose in NOMINAL.workspace.sample(rng, n):
        rows.append(solver.inverse(pose, q_init=nominal.home).actuators)
    return np.array(rows)
