"""Batched closed-loop kinematics (`ClosedLoopSolver.forward_batch` / `inverse_batch`) against the single solves."""

import dataclasses
import re
import warnings

import closed_form
import numpy as np
import pinocchio as pin
import pytest
from conftest import perturb_every_origin

from m3t1r.errors import (
    BranchChangeError,
    InvalidInputError,
    NotConvergedError,
    OutOfWorkspaceError,
    SingularConfigurationError,
    UnsupportedJointError,
)
from m3t1r.model import batch_kinematics as bk
from m3t1r.model.batch_kinematics import StackedTree, rpy_batch
from m3t1r.model.description import Mechanism
from m3t1r.model.design import NOMINAL
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.newton_rules import NewtonRules
from m3t1r.model.task import TaskSpec


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
    machine = (
        mechanism
        if seed is None
        else mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(seed), 1e-3, 1e-3))
    )
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
    so that the rotation terms of Jlog6 matter) equal `ClosedLoopSolver.closure_sensitivity`'s, pose by pose."""
    from m3t1r.model.description import Mechanism, nominal_model_paths
    from m3t1r.model.examples import five_bar_files, spherical_wrist_files

    files = {
        "m_machine": nominal_model_paths,
        "five_bar": lambda: five_bar_files(tmp_path),
        "spherical_wrist": lambda: spherical_wrist_files(tmp_path),
    }[kind]()
    solver = ClosedLoopSolver(Mechanism.load(*files))
    kin = bk.StackedKinematics(solver)
    q = solver.mechanism.home + np.random.default_rng(4).normal(0, 0.4, (7, solver.model.nq))
    residual, jac, frot, fpos, world = kin.closures(q)
    assert residual.shape == (7, solver.n_rows) and jac.shape == (7, solver.n_rows, solver.model.nv)
    for i in range(len(q)):
        expected, expected_jac, _ = solver.closure_sensitivity(q[i])
        np.testing.assert_allclose(residual[i], expected, atol=1e-13)
        np.testing.assert_allclose(jac[i], expected_jac, atol=1e-12)
        np.testing.assert_allclose(world[i], solver.data.J, atol=1e-13)
        platform = solver.data.oMf[solver.mechanism.platform_frame_id]
        np.testing.assert_allclose(frot[i, kin.platform_index], platform.rotation, atol=1e-13)
        np.testing.assert_allclose(fpos[i, kin.platform_index], platform.translation, atol=1e-13)
    np.testing.assert_array_equal(kin.closures(q, with_jacobian=False)[0], residual)


# ==================================================================================================
# The stacked tree, batched closures and batched Newton, exactly
#
# Exact agreement of the stacked tree, frames, closure rows and Jacobians with Pinocchio and the single-pose
# solver, the chord / Newton switching of `newton_batch` (on small synthetic systems whose every call is
# recorded), the typed failure rows with their reason text, and the input checks.
# ==================================================================================================


ASSEMBLE = (
    "the closures cannot be assembled here (target out of the workspace or too far from the "
    "initial configuration's branch)"
)


@pytest.fixture(scope="module")
def five_bar(tmp_path_factory) -> Mechanism:
    return Mechanism.load(*five_bar_files(tmp_path_factory.mktemp("five_bar")))


@pytest.fixture(scope="module")
def wrist(tmp_path_factory) -> Mechanism:
    return Mechanism.load(*spherical_wrist_files(tmp_path_factory.mktemp("wrist")))


# ---------------------------------------------------------------------------------------------
# Small batched helpers


def test_rpy_batch_keeps_leading_axes_and_matches_pinocchio():
    rng = np.random.default_rng(10)
    rotations = np.array([pin.rpy.rpyToMatrix(*r) for r in rng.uniform(-1.4, 1.4, (6, 3))]).reshape(2, 3, 3, 3)
    rpy = bk.rpy_batch(rotations)
    assert rpy.shape == (2, 3, 3)
    for index in np.ndindex(2, 3):
        np.testing.assert_allclose(rpy[index], pin.rpy.matrixToRpy(rotations[index]), atol=1e-14)


def _b_series(a):
    """b(a) = 1/a^2 - 1/(2 a tan(a/2)) from five terms of x cot x (x = a/2)."""
    return 1 / 12 + a**2 / 720 + a**4 / 30240 + a**6 / 1209600 + a**8 / 47900160


def _db_over_a_series(a):
    return 1 / 360 + a**2 / 7560 + a**4 / 201600 + a**6 / 5987520


def _b_closed(a):
    return 1 / a**2 - (1 + np.cos(a)) / (2 * a * np.sin(a))


def test_jlog3_t_series_and_closed_form_values():
    small = np.array([0.0, 1e-4, 3e-3, 0.0099])
    b, db_over_a = bk.jlog3_coefficients(small)
    np.testing.assert_allclose(b, _b_series(small), rtol=1e-15, atol=0)
    np.testing.assert_allclose(db_over_a, _db_over_a_series(small), rtol=1e-10, atol=0)
    large = np.array([0.3, 0.7, 1.3, 2.1, 2.9])
    b, db_over_a = bk.jlog3_coefficients(large)
    np.testing.assert_allclose(b, _b_closed(large), rtol=1e-13)
    h = 1e-30  # complex step: the derivative to rounding, no cancellation
    db = np.imag(_b_closed(large + 1j * h)) / h
    np.testing.assert_allclose(db_over_a, db / large, rtol=1e-9)  # the closed form cancels to ~2e-11 at 0.3
    # Just above the switch the closed form is used: close to the series (its cancellation ~1e-6).
    b, db_over_a = bk.jlog3_coefficients(np.array([0.0101, 0.02]))
    np.testing.assert_allclose(b, _b_series(np.array([0.0101, 0.02])), rtol=1e-8)
    np.testing.assert_allclose(db_over_a, _db_over_a_series(np.array([0.0101, 0.02])), rtol=1e-4)


