"""Closed-loop kinematics against the closed form of docs/design.md, on nominal and perturbed machines."""

import math

import closed_form
import numpy as np
import pinocchio as pin
import pytest
from conftest import perturb_every_origin

from m3t1r.errors import BranchChangeError, InvalidInputError, KinematicsError, OutOfWorkspaceError
from m3t1r.model.design import NOMINAL
from m3t1r.model.kinematics import ClosedLoopSolver, roll_pitch_of, yaw_of


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
        fd_full = np.array([(solver.closure_residual(q + e, True) - solver.closure_residual(q - e, True)) / 2e-6
                            for e in np.eye(20) * 1e-6]).T
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


@pytest.mark.parametrize("bad,message", [
    ([0.0, 0.0, np.nan, 0.0], "non-finite value nan at index 2"),
    ([0.0, 0.0, 0.0], "expected 4 values, got 3"),
    ([0.0, 700.0, 0.0, 0.0], r"actuator 'q11_B2' = 700 is beyond its joint limit \[-0.6, 0.6\]"),
    (["a", 0, 0, 0], "not a numeric vector"),
])
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
    from m3t1r.model.description import Mechanism
    from m3t1r.model.examples import FiveBarGeometry, five_bar_files, spherical_wrist_files

    # A five-bar whose motor box reaches to within a few degrees of its stretched-elbow singularity,
    # where the two assembly modes are close: a start on the wrong side of it is easy to make.
    stretched = FiveBarGeometry(distal=0.28)
    return {"M machine": mechanism, "tool machine": tool_machine,  # (machine, half-width of the slider window)
            "five-bar": Mechanism.load(*five_bar_files(tmp_path / "a")),
            "stretched five-bar": Mechanism.load(*five_bar_files(tmp_path / "b", geometry=stretched)),
            "spherical wrist": Mechanism.load(*spherical_wrist_files(tmp_path / "c"))}


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
            for solve in (lambda: ClosedLoopSolver(machine, native=native).forward(values), lambda: reset.forward(values),
                          lambda: ClosedLoopSolver(machine, native=native).forward(values, q_init=machine.home)):
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
    np.testing.assert_allclose(commandable.inverse(fk.task_pose.translation[:2]).actuators,
                               planar.home[planar.actuated_ids] + 0.01, atol=1e-9)


@pytest.mark.parametrize("values", [[0.1 + 1j, 0.0, 0.0, 0.0], np.array([0.1, 0.0, 0.0, 0.0]) + 0j])
def test_a_complex_input_is_refused_not_read_as_its_real_part(solver, values):
    with pytest.raises(InvalidInputError, match="complex values given"):
        solver.forward(values)
    with pytest.raises(InvalidInputError, match="complex values given"):
        solver.forward_batch([values])


@pytest.mark.parametrize("options,message", [
    ({"tolerance": math.inf}, "tolerance: expected a finite number above 0"),
    ({"tolerance": 1.0}, "at most 1e-06"),
    ({"tolerance": 0.0}, "above 0"),
    ({"tolerance": math.nan}, "finite number"),
    ({"max_iterations": -1}, "max_iterations: expected a whole number of at least 0"),
    ({"max_iterations": 2.5}, "whole number"),
])
def test_solver_options_that_would_pass_open_loops_as_solutions_are_refused(mechanism, options, message):
    """tolerance=inf or 1.0 returned home's neighbours as 'solved' after 0 iterations, loops 0.5 open."""
    with pytest.raises(InvalidInputError, match=message):
        ClosedLoopSolver(mechanism, **options)


@pytest.mark.parametrize("pitch", [0.0, 0.3, -1.2, 1.5607, 1.5707, -1.5708])
def test_roll_pitch_of_is_pinocchio_s_rpy(pitch):
    """Roll and pitch of a rotation or of a placement's, as Pinocchio's ZYX convention gives them,
    also next to pitch = +-pi/2 (where the heading and the roll trade places)."""
    rng = np.random.default_rng(int(1e4 * abs(pitch)))
    for _ in range(20):
        rotation = pin.rpy.rpyToMatrix(rng.uniform(-3.0, 3.0), pitch, rng.uniform(-3.0, 3.0))
        expected = pin.rpy.matrixToRpy(rotation)[:2]
        for given in (rotation, pin.SE3(rotation, np.zeros(3)).homogeneous):
            got = np.array(roll_pitch_of(given))
            wrapped = (got - expected + np.pi) % (2 * np.pi) - np.pi
            np.testing.assert_allclose(wrapped, 0.0, atol=1e-9)
