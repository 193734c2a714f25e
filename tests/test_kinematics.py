"""Closed-loop kinematics against the closed form of docs/design.md, on nominal and perturbed machines."""

import dataclasses
import itertools
import math

import closed_form
import numpy as np
import pinocchio as pin
import pytest
from conftest import perturb_every_origin
from model_files import edit_text, edit_yaml, welded_double_hinge

from m3t1r.errors import BranchChangeError, InvalidInputError, KinematicsError, NotConvergedError, OutOfWorkspaceError
from m3t1r.model.description import Mechanism
from m3t1r.model.design import NOMINAL
from m3t1r.model.examples import FiveBarGeometry, five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver, yaw_of
from m3t1r.model.newton_rules import NewtonRules


def workspace_poses(n: int, seed: int) -> np.ndarray:
    return NOMINAL.workspace.sample(np.random.default_rng(seed), n)


def test_closed_form_is_self_consistent():
    for pose in workspace_poses(20, 1):
        np.testing.assert_allclose(closed_form.forward(closed_form.inverse(pose)), pose, atol=1e-12)


def test_home_matches_the_design_note(solver, mechanism):
    fk = solver.forward(np.zeros(4))
    expected_z = NOMINAL.l_u * math.sin(NOMINAL.alpha) - NOMINAL.l_d * math.sin(NOMINAL.beta)
    np.testing.assert_allclose(fk.pose.translation, [0.5, 0.03 + 0.7 * math.cos(math.pi / 4), expected_z], atol=1e-12)
    assert abs(fk.yaw) < 1e-14
    np.testing.assert_allclose(fk.q, mechanism.home, atol=1e-12)


@pytest.mark.parametrize("all_rows,rows", [(False, 16), (True, 24)])
def test_mobility_is_four_and_rank_sixteen(solver, all_rows, rows):
    configurations = [solver.mechanism.home]
    for pose in workspace_poses(20, 2):
        configurations.append(solver.forward(closed_form.inverse(pose), q_init=solver.mechanism.home).q)
    for q in configurations:
        jac = solver.closure_jacobian(q, all_rows=all_rows)
        assert jac.shape == (rows, 20)
        assert np.linalg.matrix_rank(jac, tol=1e-9 * np.linalg.norm(jac, 2)) == 16
        assert solver.mobility(q, all_rows=all_rows) == 4
        # The redundant rows hold by themselves at the nominal geometry.
        assert np.max(np.abs(solver.closure_residual(q, all_rows=True))) < 1e-12


def test_forward_matches_closed_form_and_stays_3t1r(solver):
    for pose in workspace_poses(60, 3):
        sliders = closed_form.inverse(pose)
        fk = solver.forward(sliders, q_init=solver.mechanism.home)
        assert fk.residual <= 1e-12
        np.testing.assert_allclose(np.r_[fk.pose.translation, fk.yaw], closed_form.forward(sliders), atol=1e-10)
        np.testing.assert_allclose(np.r_[fk.pose.translation, fk.yaw], pose, atol=1e-10)
        roll, pitch = fk.roll_pitch
        assert abs(roll) < 1e-12 and abs(pitch) < 1e-12


def test_forward_of_inverse_is_identity(solver):
    for pose in workspace_poses(60, 4):
        ik = solver.inverse(pose, q_init=solver.mechanism.home)
        np.testing.assert_allclose(ik.actuators, closed_form.inverse(pose), atol=1e-10)
        fk = solver.forward(ik.actuators, q_init=solver.mechanism.home)
        np.testing.assert_allclose(np.r_[fk.pose.translation, fk.yaw], pose, atol=1e-10)
        assert max(map(abs, ik.tilt)) < 1e-12


def test_inverse_accepts_an_se3_and_reports_requested_tilt(solver):
    target = pin.SE3(pin.rpy.rpyToMatrix(0.01, -0.02, 0.3), np.array([0.5, 0.5, -0.1]))
    ik = solver.inverse(target)
    np.testing.assert_allclose(ik.pose.translation, target.translation, atol=1e-12)
    assert abs(yaw_of(ik.pose.rotation) - yaw_of(target.rotation)) < 1e-12
    np.testing.assert_allclose(ik.tilt, (-0.01, 0.02), atol=1e-12)


def test_warm_started_path_stays_on_one_branch(solver):
    t = np.linspace(0, 1, 250)[:, None]
    start, end = np.array([0.42, 0.25, -0.2, -0.7]), np.array([0.58, 0.8, -0.02, 0.7])
    path = start + t * (end - start)
    solver.forward(closed_form.inverse(path[0]), q_init=solver.mechanism.home)
    for pose in path:
        fk = solver.forward(closed_form.inverse(pose))
        assert fk.iterations <= 3
        np.testing.assert_allclose(np.r_[fk.pose.translation, fk.yaw], pose, atol=1e-10)
    for pose in path[::-1]:
        ik = solver.inverse(pose)
        np.testing.assert_allclose(ik.actuators, closed_form.inverse(pose), atol=1e-10)


def test_closure_jacobian_matches_central_differences(solver):
    rng = np.random.default_rng(5)
    for _ in range(3):
        q = solver.mechanism.home + rng.normal(0, 0.05, 20)  # off the constraint manifold on purpose
        jac = solver.closure_jacobian(q)
        fd = np.zeros_like(jac)
        for k in range(20):
            e = np.zeros(20)
            e[k] = 1e-6
            fd[:, k] = (solver.closure_residual(q + e) - solver.closure_residual(q - e)) / 2e-6
        assert np.max(np.abs(jac - fd)) <= 1e-6 * np.max(np.abs(jac))
        full = solver.closure_jacobian(q, all_rows=True)
        fd_full = np.array(
            [
                (solver.closure_residual(q + e, True) - solver.closure_residual(q - e, True)) / 2e-6
                for e in np.eye(20) * 1e-6
            ]
        ).T
        assert np.max(np.abs(full - fd_full)) <= 1e-6 * np.max(np.abs(full))


def test_perturbed_machines_assemble_across_the_workspace(mechanism):
    """1 mm / 1 mrad on every joint origin, fixed ones included: only the 16 independent rows hold."""
    for seed in range(4):
        truth = mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(seed), 1e-3, 1e-3))
        solver = ClosedLoopSolver(truth)
        for pose in workspace_poses(15, 10 + seed):
            fk = solver.forward(closed_form.inverse(pose))
            assert fk.residual <= 1e-12
            # The machine is off by millimetres, not lost on another branch.
            assert np.linalg.norm(fk.pose.translation - pose[:3]) < 0.03
        redundant = np.max(np.abs(solver.closure_residual(fk.q, all_rows=True)))
        assert redundant > 1e-5, "with errors the redundant rows cannot all hold"


@pytest.mark.parametrize(
    "bad,message",
    [
        ([0.0, 0.0, np.nan, 0.0], "non-finite value nan at index 2"),
        ([0.0, 0.0, 0.0], "expected 4 values, got 3"),
        ([0.0, 700.0, 0.0, 0.0], r"actuator 'q11_B2' = 700 is beyond its joint limit \[-0.6, 0.6\]"),
        (["a", 0, 0, 0], "not a numeric vector"),
    ],
)
def test_forward_rejects_bad_actuators(solver, bad, message):
    with pytest.raises(InvalidInputError, match=message):
        solver.forward(bad)


def test_forward_that_cannot_assemble_is_loud(solver):
    # B2 - B1 beyond 2 l_u: the five-bar cannot close.
    with pytest.raises(OutOfWorkspaceError) as info:
        solver.forward([-0.3, 0.3, 0.0, 0.0])
    assert info.value.residual > 1e-6 and "residual" in str(info.value)


@pytest.mark.parametrize("target", [[0.5, 0.5, 0.9, 0.0], [3.0, 0.5, -0.1, 0.0]])
def test_inverse_out_of_reach_is_loud(solver, target):
    with pytest.raises(KinematicsError) as info:
        solver.inverse(target)
    assert info.value.residual > 1e-6


def test_inverse_that_would_cross_a_singularity_is_loud(solver):
    """Knees below the rails exist (the five-bar's other mode) but only past a flat, singular five-bar."""
    with pytest.raises(BranchChangeError):
        solver.inverse([0.5, 0.5, -0.9, 0.0])


def test_inverse_never_clips_a_slider(solver):
    # Reachable geometrically but needs a slider beyond 0.6 m.
    with pytest.raises(OutOfWorkspaceError, match="beyond its limit"):
        solver.inverse([0.5, 1.2, -0.1, 0.0])


@pytest.mark.parametrize("bad,message", [([0.5, 0.5, np.inf, 0.0], "non-finite"), ([0.5, 0.5], "expected 4 values")])
def test_inverse_rejects_bad_targets(solver, bad, message):
    with pytest.raises(InvalidInputError, match=message):
        solver.inverse(bad)


def test_yaw_convention():
    assert math.isclose(yaw_of(pin.rpy.rpyToMatrix(0.0, 0.0, 0.4)), 0.4)


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("tolerance", 2e-6, r"tolerance 2e-06: at most 1e-06 \(m, rad of closure residual\)"),
        ("tolerance", 0.0, "tolerance: expected a finite number above 0, got 0.0"),
        ("tolerance", float("nan"), "tolerance: expected a finite number above 0"),
        ("max_iterations", -1, "max_iterations"),
        ("max_iterations", 2.5, "max_iterations"),
    ],
)
def test_a_solver_refuses_the_same_settings_given_or_set_later(mechanism, name, value, message):
    """A tolerance looser than MAX_TOLERANCE would return open loops as solutions, whether it is
    given to the constructor or set afterwards; a refused setting leaves the solver as it was."""
    with pytest.raises(InvalidInputError, match=message):
        ClosedLoopSolver(mechanism, **{name: value})
    solver = ClosedLoopSolver(mechanism)
    before = getattr(solver, name)
    with pytest.raises(InvalidInputError, match=message):
        setattr(solver, name, value)
    assert getattr(solver, name) == before
    setattr(solver, name, 1e-9 if name == "tolerance" else 7)
    assert getattr(solver, name) == (1e-9 if name == "tolerance" else 7)


