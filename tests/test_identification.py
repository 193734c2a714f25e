"""Generic identification solvers: base parameters, batch and recursive least squares, LM."""

from __future__ import annotations

import warnings

import numpy as np
import pinocchio as pin
import pytest
import scipy.linalg
import scipy.stats  # a reference for outlier_gate, which the package computes with scipy.special

from m3t1r.calibration import identification
from m3t1r.calibration.identification import (
    LMSettings,
    RecursiveLeastSquares,
    batch_least_squares,
    best_index,
    checked_outlier_sigma,
    forward_selection,
    levenberg_marquardt,
    outlier_gate,
    outlier_poses,
    parameter_columns,
    pivoted_qr,
    select_base_parameters,
    unexcited_parameters,
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
    result = levenberg_marquardt(Rosenbrock(), np.array([-1.2, 1.0]), LMSettings(max_iterations=100))
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
    result = levenberg_marquardt(Rosenbrock(), np.array([-1.2, 1.0]), LMSettings(max_iterations=2))
    assert not result.converged and result.termination == "max_iterations" and result.iterations == 2


@pytest.mark.parametrize("dof", [1, 3, 6, 12])
def test_outlier_gate_is_the_chi2_quantile_of_the_two_sided_normal_tail(dof: int) -> None:
    for sigma in (2.0, 3.0, 5.0, 8.0):
        expected = scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(sigma), dof)
        assert outlier_gate(sigma, dof) == pytest.approx(expected, rel=1e-12)
    assert outlier_gate(1.0, 1) == pytest.approx(1.0, rel=1e-12)  # chi^2_1 is N(0, 1) squared


# ==================================================================================================
# Termination rules, tolerances, base parameters and selection, exactly
#
# Every termination reason of `levenberg_marquardt` is asserted with its iteration count and the rule that
# fired; NaN and inf are fed to the solver; tolerances are probed at their boundary.
# ==================================================================================================


class ExponentialFit:
    """r_i = a exp(b t_i) - y_i with noisy y: a non-zero minimum, so only the cost or step rule can stop."""

    def __init__(self, seed: int = 0, poison=None) -> None:
        rng = np.random.default_rng(seed)
        self.t = np.linspace(0.0, 1.0, 30)
        self.y = 2.0 * np.exp(-1.5 * self.t) + rng.normal(0.0, 0.01, self.t.size)
        self.poison = poison  # (what, value, at_call): put a NaN or inf into the output
        self.calls = 0

    def residual_and_jacobian(self, x: np.ndarray):
        self.calls += 1
        e = np.exp(x[1] * self.t)
        r = x[0] * e - self.y
        J = np.column_stack((e, x[0] * self.t * e))
        if self.poison is not None and self.calls >= self.poison[2]:
            what, value, _ = self.poison
            (r if what == "r" else J)[3] = value
        return r, J

    def retract(self, x: np.ndarray, step: np.ndarray) -> np.ndarray:
        return x + step


X0 = np.array([1.0, 0.0])
# From here the relative decreases run 0.71, 0.97, 0.98, 0.14, 2.6e-6, 6.3e-12, ...: a tolerance
# of 1e-7 fires at step 6, one 100x looser at step 5.
X_FAR = np.array([0.5, 1.0])


def _decreases(result):
    history = np.array(result.cost_history)
    return history[:-1] - history[1:], history[:-1]


def test_relative_cost_rule_stops_at_the_first_small_decrease():
    tolerance = 1e-7
    result = levenberg_marquardt(
        ExponentialFit(),
        X_FAR,
        LMSettings(cost_tolerance=tolerance, step_tolerance=0.0, gradient_tolerance=0.0),
    )
    assert result.converged and result.termination == "cost"
    decrease, before = _decreases(result)
    assert decrease[-1] <= tolerance * before[-1]  # the rule that fired
    assert np.all(decrease[:-1] > tolerance * before[:-1])  # and did not fire earlier
    assert result.iterations == len(result.cost_history) - 1
    assert result.iterations == 6


def test_absolute_cost_rule_stops_at_the_first_small_decrease():
    absolute = 1e-10  # the cost is 1.5e-3: decreases of 4e-9 (step 5) then 1e-14 (step 6)
    result = levenberg_marquardt(
        ExponentialFit(),
        X_FAR,
        LMSettings(cost_tolerance=0.0, step_tolerance=0.0, gradient_tolerance=0.0, absolute_cost_tolerance=absolute),
    )
    assert result.termination == "cost"
    decrease, _ = _decreases(result)
    assert decrease[-1] <= absolute and np.all(decrease[:-1] > absolute)
    assert result.iterations == 6


def test_without_cost_rules_the_step_rule_stops():
    result = levenberg_marquardt(
        ExponentialFit(),
        X0,
        LMSettings(cost_tolerance=0.0, step_tolerance=1e-10, gradient_tolerance=0.0, max_iterations=200),
    )
    assert result.converged and result.termination == "step" and result.step_norm <= 1e-10
    # The step rule stops before the step is accepted: the iteration count includes that last solve.
    assert result.iterations == len(result.cost_history)


def test_gradient_rule_on_a_zero_residual_problem():
    class Line:
        def residual_and_jacobian(self, x):
            return np.array([x[0] - 1.0, 2.0 * (x[1] + 3.0)]), np.array([[1.0, 0.0], [0.0, 2.0]])

        def retract(self, x, step):
            return x + step

    result = levenberg_marquardt(
        Line(), np.zeros(2), LMSettings(gradient_tolerance=1e-8, cost_tolerance=0.0, step_tolerance=0.0)
    )
    assert result.termination == "gradient" and result.converged
    np.testing.assert_allclose(result.state, [1.0, -3.0], atol=1e-8)
    assert result.iterations == len(result.cost_history) - 1 and result.iterations <= 4
    # Already at the minimum: zero iterations, gradient rule, the step norm never computed.
    at_minimum = levenberg_marquardt(Line(), np.array([1.0, -3.0]))
    assert at_minimum.termination == "gradient" and at_minimum.iterations == 0 and np.isnan(at_minimum.step_norm)


def test_max_iterations_is_reported_not_converged():
    result = levenberg_marquardt(
        ExponentialFit(),
        X0,
        LMSettings(cost_tolerance=0.0, step_tolerance=0.0, gradient_tolerance=0.0, max_iterations=2),
    )
    assert result.termination == "max_iterations" and not result.converged and result.iterations == 2


@pytest.mark.parametrize("what, value", [("J", np.nan), ("J", np.inf), ("r", np.nan), ("r", np.inf)])
def test_non_finite_start_raises(what, value):
    with pytest.raises(IdentificationError, match="non-finite gradient at iteration 1"):
        levenberg_marquardt(ExponentialFit(poison=(what, value, 1)), X0)


def test_non_finite_jacobian_after_an_accepted_step_raises():
    # Call 1: the start; call 2: the first trial's residual and Jacobian (no residual-only method).
    with pytest.raises(IdentificationError, match="non-finite gradient at iteration 2"):
        levenberg_marquardt(ExponentialFit(poison=("J", np.nan, 2)), X0)


def test_non_finite_trial_cost_is_rejected_not_accepted():
    class Guarded(ExponentialFit):
        def residual(self, x):
            r, _ = self.residual_and_jacobian(x)
            return np.full_like(r, np.nan) if x[0] > 2.5 else r  # the undamped first step overshoots

    result = levenberg_marquardt(Guarded(), np.array([3.0, -3.0]), LMSettings(initial_damping=1e-9))
    assert result.converged and np.all(np.isfinite(result.cost_history))
    np.testing.assert_allclose(result.state, [2.0, -1.5], atol=0.05)


def test_stalled_when_the_jacobian_is_wrong():
    class WrongSign(ExponentialFit):
        def residual_and_jacobian(self, x):
            r, J = super().residual_and_jacobian(x)
            return r, -J

    result = levenberg_marquardt(WrongSign(), X0, LMSettings(step_tolerance=0.0))
    assert result.termination == "stalled" and not result.converged and result.iterations == 1
    assert result.cost == result.cost_history[0]  # nothing accepted
    # With the default step tolerance the ever more damped steps shrink below it first.
    assert levenberg_marquardt(WrongSign(), X0).termination == "step"


# --------------------------------------------------------------------------------------------------
# Tolerance boundaries of the linear solvers


def test_base_parameters_rank_tolerance_boundary():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(40, 3))
    weak = A[:, 0] + 1e-4 * rng.normal(size=40)  # independent at 1e-4 relative
    matrix = np.column_stack((A, weak))
    assert select_base_parameters(matrix, "abcd", rank_tolerance=1e-9).rank == 4
    assert select_base_parameters(matrix, "abcd", rank_tolerance=1e-2).rank == 3
    zero = np.column_stack((A, 1e-12 * A[:, 1]))
    base = select_base_parameters(zero, "abcd", rank_tolerance=1e-9)
    assert base.zero_columns == ("d",) and base.rank == 3
    with pytest.raises(InvalidInputError, match="rank_tolerance"):
        select_base_parameters(A, "abc", rank_tolerance=1.0)
    with pytest.raises(InvalidInputError, match="rank_tolerance"):
        select_base_parameters(A, "abc", rank_tolerance=0.0)


def test_batch_least_squares_variance_factor_near_one_from_both_sides():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(4000, 5))
    sigma = rng.uniform(0.5, 2.0, 4000) * 1e-3
    y = A @ rng.normal(size=5) + rng.normal(size=4000) * sigma
    fit = batch_least_squares(A, y, 1.0 / sigma)
    assert 0.93 < fit.variance_factor < 1.07
    assert fit.rank == 5
    # Weights of 1/sigma^2 (a whitening bug) would move it far from one.
    assert not 0.5 < batch_least_squares(A, y, 1.0 / sigma**2).variance_factor < 2.0


