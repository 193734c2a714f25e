"""Batched closed-loop kinematics (`ClosedLoopSolver.forward_batch` / `inverse_batch`) against the single solves."""

import closed_form
import numpy as np
import pinocchio as pin
import pytest
from conftest import perturb_every_origin

from m3t1r.errors import InvalidInputError, OutOfWorkspaceError, UnsupportedJointError
from m3t1r.model.batch_kinematics import StackedTree, rpy_batch
from m3t1r.model.design import NOMINAL
from m3t1r.model.kinematics import ClosedLoopSolver


def workspace_poses(n: int, seed: int) -> np.ndarray:
    return NOMINAL.workspace.sample(np.random.default_rng(seed), n)


def test_stacked_tree_matches_pinocchio_placements_and_world_jacobian(mechanism):
    model, data = mechanism.model, mechanism.model.createData()
    tree = StackedTree(model)
    q = mechanism.home + np.random.default_rng(0).normal(0, 0.5, (6, model.nq))
    rot, pos = tree.joints(q)
    world = tree.world_jacobian(rot, pos)
    for i in range(len(q)):
        pin.computeJointJacobians(model, data, q[i])
        for j in range(1, model.njoints):
            np.testing.assert_allclose(rot[j, :, :, i], data.oMi[j].rotation, atol=1e-14)
            np.testing.assert_allclose(pos[j, :, i], data.oMi[j].translation, atol=1e-14)
        np.testing.assert_allclose(world[i], data.J, atol=1e-14)


def test_rpy_batch_matches_pinocchio():
    rng = np.random.default_rng(2)
    rpy = rng.uniform(-1.2, 1.2, (20, 3))
    rotations = np.array([pin.rpy.rpyToMatrix(*r) for r in rpy])
    np.testing.assert_allclose(rpy_batch(rotations), rpy, atol=1e-13)


@pytest.mark.parametrize("seed", [None, 0])
def test_forward_batch_agrees_with_forward(mechanism, seed):
    machine = mechanism if seed is None else mechanism.with_model(
        perturb_every_origin(mechanism.model, np.random.default_rng(seed), 1e-3, 1e-3))
    solver = ClosedLoopSolver(machine)
    sliders = np.array([closed_form.inverse(p) for p in workspace_poses(40, 3)])
    batch = solver.forward_batch(sliders)
    assert batch.complete and batch.ok.all() and batch.poses.shape == (40, 4, 4)
    for k, values in enumerate(sliders):
        fk = solver.forward(values, q_init=machine.home)
        # Both stop at closure rows <= 1e-12; on a perturbed machine that leaves about 1e-12 m each.
        assert np.linalg.norm(batch.poses[k, :3, 3] - fk.pose.translation) <= (1e-12 if seed is None else 3e-12)
        np.testing.assert_allclose(batch.poses[k, :3, :3], fk.pose.rotation, atol=1e-11)
        assert batch.residuals[k] <= 1e-12
    with pytest.raises(ValueError):
        batch.poses[0, 0, 0] = 1.0  # results are read-only


def test_inverse_batch_agrees_with_inverse_and_closed_form(solver, mechanism):
    targets = workspace_poses(40, 4)
    batch = solver.inverse_batch(targets)
    assert batch.complete
    np.testing.assert_allclose(batch.actuators, [closed_form.inverse(t) for t in targets], atol=1e-10)
    for k, target in enumerate(targets[:10]):
        ik = solver.inverse(target, q_init=mechanism.home)
        np.testing.assert_allclose(batch.actuators[k], ik.actuators, atol=1e-11)
        np.testing.assert_allclose(batch.tilt[k], ik.tilt, atol=1e-11)
    np.testing.assert_allclose(batch.poses[:, :3, 3], targets[:, :3], atol=1e-11)


