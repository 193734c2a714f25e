"""Generic identification solvers: base parameters, batch and recursive least squares, LM."""

from __future__ import annotations

import warnings

import numpy as np
import pinocchio as pin
import pytest
import scipy.stats  # a reference for outlier_gate, which the package computes with scipy.special

from m3t1r.calibration.identification import (
    RecursiveLeastSquares,
    batch_least_squares,
    levenberg_marquardt,
    outlier_gate,
    select_base_parameters,
)
from m3t1r.errors import IdentificationError, InvalidInputError, PoorExcitationWarning


def random_blocks(n_blocks: int, rows: int, n_parameters: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A well-posed weighted linear problem split into blocks, as poses of a calibration would be."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n_blocks * rows, n_parameters)) * rng.uniform(0.1, 10.0, n_parameters)
    x = rng.normal(size=n_parameters)
    sigma = rng.uniform(0.5, 2.0, n_blocks * rows) * 1e-3
    y = A @ x + rng.normal(size=sigma.size) * sigma
    return A, y, 1.0 / sigma


# --------------------------------------------------------------------------------------------------
# Base parameters


def test_base_parameters_drop_dependent_and_zero_columns() -> None:
    rng = np.random.default_rng(0)
    independent = rng.normal(size=(60, 5)) * np.array([1e-3, 1.0, 1e3, 1.0, 1.0])  # mixed units
    dependent = independent[:, [1]] - 2.0 * independent[:, [3]]
    jacobian = np.hstack([independent[:, :2], np.zeros((60, 1)), independent[:, 2:], dependent])
    names = ["a", "b", "zero", "c", "d", "e", "b-2d"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        base = select_base_parameters(jacobian, names)
    assert base.rank == 5
    assert base.zero_columns == ("zero",)
    assert list(base.indices) == sorted(base.indices)
    assert {"a", "c", "e"} <= set(base.names)  # only the b, d, b-2d triple is redundant
    assert len({"b", "d", "b-2d"} & set(base.names)) == 2
    assert base.singular_values.size == 7 and base.singular_values[5] < 1e-12 * base.singular_values[0]
    assert base.r_diag_ratio.size == 6 and base.r_diag_ratio[-1] < 1e-12 < base.r_diag_ratio[-2]
    kept = jacobian[:, base.indices]
    np.testing.assert_allclose(base.condition_number, np.linalg.cond(kept / np.linalg.norm(kept, axis=0)))


def test_poorly_excited_parameters_warn() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(40, 3))
    nearly = a[:, [0]] + 1e-8 * rng.normal(size=(40, 1))  # distinguishable, but barely
    with pytest.warns(PoorExcitationWarning, match="condition number"):
        base = select_base_parameters(np.hstack([a, nearly]), ["x", "y", "z", "x'"])
    assert base.rank == 4 and base.condition_number > 1e6


def test_base_parameters_validate_input() -> None:
    with pytest.raises(InvalidInputError, match="names"):
        select_base_parameters(np.ones((4, 2)), ["only one"])
    with pytest.raises(IdentificationError, match="zero"):
        select_base_parameters(np.zeros((4, 2)), ["a", "b"])
    with pytest.raises(InvalidInputError, match="row 1, column 0"):
        select_base_parameters(np.array([[1.0, 0.0], [np.nan, 1.0]]), ["a", "b"])


# --------------------------------------------------------------------------------------------------
# Batch least squares


def test_batch_least_squares_matches_normal_equations_and_noise_model() -> None:
    A, y, w = random_blocks(30, 6, 12, seed=2)
    fit = batch_least_squares(A, y, w)
    Aw = A * w[:, None]
    information = Aw.T @ Aw
    np.testing.assert_allclose(fit.x, np.linalg.solve(information, Aw.T @ (y * w)), rtol=1e-9)
    np.testing.assert_allclose(fit.covariance, np.linalg.inv(information), rtol=1e-9)
    np.testing.assert_allclose(fit.std, np.sqrt(np.diag(np.linalg.inv(information))), rtol=1e-9)
    assert fit.rank == 12
    assert 0.7 < fit.variance_factor < 1.3  # the weights are the true inverse noise levels
    np.testing.assert_allclose(fit.residual_rms, np.sqrt(np.mean((A @ fit.x - y) ** 2)))
    scaled = batch_least_squares(A, y, w, covariance_from="residuals")
    np.testing.assert_allclose(scaled.covariance, fit.covariance * fit.variance_factor, rtol=1e-12)


def test_batch_least_squares_is_minimum_norm_when_rank_deficient() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(50, 4))
    A = np.hstack([A, A[:, [0]] + A[:, [1]]])
    y = rng.normal(size=50)
    fit = batch_least_squares(A, y)
    assert fit.rank == 4
    np.testing.assert_allclose(fit.x, np.linalg.pinv(A) @ y, atol=1e-12)
    # The unobservable direction [1, 1, 0, 0, -1] carries no estimate and no information.
    null = np.array([1.0, 1.0, 0.0, 0.0, -1.0])
    assert abs(fit.x @ null) < 1e-12 and np.linalg.norm(fit.covariance @ null) < 1e-10


# --------------------------------------------------------------------------------------------------
# Recursive least squares


