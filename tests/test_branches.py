"""Assembly branches (`m3t1r.model.branches`): the diagonal blocks of the passive closure system in
upper block-triangular order, and their determinant signs from one LU."""

import dataclasses

import numpy as np
import pinocchio as pin
import pytest
from scipy.linalg import lapack

from m3t1r.errors import SingularConfigurationError
from m3t1r.model import branches
from m3t1r.model.branches import BranchSignature, branch_blocks, det_sign, diagonal_blocks
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver


def test_diagonal_blocks_of_a_block_triangular_pattern():
    """Rows/columns permuted lower block-triangular pattern: blocks {0, 2} (2 x 2) and {1} (1 x 1)."""
    pattern = np.array([[1, 0, 1], [1, 1, 0], [1, 0, 1]], dtype=bool)
    blocks = sorted((sorted(r.tolist()), sorted(c.tolist())) for r, c in diagonal_blocks(pattern))
    assert blocks == [([0, 2], [0, 2]), ([1], [1])]
    # Each row's matched column is one of its own non-zeros.
    for rows, cols in diagonal_blocks(pattern):
        assert pattern[np.ix_(rows, cols)].any(axis=1).all()

    with pytest.raises(SingularConfigurationError, match="structurally singular"):
        diagonal_blocks(np.array([[1, 1], [0, 0]], dtype=bool))


def test_diagonal_blocks_follow_the_matched_columns_not_the_rows():
    """The only perfect matching is the cycle r0->c1, r1->c2, r2->c0 (and r3->c3), no cycle among
    the rows: four 1 x 1 blocks, each on its own matched entry."""

    pattern = np.array([[0, 1, 0, 0], [0, 1, 1, 0], [1, 0, 1, 0], [1, 0, 0, 1]], dtype=bool)
    blocks = sorted((r.tolist(), c.tolist()) for r, c in diagonal_blocks(pattern))
    assert blocks == [([0], [1]), ([1], [2]), ([2], [0]), ([3], [3])]
    with pytest.raises(SingularConfigurationError) as caught:
        diagonal_blocks(np.array([[1, 1], [0, 0]], dtype=bool))
    assert str(caught.value) == "the closure system is structurally singular (residual nan after 0 iterations)"


def test_det_sign_from_lu_factors():

    rng = np.random.default_rng(4)
    signs = []
    for n in (3, 4, 5, 6):
        for _ in range(6):
            matrix = rng.normal(size=(n, n))
            signs.append(np.linalg.det(matrix) > 0)
            assert det_sign(lapack.dgetrf(matrix)) == signs[-1]
    assert any(signs) and not all(signs)
    assert det_sign(lapack.dgetrf(np.eye(4))) is True


def test_branch_signature_reads_every_block_by_its_size():
    """A 1 x 1 block by its sign, a 2 x 2 by its closed-form determinant, larger ones by LU."""
    blocks = [
        (np.array([0]), np.array([0])),
        (np.array([1, 2]), np.array([1, 2])),
        (np.array([3, 4, 5]), np.array([3, 4, 5])),
    ]
    signature = BranchSignature(blocks, 6)
    jac = np.eye(6)
    jac[0, 0] = 0.5
    jac[1:3, 1:3] = [[1.0, 2.0], [3.0, 4.0]]  # det -2 (1 * 4 - 2 / 3 would be positive)
    jac[3:, 3:] = [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]  # det -2, needs a pivot
    assert signature(jac) == b"\x01\x00\x00"
    jac[0, 0], jac[1:3, 1:3], jac[5, 5] = -0.5, [[4.0, 1.0], [3.0, 2.0]], -2.0  # every sign flipped
    assert signature(jac) == b"\x00\x01\x01"


def test_diagonal_blocks_come_in_upper_block_triangular_order():
    """Rows 0, 1, 2 on their own unknowns; row 0 also uses unknown 1 and row 2 unknown 0: block {2}
    must come before {0}, and {0} before {1}, so that no row uses an unknown of an earlier block."""
    pattern = np.array([[1, 1, 0], [0, 1, 0], [1, 0, 1]], dtype=bool)
    blocks = diagonal_blocks(pattern)
    assert [(r.tolist(), c.tolist()) for r, c in blocks] == [([2], [2]), ([0], [0]), ([1], [1])]
    # The machine's blocks, in the solver's order, leave zeros below the diagonal blocks.
    solver = ClosedLoopSolver(Mechanism.load())
    jac = solver.closure_jacobian(solver.mechanism.home + 0.05)
    order = solver.branch_blocks
    for later, (rows, _) in enumerate(order):
        for _, columns in order[:later]:
            assert not jac[np.ix_(rows, columns)].any()


def test_branch_signature_factors_each_block_when_a_pivot_comes_from_below():
    """An entry the block structure says is zero (row 1, column 0) but is not, and larger than the
    block's own: the LU takes its pivot from the next block, so each block is factored on its own."""
    signature = BranchSignature([(np.array([0]), np.array([0])), (np.array([1]), np.array([1]))], 2)
    assert signature(np.array([[0.1, 0.0], [5.0, -1.0]])) == b"\x01\x00"
    assert signature(np.array([[0.1, 0.0], [0.0, -1.0]])) == b"\x01\x00"  # the same from the one LU
    assert signature(np.array([[-0.1, 3.0], [0.0, -1.0]])) == b"\x00\x00"


# ---------------------------------------------------------------------------------------------------
# A mechanism's branch blocks: from its closure Jacobian's pattern, cached per topology


def _as_sets(blocks):
    return [(sorted(rows.tolist()), sorted(columns.tolist())) for rows, columns in blocks]


def test_the_m_machine_s_blocks_are_the_platform_loop_then_the_four_planar_loops(monkeypatch):
    """With the cache emptied (the first machine of a topology in a process): the platform closure and
    the parallelograms' shared joints form one 8 x 8 block, which the four 2 x 2 loops' rows use."""
    monkeypatch.setattr(branches, "_BLOCK_CACHE", {})
    mechanism = Mechanism.load()
    blocks = branch_blocks(mechanism, ClosureSystem(mechanism.model, mechanism.closures))
    assert _as_sets(blocks) == [
        ([4, 5, 10, 11, 12, 13, 14, 15], [3, 4, 5, 6, 13, 14, 15, 16]),
        ([0, 1], [2, 7]),
        ([2, 3], [1, 9]),
        ([6, 7], [12, 17]),
        ([8, 9], [11, 19]),
    ]


def test_blocks_are_cached_per_topology_and_shared_by_calibrated_copies(monkeypatch, tmp_path):
    monkeypatch.setattr(branches, "_BLOCK_CACHE", {})
    five_bar = Mechanism.load(*five_bar_files(tmp_path))
    first = branch_blocks(five_bar, ClosureSystem(five_bar.model, five_bar.closures))
    assert _as_sets(first) == [([0, 1], [1, 3])]
    wrist = Mechanism.load(*spherical_wrist_files(tmp_path))
    assert _as_sets(branch_blocks(wrist, ClosureSystem(wrist.model, wrist.closures))) == [
        ([0, 1, 2, 3, 4, 5], [1, 2, 4, 5, 7, 8])
    ]
    # Another machine of the five-bar's topology (other link lengths): the cached blocks, not a new pattern.
    model = five_bar.model.copy()
    model.jointPlacements[2] = pin.SE3(np.eye(3), np.array([0.3, 0.1, 0.0])) * model.jointPlacements[2]
    copy = dataclasses.replace(five_bar, model=model)
    assert branch_blocks(copy, ClosureSystem(model, copy.closures)) is first
