"""Property-based tests (hypothesis) of the POE helpers: exp/log round trips, batched adjoints and
log Jacobians against Pinocchio, and the serial error Jacobian against finite differences at random
configurations. Few, small examples: each test runs in about a second."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from m3t1r.calibration.serial_robots import load_example_robot
from m3t1r.model.poe import (
    Placement,
    SerialChain,
    adjoint_matrices,
    forward_and_error_jacobians,
    jlog3_batch,
    log3_batch,
    perturb,
    placement_of,
    poe_forward,
    skew,
)

FAST = settings(max_examples=30, deadline=None, derandomize=True)  # reproducible mutation runs
finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
vector3 = arrays(np.float64, 3, elements=finite)
twist = arrays(np.float64, 6, elements=finite)


def _rotation_vector(direction: np.ndarray, angle: float) -> np.ndarray:
    norm = np.linalg.norm(direction)
    return np.zeros(3) if norm < 1e-6 else direction / norm * angle


@FAST
@given(vector3, st.floats(0.0, np.pi - 1e-3))
def test_log3_batch_inverts_exp3_below_pi(direction, angle):
    w = _rotation_vector(direction, angle)
    logs, angles = log3_batch(pin.exp3(w)[None])
    np.testing.assert_allclose(logs[0], w, atol=1e-9)
    assert angles[0] == pytest.approx(np.linalg.norm(w), abs=1e-9)


@FAST
@given(vector3, st.floats(np.pi - 0.2, np.pi))
def test_log3_batch_near_pi_gives_the_same_rotation(direction, angle):
    w = _rotation_vector(direction, angle)
    if not w.any():
        return
    logs, angles = log3_batch(pin.exp3(w)[None])
    np.testing.assert_allclose(pin.exp3(logs[0]), pin.exp3(w), atol=1e-9)
    assert angles[0] == pytest.approx(angle, abs=1e-7)


@FAST
@example(direction=np.array([0.0, 1.0, 1.0]), scale=0.1875)  # pin.Jlog3 off by 1.5e-9 at 1.9e-4 rad
@given(vector3, st.floats(0.0, 3.0))
def test_jlog3_batch_equals_pinocchio_small_and_large(direction, scale):
    for angle in (scale, scale * 1e-3, scale * 1e-7):
        w = _rotation_vector(direction, angle)
        jlog = jlog3_batch(w[None], np.array([np.linalg.norm(w)]))[0]
        # pin.Jlog3 reads the angle back from the matrix and loses ~1e-6 relative at small angles
        # (its [w]^2 coefficient is off by up to 1/12, i.e. by angle^2 in the matrix); the inverse
        # of the right Jacobian of exp3 (from the vector itself) is exact.
        np.testing.assert_allclose(jlog, pin.Jlog3(pin.exp3(w)), atol=1e-9 + (angle**2 if angle < 1e-2 else 0.0))
        np.testing.assert_allclose(jlog @ pin.Jexp3(w), np.eye(3), atol=1e-12)


@FAST
@given(twist, vector3)
def test_adjoint_and_skew_match_pinocchio(xi, other):
    pose = pin.exp6(xi)  # rotation below sqrt(3) < pi
    np.testing.assert_allclose(adjoint_matrices(pose.homogeneous[None])[0], pose.action, atol=1e-12)
    np.testing.assert_allclose(skew(xi[:3]) @ other, np.cross(xi[:3], other), atol=1e-15)
    # exp6 / log6 round trip for twists with rotation below pi
    np.testing.assert_allclose(pin.log6(pose).vector, xi, atol=1e-9)


@pytest.fixture(scope="module")
def ur5():
    model = load_example_robot("ur5")
    return model, SerialChain.from_model(model, "tool0")


@FAST
@given(twist.map(lambda v: v * 1e-2), st.integers(0, 6))
def test_perturb_then_read_back_is_the_error_twist(ur5, error, index):
    model, chain = ur5
    placement = chain.placements()[index]
    moved = perturb(model, {placement: error})
    relative = placement_of(model, placement).actInv(placement_of(moved, placement))
    np.testing.assert_allclose(pin.log6(relative).vector, error, atol=1e-12)


@settings(max_examples=8, deadline=None, derandomize=True)
@given(arrays(np.float64, 6, elements=st.floats(-3.0, 3.0)), st.integers(0, 41))
def test_error_jacobian_matches_finite_differences(ur5, q, column):
    """Column k of the WORLD error Jacobian is log6(g(x + eps e_k) g(x)^-1) / eps (eq. 18)."""
    model, chain = ur5
    placement = chain.placements()[column // 6]
    jacobian = forward_and_error_jacobians(chain, model, q[None])[1][0]
    eps = 1e-7
    twists = []
    for sign in (1.0, -1.0):
        error = np.zeros(6)
        error[column % 6] = sign * eps
        twists.append(
            pin.log6(
                poe_forward(chain, perturb(model, {placement: error}), q) * poe_forward(chain, model, q).inverse()
            ).vector
        )
    np.testing.assert_allclose((twists[0] - twists[1]) / (2 * eps), jacobian[:, column], atol=1e-6)


def test_placement_names_cover_every_parameter(ur5):
    _, chain = ur5
    names = chain.parameter_names()
    assert len(names) == chain.n_parameters == 6 * len(chain.placements())
    assert isinstance(chain.placements()[0], Placement)