def test_failed_rows_are_reported_and_excluded(solver):
    sliders = np.array([closed_form.inverse(p) for p in workspace_poses(5, 5)])
    sliders[1] = [-0.3, 0.3, 0.0, 0.0]  # the five-bar cannot close
    sliders[3, 1] = 0.7  # beyond the slider limit
    batch = solver.forward_batch(sliders)
    assert list(batch.indices) == [0, 2, 4] and len(batch.poses) == 3
    assert [(f.index, f.error) for f in batch.failures] == [(1, OutOfWorkspaceError), (3, InvalidInputError)]
    assert "q11_B2" in batch.failures[1].reason and "residual" in batch.failures[0].reason
    assert list(batch.ok) == [True, False, True, False, True]
    targets = workspace_poses(3, 6)
    targets[1] = [0.5, 1.2, -0.1, 0.0]  # needs q11 beyond its limit
    ik = solver.inverse_batch(targets)
    assert list(ik.indices) == [0, 2] and ik.failures[0].error is OutOfWorkspaceError
    assert "beyond its limit" in ik.failures[0].reason


def test_bad_batch_input_raises_naming_the_row(solver):
    with pytest.raises(InvalidInputError, match="row 2"):
        solver.forward_batch(np.array([[0.0] * 4, [0.0] * 4, [0.0, np.nan, 0.0, 0.0]]))
    with pytest.raises(InvalidInputError, match="shape"):
        solver.inverse_batch(np.zeros((3, 3)))


def test_unsupported_joint_is_a_typed_error():
    model = pin.Model()
    model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    with pytest.raises(UnsupportedJointError, match="Spherical"):
        StackedTree(model)


def test_compensate_batch_agrees_with_the_path_compensation(mechanism):
    from m3t1r.compensation import Compensator
    calibrated = mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(7), 1e-3, 1e-3))
    from m3t1r.model.kinematics import rehomed
    calibrated = rehomed(calibrated)
    targets = workspace_poses(30, 8)
    targets[4] = [0.5, 1.2, -0.1, 0.0]  # unreachable: reported, excluded
    path = Compensator(mechanism, calibrated).compensate(targets)
    batch = Compensator(mechanism, calibrated).compensate_batch(targets)
    assert list(batch.indices) == list(path.indices) and [f.index for f in batch.failures] == [4]
    assert batch.failures[0].error is OutOfWorkspaceError
    np.testing.assert_allclose(batch.actuators, path.actuators, atol=1e-11)
    np.testing.assert_allclose(batch.command_targets, path.command_targets, atol=1e-11)
    np.testing.assert_allclose(batch.tilt, path.tilt, atol=1e-11)


@pytest.mark.parametrize("kind", ["m_machine", "five_bar", "spherical_wrist"])
def test_stacked_closures_match_the_single_evaluation(kind, tmp_path):
    """Residual and exact Jacobian of every enforced row (3D points and the 6D weld, far from assembly
    so that the rotation terms of Jlog6 matter) equal `ClosedLoopSolver._evaluate`'s, pose by pose."""
    from m3t1r.model.description import Mechanism, nominal_model_paths
    from m3t1r.model.examples import five_bar_files, spherical_wrist_files

    files = {"m_machine": nominal_model_paths, "five_bar": lambda: five_bar_files(tmp_path),
             "spherical_wrist": lambda: spherical_wrist_files(tmp_path)}[kind]()
    solver = ClosedLoopSolver(Mechanism.load(*files))
    kin = solver._batch_kinematics()
    q = solver.mechanism.home + np.random.default_rng(4).normal(0, 0.4, (7, solver.model.nq))
    residual, jac, frot, fpos, world = kin.closures(q)
    assert residual.shape == (7, solver.n_rows) and jac.shape == (7, solver.n_rows, solver.model.nv)
    for i in range(len(q)):
        expected, expected_jac, _ = solver._evaluate(q[i], with_jacobian=True)
        np.testing.assert_allclose(residual[i], expected, atol=1e-13)
        np.testing.assert_allclose(jac[i], expected_jac, atol=1e-12)
        np.testing.assert_allclose(world[i], solver.data.J, atol=1e-13)
        platform = solver.data.oMf[solver.mechanism.platform_frame_id]
        np.testing.assert_allclose(frot[i, kin.platform_index], platform.rotation, atol=1e-13)
        np.testing.assert_allclose(fpos[i, kin.platform_index], platform.translation, atol=1e-13)
    np.testing.assert_array_equal(kin.closures(q, with_jacobian=False)[0], residual)
