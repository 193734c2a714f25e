"""The compiled Newton loops of FK and IK (`model.native`) against the Python loops they replace.

Single solves and batches against `ClosedLoopSolver(native=False)` (the Python `newton`, which a
batch runs row by row): same solutions, iterations, branches and typed failures, on the M machine, a
calibrated copy, a tool task frame and the example mechanisms (planar x, y and full-rotation tasks).
"""

import numpy as np
import pinocchio as pin
import pytest
from conftest import perturb_every_origin
from hypothesis import example, given, settings
from hypothesis import strategies as st
from model_files import edit_yaml, welded_double_hinge

from m3t1r.errors import (
    BranchChangeError,
    InvalidInputError,
    M3t1rError,
    NotConvergedError,
    OutOfWorkspaceError,
    SingularConfigurationError,
)
from m3t1r.model import native, native_status
from m3t1r.model.description import Mechanism
from m3t1r.model.design import NOMINAL
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver, rehomed
from m3t1r.model.newton_rules import NewtonRules
from m3t1r.model.solver_layout import SolverLayout


def test_the_compiled_loop_is_built():
    """`make` builds it (tools/build_native.py); every other test here would silently compare the
    Python loop with itself without it."""
    assert native.AVAILABLE, "run `make native` (python tools/build_native.py) to compile the Newton loop"


def test_status_names_the_compiled_module_in_use():
    assert native.status().startswith("compiled Newton loop (_native_newton")


def _without_the_module(monkeypatch):
    """`native` re-imported as in an install without the compiled module (restored by `_with_the_module`)."""
    import importlib
    import sys

    import m3t1r.model

    monkeypatch.setitem(sys.modules, "m3t1r.model._native_newton", None)  # None: the import fails
    monkeypatch.delattr(m3t1r.model, "_native_newton")
    return importlib.reload(native)


def _with_the_module(monkeypatch):
    import importlib

    monkeypatch.undo()
    assert importlib.reload(native).AVAILABLE is True


def test_without_the_module_the_first_solver_warns_once_that_it_is_slower(mechanism, monkeypatch):
    import warnings

    monkeypatch.delenv(native.PURE_PYTHON_VARIABLE, raising=False)
    try:
        assert _without_the_module(monkeypatch).AVAILABLE is False
        assert native.status().startswith("pure-Python Newton loop: the compiled one is not built (4-6x slower")
        assert "make native" in native.status()
        with pytest.warns(RuntimeWarning, match="not built: the solvers run their pure-Python loop, four to six"):
            assert ClosedLoopSolver(mechanism).native is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # said once per run
            assert ClosedLoopSolver(mechanism).native is None
    finally:
        _with_the_module(monkeypatch)


def test_without_the_module_the_pure_python_variable_keeps_it_quiet(mechanism, monkeypatch):
    import warnings

    monkeypatch.setenv(native.PURE_PYTHON_VARIABLE, "1")
    try:
        _without_the_module(monkeypatch)
        assert "not built, as M3T1R_PURE_PYTHON asks" in native.status()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            solver = ClosedLoopSolver(mechanism)
        assert solver.native is None
        values = mechanism.home[solver.actuated]
        assert np.allclose(
            solver.forward(values).pose.translation,
            ClosedLoopSolver(mechanism, native=False).forward(values).pose.translation,
            atol=1e-12,
        )
    finally:
        _with_the_module(monkeypatch)


@pytest.mark.parametrize(
    ("value", "chosen"),
    [("1", True), ("yes", True), (" YES ", True), ("true", True), ("True", True), ("on", True), ("ON", True)]
    + [("", False), ("0", False), ("no", False), ("off", False), ("y", False)],
)
def test_the_pure_python_variable_is_read_in_any_case_and_spacing(monkeypatch, value, chosen):
    """1, yes, true and on (any case, spaces around) choose the pure-Python loop; anything else does not."""
    monkeypatch.setenv(native.PURE_PYTHON_VARIABLE, value)
    try:
        _without_the_module(monkeypatch)
        assert native.status() == (
            f"pure-Python Newton loop: the compiled one is not built{', as M3T1R_PURE_PYTHON asks' if chosen else ''} "
            "(4-6x slower; build it: make native, or reinstall with a C++ compiler, "
            "e.g. pip install --force-reinstall .)"
        )
    finally:
        _with_the_module(monkeypatch)


def _path(solver: ClosedLoopSolver, n: int = 200) -> np.ndarray:
    """Slider values along a smooth workspace path (Lissajous in x, y, z, theta)."""
    t = np.linspace(0.0, 2.0 * np.pi, n)
    centre = solver.forward(solver.mechanism.home[solver.actuated]).pose
    solver.reset()
    targets = np.c_[
        centre.translation[0] + 0.04 * np.sin(t),
        centre.translation[1] + 0.03 * np.sin(2 * t),
        centre.translation[2] + 0.02 * np.cos(t),
        0.15 * np.sin(t),
    ]
    sliders = np.array([solver.inverse(target).actuators for target in targets])
    solver.reset()
    return sliders


def _compare_paths(machine: Mechanism, sliders: np.ndarray) -> None:
    compiled, python = ClosedLoopSolver(machine), ClosedLoopSolver(machine, native=False)
    assert compiled.native is not None and python.native is None
    for values in sliders:
        a, b = compiled.forward(values), python.forward(values)
        np.testing.assert_allclose(a.q, b.q, atol=1e-12)
        np.testing.assert_allclose(a.pose.homogeneous, b.pose.homogeneous, atol=1e-12)
        np.testing.assert_allclose(a.task_pose.homogeneous, b.task_pose.homogeneous, atol=1e-12)
        assert a.iterations == b.iterations and a.residual <= 1e-12 and b.residual <= 1e-12
        assert abs(a.residual - b.residual) <= 1e-13
        assert a.within_joint_limits is b.within_joint_limits is True
        on_platform = machine.task.frame == machine.model.frames[machine.platform_frame_id].name
        assert (a.task_pose is a.pose) == on_platform and (b.task_pose is b.pose) == on_platform
        # The warm state (branch, tangent, history) shows in the next solve: its iterations and q.
    assert not np.shares_memory(a.q, compiled.last_q)


