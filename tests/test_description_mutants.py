"""Description tests that kill mutants the behaviour tests let through (docs/mutation.md).

The home-closure check must look at every enforced row (a bad home that breaks only the last one
is caught), at no unenforced row, and at HOME_TOLERANCE exactly.
"""

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.model.description import HOME_TOLERANCE, Mechanism, _settled


def _with_closure_frame_moved(mechanism: Mechanism, closure: str, row: int, amount: float) -> Mechanism:
    """frame_b of `closure` moved so that only component `row` of its residual changes, by `amount`
    (3D: R_a^T (p_b - p_a); 6D: log6(aMb), rows 3-5 a rotation about frame_a's axes)."""
    spec = next(c for c in mechanism.closures if c.name == closure)
    model = mechanism.model.copy()
    data = model.createData()
    pin.framesForwardKinematics(model, data, mechanism.home)
    oMa, oMb = data.oMf[spec.frame_a_id], data.oMf[spec.frame_b_id]
    frame = model.frames[spec.frame_b_id]
    axis = np.zeros(3)
    axis[row % 3] = amount
    if row < 3:  # translate b along frame_a's axis `row`, in b's parent-joint coordinates
        parent = data.oMi[frame.parentJoint]
        shift = parent.rotation.T @ (oMa.rotation @ axis)
        frame.placement = pin.SE3(frame.placement.rotation, frame.placement.translation + shift)
    else:  # rotate b about frame_a's axis, i.e. about R_b^T R_a axis in b's own frame
        frame.placement = frame.placement * pin.SE3(pin.exp3(oMb.rotation.T @ oMa.rotation @ axis), np.zeros(3))
    model.frames[spec.frame_b_id] = frame
    return replace(mechanism, model=model)


@pytest.mark.parametrize("closure, rows", [("upper_parallelogram_I", (1, 2)), ("lower_parallelogram_II", (0, 2)),
                                           ("platform", (0, 1, 2, 5))])
def test_home_check_sees_every_enforced_row_alone(mechanism, closure, rows):
    spec = next(c for c in mechanism.closures if c.name == closure)
    assert spec.rows == rows
    for row in rows:
        broken = _with_closure_frame_moved(mechanism, closure, row, 1e-6)
        notes = _settled(broken).notes
        assert len(notes) == 1 and notes[0].startswith(f"home does not close: closure '{closure}' residual 1.000e-06")
        assert "assembled by Newton" in notes[0]


@pytest.mark.parametrize("closure, row", [("upper_parallelogram_I", 0), ("lower_parallelogram_II", 1),
                                          ("platform", 3), ("platform", 4)])
def test_home_check_ignores_unenforced_rows(mechanism, closure, row):
    assert _settled(_with_closure_frame_moved(mechanism, closure, row, 1e-3)).notes == ()


@pytest.mark.parametrize("amount, refused", [(1e-8, True), (2e-9, True), (5e-10, False)])
def test_home_tolerance_boundary(mechanism, amount, refused):
    assert HOME_TOLERANCE == 1e-9  # the documented value; the amounts straddle it
    moved = _with_closure_frame_moved(mechanism, "five_bar_I", 2, amount)
    notes = _settled(moved).notes
    assert (len(notes) == 1 and notes[0].startswith("home does not close")) == refused
