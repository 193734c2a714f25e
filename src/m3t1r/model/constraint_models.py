"""A machine's loop closures as Pinocchio's own constraint models, for its constrained algorithms.

`rigid_constraint_models(mechanism)` gives one `pin.RigidConstraintModel` per closure: CONTACT_3D for
a 3D closure (the origins of frames a and b coincide), CONTACT_6D for a 6D one (the frames
coincide), between frame a's joint and placement (joint1) and frame b's (joint2), with errors in
frame a (`pin.LOCAL`): the closures' residuals (models/README.md). The list works with
`pin.initConstraintDynamics`, `pin.constraintDynamics` and `pin.getConstraintsJacobian` on the
mechanism's `model`, nominal or calibrated. Pinocchio's constraint Jacobian is the velocity of c1
relative to c2, minus the derivative of m3t1r's residual (same null space); it reads the frames
that each model's `calc` (or a constrained algorithm) has placed. Where rows depend on each other
(a planar loop's held rows), `constraintDynamics` needs `pin.ProximalSettings` with mu > 0.

A Pinocchio rigid constraint holds all 3 or 6 rows. A closure of which m3t1r enforces only some
(a planar loop's rows along its hinge axes) is handed over with its other rows held at their value
at a reference configuration (frame b's placement moved onto frame a there). That is exact where
those rows hold by themselves, as on a machine whose planar loops have parallel hinges. On a
machine whose errors tilt the hinges (a calibrated one), they do not: a rigid constraint would
lock motion the machine has (its joint play takes those rows up), so the call is refused unless
`left_out_rows="hold"` asks for it.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Literal

import numpy as np
import pinocchio as pin

from m3t1r.errors import InvalidInputError
from m3t1r.model.closures import CLOSURE_TYPES, ROW_COUNT, ClosureSpec, ClosureSystem, closure_rank

if TYPE_CHECKING:
    from m3t1r.model.description import Mechanism

__all__ = ["rigid_constraint_models", "rigid_constraint_datas", "constraint_residual", "rows_left_out_that_move"]


def rigid_constraint_models(
    mechanism: Mechanism, reference: np.ndarray | None = None, *, left_out_rows: Literal["refuse", "hold"] = "refuse"
) -> pin.StdVec_RigidConstraintModel:
    """The closures of `mechanism` as Pinocchio constraint models, each named as its closure.

    `reference`: an assembled configuration (nq) [m, rad] at which the rows m3t1r does not enforce
    are held (default: the home). The models belong to `mechanism.model`.

    Raises InvalidInputError naming the closures whose left-out rows do not hold by themselves on
    this machine (`rows_left_out_that_move`), unless `left_out_rows="hold"`.
    """
    model = mechanism.model
    q = mechanism.home if reference is None else np.asarray(reference, dtype=float)
    if left_out_rows != "hold":
        moving = rows_left_out_that_move(mechanism, q)
        if moving:
            raise InvalidInputError(
                f"{mechanism.closures_path}: closure(s) {', '.join(moving)}: the rows m3t1r leaves out do not hold by "
                "themselves on this machine (its errors make them independent of the enforced rows), so a rigid "
                "Pinocchio constraint would lock motion the machine has; left_out_rows='hold' hands them over "
                "held at the reference pose anyway"
            )
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    models = pin.StdVec_RigidConstraintModel()
    for spec in mechanism.closures:
        frame_a, frame_b = model.frames[spec.frame_a_id], model.frames[spec.frame_b_id]
        placement_b = frame_b.placement
        if len(spec.rows) < ROW_COUNT[spec.type]:
            placement_b = placement_b * data.oMf[spec.frame_a_id].actInv(data.oMf[spec.frame_b_id]).inverse()
        constraint = pin.RigidConstraintModel(
            CLOSURE_TYPES[spec.type].contact,
            model,
            frame_a.parentJoint,
            frame_a.placement,
            frame_b.parentJoint,
            placement_b,
            pin.ReferenceFrame.LOCAL,
        )
        constraint.name = spec.name
        models.append(constraint)
    return models


def rows_left_out_that_move(mechanism: Mechanism, q: np.ndarray) -> tuple[str, ...]:
    """Names of the closures whose rows m3t1r leaves out are independent of the enforced rows at q
    (all its rows raise the rank of the closure Jacobian over every joint): rows that vary as the
    machine moves, which a rigid constraint would hold."""
    model = mechanism.model
    enforced = _jacobian(ClosureSystem(model, mechanism.closures), q)
    rank = closure_rank(enforced)
    moving = []
    for spec in mechanism.closures:
        if len(spec.rows) == ROW_COUNT[spec.type]:
            continue
        whole: ClosureSpec = dataclasses.replace(spec, rows=tuple(range(ROW_COUNT[spec.type])))
        if closure_rank(np.vstack([enforced, _jacobian(ClosureSystem(model, (whole,)), q)])) > rank:
            moving.append(spec.name)
    return tuple(moving)


def _jacobian(system: ClosureSystem, q: np.ndarray) -> np.ndarray:
    jacobian = system.evaluate(q, True)[1]
    assert jacobian is not None  # asked for
    return jacobian


def rigid_constraint_datas(models: pin.StdVec_RigidConstraintModel) -> pin.StdVec_RigidConstraintData:
    """One `RigidConstraintData` per model, as Pinocchio's constrained algorithms take them."""
    datas = pin.StdVec_RigidConstraintData()
    for constraint in models:
        datas.append(constraint.createData())
    return datas


def constraint_residual(model: pin.Model, models: pin.StdVec_RigidConstraintModel, q: np.ndarray) -> np.ndarray:
    """Pinocchio's position error of every constraint at q, stacked [m, rad]: the translation of c1Mc2
    (CONTACT_3D) or log6(c1Mc2) as [v; w] (CONTACT_6D), with c1, c2 the constraint's two frames."""
    data = model.createData()
    pin.forwardKinematics(model, data, q)
    rows = []
    for constraint in models:
        oMc1 = data.oMi[constraint.joint1_id] * constraint.joint1_placement
        oMc2 = data.oMi[constraint.joint2_id] * constraint.joint2_placement
        c1Mc2 = oMc1.actInv(oMc2)
        rows.append(c1Mc2.translation if constraint.type == pin.ContactType.CONTACT_3D else pin.log6(c1Mc2).vector)
    return np.concatenate(rows) if rows else np.zeros(0)
