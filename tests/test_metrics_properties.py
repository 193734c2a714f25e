"""Property-based tests (hypothesis) of the pose-error metrics: the held-out error is invariant under
a change of the measurement frame (both pose sets re-expressed in any other frame), symmetric, and
its rotation angle agrees with |log3| over the whole (0, pi) range."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from m3t1r.metrics import pose_errors_between, rotation_angles

FAST = settings(max_examples=30, deadline=None, derandomize=True)  # reproducible mutation runs
twist = arrays(np.float64, 6, elements=st.floats(-1.0, 1.0))


def _poses(seed: int, n: int, spread: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = np.array([pin.exp6(rng.normal(size=6)).homogeneous for _ in range(n)])
    b = np.array([g @ pin.exp6(rng.normal(size=6) * spread).homogeneous for g in a])
    return a, b


@FAST
@given(st.integers(0, 2**16), twist.map(lambda v: v * 3.0), st.floats(1e-6, 0.5))
def test_pose_errors_are_invariant_under_a_change_of_measurement_frame(seed, frame_twist, spread):
    """Model and truth poses both expressed in a frame F instead of the base: F^-1 A vs F^-1 B."""
    a, b = _poses(seed, 6, spread)
    frame_inverse = pin.exp6(frame_twist).inverse().homogeneous
    in_base = pose_errors_between(a, b)
    in_frame = pose_errors_between(frame_inverse @ a, frame_inverse @ b)
    np.testing.assert_allclose(in_frame.position, in_base.position, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(in_frame.rotation, in_base.rotation, rtol=1e-9, atol=1e-12)
    swapped = pose_errors_between(b, a)
    np.testing.assert_allclose(swapped.position, in_base.position, rtol=0, atol=0)
    np.testing.assert_allclose(swapped.rotation, in_base.rotation, atol=1e-15)


@FAST
@given(arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)), st.floats(0.0, np.pi - 1e-6))
def test_rotation_angle_is_the_log3_norm(direction, angle):
    norm = np.linalg.norm(direction)
    w = np.zeros(3) if norm < 1e-6 else direction / norm * angle
    base = pin.exp3(np.array([0.3, -0.2, 0.1]))
    result = rotation_angles(base[None], (base @ pin.exp3(w))[None])[0]
    assert abs(result - np.linalg.norm(w)) < 1e-9 * max(1.0, np.linalg.norm(w)) + 1e-15