def test_jlog3_t_series_at_zero_rotation_is_quiet():
    """At a = 0 the closed form (discarded there) is evaluated at a = 1, not 0: no division by zero."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b, db_over_a = bk.jlog3_coefficients(np.zeros(3))
        identity = (np.eye(3)[..., None], np.zeros((3, 1)))
        bk.weld_rows(*identity, *identity)
    np.testing.assert_array_equal(b, 1 / 12)
    np.testing.assert_array_equal(db_over_a, 1 / 360)


@pytest.mark.parametrize(
    "angles, tolerance",
    [
        ((1e-6, 1e-6, 1e-2, 1e-2), 1e-9),  # pin.Jlog6's shorter small-angle series is about 1e-10 off there
        ((0.05, 0.4, 1.1, 2.0, 2.9), 1e-12),
    ],
)
def test_weld_rows_match_pinocchio_from_small_angles_to_near_pi(angles, tolerance):
    """With frame a at the base origin, weld_rows is log6(oMb) and Jlog6(oMb) Ad(oMb^-1): both
    branches of the Jlog3 series against Pinocchio."""
    rng = np.random.default_rng(11)
    unit = lambda u: u / np.linalg.norm(u)
    omb = [pin.exp6(np.r_[rng.normal(0, 0.5, 3), unit(rng.normal(size=3)) * a]) for a in angles]
    n = len(omb)
    residual, a, b = bk.weld_rows(
        np.repeat(np.eye(3)[..., None], n, axis=2),
        np.zeros((3, n)),
        np.moveaxis(np.array([m.rotation for m in omb]), 0, -1),
        np.moveaxis(np.array([m.translation for m in omb]), 0, -1),
    )
    assert residual.shape == (6, n) and a.shape == b.shape == (3, 3, n)
    for i, m in enumerate(omb):
        np.testing.assert_allclose(residual[:, i], pin.log6(m).vector, atol=1e-13)
        jlog6 = np.block([[a[:, :, i], b[:, :, i]], [np.zeros((3, 3)), a[:, :, i]]]) @ m.toActionMatrix()
        np.testing.assert_allclose(jlog6, pin.Jlog6(m), atol=tolerance)


def test_poses_last_products_and_cross_products():
    rng = np.random.default_rng(12)
    a, b, v, w = (
        rng.normal(size=(2, 3, 3, 4)),
        rng.normal(size=(2, 3, 3, 4)),
        rng.normal(size=(2, 3, 4)),
        rng.normal(size=(2, 3, 4)),
    )
    first = lambda x: np.moveaxis(x, -1, 1)  # noqa: E731  (2, n, ...) poses first
    np.testing.assert_allclose(first(bk.times_last(a, b)), first(a) @ first(b), atol=1e-14)
    np.testing.assert_allclose(first(bk.apply_last(a, v)), np.einsum("knij,knj->kni", first(a), first(v)), atol=1e-14)
    np.testing.assert_allclose(
        first(bk.apply_transposed_last(a, v)), np.einsum("knji,knj->kni", first(a), first(v)), atol=1e-14
    )
    np.testing.assert_allclose(first(bk.cross_last(v, w)), np.cross(first(v), first(w)), atol=1e-14)
    one = v[0, :, :1]  # (3, 1): one vector against n, either side
    np.testing.assert_allclose(bk.cross_last(one, w[0]), np.cross(one.T, w[0].T).T, atol=1e-14)
    np.testing.assert_allclose(bk.cross_last(w[0], one), np.cross(w[0].T, one.T).T, atol=1e-14)
    skew = bk.skew_last(v[0])
    assert skew.shape == (3, 3, 4)
    np.testing.assert_allclose(np.einsum("ijn,jn->in", skew, w[0]), np.cross(v[0].T, w[0].T).T, atol=1e-14)


def test_weld_rows_match_log6_and_the_world_operator():
    """weld_rows: log6(aMb) and Jlog6(aMb) Ad(oMb^-1) = [[A, B], [0, A]] on WORLD twists, pose by pose."""
    rng = np.random.default_rng(13)
    oma = [pin.exp6(rng.normal(0, 0.8, 6)) for _ in range(4)]
    omb = [pin.exp6(rng.normal(0, 0.8, 6)) for _ in range(4)]
    last = lambda ms, f: np.moveaxis(np.array([f(m) for m in ms]), 0, -1)  # noqa: E731
    residual, a, b = bk.weld_rows(
        last(oma, lambda m: m.rotation),
        last(oma, lambda m: m.translation),
        last(omb, lambda m: m.rotation),
        last(omb, lambda m: m.translation),
    )
    for i in range(4):
        amb = oma[i].actInv(omb[i])
        np.testing.assert_allclose(residual[:, i], pin.log6(amb).vector, atol=1e-13)
        operator = pin.Jlog6(amb) @ omb[i].inverse().toActionMatrix()
        np.testing.assert_allclose(a[:, :, i], operator[:3, :3], atol=1e-12)
        np.testing.assert_allclose(b[:, :, i], operator[:3, 3:], atol=1e-12)
        np.testing.assert_allclose(operator[3:, 3:], a[:, :, i], atol=1e-12)
        np.testing.assert_allclose(operator[3:, :3], 0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# The stacked tree


def _every_joint_type_model() -> pin.Model:
    """A branching tree with every supported joint type (unit unaligned axes: Pinocchio takes them as
    given), random placements."""
    rng = np.random.default_rng(14)
    model = pin.Model()
    place = lambda: pin.exp6(rng.normal(0, 0.6, 6))  # noqa: E731
    joints = [
        pin.JointModelRX(),
        pin.JointModelPY(),
        pin.JointModelRY(),
        pin.JointModelPZ(),
        pin.JointModelRZ(),
        pin.JointModelPX(),
        pin.JointModelRevoluteUnaligned(np.array([0.3, -1.2, 0.5]) / 1.3341664064126333),
        pin.JointModelPrismaticUnaligned(np.array([-0.4, 0.1, 2.0]) / 2.0420577856662137),
    ]
    parents = [0, 1, 1, 0, 4, 2, 6, 3]  # joint k + 1's parent: two roots, branches, levels out of order
    for k, (joint, parent) in enumerate(zip(joints, parents)):
        joint_id = model.addJoint(parent, joint, place(), f"j{k + 1}")
        model.appendBodyToJoint(joint_id, pin.Inertia.Random(), pin.SE3.Identity())
    return model


def test_stacked_tree_handles_every_supported_joint_type():
    model = _every_joint_type_model()
    data = model.createData()
    tree = bk.StackedTree(model)
    assert list(tree.revolute) == [True, False, True, False, True, False, True, False]
    q = np.random.default_rng(15).normal(0, 0.8, (5, model.nq))
    rot, pos = tree.joints(q)
    world = tree.world_jacobian(rot, pos)
    assert rot.shape == (9, 3, 3, 5) and pos.shape == (9, 3, 5) and world.shape == (5, 6, 8)
    for i in range(len(q)):
        pin.computeJointJacobians(model, data, q[i])
        for j in range(model.njoints):
            np.testing.assert_allclose(rot[j, :, :, i], data.oMi[j].rotation, atol=1e-13)
            np.testing.assert_allclose(pos[j, :, i], data.oMi[j].translation, atol=1e-13)
        np.testing.assert_allclose(world[i], data.J, atol=1e-13)


def test_unsupported_joint_error_names_the_joint_word_for_word():
    model = pin.Model()
    model.addJoint(0, pin.JointModelRX(), pin.SE3.Identity(), "hinge")
    model.addJoint(1, pin.JointModelRUBZ(), pin.SE3.Identity(), "wheel")
    with pytest.raises(UnsupportedJointError) as caught:
        bk.StackedTree(model)
    assert str(caught.value) == (
        "joint 'wheel': joint type JointModelRUBZ is not supported by the batched "
        "kinematics (1-DoF revolute or prismatic joints only)"
    )
    assert caught.value.joint == "wheel"


# ---------------------------------------------------------------------------------------------
# Newton on synthetic systems (every call recorded)


def quadratic(targets, first=None):
    """A synthetic system: row i is r = [q0^2 - t_i, q1 - 2 q0] over the unknowns (0, 1), with a
    third Jacobian column (7.0) that is not solved for; the 'platform' of row i is (1 + i) I at
    (q0, q1, i). `first` (q0 -> (value, slope)) replaces q0^2. Every call is recorded in `.calls`."""
    targets = np.asarray(targets, dtype=float)
    first = first or (lambda x: (x**2, 2 * x))

    def call(q, rows, with_jacobian):
        call.calls.append((rows.tolist(), with_jacobian))
        value, slope = first(q[:, 0])
        r = np.stack([value - targets[rows], q[:, 1] - 2 * q[:, 0]], axis=1)
        jac = None
        if with_jacobian:
            jac = np.zeros((len(q), 2, 3))
            jac[:, 0, 0], jac[:, 1, 0], jac[:, 1, 1], jac[:, :, 2] = slope, -2.0, 1.0, 7.0
        rot = np.broadcast_to(np.eye(3), (len(q), 3, 3)) * (1.0 + rows)[:, None, None]
        return r, jac, rot, np.stack([q[:, 0], q[:, 1], rows.astype(float)], axis=1)

    call.calls = []
    return call


def sign_of_first(jac, square):
    return (square[:, 0, 0] > 0)[:, None]


UNKNOWNS = np.array([0, 1])


def test_newton_batch_statuses_iterations_and_calls():
    """Rows: converge from 1.2 (Newton, then chord near the root), converge from 1.5 to t = 4, a capped
    first step from 0.1, a NaN residual (out of workspace at once), an exactly singular start."""
    system = quadratic([1.0, 4.0, 1.0, np.nan, 1.0])
    q = np.array([[1.2, 0.0], [1.5, 3.0], [0.1, 0.0], [1.0, 0.0], [0.0, 0.0]])
    out = bk.newton_batch(q, UNKNOWNS, system, sign_of_first, NewtonRules())
    assert list(out.status) == [0, 0, 0, 1, 3]
    assert list(out.iterations) == [9, 6, 10, 0, 0]
    assert out.iterations.dtype.kind == "i" and out.norm.dtype == float and out.status.dtype.kind == "i"
    np.testing.assert_allclose(out.q[:3], [[1.0, 2.0], [2.0, 4.0], [1.0, 2.0]], atol=1e-12)
    np.testing.assert_array_equal(out.q[3:], [[1.0, 0.0], [0.0, 0.0]])  # never stepped
    np.testing.assert_array_equal(q, [[1.2, 0.0], [1.5, 3.0], [0.1, 0.0], [1.0, 0.0], [0.0, 0.0]])  # not in place
    assert np.all(out.norm[:3] <= 1e-12) and np.isnan(out.norm[3]) and out.norm[4] == 1.0
    np.testing.assert_allclose(out.rotation[:3], [np.eye(3), 2 * np.eye(3), 3 * np.eye(3)])
    np.testing.assert_allclose(out.position[:3], np.c_[out.q[:3], [0.0, 1.0, 2.0]])
    np.testing.assert_array_equal(out.rotation[3:], 0.0)
    np.testing.assert_array_equal(out.position[3:], 0.0)
    assert system.calls == [([0, 1, 2, 3, 4], True)] + [([0, 1, 2], True)] * 5 + [
        ([1], False),
        ([0, 2], True),
        ([0, 2], True),
        ([0, 2], True),
        ([0, 2], False),
        ([2], False),
    ]


def test_newton_batch_caps_the_step_and_sorts_out_unfinished_rows():
    """One iteration allowed: a far row (residual > 1e-6 after it) is out of workspace (1), a row
    one step from the tolerance is not converged (2); the step's largest component is capped at 0.3."""
    system = quadratic([1.0, 1.0, 1.0])
    q = np.array([[1.5, 0.0], [1.0 + 1e-4, 2.0], [1.0 + 1e-9, 2.0 + 2e-9]])
    out = bk.newton_batch(q, UNKNOWNS, system, sign_of_first, NewtonRules(max_iterations=1))
    assert list(out.status) == [1, 2, 0] and list(out.iterations) == [1, 1, 1]
    # Row 0: dq = J^-1 r = (1.25 / 3, -3 + 2.5 / 3), scaled by 0.3 / 2.1666...
    np.testing.assert_allclose(out.q[0], [1.5 - 0.3 * (1.25 / 3) / (3 - 2.5 / 3), 0.3], rtol=1e-14)
    np.testing.assert_allclose(out.norm[1], 1e-8, rtol=1e-3)
    assert out.norm[0] == pytest.approx(abs(out.q[0, 1] - 2 * out.q[0, 0]), rel=1e-14)
    # Row 2 starts below 1e-4: a chord step, re-evaluated without a Jacobian; rows 0, 1 get Newton's.
    assert system.calls == [([0, 1, 2], True), ([2], False), ([0, 1], True)]
    zero = bk.newton_batch(q, UNKNOWNS, quadratic([1.0, 1.0, 1.0]), sign_of_first, NewtonRules(max_iterations=0))
    assert list(zero.status) == [1, 1, 2] and list(zero.iterations) == [0, 0, 0]


