"""Property-based tests (hypothesis) of the closed-loop kinematics: FK(IK(x)) = x over the
workspace box (and for yaw targets shifted by whole turns), and the closure Jacobian against
central differences at random configurations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from m3t1r.model.design import NOMINAL
from m3t1r.model.kinematics import ClosedLoopSolver, yaw_of

BOX = NOMINAL.workspace
FAST = settings(max_examples=20, deadline=None, derandomize=True)  # reproducible mutation runs
target = st.tuples(st.floats(*BOX.x), st.floats(*BOX.y), st.floats(*BOX.z), st.floats(*BOX.theta))


@pytest.fixture(scope="module")
def solvers(mechanism):
    return ClosedLoopSolver(mechanism), ClosedLoopSolver(mechanism)


@FAST
@given(target, st.integers(-2, 2))
def test_forward_of_inverse_is_the_target(mechanism, solvers, pose, turns):
    ik_solver, fk_solver = solvers
    x, y, z, theta = pose
    ik = ik_solver.inverse((x, y, z, theta + 2 * math.pi * turns), q_init=mechanism.home)
    fk = fk_solver.forward(ik.actuators, q_init=mechanism.home)
    np.testing.assert_allclose(fk.pose.translation, [x, y, z], atol=1e-9)
    assert math.remainder(yaw_of(fk.pose.rotation) - theta, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(fk.q, ik.q, atol=1e-8)  # same assembly branch as the IK's


@settings(max_examples=6, deadline=None, derandomize=True)
@given(arrays(np.float64, 20, elements=st.floats(-0.2, 0.2)), st.booleans())
def test_closure_jacobian_matches_central_differences(mechanism, solvers, offset, all_rows):
    solver = solvers[0]
    q = mechanism.home + offset[: mechanism.model.nv]
    jacobian = solver.closure_jacobian(q, all_rows=all_rows)
    eps = 1e-6
    numeric = np.empty_like(jacobian)
    for k in range(mechanism.model.nv):
        step = np.zeros(mechanism.model.nv)
        step[k] = eps
        numeric[:, k] = (solver.closure_residual(q + step, all_rows) - solver.closure_residual(q - step, all_rows)) / (
            2 * eps
        )
    np.testing.assert_allclose(jacobian, numeric, atol=1e-7)
