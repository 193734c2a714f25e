"""Repeats of one pose (`m3t1r.calibration.repeats`): grouping rows by readings and sources, folds of
whole groups, the inlier split of a cross-validation, its errors, and grouped blocks for selection.
(The grouping and the selection score on grouped blocks are also tested in test_campaign.py.)"""

import numpy as np
import pytest

from m3t1r.calibration.repeats import (
    MAX_PADDING,
    REPEAT_TOLERANCE,
    CrossValidation,
    fold_errors,
    grouped_blocks,
    grouped_folds,
    inlier_folds,
    pose_groups,
)
from m3t1r.errors import InvalidInputError

# ---------------------------------------------------------------------------------------------------
# Groups of repeats: equal readings on a grid of the tolerance, or a shared source, transitively


def test_groups_are_numbered_in_order_of_first_appearance():
    q = np.array([[0.9, 0.0], [0.1, 0.0], [0.9, 0.0], [0.5, 0.0], [0.1, 0.0]])
    assert pose_groups(q).tolist() == [0, 1, 0, 2, 1]
    assert pose_groups(q.tolist()).tolist() == [0, 1, 0, 2, 1]  # any array-like


def test_readings_are_compared_on_a_grid_of_the_tolerance():
    """REPEAT_TOLERANCE is 1e-4: 3e-5 apart is one posture, 3e-4 apart two; a coarser tolerance joins them."""
    assert REPEAT_TOLERANCE == 1e-4
    q = np.array([[0.2, 0.3], [0.2 + 3e-5, 0.3 - 3e-5], [0.2 + 3e-4, 0.3]])
    assert pose_groups(q).tolist() == [0, 0, 1]
    assert pose_groups(q, tolerance=1e-2).tolist() == [0, 0, 0]
    assert pose_groups(q, tolerance=1e-6).tolist() == [0, 1, 2]


def test_sources_join_groups_transitively_and_relabel_by_first_appearance():
    """Rows 0-1 share readings, 1-3 a source, 3-4 readings: one group; row 2 is alone, row 5 joins
    row 2 by its source."""
    q = np.array([[0.1, 0.1], [0.1, 0.1], [0.2, 0.2], [0.3, 0.3], [0.3, 0.3], [0.4, 0.4]])
    sources = np.array(["f:1", "f:2", "f:3", "f:2", "f:5", "f:3"])
    assert pose_groups(q, sources).tolist() == [0, 0, 1, 0, 0, 1]
    assert pose_groups(q, list(sources)).tolist() == [0, 0, 1, 0, 0, 1]
    # A chain through sources only, against the order of the rows.
    q = np.arange(12.0).reshape(6, 2)
    assert pose_groups(q, np.array([3, 1, 2, 3, 2, 1])).tolist() == [0, 1, 2, 0, 2, 1]
    assert pose_groups(q, np.array([0, 1, 0, 2, 1, 2])).tolist() == [0, 1, 0, 2, 1, 2]
    # A long chain: row i shares its source with row i + 1 (pairs), readings with row i - 1.
    q = np.repeat(np.arange(5.0), 2)[1:-1].reshape(-1, 1)  # 0 1 1 2 2 3 3 4
    sources = np.array([0, 0, 1, 1, 2, 2, 3, 3])
    assert pose_groups(q, sources).tolist() == [0] * 8


@pytest.mark.parametrize(
    ("readings", "tolerance", "message"),
    [
        (np.zeros(3), 1e-4, "pose_groups: expected finite (N, n) readings, got shape (3,)"),
        (np.array([[0.0, np.nan]]), 1e-4, "pose_groups: expected finite (N, n) readings, got shape (1, 2)"),
        (np.array([[0.0, np.inf]]), 1e-4, "pose_groups: expected finite (N, n) readings, got shape (1, 2)"),
        ([[0.0, None]], 1e-4, "pose_groups: expected finite (N, n) readings, got shape (1, 2)"),  # a reading missing
        (np.zeros((2, 2)), 0.0, "pose_groups: tolerance must be positive, got 0.0"),
        (np.zeros((2, 2)), float("nan"), "pose_groups: tolerance must be positive, got nan"),
    ],
)
def test_readings_that_are_not_a_finite_table_or_a_tolerance_not_positive_are_refused(readings, tolerance, message):
    with pytest.raises(InvalidInputError) as caught:
        pose_groups(readings, tolerance=tolerance)
    assert str(caught.value) == message


