"""A machine's closures as Pinocchio constraint models (m3t1r.model.constraint_models): at m3t1r's
assembled poses Pinocchio's constraints close and have m3t1r's null space, and Pinocchio's
constrained dynamics on a calibrated machine is the dynamics of m3t1r's closures."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import perturb_every_origin
from mjcf_mechanisms import five_bar_mjcf, spatial_loop_mjcf

from m3t1r.calibration.closed_loop import calibrate_closed_loop
from m3t1r.calibration.simulation import PlacementErrorScale, simulate_study
from m3t1r.errors import InvalidInputError, ModelWarning
from m3t1r.model.closures import ClosureSystem, closure_rank
from m3t1r.model.constraint_models import (
    constraint_residual,
    rigid_constraint_datas,
    rigid_constraint_models,
    rows_left_out_that_move,
)
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import workspace_actuators

SPATIAL_SIDECAR = "platform_frame: platform\ntask: {position: [x]}\nworkspace: {actuators: {j1: [-0.3, 0.3]}}\n"


def _load(*paths) -> Mechanism:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        return Mechanism.load(*paths)


def _spatial_loop(folder: Path) -> Mechanism:
    (folder / "spatial_loop.closures.yaml").write_text(SPATIAL_SIDECAR)
    return _load(spatial_loop_mjcf(folder))


MECHANISMS = {
    "m_machine": lambda folder: _load(),
    "five_bar_urdf": lambda folder: _load(*five_bar_files(folder)),
    "spherical_wrist_urdf": lambda folder: _load(*spherical_wrist_files(folder)),
    "five_bar_mjcf": lambda folder: _load(five_bar_mjcf(folder)),
    "spatial_loop_mjcf": _spatial_loop,
}


def _null_projector(matrix: np.ndarray) -> np.ndarray:
    basis = np.linalg.svd(matrix)[2][closure_rank(matrix) :].T
    return basis @ basis.T


def _pinocchio_jacobian(mechanism: Mechanism, models, q: np.ndarray) -> np.ndarray:
    data, datas = mechanism.model.createData(), rigid_constraint_datas(models)
    pin.computeJointJacobians(mechanism.model, data, q)
    for constraint, constraint_data in zip(models, datas):
        constraint.calc(mechanism.model, data, constraint_data)
    return pin.getConstraintsJacobian(mechanism.model, data, models, datas)


def _assembled_poses(mechanism: Mechanism, count: int) -> list[np.ndarray]:
    solver = ClosedLoopSolver(mechanism)
    actuators = workspace_actuators(mechanism, count, np.random.default_rng(7))
    return [solver.forward(row).q for row in actuators]


@pytest.mark.parametrize("kind", MECHANISMS)
def test_pinocchios_constraints_close_at_our_poses_with_our_null_space(kind, tmp_path):
    mechanism = MECHANISMS[kind](tmp_path)
    models = rigid_constraint_models(mechanism)
    assert [c.name for c in models] == [c.name for c in mechanism.closures]
    assert [c.type for c in models] == [
        pin.ContactType.CONTACT_3D if c.type == "3D" else pin.ContactType.CONTACT_6D for c in mechanism.closures
    ]
    system = ClosureSystem(mechanism.model, mechanism.closures)
    for q in _assembled_poses(mechanism, 8):
        assert np.abs(constraint_residual(mechanism.model, models, q)).max() < 1e-9
        ours = system.evaluate(q, True)[1]
        theirs = _pinocchio_jacobian(mechanism, models, q)
        # Same motions allowed: the null spaces' projectors agree (to the rounding of an SVD).
        assert np.abs(_null_projector(ours) - _null_projector(theirs)).max() < 1e-8


def _reduced_dynamics(
    mechanism: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint accelerations under m3t1r's enforced closure rows (KKT system), with those rows'
    Jacobian J and drift dJ/dt v (central difference along v): the reference for Pinocchio's."""
    model, data = mechanism.model, mechanism.model.createData()
    system = ClosureSystem(model, mechanism.closures)
    mass = pin.crba(model, data, q)
    mass = np.triu(mass) + np.triu(mass, 1).T
    bias = pin.rnea(model, data, q, v, np.zeros(model.nv))
    step = 1e-6
    ahead, behind = (system.evaluate(pin.integrate(model, q, s * v), True)[1] for s in (step, -step))
    drift = (ahead - behind) @ v / (2 * step)
    jacobian = system.evaluate(q, True)[1]
    rows = jacobian.shape[0]
    kkt = np.block([[mass, jacobian.T], [jacobian, np.zeros((rows, rows))]])
    solution = np.linalg.solve(kkt, np.concatenate([tau - bias, -drift]))
    return solution[: model.nv], jacobian, drift