def test_recursive_least_squares_zero_forgetting_is_refused():
    with pytest.raises(InvalidInputError, match="forgetting_factor"):
        RecursiveLeastSquares(2, forgetting_factor=0.0)
    RecursiveLeastSquares(2, forgetting_factor=1.0)
    with pytest.raises(InvalidInputError, match="forgetting_factor"):
        RecursiveLeastSquares(2, forgetting_factor=1.0 + 1e-12)


# --------------------------------------------------------------------------------------------------
# Parameter names, outliers, forward selection and forced base parameters: tested here, in the
# module's own tests, rather than only through the assessment and CLI tests.


NAMES = ("q1.dt[0]", "q1.dt[1]", "q2.dt[0]", "tool.x")


def test_parameter_columns_by_name_and_by_placement_in_the_order_asked():
    assert parameter_columns(NAMES, ["q2.dt[0]", "q1", "tool.x"], "--fix") == [2, 0, 1, 3]
    assert parameter_columns(NAMES, [], "--fix") == []
    message = "--fix: 'q3' is neither a parameter (e.g. q1.dt[0]) nor a placement (e.g. q1: all its components)"
    with pytest.raises(InvalidInputError) as error:
        parameter_columns(NAMES, ["q1", "q3"], "--fix")
    assert str(error.value) == message
    with pytest.raises(InvalidInputError) as error:
        parameter_columns((), ["q3"], "--prior")
    assert str(error.value) == (
        "--prior: 'q3' is neither a parameter (e.g. q12.dt[3]) nor a placement (e.g. q12: all its components)"
    )
    with pytest.raises(InvalidInputError):
        parameter_columns(NAMES, ["q1.dt"], "--fix")  # only the part before ".dt[" names a placement
    # A bare string would be read letter by letter, a list holding a number is no list of names: refused.
    for wanted in ("q1", b"q1", ["q1", 3]):
        with pytest.raises(InvalidInputError) as error:
            parameter_columns(NAMES, wanted, "--fix")
        assert str(error.value) == f"--fix: expected a list of names such as ['q12'], got {wanted!r}"


def _blocks_with_d2(d2: np.ndarray, k: int) -> np.ndarray:
    blocks = np.zeros((d2.size, k))
    blocks[:, 0] = np.sqrt(d2)
    return blocks


@pytest.mark.parametrize("k", [1, 3, 6])
def test_outlier_gate_is_the_5_sigma_chi2_quantile_from_both_sides(k):
    import scipy.stats

    gate = scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(5.0), k)
    # The median d^2 is far below median(chi^2_k): the variance factor stays at one.
    d2 = np.r_[np.full(9, 1e-3), gate * (1 + 1e-9), gate * (1 - 1e-9)]
    flagged, scale = outlier_poses(_blocks_with_d2(d2, k))
    assert scale == 1.0
    assert list(np.flatnonzero(flagged)) == [9]
    # An explicit gate of 4 sigma.
    gate4 = scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(4.0), k)
    d2 = np.r_[np.full(9, 1e-3), gate4 * (1 + 1e-9), gate4 * (1 - 1e-9)]
    assert list(np.flatnonzero(outlier_poses(_blocks_with_d2(d2, k), sigma=4.0)[0])) == [9]


@pytest.mark.parametrize(("sigma", "gate"), [(None, None), (0, None), (0.0, None), (1, 1.0), (3, 3.0), (1000, 1000.0)])
def test_an_outlier_gate_of_none_or_zero_keeps_every_pose_and_1_to_1000_sigmas_is_a_gate(sigma, gate):
    assert checked_outlier_sigma(sigma) == gate


@pytest.mark.parametrize(
    ("sigma", "message"),
    [
        ("a", "expected a real number, got 'a'"),
        (float("nan"), "expected a finite number, got nan"),
    ]
    + [
        (value, f"None or 0 (keep every pose) or a gate of 1 to 1000 noise sigmas, got {value!r}")
        for value in (0.5, 0.999, -1, 1000.5, 1001.0)
    ],
)
def test_an_outlier_gate_that_flags_good_poses_or_none_is_refused_by_name(sigma, message):
    with pytest.raises(InvalidInputError) as caught:
        checked_outlier_sigma(sigma)
    assert str(caught.value) == f"outlier_sigma: {message}"


def test_poses_with_fewer_measured_rows_get_their_own_chi2_median_and_gate():
    """measured_rows: each pose's statistic is chi^2 with its own degrees of freedom (3 or 6 rows of a
    6-row block); the variance factor is the median of d^2 / median(chi^2_k_i), here 4 (s = 2), and
    each pose is gated at s^2 times its own 5-sigma quantile."""
    import scipy.stats

    dof = np.array([3, 6] * 5 + [3, 3, 6])
    median = scipy.stats.chi2.median(dof)
    gate = scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(5.0), dof)
    d2 = 4.0 * median
    d2[10] = 4.0 * gate[10] * (1 + 1e-9)  # 3 rows, just beyond its gate
    d2[11] = 4.0 * gate[11] * (1 - 1e-9)  # 3 rows, just within
    d2[12] = 4.0 * gate[10] * 1.01  # 6 rows: beyond a 3-row gate, within its own
    assert 4.0 * gate[10] * 1.01 < 4.0 * gate[12]
    blocks = np.zeros((len(dof), 6))
    blocks[:, 0] = np.sqrt(d2)
    flagged, scale = outlier_poses(blocks, measured_rows=dof)
    assert list(np.flatnonzero(flagged)) == [10]
    assert scale == pytest.approx(2.0, rel=1e-12)


def test_with_measured_rows_the_scale_is_never_below_one_and_the_exact_gate_is_not_an_outlier():
    """Residuals well inside the noise: s = 1, and each pose is gated at its own quantile unscaled; a
    statistic exactly at its gate is not beyond it, the next float is."""
    import scipy.stats

    dof = np.array([3, 6, 3, 6, 3, 6, 3])
    d2 = 0.25 * scipy.stats.chi2.median(dof)
    gate = outlier_gate(5.0, 3)
    v = float(np.sqrt(gate))
    while v * v > gate:
        v = float(np.nextafter(v, 0.0))
    blocks = np.zeros((7, 6))
    blocks[:, 0] = np.sqrt(d2)
    blocks[2, :2] = v, np.sqrt(gate - v * v)  # 3 rows: at its gate exactly
    assert np.sum(blocks[2] ** 2) == gate
    blocks[4, 0] = np.sqrt(gate * (1 + 1e-9))  # 3 rows: just beyond
    flagged, scale = outlier_poses(blocks, measured_rows=dof)
    assert scale == 1.0 and np.flatnonzero(flagged).tolist() == [4]
    blocks[2, 0] = np.nextafter(v, np.inf)
    assert np.flatnonzero(outlier_poses(blocks, measured_rows=dof)[0]).tolist() == [2, 4]


def test_outlier_scale_is_the_median_ratio_and_never_below_one():
    import scipy.stats

    k = 3
    median = scipy.stats.chi2.median(k)
    d2 = np.r_[np.full(5, 16.0 * median), np.full(4, 0.5)]  # median 16 median(chi^2_3): s = 4
    flagged, scale = outlier_poses(_blocks_with_d2(d2, k))
    assert scale == pytest.approx(4.0, rel=1e-12) and not flagged.any()
    gate = scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(5.0), k)
    d2 = np.r_[d2, 16.0 * gate * (1 + 1e-9), 16.0 * gate * (1 - 1e-9)]
    d2 = np.r_[d2, 16.0 * median]  # keep the median where it was (13 poses, 7th is 16 median)
    flagged, scale = outlier_poses(_blocks_with_d2(d2, k))
    assert scale == pytest.approx(4.0, rel=1e-12) and list(np.flatnonzero(flagged)) == [9]
    # Exactly at the median of chi^2_k the factor is one, just above it is larger.
    assert outlier_poses(_blocks_with_d2(np.full(3, median), k))[1] == pytest.approx(1.0, rel=1e-12)
    assert outlier_poses(_blocks_with_d2(np.full(3, 1.21 * median), k))[1] == pytest.approx(1.1, rel=1e-12)


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.zeros(3), np.zeros((2, 3, 1))])
def test_outlier_poses_refuses_a_shape_that_is_not_n_by_k(bad):
    with pytest.raises(InvalidInputError, match=r"expected an \(N, k\) residual"):
        outlier_poses(bad)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_outlier_poses_refuses_one_non_finite_value(value):
    blocks = np.ones((4, 2))
    blocks[2, 1] = value
    with pytest.raises(InvalidInputError, match="non-finite residual"):
        outlier_poses(blocks)


def _loo_reference(J, r, k, columns):
    """Per-pose squared leave-one-pose-out errors of the fit r + J[:, columns] x, by refitting."""
    n = J.shape[0] // k
    out = np.empty(n)
    for i in range(n):
        rows = slice(i * k, (i + 1) * k)
        keep = np.r_[np.arange(0, i * k), np.arange((i + 1) * k, n * k)]
        x = np.linalg.lstsq(J[keep][:, columns], -r[keep], rcond=None)[0] if columns else np.zeros(0)
        out[i] = np.sum((r[rows] + J[rows][:, columns] @ x) ** 2)
    return out


def _assert_each_step_adds_the_smallest_press(J, r, k, forced, order) -> None:
    """Each step of `order` adds, of the columns left, the one whose refit has the smallest PRESS
    (`_loo_reference`, explicit leave-one-pose-out refits)."""
    chosen = list(forced)
    for column in order:
        left = [c for c in range(J.shape[1]) if c not in chosen]
        scores = [_loo_reference(J, r, k, chosen + [c]).sum() for c in left]
        assert column == left[int(np.argmin(scores))]
        chosen.append(column)