def test_newton_batch_counts_predictor_steps_and_checks_the_given_branch():
    system = quadratic([1.0, 1.0])
    q = np.array([[1.2, 0.0], [-1.2, 0.0]])
    out = bk.newton_batch(q, UNKNOWNS, system, sign_of_first, NewtonRules(), steps_taken=2, branch=np.array([True]))
    assert list(out.status) == [0, 4] and list(out.iterations) == [11, 11]
    np.testing.assert_allclose(out.q, [[1.0, 2.0], [-1.0, -2.0]], atol=1e-12)
    own = bk.newton_batch(q, UNKNOWNS, quadratic([1.0, 1.0]), sign_of_first, NewtonRules())
    assert list(own.status) == [0, 0] and list(own.iterations) == [9, 9]
    # The iteration budget counts from steps_taken: 9 more steps are needed, 8 allowed.
    short = bk.newton_batch(
        q, UNKNOWNS, quadratic([1.0, 1.0]), sign_of_first, NewtonRules(max_iterations=8), steps_taken=5
    )
    assert list(short.status) == [2, 2] and list(short.iterations) == [13, 13]


def test_newton_batch_branch_change_when_a_capped_step_crosses_a_singularity():
    """r0 = q0 - 1 from q0 = -0.5 with the label sign(d r1 / d q0), r1 = q1 - q0^2 ... crossing q0 = 0."""

    def linear(q, rows, with_jacobian):
        r = np.stack([q[:, 0] - 1.0, q[:, 1] - q[:, 0] ** 2], axis=1)
        jac = None
        if with_jacobian:
            jac = np.zeros((len(q), 2, 2))
            jac[:, 0, 0], jac[:, 1, 0], jac[:, 1, 1] = 1.0, -2 * q[:, 0], 1.0
        return r, jac, np.zeros((len(q), 3, 3)), np.zeros((len(q), 3))

    label = lambda jac, square: (square[:, 1, 0] > 0)[:, None]  # noqa: E731
    out = bk.newton_batch(np.array([[-0.5, 0.25], [0.5, 0.25]]), UNKNOWNS, linear, label, NewtonRules())
    assert list(out.status) == [4, 0]
    np.testing.assert_allclose(out.q, [[1.0, 1.0], [1.0, 1.0]], atol=1e-12)


@pytest.mark.parametrize("singular_rcond, status", [(1e-4, 3), (1e-5, 0)])
def test_newton_batch_singular_at_the_solution(singular_rcond, status):
    """Root q0 = 1e-4: J = [[2e-4, 0], [-2, 1]] has 1-norm condition 2.0002 x 15000 (rcond 3.3e-5)."""
    out = bk.newton_batch(
        np.array([[1e-4 + 1e-6, 2e-4]]),
        UNKNOWNS,
        quadratic([1e-8]),
        sign_of_first,
        NewtonRules(singular_rcond=singular_rcond),
    )
    assert list(out.status) == [status]
    np.testing.assert_allclose(out.q[0, 0], 1e-4, rtol=1e-4)


def test_failures_of_reasons_and_error_classes():
    n = 6
    solved = bk.SolvedRows(
        np.zeros((n, 2)),
        np.array([0, 1, 2, 3, 4, 5]),
        np.array([0.0, 0.5, 2e-7, 1e-13, 3e-14, 0.0]),
        np.array([3, 0, 60, 7, 8, 2]),
        np.zeros((n, 3, 3)),
        np.zeros((n, 3)),
    )
    failures = bk.failures_of(solved, 10, "what")
    assert [(f.index, f.error) for f in failures] == [
        (11, OutOfWorkspaceError),
        (12, NotConvergedError),
        (13, SingularConfigurationError),
        (14, BranchChangeError),
    ]
    assert [f.reason for f in failures] == [
        f"what: {ASSEMBLE} (residual 5.000e-01 after 0 iterations)",
        "what: Newton did not reach the tolerance (residual 2.000e-07 after 60 iterations)",
        "what: singular configuration (reciprocal condition below 1e-10) (residual 1.000e-13 after 7 iterations)",
        "what: the solution lies on another assembly branch than the start (Newton crossed a singularity) "
        "(residual 3.000e-14 after 8 iterations)",
    ]


def test_inverses_of_a_stack_with_a_singular_matrix():
    stack = np.array([[[2.0, 1.0], [0.0, 4.0]], [[1.0, 2.0], [2.0, 4.0]], [[0.0, 1.0], [1.0, 0.0]]])
    inverse, singular = bk.stack_inverses(stack)
    assert list(singular) == [False, True, False]
    np.testing.assert_allclose(inverse[0], [[0.5, -0.125], [0.0, 0.25]])
    np.testing.assert_array_equal(inverse[1], 0.0)
    np.testing.assert_allclose(inverse[2], [[0.0, 1.0], [1.0, 0.0]])
    inverse, singular = bk.stack_inverses(stack[[0, 2]])
    assert list(singular) == [False, False] and singular.dtype == bool
    np.testing.assert_allclose(inverse[0], [[0.5, -0.125], [0.0, 0.25]])