def test_warm_path_matches_the_python_loop(mechanism):
    _compare_paths(mechanism, _path(ClosedLoopSolver(mechanism)))


def test_warm_path_of_a_calibrated_copy_matches(mechanism):
    """The compiled model is rebuilt from the copy's own joint and frame placements."""
    machine = rehomed(mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(3), 1e-3, 1e-3)))
    _compare_paths(machine, _path(ClosedLoopSolver(machine), 60))
    nominal = ClosedLoopSolver(mechanism).forward(machine.home[machine.actuated_ids], q_init=machine.home)
    moved = ClosedLoopSolver(machine).forward(machine.home[machine.actuated_ids], q_init=machine.home)
    assert np.linalg.norm(nominal.pose.translation - moved.pose.translation) > 1e-4


def test_a_tool_task_frame_is_returned_as_the_python_loop_does(tool_machine):
    _compare_paths(tool_machine, _path(ClosedLoopSolver(tool_machine), 40))
    result = ClosedLoopSolver(tool_machine).forward(tool_machine.home[tool_machine.actuated_ids])
    data = tool_machine.model.createData()
    pin.framesForwardKinematics(tool_machine.model, data, result.q)
    np.testing.assert_allclose(
        result.task_pose.homogeneous, data.oMf[tool_machine.model.getFrameId("tool")].homogeneous, atol=1e-13
    )


@pytest.mark.parametrize("files", [five_bar_files, spherical_wrist_files])
def test_example_mechanisms_match(files, tmp_path):
    machine = Mechanism.load(*files(tmp_path))
    rng = np.random.default_rng(5)
    low, high = machine.joint_limits()
    home = machine.home[machine.actuated_ids]
    sliders = home + np.cumsum(rng.uniform(-1, 1, (30, len(home))) * 0.01 * (high - low), axis=0)
    _compare_paths(machine, np.clip(sliders, low, high))


def _outcome(solver: ClosedLoopSolver, values: np.ndarray, q_init: np.ndarray | None):
    try:
        return solver.forward(values, q_init=q_init)
    except M3t1rError as error:
        return type(error)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4))
@example(fractions=[0.5] * 4)
def test_cold_solves_that_both_loops_finish_agree(mechanism, fractions):
    """Anywhere in the slider box, far from home included: where both converge, one solution (the
    branch check keeps both on home's); where one fails, so does the other, or the one that
    converged needed a long Newton path (over 12 steps), where rounding may decide the last step
    (see the next test). The box's centre is always tried: both loops converge there."""
    low, high = mechanism.joint_limits()
    values = low + np.array(fractions) * (high - low)
    a = _outcome(ClosedLoopSolver(mechanism), values, mechanism.home)
    b = _outcome(ClosedLoopSolver(mechanism, native=False), values, mechanism.home)
    if not isinstance(a, type) and not isinstance(b, type):
        np.testing.assert_allclose(a.q, b.q, atol=1e-11)
    elif isinstance(a, type) != isinstance(b, type):
        converged = b if isinstance(a, type) else a
        assert converged.iterations > 12, (a, b)
    if fractions == [0.5] * 4:
        assert not isinstance(a, type) and not isinstance(b, type), (a, b)


def test_cold_solves_end_alike_but_for_rounding_in_long_newton_paths(mechanism):
    """Same typed outcome and iteration count on 300 random slider sets solved from home (76 converge,
    224 fail alike; measured: no difference). Hypothesis finds rare exceptions in long paths (tens of
    steps far from any solution), where rounding (Eigen's LU against LAPACK's, another Jacobian
    assembly) decides a chord refresh or the last step: sliders at fractions (0.719, 0, 0.719, 0) of
    their ranges took 35 steps against 36."""
    low, high = mechanism.joint_limits()
    values = low + np.random.default_rng(7).random((300, 4)) * (high - low)
    compiled, python = ClosedLoopSolver(mechanism), ClosedLoopSolver(mechanism, native=False)
    differ = 0
    for row in values:
        a, b = _outcome(compiled, row, mechanism.home), _outcome(python, row, mechanism.home)
        same = a == b if isinstance(a, type) or isinstance(b, type) else a.iterations == b.iterations
        if not same:
            differ += 1
            assert max(getattr(a, "iterations", 99), getattr(b, "iterations", 99)) > 12
    assert differ <= 3


def test_failures_are_the_python_loop_s_typed_errors(mechanism):
    low, high = mechanism.joint_limits()
    far = np.array([low[0], high[1], low[2], high[3]])
    kinds = set()
    for use in (True, False):
        solver = ClosedLoopSolver(mechanism, native=use)
        with pytest.raises((OutOfWorkspaceError, BranchChangeError)) as caught:
            solver.forward(far, q_init=mechanism.home)
        kinds.add((type(caught.value), caught.value.iterations))
        solver.forward(mechanism.home[mechanism.actuated_ids])
        # A branch the next solve cannot keep: set by hand, as no public call leaves a solver on one.
        solver.warm.branch = bytes(1 - b for b in solver.warm.branch)
        with pytest.raises(BranchChangeError) as caught:
            solver.forward(mechanism.home[mechanism.actuated_ids] + 1e-3)
        kinds.add((type(caught.value), caught.value.iterations))
    assert len(kinds) == 2


def test_home_derivatives_agree_between_the_loops(mechanism):
    """The prediction from home's derivatives: the compiled tangents give the Python loop's (their
    central differences amplify the rounding by 1 / h^2 = 1e8 for G)."""
    (curvature, third), (python_curvature, python_third) = (
        ClosedLoopSolver(mechanism, native=use).home_derivatives() for use in (True, False)
    )
    np.testing.assert_allclose(curvature, python_curvature, atol=1e-9 * np.abs(python_curvature).max())
    np.testing.assert_allclose(third, python_third, atol=1e-6 * np.abs(python_third).max())


