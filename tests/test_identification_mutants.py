"""Identification tests that kill mutants the behaviour tests let through (docs/mutation.md).

Every termination reason of `levenberg_marquardt` is asserted with its iteration count and the
rule that fired; NaN and inf are fed to the solver; tolerances are probed at their boundary.
"""

from __future__ import annotations

import numpy as np
import pytest

from m3t1r.calibration.identification import (
    RecursiveLeastSquares,
    batch_least_squares,
    levenberg_marquardt,
    select_base_parameters,
)
from m3t1r.errors import IdentificationError, InvalidInputError


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
    result = levenberg_marquardt(ExponentialFit(), X_FAR, cost_tolerance=tolerance, step_tolerance=0.0,
                                 gradient_tolerance=0.0)
    assert result.converged and result.termination == "cost"
    decrease, before = _decreases(result)
    assert decrease[-1] <= tolerance * before[-1]  # the rule that fired
    assert np.all(decrease[:-1] > tolerance * before[:-1])  # and did not fire earlier
    assert result.iterations == len(result.cost_history) - 1
    assert result.iterations == 6


def test_absolute_cost_rule_stops_at_the_first_small_decrease():
    absolute = 1e-10  # the cost is 1.5e-3: decreases of 4e-9 (step 5) then 1e-14 (step 6)
    result = levenberg_marquardt(ExponentialFit(), X_FAR, cost_tolerance=0.0, step_tolerance=0.0,
                                 gradient_tolerance=0.0, absolute_cost_tolerance=absolute)
    assert result.termination == "cost"
    decrease, _ = _decreases(result)
    assert decrease[-1] <= absolute and np.all(decrease[:-1] > absolute)
    assert result.iterations == 6


def test_without_cost_rules_the_step_rule_stops():
    result = levenberg_marquardt(ExponentialFit(), X0, cost_tolerance=0.0, step_tolerance=1e-10,
                                 gradient_tolerance=0.0, max_iterations=200)
    assert result.converged and result.termination == "step" and result.step_norm <= 1e-10
    # The step rule stops before the step is accepted: the iteration count includes that last solve.
    assert result.iterations == len(result.cost_history)


def test_gradient_rule_on_a_zero_residual_problem():
    class Line:
        def residual_and_jacobian(self, x):
            return np.array([x[0] - 1.0, 2.0 * (x[1] + 3.0)]), np.array([[1.0, 0.0], [0.0, 2.0]])

        def retract(self, x, step):
            return x + step

    result = levenberg_marquardt(Line(), np.zeros(2), gradient_tolerance=1e-8, cost_tolerance=0.0,
                                 step_tolerance=0.0)
    assert result.termination == "gradient" and result.converged
    np.testing.assert_allclose(result.state, [1.0, -3.0], atol=1e-8)
    assert result.iterations == len(result.cost_history) - 1 and result.iterations <= 4
    # Already at the minimum: zero iterations, gradient rule, the step norm never computed.
    at_minimum = levenberg_marquardt(Line(), np.array([1.0, -3.0]))
    assert at_minimum.termination == "gradient" and at_minimum.iterations == 0 and np.isnan(at_minimum.step_norm)


def test_max_iterations_is_reported_not_converged():
    result = levenberg_marquardt(ExponentialFit(), X0, cost_tolerance=0.0, step_tolerance=0.0,
                                 gradient_tolerance=0.0, max_iterations=2)
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

    result = levenberg_marquardt(Guarded(), np.array([3.0, -3.0]), initial_damping=1e-9)
    assert result.converged and np.all(np.isfinite(result.cost_history))
    np.testing.assert_allclose(result.state, [2.0, -1.5], atol=0.05)


def test_stalled_when_the_jacobian_is_wrong():
    class WrongSign(ExponentialFit):
        def residual_and_jacobian(self, x):
            r, J = super().residual_and_jacobian(x)
            return r, -J

    result = levenberg_marquardt(WrongSign(), X0, step_tolerance=0.0)
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
    assert select_base_parameters(matrix, "abcd", rel_tol=1e-9).rank == 4
    assert select_base_parameters(matrix, "abcd", rel_tol=1e-2).rank == 3
    zero = np.column_stack((A, 1e-12 * A[:, 1]))
    base = select_base_parameters(zero, "abcd", rel_tol=1e-9)
    assert base.zero_columns == ("d",) and base.rank == 3
    with pytest.raises(InvalidInputError, match="rel_tol"):
        select_base_parameters(A, "abc", rel_tol=1.0)
    with pytest.raises(InvalidInputError, match="rel_tol"):
        select_base_parameters(A, "abc", rel_tol=0.0)


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