def test_factors_refresh_rcond_labels_and_start():
    factors = bk.RowFactors(4, 2)
    jac = np.array(
        [[[1.0, 3.0, 9.0], [0.0, 2.0, 9.0]], [[1.0, 2.0, 9.0], [2.0, 4.0, 9.0]], [[-2.0, 0.0, 9.0], [0.0, 1.0, 9.0]]]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the singular row divides by nothing
        singular = factors.refresh(np.array([0, 2, 3]), jac, UNKNOWNS, sign_of_first)
    assert list(singular) == [False, True, False]
    square = jac[[0, 2], :, :2]
    np.testing.assert_allclose(
        factors.rcond, [1 / np.linalg.cond(square[0], 1), 0.0, 0.0, 1 / np.linalg.cond(square[1], 1)], rtol=1e-14
    )
    # 1-norms (largest column sum): 5 and 2 (inverse [[1, -1.5], [0, 0.5]]); the row sums would give 4 and 2.5.
    assert factors.rcond[0] == pytest.approx(1 / 10, rel=1e-15)
    assert factors.labels.tolist() == [[True], [False], [True], [False]]
    assert factors.start.tolist() == [[True], [False], [True], [False]]
    np.testing.assert_allclose(factors.inverse[0], [[1.0, -1.5], [0.0, 0.5]])
    factors.refresh(np.array([0]), -jac[:1], UNKNOWNS, sign_of_first)
    assert factors.labels.tolist() == [[False], [False], [True], [False]]
    assert factors.start.tolist() == [[True], [False], [True], [False]]  # labels at the first Jacobian stay


@pytest.mark.parametrize("factor, status", [(1.0, 0), (1.0 + 1e-15, 3)])
def test_newton_batch_singular_threshold_is_strict(factor, status):
    """Converged at the start with J = [[2, 0], [-2, 1]]: 1-norm condition 4 x 1.5 = 6 exactly; a
    threshold of exactly 1/6 is not above the reciprocal condition, so the row is not singular."""
    out = bk.newton_batch(
        np.array([[1.0, 2.0]]),
        UNKNOWNS,
        quadratic([1.0]),
        sign_of_first,
        NewtonRules(singular_rcond=(1.0 / 6.0) * factor),
    )
    assert list(out.status) == [status] and list(out.iterations) == [0]


def test_evaluate_rows_chooses_newton_or_chord_per_row():
    """Rows above 1e-4 get a Jacobian; the others a residual first, and a Jacobian only when it
    contracted by less than 0.05, is above the tolerance and finite (the boundaries are strict)."""

    def identity(q, rows, with_jacobian):
        identity.calls.append((rows.tolist(), with_jacobian))
        jac = np.broadcast_to(np.eye(2) * (1.0 + rows)[:, None, None], (len(q), 2, 2)).copy() if with_jacobian else None
        return (
            q[:, :2].copy(),
            jac,
            np.broadcast_to(np.eye(3), (len(q), 3, 3)) * rows[:, None, None],
            np.stack([q[:, 0], q[:, 1], rows.astype(float)], axis=1),
        )

    identity.calls = []
    previous = np.array([2e-4, 1e-4, 1e-5, 1e-5, 1e-5, 2e-12, 1e-5, 3e-12])
    new = np.array([1e-5, 1e-6, 1e-7, 1e-6, 0.05 * 1e-5, 1e-12, np.inf, 2e-12])
    active = np.array([9, 8, 7, 6, 5, 4, 3, 2])
    q = np.zeros((10, 2))
    q[active] = np.c_[new, -new / 2]
    factors = bk.RowFactors(10, 2)
    residual, rot, pos, singular = bk.evaluate_rows(
        q, active, previous, NewtonRules(), identity, factors, UNKNOWNS, sign_of_first
    )
    assert identity.calls == [([8, 7, 6, 5, 4, 3, 2], False), ([9, 6, 2], True)]
    np.testing.assert_array_equal(residual, q[active])
    np.testing.assert_array_equal(rot, np.eye(3) * active[:, None, None])
    np.testing.assert_array_equal(pos[:, 2], active)
    assert not singular.any() and singular.shape == (8,)
    np.testing.assert_array_equal(factors.inverse[[9, 6, 2]], np.eye(2) / np.array([10.0, 7.0, 3.0])[:, None, None])
    np.testing.assert_array_equal(factors.inverse[[8, 7, 5, 4, 3]], 0.0)
    # Every row above 1e-4: one call, with the Jacobian; singular rows reported.
    identity.calls = []
    q[9] = 0.0
    residual, rot, pos, singular = bk.evaluate_rows(
        q, np.array([9, 1, 0]), np.full(3, 1.0), NewtonRules(), identity, bk.RowFactors(10, 2), UNKNOWNS, sign_of_first
    )
    assert identity.calls == [([9, 1, 0], True)] and list(singular) == [False, False, False]
    np.testing.assert_array_equal(rot, np.eye(3) * np.array([9, 1, 0])[:, None, None])


# ---------------------------------------------------------------------------------------------
# Stacked closures of a mechanism


def test_signatures_of_one_two_and_larger_blocks(five_bar):
    kin = bk.StackedKinematics(ClosedLoopSolver(five_bar))
    jac = np.random.default_rng(16).normal(size=(40, 5, 6))
    kin.blocks = [
        (np.array([3]), np.array([4])),
        (np.array([1, 0]), np.array([5, 2])),
        (np.array([0, 2, 4]), np.array([1, 3, 0])),
    ]
    signs = kin.signatures(jac)
    assert signs.shape == (40, 3) and signs.dtype == bool
    for k, (rows, cols) in enumerate(kin.blocks):
        expected = np.linalg.det(jac[:, rows[:, None], cols[None, :]]) > 0
        np.testing.assert_array_equal(signs[:, k], expected)
    assert signs.any(axis=0).all() and (~signs).any(axis=0).all()  # both signs seen in every block
    singular = np.zeros((1, 5, 6))
    singular[0, 1, 5], singular[0, 1, 2], singular[0, 0, 5], singular[0, 0, 2] = 1.0, 2.0, 2.0, 4.0  # det 0 exactly
    singular[0, 0, 1], singular[0, 2, 3] = 1.0, 1.0  # the 3 x 3 block's third column is zero
    assert kin.signatures(singular).tolist() == [[False, False, False]]  # True only where det > 0


def with_tool(five_bar: Mechanism, task: TaskSpec = TaskSpec("tool", ("x", "y"), "none")) -> Mechanism:
    """The five-bar commanded at a `tool` frame 5 cm beside the effector (the platform) on its link,
    turned by 0.4 rad about z."""
    model = five_bar.model.copy()
    effector = model.frames[model.getFrameId("effector")]
    offset = pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, 0.4), np.array([0.03, 0.04, 0.0]))
    model.addFrame(
        pin.Frame(
            "tool",
            effector.parentJoint,
            model.getFrameId("effector"),
            effector.placement * offset,
            pin.FrameType.OP_FRAME,
        )
    )
    return dataclasses.replace(five_bar.with_model(model), task=task)


TOOL_YAW = TaskSpec("tool", ("x",), "yaw")  # the tool's x and heading: square for the five-bar


def test_task_frame_other_than_the_platform(five_bar):
    """Task on `tool`: the platform frame sits before the task frame (-2); poses are the platform's,
    the task rows follow the tool, moved by chain 1's joints only."""
    moved = with_tool(five_bar)
    solver = ClosedLoopSolver(moved)
    kin = bk.StackedKinematics(solver)
    assert kin.platform_index == -2 and bk.StackedKinematics(ClosedLoopSolver(five_bar)).platform_index == -1
    np.testing.assert_array_equal(kin.task_support, [1.0, 1.0, 0.0, 0.0])
    q = five_bar.home + np.random.default_rng(17).normal(0, 0.3, (3, 4))
    _, _, frot, fpos, world = kin.closures(q)
    model, data = moved.model, moved.model.createData()
    for i in range(3):
        pin.framesForwardKinematics(model, data, q[i])
        for index, name in ((-1, "tool"), (-2, "effector")):
            placement = data.oMf[model.getFrameId(name)]
            np.testing.assert_allclose(frot[i, index], placement.rotation, atol=1e-14)
            np.testing.assert_allclose(fpos[i, index], placement.translation, atol=1e-14)
    sliders = five_bar.home[[0, 2]] + np.array([[0.0, 0.0], [0.05, 0.05], [-0.1, 0.2]])
    reference = ClosedLoopSolver(five_bar).forward_batch(sliders)
    batch = solver.forward_batch(sliders)
    np.testing.assert_allclose(batch.poses, reference.poses, atol=1e-12)  # the effector's, not the tool's
    tool = batch.poses[:, :3, :3] @ np.array([0.03, 0.04, 0.0]) + batch.poses[:, :3, 3]
    ik = solver.inverse_batch(tool[:, :2])
    assert ik.complete
    np.testing.assert_allclose(ik.actuators, sliders, atol=1e-10)
    np.testing.assert_allclose(ik.poses, reference.poses, atol=1e-10)
    cold = solver.inverse_batch(tool[:, :2], q_init=five_bar.home)
    np.testing.assert_allclose(cold.actuators, sliders, atol=1e-10)
    assert list(ik.iterations) == [1, 3, 4] and list(cold.iterations) == [0, 3, 4]  # home: the first step is 0


# ---------------------------------------------------------------------------------------------
# forward_batch / inverse_batch


def test_forward_batch_slider_limits_are_inclusive_and_named(five_bar):
    """Limits [1.83, 2.83] and [0.31, 1.31]: a row at a limit is solved; beyond, the first slider
    beyond its limit is named; the rows keep their input order."""
    solver = ClosedLoopSolver(five_bar)
    sliders = np.array([[2.33, 0.3], [2.33, 1.4], [1.7, 1.4], [1.83, 0.81], [2.33, 0.81], [2.83, 0.31]])
    batch = solver.forward_batch(sliders)
    assert list(batch.indices) == [3, 4, 5] and list(batch.iterations) == [5, 1, 4]
    assert [(f.index, f.reason, f.error) for f in batch.failures] == [
        (0, "actuator 'motor_2' = 0.3 is beyond its joint limit", InvalidInputError),
        (1, "actuator 'motor_2' = 1.4 is beyond its joint limit", InvalidInputError),
        (2, "actuator 'motor_1' = 1.7 is beyond its joint limit", InvalidInputError),
    ]
    assert list(batch.ok) == [False, False, False, True, True, True] and not batch.complete
    np.testing.assert_allclose(batch.q[:, [0, 2]], sliders[3:], atol=0)
    np.testing.assert_allclose(batch.poses[:, 3], [[0, 0, 0, 1]] * 3, atol=0)
    assert batch.residuals.shape == (3,) and np.all(batch.residuals <= 1e-12)
    for k, i in enumerate(batch.indices):
        fk = solver.forward(sliders[i], q_init=five_bar.home)
        np.testing.assert_allclose(batch.poses[k], fk.pose.homogeneous, atol=1e-12)