def test_warm_path_through_a_singularity_is_loud(solver):
    """Driving the knees down through the flat five-bar by small warm steps must not silently
    continue on the knees-below-the-rails branch."""
    solver.inverse([0.5, 0.5, -0.1, 0.0], q_init=solver.mechanism.home)
    knee = solver.model.idx_qs[solver.model.getJointId("q12")]
    with pytest.raises(KinematicsError):
        for z in np.linspace(-0.1, -0.9, 400):
            result = solver.inverse([0.5, 0.5, z, 0.0])
            assert result.q[knee] > 0.0, f"crossed to the other assembly mode at z = {z}"


def _path_from_home(mechanism, sliders: np.ndarray, steps: int = 10):
    """FK at `sliders` by a warm path of `steps` equal slider steps from home: the continuation that
    defines home's assembly mode (None where it fails)."""
    path = ClosedLoopSolver(mechanism)
    home = mechanism.home[mechanism.actuated_ids]
    try:
        for t in np.linspace(1.0 / steps, 1.0, steps):
            result = path.forward(home + t * (sliders - home))
    except KinematicsError:
        return None
    return result


def _machines(mechanism, tool_machine, tmp_path):
    # A five-bar whose motor box reaches to within a few degrees of its stretched-elbow singularity,
    # where the two assembly modes are close: a start on the wrong side of it is easy to make.
    stretched = FiveBarGeometry(distal=0.28)
    return {
        "M machine": mechanism,
        "tool machine": tool_machine,  # (machine, half-width of the slider window)
        "five-bar": Mechanism.load(*five_bar_files(tmp_path / "a")),
        "stretched five-bar": Mechanism.load(*five_bar_files(tmp_path / "b", geometry=stretched)),
        "spherical wrist": Mechanism.load(*spherical_wrist_files(tmp_path / "c")),
    }


@pytest.mark.parametrize("native", [True, False])
def test_a_fresh_solver_s_first_forward_is_the_path_from_home(mechanism, tool_machine, tmp_path, native):
    """On every mechanism: the first forward of a new solver, of a reset one and of forward(q_init=home)
    equal a warm path from home and forward_batch's row, on home's assembly mode; where the path
    from home fails, none of them returns a pose on another mode."""
    for name, machine in _machines(mechanism, tool_machine, tmp_path).items():
        low, high = machine.joint_limits()
        home = machine.home[machine.actuated_ids]
        width = 0.5 if name == "stretched five-bar" else 0.25  # [m or rad]
        low, high = np.maximum(low, home - width), np.minimum(high, home + width)
        sliders = low + np.random.default_rng(3).random((16, len(low))) * (high - low)
        batch = ClosedLoopSolver(machine, native=native).forward_batch(sliders)
        reset = ClosedLoopSolver(machine, native=native)
        agreed = 0
        for k, values in enumerate(sliders):
            path = _path_from_home(machine, values)
            reset.forward(home + 0.01)
            reset.reset()
            solves = []
            for solve in (
                lambda: ClosedLoopSolver(machine, native=native).forward(values),
                lambda: reset.forward(values),
                lambda: ClosedLoopSolver(machine, native=native).forward(values, q_init=machine.home),
            ):
                try:
                    solves.append(solve().q)
                except KinematicsError:
                    solves.append(None)
            if k in batch.indices:
                solves.append(batch.q[list(batch.indices).index(k)])
            for q in solves:
                if q is not None and path is not None:
                    np.testing.assert_allclose(q, path.q, atol=1e-9, err_msg=f"{name}, row {k}")
                assert q is None or path is not None, f"{name}, row {k}: a pose where the path from home has none"
            agreed += path is not None and all(q is not None for q in solves)
        assert agreed >= 8, name


def test_a_task_coordinate_the_mechanism_cannot_move_is_refused_by_name(tmp_path):
    """The five-bar moves in the x-y plane: a task (x, z) is square, but z never changes, so IK would
    end 'singular' at every target it converges to. It is refused naming z, before any solve;
    forward kinematics is unaffected, and the (x, y) task it can command solves."""
    import yaml

    from m3t1r.errors import InvalidInputError as Refused
    from m3t1r.model.description import Mechanism
    from m3t1r.model.examples import five_bar_files

    urdf, closures = five_bar_files(tmp_path)
    good = Mechanism.load(urdf, closures)
    document = yaml.safe_load(closures.read_text())
    document["task"]["position"] = ["x", "z"]
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    planar = Mechanism.load(urdf, closures)
    solver = ClosedLoopSolver(planar)
    assert solver.uncommandable_task_rows() == ("z",)
    fk = solver.forward(planar.home[planar.actuated_ids] + 0.01)
    target = fk.task_pose.translation[[0, 2]]
    for solve in (lambda: solver.inverse(target), lambda: solver.inverse_batch(target[None, :])):
        with pytest.raises(Refused, match=r"the task's z \(frame 'effector'\) cannot be commanded"):
            solve()
    commandable = ClosedLoopSolver(good)
    assert commandable.uncommandable_task_rows() == ()
    np.testing.assert_allclose(
        commandable.inverse(fk.task_pose.translation[:2]).actuators, planar.home[planar.actuated_ids] + 0.01, atol=1e-9
    )


@pytest.mark.parametrize("values", [[0.1 + 1j, 0.0, 0.0, 0.0], np.array([0.1, 0.0, 0.0, 0.0]) + 0j])
def test_a_complex_input_is_refused_not_read_as_its_real_part(solver, values):
    with pytest.raises(InvalidInputError, match="complex values given"):
        solver.forward(values)
    with pytest.raises(InvalidInputError, match="complex values given"):
        solver.forward_batch([values])


@pytest.mark.parametrize(
    "options,message",
    [
        ({"tolerance": math.inf}, "tolerance: expected a finite number above 0"),
        ({"tolerance": 1.0}, "at most 1e-06"),
        ({"tolerance": 0.0}, "above 0"),
        ({"tolerance": math.nan}, "finite number"),
        ({"max_iterations": -1}, "max_iterations: expected a whole number of at least 0"),
        ({"max_iterations": 2.5}, "whole number"),
    ],
)
def test_solver_options_that_would_pass_open_loops_as_solutions_are_refused(mechanism, options, message):
    """tolerance=inf or 1.0 returned home's neighbours as 'solved' after 0 iterations, loops 0.5 open."""
    with pytest.raises(InvalidInputError, match=message):
        ClosedLoopSolver(mechanism, **options)


# ===========================================================================================


# Yaw wrap, tolerance boundaries, warm starts and the solver's typed errors
# ==================================================================================================


TARGET = np.array([0.55, 0.60, -0.10, 0.3])


@pytest.mark.parametrize("turns", [1, -1, 2])
def test_inverse_wraps_a_yaw_target_beyond_pi(mechanism, turns):
    """theta + 2 k pi is the same heading: cold IK lands on the same sliders, not OutOfWorkspaceError."""
    reference = ClosedLoopSolver(mechanism).inverse(TARGET)
    wrapped = ClosedLoopSolver(mechanism).inverse(TARGET + [0.0, 0.0, 0.0, 2 * math.pi * turns])
    np.testing.assert_allclose(wrapped.actuators, reference.actuators, atol=1e-10)
    assert yaw_of(wrapped.pose.rotation) == pytest.approx(0.3, abs=1e-10)
    assert wrapped.residual <= 1e-12


def test_warm_inverse_predictor_wraps_the_yaw_change(mechanism):
    """The warm predictor steps by the wrapped yaw change: 0.3 -> 0.35 + 2 pi is a 0.05 rad move."""
    solver = ClosedLoopSolver(mechanism)
    solver.inverse(TARGET)
    warm = solver.inverse(TARGET + [0.01, 0.0, 0.0, 0.05 + 2 * math.pi])
    cold = ClosedLoopSolver(mechanism).inverse(TARGET + [0.01, 0.0, 0.0, 0.05])
    np.testing.assert_allclose(warm.actuators, cold.actuators, atol=1e-10)
    assert warm.iterations <= 3  # the predictor did its job: a neighbour, not a 2 pi jump


def test_se3_target_with_nan_is_refused(solver):
    target = pin.SE3(np.eye(3), np.array([0.5, 0.5, np.nan]))
    with pytest.raises(InvalidInputError, match="non-finite"):
        solver.inverse(target)


def test_forward_tolerance_is_met_and_iterations_are_bounded(mechanism):
    solver = ClosedLoopSolver(mechanism, tolerance=1e-12)
    ik = ClosedLoopSolver(mechanism).inverse(TARGET)
    fk = solver.forward(ik.actuators, q_init=mechanism.home)
    assert 0 < fk.iterations <= 10 and fk.residual <= 1e-12
    np.testing.assert_allclose(fk.pose.translation, TARGET[:3], atol=1e-10)


def test_too_few_iterations_is_not_converged_not_out_of_workspace(mechanism):
    """Newton stopped early close to a solution (residual <= 1e-6) is NotConverged, far is OutOfWorkspace."""
    ik = ClosedLoopSolver(mechanism).inverse(TARGET)
    with pytest.raises(OutOfWorkspaceError):
        ClosedLoopSolver(mechanism, max_iterations=0).forward(ik.actuators, q_init=mechanism.home)
    # Start within a micrometre of the solution: one Newton step short of the tolerance.
    start = ik.q.copy()
    start[mechanism.passive_ids] += 1e-8
    with pytest.raises(NotConvergedError) as caught:
        ClosedLoopSolver(mechanism, tolerance=1e-300, max_iterations=1).forward(ik.actuators, q_init=start)
    assert caught.value.residual <= 1e-6


# --------------------------------------------------------------------------------------------------
# Block patterns, quadratic convergence of a cold inverse, closure sizes, named bad configurations


@pytest.mark.parametrize(
    "target, most", [((0.55, 0.6, -0.1, 0.3), 6), ((0.45, 0.3, -0.2, -0.6), 8), ((0.58, 0.8, -0.02, 0.7), 7)]
)
def test_cold_inverse_converges_quadratically(mechanism, target, most):
    """Exact Newton from home: a wrong yaw-row Jacobian still converges, but in more steps."""
    assert ClosedLoopSolver(mechanism).inverse(target).iterations <= most


