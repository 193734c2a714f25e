"""Assembly branches of a closed-loop mechanism: the diagonal blocks of its passive closure system
and the signs of their determinants, which every solve (single, batch, compiled) must keep.

A branch label is one byte per block (1: det > 0). A solve fails with BranchChangeError when its
solution's labels differ from the start's: it crossed a singularity onto another assembly mode.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import lapack
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, maximum_bipartite_matching

from m3t1r.errors import SingularConfigurationError

if TYPE_CHECKING:
    from m3t1r.model.closures import ClosureSystem
    from m3t1r.model.description import Mechanism

__all__ = ["BranchSignature", "branch_blocks", "det_sign", "diagonal_blocks"]

Blocks = list[tuple[np.ndarray, np.ndarray]]
_BLOCK_CACHE: dict[tuple, Blocks] = {}


def det_sign(lu: tuple) -> bool:
    """Whether det(A) > 0, from LAPACK getrf factors (0-based pivots)."""
    factors, pivots = lu[0], lu[1]
    flips = np.count_nonzero(factors.diagonal() < 0) + np.count_nonzero(pivots != _ARANGE[: len(pivots)])
    return bool(flips % 2 == 0)


_ARANGE = np.arange(256)


def diagonal_blocks(pattern: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rows, columns) of the diagonal blocks of the block-triangular form of a square pattern,
    in upper block-triangular order: no row uses an unknown of an earlier block.

    A perfect matching puts one unknown on each row; the strongly connected components of
    "row i uses the unknown matched to row k" are the blocks (Dulmage-Mendelsohn fine form).
    """
    match = maximum_bipartite_matching(csr_matrix(pattern.astype(np.int8)), perm_type="column")
    if np.any(match < 0):
        raise SingularConfigurationError("the closure system is structurally singular")
    uses = pattern[:, match]
    count, labels = connected_components(csr_matrix(uses.astype(np.int8)), directed=True, connection="strong")
    before = np.zeros((count, count), dtype=bool)  # before[a, b]: block a's rows use block b's unknowns
    row, used = np.nonzero(uses)
    before[labels[row], labels[used]] = True
    order: list[int] = []
    while len(order) < count:  # the blocks form a DAG: one of them is never used by the others left
        order.append(
            next(
                b
                for b in range(count)
                if b not in order and not any(before[a, b] for a in range(count) if a != b and a not in order)
            )
        )
    return [(rows, match[rows]) for rows in (np.flatnonzero(labels == b) for b in order)]


class BranchSignature:
    """Signs of the determinants of the diagonal blocks of the passive closure system.

    One determinant over the whole system would miss two loops flipping at once (e.g. both
    five-bars folding their knees below the rails); each block's determinant changes sign only
    through that block's own singularity. All of them come from one LU of the system permuted to
    upper block-triangular form (`diagonal_blocks`' order): with zeros below the diagonal blocks,
    partial pivoting takes each pivot of a block's columns among that block's rows, so a block's
    sign is that of its U diagonal times that of its own row swaps. Should a pivot come from below
    its block (entries the structure says are zero are not), the blocks are factored one by one.
    """

    def __init__(self, blocks: list[tuple[np.ndarray, np.ndarray]], n_columns: int) -> None:
        rows, columns = np.concatenate([r for r, _ in blocks]), np.concatenate([c for _, c in blocks])
        self._square = rows[:, None] * n_columns + columns[None, :]  # flat indices into a (rows x n_columns) Jacobian
        ends = np.cumsum([len(r) for r, _ in blocks]).tolist()
        self._spans = list(zip([0] + ends[:-1], ends))  # each block's positions in the permuted system

    def __call__(self, jac: np.ndarray) -> bytes:
        square = jac.take(self._square)
        factors, pivots = lapack.dgetrf(square)[:2]
        # Python lists: at this size a loop costs less than the numpy calls that would replace it.
        diagonal, swaps, signs = factors.diagonal().tolist(), pivots.tolist(), []
        for start, end in self._spans:
            flips = 0
            for k in range(start, end):
                if swaps[k] >= end:  # a pivot from below the block: its structural zeros are not
                    return b"".join(
                        b"\x01" if det_sign(lapack.dgetrf(square[a:b, a:b])) else b"\x00" for a, b in self._spans
                    )
                flips += (diagonal[k] < 0.0) + (swaps[k] != k)
            signs.append(flips % 2 == 0)
        return bytes(signs)


def branch_blocks(mechanism: Mechanism, system: ClosureSystem) -> Blocks:
    """The diagonal blocks (closure rows, passive velocity indices) of `mechanism`'s passive closure
    Jacobian, in upper block-triangular order.

    The pattern is taken at a few generic configurations near home (entries numerically zero at one
    q, e.g. by axis alignment at home, must not split blocks). It depends on the topology only, so
    calibrated copies of a machine share it (cached on closures, actuators and joint names).
    """
    model, passive = mechanism.model, mechanism.passive_ids
    key = (mechanism.closures, mechanism.actuated_joints, tuple(model.names))
    if key not in _BLOCK_CACHE:
        rng = np.random.default_rng(0)
        pattern = np.zeros((system.n_rows, len(passive)), dtype=bool)
        for _ in range(3):
            q = mechanism.home + rng.normal(0.0, 0.1, model.nv)
            jac = system.evaluate(q, True)[1][:, passive]
            pattern |= np.abs(jac) > 1e-9 * np.max(np.abs(jac))
        _BLOCK_CACHE[key] = [(rows, passive[cols]) for rows, cols in diagonal_blocks(pattern)]
    return _BLOCK_CACHE[key]