def test_forward_batch_every_row_beyond_its_limits(five_bar):
    batch = ClosedLoopSolver(five_bar).forward_batch(np.array([[2.33, 0.3], [3.0, 0.8]]))
    assert batch.n == 2 and len(batch.indices) == 0 and batch.indices.dtype.kind == "i"
    # q keeps its width nq when no row converged (it was (0, 0) before the fix).
    assert batch.poses.shape == (0, 4, 4) and batch.q.shape == (0, 4) and batch.residuals.shape == (0,)
    assert batch.iterations.shape == (0,) and [f.index for f in batch.failures] == [0, 1]
    assert list(batch.ok) == [False, False]


@pytest.mark.parametrize("compiled", [True, False])
def test_forward_batch_predictor_from_home_and_given_starts(five_bar, compiled):
    """From home's tangent the predictor is step 1 (home itself: converged at 1); from q_init = home,
    plain Newton. Both end on the same poses; q_init is neither modified nor shared. Both Newton loops."""
    solver = ClosedLoopSolver(five_bar, native=compiled)
    sliders = np.array([[2.73, 0.41], [2.9, 0.8], [1.93, 1.21], [2.33, 0.81]])
    predicted = solver.forward_batch(sliders)
    assert list(predicted.indices) == [0, 2, 3] and list(predicted.iterations) == [4, 4, 1]
    start = five_bar.home.copy()
    plain = solver.forward_batch(sliders, q_init=start)
    np.testing.assert_array_equal(start, five_bar.home)
    assert list(plain.indices) == [0, 2, 3] and list(plain.iterations) == [7, 7, 0]
    np.testing.assert_allclose(plain.poses, predicted.poses, atol=1e-12)
    per_row = np.repeat(five_bar.home[None, :], 4, axis=0)
    per_row[2] = plain.q[1]  # row 2 starts at its solution: no step
    rows = solver.forward_batch(sliders, q_init=per_row)
    assert list(rows.iterations) == [7, 0, 0]
    np.testing.assert_array_equal(per_row[2], plain.q[1])
    kin = bk.StackedKinematics(solver)
    _, jac, _ = solver.closure_sensitivity(five_bar.home)
    tangent, branch = kin.home_reference()
    np.testing.assert_allclose(tangent, -np.linalg.solve(jac[:, kin.passive], jac[:, kin.actuated]), atol=1e-14)
    np.testing.assert_array_equal(branch, kin.signatures(jac[None])[0])
    assert kin.home_reference()[0] is tangent  # computed once