@pytest.mark.parametrize("forced", [(), (5,), (6, 1)])
def test_forward_selection_path_press_order_and_ties_against_refits(forced):
    rng = np.random.default_rng(5)
    n, k, p = 12, 3, 7
    J = rng.normal(size=(n * k, p))
    r = -(J @ np.r_[1.0, -0.6, 0.3, 0.0, 0.0, 0.0, 0.0]) + rng.normal(size=n * k)
    selection = forward_selection(J, r, k, range(p), forced=forced)
    assert set(selection.order).isdisjoint(forced) and sorted(selection.order + tuple(forced)) == list(range(p))
    per_pose = [
        _loo_reference(J, r, k, list(forced) + list(selection.order[:size])) for size in range(p - len(forced) + 1)
    ]
    path = np.array([pp.sum() for pp in per_pose])
    np.testing.assert_allclose(selection.path, path, rtol=1e-8)
    best = int(np.argmin(path))
    assert selection.indices == tuple(sorted(list(forced) + list(selection.order[:best])))
    assert selection.press == pytest.approx(path[best], rel=1e-8)
    assert selection.press_all == pytest.approx(path[-1], rel=1e-8)
    _assert_each_step_adds_the_smallest_press(J, r, k, forced, selection.order)
    differences = np.array(per_pose) - per_pose[best]
    se = differences.std(axis=1, ddof=1) * np.sqrt(n)
    assert selection.tied == int(np.count_nonzero(path - path[best] <= se)) - 1
    assert selection.tied >= 1  # on 12 poses a few sizes are within one standard error
    assert len(selection.indices) < p  # and the best is not every column


@pytest.mark.parametrize("forced", [(), (5,), (6, 1), (2, 4)])
def test_forward_selection_in_place_is_the_same_selection(forced):
    """overwrite=True projects a column-major Jacobian in place (its columns are spent) and chooses
    as the copying selection does; a row-major one, which cannot be projected in place, is left as it is."""
    rng = np.random.default_rng(6)
    n, k, p = 12, 3, 7
    J = rng.normal(size=(n * k, p))
    r = -(J @ np.r_[1.0, -0.6, 0.3, 0.0, 0.0, 0.0, 0.0]) + rng.normal(size=n * k)
    copied = forward_selection(J, r, k, range(p), forced=forced)
    spent = np.asfortranarray(J)
    in_place = forward_selection(spent, r, k, range(p), forced=forced, overwrite=True)
    assert (in_place.indices, in_place.order, in_place.tied) == (copied.indices, copied.order, copied.tied)
    np.testing.assert_allclose(in_place.path, copied.path, rtol=1e-12)
    assert not np.allclose(spent, J)  # projected in place: no second matrix of every row
    row_major = J.copy()
    assert forward_selection(row_major, r, k, range(p), forced=forced, overwrite=True).order == copied.order
    np.testing.assert_array_equal(row_major, J)
    kept = np.asfortranarray(J)  # column-major, but not given to overwrite: the default copies
    assert forward_selection(kept, r, k, range(p), forced=forced).order == copied.order
    np.testing.assert_array_equal(kept, J)


def test_forward_selection_stops_when_no_candidate_is_independent_and_checks_rows():
    rng = np.random.default_rng(5)
    base = rng.normal(size=(30, 2))
    J = np.column_stack((base, base[:, 0] - base[:, 1], 1e-12 * base[:, 0]))  # 2 = 0 - 1, 3 tiny
    r = rng.normal(size=30)
    selection = forward_selection(J, r, 3, range(4))
    assert len(selection.order) == 2 and len(selection.path) == 3
    # A relative tolerance of one refuses every column.
    assert forward_selection(J, r, 3, range(4), rank_tolerance=1.0 + 1e-9).order == ()
    with pytest.raises(InvalidInputError, match="31 rows are not a multiple of 3 per pose"):
        forward_selection(np.ones((31, 2)), np.ones(31), 3, range(2))
    with pytest.raises(InvalidInputError, match="residual"):
        forward_selection(J, r[:-1], 3, range(4))


def test_forced_base_parameters_match_the_documented_quantities():
    rng = np.random.default_rng(4)
    base = rng.normal(size=(60, 4))
    J = np.column_stack([base, base[:, 0] + base[:, 1], base[:, 2] * 3.0, np.zeros(60), 1e-13 * base[:, 3]])
    names = [f"p{i}" for i in range(J.shape[1])]
    chosen = select_base_parameters(J, names, forced=[4, 6, 5, 2])  # 6 is zero, 2 is explained by 5
    assert chosen.indices == (0, 3, 4, 5) or chosen.indices == (1, 3, 4, 5)
    assert chosen.names == tuple(names[i] for i in chosen.indices) and chosen.rank == 4
    assert chosen.zero_columns == ("p6", "p7")
    normalised = J[:, :6] / np.linalg.norm(J[:, :6], axis=0)
    kept = normalised[:, list(chosen.indices)]
    s = np.linalg.svd(kept, compute_uv=False)
    assert chosen.condition_number == pytest.approx(s[0] / s[-1], rel=1e-9)
    np.testing.assert_allclose(chosen.singular_values[:6], np.linalg.svd(normalised, compute_uv=False), atol=1e-12)
    np.testing.assert_array_equal(chosen.singular_values[6:], 0.0)
    assert chosen.singular_values.shape == (8,)
    # r_diag_ratio: the forced columns' lengths (first one 1), then the rest's pivots and one dropped.
    assert chosen.r_diag_ratio[0] == pytest.approx(1.0) and chosen.r_diag_ratio.size == 2 + 2 + 1
    assert chosen.r_diag_ratio[-1] < 1e-9 < chosen.r_diag_ratio[-2]
    with pytest.raises(InvalidInputError, match="8 columns but 7 names"):
        select_base_parameters(J, names[:7], forced=[4])
    with pytest.raises(IdentificationError, match="identically zero"):
        select_base_parameters(np.zeros((5, 2)), "ab", forced=[0])


def test_forced_base_parameters_warn_above_max_condition_from_both_sides():
    rng = np.random.default_rng(6)
    a = rng.normal(size=40)
    J = np.column_stack((a, a + 1e-3 * rng.normal(size=40), rng.normal(size=40)))
    condition = select_base_parameters(J, "abc", forced=[2]).condition_number
    assert condition > 100
    with pytest.warns(PoorExcitationWarning):
        select_base_parameters(J, "abc", forced=[2], max_condition=condition * (1 - 1e-9))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        select_base_parameters(J, "abc", forced=[2], max_condition=condition * (1 + 1e-9))
    # The same boundary without forced columns.
    plain = select_base_parameters(J, "abc").condition_number
    with pytest.warns(PoorExcitationWarning):
        select_base_parameters(J, "abc", max_condition=plain * (1 - 1e-9))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        select_base_parameters(J, "abc", max_condition=plain * (1 + 1e-9))


# --------------------------------------------------------------------------------------------------
# Refusals name the argument and the fault (exact messages)


def _message(call) -> str:
    with pytest.raises((InvalidInputError, IdentificationError)) as error:
        call()
    return str(error.value)


def test_linear_solvers_refuse_bad_input_with_exact_messages():
    A = np.arange(12.0).reshape(6, 2) ** 0.5
    y = np.ones(6)
    assert _message(lambda: batch_least_squares(np.ones(3), y)) == "A: expected a 2-D array, got shape (3,)"
    assert _message(lambda: batch_least_squares(A, y[:5])) == "y: expected 6 values, got 5"
    y_bad = y.copy()
    y_bad[4] = np.inf
    assert _message(lambda: batch_least_squares(A, y_bad)) == "y: non-finite value at index 4"
    y_bad[[1, 4]] = np.nan
    assert _message(lambda: batch_least_squares(A, y_bad)) == "y: non-finite value at index 1"
    assert batch_least_squares(A, y.reshape(3, 2)).x.shape == (2,)  # any shape of 6 values
    assert _message(lambda: batch_least_squares(A, y, np.ones(5))) == "weights: expected 6 values, got 5"
    weights = np.ones(6)
    weights[2] = 0.0
    assert _message(lambda: batch_least_squares(A, y, weights)) == (
        "weights: must be positive inverse standard deviations"
    )
    weights[2] = -1e-300
    assert "weights: must be positive" in _message(lambda: batch_least_squares(A, y, weights))
    weights[2] = 1e-300  # tiny but positive is a weight
    batch_least_squares(A, y, weights)
    weights[2] = 0.5  # below one is a weight too
    batch_least_squares(A, y, weights)
    A_bad = A.copy()
    A_bad[3, 1] = np.nan
    assert _message(lambda: batch_least_squares(A_bad, y)) == "A: non-finite value at row 3, column 1"
    assert _message(lambda: batch_least_squares(np.zeros((6, 2)), y)) == "batch_least_squares: A is identically zero"
    assert _message(lambda: batch_least_squares(np.ones((2, 2)) * [1.0, 2.0] + np.eye(2), y[:2])) == (
        "batch_least_squares: no redundancy to estimate the noise from residuals"
    )
    # Integer input is read as float (a list of ints gives a float solution).
    fit = batch_least_squares([[1, 0], [0, 1], [1, 1]], [1, 2, 4])
    np.testing.assert_allclose(fit.x, [4 / 3, 7 / 3])