def test_every_row_of_every_closure_in_closure_order(mechanism):
    """closure_residual(all_rows=True): 3 rows R_a^T (p_b - p_a) per 3D closure and 6 rows log6(aMb)
    per 6D one, in the closures file's order, from the frames' placements at q."""
    model, q = mechanism.model, mechanism.home + 0.01
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    expected = []
    for spec in mechanism.closures:
        oMa, oMb = data.oMf[spec.frame_a_id], data.oMf[spec.frame_b_id]
        if spec.type == "3D":
            expected.append(oMa.rotation.T @ (oMb.translation - oMa.translation))
        else:
            expected.append(pin.log6(oMa.actInv(oMb)).vector)
    types = {spec.name: spec.type for spec in mechanism.closures}
    assert types["platform"] == "6D" and types["five_bar_I"] == "3D"
    residual = ClosedLoopSolver(mechanism).closure_residual(q, all_rows=True)
    assert residual.shape == (sum(len(rows) for rows in expected),)
    np.testing.assert_allclose(residual, np.concatenate(expected), atol=1e-15)


def test_bad_configuration_is_named(solver, mechanism):
    with pytest.raises(InvalidInputError, match="configuration q"):
        solver.closure_residual(np.full(mechanism.model.nq, np.nan))
    with pytest.raises(InvalidInputError, match="configuration q"):
        solver.closure_jacobian(np.zeros(3))
    assert solver.mobility(mechanism.home, all_rows=True) == 4


# ------------------------------------------------------------------------------------------------
# Rehoming, the batch methods and the pieces the calibration relies on
def test_rehomed_assembles_home_at_the_given_sliders_and_keeps_everything_else(mechanism):

    from m3t1r.model.kinematics import rehomed

    perturbed = mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(3), 1e-3, 1e-3))
    assert np.linalg.norm(ClosedLoopSolver(perturbed).closure_residual(perturbed.home)) > 1e-5
    for sliders in (None, mechanism.home[mechanism.actuated_ids] + [0.01, -0.01, 0.02, 0.0]):
        moved = rehomed(perturbed, sliders)
        expected = perturbed.home[perturbed.actuated_ids] if sliders is None else sliders
        np.testing.assert_allclose(moved.home[moved.actuated_ids], expected, atol=0.0)
        assert np.linalg.norm(ClosedLoopSolver(moved).closure_residual(moved.home)) < 1e-12
        assert moved.model is perturbed.model and moved.visual_model is perturbed.visual_model
        assert moved.closures == perturbed.closures and moved.actuated_joints == perturbed.actuated_joints
        assert moved.principal_chains == perturbed.principal_chains
        assert moved.platform_frame == perturbed.platform_frame
        assert (moved.urdf_path, moved.closures_path) == (perturbed.urdf_path, perturbed.closures_path)
    # On the branch of the old home: the passive joints move by about the perturbation, not a flip.
    assert np.max(np.abs(rehomed(perturbed).home - perturbed.home)) < 0.2


def test_closure_sensitivity_is_the_residual_jacobian_and_row_operator(solver, mechanism):
    q = ClosedLoopSolver(mechanism).forward(mechanism.home[mechanism.actuated_ids] + 0.02).q
    residual, jacobian, operator = solver.closure_sensitivity(q)
    np.testing.assert_array_equal(residual, solver.closure_residual(q))
    np.testing.assert_allclose(jacobian, solver.closure_jacobian(q), atol=1e-15)
    assert operator.shape == (len(residual), 6)
    start = 0  # each closure's rows: the operator on the relative spatial twist of its two frames
    for closure in mechanism.closures:
        frame_b, frame_a = (
            pin.getFrameJacobian(solver.model, solver.data, f, pin.WORLD)
            for f in (closure.frame_b_id, closure.frame_a_id)
        )
        rows = slice(start, start + len(closure.rows))
        np.testing.assert_allclose(operator[rows] @ (frame_b - frame_a), jacobian[rows], atol=1e-15)
        start = rows.stop
    assert start == len(residual)
    with pytest.raises(InvalidInputError, match=r"configuration q: expected \d+ values, got 3"):
        solver.closure_sensitivity(np.zeros(3))


def test_batch_solves_equal_the_solves_from_home(mechanism):
    solver = ClosedLoopSolver(mechanism)
    targets = np.array([TARGET, TARGET + [0.02, -0.03, 0.01, -0.2], TARGET + [0.04, 0.05, -0.02, 0.4]])
    inverse = solver.inverse_batch(targets)
    np.testing.assert_array_equal(inverse.indices, [0, 1, 2])
    for k, target in enumerate(targets):
        single = ClosedLoopSolver(mechanism).inverse(target, q_init=mechanism.home)
        np.testing.assert_allclose(inverse.actuators[k], single.actuators, atol=1e-10)
    forward = solver.forward_batch(inverse.actuators)
    for k, actuators in enumerate(inverse.actuators):
        single = ClosedLoopSolver(mechanism).forward(actuators, q_init=mechanism.home)
        np.testing.assert_allclose(forward.poses[k], single.pose.homogeneous, atol=1e-10)
    # Explicit starts are used: a start at the first solution gives the same answers.
    start = ClosedLoopSolver(mechanism).inverse(targets[0]).q
    np.testing.assert_allclose(solver.inverse_batch(targets, q_init=start).actuators, inverse.actuators, atol=1e-10)
    np.testing.assert_allclose(solver.forward_batch(inverse.actuators, q_init=start).poses, forward.poses, atol=1e-10)
    np.testing.assert_array_equal(solver.last_q, mechanism.home)  # the warm start is left alone


def test_reset_forgets_every_warm_start(mechanism):
    solver = ClosedLoopSolver(mechanism)
    solver.inverse(TARGET)
    solver.forward(solver.last_q[solver.actuated] + 0.01)
    solver.inverse(TARGET + [0.01, 0.0, 0.0, 0.05])
    solver.reset()
    for name in ("previous", "task_inverse", "inverse_previous", "goal", "inverse_branch", "task"):
        assert getattr(solver.warm, name) is None, name
    np.testing.assert_array_equal(solver.last_q, mechanism.home)
    # What is left is a new solver's start: home's tangent and branch, the batch's first step.
    sliders = mechanism.home[solver.actuated] + 0.01
    after_reset, fresh = solver.forward(sliders), ClosedLoopSolver(mechanism).forward(sliders)
    np.testing.assert_allclose(after_reset.q, fresh.q, atol=1e-12)
    assert after_reset.iterations == fresh.iterations
    solver.reset()
    solver.last_q[0] += 1.0  # a copy: home itself is untouched
    assert mechanism.home[0] != solver.last_q[0]


def test_mobility_counts_rows_and_singular_values_as_documented(mechanism):

    from m3t1r.model.kinematics import rehomed

    perturbed = rehomed(
        mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(3), 1e-3, 1e-3))
    )
    solver = ClosedLoopSolver(perturbed)
    assert solver.mobility(perturbed.home) == 4  # enforced rows by default
    assert solver.mobility(perturbed.home, all_rows=True) == 0  # the redundant rows no longer are
    nominal = ClosedLoopSolver(mechanism)
    singular = np.linalg.svd(nominal.closure_jacobian(mechanism.home), compute_uv=False)
    for rank_tolerance in (0.1, 0.28):
        expected = mechanism.model.nv - int(np.sum(singular > rank_tolerance * singular[0]))
        assert nominal.mobility(mechanism.home, rank_tolerance=rank_tolerance) == expected


def test_check_actuators_limits_are_inclusive_and_a_copy(solver):
    lower, upper = (np.array(limit, dtype=float) for limit in solver.mechanism.joint_limits())
    for values in (lower, upper):
        checked = solver.check_actuators(values)
        np.testing.assert_array_equal(checked, values)
        assert checked is not values
        checked[0] += 1.0
        assert checked[0] != values[0]  # a copy, not a view of the caller's array
        np.testing.assert_array_equal(solver.check_actuators(values.tolist()), values)
    beyond = upper.copy()
    beyond[2] = np.nextafter(upper[2], np.inf)
    for given in (beyond, beyond.tolist()):
        with pytest.raises(InvalidInputError) as caught:
            solver.check_actuators(given)
        assert str(caught.value) == (
            f"actuator 'q21' = {beyond[2]:.6g} is beyond its joint limit "
            f"[{lower[2]:.6g}, {upper[2]:.6g}] (SI units: metres for sliders)"
        )
    with pytest.raises(InvalidInputError) as caught:
        solver.check_actuators([0.1, 0.2])
    assert str(caught.value) == "actuator values: expected 4 values, got 2"


def test_refusals_name_their_argument_word_for_word(solver, mechanism):
    nq = mechanism.model.nq
    for call in (solver.closure_residual, solver.closure_jacobian):
        with pytest.raises(InvalidInputError) as caught:
            call(np.zeros(3))
        assert str(caught.value) == f"configuration q: expected {nq} values, got 3"
    sliders = mechanism.home[mechanism.actuated_ids]
    for call, argument in ((solver.forward, sliders), (solver.inverse, TARGET)):
        with pytest.raises(InvalidInputError) as caught:
            call(argument, q_init=np.zeros(3))
        assert str(caught.value) == f"q_init: expected {nq} values, got 3"
    with pytest.raises(InvalidInputError) as caught:
        solver.inverse(pin.SE3(np.eye(3), np.array([0.5, 0.5, np.nan])))
    assert str(caught.value) == "target pose: non-finite value"
    with pytest.raises(InvalidInputError) as caught:
        solver.inverse(TARGET[:3])
    assert str(caught.value) == "target (x, y, z, theta): expected 4 values, got 3"


def test_an_explicit_start_at_the_solution_needs_no_step(mechanism):
    solver = ClosedLoopSolver(mechanism)
    solution = solver.inverse(TARGET)
    solver.inverse(TARGET + [0.05, 0.05, 0.0, 0.2])
    assert solver.inverse(TARGET, q_init=solution.q).iterations == 0
    forward = solver.forward(solution.actuators)
    solver.forward(solution.actuators + 0.02)
    assert solver.forward(solution.actuators, q_init=forward.q).iterations == 0


def test_warm_forward_along_a_curved_path_uses_the_second_order_predictor(mechanism):
    """Measured: 29 Newton steps over the path (39 with a first-order predictor only, 57 without
    any): a slack of 2 for rounding."""
    start = mechanism.home[mechanism.actuated_ids]
    solver = ClosedLoopSolver(mechanism)
    steps = []
    for k in range(12):
        sliders = start + 0.01 * k * np.array([1.0, 0.8, -0.6, 0.4]) + 0.002 * k * k * np.array([1.0, -1.0, 0.5, 0.2])
        result = solver.forward(sliders)
        steps.append(result.iterations)
        cold = ClosedLoopSolver(mechanism).forward(sliders, q_init=mechanism.home)
        np.testing.assert_allclose(result.q, cold.q, atol=1e-9)
    assert sum(steps) <= 31, steps