@pytest.mark.parametrize("compiled", [True, False])
def test_forward_batch_failures_sorted_by_row(mechanism, compiled):
    """A row that cannot close (row 0) and a slider beyond its limit (row 1): reported in row order,
    word for word, by both Newton loops."""
    solver = ClosedLoopSolver(mechanism, native=compiled)
    sliders = np.array([[-0.3, 0.3, 0.0, 0.0], [0.0, 0.7, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    batch = solver.forward_batch(sliders)
    assert [(f.index, f.error) for f in batch.failures] == [(0, OutOfWorkspaceError), (1, InvalidInputError)]
    assert batch.failures[1].reason == "actuator 'q11_B2' = 0.7 is beyond its joint limit"
    assert re.fullmatch(
        rf"forward kinematics: {re.escape(ASSEMBLE)} \(residual \d\.\d{{3}}e[-+]\d\d after \d+ "
        r"iterations\)",
        batch.failures[0].reason,
    )


def test_forward_batch_in_chunks(five_bar, monkeypatch):
    """300 rows in chunks of 256: two chunks; the same poses as the rows solved alone, in input order."""
    monkeypatch.setattr(bk, "_CHUNK", 256)
    solver = ClosedLoopSolver(five_bar)
    sliders = five_bar.home[[0, 2]] + np.random.default_rng(18).uniform(-0.3, 0.3, (300, 2))
    sliders[[5, 280]] = [[3.0, 0.8], [2.3, 0.2]]  # beyond the limits, one in each chunk
    batch = solver.forward_batch(sliders)
    assert [f.index for f in batch.failures] == [5, 280] and batch.complete is False
    assert list(batch.indices) == [i for i in range(300) if i not in (5, 280)]
    some = np.array([0, 4, 6, 255, 256, 257, 299])
    alone = solver.forward_batch(sliders[some])
    np.testing.assert_allclose(batch.poses[np.searchsorted(batch.indices, some)], alone.poses, atol=1e-13)


@pytest.mark.parametrize("compiled", [True, False])
def test_inverse_batch_limit_and_assembly_failures_word_for_word(five_bar, compiled):
    solver = ClosedLoopSolver(five_bar, native=compiled)
    targets = np.array([[0.0, 0.7], [0.0, 0.40], [0.15, 0.3], [0.0, 0.3], [-0.2, 0.3]])
    ik = solver.inverse_batch(targets)
    assert list(ik.indices) == [1, 3] and list(ik.iterations) == [3, 4]
    assert [(f.index, f.error) for f in ik.failures] == [
        (0, OutOfWorkspaceError),
        (2, OutOfWorkspaceError),
        (4, OutOfWorkspaceError),
    ]
    # A Newton that cannot assemble ends wherever rounding takes it: its residual is checked as a
    # number above the tolerance, not by its digits (which differ between BLAS kernels).
    no_assembly = re.fullmatch(
        rf"inverse kinematics: {re.escape(ASSEMBLE)} \(residual (\S+) after 61 iterations\)", ik.failures[0].reason
    )
    assert no_assembly is not None and float(no_assembly[1]) > 1e-6
    # The five-bar's motors are revolute: their values and limits are in rad.
    assert ik.failures[1].reason == (
        "inverse kinematics: target needs actuator 'motor_2' = 0.0502313 rad, beyond its limit [0.31, 1.31]"
    )
    assert ik.failures[2].reason == (
        "inverse kinematics: target needs actuator 'motor_1' = 3.20758 rad, beyond its limit [1.83, 2.83]"
    )
    np.testing.assert_allclose(ik.poses[:, :2, 3], targets[[1, 3]], atol=1e-12)
    np.testing.assert_array_equal(ik.actuators, ik.q[:, [0, 2]])
    np.testing.assert_array_equal(ik.tilt, 0.0)  # a planar machine: no roll or pitch
    cold = solver.inverse_batch(targets, q_init=five_bar.home)
    assert list(cold.iterations) == [3, 4] and "after 60 iterations" in cold.failures[0].reason


def _task_placement_jacobian(rot, pos, twist):
    """LOCAL_WORLD_ALIGNED frame Jacobian [v + w x p; w] from WORLD twist columns [v; w]."""
    return np.concatenate((twist[:3] + np.cross(twist[3:].T, pos).T, twist[3:]))


@pytest.mark.parametrize(
    "task",
    [
        TaskSpec("f", ("x", "y", "z"), "yaw"),
        TaskSpec("f", ("x", "z"), "none"),
        TaskSpec("f", ("y",), "full"),
        TaskSpec("f", (), "full"),
    ],
)
def test_task_rows_match_the_single_task_residual_and_jacobian(task):
    rng = np.random.default_rng(19)
    n, nv = 5, 4
    placements = [pin.exp6(rng.normal(0, 0.7, 6)) for _ in range(n)]
    rot, pos = np.array([m.rotation for m in placements]), np.array([m.translation for m in placements])
    twist = rng.normal(size=(n, 6, nv))
    goal_rot = np.array([pin.exp3(rng.normal(0, 0.5, 3)) for _ in range(n)]) if task.rotation == "full" else None
    goal = rng.normal(size=(n, len(task.position) + (1 if task.rotation == "yaw" else 0)))
    if task.rotation == "yaw":
        goal[:, -1] += np.array([0, 2 * np.pi, -2 * np.pi, 4 * np.pi, 3.0])  # wrapped
    residual, jacobian = bk.task_rows(task, rot, pos, twist, goal, goal_rot)
    assert residual.shape == (n, task.dimension) and jacobian.shape == (n, task.dimension, nv)
    for i in range(n):
        frame_jac = _task_placement_jacobian(rot[i], pos[i], twist[i])
        g_rot = None if goal_rot is None else goal_rot[i]
        np.testing.assert_allclose(residual[i], task.residual(placements[i], goal[i], g_rot), atol=1e-12)
        np.testing.assert_allclose(jacobian[i], task.jacobian(placements[i], frame_jac, g_rot), atol=1e-12)


@pytest.mark.parametrize("machine", ["m_machine", "tool", "tool_yaw"])
def test_first_step_from_home_is_one_newton_step_of_the_whole_system(machine, mechanism, five_bar):
    """Rows 0, 2, 3 of 4 get -J^-1 [closures; task - goal] at home, capped at 0.3 (row 2) or not (row 3)."""
    if machine == "tool":
        mechanism = with_tool(five_bar)
        targets = np.array([[0.05, 0.45], [0.0, 0.4], [0.3, 0.2], [0.01, 0.44]])
    elif machine == "tool_yaw":
        mechanism = with_tool(five_bar, TOOL_YAW)
        home = bk.StackedKinematics(ClosedLoopSolver(mechanism)).closures(mechanism.home[None, :])
        x, yaw = home[3][0, -1, 0], np.arctan2(home[2][0, -1, 1, 0], home[2][0, -1, 0, 0])
        targets = np.array([[x + 0.01, yaw + 0.02], [x, yaw], [x + 0.2, yaw + 1.0], [x + 1e-3, yaw - 1e-3]])
    else:
        targets = np.array(
            [[0.55, 0.60, -0.10, 0.3], [0.5, 0.5, -0.1, 0.0], [0.3, 0.9, 0.0, -2.5], [0.6, 0.6, -0.1, 0.1]]
        )
    solver = ClosedLoopSolver(mechanism)
    kin = bk.StackedKinematics(solver)
    task = mechanism.task
    start = np.repeat(mechanism.home[None, :], 4, axis=0)
    rows = np.array([0, 2, 3])
    signature = lambda jac, square: np.concatenate(  # noqa: E731
        (kin.signatures(jac), (np.linalg.slogdet(square)[0] > 0)[:, None]), axis=1
    )
    labels = bk.first_step_from_home(kin, start, rows, targets, signature)
    closure, closure_jac, _ = solver.closure_sensitivity(mechanism.home)
    data = solver.data
    frame = mechanism.model.getFrameId(task.frame)
    pin.framesForwardKinematics(solver.model, data, mechanism.home)
    frame_jac = pin.computeFrameJacobian(solver.model, data, mechanism.home, frame, pin.LOCAL_WORLD_ALIGNED)
    full_jac = np.vstack((closure_jac, task.jacobian(data.oMf[frame], frame_jac, None)))
    square = full_jac[:, kin.unknowns]
    np.testing.assert_array_equal(labels, signature(full_jac[None], square[None])[0])
    np.testing.assert_array_equal(start[1], mechanism.home)  # a row not asked for
    for k, row in enumerate(rows):
        residual = np.r_[closure, task.residual(data.oMf[frame], targets[row], None)]
        step = np.linalg.solve(square, residual)
        step *= min(1.0, 0.3 / np.abs(step).max())
        expected = mechanism.home.copy()
        expected[kin.unknowns] -= step
        np.testing.assert_allclose(start[row], expected, atol=1e-12)
    assert np.abs(start[2] - mechanism.home).max() == pytest.approx(0.3, abs=1e-15)  # a capped step
    assert np.abs(start[3] - mechanism.home).max() < 0.3  # a full step


def test_first_step_from_a_singular_home_is_skipped(mechanism):
    """Home judged singular (threshold just above its reciprocal 1-norm condition): start untouched,
    no reference; just below the threshold the step is taken."""
    solver = ClosedLoopSolver(mechanism)
    kin = bk.StackedKinematics(solver)
    targets = np.array([[0.5, 0.5, -0.1, 0.0]] * 2)
    home = np.repeat(mechanism.home[None, :], 2, axis=0)
    _, jac, frot, fpos, world = kin.closures(mechanism.home[None, :])
    _, task_jac = bk.task_rows(mechanism.task, frot[:, -1], fpos[:, -1], world * kin.task_support, targets[:1], None)
    square = np.concatenate((jac, task_jac), axis=1)[0][:, kin.unknowns]
    rcond = 1 / np.linalg.cond(square, 1)
    exact = 1.0 / (np.abs(square[None]).sum(axis=1).max() * np.abs(np.linalg.inv(square[None])).sum(axis=1).max())
    assert exact == pytest.approx(rcond, rel=1e-12)
    for threshold, skipped in ((rcond * (1 + 1e-9), True), (rcond * (1 - 1e-9), False), (exact, False)):
        solver.singular_rcond = threshold  # skipped below the threshold, not at it
        start = home.copy()
        labels = bk.first_step_from_home(kin, start, np.array([0, 1]), targets, lambda jac, square: np.ones((1, 1)))
        assert (labels is None) is skipped
        assert np.array_equal(start, home) is skipped


def test_inverse_batch_with_a_full_rotation_task(wrist):
    solver = ClosedLoopSolver(wrist)
    sliders = wrist.home[[0, 3, 6]] + np.array([[0.0, 0.0, 0.0], [0.1, -0.1, 0.05], [0.2, 0.1, -0.2]])
    fk = solver.forward_batch(sliders)
    assert list(fk.iterations) == [1, 4, 4]
    assert list(solver.forward_batch(sliders, q_init=wrist.home).iterations) == [0, 4, 4]
    quaternions = np.array([pin.Quaternion(p[:3, :3]).coeffs() for p in fk.poses])
    ik = solver.inverse_batch(quaternions)
    assert ik.complete and list(ik.iterations) == [0, 4, 4]
    np.testing.assert_allclose(ik.actuators, sliders, atol=1e-12)
    np.testing.assert_allclose(ik.poses, fk.poses, atol=1e-12)
    assert np.abs(bk.rpy_batch(fk.poses[:, :3, :3])[2, :2]).min() > 0.15  # the goal has roll and pitch
    np.testing.assert_allclose(ik.tilt, 0.0, atol=1e-12)  # reached minus commanded roll and pitch
    single = solver.inverse(quaternions[2])
    np.testing.assert_allclose(ik.actuators[2], single.actuators, atol=1e-12)
    np.testing.assert_allclose(ik.tilt[2], single.tilt, atol=1e-12)


@pytest.mark.parametrize(
    "values, message",
    [
        ([["a", 1.0]], "actuator values: not numeric rows (could not convert string to float: 'a')"),
        (
            object(),
            "actuator values: not numeric rows (float() argument must be a string or a real number, not 'object')",
        ),
        ([[1.0, 2.0, 3.0]], "actuator values: shape (1, 3), expected (n, 2) rows ('motor_1', 'motor_2')"),
        ([1.0, 2.0], "actuator values: shape (2,), expected (n, 2) rows ('motor_1', 'motor_2')"),
        (np.zeros((0, 3)), "actuator values: shape (0, 3), expected (n, 2) rows ('motor_1', 'motor_2')"),
        (np.zeros((1, 2, 1)), "actuator values: shape (1, 2, 1), expected (n, 2) rows ('motor_1', 'motor_2')"),
        ([[1.0, 2.0], [1.0, np.inf]], "actuator values: row 1 (0-based): motor_2 = inf, not finite"),
        ([[2.0, 1.0], [np.nan, np.inf]], "actuator values: row 1 (0-based): motor_1 = nan, not finite"),
    ],
)
def test_bad_slider_rows_are_refused_word_for_word(five_bar, values, message):
    with pytest.raises(InvalidInputError) as caught:
        ClosedLoopSolver(five_bar).forward_batch(values)
    assert str(caught.value) == message


def test_bad_targets_and_starts_are_refused_word_for_word(five_bar):
    solver = ClosedLoopSolver(five_bar)
    with pytest.raises(InvalidInputError) as caught:
        solver.inverse_batch([[0.0, 0.4, 1.0]])
    assert str(caught.value) == "targets: shape (1, 3), expected (n, 2) rows ('x', 'y')"
    with pytest.raises(InvalidInputError) as caught:
        solver.inverse_batch([[0.0, 0.4], [0.0, np.nan]])
    assert str(caught.value) == "targets: row 1 (0-based): y = nan, not finite"
    sliders = [[2.33, 0.81], [2.33, 0.81]]
    for q_init, shape in (
        (np.zeros(3), "(3,)"),
        (np.zeros((3, 4)), "(3, 4)"),
        ([[0.0] * 4], "(1, 4)"),
        (np.r_[np.nan, 0.0, 0.0, 0.0], "(2, 4)"),
        (np.full((2, 4), np.inf), "(2, 4)"),
    ):
        with pytest.raises(InvalidInputError) as caught:
            solver.forward_batch(sliders, q_init=q_init)
        assert str(caught.value) == f"q_init: expected finite (4,) or (2, 4) values, got shape {shape}"
    kin = bk.StackedKinematics(solver)
    starts = bk.start_configurations(kin, 3, None)
    np.testing.assert_array_equal(starts, np.repeat(five_bar.home[None, :], 3, axis=0))
    starts[0, 0] = 9.0
    np.testing.assert_array_equal(bk.start_configurations(kin, 3, None)[0], five_bar.home)
    given = np.arange(8.0).reshape(2, 4)
    start = bk.start_configurations(kin, 2, given)
    start[0, 0] = 9.0
    assert given[0, 0] == 0.0  # a copy
    np.testing.assert_array_equal(bk.start_configurations(kin, 2, [1, 2, 3, 4]), [[1, 2, 3, 4], [1, 2, 3, 4]])
    assert bk.start_configurations(kin, 2, [1, 2, 3, 4]).dtype == float


def test_m_machine_iteration_counts_from_home(mechanism):
    """Position + yaw: IK's first step from home is batched and counted (the unreachable row runs
    60 steps after it); FK's predictor is counted the same way."""
    solver = ClosedLoopSolver(mechanism)
    targets = np.array([[0.55, 0.60, -0.10, 0.3], [0.5, 0.5, -0.1, 0.0], [0.3, 0.9, 0.0, -2.5], [0.6, 0.6, -0.1, 0.1]])
    ik = solver.inverse_batch(targets)
    assert list(ik.indices) == [0, 1, 3] and list(ik.iterations) == [4, 3, 4]
    assert ik.failures[0].index == 2 and ik.failures[0].reason.endswith("after 61 iterations)")
    cold = solver.inverse_batch(targets, q_init=mechanism.home)
    assert list(cold.iterations) == [4, 3, 4] and cold.failures[0].reason.endswith("after 60 iterations)")
    np.testing.assert_allclose(cold.actuators, ik.actuators, atol=1e-11)
    assert list(solver.forward_batch(ik.actuators).iterations) == [5, 3, 4]
    assert list(solver.forward_batch(ik.actuators, q_init=mechanism.home).iterations) == [4, 3, 4]
    np.testing.assert_allclose(ik.poses[:, :3, 3], targets[[0, 1, 3], :3], atol=1e-12)
    np.testing.assert_allclose(bk.rpy_batch(ik.poses[:, :3, :3])[:, 2], targets[[0, 1, 3], 3], atol=1e-12)


def _recorded_newton(monkeypatch):
    """Record every newton_batch call's arguments (the batch solves' systems and signatures)."""
    calls = []
    real = bk.newton_batch

    def recording(*args):
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(bk, "newton_batch", recording)
    return calls


def test_inverse_batch_system_and_labels(monkeypatch, wrist):
    """The IK system is [closure rows; task rows] at the platform (task) frame with the goals of the
    rows asked for; its labels are the closure blocks plus sign(det) of the whole square system."""
    solver = ClosedLoopSolver(wrist, native=False)  # the numpy Newton (the compiled one never calls newton_batch)
    kin = bk.StackedKinematics(solver)
    calls = _recorded_newton(monkeypatch)
    goals = np.array(
        [pin.Quaternion(pin.exp3(np.array(v))).coeffs() for v in ([0.1, 0.2, 0.0], [0.0, -0.1, 0.3], [0.2, 0.0, 0.1])]
    )
    solver.inverse_batch(goals)
    ((start, unknowns, system, signature, rules, steps, branch),) = calls
    assert (rules, steps, branch) == (solver.rules, 0, None) and rules == NewtonRules()
    np.testing.assert_array_equal(unknowns, np.arange(9))
    np.testing.assert_array_equal(start, np.repeat(wrist.home[None, :], 3, axis=0))
    q = wrist.home + np.random.default_rng(20).normal(0, 0.2, (2, 9))
    rows = np.array([2, 0])
    residual, jac, rot, pos = system(q, rows, True)
    for k, i in enumerate(rows):
        closure, closure_jac, _ = solver.closure_sensitivity(q[k])
        placement = solver.data.oMf[wrist.platform_frame_id]
        frame_jac = pin.computeFrameJacobian(
            solver.model, solver.data, q[k], wrist.platform_frame_id, pin.LOCAL_WORLD_ALIGNED
        )
        goal_rot = pin.Quaternion(*goals[i][[3, 0, 1, 2]]).matrix()
        np.testing.assert_allclose(
            residual[k], np.r_[closure, wrist.task.residual(placement, goals[i], goal_rot)], atol=1e-12
        )
        np.testing.assert_allclose(
            jac[k], np.vstack((closure_jac, wrist.task.jacobian(placement, frame_jac, goal_rot))), atol=1e-12
        )
        np.testing.assert_allclose(rot[k], placement.rotation, atol=1e-14)
        np.testing.assert_allclose(pos[k], placement.translation, atol=1e-14)
    no_jac = system(q, rows, False)
    assert no_jac[1] is None
    np.testing.assert_array_equal(no_jac[0], residual)
    square = np.array(
        [
            np.diag([2.0, 1, 1, 1, 1, 1, 1, 1, 1]),
            np.diag([-0.5, 1, 1, 1, 1, 1, 1, 1, 1]),
            np.diag([0.5, 1, 1, 1, 1, 1, 1, 1, 1]),
        ]
    )
    full = np.zeros((3, 9, 9))
    full[:] = jac[0]
    full[:, 6:] = square[:, 6:]
    labels = signature(full, square)
    np.testing.assert_array_equal(labels[:, :-1], kin.signatures(full))
    np.testing.assert_array_equal(labels[:, -1], [True, False, True])


def test_forward_batch_system_and_labels(monkeypatch, five_bar):
    solver = ClosedLoopSolver(five_bar, native=False)  # the numpy Newton (the compiled one never calls newton_batch)
    kin = bk.StackedKinematics(solver)
    calls = _recorded_newton(monkeypatch)
    solver.forward_batch(np.array([[2.4, 0.9], [2.3, 0.7]]))
    ((start, unknowns, system, signature, rules, steps, branch),) = calls
    assert (rules, steps) == (solver.rules, 1) and rules == NewtonRules()
    np.testing.assert_array_equal(unknowns, kin.passive)
    np.testing.assert_array_equal(branch, kin.home_reference()[1])
    tangent = kin.home_reference()[0]
    expected = np.repeat(five_bar.home[None, :], 2, axis=0)
    expected[:, kin.passive] += (np.array([[2.4, 0.9], [2.3, 0.7]]) - five_bar.home[kin.actuated]) @ tangent.T
    expected[:, kin.actuated] = [[2.4, 0.9], [2.3, 0.7]]
    np.testing.assert_allclose(start, expected, atol=1e-15)
    q = five_bar.home + np.random.default_rng(21).normal(0, 0.2, (2, 4))
    residual, jac, rot, pos = system(q, np.array([1, 0]), True)
    for k in range(2):
        closure, closure_jac, _ = solver.closure_sensitivity(q[k])
        np.testing.assert_allclose(residual[k], closure, atol=1e-14)
        np.testing.assert_allclose(jac[k], closure_jac, atol=1e-14)
        np.testing.assert_allclose(pos[k], solver.data.oMf[five_bar.platform_frame_id].translation, atol=1e-14)
    assert system(q, np.array([1, 0]), False)[1] is None
    np.testing.assert_array_equal(signature(jac, jac[:, :, kin.passive]), kin.signatures(jac))
    calls.clear()
    solver.forward_batch(np.array([[2.4, 0.9]]), q_init=five_bar.home)
    assert calls[0][5] == 0 and calls[0][6] is None


def test_one_target_and_one_slider_set(mechanism, five_bar):
    ik = ClosedLoopSolver(mechanism).inverse_batch([[0.5, 0.5, -0.1, 0.0]])
    assert ik.complete and list(ik.indices) == [0] and ik.actuators.shape == (1, 4) and ik.tilt.shape == (1, 2)
    fk = ClosedLoopSolver(five_bar).forward_batch([[2.4, 0.9]])
    assert fk.complete and fk.poses.shape == (1, 4, 4) and fk.q.shape == (1, 4)


def test_newton_batch_boundaries_at_exact_residuals():
    """Residual exactly 1e-6 (2^-20 - (2^-20 - 1e-6) is exact): converged at a tolerance of 1e-6, and
    with no step allowed below a tolerance, 'not converged' (not out of workspace: <= 1e-6)."""
    q0 = 2.0**-10
    t = q0**2 - 1e-6
    q = np.array([[q0, 2 * q0]])
    assert (q0**2 - t) == 1e-6
    done = bk.newton_batch(q, UNKNOWNS, quadratic([t]), sign_of_first, NewtonRules(tolerance=1e-6))
    assert list(done.status) == [0] and list(done.iterations) == [0] and done.norm[0] == 1e-6
    left = bk.newton_batch(q, UNKNOWNS, quadratic([t]), sign_of_first, NewtonRules(max_iterations=0))
    assert list(left.status) == [2] and left.norm[0] == 1e-6


def test_batch_results_are_typed_arrays(five_bar):
    batch = ClosedLoopSolver(five_bar).forward_batch([[2.4, 0.9], [2.3, 0.7]])
    assert batch.residuals.dtype == float and batch.iterations.dtype.kind == "i" and batch.q.dtype == float
    assert batch.poses.dtype == float and batch.indices.dtype.kind == "i"
    assert all(not a.flags.writeable for a in (batch.indices, batch.poses, batch.q, batch.residuals, batch.iterations))


def test_newton_batch_a_jacobian_singular_after_a_step_ends_the_row():
    """r = q + 10 with J = 1 at q = 0 and exactly 0 elsewhere: after the capped first step (q = -0.3)
    the refreshed Jacobian is singular, and the row stops there as singular (3), not after 60 steps."""

    def kink(q, rows, with_jacobian):
        jac = np.where(q[:, 0] == 0.0, 1.0, 0.0)[:, None, None] if with_jacobian else None
        return q[:, :1] + 10.0, jac, np.zeros((len(q), 3, 3)), np.zeros((len(q), 3))

    out = bk.newton_batch(
        np.zeros((1, 1)), np.array([0]), kink, lambda jac, square: np.ones((len(jac), 1), bool), NewtonRules()
    )
    assert list(out.status) == [3] and list(out.iterations) == [1]
    np.testing.assert_allclose(out.q, [[-0.3]], rtol=1e-15)


def test_inverse_batch_of_a_yaw_task_on_a_frame_off_the_platform(monkeypatch, five_bar):
    """The tool's x and heading (turned 0.4 rad from the effector): IK reaches them, from home (first
    step batched, branch labels of home) and from given starts (no step, labels at the start)."""
    machine = with_tool(five_bar, TOOL_YAW)
    solver = ClosedLoopSolver(machine, native=False)  # the numpy Newton's calls are recorded
    kin = bk.StackedKinematics(solver)
    sliders = five_bar.home[[0, 2]] + np.array([[0.0, 0.0], [0.05, 0.05], [-0.1, 0.2]])
    fk = solver.forward_batch(sliders)
    _, _, frot, fpos, _ = kin.closures(fk.q)
    targets = np.c_[fpos[:, -1, 0], np.arctan2(frot[:, -1, 1, 0], frot[:, -1, 0, 0])]
    calls = _recorded_newton(monkeypatch)
    ik = solver.inverse_batch(targets)
    assert ik.complete and ik.n == 3 and list(ik.ok) == [True] * 3
    np.testing.assert_allclose(ik.actuators, sliders, atol=1e-10)
    np.testing.assert_allclose(ik.poses, fk.poses, atol=1e-10)  # the platform's poses
    assert calls[0][5] == 1
    start = np.repeat(machine.home[None, :], 3, axis=0)
    signature = calls[0][3]
    np.testing.assert_array_equal(calls[0][6], bk.first_step_from_home(kin, start, np.arange(3), targets, signature))
    calls.clear()
    warm = solver.inverse_batch(targets, q_init=fk.q)
    assert list(warm.iterations) == [0, 0, 0] and calls[0][5] == 0 and calls[0][6] is None
    np.testing.assert_array_equal(calls[0][0], fk.q)


def test_inverse_batch_counts_every_row(five_bar):
    ik = ClosedLoopSolver(five_bar).inverse_batch([[0.0, 0.7], [0.0, 0.40]])
    assert ik.n == 2 and list(ik.ok) == [False, True] and not ik.complete


# ------------------------------------------------------------------------------------------------
# The task frame apart from the platform, and batches of no rows


def test_batch_task_poses_of_a_tool_frame_are_the_single_solves(tool_machine):
    """forward_batch and inverse_batch report the platform in `poses` and the tool in `task_poses`, as
    the single solves do; the batch IK's tilt is the tool's."""
    solver = ClosedLoopSolver(tool_machine)
    home_tool = tool_machine.task.coordinates(
        solver.forward(tool_machine.home[tool_machine.actuated_ids]).task_pose.homogeneous[None]
    )[0]
    targets = home_tool + np.array([[0.0, 0.0, 0.0, 0.0], [0.02, -0.03, 0.01, 0.1], [-0.02, 0.05, -0.02, -0.2]])
    inverse = solver.inverse_batch(targets)
    assert list(inverse.indices) == [0, 1, 2]
    for k, target in enumerate(targets):
        single = ClosedLoopSolver(tool_machine).inverse(target)
        np.testing.assert_allclose(inverse.task_poses[k], single.task_pose.homogeneous, atol=1e-10)
        np.testing.assert_allclose(inverse.poses[k], single.pose.homogeneous, atol=1e-10)
        np.testing.assert_allclose(inverse.tilt[k], single.tilt, atol=1e-10)
    forward = solver.forward_batch(inverse.actuators)
    np.testing.assert_allclose(forward.task_poses, inverse.task_poses, atol=1e-10)
    np.testing.assert_allclose(forward.poses, inverse.poses, atol=1e-10)
    assert np.all(np.linalg.norm(forward.poses[:, :3, 3] - forward.task_poses[:, :3, 3], axis=1) > 0.1)


def test_batches_of_no_rows_have_empty_task_poses(tool_machine, mechanism):
    for machine in (tool_machine, mechanism):
        solver = ClosedLoopSolver(machine)
        forward = solver.forward_batch(np.zeros((0, 4)))
        inverse = solver.inverse_batch(np.zeros((0, 4)))
        for batch in (forward, inverse):
            assert batch.task_poses.shape == (0, 4, 4) and batch.poses.shape == (0, 4, 4) and batch.failures == ()
        assert inverse.actuators.shape == (0, 4) and inverse.tilt.shape == (0, 2)
    everything_beyond = ClosedLoopSolver(tool_machine).forward_batch(np.full((2, 4), 9.0))
    assert everything_beyond.task_poses.shape == (0, 4, 4) and len(everything_beyond.failures) == 2
    platform = ClosedLoopSolver(mechanism).forward_batch(mechanism.home[mechanism.actuated_ids][None])
    assert platform.task_poses is platform.poses


def test_batch_task_poses_of_a_task_frame_on_another_joint(mechanism, tmp_path):
    """P_II as the task frame: on chain B3's last joint, not on P_I's; the batch places it from its own
    parent joint, as the single solve does."""
    import yaml

    closures = yaml.safe_load(mechanism.closures_path.read_text())
    closures["task"]["frame"] = "P_II"
    (tmp_path / "m.closures.yaml").write_text(yaml.safe_dump(closures))
    machine = Mechanism.load(mechanism.urdf_path, tmp_path / "m.closures.yaml")
    model = machine.model
    assert model.frames[model.getFrameId("P_II")].parentJoint != model.frames[machine.platform_frame_id].parentJoint
    sliders = machine.home[machine.actuated_ids] + np.array([[0.0, 0.0, 0.0, 0.0], [0.02, -0.01, 0.03, 0.01]])
    batch = ClosedLoopSolver(machine).forward_batch(sliders)
    for k, values in enumerate(sliders):
        single = ClosedLoopSolver(machine).forward(values, q_init=machine.home)
        np.testing.assert_allclose(batch.task_poses[k], single.task_pose.homogeneous, atol=1e-10)


def test_a_singular_row_names_the_threshold_of_the_solver_s_rules(mechanism):
    """Every converged row is singular under a threshold no configuration meets; the reason names it."""
    for native in (True, False):
        solver = ClosedLoopSolver(mechanism, native=native, rules=NewtonRules(singular_rcond=2.0))
        batch = solver.forward_batch(mechanism.home[mechanism.actuated_ids][None, :] + 1e-3)
        (failure,) = batch.failures
        assert failure.error is SingularConfigurationError
        assert "(reciprocal condition below 2)" in failure.reason
