"""Kinematics tests that kill mutants the behaviour tests let through (docs/mutation.md).

Each test pins one decision of `m3t1r.model.kinematics` that a plausible bug would change: the yaw wrap
of IK targets beyond (-pi, pi], tolerance boundaries, and the typed errors of the solver.
"""

import math

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.errors import InvalidInputError, NotConvergedError, OutOfWorkspaceError
from m3t1r.model.kinematics import ClosedLoopSolver, yaw_of

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
# Survivors of the first `make mutation` run (docs/mutation.md)


def test_diagonal_blocks_of_a_block_triangular_pattern():
    """Rows/columns permuted lower block-triangular pattern: blocks {0, 2} (2 x 2) and {1} (1 x 1)."""
    from m3t1r.model.kinematics import diagonal_blocks

    pattern = np.array([[1, 0, 1], [1, 1, 0], [1, 0, 1]], dtype=bool)
    blocks = sorted((sorted(r.tolist()), sorted(c.tolist())) for r, c in diagonal_blocks(pattern))
    assert blocks == [([0, 2], [0, 2]), ([1], [1])]
    # Each row's matched column is one of its own non-zeros.
    for rows, cols in diagonal_blocks(pattern):
        assert pattern[np.ix_(rows, cols)].any(axis=1).all()
    from m3t1r.errors import SingularConfigurationError
    with pytest.raises(SingularConfigurationError, match="structurally singular"):
        diagonal_blocks(np.array([[1, 1], [0, 0]], dtype=bool))


@pytest.mark.parametrize("target, most", [((0.55, 0.6, -0.1, 0.3), 6), ((0.45, 0.3, -0.2, -0.6), 8),
                                          ((0.58, 0.8, -0.02, 0.7), 7)])
def test_cold_inverse_converges_quadratically(mechanism, target, most):
    """Exact Newton from home: a wrong yaw-row Jacobian still converges, but in more steps."""
    assert ClosedLoopSolver(mechanism).inverse(target).iterations <= most


def test_closure_residual_by_closure_sizes(mechanism):
    from m3t1r.model.description import closure_residual_by_closure

    sizes = {spec.name: residual.shape for spec, residual in closure_residual_by_closure(mechanism, mechanism.home)}
    assert sizes["platform"] == (6,) and sizes["five_bar_I"] == (3,)
    solver = ClosedLoopSolver(mechanism)
    full = np.concatenate([r for _, r in closure_residual_by_closure(mechanism, mechanism.home + 0.01)])
    np.testing.assert_allclose(solver.closure_residual(mechanism.home + 0.01, all_rows=True), full, atol=1e-15)


def test_bad_configuration_is_named(solver, mechanism):
    with pytest.raises(InvalidInputError, match="configuration q"):
        solver.closure_residual(np.full(mechanism.model.nq, np.nan))
    with pytest.raises(InvalidInputError, match="configuration q"):
        solver.closure_jacobian(np.zeros(3))
    assert solver.mobility(mechanism.home, all_rows=True) == 4


# ------------------------------------------------------------------------------------------------
# Functions only the batch and calibration tests reached (mutation run of 2026-11-29: "no tests")
def test_rehomed_assembles_home_at_the_given_sliders_and_keeps_everything_else(mechanism):
    from conftest import perturb_every_origin

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
    np.testing.assert_allclose((operator @ solver.data.J) * solver._row_masks[False], jacobian, atol=1e-15)
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
    assert solver._batch_kinematics() is solver._batch_kinematics()  # built once
    np.testing.assert_array_equal(solver.last_q, mechanism.home)  # the warm start is left alone


def test_reset_forgets_every_warm_start(mechanism):
    solver = ClosedLoopSolver(mechanism)
    solver.inverse(TARGET)
    solver.forward(solver.last_q[solver.actuated] + 0.01)
    solver.inverse(TARGET + [0.01, 0.0, 0.0, 0.05])
    solver.reset()
    for name in ("_tangent", "_previous", "_last_branch", "_lu_inverse", "_last_inverse_branch", "_last_task"):
        assert getattr(solver, name) is None, name
    np.testing.assert_array_equal(solver.last_q, mechanism.home)
    solver.last_q[0] += 1.0  # a copy: home itself is untouched
    assert mechanism.home[0] != solver.last_q[0]


def test_diagonal_blocks_follow_the_matched_columns_not_the_rows():
    """The only perfect matching is the cycle r0->c1, r1->c2, r2->c0 (and r3->c3), no cycle among
    the rows: four 1 x 1 blocks, each on its own matched entry."""
    from m3t1r.errors import SingularConfigurationError
    from m3t1r.model.kinematics import diagonal_blocks

    pattern = np.array([[0, 1, 0, 0], [0, 1, 1, 0], [1, 0, 1, 0], [1, 0, 0, 1]], dtype=bool)
    blocks = sorted((r.tolist(), c.tolist()) for r, c in diagonal_blocks(pattern))
    assert blocks == [([0], [1]), ([1], [2]), ([2], [0]), ([3], [3])]
    with pytest.raises(SingularConfigurationError) as caught:
        diagonal_blocks(np.array([[1, 1], [0, 0]], dtype=bool))
    assert str(caught.value) == "the closure system is structurally singular (residual nan after 0 iterations)"