def test_batch_least_squares_rank_and_covariance_choice():
    rng = np.random.default_rng(8)
    A = rng.normal(size=(20, 3))
    A = np.column_stack((A, A[:, 0] * 1e-13 + A[:, 1]))  # s_min / s_max around 1e-13
    s = np.linalg.svd(A, compute_uv=False)
    y = rng.normal(size=20)
    assert batch_least_squares(A, y).rank == 3
    assert batch_least_squares(A, y, rcond=s[-1] / s[0] * (1 - 1e-6)).rank == 4
    assert batch_least_squares(A, y, rcond=s[-1] / s[0] * (1 + 1e-6)).rank == 3
    # Unit weights given explicitly: noise model covariance; not given: scaled by the variance factor.
    B = rng.normal(size=(20, 3))
    unweighted, weighted = batch_least_squares(B, y), batch_least_squares(B, y, np.ones(20))
    np.testing.assert_allclose(weighted.covariance, np.linalg.inv(B.T @ B), rtol=1e-10)
    np.testing.assert_allclose(unweighted.covariance, np.linalg.inv(B.T @ B) * unweighted.variance_factor, rtol=1e-10)
    residual = B @ unweighted.x - y
    assert unweighted.variance_factor == pytest.approx(residual @ residual / 17, rel=1e-12)
    # Square and full rank: no degree of freedom, NaN variance factor with a noise-model covariance.
    square = batch_least_squares(B[:3], y[:3], np.ones(3))
    assert np.isnan(square.variance_factor)
    np.testing.assert_allclose(square.covariance, np.linalg.inv(B[:3].T @ B[:3]), rtol=1e-8)
    with pytest.raises(IdentificationError, match="no redundancy"):
        batch_least_squares(B[:3], y[:3])


def test_recursive_least_squares_refusals_with_exact_messages():
    assert _message(lambda: RecursiveLeastSquares(0)) == "RecursiveLeastSquares: n_parameters must be >= 1, got 0"
    RecursiveLeastSquares(1)
    for std in (0.0, -1.0, np.inf, np.nan, [1.0, 0.0]):
        assert _message(lambda std=std: RecursiveLeastSquares(2, prior_std=std)) == (
            "RecursiveLeastSquares: prior_std must be positive and finite"
        )
    assert _message(lambda: RecursiveLeastSquares(2, prior_mean=[1.0, 2.0])) == (
        "RecursiveLeastSquares: prior_mean needs prior_std"
    )
    assert _message(lambda: RecursiveLeastSquares(2, prior_std=1.0, prior_mean=[1.0])) == (
        "prior_mean: expected 2 values, got 1"
    )
    rls = RecursiveLeastSquares(2)
    assert _message(lambda: rls.update(np.ones((2, 3)), np.ones(2))) == "A_k: expected 2 columns, got 3"
    assert _message(lambda: rls.update(np.ones((2, 2)), np.ones(3))) == "y_k: expected 2 values, got 3"
    assert _message(lambda: rls.update(np.ones((2, 2)), np.ones(2), [1.0, 0.0])) == (
        "weights_k: must be positive inverse standard deviations"
    )
    assert _message(lambda: rls.update([[1.0, np.nan]], [1.0])) == "A_k: non-finite value at row 0, column 1"
    # One row as a 1-D array, integers accepted.
    np.testing.assert_allclose(rls.update([1, 0], [2]), [2.0, 0.0])
    assert rls.n_rows == 1


def test_recursive_least_squares_prior_factor_and_residual_sum():
    rls = RecursiveLeastSquares(2, prior_std=[0.5, 2.0], prior_mean=[1.0, -4.0])
    np.testing.assert_allclose(rls.information_factor, np.diag([2.0, 0.5]))
    np.testing.assert_allclose(rls.covariance, np.diag([0.25, 4.0]))
    rls.update([[1.0, 0.0]], [3.0], [1.0])
    # Posterior of x0: information 4 + 1, mean (4 * 1 + 3) / 5; x1 untouched.
    np.testing.assert_allclose(rls.estimate, [7.0 / 5.0, -4.0])
    assert rls.weighted_residual_sum_of_squares == pytest.approx(4 * (0.4) ** 2 + (1.6) ** 2, rel=1e-12)
    # Without a prior, 1 row in 2 unknowns: the minimum-norm estimate (lstsq branch).
    free = RecursiveLeastSquares(2)
    np.testing.assert_allclose(free.update([[3.0, 4.0]], [5.0]), [0.6, 0.8], atol=1e-12)
    # Nearly dependent rows within rcond: still the minimum-norm answer, not a huge one.
    near = RecursiveLeastSquares(2, rcond=1e-6)
    x = near.update([[1.0, 1.0], [1.0, 1.0 + 1e-9]], [2.0, 2.0])
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-6)
    exact = RecursiveLeastSquares(2, rcond=1e-12)
    np.testing.assert_allclose(exact.update([[1.0, 1.0], [1.0, 1.0 + 1e-9]], [2.0, 2.0 + 1e-9]), [1.0, 1.0], atol=1e-5)


# --------------------------------------------------------------------------------------------------
# The damping schedule, step by step, against the documented rule


class Recorded(ExponentialFit):
    def __init__(self) -> None:
        super().__init__()
        self.steps = []

    def retract(self, x, step):
        self.steps.append(np.array(step))
        return x + step


def _reference_steps(problem, x, mu, iterations, unit_damping=False):
    """Every trial step of LM with Marquardt scaling (or unit damping: D = max_j ||J_j|| I) and Nielsen's
    damping update (the docstring)."""
    r, J = problem.residual_and_jacobian(x)
    cost, nu, steps = 0.5 * r @ r, 2.0, []
    for _ in range(iterations):
        d2 = np.diag(J.T @ J)
        if unit_damping:
            d2 = np.full_like(d2, d2.max())
        while True:
            dx = np.linalg.solve(J.T @ J + mu * np.diag(d2), -J.T @ r)
            steps.append(dx)
            r_trial, J_trial = problem.residual_and_jacobian(x + dx)
            decrease = cost - 0.5 * r_trial @ r_trial
            if decrease > 0:
                predicted = -(r @ (J @ dx)) - 0.5 * (J @ dx) @ (J @ dx)
                rho = decrease / predicted
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                x, r, J, cost = x + dx, r_trial, J_trial, cost - decrease
                break
            mu *= nu
            nu *= 2.0
    return steps


@pytest.mark.parametrize("damping", [1e-3, 1e-9, 10.0])
def test_trial_steps_follow_the_marquardt_nielsen_schedule(damping):
    problem = Recorded()
    start = np.array([0.1, 6.0])  # far: the first undamped steps overshoot and are rejected
    result = levenberg_marquardt(
        problem,
        start,
        LMSettings(
            initial_damping=damping, max_iterations=6, cost_tolerance=0.0, step_tolerance=0.0, gradient_tolerance=0.0
        ),
    )
    assert result.termination == "max_iterations" and result.iterations == 6
    reference = _reference_steps(ExponentialFit(), start, damping, 6)
    assert len(problem.steps) == len(reference)
    np.testing.assert_allclose(np.array(problem.steps), np.array(reference), rtol=1e-6, atol=1e-12)
    assert result.step_norm == pytest.approx(np.linalg.norm(reference[-1]), rel=1e-6)


class ScaledExponentialFit(Recorded):
    """`ExponentialFit` with residual and Jacobian times c (c = 1e-3: every column norm below 1)."""

    def __init__(self, c: float) -> None:
        super().__init__()
        self.c = c

    def residual_and_jacobian(self, x):
        r, J = super().residual_and_jacobian(x)
        return self.c * r, self.c * J


@pytest.mark.parametrize("c", [1.0, 1e-3])
def test_unit_damping_is_by_the_largest_column_norm_whatever_the_residuals_scale(c):
    """unit_damping: D = max_j ||J_j|| I, so that mu stays unit free (the same steps for r and J scaled
    by c, column norms below 1 included), every trial step as the documented rule gives it."""
    problem = ScaledExponentialFit(c)
    start = np.array([0.1, 6.0])
    settings = LMSettings(
        initial_damping=1e-3,
        unit_damping=True,
        max_iterations=6,
        cost_tolerance=0.0,
        step_tolerance=0.0,
        gradient_tolerance=0.0,
    )
    result = levenberg_marquardt(problem, start, settings)
    assert result.termination == "max_iterations" and result.iterations == 6
    reference = _reference_steps(ScaledExponentialFit(1.0), start, 1e-3, 6, unit_damping=True)
    assert len(problem.steps) == len(reference)
    np.testing.assert_allclose(np.array(problem.steps), np.array(reference), rtol=1e-6, atol=1e-12)
    marquardt = _reference_steps(ScaledExponentialFit(1.0), start, 1e-3, 6)
    assert not np.allclose(marquardt[0], reference[0], rtol=1e-3)  # the scaling differs from Marquardt's


def test_without_a_residual_hook_a_trial_is_evaluated_once_with_its_jacobian():
    """A problem with residual_and_jacobian alone: each trial step is one evaluation, which serves the
    next iteration when the step is accepted (no second one at the same state)."""
    problem = Recorded()
    result = levenberg_marquardt(
        problem,
        np.array([0.1, 6.0]),
        LMSettings(max_iterations=6, cost_tolerance=0.0, step_tolerance=0.0, gradient_tolerance=0.0),
    )
    assert result.iterations == 6 and len(problem.steps) > 6  # rejected trials too
    assert problem.calls == 1 + len(problem.steps)


def test_rejections_happen_in_the_schedule_test():
    problem = Recorded()
    levenberg_marquardt(
        problem,
        np.array([0.1, 6.0]),
        LMSettings(
            initial_damping=1e-9, max_iterations=6, cost_tolerance=0.0, step_tolerance=0.0, gradient_tolerance=0.0
        ),
    )
    assert len(problem.steps) >= 6 + 3  # several rejected trials in a row: nu doubles