def test_warm_inverse_along_a_curved_path_reuses_its_factors(mechanism):
    """Measured: 30 Newton steps over the path (40 with a first-order predictor only, 75 without the
    last solution's factors): a slack of 2."""
    solver = ClosedLoopSolver(mechanism)
    steps = []
    for k in range(12):
        target = (
            TARGET + 0.002 * k * np.array([2.0, 1.5, -1.0, 10.0]) + 0.0005 * k * k * np.array([1.0, -1.0, 0.5, 2.0])
        )
        result = solver.inverse(target)
        steps.append(result.iterations)
        np.testing.assert_allclose(result.actuators, ClosedLoopSolver(mechanism).inverse(target).actuators, atol=1e-9)
    assert sum(steps) <= 32, steps


@pytest.mark.parametrize(
    "target, most", [((0.55, 0.6, -0.1, 0.3), 9), ((0.45, 0.3, -0.2, -0.6), 8), ((0.58, 0.8, -0.02, 0.7), 8)]
)
def test_cold_inverse_of_a_tilting_machine_converges_quadratically(mechanism, target, most):
    """A perturbed machine tilts its platform by 0.05-0.14 rad: the yaw row's Jacobian terms in the
    tilt (c_z) count. Measured 8, 7, 7 steps; one of slack."""

    from m3t1r.model.kinematics import rehomed

    tilting = rehomed(mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(5), 2e-3, 2e-2)))
    result = ClosedLoopSolver(tilting).inverse(np.array(target))
    assert result.residual <= 1e-12 and max(abs(t) for t in result.tilt) > 0.05
    assert result.iterations <= most


def test_newton_failures_say_why_word_for_word(mechanism):
    with pytest.raises(OutOfWorkspaceError) as caught:
        ClosedLoopSolver(mechanism).inverse(np.array([3.0, 3.0, 1.0, 0.0]))
    assert str(caught.value).startswith(
        "the closures cannot be assembled here (target out of the workspace or too far from the initial "
        "configuration's branch) (residual "
    )
    assert caught.value.iterations == 60 and caught.value.residual > 1.0
    ik = ClosedLoopSolver(mechanism).inverse(TARGET)
    start = ik.q.copy()
    start[mechanism.passive_ids] += 1e-8
    with pytest.raises(NotConvergedError) as caught:
        ClosedLoopSolver(mechanism, tolerance=1e-300, max_iterations=1).forward(ik.actuators, q_init=start)
    assert str(caught.value).startswith("Newton did not reach the tolerance (residual ")
    assert caught.value.iterations == 1 and 0.0 < caught.value.residual <= 1e-6


def test_block_structure_of_the_passive_system_from_a_cold_cache(mechanism):
    """The five-bars and the platform loop: four 2 x 2 blocks and one 8 x 8, found from scratch."""
    from m3t1r.model import branches

    key = (mechanism.closures, mechanism.actuated_joints, tuple(mechanism.model.names))
    saved = branches._BLOCK_CACHE.pop(key, None)
    try:
        blocks = ClosedLoopSolver(mechanism).branch_blocks
    finally:
        if saved is not None:
            branches._BLOCK_CACHE[key] = saved
    found = sorted((sorted(r.tolist()), sorted(c.tolist())) for r, c in blocks)
    assert found == [
        ([0, 1], [2, 7]),
        ([2, 3], [1, 9]),
        ([4, 5, 10, 11, 12, 13, 14, 15], [3, 4, 5, 6, 13, 14, 15, 16]),
        ([6, 7], [12, 17]),
        ([8, 9], [11, 19]),
    ]


def test_returned_poses_do_not_move_with_later_solves(mechanism):
    """FK and IK hand out their own placements: the solver's next solves leave them as they were."""
    solver = ClosedLoopSolver(mechanism)
    sliders = mechanism.home[mechanism.actuated_ids]
    forward = solver.forward(sliders + 0.01)
    inverse = solver.inverse(TARGET)
    kept = forward.pose.homogeneous.copy(), inverse.pose.homogeneous.copy()
    solver.forward(sliders - 0.02)
    solver.inverse(TARGET + [0.02, 0.0, 0.0, 0.1])
    np.testing.assert_array_equal(forward.pose.homogeneous, kept[0])
    np.testing.assert_array_equal(inverse.pose.homogeneous, kept[1])


def test_a_failed_inverse_leaves_a_usable_warm_start(mechanism):
    """A failed solve drops its factors and branch: the next warm solve starts from the last good one."""
    solver = ClosedLoopSolver(mechanism)
    solver.inverse(TARGET)
    with pytest.raises(OutOfWorkspaceError):
        solver.inverse(np.array([3.0, 3.0, 1.0, 0.0]))
    near = TARGET + [0.01, 0.0, 0.0, 0.05]
    np.testing.assert_allclose(
        solver.inverse(near).actuators, ClosedLoopSolver(mechanism).inverse(near).actuators, atol=1e-10
    )


# ------------------------------------------------------------------------------------------------
# The predictor's bounds, the batch methods' q_init


def test_predictor_second_order_term_only_for_0_lt_lambda_lt_2(mechanism):
    """With T = 0 the prediction is lam^2 (q_prev - q_last) exactly while 0 < lam < 2, else nothing;
    a repeated slider set (e = 0) has no direction: nothing either."""
    solver = ClosedLoopSolver(mechanism)
    sliders, passive = solver.last_q[solver.actuated], solver.last_q[solver.passive]
    e = np.array([2.0**-7, -(2.0**-6), 2.0**-8, 2.0**-7])  # binary fractions: dot products without rounding
    offset = np.linspace(-0.01, 0.02, len(passive))  # q_prev - q_last on the passive joints
    tangent = np.zeros((len(passive), len(sliders)))
    previous = (sliders - e, passive + offset)  # the solution before the start, home
    # Binary fractions make lam = d.e / e.e exact on every BLAS kernel (with decimal steps its
    # rounding left 1e-38 where 'nothing' is expected), so the expected terms hold exactly.
    for lam, expected in ((0.5, 0.25), (1.0, 1.0), (1.5, 2.25), (0.0, 0.0), (2.0, 0.0), (2.5, 0.0), (-0.5, 0.0)):
        change = lam * e if lam else np.array([2.0**-6, 2.0**-7, 0.0, 0.0])  # orthogonal to e, exactly
        np.testing.assert_allclose(
            solver.predict(solver.last_q, change, tangent, previous),
            expected * offset,
            rtol=1e-12,
            atol=0.0,
            err_msg=str(lam),
        )
    np.testing.assert_allclose(solver.predict(solver.last_q, e, tangent, None), np.zeros(len(passive)), atol=0.0)
    # The same sliders twice: e = 0, no direction.
    np.testing.assert_array_equal(
        solver.predict(solver.last_q, e, tangent, (sliders, passive + offset)), np.zeros(len(passive))
    )


def test_batch_methods_pass_q_init_on(solver, mechanism):
    """An explicit start reaches the batch solvers: a wrong one is refused there, by shape."""
    sliders = mechanism.home[mechanism.actuated_ids][None, :]
    nq = mechanism.model.nq
    for call, rows in ((solver.forward_batch, sliders), (solver.inverse_batch, TARGET[None, :])):
        with pytest.raises(InvalidInputError) as caught:
            call(rows, q_init=np.zeros(3))
        assert str(caught.value) == f"q_init: expected finite ({nq},) or (1, {nq}) values, got shape (3,)"


def test_inverse_of_a_full_rotation_task_commands_roll_and_pitch(tmp_path):
    """The spherical wrist's task is the full orientation (qx, qy, qz, qw): IK meets the goal's
    rotation, so nothing is left uncommanded (tilt 0), whether the goal is a quaternion or an SE3."""
    from m3t1r.model.description import Mechanism
    from m3t1r.model.examples import spherical_wrist_files

    wrist = Mechanism.load(*spherical_wrist_files(tmp_path))
    solver = ClosedLoopSolver(wrist)
    sliders = wrist.home[wrist.actuated_ids] + np.array([0.2, 0.1, -0.2])
    fk = ClosedLoopSolver(wrist).forward(sliders, q_init=wrist.home)
    assert min(abs(angle) for angle in fk.roll_pitch) > 0.15  # the goal has roll and pitch
    quaternion = pin.Quaternion(fk.pose.rotation).coeffs()
    for target in (quaternion, pin.SE3(fk.pose)):
        ik = solver.inverse(target, q_init=wrist.home)
        np.testing.assert_allclose(ik.actuators, sliders, atol=1e-10)
        np.testing.assert_allclose(ik.pose.rotation, fk.pose.rotation, atol=1e-10)
        np.testing.assert_allclose(ik.tilt, 0.0, atol=1e-10)
    # Warm: the predictor's task rows are those of the new goal rotation at the last pose reached.
    nearby = ClosedLoopSolver(wrist).forward(sliders + 0.02, q_init=wrist.home)
    warm = solver.inverse(pin.Quaternion(nearby.pose.rotation).coeffs())
    np.testing.assert_allclose(warm.actuators, sliders + 0.02, atol=1e-10)
    assert warm.iterations <= 3
    # Warm again: the second-order term reads the previous goal's rotation at the last pose.
    further = ClosedLoopSolver(wrist).forward(sliders + 0.04, q_init=wrist.home)
    again = solver.inverse(pin.Quaternion(further.pose.rotation).coeffs())
    np.testing.assert_allclose(again.actuators, sliders + 0.04, atol=1e-10)
    # A quaternion goal is checked and renormalised: norm 2 is refused, norm 1 + 1e-7 is the unit one.
    with pytest.raises(InvalidInputError, match="norm"):
        solver.inverse(2.0 * quaternion, q_init=wrist.home)
    scaled = solver.inverse((1.0 + 1e-7) * quaternion, q_init=wrist.home)
    np.testing.assert_allclose(scaled.actuators, sliders, atol=1e-10)