def test_compiled_tangents_are_home_s_and_refused_below_the_threshold(mechanism):
    solver = ClosedLoopSolver(mechanism)
    assert solver.native is not None
    configurations = np.array([mechanism.home, mechanism.home + 1e-3])
    tangents, regular = solver.native.tangents(configurations, solver.rules.singular_rcond)
    assert tangents.shape == (2, len(solver.passive), len(solver.actuated)) and list(regular) == [True, True]
    assert regular.dtype == bool
    rounded = solver.native.tangents(configurations.astype(np.float32), solver.rules.singular_rcond)[0]
    np.testing.assert_allclose(rounded, tangents, atol=1e-4 * np.abs(tangents).max())  # converted, not refused
    np.testing.assert_allclose(tangents[0], solver.home_reference()[0], atol=1e-12)
    jacobian = solver.closure_jacobian(configurations[1])  # off the manifold: T of the unsolved q
    expected = -np.linalg.solve(jacobian[:, solver.passive], jacobian[:, solver.actuated])
    np.testing.assert_allclose(tangents[1], expected, atol=1e-11)
    assert not solver.native.tangents(configurations, 2.0)[1].any()  # no reciprocal condition reaches 2


def test_a_singular_configuration_is_refused_with_its_class(mechanism, monkeypatch):
    """A threshold no configuration meets makes every converged solve singular, in both loops."""
    for use in (True, False):
        solver = ClosedLoopSolver(mechanism, native=use, rules=NewtonRules(singular_rcond=2.0))
        with pytest.raises(SingularConfigurationError):
            solver.forward(mechanism.home[mechanism.actuated_ids] + 1e-3)


@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_a_threshold_beside_the_exact_reciprocal_condition_decides_as_the_python_loop(mechanism, side):
    """The compiled loop clears most solves by a cheap lower bound on the reciprocal condition; a
    threshold a hair below or above the exact value (where the bound cannot decide) must still end as
    the Python loop's exact test does: single FK, FK from home, and forward_batch rows started where
    the single solve from home starts (home moved along its tangent: the same Newton path)."""
    sliders = mechanism.home[mechanism.actuated_ids] + np.array([0.02, -0.01, 0.015, -0.02])
    q = ClosedLoopSolver(mechanism, native=False).forward(sliders, q_init=mechanism.home).q
    reference = ClosedLoopSolver(mechanism, native=False)
    exact = 1.0 / np.linalg.cond(reference.closure_jacobian(q)[:, reference.passive], 1)
    assert 1e-6 < exact < 1.0
    rules = NewtonRules(singular_rcond=exact * (1.0 + side * 1e-6))
    for use in (True, False):
        solver = ClosedLoopSolver(mechanism, native=use, rules=rules)
        start = mechanism.home.copy()
        start[solver.actuated] = sliders
        start[solver.passive] += solver.predict_from_home((sliders - mechanism.home[solver.actuated])[None], 1)[0]
        batch = solver.forward_batch(np.array([sliders, sliders]), q_init=start)
        if side < 0:
            np.testing.assert_allclose(solver.forward(sliders, q_init=mechanism.home).q, q, atol=1e-11)
            assert batch.complete
        else:
            with pytest.raises(SingularConfigurationError, match="reciprocal condition"):
                solver.forward(sliders, q_init=mechanism.home)
            assert [f.error for f in batch.failures] == [SingularConfigurationError] * 2


def test_tolerance_and_iteration_limits_are_read_at_each_solve(mechanism):
    solver = ClosedLoopSolver(mechanism)
    far = mechanism.home[mechanism.actuated_ids] + np.array([0.02, -0.01, 0.015, -0.02])
    solver.max_iterations = 1
    with pytest.raises(M3t1rError) as caught:
        solver.forward(far, q_init=mechanism.home)
    assert caught.value.iterations == 1
    solver.max_iterations, solver.tolerance = 60, 1e-6
    loose = solver.forward(far, q_init=mechanism.home)
    assert 1e-13 < loose.residual <= 1e-6
    assert loose.iterations < ClosedLoopSolver(mechanism).forward(far, q_init=mechanism.home).iterations


def test_forward_batch_matches_the_numpy_newton(mechanism):
    cloud = NOMINAL.workspace.sample(np.random.default_rng(2), 300)
    sliders = ClosedLoopSolver(mechanism).inverse_batch(cloud).actuators
    low, high = mechanism.joint_limits()
    # a far row, a row beyond the limits, and five rows of the slider box whose solution from home's
    # predicted start lies on another branch than home's (found among 3,000 draws)
    crossing = low + np.random.default_rng(0).random((3000, 4))[[29, 51, 92, 165, 203]] * (high - low)
    sliders = np.vstack((sliders, [low[0], high[1], low[2], high[3]], high + 1.0, crossing))
    compiled = ClosedLoopSolver(mechanism).forward_batch(sliders)
    numpy_batch = ClosedLoopSolver(mechanism, native=False).forward_batch(sliders)
    assert sum(f.error is BranchChangeError for f in compiled.failures) >= 3
    np.testing.assert_array_equal(compiled.indices, numpy_batch.indices)
    np.testing.assert_allclose(compiled.q, numpy_batch.q, atol=1e-12)
    np.testing.assert_allclose(compiled.poses, numpy_batch.poses, atol=1e-12)
    np.testing.assert_array_equal(compiled.iterations, numpy_batch.iterations)
    assert [(f.index, f.error) for f in compiled.failures] == [(f.index, f.error) for f in numpy_batch.failures]
    assert len(compiled.failures) >= 1 and not compiled.poses.flags.writeable
    assert [f.reason.split(" (residual")[0] for f in compiled.failures] == [
        f.reason.split(" (residual")[0] for f in numpy_batch.failures
    ]
    short = []
    for use in (True, False):  # three steps at most: some rows stop unconverged, counted alike
        solver = ClosedLoopSolver(mechanism, native=use)
        solver.max_iterations = 3
        batch = solver.forward_batch(sliders[:40])
        short.append((list(batch.indices), list(batch.iterations), [(f.index, f.error) for f in batch.failures]))
    assert short[0] == short[1] and short[0][2]
    given_start = ClosedLoopSolver(mechanism).forward_batch(sliders[:20], q_init=mechanism.home)
    numpy_start = ClosedLoopSolver(mechanism, native=False).forward_batch(sliders[:20], q_init=mechanism.home)
    np.testing.assert_array_equal(given_start.indices, numpy_start.indices)
    np.testing.assert_allclose(given_start.q, numpy_start.q, atol=1e-12)