# --------------------------------------------------------------------------------------------------
# Termination rules at their exact boundary, every field of every LMResult, the
# optional `residual` and `release` hooks, the documented tie-break of 1e-9 from both sides.


class Linear:
    """r = x - 0.75 with J = 1: with no damping the first step is exactly 0.75, the cost exactly 0.28125 -> 0."""

    def __init__(self) -> None:
        self.steps = []

    def residual_and_jacobian(self, x):
        return np.array([x[0] - 0.75]), np.array([[1.0]])

    def retract(self, x, step):
        self.steps.append(np.array(step))
        return x + step


def test_step_rule_at_its_exact_tolerance_and_every_field_of_the_result():
    problem = Linear()
    result = levenberg_marquardt(problem, np.zeros(1), LMSettings(initial_damping=0.0, step_tolerance=0.75))
    assert result.termination == "step" and result.converged is True and result.iterations == 1
    assert result.step_norm == 0.75 and problem.steps == []  # a step of exactly the tolerance is not taken
    np.testing.assert_array_equal(result.state, [0.0])
    assert result.cost == 0.28125 and result.cost_history == (0.28125,)
    # Just below the step: taken, then the gradient rule stops at the minimum.
    result = levenberg_marquardt(
        Linear(), np.zeros(1), LMSettings(initial_damping=0.0, step_tolerance=0.75 * (1 - 1e-12))
    )
    assert result.termination == "gradient" and result.iterations == 1 and result.cost == 0.0


def test_cost_rules_at_their_exact_tolerance_and_every_field_of_the_result():
    # The first step removes the whole cost: decrease 0.28125 = 1.0 x the cost before the step.
    relative = levenberg_marquardt(Linear(), np.zeros(1), LMSettings(initial_damping=0.0, cost_tolerance=1.0))
    assert relative.termination == "cost" and relative.converged is True and relative.iterations == 1
    assert relative.cost == 0.0 and relative.cost_history == (0.28125, 0.0) and relative.step_norm == 0.75
    np.testing.assert_array_equal(relative.state, [0.75])
    absolute = levenberg_marquardt(
        Linear(),
        np.zeros(1),
        LMSettings(initial_damping=0.0, cost_tolerance=0.0, absolute_cost_tolerance=0.28125),
    )
    assert absolute.termination == "cost" and absolute.iterations == 1 and absolute.cost == 0.0
    # Just below: the cost rules let the step through and the gradient rule stops one iteration on.
    for tolerances in ({"cost_tolerance": 1.0 - 1e-12}, {"cost_tolerance": 0.0, "absolute_cost_tolerance": 0.28}):
        result = levenberg_marquardt(Linear(), np.zeros(1), LMSettings(initial_damping=0.0, **tolerances))
        assert result.termination == "gradient" and result.iterations == 1 and result.cost == 0.0


def test_gradient_rule_at_its_exact_tolerance():
    class Line:
        def residual_and_jacobian(self, x):
            return np.array([x[0] - 1.0, 2.0 * (x[1] + 3.0)]), np.array([[1.0, 0.0], [0.0, 2.0]])

        def retract(self, x, step):
            return x + step

    start = np.array([0.5, -3.0])  # gradient J^T r = (-0.5, 0) exactly
    at = levenberg_marquardt(Line(), start, LMSettings(gradient_tolerance=0.5))
    assert at.termination == "gradient" and at.iterations == 0 and at.state is start
    assert levenberg_marquardt(Line(), start, LMSettings(gradient_tolerance=0.5 * (1 - 1e-12))).iterations >= 1


def test_no_parameters_stops_on_the_gradient_rule():
    class Fixed:
        def residual_and_jacobian(self, x):
            return np.array([1.0, -2.0]), np.zeros((2, 0))

        def retract(self, x, step):
            raise AssertionError("nothing to move")

    result = levenberg_marquardt(Fixed(), np.zeros(0))
    assert result.termination == "gradient" and result.iterations == 0 and result.cost == 2.5


class Decaying:
    """r = exp(-x): every step lowers the cost by most of it and the minimum is at infinity."""

    def residual_and_jacobian(self, x):
        return np.exp(-x), -np.exp(-x)[:, None]

    def retract(self, x, step):
        return x + step


def test_default_iteration_limit_is_50_and_every_field_of_the_result():
    result = levenberg_marquardt(Decaying(), np.zeros(1), LMSettings(gradient_tolerance=0.0))
    assert result.termination == "max_iterations" and result.iterations == 50 and result.converged is False
    assert len(result.cost_history) == 51 and result.cost == result.cost_history[-1] < 1e-40
    assert result.state[0] > 45.0 and 0.5 < result.step_norm < 1.5


class Opposed:
    """A Jacobian of the wrong sign: no trial step is ever accepted."""

    def __init__(self) -> None:
        self.steps = []

    def residual_and_jacobian(self, x):
        return np.array([x[0] - 1.0, 2.0 * x[0]]), -np.array([[1.0], [2.0]])

    def retract(self, x, step):
        self.steps.append(np.array(step))
        return x + step


def test_stalled_after_the_damping_passes_1e30_and_every_field_of_the_result():
    start = np.array([0.3])
    problem = Opposed()
    result = levenberg_marquardt(problem, start, LMSettings(step_tolerance=0.0))
    # mu = 1e-3 x 2 x 4 x ... x 2^k first exceeds 1e30 at k = 15 (2^120 > 1e33 > 2^105).
    assert len(problem.steps) == 15
    assert result.termination == "stalled" and result.converged is False and result.iterations == 1
    assert result.state is start and result.cost == result.cost_history[0] == pytest.approx(0.425)
    assert result.step_norm == float(np.linalg.norm(problem.steps[-1])) > 0.0
    # Rejected steps shrink as 1 / mu: each is the previous over (1 + mu nu) / (1 + mu), mu the damping.
    norms = np.array([np.linalg.norm(s) for s in problem.steps])
    assert np.all(norms[1:] < norms[:-1])
    # Exactly 1e30 is not beyond the limit: 5e29 x 2 = 1e30 leads to one more trial (at 4e30).
    problem = Opposed()
    assert (
        levenberg_marquardt(problem, start, LMSettings(step_tolerance=0.0, initial_damping=5e29)).termination
        == "stalled"
    )
    assert len(problem.steps) == 2


def test_residual_only_trials_and_release_of_superseded_iterates():
    class Hooked(ExponentialFit):
        def __init__(self) -> None:
            super().__init__()
            self.trials = 0
            self.released = []
            self.states = []

        def residual_and_jacobian(self, x):
            self.states.append(x)
            return super().residual_and_jacobian(x)

        def residual(self, x):
            self.trials += 1
            e = np.exp(x[1] * self.t)
            return x[0] * e - self.y

        def release(self, x):
            self.released.append(x)

    problem = Hooked()
    start = np.array([0.1, 6.0])  # far: several trials are rejected
    result = levenberg_marquardt(
        problem,
        start,
        LMSettings(max_iterations=6, cost_tolerance=0.0, step_tolerance=0.0, gradient_tolerance=0.0),
    )
    accepted = len(result.cost_history) - 1
    assert accepted == 6 and problem.trials > accepted  # rejected trials cost no Jacobian
    assert problem.calls == 1 + accepted  # one Jacobian per accepted step, plus the start
    assert len(problem.released) == accepted and problem.released[0] is start
    assert all(a is b for a, b in zip(problem.released, problem.states[:-1], strict=True))


def test_a_run_stopped_by_the_cost_test_evaluates_no_jacobian_at_its_last_iterate():
    """The cost test needs only the accepted trial's cost: with a residual-only method the run returns
    there, one Jacobian per accepted step but the last; without one every trial brings its Jacobian.
    Both take the same steps to the same state."""

    class ResidualOnly(ExponentialFit):
        def residual(self, x):
            return x[0] * np.exp(x[1] * self.t) - self.y

    lean, plain = ResidualOnly(), ExponentialFit()
    settings = LMSettings(cost_tolerance=1e-6)
    result = levenberg_marquardt(lean, X0, settings)
    reference = levenberg_marquardt(plain, X0, settings)
    assert result.termination == reference.termination == "cost" and result.iterations >= 2
    assert lean.calls == result.iterations  # the start and each accepted step but the last
    assert result.cost_history == reference.cost_history
    np.testing.assert_array_equal(result.state, reference.state)


def test_steps_are_invariant_under_a_scaling_of_the_residual_even_with_a_vanishing_column():
    class Scaled:
        """Column 1 is 1e-14 of column 0: below the 1e-12 floor of Marquardt's scaling at any c."""

        def __init__(self, c: float) -> None:
            self.c = c
            self.steps = []

        def residual_and_jacobian(self, x):
            r = np.array([x[0] - 1.0 + 0.3 * x[0] ** 2, 1e-14 * (x[1] - 2.0), 1e-14 * x[0] * x[1]])
            J = np.array([[1.0 + 0.6 * x[0], 0.0], [0.0, 1e-14], [1e-14 * x[1], 1e-14 * x[0]]])
            return self.c * r, self.c * J

        def retract(self, x, step):
            self.steps.append(np.array(step))
            return x + step

    runs = []
    for c in (1.0, 1e-3, 1e3):
        problem = Scaled(c)
        levenberg_marquardt(
            problem,
            np.array([3.0, 0.0]),
            LMSettings(max_iterations=3, gradient_tolerance=0.0, cost_tolerance=0.0, step_tolerance=0.0),
        )
        runs.append(np.array(problem.steps))
    assert runs[0].shape == (3, 2)
    np.testing.assert_allclose(runs[1], runs[0], rtol=1e-9)
    np.testing.assert_allclose(runs[2], runs[0], rtol=1e-9)


