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