def test_forward_batch_task_frame_of_a_tool(tool_machine):
    solver = ClosedLoopSolver(tool_machine)
    sliders = tool_machine.home[tool_machine.actuated_ids] + np.linspace(0, 0.01, 5)[:, None]
    batch = solver.forward_batch(sliders)
    for q, task in zip(batch.q, batch.task_poses):
        data = tool_machine.model.createData()
        pin.framesForwardKinematics(tool_machine.model, data, q)
        np.testing.assert_allclose(task, data.oMf[tool_machine.model.getFrameId("tool")].homogeneous, atol=1e-13)


def test_only_one_dof_revolute_and_prismatic_trees_are_compiled(mechanism):
    model = pin.Model()
    model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    none = np.zeros(0, dtype=int)
    layout = SolverLayout(none, none, None, 0, np.zeros(0), np.zeros(0), 0, 0, [])
    assert native.NativeChain.of(model, (), layout, mechanism.task) is None
    assert ClosedLoopSolver(mechanism, native=False).native is None


def test_the_compiled_loop_refuses_buffers_of_the_wrong_size(mechanism):
    chain = ClosedLoopSolver(mechanism).native
    limits, sliders = NewtonRules().compiled(), np.zeros(4)
    with pytest.raises(ValueError, match="q"):
        chain.forward(np.zeros(3), sliders, 0, None, None, limits)
    with pytest.raises(ValueError, match="q"):
        chain.forward(np.zeros(mechanism.model.nq, dtype=np.float32), sliders, 0, None, None, limits)
    with pytest.raises(ValueError, match="sliders"):
        chain.forward(mechanism.home.copy(), np.zeros(3), 0, None, None, limits)
    with pytest.raises(ValueError, match="previous"):
        chain.forward(mechanism.home.copy(), sliders, 2, np.zeros(3), None, limits)
    with pytest.raises(ValueError, match="goal"):
        chain.inverse(mechanism.home.copy(), np.zeros(2), None, 0, None, None, limits)
    with pytest.raises(ValueError):
        chain.forward_rows(np.zeros((2, 3)), None, 0, limits)
    q = mechanism.home.copy()
    chain.forward(q, mechanism.home[mechanism.actuated_ids], 0, None, None, limits)
    np.testing.assert_allclose(q, mechanism.home, atol=1e-12)  # nothing clipped or moved by the refusals


def _targets(machine: Mechanism, n: int, seed: int) -> np.ndarray:
    """Task coordinates along a smooth path of reachable poses (FK of a slider random walk)."""
    solver = ClosedLoopSolver(machine, native=False)
    low, high = machine.joint_limits()
    rng = np.random.default_rng(seed)
    sliders = machine.home[machine.actuated_ids] + np.cumsum(
        rng.uniform(-1, 1, (n, len(low))) * 0.004 * (high - low), axis=0
    )
    poses = [solver.forward(values).task_pose.homogeneous for values in np.clip(sliders, low, high)]
    return machine.task.coordinates(np.array(poses))


def _compare_inverse(machine: Mechanism, targets: np.ndarray) -> None:
    compiled, python = ClosedLoopSolver(machine), ClosedLoopSolver(machine, native=False)
    for target in targets:
        a, b = compiled.inverse(target), python.inverse(target)
        np.testing.assert_allclose(a.q, b.q, atol=1e-12)
        np.testing.assert_allclose(a.actuators, b.actuators, atol=1e-12)
        np.testing.assert_allclose(a.pose.homogeneous, b.pose.homogeneous, atol=1e-12)
        np.testing.assert_allclose(a.task_pose.homogeneous, b.task_pose.homogeneous, atol=1e-12)
        np.testing.assert_allclose(a.tilt, b.tilt, atol=1e-12)
        assert a.iterations == b.iterations and a.residual <= 1e-12
        assert a.within_joint_limits is b.within_joint_limits is True
    # What a caller does to the results does not reach the warm start of the next solve.
    for result in (a, b):
        result.task_pose.translation = result.task_pose.translation + 0.1
        result.q[:] += 0.1
    again, expected = compiled.inverse(targets[-1]), python.inverse(targets[-1])
    np.testing.assert_allclose(again.q, expected.q, atol=1e-12)
    assert again.iterations == expected.iterations


def test_warm_inverse_path_matches_the_python_loop(mechanism):
    _compare_inverse(mechanism, _targets(mechanism, 120, 1))


def test_inverse_from_home_across_the_workspace_ends_as_the_python_loop(mechanism):
    """The compiled IK factorises its system with the loop blocks first (its branch labels read from
    those factors); over the whole workspace box each solve from home ends as the Python loop's
    (dgetrf of the system as it comes, labels from a second factorisation): same solution, iterations
    and failure class."""
    compiled, python = ClosedLoopSolver(mechanism), ClosedLoopSolver(mechanism, native=False)
    outcomes = []
    for target in NOMINAL.workspace.sample(np.random.default_rng(7), 80):
        ends = []
        for solver in (compiled, python):
            try:
                ends.append(solver.inverse(target, q_init=mechanism.home))
            except M3t1rError as error:
                ends.append(type(error))
        a, b = ends
        if isinstance(a, type) or isinstance(b, type):
            assert a == b
            continue
        np.testing.assert_allclose(a.q, b.q, atol=1e-11)
        assert a.iterations == b.iterations
        outcomes.append(a.iterations)
    assert len(outcomes) >= 70  # the box is the workspace: nearly every target is reached


def test_inverse_of_a_tool_and_of_a_calibrated_copy_match(mechanism, tool_machine):
    _compare_inverse(tool_machine, _targets(tool_machine, 30, 2))
    machine = rehomed(mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(4), 1e-3, 1e-3)))
    _compare_inverse(machine, _targets(machine, 30, 3))