def test_an_accepted_step_with_a_predicted_decrease_of_zero_doubles_the_damping():
    class Blind:
        """Row 1 drops from 1 to 0.5 once x < 0, which its zero Jacobian row cannot predict; row 0
        is 1e-100 x + 1e-170, whose predicted decrease (of order 1e-340) underflows to exactly 0.
        (Row 0 first: the QR of [J r] then needs no reflection, and Q^T r keeps the 1e-170 exactly.)"""

        def __init__(self) -> None:
            self.steps = []

        def residual_and_jacobian(self, x):
            return np.array([1e-100 * x[0] + 1e-170, 1.0 if x[0] >= 0 else 0.5]), np.array([[1e-100], [0.0]])

        def retract(self, x, step):
            self.steps.append(float(step[0]))
            return x + step

    problem = Blind()
    result = levenberg_marquardt(
        problem,
        np.zeros(1),
        LMSettings(max_iterations=2, gradient_tolerance=0.0, cost_tolerance=0.0, step_tolerance=0.0),
    )
    assert result.cost_history[:2] == (0.5, 0.125)
    # Step k is -r_1 / (1e-100 (1 + mu)): mu = 1e-3 first, then 2e-3 (rho taken as 0: mu x 2).
    assert problem.steps[0] / -1e-70 == pytest.approx(1.0 / 1.001, rel=1e-12)
    assert problem.steps[1] / -(1e-70 + problem.steps[0]) == pytest.approx(1.0 / 1.002, rel=1e-9)


# --------------------------------------------------------------------------------------------------
# Base parameters: exact boundaries, the tie-break, the warning, the names in messages


def _two_on_one_plane(d: float) -> np.ndarray:
    """Columns e1, (cos a, sin a) and (cos b, sin b) with sin b = (1 + d) sin a: after e1, the other two
    are dependent and their lengths differ by the relative amount d."""
    a = 0.6
    J = np.zeros((4, 3))
    J[0] = [1.0, np.cos(a), np.sqrt(1.0 - ((1 + d) * np.sin(a)) ** 2)]
    J[1] = [0.0, np.sin(a), (1 + d) * np.sin(a)]
    return J


def test_ties_within_1e_9_go_to_the_lower_column():
    # After e1, column 2 is longer than column 1 by the relative amount d: it wins only beyond 1e-9.
    for d, kept in ((0.0, (0, 1)), (0.5e-9, (0, 1)), (0.9e-9, (0, 1)), (2e-9, (0, 2)), (-2e-9, (0, 1))):
        assert select_base_parameters(_two_on_one_plane(d), "abc").indices == kept, d
        assert select_base_parameters(_two_on_one_plane(d), "abc", forced=[0]).indices == kept, d
    # The twin listed first wins, whichever it is: the rule is about the original column order.
    swapped = _two_on_one_plane(0.0)[:, [0, 2, 1]]
    assert select_base_parameters(swapped, "abc").indices == (0, 1)


def test_pivoted_qr_factors_the_permuted_matrix_and_pivots_on_the_largest_remaining_norm():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(9, 6)) * [1.0, 3.0, 0.5, 2.0, 1.0, 0.1]
    r, pivots = pivoted_qr(A)
    np.testing.assert_allclose(r.T @ r, A[:, pivots].T @ A[:, pivots], rtol=1e-12, atol=1e-12)
    assert np.array_equal(r, np.triu(r)) and sorted(pivots) == list(range(6))
    assert np.all(np.diff(np.abs(np.diag(r))) <= 1e-12)  # each pivot the largest of what remains
    assert pivots[0] == 1  # the longest column first
    wide, wide_pivots = pivoted_qr(A.T)  # more columns than rows: min(rows, cols) rows of R
    assert wide.shape == (6, 9)
    np.testing.assert_allclose(wide.T @ wide, A[wide_pivots] @ A[wide_pivots].T, atol=1e-12)
    zero, zero_pivots = pivoted_qr(np.zeros((3, 2)))  # nothing to reflect: no division by zero
    assert np.all(zero == 0.0) and zero_pivots.tolist() == [0, 1]


def test_pivoted_qr_ties_go_to_the_lower_original_column_after_swaps_and_integers_are_floats():
    """The tie rule is about original columns, also once a pivot has moved them: here column 3 first
    (swapped with 0), then 0 and 1 tie and 0, now at position 3, wins. Zero columns left: still ordered by
    the rule (0, 1, 2 after 3). Integer input is factored in floating point."""
    A = np.zeros((4, 4))
    A[:, 3] = [0.0, 0.0, 0.0, 2.0]
    A[:, 0] = [1.0, 0.0, 0.0, 0.0]
    A[:, 1] = [0.0, 1.0, 0.0, 0.0]
    r, pivots = pivoted_qr(A)
    assert pivots.tolist() == [3, 0, 1, 2]
    np.testing.assert_allclose(np.abs(np.diag(r)), [2.0, 1.0, 1.0, 0.0], atol=1e-15)
    assert pivoted_qr(np.eye(4)[:, ::-1] * [0, 0, 0, 1])[1].tolist() == [3, 0, 1, 2]  # one non-zero column
    integers = np.array([[2, 1], [1, 3], [0, 1]])
    r_int, pivots_int = pivoted_qr(integers)
    r_float, pivots_float = pivoted_qr(integers.astype(float))
    assert pivots_int.tolist() == pivots_float.tolist() == [1, 0]
    np.testing.assert_allclose(r_int, r_float, rtol=1e-14)
    np.testing.assert_allclose(r_int.T @ r_int, integers[:, pivots_int].T @ integers[:, pivots_int], rtol=1e-14)


def test_unexcited_parameters_are_invariant_under_column_scaling_weakest_direction_first_and_name_the_jacobian():
    """The directions are those of the column-normalised Jacobian, also for columns shorter than 1; with
    count 2 the weakest direction's parameters come first; a bad Jacobian is refused by its name."""
    rng = np.random.default_rng(7)
    base = rng.normal(size=(8, 5))
    J = np.column_stack((base[:, :3], base[:, 0] + 1e-4 * base[:, 3], base[:, 2] + 1e-2 * base[:, 4]))
    names = "abcde"
    weakest = unexcited_parameters(J, names, range(5), 1)
    both = unexcited_parameters(J, names, range(5), 2)
    assert set(weakest) == {"a", "d"} and both[: len(weakest)] == weakest and {"c", "e"} <= set(both)
    for scales in ([1e-3, 2e-3, 5e-4, 1e-3, 3e-3], [1e3, 1e-2, 1.0, 0.5, 2e2]):
        assert unexcited_parameters(J * scales, names, range(5), 2) == both
    with pytest.raises(InvalidInputError) as error:
        unexcited_parameters(np.ones(3), names, [0], 1)
    assert str(error.value) == "jacobian: expected a 2-D array, got shape (3,)"


def test_unexcited_parameters_of_equal_weight_come_in_the_order_of_the_columns_given():
    """A circulant block whose rows sum to zero: its columns have one length and the weakest direction
    weighs all 20 equally (5 independent columns beside it weigh nothing); the 20 come in the order of
    `columns`, however many there are (a stable sort: rounding does not reorder twins)."""
    rng = np.random.default_rng(9)
    a = rng.normal(size=20)
    J = scipy.linalg.block_diag(scipy.linalg.circulant(a - a.mean()), rng.normal(size=(10, 5)))
    names = [f"p{j}" for j in range(25)]
    order = [int(c) for c in rng.permutation(25)]
    assert unexcited_parameters(J, names, order, 1) == tuple(names[c] for c in order if c < 20)


@pytest.mark.parametrize(("delta", "tied"), [(4e-10, True), (2e-9, False)])
def test_unexcited_weights_equal_to_9_digits_are_twins_in_column_order(delta, tied):
    """c = a + (1 + delta) b: the weakest direction weighs a and b 1 / |c| and (1 + delta) / |c| of c's,
    0.71 delta apart. Equal to 9 digits (delta 4e-10: 0.7071067810 and 0.7071067813) they are twins and
    come in the order of `columns`; 1.4e-9 apart (delta 2e-9), b, the heavier, comes first either way."""
    J = np.zeros((4, 3))
    J[0, 0] = J[1, 1] = 1.0
    J[:, 2] = J[:, 0] + (1.0 + delta) * J[:, 1]
    assert unexcited_parameters(J, "abc", [0, 1, 2], 1) == (("c", "a", "b") if tied else ("c", "b", "a"))
    assert unexcited_parameters(J, "abc", [1, 0, 2], 1) == ("c", "b", "a")


def test_unexcited_parameters_name_the_main_parts_of_the_weakest_directions():
    """Weak means nearly dependent on the others once columns are normalised (as for the rank)."""
    J = np.zeros((5, 4))
    J[0, 0], J[1, 1], J[3, 3] = 1.0, 2.0, 3.0
    J[:, 2] = J[:, 0] + 0.5 * J[:, 1] + [0, 0, 1e-9, 0, 0]  # c' ~ (a' + b') / sqrt2: (-0.71, -0.71, 1)
    assert unexcited_parameters(J, "abcd", [0, 1, 2, 3], 1) == ("c", "a", "b")
    J[:, 2] = J[:, 0] + 0.01 * J[:, 1]  # nearly a alone: b weighs 0.02 of the direction
    assert unexcited_parameters(J, "abcd", [0, 1, 2], 1) == ("c", "a")
    assert unexcited_parameters(J, "abcd", [0, 1, 3], 1) in {("a",), ("b",), ("d",)}  # orthogonal: any one
    assert "d" in unexcited_parameters(J[:2], "abcd", [0, 1, 2, 3], 2)  # a zero column, fewer rows than columns