def test_recursive_least_squares_equals_batch() -> None:
    A, y, w = random_blocks(25, 6, 20, seed=4)
    rls = RecursiveLeastSquares(20)
    for k in range(25):
        rows = slice(6 * k, 6 * k + 6)
        estimate = rls.update(A[rows], y[rows], w[rows])
        # Minimum-norm batch answer at every step, including the first, rank-deficient ones.
        batch = batch_least_squares(A[: rows.stop], y[: rows.stop], w[: rows.stop], rcond=1e-12)
        assert np.linalg.norm(estimate - batch.x) <= 1e-9 * max(1.0, np.linalg.norm(batch.x))
    fit = batch_least_squares(A, y, w)
    np.testing.assert_allclose(rls.estimate, fit.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(rls.covariance, fit.covariance, rtol=1e-9)
    residual = (A @ fit.x - y) * w
    np.testing.assert_allclose(rls.weighted_residual_sum_of_squares, residual @ residual, rtol=1e-9)
    assert rls.n_rows == A.shape[0]


def test_recursive_least_squares_forgetting_and_prior() -> None:
    A, y, w = random_blocks(10, 6, 5, seed=5)
    lam = 0.9
    rls = RecursiveLeastSquares(5, forgetting_factor=lam)
    for k in range(10):
        rls.update(A[6 * k : 6 * k + 6], y[6 * k : 6 * k + 6], w[6 * k : 6 * k + 6])
    # Forgetting = batch with block k down-weighted by sqrt(lambda)^(K-1-k).
    decay = np.repeat(np.sqrt(lam) ** np.arange(9, -1, -1), 6)
    np.testing.assert_allclose(rls.estimate, batch_least_squares(A, y, w * decay).x, rtol=1e-9)

    mean, std = np.full(5, 0.5), np.full(5, 0.1)
    prior = RecursiveLeastSquares(5, prior_mean=mean, prior_std=std)
    estimate = prior.update(A[:3], y[:3], w[:3])  # three rows only: the prior makes it well posed
    stacked = batch_least_squares(np.vstack([A[:3], np.eye(5)]), np.r_[y[:3], mean], np.r_[w[:3], 1.0 / std])
    np.testing.assert_allclose(estimate, stacked.x, rtol=1e-9)
    with pytest.raises(InvalidInputError, match="columns"):
        prior.update(np.ones((2, 4)), np.ones(2))


# --------------------------------------------------------------------------------------------------
# Levenberg-Marquardt


class Rosenbrock:
    """r = [10 (x1 - x0^2), 1 - x0]: the classic curved valley, minimum 0 at (1, 1)."""

    def residual_and_jacobian(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]), np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])

    def retract(self, x: np.ndarray, step: np.ndarray) -> np.ndarray:
        return x + step


class RotationFit:
    """Find R minimising sum ||R a_i - b_i||^2 / sigma^2 over SO(3), with R <- R exp3(dx)."""

    def __init__(self, a: np.ndarray, b: np.ndarray, sigma: float) -> None:
        self.a, self.b, self.sigma = a, b, sigma

    def residual_and_jacobian(self, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rotated = self.a @ rotation.T
        residual = (rotated - self.b).reshape(-1) / self.sigma
        # d(R exp(dx) a) = -R [a]x dx
        jacobian = -np.einsum("ij,njk->nik", rotation, np.array([pin.skew(v) for v in self.a])) / self.sigma
        return residual, jacobian.reshape(-1, 3)

    def retract(self, rotation: np.ndarray, step: np.ndarray) -> np.ndarray:
        return rotation @ pin.exp3(step)


def test_levenberg_marquardt_rosenbrock() -> None:
    result = levenberg_marquardt(Rosenbrock(), np.array([-1.2, 1.0]), max_iterations=100)
    assert result.converged, result.termination
    np.testing.assert_allclose(result.state, [1.0, 1.0], atol=1e-10)
    assert result.cost < 1e-20
    assert all(b <= a for a, b in zip(result.cost_history, result.cost_history[1:]))


def test_levenberg_marquardt_on_a_manifold_matches_closed_form() -> None:
    rng = np.random.default_rng(6)
    truth = pin.exp3(np.array([2.0, -1.0, 0.5]))
    a = rng.normal(size=(40, 3))
    b = a @ truth.T + rng.normal(scale=1e-3, size=(40, 3))
    result = levenberg_marquardt(RotationFit(a, b, 1e-3), np.eye(3))
    assert result.converged and result.iterations < 20
    # Closed-form orthogonal Procrustes solution of the same problem.
    u, _, vt = np.linalg.svd(b.T @ a)
    best = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    assert np.linalg.norm(pin.log3(best.T @ result.state)) < 1e-9
    np.testing.assert_allclose(result.state.T @ result.state, np.eye(3), atol=1e-12)


def test_levenberg_marquardt_reports_non_convergence() -> None:
    result = levenberg_marquardt(Rosenbrock(), np.array([-1.2, 1.0]), max_iterations=2)
    assert not result.converged and result.termination == "max_iterations" and result.iterations == 2


@pytest.mark.parametrize("dof", [1, 3, 6, 12])
def test_outlier_gate_is_the_chi2_quantile_of_the_two_sided_normal_tail(dof: int) -> None:
    for sigma in (2.0, 3.0, 5.0, 8.0):
        expected = scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(sigma), dof)
        assert outlier_gate(sigma, dof) == pytest.approx(expected, rel=1e-12)
    assert outlier_gate(1.0, 1) == pytest.approx(1.0, rel=1e-12)  # chi^2_1 is N(0, 1) squared