def test_det_sign_from_lu_factors():
    from scipy.linalg import lapack

    from m3t1r.model.kinematics import _det_sign

    rng = np.random.default_rng(4)
    signs = []
    for n in (3, 4, 5, 6):
        for _ in range(6):
            matrix = rng.normal(size=(n, n))
            signs.append(np.linalg.det(matrix) > 0)
            assert _det_sign(lapack.dgetrf(matrix)) == signs[-1]
    assert any(signs) and not all(signs)
    assert _det_sign(lapack.dgetrf(np.eye(4))) is True


def test_mobility_counts_rows_and_singular_values_as_documented(mechanism):
    from conftest import perturb_every_origin

    from m3t1r.model.kinematics import rehomed

    perturbed = rehomed(mechanism.with_model(perturb_every_origin(mechanism.model, np.random.default_rng(3), 1e-3, 1e-3)))
    solver = ClosedLoopSolver(perturbed)
    assert solver.mobility(perturbed.home) == 4  # enforced rows by default
    assert solver.mobility(perturbed.home, all_rows=True) == 0  # the redundant rows no longer are
    nominal = ClosedLoopSolver(mechanism)
    singular = np.linalg.svd(nominal.closure_jacobian(mechanism.home), compute_uv=False)
    for rank_tolerance in (0.1, 0.28):
        expected = mechanism.model.nv - int(np.sum(singular > rank_tolerance * singular[0]))
        assert nominal.mobility(mechanism.home, rank_tolerance=rank_tolerance) == expected


def test_check_actuators_limits_are_inclusive_and_a_copy(solver):
    lower, upper = solver._act_lower.copy(), solver._act_upper.copy()
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
        assert str(caught.value) == (f"actuator 'q21' = {beyond[2]:.6g} is beyond its joint limit "
                                     f"[{lower[2]:.6g}, {upper[2]:.6g}] (SI units: metres for sliders)")
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
    """Measured: 40 Newton steps over the path (75 without the last solution's factors)."""
    solver = ClosedLoopSolver(mechanism)
    steps = []
    for k in range(12):
        target = TARGET + 0.002 * k * np.array([2.0, 1.5, -1.0, 10.0]) + 0.0005 * k * k * np.array([1.0, -1.0, 0.5, 2.0])
        result = solver.inverse(target)
        steps.append(result.iterations)
        np.testing.assert_allclose(result.actuators, ClosedLoopSolver(mechanism).inverse(target).actuators, atol=1e-9)
    assert sum(steps) <= 42, steps


@pytest.mark.parametrize("target, most", [((0.55, 0.6, -0.1, 0.3), 9), ((0.45, 0.3, -0.2, -0.6), 8),
                                          ((0.58, 0.8, -0.02, 0.7), 8)])
def test_cold_inverse_of_a_tilting_machine_converges_quadratically(mechanism, target, most):
    """A perturbed machine tilts its platform by 0.05-0.14 rad: the yaw row's Jacobian terms in the
    tilt (c_z) count. Measured 8, 7, 7 steps; one of slack."""
    from conftest import perturb_every_origin

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
        "configuration's branch) (residual ")
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
    from m3t1r.model import kinematics

    key = (mechanism.closures, mechanism.actuated_joints, tuple(mechanism.model.names))
    saved = kinematics._BLOCK_CACHE.pop(key, None)
    try:
        blocks = ClosedLoopSolver(mechanism)._branch_blocks
    finally:
        if saved is not None:
            kinematics._BLOCK_CACHE[key] = saved
    found = sorted((sorted(r.tolist()), sorted(c.tolist())) for r, c in blocks)
    assert found == [([0, 1], [2, 7]), ([2, 3], [1, 9]), ([4, 5, 10, 11, 12, 13, 14, 15], [3, 4, 5, 6, 13, 14, 15, 16]),
                     ([6, 7], [12, 17]), ([8, 9], [11, 19])]


def test_branch_signature_reads_every_block_by_its_size():
    """A 1 x 1 block by its sign, a 2 x 2 by its closed-form determinant, larger ones by LU."""
    from m3t1r.model.kinematics import _BranchSignature

    blocks = [(np.array([0]), np.array([0])), (np.array([1, 2]), np.array([1, 2])),
              (np.array([3, 4, 5]), np.array([3, 4, 5]))]
    signature = _BranchSignature(blocks, 6)
    jac = np.eye(6)
    jac[0, 0] = 0.5
    jac[1:3, 1:3] = [[1.0, 2.0], [3.0, 4.0]]  # det -2 (1 * 4 - 2 / 3 would be positive)
    jac[3:, 3:] = [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]  # det -2, needs a pivot
    assert signature(jac) == b"\x01\x00\x00"
    jac[0, 0], jac[1:3, 1:3], jac[5, 5] = -0.5, [[4.0, 1.0], [3.0, 2.0]], -2.0  # every sign flipped
    assert signature(jac) == b"\x00\x01\x01"


def test_a_failed_inverse_leaves_a_usable_warm_start(mechanism):
    """A failed solve drops its factors and branch: the next warm solve starts from the last good one."""
    solver = ClosedLoopSolver(mechanism)
    solver.inverse(TARGET)
    with pytest.raises(OutOfWorkspaceError):
        solver.inverse(np.array([3.0, 3.0, 1.0, 0.0]))
    near = TARGET + [0.01, 0.0, 0.0, 0.05]
    np.testing.assert_allclose(solver.inverse(near).actuators, ClosedLoopSolver(mechanism).inverse(near).actuators,
                               atol=1e-10)
