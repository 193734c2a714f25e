"""What a closed-loop solver knows about its mechanism before any solve, built once and frozen.

Single solves (`ClosedLoopSolver`), the batches (`batch_kinematics`) and the compiled loop's build
read one `SolverLayout`: joint columns, frames, slider limits and branch blocks, so that a batch row
and a single solve are the same problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from m3t1r.errors import InvalidInputError
from m3t1r.model.branches import Blocks, branch_blocks

if TYPE_CHECKING:
    from m3t1r.model.closures import ClosureSystem
    from m3t1r.model.description import Mechanism

__all__ = ["SolverLayout", "solver_layout"]


@dataclass(frozen=True, eq=False)
class SolverLayout:
    """The fixed bookkeeping of one mechanism's closure solves (read-only arrays).

    passive, actuated: velocity indices of FK's unknowns and of the sliders; unknowns: IK's columns,
    every joint but the locked ones (None when that is every joint: a copy per step saved);
    n_rows: enforced closure rows (= len(passive)); actuator_lower, actuator_upper: slider limits [m]
    in `actuated_joints` order; platform_frame, task_frame: frame ids; blocks: the diagonal blocks
    (closure rows, passive columns) of the passive closure Jacobian, whose determinant signs label
    the assembly branch (`branches`).
    """

    passive: np.ndarray
    actuated: np.ndarray
    unknowns: np.ndarray | None
    n_rows: int
    actuator_lower: np.ndarray
    actuator_upper: np.ndarray
    platform_frame: int
    task_frame: int
    blocks: Blocks

    @property
    def unknown_columns(self) -> np.ndarray | slice:
        """IK's columns as an index: `unknowns`, or every column."""
        return slice(None) if self.unknowns is None else self.unknowns

    @property
    def finite_limits(self) -> bool:
        """Whether every slider has finite limits on both sides."""
        return bool(np.all(np.isfinite(self.actuator_lower)) and np.all(np.isfinite(self.actuator_upper)))


def _read_only(array: np.ndarray) -> np.ndarray:
    array = np.array(array)
    array.setflags(write=False)
    return array


def solver_layout(mechanism: Mechanism, system: ClosureSystem) -> SolverLayout:
    """The layout of `mechanism`'s closure solves, its closure rows being `system`'s.

    Raises InvalidInputError when FK is not square (one enforced row per passive joint).
    """
    passive = mechanism.passive_ids
    if system.n_rows != len(passive):
        raise InvalidInputError(
            f"{mechanism.closures_path}: {system.n_rows} enforced closure rows for "
            f"{len(passive)} passive joints; "
            "forward kinematics needs a square system (one row per passive joint)"
        )
    locked = np.zeros(mechanism.model.nv, dtype=bool)
    locked[mechanism.locked_ids] = True
    lower, upper = mechanism.joint_limits()
    return SolverLayout(
        passive=_read_only(passive),
        actuated=_read_only(mechanism.actuated_ids),
        unknowns=_read_only(np.flatnonzero(~locked)) if locked.any() else None,
        n_rows=system.n_rows,
        actuator_lower=_read_only(lower),
        actuator_upper=_read_only(upper),
        platform_frame=mechanism.platform_frame_id,
        task_frame=mechanism.model.getFrameId(mechanism.task.frame),
        blocks=branch_blocks(mechanism, system),
    )
