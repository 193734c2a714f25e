"""The fit past the nominal's rank (`m3t1r.calibration.generic_rank`): how much of the residual a fit
over some columns explains, and the F test that decides whether more parameters are warranted."""

import numpy as np
import pytest
import scipy.stats

from m3t1r.calibration.generic_rank import GENERIC_RANK_SIGNIFICANCE, explained, significant

# ---------------------------------------------------------------------------------------------------
# What a linear fit over chosen columns explains: |P Q^T r|^2


def test_explained_is_the_squared_projection_on_the_chosen_columns():
    """R upper triangular (3 x 3), Q^T r = (3, 4, 12): the first column explains 3^2, the first two
    5^2, all three the whole 13^2; a column of R that mixes two axes explains its own direction only."""
    factor = np.array([[2.0, 0.0, 1.0], [0.0, 5.0, 1.0], [0.0, 0.0, 3.0]])
    rotated = np.array([3.0, 4.0, 12.0])
    assert explained(factor, rotated, [0]) == pytest.approx(9.0, rel=1e-12)
    assert explained(factor, rotated, (0, 1)) == pytest.approx(25.0, rel=1e-12)
    assert explained(factor, rotated, range(3)) == pytest.approx(169.0, rel=1e-12)
    assert explained(factor, rotated, [2]) == pytest.approx((3 + 4 + 36) ** 2 / 11, rel=1e-12)


def test_explained_weighs_columns_of_very_different_sizes_alike():
    """A column 1e-20 times smaller than another, but independent of it, still explains its direction:
    the columns are scaled to unit length before the least-squares solve drops small singular values."""
    factor = np.array([[1.0, 0.0], [1.0, 1e-20]])
    assert explained(factor, np.array([0.0, 1.0]), [0, 1]) == pytest.approx(1.0, rel=1e-12)
    assert explained(factor.T, np.array([1.0, 0.0]), [0, 1]) == pytest.approx(1.0, rel=1e-12)
    assert explained(factor, np.array([0.0, 1.0]), [0]) == pytest.approx(0.5, rel=1e-12)


# ---------------------------------------------------------------------------------------------------
# Whether a drop in chi^2 is significant: the F test at p < 1e-3


def _drop_at(p_value, extra, dof, after=50.0):
    """chi^2 before a fit that would drop it to `after` with `extra` more parameters at exactly `p_value`."""
    return after + extra * after / dof * scipy.stats.f.isf(p_value, extra, dof)


@pytest.mark.parametrize(("extra", "dof"), [(1, 1), (2, 50), (7, 300)])
def test_a_drop_is_significant_just_beyond_the_thousandth_quantile_of_the_f_distribution(extra, dof):
    assert GENERIC_RANK_SIGNIFICANCE == 1e-3
    assert significant(_drop_at(0.99e-3, extra, dof), 50.0, extra, dof) is True
    assert significant(_drop_at(1.01e-3, extra, dof), 50.0, extra, dof) is False
    assert significant(_drop_at(0.2, extra, dof), 50.0, extra, dof) is False


def test_a_drop_to_an_exact_fit_is_significant():
    """No residual left (noise-free data): the variance floor 1e-300 keeps the ratio finite and huge."""
    assert significant(1e-6, 0.0, 3, 40) is True


@pytest.mark.parametrize(
    ("before", "after", "extra", "dof"),
    [
        (100.0, 50.0, 0, 40),
        (100.0, 50.0, -1, 40),
        (100.0, 50.0, 3, 0),
        (100.0, 50.0, 3, -2),
        (50.0, 50.0, 3, 40),
        (40.0, 50.0, 3, 40),
    ],
)
def test_no_extra_parameter_no_degree_of_freedom_or_no_drop_is_never_significant(before, after, extra, dof):
    assert significant(before, after, extra, dof) is False