def test_warm_inverse_with_a_locked_joint_steps_the_unlocked_columns(tmp_path):
    """The welded double hinge locks one joint: IK's unknowns are the other columns, and the warm
    predictor's step goes to those columns only."""
    import warnings

    from m3t1r.model.description import Mechanism

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hinge = Mechanism.load(*welded_double_hinge(tmp_path))
    assert len(hinge.locked_joints) == 1
    solver = ClosedLoopSolver(hinge)
    sliders = hinge.home[hinge.actuated_ids]
    for change in (0.05, 0.1):
        target = ClosedLoopSolver(hinge).forward(sliders + change, q_init=hinge.home).pose.translation[:2]
        warm = solver.inverse(target)
        np.testing.assert_allclose(warm.actuators, sliders + change, atol=1e-9)
        assert warm.q[hinge.locked_ids] == hinge.home[hinge.locked_ids]


@pytest.mark.parametrize("compiled", [True, False])
def test_an_explicit_start_takes_its_own_branch_not_the_warm_one(mechanism, compiled):
    """With q_init the branch is labelled at that start: the warm solve's branch is not asked for
    (here one no solve can have), in IK as in FK, in both Newton loops."""
    solver = ClosedLoopSolver(mechanism, native=compiled)
    solution = solver.inverse(TARGET)
    # Labels set by hand: no public call leaves a solver's warm start on a branch no solve can have.
    solver.warm.inverse_branch = b"\x02"
    assert solver.inverse(TARGET, q_init=mechanism.home).residual <= 1e-12
    solver.warm.branch = b"\x02"  # after the IK, which sets it
    assert solver.forward(solution.actuators, q_init=mechanism.home).residual <= 1e-12


def _with_q13_upper_limit(mechanism, upper_limit: float):
    model = mechanism.model.copy()
    upper = model.upperPositionLimit.copy()
    upper[model.idx_qs[model.getJointId("q13")]] = upper_limit
    model.upperPositionLimit = upper
    return mechanism.with_model(model)


@pytest.mark.parametrize("compiled", [True, False])
def test_solutions_say_whether_every_joint_is_within_its_limits(mechanism, compiled):
    """On a copy whose hinge q13 may turn only to 1.05 rad (nominal: 2.62), IK and FK solutions
    putting q13 beyond it say so in within_joint_limits (a flag: only the sliders' limits are
    refusals); on the nominal model every one is within; a hinge exactly at its stop is within."""
    k = mechanism.model.idx_qs[mechanism.model.getJointId("q13")]
    stiff = ClosedLoopSolver(_with_q13_upper_limit(mechanism, 1.05), native=compiled)
    nominal = ClosedLoopSolver(mechanism, native=compiled)
    targets = np.array([[0.50, 0.50, -0.10, 0.0], [0.52, 0.55, -0.12, 0.1], [0.48, 0.60, -0.08, -0.2]])
    flags = []
    for target in targets:
        ik = stiff.inverse(target, q_init=mechanism.home)
        fk = stiff.forward(ik.actuators, q_init=mechanism.home)
        assert ik.within_joint_limits is fk.within_joint_limits is bool(ik.q[k] <= 1.05)
        assert nominal.inverse(target, q_init=mechanism.home).within_joint_limits is True
        assert nominal.forward(ik.actuators).within_joint_limits is True
        flags.append(ik.within_joint_limits)
    assert flags == [True, True, False]  # the targets straddle the stop
    angle = nominal.inverse(targets[0], q_init=mechanism.home).q[k]
    for upper_limit, within in ((angle, True), (np.nextafter(angle, -np.inf), False)):
        solver = ClosedLoopSolver(_with_q13_upper_limit(mechanism, upper_limit), native=compiled)
        solution = solver.inverse(targets[0], q_init=mechanism.home)
        assert solution.q[k] == angle and solution.within_joint_limits is within


def test_roll_and_pitch_of_the_m_machine_are_not_commandable(mechanism, tmp_path):
    """The M machine's platform keeps its roll and pitch (3T1R): a task of z and the full rotation
    has rx and ry that no closure-compatible motion moves, though every joint alone tilts it."""
    urdf = tmp_path / "m3t1r.urdf"
    closures = tmp_path / "m3t1r.closures.yaml"
    urdf.write_text(mechanism.urdf_path.read_text())
    closures.write_text(mechanism.closures_path.read_text())
    edit_yaml(
        closures, lambda document: (document["task"].update(position=["z"], rotation="full"), document.pop("workspace"))
    )
    assert ClosedLoopSolver(Mechanism.load(urdf, closures)).uncommandable_task_rows() == ("rx", "ry")


@pytest.mark.parametrize("compiled", [True, False])
def test_a_passive_first_coordinate_beyond_its_limit_is_flagged(tmp_path, compiled):
    """The five-bar driven by elbow_1 and motor_2, motor_1 (coordinate 0 of q) free to turn only to
    2.35 rad: FK moving it to 2.376 rad says so, and IK to that pose too; moving it to 2.285 is within."""
    urdf, closures = five_bar_files(tmp_path)
    edit_text(urdf, lambda text: text.replace('lower="1.83" upper="2.83"', 'lower="1.83" upper="2.35"', 1))
    edit_yaml(closures, lambda document: document.update(actuated_joints=["elbow_1", "motor_2"], workspace=None))
    machine = Mechanism.load(urdf, closures)
    assert machine.model.names[1] == "motor_1" and 0 not in machine.actuated_ids
    solver = ClosedLoopSolver(machine, native=compiled)
    home_sliders = machine.home[machine.actuated_ids]
    for change, within in ((-0.05, False), (0.05, True)):
        fk = solver.forward(home_sliders + [change, 0.0], q_init=machine.home)
        assert (fk.q[0] > 2.35) is not within and fk.within_joint_limits is within
        ik = solver.inverse(machine.task.coordinates(fk.task_placement[None])[0], q_init=machine.home)
        np.testing.assert_allclose(ik.q, fk.q, atol=1e-9)
        assert ik.within_joint_limits is within


@pytest.mark.parametrize("slider, bound", [(0, "upper"), (1, "lower")])
def test_inverse_accepts_an_actuator_exactly_at_its_limit(mechanism, slider, bound):
    """IK's limit check is inclusive, as `check_actuators`: a start at a solution with a slider
    exactly at its limit takes no step and is accepted."""
    solver = ClosedLoopSolver(mechanism)
    sliders = mechanism.home[mechanism.actuated_ids].copy()
    sliders[slider] = mechanism.joint_limits()[1 if bound == "upper" else 0][slider]
    fk = ClosedLoopSolver(mechanism).forward(sliders, q_init=mechanism.home)
    ik = solver.inverse(np.r_[fk.pose.translation, fk.yaw], q_init=fk.q)
    assert ik.iterations == 0
    np.testing.assert_array_equal(ik.actuators, sliders)


def test_warm_forward_keeps_the_last_solution_s_branch(mechanism):
    """Without q_init, FK must end on the branch of the last solution: a label no solve can have
    (set by hand here) makes it refuse the solution it finds."""
    from m3t1r.errors import BranchChangeError

    solver = ClosedLoopSolver(mechanism)
    sliders = solver.forward(mechanism.home[mechanism.actuated_ids] + 0.01).q[mechanism.actuated_ids]
    solver.warm.branch = b"\x02"
    with pytest.raises(BranchChangeError):
        solver.forward(sliders + 0.01)


def test_a_task_that_is_not_square_is_refused_word_for_word(tmp_path):

    from m3t1r.model.description import Mechanism
    from m3t1r.model.examples import five_bar_files

    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d["task"].update(position=["x", "y", "z"]))
    solver = ClosedLoopSolver(Mechanism.load(urdf, closures))
    with pytest.raises(InvalidInputError) as caught:
        solver.inverse(np.zeros(3))
    assert str(caught.value) == (
        f"{closures}: inverse kinematics needs as many task coordinates as actuators; the task (x, y, z of "
        "frame 'effector') commands 3 for 2 actuators (declare the task in the closures file: models/README.md)"
    )


# ------------------------------------------------------------------------------------------------
# `newton` on stand-in systems: every evaluation recorded, residuals scripted


@pytest.mark.parametrize("compiled", [False, True])
def test_forward_records_the_predictor_history_and_the_branch(mechanism, compiled):
    """After each FK, where it continued from: the solution before it (warm) or q_init (a continuation
    from q_init). The compiled loop keeps the same history as one array (sliders, then passive joints).
    (The branch label at the solution shows in the warm solves here, which must keep it.)"""
    solver = ClosedLoopSolver(mechanism, native=compiled)
    home_sliders = mechanism.home[mechanism.actuated_ids]
    history = []
    for change, start in ((0.01, mechanism.home), (0.02, None), (0.03, mechanism.home), (0.04, None)):
        before = solver.last_q.copy() if start is None else start
        result = solver.forward(home_sliders + change, q_init=start)
        assert result.residual <= 1e-12
        # Read directly: publicly the history only shapes the next start's second-order term; this pins
        # what it holds, exactly, in both loops.
        previous = solver.warm.previous
        if compiled and previous is not None:
            previous = (previous[: len(home_sliders)], previous[len(home_sliders) :])
        history.append(None if previous is None else previous[0].copy())
        if previous is not None:
            np.testing.assert_array_equal(previous[1], before[solver.passive])
    np.testing.assert_array_equal(history[0], home_sliders)
    np.testing.assert_allclose(history[1], home_sliders + 0.01, atol=0.0)
    np.testing.assert_array_equal(history[2], home_sliders)  # continued from q_init = home
    np.testing.assert_allclose(history[3], home_sliders + 0.03, atol=0.0)


def test_inverse_beyond_an_actuator_limit_reports_the_converged_solve(mechanism):
    """The assembly exists but needs q21 = 0.656 m: refused with the solve's own residual and steps."""
    with pytest.raises(OutOfWorkspaceError) as caught:
        ClosedLoopSolver(mechanism).inverse(TARGET + [0.0, 0.5, 0.0, 0.0])
    assert str(caught.value).startswith(
        "target needs actuator 'q21' = 0.656167 m, beyond its limit [-0.6, 0.6] (residual "
    )
    assert caught.value.residual <= 1e-12 and 3 <= caught.value.iterations <= 20


