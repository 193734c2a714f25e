"""What a closed-loop solver knows before any solve (`m3t1r.model.solver_layout`): joint columns,
frames, slider limits and branch blocks, read-only; a closure system that is not square is refused."""

import warnings
from dataclasses import replace

import numpy as np
import pytest
from model_files import welded_double_hinge

from m3t1r.errors import InvalidInputError
from m3t1r.model import branches
from m3t1r.model.branches import branch_blocks
from m3t1r.model.closures import ClosureSystem, without_rows
from m3t1r.model.description import Mechanism
from m3t1r.model.solver_layout import solver_layout

# ---------------------------------------------------------------------------------------------------
# The layout of a mechanism's solves


def test_the_m_machine_s_layout_is_its_joints_limits_frames_and_blocks(mechanism):
    system = ClosureSystem(mechanism.model, mechanism.closures)
    layout = solver_layout(mechanism, system)
    assert layout.passive.tolist() == mechanism.passive_ids.tolist() and len(layout.passive) == 16
    assert layout.actuated.tolist() == mechanism.actuated_ids.tolist() and len(layout.actuated) == 4
    assert layout.n_rows == 16 and layout.unknowns is None and layout.unknown_columns == slice(None)
    lower, upper = mechanism.joint_limits()
    assert layout.actuator_lower.tolist() == lower.tolist() and layout.actuator_upper.tolist() == upper.tolist()
    assert layout.finite_limits
    assert layout.platform_frame == mechanism.platform_frame_id
    assert layout.task_frame == mechanism.model.getFrameId(mechanism.task.frame) == layout.platform_frame
    assert [(r.tolist(), c.tolist()) for r, c in layout.blocks] == [
        (r.tolist(), c.tolist()) for r, c in branch_blocks(mechanism, system)
    ]


def test_a_tool_task_frame_is_its_own_frame(tool_machine):
    layout = solver_layout(tool_machine, ClosureSystem(tool_machine.model, tool_machine.closures))
    assert layout.task_frame == tool_machine.model.getFrameId("tool") != layout.platform_frame


def test_the_layout_s_arrays_are_read_only_copies(mechanism):
    layout = solver_layout(mechanism, ClosureSystem(mechanism.model, mechanism.closures))
    for array in (layout.passive, layout.actuated, layout.actuator_lower, layout.actuator_upper):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0
    assert not np.shares_memory(layout.passive, mechanism.passive_ids)


def test_locked_joints_are_left_out_of_the_inverse_s_columns(tmp_path):

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hinge = Mechanism.load(*welded_double_hinge(tmp_path))
    layout = solver_layout(hinge, ClosureSystem(hinge.model, hinge.closures))
    free = [i for i in range(hinge.model.nv) if i not in hinge.locked_ids.tolist()]
    assert len(free) == hinge.model.nv - 1
    assert layout.unknowns.tolist() == free and layout.unknown_columns.tolist() == free
    with pytest.raises(ValueError, match="read-only"):
        layout.unknowns[0] = 0


def test_an_infinite_stroke_end_is_not_a_finite_limit(mechanism):
    model = mechanism.model.copy()
    upper = model.upperPositionLimit.copy()
    upper[model.idx_qs[model.getJointId(mechanism.actuated_joints[0])]] = np.inf
    model.upperPositionLimit = upper
    open_ended = replace(mechanism, model=model)
    layout = solver_layout(open_ended, ClosureSystem(model, open_ended.closures))
    assert layout.actuator_upper[0] == np.inf and not layout.finite_limits


def test_a_closure_system_that_is_not_square_is_refused_word_for_word(mechanism):
    short = replace(mechanism, closures=without_rows(mechanism.closures, (0,)))
    with pytest.raises(InvalidInputError) as caught:
        solver_layout(short, ClosureSystem(short.model, short.closures))
    assert str(caught.value) == (
        f"{mechanism.closures_path}: 15 enforced closure rows for 16 passive joints; forward kinematics needs a "
        "square system (one row per passive joint)"
    )


def test_the_first_layout_of_a_topology_reads_its_blocks_from_the_system_given(mechanism, monkeypatch):
    """Blocks are cached per topology; with the cache emptied (as for the first machine of a topology
    in a process) the layout takes the pattern from `system`'s closure Jacobian: the M machine's 16
    passive joints fall in blocks that cover each row and each passive joint once."""
    monkeypatch.setattr(branches, "_BLOCK_CACHE", {})
    layout = solver_layout(mechanism, ClosureSystem(mechanism.model, mechanism.closures))
    rows = sorted(r for block, _ in layout.blocks for r in block.tolist())
    columns = sorted(c for _, block in layout.blocks for c in block.tolist())
    assert rows == list(range(16)) and columns == sorted(mechanism.passive_ids.tolist())