@pytest.mark.parametrize("files", [five_bar_files, spherical_wrist_files])
def test_inverse_of_example_mechanisms_match(files, tmp_path):
    """Planar (x, y) and full-rotation (quaternion) tasks."""
    machine = Mechanism.load(*files(tmp_path))
    _compare_inverse(machine, _targets(machine, 30, 4))


def test_inverse_failures_are_the_python_loop_s(mechanism):
    kinds = []
    for use in (True, False):
        solver = ClosedLoopSolver(mechanism, native=use)
        # no assembly; a branch crossed (yaw 3 rad); a slider beyond its limit (y 1.5 m)
        for target in ([0.5, 0.5, 0.4, 0.0], [0.52, 0.52, -0.11, 3.0], [0.52, 1.5, -0.11, 0.0]):
            with pytest.raises(M3t1rError) as caught:
                solver.inverse(np.array(target), q_init=mechanism.home)
            kinds.append((type(caught.value), caught.value.iterations))
    assert kinds[:3] == kinds[3:]
    assert [kind for kind, _ in kinds[:3]] == [OutOfWorkspaceError, BranchChangeError, OutOfWorkspaceError]


def test_forward_batch_on_several_threads_gives_the_same_rows(mechanism):
    cloud = NOMINAL.workspace.sample(np.random.default_rng(8), 400)
    sliders = ClosedLoopSolver(mechanism).inverse_batch(cloud).actuators
    solver = ClosedLoopSolver(mechanism)
    one, three = solver.forward_batch(sliders, threads=1), solver.forward_batch(sliders, threads=3)
    np.testing.assert_array_equal(one.q, three.q)  # rows are independent: bit for bit
    np.testing.assert_array_equal(one.iterations, three.iterations)
    np.testing.assert_array_equal(one.poses, three.poses)
    assert native.available_cores() >= 1


@pytest.mark.parametrize("threads", [0, -2, 1.5, "2", True])
def test_a_bad_thread_count_is_refused_by_name(solver, threads):
    from m3t1r.errors import InvalidInputError

    with pytest.raises(InvalidInputError, match="threads"):
        solver.forward_batch(np.zeros((2, 4)), threads=threads)


def _compare_inverse_batches(machine: Mechanism, targets: np.ndarray, q_init: np.ndarray | None = None) -> None:
    compiled = ClosedLoopSolver(machine).inverse_batch(targets, q_init=q_init)
    numpy_batch = ClosedLoopSolver(machine, native=False).inverse_batch(targets, q_init=q_init)
    np.testing.assert_array_equal(compiled.indices, numpy_batch.indices)
    for name in ("q", "actuators", "poses", "task_poses", "tilt"):
        np.testing.assert_allclose(getattr(compiled, name), getattr(numpy_batch, name), atol=1e-11, err_msg=name)
    np.testing.assert_array_equal(compiled.iterations, numpy_batch.iterations)
    assert [(f.index, f.error) for f in compiled.failures] == [(f.index, f.error) for f in numpy_batch.failures]


def test_inverse_batch_matches_the_numpy_newton(mechanism):
    cloud = NOMINAL.workspace.sample(np.random.default_rng(9), 300)
    # a target beyond the sliders (y 1.5 m), one without assembly (z 0.4 m), one crossing a branch (yaw 3 rad)
    targets = np.vstack((cloud, [[0.52, 1.5, -0.11, 0.0], [0.5, 0.5, 0.4, 0.0], [0.52, 0.52, -0.11, 3.0]]))
    _compare_inverse_batches(mechanism, targets)
    _compare_inverse_batches(mechanism, targets[:30], q_init=mechanism.home)
    one = ClosedLoopSolver(mechanism).inverse_batch(targets, threads=1)
    two = ClosedLoopSolver(mechanism).inverse_batch(targets, threads=2)
    np.testing.assert_array_equal(one.q, two.q)
    assert {f.error for f in one.failures} >= {OutOfWorkspaceError}


def test_inverse_batch_of_a_tool_and_of_the_example_mechanisms_match(tool_machine, tmp_path):
    _compare_inverse_batches(tool_machine, _targets(tool_machine, 40, 5))
    for files in (five_bar_files, spherical_wrist_files):  # planar x, y; full rotation (from home, no first step)
        machine = Mechanism.load(*files(tmp_path / files.__name__))
        _compare_inverse_batches(machine, _targets(machine, 40, 6))


def test_a_batch_in_another_thread_does_not_disturb_single_solves(mechanism):
    """The batch runs without the GIL; single solves of the same solver from this thread meanwhile
    wait for its lock instead of sharing its buffers: both give what they give alone."""
    import threading

    cloud = NOMINAL.workspace.sample(np.random.default_rng(10), 3000)
    sliders = ClosedLoopSolver(mechanism).inverse_batch(cloud).actuators
    path = _path(ClosedLoopSolver(mechanism), 100)
    alone_batch = ClosedLoopSolver(mechanism).forward_batch(sliders)
    alone_path = [ClosedLoopSolver(mechanism).forward(values, q_init=mechanism.home).q for values in path]
    solver, out = ClosedLoopSolver(mechanism), {}
    worker = threading.Thread(target=lambda: out.setdefault("batch", solver.forward_batch(sliders, threads=2)))
    worker.start()
    shared = [solver.forward(values, q_init=mechanism.home).q for values in path]
    worker.join()
    np.testing.assert_array_equal(out["batch"].q, alone_batch.q)
    np.testing.assert_array_equal(np.array(shared), np.array(alone_path))


def test_available_cores_follows_the_affinity_else_the_cpu_count(monkeypatch):
    import os

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3} if pid == 0 else set(), raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 7)
    assert native.available_cores() == 1
    monkeypatch.delattr(os, "sched_getaffinity")
    assert native.available_cores() == 7
    monkeypatch.setattr(os, "cpu_count", lambda: None)  # "undetermined"
    assert native.available_cores() == 1