def test_a_closure_system_that_is_not_square_is_refused_word_for_word(mechanism):
    from dataclasses import replace

    from m3t1r.model.closures import without_rows

    short = replace(mechanism, closures=without_rows(mechanism.closures, (0,)))
    with pytest.raises(InvalidInputError) as caught:
        ClosedLoopSolver(short)
    assert str(caught.value) == (
        f"{mechanism.closures_path}: 15 enforced closure rows for 16 passive joints; forward kinematics needs a "
        "square system (one row per passive joint)"
    )


def test_a_half_open_stroke_still_refuses_an_infinite_slider(mechanism):
    """Limits finite below, infinite above: the fast path (which trusts the limits to reject inf)
    is off, so +inf is refused as non-finite instead of passing as 'inside'."""
    model = mechanism.model.copy()
    upper = model.upperPositionLimit.copy()
    upper[model.idx_qs[model.getJointId(mechanism.actuated_joints[0])]] = np.inf
    model.upperPositionLimit = upper
    solver = ClosedLoopSolver(mechanism.with_model(model))
    lower, upper = solver.mechanism.joint_limits()
    assert np.isinf(upper[0]) and np.all(np.isfinite(lower))
    sliders = mechanism.home[mechanism.actuated_ids].copy()
    sliders[0] = np.inf
    with pytest.raises(InvalidInputError, match="actuator values"):
        solver.check_actuators(sliders)


def test_the_block_cache_is_per_topology(mechanism, tmp_path):
    """A five-bar built after the M machine gets its own blocks (two 1 x 1), not the machine's."""
    from m3t1r.model.description import Mechanism
    from m3t1r.model.examples import five_bar_files

    ClosedLoopSolver(mechanism)
    five_bar = Mechanism.load(*five_bar_files(tmp_path))
    solver = ClosedLoopSolver(five_bar)
    found = sorted((r.tolist(), c.tolist()) for r, c in solver.branch_blocks)
    assert sorted(sum((c for _, c in found), [])) == sorted(solver.passive.tolist())
    assert sorted(sum((r for r, _ in found), [])) == list(range(solver.n_rows))
    result = solver.forward(five_bar.home[five_bar.actuated_ids] + 0.01)
    assert result.residual <= 1e-12


# ------------------------------------------------------------------------------------------------
# The prediction from home of batch rows: home's derivatives and the order of its miss


def test_home_derivatives_are_those_of_the_solved_passive_joints(mechanism):
    """H = d^2 q_passive / da^2 and G = d^3 q_passive / da^3 at home, against central differences of
    solves from home, extrapolated from two steps (10 and 5 mm, 20 and 10 mm)."""
    solver = ClosedLoopSolver(mechanism)
    home, act, passive = mechanism.home, solver.actuated, solver.passive

    def solved(change):
        return solver.forward(home[act] + change, q_init=home).q[passive]

    def difference(h, *axes):  # the mixed central difference along the given slider axes
        total = 0.0
        for signs in itertools.product((1.0, -1.0), repeat=len(axes)):
            total = total + np.prod(signs) * solved(h * sum(s * np.eye(len(act))[a] for s, a in zip(signs, axes)))
        return total / (2 * h) ** len(axes)

    derivatives = solver.home_derivatives()
    assert derivatives is not None
    curvature, third = derivatives
    assert curvature.shape == (len(passive), 4, 4) and third.shape == (len(passive), 4, 4, 4)

    def extrapolated(h, *axes):  # Richardson from steps h and h / 2: O(h^4)
        return (4.0 * difference(h / 2, *axes) - difference(h, *axes)) / 3.0

    for i, j in itertools.product(range(4), repeat=2):
        np.testing.assert_allclose(curvature[:, i, j], extrapolated(1e-2, i, j), atol=1e-4 * np.abs(curvature).max())
    for i, j, k in [(0, 0, 0), (0, 1, 2), (3, 1, 3), (2, 2, 1)]:
        np.testing.assert_allclose(third[:, i, j, k], extrapolated(2e-2, i, j, k), atol=1e-3 * np.abs(third).max())
    np.testing.assert_allclose(third, np.swapaxes(third, 1, 3), atol=1e-5 * np.abs(third).max())


@pytest.mark.parametrize("compiled", [True, False])
def test_a_home_barely_regular_has_no_derivatives_and_predicts_to_first_order(mechanism, compiled):
    """A threshold a hair below home's reciprocal condition: home is regular, but points 1e-4 away
    along its tangents are not, so its derivatives are unknown and every order predicts as the first."""
    home = mechanism.home
    plain = ClosedLoopSolver(mechanism, native=compiled)
    exact = 1.0 / np.linalg.cond(plain.closure_jacobian(home)[:, plain.passive], 1)
    solver = ClosedLoopSolver(mechanism, native=compiled, rules=NewtonRules(singular_rcond=exact * (1 - 1e-9)))
    assert solver.home_reference() is not None and solver.home_derivatives() is None
    assert plain.home_derivatives() is not None
    change = np.array([[0.02, -0.01, 0.015, -0.02]])
    np.testing.assert_array_equal(solver.predict_from_home(change, 3), solver.predict_from_home(change, 1))
    assert np.abs(plain.predict_from_home(change, 3) - plain.predict_from_home(change, 1)).max() > 1e-5


def test_the_prediction_from_home_has_the_order_asked(mechanism):
    """Home moved along its manifold to order m misses the solution by O(|d|^(m+1)): halving d divides
    the miss by about 2^(m+1): 4, 8, 16."""
    solver = ClosedLoopSolver(mechanism)
    home, act, passive = mechanism.home, solver.actuated, solver.passive
    direction = np.array([0.04, -0.03, 0.02, 0.05])
    misses: dict[int, list[float]] = {1: [], 2: [], 3: []}
    for scale in (1.0, 0.5):
        change = scale * direction
        exact = solver.forward(home[act] + change, q_init=home).q[passive] - home[passive]
        for order, miss in misses.items():
            miss.append(np.abs(solver.predict_from_home(change[None], order)[0] - exact).max())
    ratios = {order: miss[0] / miss[1] for order, miss in misses.items()}
    assert 3.0 < ratios[1] < 5.0 and 6.0 < ratios[2] < 10.0 and 12.0 < ratios[3] < 20.0, ratios
    assert misses[3][0] < misses[2][0] / 5 < misses[1][0] / 25


def test_a_prediction_past_third_order_is_the_third_order_one(mechanism):
    """Only home's second and third derivatives are known: orders above 3 predict as order 3, for
    one row and for many (each row's monomials are its own)."""
    solver = ClosedLoopSolver(mechanism)
    changes = np.array([[0.04, -0.03, 0.02, 0.05], [-0.02, 0.01, 0.03, 0.0], [0.0, 0.0, 0.0, 0.0]])
    third = solver.predict_from_home(changes, 3)
    np.testing.assert_array_equal(solver.predict_from_home(changes, 4), third)
    np.testing.assert_array_equal(solver.predict_from_home(changes, 7), third)
    np.testing.assert_array_equal(third[2], np.zeros(len(solver.passive)))
    np.testing.assert_allclose(solver.predict_from_home(changes[:1], 3)[0], third[0], rtol=0, atol=1e-15)


# ------------------------------------------------------------------------------------------------
# The block order the one-LU signature relies on, its fallback, the exact rcond


# The last IK task pose of the predictor tests: coordinates about (0.5, 0.625, -0.125, 0.2), returned
# exactly (binary fractions and the pose's own yaw: task rows without rounding).
_LAST_TASK = pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, 0.2), np.array([0.5, 0.625, -0.125]))
_HERE = np.array([0.5, 0.625, -0.125, yaw_of(_LAST_TASK.rotation)])


def test_inverse_predictor_first_order_is_minus_x_times_the_task_rows(mechanism):
    solver = ClosedLoopSolver(mechanism)
    x = np.random.default_rng(2).normal(size=(mechanism.model.nv, 4))
    goal = _HERE + [0.01, -0.02, 0.005, 0.03]
    np.testing.assert_allclose(
        solver.inverse_predict(goal, None, x, _LAST_TASK, None), -(x @ (_HERE - goal)), rtol=1e-12
    )


def test_inverse_predictor_second_order_term_only_for_0_lt_lambda_lt_2(mechanism):
    """With X = 0 the prediction is lam^2 (q_prev - q_last) exactly while 0 < lam < 2, else nothing;
    lam is the new goal change along the last one, e (task rows of the previous goal at the last pose)."""
    solver = ClosedLoopSolver(mechanism)
    offset = np.linspace(-0.01, 0.02, mechanism.model.nv)  # q_prev - q_last
    e = np.array([2.0**-7, -(2.0**-6), 2.0**-8, 0.0])
    zero = np.zeros((mechanism.model.nv, 4))
    previous = ((_HERE - e, None), solver.last_q + offset)
    for lam, expected in ((0.5, 0.25), (1.0, 1.0), (1.5, 2.25), (0.0, 0.0), (2.0, 0.0), (2.5, 0.0), (-0.5, 0.0)):
        goal = _HERE + (lam * e if lam else np.array([2.0**-6, 2.0**-7, 0.0, 0.0]))  # at right angles to e
        np.testing.assert_allclose(
            solver.inverse_predict(goal, None, zero, _LAST_TASK, previous),
            expected * offset,
            rtol=1e-9,
            atol=1e-17,
            err_msg=str(lam),
        )
    same_goal = ((_HERE, None), solver.last_q + offset)  # e = 0
    np.testing.assert_array_equal(
        solver.inverse_predict(_HERE + e, None, zero, _LAST_TASK, same_goal), np.zeros(mechanism.model.nv)
    )


def _start_residual(solver, target):
    """The residual [m, rad] where a warm IK starts, its prediction: Newton allowed no step reports it."""
    limit, solver.max_iterations = solver.max_iterations, 0
    try:
        with pytest.raises((NotConvergedError, OutOfWorkspaceError)) as caught:
            solver.inverse(target)
    finally:
        solver.max_iterations = limit
    return caught.value.residual


