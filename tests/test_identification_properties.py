"""Property-based tests (hypothesis) of the linear solvers: recursive least squares equals the batch
solution whatever the order and grouping of the blocks, and the batch fit is invariant under a
rescaling of the parameters."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from m3t1r.calibration.identification import RecursiveLeastSquares, batch_least_squares

FAST = settings(max_examples=25, deadline=None, derandomize=True)  # reproducible mutation runs


def _problem(seed: int, n_blocks: int = 8, rows: int = 3, n_parameters: int = 4):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n_blocks * rows, n_parameters)) * rng.uniform(0.1, 10.0, n_parameters)
    y = A @ rng.normal(size=n_parameters) + rng.normal(size=n_blocks * rows) * 1e-3
    weights = 1.0 / rng.uniform(0.5e-3, 2e-3, n_blocks * rows)
    return A.reshape(n_blocks, rows, -1), y.reshape(n_blocks, rows), weights.reshape(n_blocks, rows)


@FAST
@given(st.integers(0, 2**16), st.permutations(range(8)), st.integers(1, 4))
def test_recursive_equals_batch_for_any_order_and_grouping(seed, order, group):
    A, y, w = _problem(seed)
    batch = batch_least_squares(A.reshape(-1, 4), y.reshape(-1), w.reshape(-1))
    rls = RecursiveLeastSquares(4)
    order = list(order)
    for start in range(0, len(order), group):
        pick = order[start : start + group]
        rls.update(A[pick].reshape(-1, 4), y[pick].reshape(-1), w[pick].reshape(-1))
    np.testing.assert_allclose(rls.estimate, batch.x, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(rls.covariance, batch.covariance, rtol=1e-7, atol=1e-18)
    chi2 = batch.variance_factor * (A.shape[0] * A.shape[1] - batch.rank)
    np.testing.assert_allclose(rls.weighted_residual_sum_of_squares, chi2, rtol=1e-6)
    assert rls.n_rows == A.shape[0] * A.shape[1]


@FAST
@given(st.integers(0, 2**16), st.lists(st.floats(1e-3, 1e3), min_size=4, max_size=4))
def test_batch_fit_is_equivariant_under_parameter_scaling(seed, scales):
    A, y, w = _problem(seed)
    A, y, w = A.reshape(-1, 4), y.reshape(-1), w.reshape(-1)
    scales = np.array(scales)
    plain = batch_least_squares(A, y, w)
    scaled = batch_least_squares(A / scales, y, w)  # parameters x * scales
    np.testing.assert_allclose(scaled.x, plain.x * scales, rtol=1e-7)
    np.testing.assert_allclose(scaled.std, plain.std * scales, rtol=1e-6)
    np.testing.assert_allclose(scaled.variance_factor, plain.variance_factor, rtol=1e-7)