def test_labels_no_solution_can_have_fail_every_row_and_solve(mechanism):
    """Given labels are what rows and solves must end with: labels of another length, or 2 (labels
    are 0 or 1), fail them all with BranchChangeError (status 4); without labels they succeed."""
    solver = ClosedLoopSolver(mechanism)
    chain, limits = solver.native, NewtonRules().compiled()
    blocks = len(solver.home_reference()[1])
    start = np.repeat(mechanism.home[None, :], 3, axis=0)
    start[:, solver.actuated] += np.linspace(0.0, 0.01, 3)[:, None]
    assert list(chain.forward_rows(start.copy(), None, 0, limits)[0]) == [0, 0, 0]
    assert list(chain.forward_rows(start.copy(), np.full(blocks, 2), 0, limits)[0]) == [4, 4, 4]
    goals = np.ascontiguousarray(
        mechanism.task.coordinates(ClosedLoopSolver(mechanism).forward_batch(start[:, solver.actuated]).task_poses)
    )
    assert list(chain.inverse_rows(start.copy(), goals, None, None, 0, limits)[0]) == [0, 0, 0]
    assert list(chain.inverse_rows(start.copy(), goals, None, np.full(blocks + 1, 2), 0, limits)[0]) == [4] * 3
    sliders = start[1, solver.actuated]
    for labels in (b"\x01", bytes(blocks + 1), b"\x02" * blocks):
        assert chain.forward(mechanism.home.copy(), sliders, 0, None, labels, limits)[0] == 4
    for labels in (b"\x01", bytes(blocks), b"\x02" * (blocks + 1)):
        assert chain.inverse(mechanism.home.copy(), goals[1], None, 0, None, labels, limits)[0] == 4
    assert chain.inverse(mechanism.home.copy(), goals[1], None, 0, None, None, limits)[0] == 0


@pytest.mark.parametrize("task", [{"position": ["x", "y", "z"]}, {"position": ["x", "y"], "rotation": "yaw"}])
def test_a_task_that_is_not_square_still_gets_the_compiled_forward(tmp_path, task):
    """IK needs as many task rows as actuators; FK does not: the five-bar commanding x, y, z or x, y,
    yaw (3 rows for 2 sliders) solves FK in the compiled loop as in the Python one, and IK is refused
    by name."""

    from m3t1r.errors import InvalidInputError

    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d["task"].update(task))
    machine = Mechanism.load(urdf, closures)
    assert ClosedLoopSolver(machine).native is not None
    low, high = machine.joint_limits()
    home = machine.home[machine.actuated_ids]
    _compare_paths(machine, np.clip(home + np.linspace(0, 1, 20)[:, None] * 0.05 * (high - low), low, high))
    with pytest.raises(InvalidInputError, match="as many task coordinates as actuators"):
        ClosedLoopSolver(machine).inverse(np.zeros(len(machine.task.columns)))


def test_a_module_compiled_from_other_source_is_not_used(monkeypatch):
    """The build stamps the source's sha256 into the module; an edited source (or an old build) makes
    `native` warn and leave the Python loops in charge rather than call a module of another interface."""
    import hashlib
    import importlib

    assert [source.name for source in native_status.SOURCES] == ["_native_newton.cpp", "_native_core.hpp"]
    sources = b"".join(source.read_bytes() for source in native_status.SOURCES)
    module = importlib.import_module("m3t1r.model._native_newton")  # the compiled module `native` loaded
    assert module.source_sha256 == hashlib.sha256(sources).hexdigest()
    monkeypatch.setattr(module, "source_sha256", "0" * 64)
    try:
        with pytest.warns(RuntimeWarning, match="older than its source"):
            assert importlib.reload(native).AVAILABLE is False
    finally:
        monkeypatch.undo()
        assert importlib.reload(native).AVAILABLE is True


def test_a_locked_gauge_joint_stays_out_of_the_compiled_ik(tmp_path):
    """The welded double hinge locks one joint: the compiled IK solves the other columns, as the Python one."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hinge = Mechanism.load(*welded_double_hinge(tmp_path))
    assert len(hinge.locked_joints) == 1
    _compare_inverse(hinge, _targets(hinge, 20, 7))
    result = ClosedLoopSolver(hinge).inverse(_targets(hinge, 3, 8)[-1], q_init=hinge.home)
    assert result.q[hinge.locked_ids] == hinge.home[hinge.locked_ids]


def _failure(solve):
    try:
        solve()
    except M3t1rError as error:
        return error
    raise AssertionError("the solve did not fail")


def test_failures_read_word_for_word_as_the_python_loop_s(mechanism, monkeypatch):
    """Each typed failure of FK and IK: the same class, message, iterations and residual (to rounding)."""
    low, high = mechanism.joint_limits()
    far = np.array([low[0], high[1], low[2], high[3]])
    near = mechanism.home[mechanism.actuated_ids] + np.array([0.01, -0.005, 0.0, 0.004])
    scenarios = {
        "no assembly (FK)": lambda s: s.forward(far, q_init=mechanism.home),
        "no assembly (IK)": lambda s: s.inverse(np.array([0.5, 0.5, 0.4, 0.0]), q_init=mechanism.home),
        "branch (IK)": lambda s: s.inverse(np.array([0.52, 0.52, -0.11, 3.0]), q_init=mechanism.home),
        "not converged": lambda s: setattr(s, "tolerance", 1e-30) or s.forward(near, q_init=mechanism.home),
        "singular": lambda s: s.forward(near, q_init=mechanism.home),
        "singular (IK)": lambda s: s.inverse(np.array([0.5, 0.52, -0.1, 0.1]), q_init=mechanism.home),
    }
    for name, scenario in scenarios.items():
        errors = []
        for use in (True, False):
            solver = ClosedLoopSolver(mechanism, native=use)
            solver.singular_rcond = 2.0 if name.startswith("singular") else solver.singular_rcond
            errors.append(_failure(lambda: scenario(solver)))
        a, b = errors
        assert type(a) is type(b) and a.iterations == b.iterations, name
        message_a, message_b = (str(e).split(" (residual")[0] for e in errors)  # the residual is compared below
        if name.startswith("singular"):  # the reciprocal condition's last digits may differ
            assert message_a[:42] == message_b[:42] == "singular configuration (reciprocal conditi"
            assert abs(float(message_a.split()[-1][:-1]) - float(message_b.split()[-1][:-1])) < 1e-3
        else:
            assert message_a == message_b, name
        if not name.startswith("no assembly"):  # sixty steps far from any solution end wherever rounding takes them
            assert abs(a.residual - b.residual) <= 1e-9 * max(1.0, abs(b.residual)), name


def test_fk_and_ik_in_turn_match_the_python_loop(mechanism):
    """Warm starts handed between FK and IK (IK's solution starts FK without its tangent; FK's starts IK
    without its predictor), with cold solves in between: both loops take the same steps."""
    targets = _targets(mechanism, 24, 11)
    compiled, python = ClosedLoopSolver(mechanism), ClosedLoopSolver(mechanism, native=False)
    for k, target in enumerate(targets):
        for solver in (compiled, python):
            solver.results = getattr(solver, "results", [])
            start = mechanism.home if k % 7 == 3 else None
            ik = solver.inverse(target, q_init=start)
            fk = solver.forward(ik.actuators + 1e-4 * (k % 3), q_init=start if k % 5 == 4 else None)
            solver.results.append((ik.q, ik.iterations, fk.q, fk.iterations))
    for (qa, ia, fa, ja), (qb, ib, fb, jb) in zip(compiled.results, python.results):
        np.testing.assert_allclose(qa, qb, atol=1e-12)
        np.testing.assert_allclose(fa, fb, atol=1e-12)
        assert (ia, ja) == (ib, jb)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_warm_inverse_keeps_the_last_solution_s_branch(mechanism, compiled):
    """Without q_init, IK must end on the branch of its last solution (and working mode): a label no
    solve can have (set by hand) makes it refuse what it finds; with q_init it takes the start's."""
    solver = ClosedLoopSolver(mechanism, native=compiled)
    targets = _targets(mechanism, 3, 12)
    solver.inverse(targets[0])
    solver.warm.inverse_branch = b"\x02" * (len(solver.home_reference()[1]) + 1)
    with pytest.raises(BranchChangeError):
        solver.inverse(targets[1])
    solver.warm.inverse_branch = b"\x02" * (len(solver.home_reference()[1]) + 1)
    assert solver.inverse(targets[2], q_init=mechanism.home).residual <= 1e-12