def test_inverse_records_the_predictor_history_and_forward_drops_it(mechanism):
    """After a warm IK the next one predicts to second order from the solution before it and its goal
    (on a straight path of goals, far closer than the first order); after a cold one (q_init) or an
    FK, to first order only."""
    step = np.array([0.01, 0.0, 0.0, 0.02])
    second, third = TARGET + step, TARGET + 2 * step
    warm = ClosedLoopSolver(mechanism)
    first = warm.inverse(TARGET)
    warm.inverse(second)
    cold = ClosedLoopSolver(mechanism)
    cold.inverse(TARGET)
    cold.inverse(second, q_init=first.q)
    moved = ClosedLoopSolver(mechanism)
    moved.inverse(TARGET)
    moved.inverse(second)
    moved.forward(moved.last_q[moved.actuated])
    second_order, first_order = _start_residual(warm, third), _start_residual(cold, third)
    assert second_order < 0.1 * first_order
    assert _start_residual(moved, third) == pytest.approx(first_order, rel=1e-6)
    # A warm IK after a cold one from home has no history either: one solution, no step between two.
    home_first = ClosedLoopSolver(mechanism)
    home_first.inverse(second, q_init=mechanism.home)
    assert _start_residual(home_first, third) > 10 * second_order


def test_inverse_keeps_its_own_copy_of_the_goal(mechanism):
    """The caller's target array may be reused for the next target: the kept goal, the next
    prediction's history, does not move with it."""
    step = np.array([0.01, 0.0, 0.0, 0.02])
    reused, kept = ClosedLoopSolver(mechanism), ClosedLoopSolver(mechanism)
    target = TARGET.copy()
    reused.inverse(target)
    target[0] += 0.05
    reused.inverse(TARGET + step)
    kept.inverse(TARGET.copy())
    kept.inverse(TARGET + step)
    assert _start_residual(reused, TARGET + 2 * step) == _start_residual(kept, TARGET + 2 * step)


# ------------------------------------------------------------------------------------------------
# The task frame and the input fast path


def test_the_task_pose_is_the_platform_pose_when_the_task_is_on_the_platform(mechanism):
    solver = ClosedLoopSolver(mechanism)
    forward = solver.forward(mechanism.home[mechanism.actuated_ids] + 0.01)
    inverse = solver.inverse(np.array([0.5, 0.5, -0.1, 0.1]))
    assert forward.task_pose is forward.pose and inverse.task_pose is inverse.pose


@pytest.mark.parametrize("compiled", [True, False])
def test_a_result_keeps_its_own_placements_while_the_solver_moves_on(mechanism, compiled):
    """Results hold copies of the placements a solve ends at (`platform_placement`, `task_placement`):
    later solves, which reuse the solver's buffers, leave them alone; `pose` is their pin.SE3."""
    solver = ClosedLoopSolver(mechanism, native=compiled)
    inverse = solver.inverse(TARGET)
    forward = solver.forward(inverse.actuators)
    placements = [r.platform_placement.copy() for r in (inverse, forward)]
    solver.inverse(TARGET + [0.02, -0.01, 0.01, 0.05])
    solver.forward(inverse.actuators + 0.01)
    for result, placement in zip((inverse, forward), placements):
        np.testing.assert_array_equal(result.platform_placement, placement)
        np.testing.assert_array_equal(result.pose.homogeneous, placement)
    np.testing.assert_allclose(inverse.platform_placement[:3, 3], TARGET[:3], atol=1e-12)
    assert yaw_of(inverse.platform_placement) == pytest.approx(TARGET[3], abs=1e-12)
    np.testing.assert_allclose(forward.platform_placement, inverse.platform_placement, atol=1e-10)


def test_a_tool_task_frame_is_reported_apart_from_the_platform(tool_machine):
    """IK puts the tool, not the platform, on the target; FK and IK report both frames at q."""
    from conftest import frame_coordinates

    solver = ClosedLoopSolver(tool_machine)
    target = frame_coordinates(tool_machine, tool_machine.home, "tool") + [0.01, -0.02, 0.01, 0.05]
    inverse = solver.inverse(target)
    np.testing.assert_allclose(
        tool_machine.task.coordinates(inverse.task_pose.homogeneous[None])[0], target, atol=1e-12
    )
    np.testing.assert_allclose(
        frame_coordinates(tool_machine, inverse.q, "P_I"),
        tool_machine.task.coordinates(inverse.pose.homogeneous[None])[0],
        atol=1e-12,
    )
    forward = solver.forward(inverse.actuators)
    np.testing.assert_allclose(forward.task_pose.homogeneous, inverse.task_pose.homogeneous, atol=1e-12)
    np.testing.assert_allclose(forward.pose.homogeneous, inverse.pose.homogeneous, atol=1e-12)
    assert np.linalg.norm(forward.pose.translation - forward.task_pose.translation) > 0.1


def test_slider_arrays_of_every_dtype_are_checked(solver, mechanism):
    """Integer sliders are converted; an object array holding a word is refused as not numeric, not
    with numpy's ValueError (float arrays take a fast path, the others the general one)."""
    home = mechanism.home[mechanism.actuated_ids]
    reference = ClosedLoopSolver(mechanism).forward(home)
    as_list = ClosedLoopSolver(mechanism).forward(home.tolist())
    np.testing.assert_allclose(as_list.pose.homogeneous, reference.pose.homogeneous, atol=1e-12)
    assert solver.check_actuators(np.zeros(4, dtype=int)).dtype == np.float64
    with pytest.raises(InvalidInputError, match="not a numeric vector"):
        solver.forward(np.array([0.0, 0.0, 0.0, "x"], dtype=object))
    values = np.zeros(4)
    assert solver.check_actuators(values) is not values  # a copy


def test_targets_of_every_kind_give_the_same_solve(mechanism):
    """An array, a list and a wrong-dtype array of the same target: the same sliders and tilt (the
    array takes a fast input path, the others the general one); a NaN in an array is refused."""
    array = TARGET.copy()
    reference = ClosedLoopSolver(mechanism).inverse(array)
    for other in (TARGET.tolist(), TARGET.astype(np.longdouble), (TARGET * 1.0).reshape(1, 4)):
        result = ClosedLoopSolver(mechanism).inverse(other)
        np.testing.assert_allclose(result.actuators, reference.actuators, atol=1e-12)
        np.testing.assert_allclose(result.tilt, reference.tilt, atol=1e-12)
    np.testing.assert_array_equal(array, TARGET)  # the caller's array is left alone
    for bad in (np.array([0.5, np.nan, -0.1, 0.0]), np.array([0.5, 0.5, np.inf, 0.0])):
        with pytest.raises(InvalidInputError, match="non-finite"):
            ClosedLoopSolver(mechanism).inverse(bad)
    with pytest.raises(InvalidInputError, match="not a numeric vector"):  # not a float array: the general path
        ClosedLoopSolver(mechanism).inverse(np.array([0.5, 0.5, -0.1, "x"], dtype=object))


# ------------------------------------------------------------------------------------------------
# Refusals word for word, what `data` holds after a call, the row solves' codes


@pytest.mark.parametrize(
    "options,message",
    [
        ({"tolerance": 0.0}, "ClosedLoopSolver tolerance: expected a finite number above 0, got 0.0"),
        ({"max_iterations": -1}, "ClosedLoopSolver max_iterations: expected a whole number of at least 0, got -1"),
    ],
)
def test_a_refused_solver_setting_names_the_solver_word_for_word(mechanism, options, message):
    with pytest.raises(InvalidInputError) as caught:
        ClosedLoopSolver(mechanism, **options)
    assert str(caught.value) == message


def _m_machine_with_task(mechanism, tmp_path, **task):
    """The M machine's files in tmp_path with the task's fields replaced (and no workspace box)."""
    urdf, closures = tmp_path / "m3t1r.urdf", tmp_path / "m3t1r.closures.yaml"
    urdf.write_text(mechanism.urdf_path.read_text())
    closures.write_text(mechanism.closures_path.read_text())
    edit_yaml(closures, lambda document: (document["task"].update(**task), document.pop("workspace")))
    return Mechanism.load(urdf, closures)


def test_an_uncommandable_task_is_refused_word_for_word(mechanism, tmp_path):
    """IK of the M machine's z and full rotation: square, but rx and ry never move: refused naming both."""
    machine = _m_machine_with_task(mechanism, tmp_path, position=["z"], rotation="full")
    with pytest.raises(InvalidInputError) as caught:
        ClosedLoopSolver(machine).inverse(np.array([-0.1, 0.0, 0.0, 0.0, 1.0]))
    assert str(caught.value) == (
        f"{machine.closures_path}: the task's rx, ry (frame 'P_I') cannot be commanded: no motion the closures "
        "allow changes it (at home and near it), so inverse kinematics would be singular at every target; "
        "declare a task of coordinates the mechanism moves (models/README.md)"
    )


def test_a_task_that_is_not_square_is_refused_after_its_rows_were_asked_for(mechanism, tmp_path):
    """The M machine's (x, y, z): every row is commandable, but three rows for four sliders is not a
    square IK: still refused once `uncommandable_task_rows` has answered ()."""
    machine = _m_machine_with_task(mechanism, tmp_path, rotation="none")
    solver = ClosedLoopSolver(machine)
    assert solver.uncommandable_task_rows() == ()
    with pytest.raises(InvalidInputError, match="inverse kinematics needs as many task coordinates as actuators"):
        solver.inverse(np.array([0.5, 0.5, -0.1]))


def _frame_placements(model: pin.Model, q: np.ndarray) -> list[np.ndarray]:
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    return [placement.homogeneous for placement in data.oMf]


def test_every_row_residual_and_jacobian_leave_data_at_q(mechanism):
    """closure_residual(all_rows=True) leaves `data` at q with every frame placed, closure_jacobian(all_rows=True)
    its joint placements at q, as the enforced rows' calls do: the solver's one Data, whatever the rows."""
    solver = ClosedLoopSolver(mechanism)
    elsewhere = solver.forward(mechanism.home[mechanism.actuated_ids] + 0.02).q
    for all_rows in (False, True):
        solver.closure_residual(mechanism.home)
        solver.closure_residual(elsewhere, all_rows=all_rows)
        for got, expected in zip(solver.data.oMf, _frame_placements(mechanism.model, elsewhere)):
            np.testing.assert_allclose(got.homogeneous, expected, atol=1e-12)
        solver.closure_residual(mechanism.home)
        solver.closure_jacobian(elsewhere, all_rows=all_rows)
        joints = mechanism.model.createData()
        pin.forwardKinematics(mechanism.model, joints, elsewhere)
        for got, expected in zip(solver.data.oMi, joints.oMi):
            np.testing.assert_allclose(got.homogeneous, expected.homogeneous, atol=1e-12)