# ---------------------------------------------------------------------------------------------------
# Folds of whole groups


def test_folds_deal_the_permuted_groups_round_by_first_appearance():
    """Labels 7, 7, 3, 9, 3: groups 0, 0, 1, 2, 1, dealt as rng.permutation(3) % 2."""
    folds = grouped_folds(np.array([7, 7, 3, 9, 3]), 2, np.random.default_rng(4))
    dealt = np.random.default_rng(4).permutation(3) % 2
    assert folds.tolist() == dealt[[0, 0, 1, 2, 1]].tolist()


def test_fewer_groups_than_folds_are_refused_with_both_counts():
    with pytest.raises(InvalidInputError) as caught:
        grouped_folds(np.array([1, 1, 2, 2]), 3, np.random.default_rng(0))
    assert str(caught.value) == (
        "cross-validation: 3 folds need at least 3 distinct poses (repeats of a pose count once), got 2"
    )
    with pytest.raises(InvalidInputError, match="got 0$"):
        grouped_folds(np.array([], dtype=int), 2, np.random.default_rng(0))
    assert grouped_folds(np.array([5, 6]), 2, np.random.default_rng(0)).tolist() in ([0, 1], [1, 0])


# ---------------------------------------------------------------------------------------------------
# The inlier split of a cross-validation


def test_inlier_folds_split_the_active_poses_by_the_seed():
    active = np.array([True, False, True, True, True, False, True, True])
    split = inlier_folds(active, 3, 11)
    assert split.inliers.tolist() == [0, 2, 3, 4, 6, 7] and split.groups == 6
    assert split.fold.tolist() == (np.random.default_rng(11).permutation(6) % 3).tolist()
    assert inlier_folds(active, 3, 11).fold.tolist() == split.fold.tolist()  # the seed decides


def test_inlier_folds_keep_groups_whole_and_count_the_inliers_groups():
    active = np.array([True, True, True, True, False, True, True])
    labels = np.array([0, 0, 1, 2, 3, 2, 4])
    split = inlier_folds(active, 2, 0, labels)
    assert split.inliers.tolist() == [0, 1, 2, 3, 5, 6] and split.groups == 4
    fold = dict(zip(split.inliers.tolist(), split.fold.tolist()))
    assert fold[0] == fold[1] and fold[3] == fold[5]
    assert split.fold.tolist() == ((np.random.default_rng(0).permutation(4) % 2)[[0, 0, 1, 2, 2, 3]]).tolist()


@pytest.mark.parametrize(
    ("folds", "active", "groups", "seed", "message"),
    [
        (1, np.ones(10, bool), None, 0, "cross-validation: 1 folds need at least 2 inlier poses"),
        (
            3,
            np.r_[np.ones(5, bool), np.zeros(5, bool)],
            None,
            0,
            "cross-validation: 3 folds need at least 6 inlier poses",
        ),
        (2, np.ones(4, bool), np.zeros(3, int), 0, "cross-validation: (3,) group labels for 4 poses"),
        (2, np.ones(4, bool), None, -1, "seed: expected a whole number of at least 0, got -1"),
    ],
)
def test_a_split_that_cannot_be_made_is_refused_word_for_word(folds, active, groups, seed, message):
    with pytest.raises(InvalidInputError) as caught:
        inlier_folds(active, folds, seed, groups)
    assert str(caught.value) == message


def test_exactly_two_inliers_per_fold_are_enough():
    split = inlier_folds(np.ones(4, bool), 2, 0)
    assert sorted(split.fold.tolist()) == [0, 0, 1, 1]
    assert inlier_folds(np.ones(4, bool), 2, 0.0).fold.tolist() == split.fold.tolist()


