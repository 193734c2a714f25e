"""The one Python Newton (`m3t1r.model.newton`) on stand-in systems: every evaluation recorded,
residuals scripted; chord steps, the step cap's neighbours, and the typed failures word for word."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.linalg import lapack

from m3t1r.errors import BranchChangeError, NotConvergedError, OutOfWorkspaceError, SingularConfigurationError
from m3t1r.model.newton import inverse_and_rcond, newton
from m3t1r.model.newton_rules import NewtonRules


class _Scripted:
    """A 2 x 2 stand-in system: the k-th evaluation returns residuals[k] (whatever q is), and the
    Jacobian `jacobian` when asked. `calls` records each with_jacobian argument."""

    def __init__(self, residuals, jacobian=np.eye(2)):
        self.residuals, self.jacobian, self.calls = [np.asarray(r, dtype=float) for r in residuals], jacobian, []

    def __call__(self, q, with_jacobian):
        self.calls.append(with_jacobian)
        residual = self.residuals[min(len(self.calls), len(self.residuals)) - 1]
        return residual, (self.jacobian.copy() if with_jacobian else None)


def _label(jac, lu):
    return b"branch"


# The stand-ins' residuals are of order 1: with chord steps allowed from any residual, the
# contraction rule alone decides when the Jacobian is refreshed.
CHORD_FROM_ANY_RESIDUAL = NewtonRules(chord_below=math.inf)


def test_newton_refreshes_the_jacobian_only_when_a_chord_step_contracts_too_little():
    """Chord steps while |r| <= 0.05 |r_previous| (a contraction of exactly 0.05 is still enough);
    a refresh otherwise, and none once the tolerance is met (a residual exactly at it is converged)."""
    rules = dataclasses.replace(CHORD_FROM_ANY_RESIDUAL, tolerance=0.04)  # the stand-ins' residuals are of order 1
    # 1 -> 0.05 (exactly 0.05 of it: keep the factors) -> 0.04 (met).
    system = _Scripted([[1.0, 0.0], [0.05, 0.0], [0.04, 0.0]])
    outcome = newton(np.zeros(2), None, system, _label, rules)
    assert system.calls == [True, False, False] and outcome.iterations == 2 and outcome.residual == 0.04
    assert outcome.branch == b"branch"
    # 1 -> 0.5 (too little: refresh) -> 0.04 = tolerance, 0.04 > 0.05 * 0.5: met all the same, no refresh.
    system = _Scripted([[1.0, 0.0], [0.5, 0.0], [0.5, 0.0], [0.04, 0.0]])
    outcome = newton(np.zeros(2), None, system, _label, rules)
    assert system.calls == [True, False, True, False] and outcome.iterations == 2 and outcome.branch == b"branch"
    # The first evaluation has the Jacobian, then chord steps while they contract.
    rules = dataclasses.replace(rules, tolerance=1e-12)
    system = _Scripted([[1.0, 0.0], [0.01, 0.0], [1e-4, 0.0], [0.0, 0.0]])
    outcome = newton(np.zeros(2), None, system, _label, rules)
    assert system.calls == [True, False, False, False] and outcome.iterations == 3
    np.testing.assert_array_equal(outcome.jacobian, np.eye(2))
    # Under the default rules a step from a residual above chord_below (1e-4) gets a fresh Jacobian
    # whatever its contraction; from 1e-4 itself, a chord step.
    rules = dataclasses.replace(rules, chord_below=1e-4)
    system = _Scripted([[1.0, 0.0], [1e-4, 0.0], [1e-9, 0.0], [0.0, 0.0]])
    outcome = newton(np.zeros(2), None, system, _label, rules)
    assert system.calls == [True, True, False, False] and outcome.iterations == 3


def test_newton_stops_on_a_non_finite_residual_as_out_of_workspace():
    """Wherever the nan is: after a larger entry too (BLAS idamax may skip a nan there)."""
    rules = CHORD_FROM_ANY_RESIDUAL
    for residual in ([np.nan, 0.0], [np.inf, 0.0], [5.0, np.nan], [0.5, -np.inf]):
        system = _Scripted([[1.0, 0.0], residual])
        with pytest.raises(OutOfWorkspaceError) as caught:
            newton(np.zeros(2), None, system, _label, rules)
        assert caught.value.iterations == 1 and system.calls == [True, False]
        assert not math.isfinite(caught.value.residual)


def test_newton_singular_verdict_uses_the_one_norm_and_is_word_for_word():
    """J = [[1, 1], [0, 1e-11]]: 1-norm 1, |J^-1|_1 = 2e11, so rcond = 5e-12 (the infinity norm,
    2, would give 2.5e-12)."""
    system = _Scripted([[1.0, 0.0], [3e-13, 0.0]], jacobian=np.array([[1.0, 1.0], [0.0, 1e-11]]))
    rules = NewtonRules(tolerance=1e-12)
    with pytest.raises(SingularConfigurationError) as caught:
        newton(np.zeros(2), None, system, _label, rules)
    assert (
        str(caught.value)
        == "singular configuration (reciprocal condition 5.00e-12) (residual 3.000e-13 after 1 iterations)"
    )
    assert caught.value.residual == 3e-13 and caught.value.iterations == 1


def test_newton_branch_change_is_word_for_word():
    rules = CHORD_FROM_ANY_RESIDUAL
    system = _Scripted([[1.0, 0.0], [0.5, 0.0], [0.5, 0.0], [2e-13, 0.0]])
    labels = iter([b"start", b"other", b"other"])
    with pytest.raises(BranchChangeError) as caught:
        newton(np.zeros(2), None, system, lambda jac, lu: next(labels), rules)
    assert str(caught.value) == (
        "the solution lies on another assembly branch than the start (Newton crossed a "
        "singularity) (residual 2.000e-13 after 2 iterations)"
    )
    assert caught.value.residual == 2e-13 and caught.value.iterations == 2


def test_newton_far_or_near_after_the_last_step_at_exactly_1e_6():
    """Stopped by max_iterations: a residual of exactly 1e-6 is near (NotConverged), above it far."""
    rules = NewtonRules(max_iterations=1)
    for last, error in ((1e-6, NotConvergedError), (np.nextafter(1e-6, 1.0), OutOfWorkspaceError)):
        system = _Scripted([[1.0, 0.0], [last, 0.0]])
        with pytest.raises(error) as caught:
            newton(np.zeros(2), None, system, _label, rules)
        assert caught.value.residual == last and caught.value.iterations == 1


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the steps on these factors are nan
@pytest.mark.parametrize(
    "jacobian", [np.array([[1.0, 1.0], [1.0, 1.0]]), np.array([[1.0, np.nan], [0.0, 1.0]])], ids=["zero pivot", "nan"]
)
def test_newton_calls_a_zero_pivot_or_a_nan_inverse_singular(jacobian):
    """rcond is 0 when U has a zero pivot (no inverse) or the inverse is nan, never accepted."""
    system, rules = _Scripted([[1.0, 0.0], [0.0, 0.0]], jacobian=jacobian), NewtonRules()
    with pytest.raises(SingularConfigurationError) as caught:
        newton(np.zeros(2), None, system, _label, rules)
    assert str(caught.value).startswith("singular configuration (reciprocal condition 0.00e+00)")


def test_newton_rcond_is_exact_and_its_inverse_is_returned():
    """rcond = 1 / (|J|_1 |J^-1|_1): J = [[2, 1], [0, 4]] has |J|_1 = 5, J^-1 = [[0.5, -0.125], [0, 0.25]],
    |J^-1|_1 = 0.5: 0.4, reported with the inverse (FK's tangent uses it)."""
    jacobian = np.array([[2.0, 1.0], [0.0, 4.0]])
    system, rules = _Scripted([[1.0, 0.0], [0.0, 0.0]], jacobian=jacobian), NewtonRules()
    outcome = newton(np.zeros(2), None, system, _label, rules)
    np.testing.assert_allclose(outcome.inverse, np.linalg.inv(jacobian), rtol=1e-15)
    inverse, rcond = inverse_and_rcond(lapack.dgetrf(jacobian)[:2], 5.0)
    assert rcond == pytest.approx(0.4, rel=1e-15)


def test_newton_labels_a_single_jacobian_once():
    """A cold solve on one Jacobian computes its signature once and compares it with itself."""
    rules = CHORD_FROM_ANY_RESIDUAL
    calls = []

    def counted(jac, lu):
        calls.append(1)
        return b"branch"

    system = _Scripted([[1.0, 0.0], [0.01, 0.0], [0.0, 0.0]])
    outcome = newton(np.zeros(2), None, system, counted, rules)
    assert len(calls) == 1 and outcome.branch == b"branch" and system.calls == [True, False, False]


def test_a_zero_pivot_before_convergence_ends_the_solve_as_singular():
    """No step exists from an exactly singular Jacobian: the solve stops there as singular (the
    compiled loop's `factor` says the same), before any step and whatever the residual."""
    system = _Scripted([[1.0, 0.0], [0.5, 0.0]], jacobian=np.array([[1.0, 1.0], [1.0, 1.0]]))
    with pytest.raises(SingularConfigurationError) as caught:
        newton(np.zeros(2), None, system, _label, NewtonRules())
    assert (
        str(caught.value)
        == "singular configuration (reciprocal condition 0.00e+00) (residual 1.000e+00 after 0 iterations)"
    )
    assert system.calls == [True]


# ---------------------------------------------------------------------------------------------------
# Steps on a system that depends on q: in place, over some columns, capped, and what the labels see


class _Linear:
    """r(q) = A q - b with Jacobian A (rows x nv); `seen` records a copy of every q evaluated."""

    def __init__(self, matrix, target):
        self.matrix, self.target, self.seen = np.asarray(matrix, dtype=float), np.asarray(target, dtype=float), []

    def __call__(self, q, with_jacobian):
        self.seen.append(q.copy())
        return self.matrix @ q - self.target, (self.matrix.copy() if with_jacobian else None)


UNCAPPED = NewtonRules(max_step=10.0)  # one Newton step solves a linear system


def test_newton_solves_in_place_and_returns_the_solution():
    """A linear system: one Newton step from 0 lands on A^-1 b = (0.25, 0.5), in the array passed."""
    system, q = _Linear([[2.0, 1.0], [0.0, 4.0]], [1.0, 2.0]), np.zeros(2)
    outcome = newton(q, None, system, _label, UNCAPPED)
    assert outcome.q is q and outcome.iterations == 1 and outcome.residual == 0.0
    np.testing.assert_allclose(q, [0.25, 0.5], rtol=0, atol=1e-15)
    np.testing.assert_allclose(system.seen, [[0.0, 0.0], [0.25, 0.5]], rtol=0, atol=1e-15)


def test_newton_over_some_columns_leaves_the_others_alone():
    """Three columns, unknowns 0 and 2: the square system is A's columns 0 and 2; q[1] stays 0.1."""
    matrix = np.array([[2.0, 5.0, 1.0], [0.0, 7.0, 4.0]])
    system, q = _Linear(matrix, [1.0, 2.0]), np.array([0.0, 0.1, 0.0])
    outcome = newton(q, np.array([0, 2]), system, _label, UNCAPPED)
    assert outcome.q is q and q[1] == 0.1 and outcome.iterations == 1
    np.testing.assert_allclose(matrix @ q, [1.0, 2.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(outcome.jacobian, matrix)
    np.testing.assert_allclose(outcome.inverse, np.linalg.inv(matrix[:, [0, 2]]), rtol=1e-15)


def test_newton_caps_a_step_at_max_step_keeping_its_direction():
    """From 0 towards (0.1, 1) under max_step 0.3: steps of (0.03, 0.3), capped by their largest
    component, until the last, shorter one."""
    system, q = _Linear(np.eye(2), [0.1, 1.0]), np.zeros(2)
    outcome = newton(q, None, system, _label, NewtonRules())
    expected = [[0.0, 0.0], [0.03, 0.3], [0.06, 0.6], [0.09, 0.9], [0.1, 1.0]]
    np.testing.assert_allclose(system.seen, expected, rtol=0, atol=1e-15)
    assert outcome.iterations == 4


def test_a_refreshed_jacobian_is_evaluated_where_the_solve_stands():
    """Chord steps allowed from any residual: each capped step contracts |r| by 0.7 only (> 0.05),
    so the Jacobian is refreshed, at the new q, after every evaluation without it."""
    system, q = _Linear(np.eye(2), [0.1, 1.0]), np.zeros(2)
    assert newton(q, None, system, _label, CHORD_FROM_ANY_RESIDUAL).iterations == 4
    steps = [[0.0, 0.0], [0.03, 0.3], [0.06, 0.6], [0.09, 0.9], [0.1, 1.0]]
    expected = [steps[0]] + [s for s in steps[1:-1] for _ in range(2)] + [steps[-1]]
    np.testing.assert_allclose(system.seen, expected, rtol=0, atol=1e-15)


def test_newton_judges_contraction_against_the_previous_residual():
    """From |r| = 2, a chord step to 0.09 contracts by 0.045 <= 0.05: no refresh (0.05 of 2 is 0.1)."""
    system = _Scripted([[2.0, 0.0], [0.09, 0.0], [0.0, 0.0]])
    outcome = newton(np.zeros(2), None, system, _label, CHORD_FROM_ANY_RESIDUAL)
    assert system.calls == [True, False, False] and outcome.iterations == 2


def test_a_zero_first_pivot_is_singular_before_any_step():
    """A first column of zeros: getrf's first pivot is zero (info 1)."""
    system = _Scripted([[1.0, 0.0]], jacobian=np.array([[0.0, 1.0], [0.0, 2.0]]))
    with pytest.raises(SingularConfigurationError) as caught:
        newton(np.zeros(2), None, system, _label, NewtonRules())
    assert caught.value.iterations == 0 and system.calls == [True]


def test_a_converged_system_exactly_at_the_rcond_threshold_is_accepted():
    """rcond of [[2, 1], [0, 4]] is 0.4 exactly (test above): refused below the threshold only."""
    jacobian = np.array([[2.0, 1.0], [0.0, 4.0]])
    system = _Scripted([[1.0, 0.0], [0.0, 0.0]], jacobian=jacobian)
    assert newton(np.zeros(2), None, system, _label, NewtonRules(singular_rcond=0.4)).iterations == 1
    system = _Scripted([[1.0, 0.0], [0.0, 0.0]], jacobian=jacobian)
    with pytest.raises(SingularConfigurationError, match=r"reciprocal condition 4.00e-01"):
        newton(np.zeros(2), None, system, _label, NewtonRules(singular_rcond=np.nextafter(0.4, 1.0)))


def test_the_factors_of_a_singular_matrix_have_rcond_zero():
    """getri fails on U's zero pivot (leaving finite numbers in its output): rcond 0, not their condition."""
    for singular in ([[1.0, 2.0], [2.0, 4.0]], [[0.0, 1.0], [0.0, 2.0]], [[1.0, 0.0], [0.0, 0.0]]):
        assert inverse_and_rcond(lapack.dgetrf(np.array(singular))[:2], 3.0)[1] == 0.0


def test_the_labels_read_the_jacobian_and_the_factors_of_its_square_system():
    """The start's label (unless a start branch is given) and the converged one: each reads the full
    Jacobian and the getrf factors of its unknowns' columns."""
    matrix = np.array([[2.0, 5.0, 1.0], [0.0, 7.0, 4.0]])
    factors = lapack.dgetrf(matrix[:, [0, 2]])[:2]
    for start in (None, b"branch"):
        seen = []

        def recording(jac, lu):
            seen.append((jac.copy(), lu))
            return b"branch"

        newton(np.zeros(3), np.array([0, 2]), _Linear(matrix, [1.0, 2.0]), recording, UNCAPPED, start)
        assert len(seen) == (2 if start is None else 1)  # the start's, then the converged Jacobian's
        for jac, lu in seen:
            np.testing.assert_array_equal(jac, matrix)
            np.testing.assert_array_equal(lu[0], factors[0])
            np.testing.assert_array_equal(lu[1], factors[1])