def test_constraint_dynamics_on_a_calibrated_machine_keeps_its_loop_closed(tmp_path):
    nominal = _spatial_loop(tmp_path)
    study = simulate_study(nominal, n_poses=30, n_holdout=5, seed=2, errors=PlacementErrorScale(1e-4, 1e-4))
    calibrated = calibrate_closed_loop(nominal, study.measurements).mechanism
    model = calibrated.model
    models = rigid_constraint_models(calibrated)
    datas = rigid_constraint_datas(models)
    data = model.createData()
    pin.initConstraintDynamics(model, data, models, datas)
    rng = np.random.default_rng(3)
    for q in _assembled_poses(calibrated, 4):
        system = ClosureSystem(model, calibrated.closures)
        null = np.linalg.svd(system.evaluate(q, True)[1])[2][-1]  # mobility 1: the loop's one motion
        v, tau = 2.0 * null, rng.normal(scale=0.05, size=model.nv)
        acceleration = pin.constraintDynamics(model, data, q, v, tau, models, datas)
        expected, jacobian, drift = _reduced_dynamics(calibrated, q, v, tau)
        # The closure's acceleration is zero (its rows' second derivative along the motion; the drift's
        # central difference carries ~1e-10 of rounding) ...
        assert np.abs(jacobian @ acceleration + drift).max() < 1e-8 * (1 + np.abs(drift).max())
        # ... and the accelerations are those of m3t1r's closures (measured 2e-11 relative).
        assert np.abs(acceleration - expected).max() < 1e-8 * np.abs(expected).max()


def test_rows_a_calibrated_planar_loop_leaves_out_are_held_only_on_request(tmp_path):
    nominal = _load(five_bar_mjcf(tmp_path))
    study = simulate_study(nominal, n_poses=30, n_holdout=5, seed=5, errors=PlacementErrorScale(1e-4, 1e-4))
    with pytest.raises(InvalidInputError, match=r"closure\(s\) tip: the rows m3t1r leaves out do not hold"):
        rigid_constraint_models(study.truth)
    held = rigid_constraint_models(study.truth, left_out_rows="hold")
    assert np.abs(constraint_residual(study.truth.model, held, study.truth.home)).max() < 1e-9
    # The nominal planar loop's left-out row holds by itself: handed over without asking.
    assert len(rigid_constraint_models(nominal)) == 1


# ---------------------------------------------------------------------------------------------------
# Closures enforced whole, the reference pose, and the refusal word for word


def _whole(mechanism: Mechanism) -> Mechanism:
    """`mechanism` with every row of every closure enforced."""
    closures = tuple(dataclasses.replace(c, rows=tuple(range(6 if c.type == "6D" else 3))) for c in mechanism.closures)
    return dataclasses.replace(mechanism, closures=closures)


def test_a_closure_enforced_whole_is_handed_over_as_it_is_whatever_the_reference(tmp_path):
    """The spherical wrist's two 6D closures with all six rows: Pinocchio's error at any configuration,
    assembled or not, is m3t1r's residual [v; w], and a reference (here one that is not assembled) moves
    nothing."""
    whole = _whole(_load(*spherical_wrist_files(tmp_path)))
    q = whole.home + np.random.default_rng(1).normal(0.0, 0.1, whole.model.nq)
    ours = ClosureSystem(whole.model, whole.closures).evaluate(q, False)[0]
    assert np.abs(ours[[3, 4, 5, 9, 10, 11]]).min() > 1e-3  # the rotation rows are far from closed
    for reference in (None, q.tolist()):
        models = rigid_constraint_models(whole, reference)
        np.testing.assert_allclose(constraint_residual(whole.model, models, q), ours, atol=1e-12, rtol=0)


def test_left_out_rows_are_held_at_the_reference_pose_given(tmp_path):
    """On a calibrated five-bar the held row moves with the machine: held at another assembled pose
    (given as a list), the constraints close there and not at home."""
    nominal = _load(five_bar_mjcf(tmp_path))
    truth = simulate_study(nominal, n_poses=30, n_holdout=5, seed=5, errors=PlacementErrorScale(1e-4, 1e-4)).truth
    pose = _assembled_poses(truth, 3)[-1]
    held = rigid_constraint_models(truth, pose.tolist(), left_out_rows="hold")
    assert np.abs(constraint_residual(truth.model, held, pose)).max() < 1e-9
    assert np.abs(constraint_residual(truth.model, held, truth.home)).max() > 1e-7


def test_no_constraints_have_an_empty_residual():
    mechanism = _load()
    residual = constraint_residual(mechanism.model, pin.StdVec_RigidConstraintModel(), mechanism.home)
    assert residual.shape == (0,)


def test_every_closure_whose_left_out_rows_move_is_named_in_the_refusal():
    """An M machine with errors on every joint and frame placement: all seven closures' left-out rows
    move; a closure enforced whole is never among them, and the closures after it are still checked."""
    mechanism = _load()
    erred = dataclasses.replace(
        mechanism, model=perturb_every_origin(mechanism.model, np.random.default_rng(3), 1e-4, 1e-4)
    )
    names = [c.name for c in mechanism.closures]
    assert rows_left_out_that_move(erred, erred.home) == tuple(names)
    with pytest.raises(InvalidInputError) as caught:
        rigid_constraint_models(erred)
    assert str(caught.value) == (
        f"{mechanism.closures_path}: closure(s) {', '.join(names)}: the rows m3t1r leaves out do not hold by "
        "themselves on this machine (its errors make them independent of the enforced rows), so a rigid "
        "Pinocchio constraint would lock motion the machine has; left_out_rows='hold' hands them over "
        "held at the reference pose anyway"
    )
    first_whole = dataclasses.replace(erred, closures=(_whole(erred).closures[0], *erred.closures[1:]))
    assert rows_left_out_that_move(first_whole, erred.home) == tuple(names[1:])