@pytest.mark.parametrize("compiled", [True, False])
def test_a_warm_forward_refuses_sliders_beyond_their_limits_and_keeps_its_warm_start(mechanism, compiled):
    """Sliders one ulp beyond a limit, or NaN, given as a float array to a warm FK (which the compiled
    loop checks itself): InvalidInputError naming the slider as `check_actuators` does, and nothing
    of the warm start changes: the next solves take the same steps to the same configurations as a
    solver that never saw the refusals."""
    sliders = _path(ClosedLoopSolver(mechanism), 12)
    solver, untouched = ClosedLoopSolver(mechanism, native=compiled), ClosedLoopSolver(mechanism, native=compiled)
    assert (solver.native is not None) == compiled
    for values in sliders[:6]:
        solver.forward(values)
        untouched.forward(values)
    lower, upper = mechanism.joint_limits()
    beyond, missing = sliders[6].copy(), sliders[6].copy()
    beyond[2], missing[0] = np.nextafter(upper[2], np.inf), np.nan
    with pytest.raises(InvalidInputError) as caught:
        solver.forward(beyond)
    assert str(caught.value) == (
        f"actuator 'q21' = {beyond[2]:.6g} is beyond its joint limit "
        f"[{lower[2]:.6g}, {upper[2]:.6g}] (SI units: metres for sliders)"
    )
    with pytest.raises(InvalidInputError, match="actuator values"):
        solver.forward(missing)
    with pytest.raises(InvalidInputError, match="actuator 'q21'"):
        solver.forward(beyond, q_init=mechanism.home)  # a start of its own: refused before its tangent is taken
    for values in sliders[6:]:
        a, b = solver.forward(values), untouched.forward(values)
        np.testing.assert_array_equal(a.q, b.q)
        assert a.iterations == b.iterations


def test_after_an_inverse_and_after_a_failed_one_both_loops_take_the_same_steps(mechanism):
    """FK right after IK starts from IK's solution without a tangent (a slider moved 5 mm); IK after a
    failed IK starts from the last solution without the failed solve's predictor or labels: the
    compiled loop takes the Python loop's steps to the same configurations."""
    targets = _targets(mechanism, 4, 13)
    results = []
    for solver in (ClosedLoopSolver(mechanism), ClosedLoopSolver(mechanism, native=False)):
        ik = solver.inverse(targets[0])
        fk = solver.forward(ik.actuators + [5e-3, 0.0, 0.0, 0.0])
        solver.inverse(targets[1])
        with pytest.raises(OutOfWorkspaceError):
            solver.inverse(targets[2] + [5.0, 0.0, 0.0, 0.0])  # 5 m away
        after = solver.inverse(targets[3])
        results.append((fk.q, fk.iterations, after.q, after.iterations))
    (fa, ja, qa, ia), (fb, jb, qb, ib) = results
    np.testing.assert_allclose(fa, fb, atol=1e-12)
    np.testing.assert_allclose(qa, qb, atol=1e-12)
    assert (ja, ia) == (jb, ib) and ja >= 1


def test_a_bad_thread_count_is_refused_by_inverse_batch_too(solver):
    from m3t1r.errors import InvalidInputError

    with pytest.raises(InvalidInputError, match="threads"):
        solver.inverse_batch(np.zeros((2, 4)), threads=0)


@pytest.mark.parametrize("compiled", [True, False])
def test_batches_of_no_rows_in_both_loops(mechanism, compiled):
    solver = ClosedLoopSolver(mechanism, native=compiled)
    forward, inverse = solver.forward_batch(np.zeros((0, 4))), solver.inverse_batch(np.zeros((0, 4)))
    assert forward.n == inverse.n == 0 and forward.q.shape == inverse.q.shape == (0, mechanism.model.nq)
    assert forward.complete and inverse.complete and inverse.actuators.shape == (0, 4)