# ---------------------------------------------------------------------------------------------------
# The errors of held-out poses


def test_fold_errors_of_full_poses_positions_and_points():
    residuals = np.array([[3.0, 4.0, 0.0, 0.6, 0.8, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    errors = fold_errors(residuals)
    assert errors.position.tolist() == [5.0, 1.0] and errors.rotation.tolist() == [1.0, 0.0]
    positions = fold_errors(residuals[:, :3])
    assert positions.position.tolist() == [5.0, 1.0] and np.isnan(positions.rotation).all()
    seen = np.array([[True, False], [True, True]])  # two points per pose, the first pose's second unseen
    points = fold_errors(residuals, seen)
    assert points.position.tolist() == [5.0, 1.0, 0.0]  # pose 0's first point, pose 1's two
    assert len(points.rotation) == 3 and np.isnan(points.rotation).all()


def test_a_cross_validation_record_counts_no_groups_unless_told():
    record = CrossValidation(fold_errors(np.zeros((2, 6))), 5)
    assert (record.folds, record.groups) == (5, 0)


# ---------------------------------------------------------------------------------------------------
# Grouped blocks for a leave-one-group-out selection score


def test_grouped_blocks_put_each_group_in_one_zero_padded_block_in_row_order():
    """Poses of 2 rows, groups 0, 1, 0, 2: blocks of 2 poses (4 rows): group 0's poses 0 and 2, group
    1's pose 1 and a zero pose, group 2's pose 3 and a zero pose."""
    jacobian = np.arange(16.0).reshape(8, 2) + 1.0
    residual = np.arange(8.0) + 1.0
    out_j, out_r, block = grouped_blocks(jacobian, residual, 2, np.array([5, 6, 5, 7]))
    assert block == 4 and out_j.shape == (12, 2) and out_r.shape == (12,)
    poses = [[0, 1], [4, 5], [2, 3], None, [6, 7], None]  # rows of each slot, None: padding
    for slot, rows in enumerate(poses):
        got_j, got_r = out_j[2 * slot : 2 * slot + 2], out_r[2 * slot : 2 * slot + 2]
        if rows is None:
            assert not got_j.any() and not got_r.any()
        else:
            np.testing.assert_array_equal(got_j, jacobian[rows])
            np.testing.assert_array_equal(got_r, residual[rows])


def test_grouped_blocks_are_the_inputs_when_grouping_changes_nothing_or_pads_too_much():
    jacobian, residual = np.ones((6, 2)), np.ones(6)
    for groups in (None, np.arange(6), [0, 1, 2, 3, 4, 5]):
        out = grouped_blocks(jacobian, residual, 1, groups)
        assert out[0] is jacobian and out[1] is residual and out[2] == 1
    assert MAX_PADDING == 2.0
    # One pose repeated 4 times among 3 single ones: 4 blocks of 4 = 16 rows > 2 x 7: left as they are.
    out = grouped_blocks(np.ones((7, 2)), np.ones(7), 1, [0, 0, 0, 0, 1, 2, 3])
    assert out[2] == 1 and out[0].shape == (7, 2)
    # Repeated 3 times among 3 single ones: 4 blocks of 3 = 12 rows, exactly 2 x 6: grouped.
    out = grouped_blocks(jacobian, residual, 1, [0, 0, 0, 1, 2, 3])
    assert out[2] == 3 and out[0].shape == (12, 2) and out[1].shape == (12,)


def test_grouped_blocks_keep_the_poses_of_a_group_in_their_order_in_a_long_campaign():
    """60 poses in 3 interleaved groups of 20: each block holds its group's poses in campaign order."""
    groups = np.arange(60) % 3
    jacobian, residual = np.arange(60.0)[:, None] * np.ones((1, 2)), np.arange(60.0)
    out_j, out_r, block = grouped_blocks(jacobian, residual, 1, groups)
    assert block == 20
    for g in range(3):
        assert out_r[20 * g : 20 * g + 20].tolist() == list(range(g, 60, 3))
        assert out_j[20 * g : 20 * g + 20, 1].tolist() == list(range(g, 60, 3))
