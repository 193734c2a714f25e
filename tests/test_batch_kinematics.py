"""Batched closed-loop kinematics (`ClosedLoopSolver.forward_batch` / `inverse_batch`) against the single solves."""

import dataclasses
import re

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
)
from m3t1r.model import batch_kinematics as bk
from m3t1r.model.description import Mechanism
from m3t1r.model.design import NOMINAL
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.newton_rules import NewtonRules
from m3t1r.model.rotations import rpy_batch
from m3t1r.model.task import TaskSpec


def workspace_poses(n: int, seed: int) -> np.ndarray:
    return NOMINAL.workspace.sample(np.random.default_rng(seed), n)


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


# ==================================================================================================
# Batches row by row: the typed failure rows with their reason text, the predictor from home, the task
# frame apart from the platform, and the input checks. Each row is a single solve's Newton (the same
# closure rows, rules and branch labels), so these tests check what a batch adds.
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
# Typed failure rows


def test_failures_of_reasons_and_error_classes():
    n = 6
    solved = bk.SolvedRows(
        np.zeros((n, 2)),
        np.array([0, 1, 2, 3, 4, 5]),
        np.array([0.0, 0.5, 2e-7, 1e-13, 3e-14, 0.0]),
        np.array([3, 0, 60, 7, 8, 2]),
        np.zeros((n, 4, 4)),
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
    assert solver.layout.task_frame != solver.layout.platform_frame
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
    assert list(ik.iterations) == [0, 3, 4] and list(cold.iterations) == [0, 3, 4]  # home: converged at once


# ---------------------------------------------------------------------------------------------
# forward_batch / inverse_batch


def test_forward_batch_slider_limits_are_inclusive_and_named(five_bar):
    """Limits [1.83, 2.83] and [0.31, 1.31]: a row at a limit is solved; beyond, the first slider
    beyond its limit is named; the rows keep their input order."""
    solver = ClosedLoopSolver(five_bar)
    sliders = np.array([[2.33, 0.3], [2.33, 1.4], [1.7, 1.4], [1.83, 0.81], [2.33, 0.81], [2.83, 0.31]])
    batch = solver.forward_batch(sliders)
    assert list(batch.indices) == [3, 4, 5] and list(batch.iterations) == [3, 1, 4]
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


@pytest.mark.parametrize("compiled", [True, False])
def test_a_row_the_third_order_start_loses_is_solved_from_the_first_order_one(mechanism, compiled):
    """Sliders near the M machine's URDF limits, outside its workspace: from home's third-order start
    Newton crosses a singularity (status 4, another branch); the batch solves such a row again from
    the first-order start, the single solve's from home, and returns that solve's solution, its
    predicted start counted as one step."""
    solver, home = ClosedLoopSolver(mechanism, native=compiled), mechanism.home
    sliders = np.array([[-0.392, -0.179, 0.436, -0.483], [0.572, -0.307, 0.244, -0.491]])
    start = np.repeat(home[None], 2, axis=0)
    start[:, solver.actuated] = sliders
    start[:, solver.passive] += solver.predict_from_home(sliders - home[solver.actuated])
    reference = solver.home_reference()
    assert reference is not None and list(solver.solve_rows(start, reference[1], 1).status) == [4, 4]
    batch = solver.forward_batch(sliders)
    assert batch.complete
    for row, values in enumerate(sliders):
        single = ClosedLoopSolver(mechanism, native=compiled).forward(values, q_init=home)
        np.testing.assert_allclose(batch.q[row], single.q, atol=1e-12)
        assert batch.iterations[row] == single.iterations + 1
    # From this one's third-order start Newton converges on another branch: held to home's, refused.
    other = np.array([[0.0086, -0.0357, 0.4981, -0.5907]])
    start = np.repeat(home[None], 1, axis=0)
    start[:, solver.actuated] = other
    start[:, solver.passive] += solver.predict_from_home(other - home[solver.actuated])
    assert list(solver.solve_rows(start, None, 1).status) == [0]  # labels at its start: assembled
    assert [f.error for f in solver.forward_batch(other).failures] == [BranchChangeError]


def test_forward_batch_every_row_beyond_its_limits(five_bar):
    batch = ClosedLoopSolver(five_bar).forward_batch(np.array([[2.33, 0.3], [3.0, 0.8]]))
    assert batch.n == 2 and len(batch.indices) == 0 and batch.indices.dtype.kind == "i"
    # q keeps its width nq when no row converged (it was (0, 0) before the fix).
    assert batch.poses.shape == (0, 4, 4) and batch.q.shape == (0, 4) and batch.residuals.shape == (0,)
    assert batch.iterations.shape == (0,) and [f.index for f in batch.failures] == [0, 1]
    assert list(batch.ok) == [False, False]


@pytest.mark.parametrize("compiled", [True, False])
def test_forward_batch_predictor_from_home_and_given_starts(five_bar, compiled):
    """From home the third-order prediction is step 1 (home itself: converged at 1); from q_init = home,
    plain Newton. Both end on the same poses; q_init is neither modified nor shared. Both Newton loops."""
    solver = ClosedLoopSolver(five_bar, native=compiled)
    sliders = np.array([[2.73, 0.41], [2.9, 0.8], [1.93, 1.21], [2.33, 0.81]])
    predicted = solver.forward_batch(sliders)
    assert list(predicted.indices) == [0, 2, 3] and list(predicted.iterations) == [3, 3, 1]
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
    _, jac, _ = solver.closure_sensitivity(five_bar.home)
    tangent, branch = solver.home_reference()
    passive, actuated = solver.passive, solver.actuated
    np.testing.assert_allclose(tangent, -np.linalg.solve(jac[:, passive], jac[:, actuated]), atol=1e-14)
    signs = [int(np.linalg.det(jac[np.ix_(r, c)]) > 0) for r, c in solver.branch_blocks]
    assert branch == bytes(signs)
    assert solver.home_reference()[0] is tangent  # computed once


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
        rf"inverse kinematics: {re.escape(ASSEMBLE)} \(residual (\S+) after 60 iterations\)", ik.failures[0].reason
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


def test_inverse_batch_slider_limits_are_inclusive(five_bar):
    """A target whose solution puts motor_1 exactly at its lower limit and motor_2 exactly at its
    upper one (the limits moved to home's values) is solved, as forward_batch and the single solve
    accept those sliders."""
    model = five_bar.model.copy()
    model.lowerPositionLimit[0], model.upperPositionLimit[2] = five_bar.home[0], five_bar.home[2]
    machine = five_bar.with_model(model)
    solver = ClosedLoopSolver(machine)
    sliders = five_bar.home[[0, 2]]
    # The limits are copies of home's values: the solution sits at them, not within rounding of them.
    assert solver.layout.actuator_lower[0] == sliders[0] and solver.layout.actuator_upper[1] == sliders[1]
    assert solver.forward_batch(sliders[None]).complete
    target = solver.forward(sliders).pose.translation[:2]
    single = solver.inverse(target)
    ik = solver.inverse_batch(target[None])
    assert ik.complete and ik.failures == () and list(ik.iterations) == [single.iterations]
    np.testing.assert_allclose(ik.actuators[0], single.actuators, atol=1e-12)


def test_inverse_batch_with_a_full_rotation_task(wrist):
    solver = ClosedLoopSolver(wrist)
    sliders = wrist.home[[0, 3, 6]] + np.array([[0.0, 0.0, 0.0], [0.1, -0.1, 0.05], [0.2, 0.1, -0.2]])
    fk = solver.forward_batch(sliders)
    assert list(fk.iterations) == [1, 3, 3]
    assert list(solver.forward_batch(sliders, q_init=wrist.home).iterations) == [0, 4, 4]
    quaternions = np.array([pin.Quaternion(p[:3, :3]).coeffs() for p in fk.poses])
    ik = solver.inverse_batch(quaternions)
    assert ik.complete and list(ik.iterations) == [0, 4, 4]
    np.testing.assert_allclose(ik.actuators, sliders, atol=1e-12)
    np.testing.assert_allclose(ik.poses, fk.poses, atol=1e-12)
    assert np.abs(rpy_batch(fk.poses[:, :3, :3])[2, :2]).min() > 0.15  # the goal has roll and pitch
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
    with pytest.raises(InvalidInputError) as caught:
        solver.forward_batch(sliders, q_init=[["a", 0.0, 0.0, 0.0]])
    assert str(caught.value) == "q_init: not numeric (could not convert string to float: 'a')"
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
    starts = bk.start_configurations(solver, 3, None)
    np.testing.assert_array_equal(starts, np.repeat(five_bar.home[None, :], 3, axis=0))
    starts[0, 0] = 9.0
    np.testing.assert_array_equal(bk.start_configurations(solver, 3, None)[0], five_bar.home)
    given = np.arange(8.0).reshape(2, 4)
    start = bk.start_configurations(solver, 2, given)
    start[0, 0] = 9.0
    assert given[0, 0] == 0.0  # a copy
    np.testing.assert_array_equal(bk.start_configurations(solver, 2, [1, 2, 3, 4]), [[1, 2, 3, 4], [1, 2, 3, 4]])
    assert bk.start_configurations(solver, 2, [1, 2, 3, 4]).dtype == float


def test_m_machine_iteration_counts_from_home(mechanism):
    """Position + yaw: IK from home is the single solve from home, step for step (the unreachable row
    runs its 60 steps); FK's predictor from home is counted as one step."""
    solver = ClosedLoopSolver(mechanism)
    targets = np.array([[0.55, 0.60, -0.10, 0.3], [0.5, 0.5, -0.1, 0.0], [0.3, 0.9, 0.0, -2.5], [0.6, 0.6, -0.1, 0.1]])
    ik = solver.inverse_batch(targets)
    assert list(ik.indices) == [0, 1, 3] and list(ik.iterations) == [4, 3, 4]
    assert ik.failures[0].index == 2 and ik.failures[0].reason.endswith("after 60 iterations)")
    cold = solver.inverse_batch(targets, q_init=mechanism.home)
    assert list(cold.iterations) == [4, 3, 4] and cold.failures[0].reason.endswith("after 60 iterations)")
    np.testing.assert_allclose(cold.actuators, ik.actuators, atol=1e-11)
    assert list(solver.forward_batch(ik.actuators).iterations) == [3, 2, 3]
    assert list(solver.forward_batch(ik.actuators, q_init=mechanism.home).iterations) == [4, 3, 4]
    np.testing.assert_allclose(ik.poses[:, :3, 3], targets[[0, 1, 3], :3], atol=1e-12)
    np.testing.assert_allclose(rpy_batch(ik.poses[:, :3, :3])[:, 2], targets[[0, 1, 3], 3], atol=1e-12)


def test_one_target_and_one_slider_set(mechanism, five_bar):
    ik = ClosedLoopSolver(mechanism).inverse_batch([[0.5, 0.5, -0.1, 0.0]])
    assert ik.complete and list(ik.indices) == [0] and ik.actuators.shape == (1, 4) and ik.tilt.shape == (1, 2)
    fk = ClosedLoopSolver(five_bar).forward_batch([[2.4, 0.9]])
    assert fk.complete and fk.poses.shape == (1, 4, 4) and fk.q.shape == (1, 4)


def test_batch_results_are_typed_arrays(five_bar):
    batch = ClosedLoopSolver(five_bar).forward_batch([[2.4, 0.9], [2.3, 0.7]])
    assert batch.residuals.dtype == float and batch.iterations.dtype.kind == "i" and batch.q.dtype == float
    assert batch.poses.dtype == float and batch.indices.dtype.kind == "i"
    assert all(not a.flags.writeable for a in (batch.indices, batch.poses, batch.q, batch.residuals, batch.iterations))


@pytest.mark.parametrize("compiled", [True, False])
def test_inverse_batch_of_a_yaw_task_on_a_frame_off_the_platform(five_bar, compiled):
    """The tool's x and heading (turned 0.4 rad from the effector): IK reaches them from home and from
    given starts (no step at a start that is the solution), in both Newton loops."""
    machine = with_tool(five_bar, TOOL_YAW)
    solver = ClosedLoopSolver(machine, native=compiled)
    sliders = five_bar.home[[0, 2]] + np.array([[0.0, 0.0], [0.05, 0.05], [-0.1, 0.2]])
    fk = solver.forward_batch(sliders)
    tool = fk.task_poses
    targets = np.c_[tool[:, 0, 3], np.arctan2(tool[:, 1, 0], tool[:, 0, 0])]
    ik = solver.inverse_batch(targets)
    assert ik.complete and ik.n == 3 and list(ik.ok) == [True] * 3
    np.testing.assert_allclose(ik.actuators, sliders, atol=1e-10)
    np.testing.assert_allclose(ik.poses, fk.poses, atol=1e-10)  # the platform's poses
    for k in range(3):
        single = ClosedLoopSolver(machine, native=compiled).inverse(targets[k], q_init=machine.home)
        assert ik.iterations[k] == single.iterations
    warm = solver.inverse_batch(targets, q_init=fk.q)
    assert list(warm.iterations) == [0, 0, 0]


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


def test_a_singular_ik_row_names_the_threshold_of_the_solver_s_rules(five_bar):
    """IK under a threshold no configuration meets: the row fails as the single solve does (its error
    class, after as many steps), and its reason names the solver's threshold, not the default's."""
    target = ClosedLoopSolver(five_bar).forward(five_bar.home[[0, 2]] + 1e-3).pose.translation[:2]
    for native in (True, False):
        solver = ClosedLoopSolver(five_bar, native=native, rules=NewtonRules(singular_rcond=2.0))
        with pytest.raises(SingularConfigurationError) as caught:
            solver.inverse(target)
        steps = re.search(r"after (\d+) iterations\)$", str(caught.value))
        assert steps is not None
        (failure,) = solver.inverse_batch(target[None]).failures
        assert failure.error is SingularConfigurationError
        assert re.fullmatch(
            r"inverse kinematics: singular configuration \(reciprocal condition below 2\) "
            rf"\(residual \S+ after {steps[1]} iterations\)",
            failure.reason,
        )