def test_closure_operators_of_many_configurations_are_those_of_closure_sensitivity(mechanism):
    solver = ClosedLoopSolver(mechanism)
    home = mechanism.home[mechanism.actuated_ids]
    configurations = [solver.forward(home + change).q for change in (0.0, 0.03, -0.05)]
    operators, placements = [], []
    for q in configurations:
        operators.append(solver.closure_sensitivity(q)[2])
        placements.append([placement.homogeneous for placement in solver.data.oMi])
    batch = solver.closure_operators(np.array(placements))
    assert batch.shape == (3, *operators[0].shape)
    np.testing.assert_allclose(batch, np.array(operators), atol=1e-12)


@pytest.mark.parametrize("slider, bound, beyond", [(0, "upper", 1), (1, "lower", 2)])
def test_an_ik_refusal_names_the_actuator_beyond_not_one_exactly_at_its_limit(mechanism, slider, bound, beyond):
    """One slider exactly at its limit (allowed), a later one past a limit lowered on a copy: IK from the
    solution takes no step and names the later one, in both loops."""
    limits = mechanism.joint_limits()
    sliders = mechanism.home[mechanism.actuated_ids].copy()
    sliders[slider] = limits[0 if bound == "lower" else 1][slider]
    fk = ClosedLoopSolver(mechanism).forward(sliders, q_init=mechanism.home)
    model = mechanism.model.copy()
    upper = model.upperPositionLimit.copy()
    upper[model.idx_qs[model.getJointId(mechanism.actuated_joints[beyond])]] = sliders[beyond] - 0.01
    model.upperPositionLimit = upper
    name = mechanism.actuated_joints[beyond]
    for compiled in (True, False):
        solver = ClosedLoopSolver(mechanism.with_model(model), native=compiled)
        with pytest.raises(OutOfWorkspaceError) as caught:
            solver.inverse(np.r_[fk.pose.translation, fk.yaw], q_init=fk.q)
        message = f"target needs actuator '{name}' = {sliders[beyond]:.6g} m, beyond its limit [-0.6, "
        assert str(caught.value).startswith(f"{message}{sliders[beyond] - 0.01:.6g}]")
        assert caught.value.iterations == 0


@pytest.mark.parametrize("compiled", [True, False])
def test_row_solves_give_whole_status_codes_and_iterations_and_keep_a_given_branch(mechanism, compiled):
    """solve_rows' IK rows: integer status codes and iteration counts (the two loops alike), 0 converged
    toward the goals; given labels no solve can have, every row is a branch change (code 4)."""
    solver = ClosedLoopSolver(mechanism, native=compiled)
    goals = np.array([TARGET, TARGET + [0.01, 0.0, 0.0, 0.0]])
    impossible = b"\x02" * (len(solver.home_reference()[1]) + 1)  # IK's labels: the passive blocks', then det's
    for branch, status in ((None, 0), (impossible, 4)):
        starts = np.repeat(mechanism.home[None, :], 2, axis=0)
        solved = solver.solve_rows(starts, branch, 1, goals)
        assert solved.status.dtype.kind == solved.iterations.dtype.kind == "i"
        assert solved.status.tolist() == [status, status]
        assert all(2 <= steps <= 21 for steps in solved.iterations.tolist())
    fk = solver.solve_rows(np.repeat(mechanism.home[None, :], 2, axis=0), None, 0)
    assert fk.status.dtype.kind == fk.iterations.dtype.kind == "i" and fk.status.tolist() == [0, 0]


# ------------------------------------------------------------------------------------------------
# Assembly modes: an explicit start's own, and the first step from home held to home's


@pytest.mark.parametrize("compiled", [True, False])
def test_an_explicit_start_on_the_other_assembly_mode_stays_on_it(tmp_path, compiled):
    """The five-bar's two assembly modes at the same motors: the effector mirrored across the line of
    the elbows. FK from a solution on the mode home is not on continues on that mode (its own tangent
    and labels), while the warm solve from home stays on home's."""
    machine = Mechanism.load(*five_bar_files(tmp_path))
    sliders = machine.home[machine.actuated_ids]
    folded = machine.home.copy()
    folded[machine.model.idx_qs[machine.model.getJointId("elbow_1")]] = -3.0
    folded[machine.model.idx_qs[machine.model.getJointId("elbow_2")]] = -3.0
    other = ClosedLoopSolver(machine, native=compiled).forward(sliders, q_init=folded)
    solver = ClosedLoopSolver(machine, native=compiled)
    on_home_s = solver.forward(sliders + 0.02)
    on_other = solver.forward(sliders + 0.02, q_init=other.q)
    data = machine.model.createData()
    pin.forwardKinematics(machine.model, data, on_other.q)
    elbow_1, elbow_2 = (data.oMi[machine.model.getJointId(name)].translation for name in ("elbow_1", "elbow_2"))
    axis = (elbow_2 - elbow_1) / np.linalg.norm(elbow_2 - elbow_1)
    effector = on_home_s.task_pose.translation
    foot = elbow_1 + axis * axis.dot(effector - elbow_1)
    np.testing.assert_allclose(on_other.task_pose.translation, 2.0 * foot - effector, atol=1e-9)
    assert np.linalg.norm(on_other.task_pose.translation - effector) > 0.3


@pytest.mark.parametrize("compiled", [True, False])
def test_a_first_forward_whose_first_step_crosses_a_singularity_is_refused(mechanism, compiled):
    """Sliders whose first-order step from home lands past a singularity of the passive system, where
    the path from home fails too: the first forward of a fresh and of a reset solver, held to home's
    labels, refuse the pose Newton finds there (on another assembly mode) instead of returning it."""
    sliders = np.array([0.09, 0.12, 0.55, -0.51])
    assert _path_from_home(mechanism, sliders) is None
    reset = ClosedLoopSolver(mechanism, native=compiled)
    reset.forward(mechanism.home[mechanism.actuated_ids] + 0.01)
    reset.reset()
    for solver in (ClosedLoopSolver(mechanism, native=compiled), reset):
        with pytest.raises(BranchChangeError):
            solver.forward(sliders)


# ------------------------------------------------------------------------------------------------
# Task rows no closure-compatible motion moves: their names, a home singular for IK, home alone


@pytest.mark.parametrize(
    "task, unmoved",
    [
        ({"position": ["x", "y"], "rotation": "yaw"}, ("x", "theta")),
        ({"position": ["y"], "rotation": "full"}, ("rx", "ry", "rz")),
    ],
)
def test_a_task_on_a_slider_s_carriage_can_command_only_its_rail(mechanism, tmp_path, task, unmoved):
    """Slider q11's carriage (slider_B1) translates along its rail, the base's y axis, and never turns:
    of a task on it, only y is moved (its yaw and full rotation never are)."""
    machine = _m_machine_with_task(mechanism, tmp_path, frame="slider_B1", **task)
    assert ClosedLoopSolver(machine).uncommandable_task_rows() == unmoved


def test_a_task_row_unmoved_only_at_a_singular_home_is_commandable(tmp_path):
    """A five-bar whose home has leg 1 stretched along x (motor_1 and elbow_1 at 0, the effector at
    (0.5, 0)): there the effector can move along y only, but a step away from home it moves along x
    too. So x is commandable (only home's own rates would call it dead), and IK near home solves.
    The rows come from home and two steps of 1e-3 along home's tangent."""
    urdf, closures = five_bar_files(tmp_path)
    edit_text(urdf, lambda text: text.replace('lower="1.83" upper="2.83"', 'lower="-0.5" upper="2.83"', 1))
    # Leg 2 from (0.1, 0) to (0.5, 0): sides 0.25, 0.35 and 0.4, its motor at 60 degrees.
    motor_2 = math.pi / 3
    elbow = np.array([0.1 + 0.25 * math.cos(motor_2), 0.25 * math.sin(motor_2)])
    elbow_2 = math.atan2(-elbow[1], 0.5 - elbow[0]) - motor_2
    home = {"motor_1": 0.0, "elbow_1": 0.0, "motor_2": motor_2, "elbow_2": elbow_2}
    edit_yaml(closures, lambda document: document.update(home=home, workspace=None))
    machine = Mechanism.load(urdf, closures)
    solver = ClosedLoopSolver(machine)
    np.testing.assert_allclose(
        solver.forward(machine.home[machine.actuated_ids]).task_pose.translation, [0.5, 0.0, 0.0], atol=1e-12
    )
    assert solver.uncommandable_task_rows() == ()
    sliders = machine.home[machine.actuated_ids] + [0.05, 0.02]
    target = ClosedLoopSolver(machine).forward(sliders).task_pose.translation[:2]
    nearby = ClosedLoopSolver(machine).forward(sliders - 0.01).q  # home itself is singular for IK
    np.testing.assert_allclose(solver.inverse(target, q_init=nearby).actuators, sliders, atol=1e-9)


def test_a_solver_that_calls_home_singular_answers_the_task_rows_from_home_alone(mechanism, tmp_path):
    """With a singular threshold of 1 (every rcond below it) home has no reference, so no step along
    its tangent: the rows are home's own (the five-bar's z of a task (x, z), the M machine's none)."""
    from m3t1r.model.newton_rules import DEFAULT_RULES

    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda document: document["task"].update(position=["x", "z"]))
    rules = dataclasses.replace(DEFAULT_RULES, singular_rcond=1.0)
    for machine, unmoved in ((Mechanism.load(urdf, closures), ("z",)), (mechanism, ())):
        solver = ClosedLoopSolver(machine, rules=rules)
        assert solver.home_reference() is None
        assert solver.uncommandable_task_rows() == unmoved


def test_the_task_rows_of_a_solver_with_a_single_closure_row(tmp_path):
    """The five-bar driven by three joints (motor_1, elbow_1, motor_2), its closure enforcing x alone: one
    closure row over four unknowns leaves a 3D closure-compatible motion, which moves both x and y."""
    urdf, closures = five_bar_files(tmp_path)

    def three_inputs(document):
        document.update(actuated_joints=["motor_1", "elbow_1", "motor_2"], workspace=None)
        document["closures"][0]["rows"] = [0]

    edit_yaml(closures, three_inputs)
    solver = ClosedLoopSolver(Mechanism.load(urdf, closures))
    assert solver.n_rows == 1
    assert solver.uncommandable_task_rows() == ()