def _class_and_steps(solve) -> tuple:
    """(error class or None, iterations) of a solve."""
    try:
        return None, solve().iterations
    except M3t1rError as error:
        return type(error), error.iterations


@pytest.mark.parametrize(
    "rule",
    [
        {"max_step": 1e-5},
        {"chord_below": 1.0, "chord_contraction": 0.999},
        {"max_iterations": 1, "no_assembly": 1.0},
        {"singular_rcond": 2.0},
        {"tolerance": 1e-6},
    ],
)
def test_every_loop_obeys_every_newton_rule(mechanism, rule):
    """One NewtonRules, read by the compiled and the Python single solves and by both batches: each
    rule changed alone changes the outcome, and alike in every loop."""
    far = mechanism.home[mechanism.actuated_ids] + np.array([0.02, -0.01, 0.015, -0.02])
    outcomes = []
    for rules in (NewtonRules(), NewtonRules(**rule)):
        for use in (True, False):
            solver = ClosedLoopSolver(mechanism, native=use, rules=rules)
            single = _class_and_steps(lambda: solver.forward(far, q_init=mechanism.home))
            batch = solver.forward_batch(far[None, :])  # from home, as forward(q_init=home)
            # A batch row counts its predicted start as a step; the single solve does not.
            rows = (
                (None, int(batch.iterations[0]) - 1)
                if batch.complete
                else (batch.failures[0].error, int(batch.failures[0].reason.split(" after ")[1].split()[0]) - 1)
            )
            outcomes.append((single, rows))
    default, changed = outcomes[:2], outcomes[2:]
    assert default[0] == default[1] and changed[0] == changed[1], (default, changed)
    assert default[0][0] == default[0][1]  # forward(q_init=home) is the batch's solve from home
    assert changed[0] != default[0]
    if "no_assembly" in rule:
        assert changed[0][0][0] is NotConvergedError  # out of steps near enough: not "no assembly"


def test_newton_rules_refuse_what_no_loop_could_obey():
    for bad in (
        {"tolerance": 0.0},
        {"tolerance": float("nan")},
        {"max_iterations": -1},
        {"max_iterations": 1.5},
        {"singular_rcond": -1e-3},
        {"chord_contraction": 1.0},
        {"max_step": -0.1},
        {"no_assembly": 0.0},
    ):
        with pytest.raises(InvalidInputError, match=f"Newton rules: {next(iter(bad))}"):
            NewtonRules(**bad)
    assert ClosedLoopSolver(Mechanism.load(), tolerance=1e-9).rules == NewtonRules(tolerance=1e-9)


# ---------------------------------------------------------------------------------------------------
# Whether the compiled loop is usable (`native_status`): what `m3t1r --version` reports, and why not


def test_a_built_module_of_these_sources_is_loaded_and_reported_usable():
    module, why = native_status.load_compiled()
    assert (module.__name__, why) == ("m3t1r.model._native_newton", "")
    assert native_status.compiled_newton_status() == "yes"


@pytest.mark.parametrize("stamp", [None, "0" * 64, ""])
def test_a_module_without_its_sources_stamp_is_stale_and_the_status_says_how_to_rebuild(monkeypatch, stamp):
    """A missing stamp (an old build) is as stale as a wrong one: neither is loaded."""
    import importlib

    module = importlib.import_module("m3t1r.model._native_newton")
    if stamp is None:
        monkeypatch.delattr(module, "source_sha256")
    else:
        monkeypatch.setattr(module, "source_sha256", stamp)
    assert native_status.load_compiled() == (None, native_status.STALE)
    expected = "no: older than its source (make native, or python tools/build_native.py)"
    assert native_status.compiled_newton_status() == expected


def test_an_install_without_the_sources_trusts_its_build(monkeypatch, tmp_path):
    import importlib

    module = importlib.import_module("m3t1r.model._native_newton")
    monkeypatch.setattr(module, "source_sha256", "0" * 64)
    monkeypatch.setattr(native_status, "SOURCES", (tmp_path / "_native_newton.cpp", native_status.SOURCES[1]))
    assert native_status.load_compiled() == (module, "")
    assert native_status.compiled_newton_status() == "yes"


def test_a_module_not_built_is_reported_with_how_to_build_it(monkeypatch):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name.endswith("_native_newton") else find_spec(name, *a)
    )
    assert native_status.load_compiled() == (None, native_status.NOT_BUILT)
    assert native_status.compiled_newton_status() == "no: not built (make native, or python tools/build_native.py)"


def test_a_module_that_does_not_load_is_reported_with_the_import_error_alone(monkeypatch):
    import importlib

    import_module = importlib.import_module

    def failing(name, *args):
        if name.endswith("_native_newton"):
            raise ImportError("undefined symbol: pinocchio_x")
        return import_module(name, *args)

    monkeypatch.setattr(importlib, "import_module", failing)
    assert native_status.load_compiled() == (None, "it does not load (undefined symbol: pinocchio_x)")
    assert native_status.compiled_newton_status() == "no: it does not load (undefined symbol: pinocchio_x)"


def test_newton_rules_at_their_bounds_name_the_rule_and_the_value():
    """Zero is a valid rcond floor (never refuse as singular) and a valid iteration budget (only the
    start is judged); a zero contraction or chord threshold is not, and the refusal quotes the value."""
    assert NewtonRules(singular_rcond=0.0, max_iterations=0).compiled() == (1e-12, 0, 0.0, 0.3, 0.05, 1e-4, 1e-6)
    refusals = {
        "chord_below": "Newton rules: chord_below must be a number > 0, got 0.0",
        "chord_contraction": "Newton rules: chord_contraction must be in (0, 1), got 0.0",
        "max_step": "Newton rules: max_step must be a number > 0, got 0.0",
    }
    for name, message in refusals.items():
        with pytest.raises(InvalidInputError) as caught:
            NewtonRules(**{name: 0.0})
        assert str(caught.value) == message
    with pytest.raises(InvalidInputError) as caught:
        NewtonRules(max_iterations=True)
    assert str(caught.value) == "Newton rules: max_iterations must be an integer >= 0, got True"