def test_best_index_takes_the_lower_of_scores_within_1e_9():
    assert best_index([1.0, 3.0, 3.0 * (1 + 0.5e-9), 2.0]) == 1
    assert best_index([1.0, 3.0, 3.0 * (1 + 2e-9), 2.0]) == 2
    assert best_index([-np.inf, -np.inf, 0.5]) == 2 and best_index([-np.inf, -np.inf]) == 0
    assert best_index([1.0, np.inf, 2.0]) == 1 and best_index([np.inf, -np.inf], largest=False) == 1
    # Scores are compared as floats: unsigned integers negate as numbers (the smallest of 0 and 2 is 0).
    assert best_index(np.array([0, 2], dtype=np.uint8), largest=False) == 0
    assert best_index(np.array([3, 0, 2], dtype=np.uint8), largest=False) == 1
    assert best_index([4.0, 2.0, 2.0 * (1 - 0.5e-9)], largest=False) == 1
    assert best_index([4.0, 2.0, 2.0 * (1 - 2e-9)], largest=False) == 2
    assert best_index([np.inf, 5.0, np.inf], largest=False) == 1


def test_r_diag_ratio_starts_at_exactly_one_and_ends_one_past_the_rank():
    rng = np.random.default_rng(11)
    A = rng.normal(size=(30, 3))
    J = np.column_stack((A, A[:, 0] + A[:, 1], A[:, 1] - A[:, 2]))  # rank 3, two dropped
    base = select_base_parameters(J, "abcde")
    assert base.rank == 3 and base.r_diag_ratio.size == 4 and base.r_diag_ratio[0] == 1.0
    assert base.r_diag_ratio[3] < 1e-12 < base.r_diag_ratio[2] < 1.0
    one = select_base_parameters(A[:, :1], "a")
    assert one.rank == 1 and one.r_diag_ratio.tolist() == [1.0] and one.condition_number == 1.0
    # Forced: the forced lengths then the rest's pivots, with none dropped when the rest is independent.
    forced = select_base_parameters(A, "abc", forced=[1])
    assert forced.indices == (0, 1, 2) and forced.r_diag_ratio.size == 3
    assert forced.r_diag_ratio[0] == pytest.approx(1.0, rel=1e-15)
    # The rest's diagonal is that of the normalised columns after projecting the forced one out:
    # lengths below one, whose product is the product of that projected block's singular values.
    assert np.all(forced.r_diag_ratio[1:] < 1.0) and np.all(forced.r_diag_ratio[1:] > 0.5)
    rest = A[:, [0, 2]] / np.linalg.norm(A[:, [0, 2]], axis=0)
    q = A[:, 1] / np.linalg.norm(A[:, 1])
    rest = rest - np.outer(q, q @ rest)
    assert np.prod(forced.r_diag_ratio[1:]) == pytest.approx(np.prod(np.linalg.svd(rest, compute_uv=False)), rel=1e-8)


def test_forced_columns_that_are_all_zero_leave_the_plain_selection():
    rng = np.random.default_rng(12)
    A = rng.normal(size=(20, 3))
    J = np.column_stack((A, np.zeros(20)))
    forced = select_base_parameters(J, "abcd", forced=[3])
    plain = select_base_parameters(J, "abcd")
    assert forced.indices == plain.indices == (0, 1, 2) and forced.zero_columns == ("d",)
    # Column indices of integral floats are read as integers.
    assert select_base_parameters(J, "abcd", forced=np.array([2.0])).indices == (0, 1, 2)


def test_zero_columns_are_relative_to_the_largest_column_at_the_exact_tolerance():
    J = np.array([[2.0, 0.0], [0.0, 1.0], [0.0, 0.0]])  # norms 2 and 1
    assert select_base_parameters(J, "ab", rank_tolerance=0.5).zero_columns == ("b",)  # 1 = 0.5 x 2 is not above
    assert select_base_parameters(J, "ab", rank_tolerance=0.5 * (1 - 1e-12)).zero_columns == ()
    # Scaling the whole Jacobian changes nothing: a column 1e-10 of the largest is zero at any scale.
    rng = np.random.default_rng(13)
    A = rng.normal(size=(20, 3))
    tiny = np.column_stack((A, 1e-10 * rng.normal(size=20)))
    for scale in (1e-3, 1.0, 1e3):
        base = select_base_parameters(scale * tiny, "abcd", rank_tolerance=1e-6)
        assert base.zero_columns == ("d",) and base.indices == (0, 1, 2)


def test_zero_by_zero_and_empty_jacobians_are_identically_zero_with_the_exact_message():
    for J in (np.zeros((3, 2)), np.zeros((3, 0))):
        for forced in ((), (0,)):
            names = "ab"[: J.shape[1]]
            with pytest.raises(IdentificationError) as error:
                select_base_parameters(J, names, forced=forced if names else ())
            assert str(error.value) == "select_base_parameters: the Jacobian is identically zero"


def test_jacobian_is_named_in_the_non_finite_message_with_and_without_forced_columns():
    J = np.ones((3, 2))
    J[2, 1] = np.nan
    for forced in ((), (0,)):
        with pytest.raises(InvalidInputError) as error:
            select_base_parameters(J, "ab", forced=forced)
        assert str(error.value) == "jacobian: non-finite value at row 2, column 1"


def _poorly_excited() -> np.ndarray:
    rng = np.random.default_rng(6)
    a = rng.normal(size=40)
    return np.column_stack((a, a + 1e-3 * rng.normal(size=40), rng.normal(size=40)))


@pytest.mark.parametrize("forced", [(), (2,)])
def test_poor_excitation_warning_text_caller_and_exact_boundary(forced):
    J = _poorly_excited()
    condition = select_base_parameters(J, "abc", forced=forced).condition_number
    with pytest.warns(PoorExcitationWarning) as record:
        select_base_parameters(J, "abc", forced=forced, max_condition=100.0)
    assert len(record) == 1
    assert str(record[0].message) == (
        f"kept 3 parameters with condition number {condition:.3g} > 100: add or spread out poses"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        select_base_parameters(J, "abc", forced=forced, max_condition=condition)  # not above itself


@pytest.mark.skipif(
    "/mutants/" in identification.__file__, reason="mutmut's trampoline adds frames between the caller and the warning"
)
@pytest.mark.parametrize("forced", [(), (2,)])
def test_poor_excitation_warning_points_at_the_caller(forced):
    with pytest.warns(PoorExcitationWarning) as record:
        select_base_parameters(_poorly_excited(), "abc", forced=forced, max_condition=100.0)
    assert record[0].filename == __file__


# --------------------------------------------------------------------------------------------------
# Linear solvers, outliers and names: input conversion, boundaries, exact messages


def test_float32_and_exact_python_numbers_are_computed_in_double_precision():
    from decimal import Decimal
    from fractions import Fraction

    rng = np.random.default_rng(14)
    A = rng.normal(size=(12, 3)).astype(np.float32)
    y = rng.normal(size=12).astype(np.float32)
    fit32, fit64 = batch_least_squares(A, y), batch_least_squares(A.astype(float), y.astype(float))
    np.testing.assert_array_equal(fit32.x, fit64.x)
    assert fit32.variance_factor == fit64.variance_factor
    exact = batch_least_squares(
        [[Fraction(1), Fraction(0)], [Fraction(0), Decimal(1)], [1, 1]], [Fraction(1, 2), Decimal("2"), 4]
    )
    np.testing.assert_allclose(exact.x, batch_least_squares([[1, 0], [0, 1], [1, 1]], [0.5, 2.0, 4.0]).x, rtol=1e-15)
    blocks = (rng.normal(size=(9, 3)) * 3).astype(np.float32)
    assert outlier_poses(blocks)[1] == outlier_poses(blocks.astype(float))[1] > 1.0
    assert outlier_poses([[Fraction(1, 2)], [Decimal(3)]])[1] == outlier_poses([[0.5], [3.0]])[1]
    std = np.float32(0.3)
    np.testing.assert_array_equal(
        RecursiveLeastSquares(2, prior_std=std).information_factor,
        RecursiveLeastSquares(2, prior_std=float(std)).information_factor,
    )


def test_batch_least_squares_one_column_one_redundant_row_and_no_column():
    fit = batch_least_squares([[1.0], [2.0]], [1.0, 3.0])
    assert fit.rank == 1 and fit.x == pytest.approx([1.4])
    # One degree of freedom: the variance factor is the residual sum of squares itself.
    assert fit.variance_factor == pytest.approx((1.0 - 1.4) ** 2 + (3.0 - 2.8) ** 2, rel=1e-12)
    assert fit.covariance[0, 0] == pytest.approx(fit.variance_factor / 5.0, rel=1e-12)
    with pytest.raises(IdentificationError) as error:
        batch_least_squares(np.zeros((3, 0)), np.ones(3))
    assert str(error.value) == "batch_least_squares: A is identically zero"


def test_outlier_gate_at_its_exact_value_is_not_an_outlier():
    import scipy.stats

    gate = float(scipy.stats.chi2.isf(2.0 * scipy.stats.norm.sf(5.0), 2))
    v = float(np.sqrt(gate))
    candidates = [v + i * np.spacing(v) for i in range(-4, 5)]
    exact = next(c for c in candidates if c * c == gate)  # d^2 = gate exactly
    blocks = np.zeros((5, 2))
    blocks[:4, 0] = 0.1
    blocks[4, 0] = exact
    flagged, scale = outlier_poses(blocks)
    assert scale == 1.0 and not flagged.any()
    blocks[4, 0] = np.nextafter(exact, np.inf)
    assert outlier_poses(blocks)[0].tolist() == [False] * 4 + [True]
    blocks[4, 0] = np.nan
    with pytest.raises(InvalidInputError) as error:
        outlier_poses(blocks)
    assert str(error.value) == "outlier_poses: non-finite residual"


def test_placement_is_everything_before_the_last_dt():
    names = ("arm.dt[1].dt[0]", "arm.dt[1].dt[1]", "arm.dt[2]")
    assert parameter_columns(names, ["arm.dt[1]"], "--fix") == [0, 1]
    assert parameter_columns(names, ["arm"], "--fix") == [2]
    with pytest.raises(InvalidInputError) as error:
        parameter_columns(names, ["leg"], "--fix")
    assert str(error.value) == (
        "--fix: 'leg' is neither a parameter (e.g. arm.dt[1].dt[0]) nor a placement "
        "(e.g. arm.dt[1]: all its components)"
    )


def test_rls_prior_without_mean_and_estimate_before_any_row():
    rls = RecursiveLeastSquares(2, prior_std=[0.5, 2.0])
    np.testing.assert_array_equal(rls.estimate, [0.0, 0.0])
    np.testing.assert_array_equal(rls.information_factor, np.diag([2.0, 0.5]))
    assert rls.weighted_residual_sum_of_squares == 0.0 and rls.n_rows == 0
    np.testing.assert_array_equal(RecursiveLeastSquares(3).estimate, np.zeros(3))
    # With a prior mean and no row yet, the estimate is the prior mean.
    np.testing.assert_allclose(
        RecursiveLeastSquares(2, prior_std=[0.5, 2.0], prior_mean=[1.0, -4.0]).estimate, [1.0, -4.0], rtol=1e-15
    )


# --------------------------------------------------------------------------------------------------
# Forward selection: batches of candidates, dead columns, tiny scales, the standard error of ties


def test_forward_selection_scores_every_batch_of_candidates_and_skips_dead_ones():
    # 25,000 poses of 10 rows: 5e5 // (25,000 x 10) = 2 candidates per batch, three batches for five.
    rng = np.random.default_rng(15)
    n, k = 25000, 10
    live = rng.normal(size=(n * k, 3))
    J = np.column_stack((np.zeros(n * k), np.zeros(n * k), live))  # the first batch is dead
    r = -(live @ np.r_[0.05, 0.2, 1.0]) + 3.0 * rng.normal(size=n * k)
    selection = forward_selection(J, r, k, range(5))
    # The same as without the zero columns, which are never chosen; the last candidate goes first.
    alone = forward_selection(live, r, k, range(3))
    assert selection.order == tuple(c + 2 for c in alone.order) and selection.order[0] == 4
    np.testing.assert_allclose(selection.path, alone.path, rtol=1e-12)
    assert len(selection.path) == 4 and selection.path[1] < selection.path[0]


def test_forward_selection_is_scale_invariant_and_a_column_is_never_longer_than_itself():
    rng = np.random.default_rng(16)
    J = rng.normal(size=(30, 3))
    r = -(J @ np.r_[1.0, 0.5, 0.0]) + rng.normal(size=30)
    reference = forward_selection(J, r, 3, range(3))
    tiny = forward_selection(1e-12 * J, 1e-12 * r, 3, range(3))
    assert tiny.order == reference.order and tiny.indices == reference.indices
    assert forward_selection(J, r, 3, range(3), rank_tolerance=1.0).order == ()
    # Just below one, the first column is taken and the others, shortened by its projection, are not.
    assert forward_selection(J, r, 3, range(3), rank_tolerance=1.0 - 1e-9).order == reference.order[:1]


def test_forward_selection_messages_name_the_arguments():
    J = np.ones((6, 2))
    with pytest.raises(InvalidInputError) as error:
        forward_selection(J, np.ones(5), 3, range(2))
    assert str(error.value) == "residual: expected 6 values, got 5"
    J[4, 0] = np.inf
    with pytest.raises(InvalidInputError) as error:
        forward_selection(J, np.ones(6), 3, range(2))
    assert str(error.value) == "jacobian: non-finite value at row 4, column 0"


@pytest.mark.parametrize("n, seed, tied", [(1, 0, 0), (2, 2, 1), (4, 19, 1)])
def test_forward_selection_ties_use_the_sample_standard_error(n, seed, tied):
    # n = 4, seed 19: the population std (ddof 0) gives 0 ties, ddof 2 gives 2; n = 2: a zero
    # standard error would give 0; one pose: no spread to estimate, no warning, no tie.
    rng = np.random.default_rng(seed)
    k = 3
    J = rng.normal(size=(n * k, 3))
    r = -(J @ np.r_[1.0, 0.2, 0.0]) + rng.normal(size=n * k)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        selection = forward_selection(J, r, k, range(3))
    assert selection.tied == tied


@pytest.mark.parametrize("forced", [(), (4, 9)])
def test_forward_selection_scores_candidates_as_refits_do_where_a_few_poses_have_high_leverage(forced):
    """Each candidate's PRESS comes from a rank-one update of every pose's (I - H_ii)^-1: on 6-row
    poses, three of them far out (leverage near one for some columns), the order of the columns and
    the PRESS path are those of explicit leave-one-pose-out refits."""
    rng = np.random.default_rng(24)
    n, k, p = 25, 6, 11
    J = rng.normal(size=(n * k, p))
    J[: 3 * k] *= 30.0  # poses 0-2 dominate their columns' fit
    r = -(J @ np.r_[0.4, -0.2, 0.1, 0.05, np.zeros(p - 4)]) + rng.normal(size=n * k)
    selection = forward_selection(J, r, k, range(p), forced=forced)
    _assert_each_step_adds_the_smallest_press(J, r, k, forced, selection.order)
    assert len(selection.path) == p - len(forced) + 1  # every candidate independent: the whole path
    path = [
        _loo_reference(J, r, k, (list(forced) + list(selection.order))[: len(forced) + size]).sum()
        for size in range(len(selection.path))
    ]
    np.testing.assert_allclose(selection.path, path, rtol=1e-8)


# --------------------------------------------------------------------------------------------------
# Memory-bounded pieces: the triangular factor in row blocks, in-place projections and column removal


def test_triangular_factor_over_several_row_blocks_with_a_vector_and_a_previous_factor():
    """R^T R = P^T P + M^T M and R^T (last column) = M^T r over more rows than one block (4,096);
    a previous factor is stacked on; with fewer rows than columns R has only that many rows."""
    rng = np.random.default_rng(21)
    matrix, vector = rng.normal(size=(9000, 4)), rng.normal(size=9000)
    augmented = np.column_stack((matrix, vector))
    factor = identification.triangular_factor(matrix, vector)
    assert factor.shape == (5, 5) and np.allclose(np.tril(factor, -1), 0.0)
    np.testing.assert_allclose(factor.T @ factor, augmented.T @ augmented, rtol=1e-10)
    alone = identification.triangular_factor(matrix)
    np.testing.assert_allclose(alone.T @ alone, matrix.T @ matrix, rtol=1e-10)
    previous = rng.normal(size=(3, 4))
    stacked = identification.triangular_factor(matrix[:10], previous=previous)
    both = np.vstack((previous, matrix[:10]))
    np.testing.assert_allclose(stacked.T @ stacked, both.T @ both, rtol=1e-10)
    few = identification.triangular_factor(matrix[:2])
    assert few.shape == (2, 4)
    np.testing.assert_allclose(few.T @ few, matrix[:2].T @ matrix[:2], atol=1e-12)


def test_in_place_projection_and_column_removal_over_several_column_blocks():
    # Done a few columns at a time to bound memory, which no result of forward_selection shows (every
    # block size gives the same numbers), so only a direct call checks the blocks past the first.
    rng = np.random.default_rng(22)
    matrix = np.asfortranarray(rng.normal(size=(30, 21)))
    basis = np.linalg.qr(rng.normal(size=(30, 2)))[0]
    expected = matrix - basis @ (basis.T @ matrix)
    identification.project_out(matrix, basis)
    np.testing.assert_allclose(matrix, expected, atol=1e-13)
    identification.project_out(matrix, np.zeros((30, 0)))  # an empty basis changes nothing
    np.testing.assert_allclose(matrix, expected, atol=1e-13)
    removed = identification.without_column(matrix, 2)
    np.testing.assert_array_equal(removed, np.delete(expected, 2, axis=1))
    np.testing.assert_array_equal(identification.without_column(removed, 19), np.delete(expected, [2, 20], axis=1))


def test_forward_selection_with_more_candidates_than_one_update_block_matches_refits():
    """20 candidates (more than the 8 columns updated at a time) with two forced columns: the path
    and the order against refits, as with 7 columns."""
    rng = np.random.default_rng(23)
    n, k, p = 10, 4, 22
    J = rng.normal(size=(n * k, p))
    r = -(J @ np.r_[1.0, -0.6, 0.3, np.zeros(p - 3)]) + 0.5 * rng.normal(size=n * k)
    forced = (17, 3)
    selection = forward_selection(J, r, k, range(p), forced=forced)
    chosen = list(forced)
    for column in selection.order[:6]:
        left = [c for c in range(p) if c not in chosen]
        scores = [_loo_reference(J, r, k, chosen + [c]).sum() for c in left]
        assert column == left[int(np.argmin(scores))]
        chosen.append(column)
    path = [_loo_reference(J, r, k, list(forced) + list(selection.order[:size])).sum() for size in range(7)]
    np.testing.assert_allclose(selection.path[:7], path, rtol=1e-8)
