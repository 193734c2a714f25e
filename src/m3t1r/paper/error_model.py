"""The paper's error model (section 3): per chain the local POE of eq. (6), every error lumped into
the initial poses T(0) (eq. 11), y_i = log6(g_meas g_i(q)^-1) (eq. 18) = J_i x_i (eq. 19-20),
WORLD rows, stacked over both chains and m poses (eq. 21, 31), and the rank analysis of that stack.

Eq. (21) is implemented in the stacked form [y1; y2] = blockdiag(J1, J2) [x1; x2], not as
written (A = [J1, J2], Y = y1 = y2), which adds both chains' predictions of one error
(`TwoChainErrorModel` says why).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.identification import BaseParameters, select_base_parameters
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.model.description import Mechanism
from m3t1r.model.poe import forward_and_error_jacobians
from m3t1r.paper.chains import _TWIST, PaperChain, _as_configurations, paper_chains

__all__ = [
    "PAPER_IDENTIFIABLE_BOUND",
    "Identifiability",
    "TwoChainErrorModel",
    "two_chain_error_model",
    "two_chain_identifiability",
]

#: The paper's bound on identifiable parameters of the whole machine, 4r + 2p + 6 with its six
#: equivalent revolute and two prismatic joints (section 3.2): 4 * 6 + 2 * 2 + 6.
PAPER_IDENTIFIABLE_BOUND = 34


@dataclass(frozen=True)
class TwoChainErrorModel:
    """Both chains' linearised pose errors at N poses, stacked (eq. 18-20, 31).

    Per pose, [y_1; y_2] = blockdiag(J_1, J_2) [x_1; x_2] to first order, with
    y_i = log6(g_meas,i g_i(q)^-1) ([v; w], m and rad, WORLD: v is the velocity of the point at
    {B}'s origin) and J_i the (6, 42) error Jacobian of eq. (19), columns the right-multiplied
    errors dt of chain i's placements in `parameter_names` order (chain 1's 42, then chain 2's).

    Why not eq. (21) as printed: with A = [J_1, J_2] and Y = y_1 = y_2, one measured error is
    explained by the *sum* J_1 x_1 + J_2 x_2, as if each chain moved the platform on top of the
    other. Along directions both chains share (their base and end placements) the fit can split
    the error between them (the minimum-norm solution halves it), and then neither chain's model
    reproduces the platform. Each chain is a complete serial model of the same platform pose,
    so each must reproduce the measurement on its own: that is the stacked form, and it is also
    the paper's objective (13), a sum over i of each chain's residual.

    y: (N, 12); jacobian: (N, 12, 84); poses: the model's tool poses g_i(q), per chain.
    """

    y: np.ndarray = field(repr=False)
    jacobian: np.ndarray = field(repr=False)
    poses: tuple[tuple[pin.SE3, ...], ...] = field(repr=False)
    parameter_names: tuple[str, ...]

    def at_tool_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(y, jacobian) with each chain's rows re-expressed at its tool point: [dp; w], the tool
        origin's displacement (m) and the rotation (rad), both on {B}'s axes.

        A linear, invertible change of rows per pose, so the least-squares problem keeps its
        solutions; but the tracker's position and orientation noise are isotropic in these rows,
        unlike in eq. (18)'s, whose linear part carries the rotation noise times the lever arm
        from {B}'s origin. Diagonal weights 1/sigma are therefore the right whitening here.
        """
        y = self.y.copy()
        jacobian = self.jacobian.copy()
        for c, poses in enumerate(self.poses):
            rows = slice(_TWIST * c, _TWIST * c + 3)
            spin = slice(_TWIST * c + 3, _TWIST * (c + 1))
            p = np.array([g.translation for g in poses])
            y[:, rows] += np.cross(y[:, spin], p)  # v + w x p: velocity of the tool point
            jacobian[:, rows, :] += np.cross(jacobian[:, spin, :], p[:, :, None], axis=1)
        return y, jacobian


def two_chain_error_model(
    model: pin.Model, chains: Sequence[PaperChain], configurations: np.ndarray, measured: Sequence[Sequence[pin.SE3]]
) -> TwoChainErrorModel:
    """The stacked error model of `model` at configurations (N, nq) against each chain's
    measured tool poses (`measured[i]`, N SE3 in {B}). See `TwoChainErrorModel`."""
    n_poses = configurations.shape[0]
    n_total = sum(c.n_parameters for c in chains)
    y = np.empty((n_poses, _TWIST * len(chains)))
    jacobian = np.zeros((n_poses, _TWIST * len(chains), n_total))
    poses_per_chain = []
    column = 0
    for c, (chain, targets) in enumerate(zip(chains, measured)):
        poses, J = forward_and_error_jacobians(chain.serial, model, chain.coordinates(configurations))
        rows = slice(_TWIST * c, _TWIST * (c + 1))
        y[:, rows] = [pin.log6(target * g.inverse()).vector for target, g in zip(targets, poses)]
        jacobian[:, rows, column : column + chain.n_parameters] = J
        column += chain.n_parameters
        poses_per_chain.append(tuple(poses))
    names = tuple(name for chain in chains for name in chain.serial.parameter_names())
    return TwoChainErrorModel(y, jacobian, tuple(poses_per_chain), names)


def _row_weights(noise: TrackerNoise, n_chains: int) -> np.ndarray:
    return np.tile(np.r_[np.full(3, 1.0 / noise.position), np.full(3, 1.0 / noise.rotation)], n_chains)


@dataclass(frozen=True)
class Identifiability:
    """How many combinations of the two chains' placement errors the data determine.

    n_parameters: 84 = 2 chains x 7 placements x 6.
    rank_per_chain: numerical rank of each chain's stacked J_i (eq. 31 for one chain).
    rank_stacked: rank of the stacked model, blockdiag(J_1, J_2); the sum of the two.
    rank_literal_eq21: rank of eq. (21) as printed, [J_1, J_2] against one error, for comparison.
    paper_bound: 4r + 2p + 6 = 34, the paper's count for the whole machine.
    base: the base parameters of the stacked model (pivoted QR of the weighted Jacobian).

    What is counted: independent combinations of each chain's 7 placement errors that change
    its end pose at the readings given, i.e. on the configurations the machine reaches.

    Why 24 per chain and not 4r + 2p + 6 = 28 (5 revolute joints, 1 prismatic): on the machine
    each parallelogram's crank and coupling joint move at coupled angles (q_pa = alpha - q on
    the nominal machine), so the data see the knee (or foot) in circular translation, a
    one-DoF motion that the rank shows to carry 6 identifiable parameters where two independent
    revolute joints carry 8. Per chain: slider 2 + parallelograms 6 + 6 + platform hinge 4 + end pose 6 = 24.
    Anything that breaks the coupling in the readings (encoder noise, a real machine's
    parallelogram errors) brings the count back to 28, the extra 4 weakly.

    Why 48 and not the paper's 34: 34 = 4 * 6 + 2 * 2 + 6 counts the machine once, as a
    non-over-constrained parallel mechanism with six equivalent revolute and two prismatic
    joints. The stacked model is two serial chains whose ends are not tied together, so each
    carries its own end-pose 6: 2 * (4 * 3 + 2 * 1 + 6) = 40 = 34 + 6 for the paper's rigid
    chains. Each of the four parallelograms adds 2 over the revolute joint the paper counts:
    40 + 8 = 48. Eq. (21) as printed shares one 6-row error between the chains and has 37
    independent columns here, but they are sums of the two chains' errors, not either chain's.
    """

    n_parameters: int
    rank_per_chain: Mapping[str, int]
    rank_stacked: int
    rank_literal_eq21: int
    paper_bound: int
    base: BaseParameters


def _numerical_rank(matrix: np.ndarray, rank_tolerance: float) -> int:
    """Rank of the column-normalised matrix (the same scaling as `select_base_parameters`)."""
    norms = np.linalg.norm(matrix, axis=0)
    keep = norms > rank_tolerance * norms.max()
    singular = np.linalg.svd(matrix[:, keep] / norms[keep], compute_uv=False)
    return int(np.count_nonzero(singular > rank_tolerance * singular[0]))


@on_one_blas_thread
def two_chain_identifiability(
    mechanism: Mechanism,
    readings: ArrayLike | Mapping[str, ArrayLike],
    *,
    noise: TrackerNoise = TrackerNoise(),
    rank_tolerance: float = 1e-9,
    model: pin.Model | None = None,
) -> Identifiability:
    """Rank analysis of the stacked model at the given readings (N, nq) (measured poses do not
    enter the Jacobian). `model` defaults to the mechanism's (nominal) tree model."""
    model = mechanism.model if model is None else model
    chains = paper_chains(mechanism)
    q = _as_configurations(mechanism, readings)
    identity = tuple(pin.SE3.Identity() for _ in range(q.shape[0]))
    system = two_chain_error_model(model, chains, q, (identity, identity))
    _, jacobian = system.at_tool_points()
    weighted = jacobian * _row_weights(noise, len(chains))[None, :, None]
    base = select_base_parameters(weighted.reshape(-1, jacobian.shape[2]), system.parameter_names, rank_tolerance)
    ranks = {}
    column = 0
    for c, chain in enumerate(chains):
        block = weighted[:, _TWIST * c : _TWIST * (c + 1), column : column + chain.n_parameters]
        ranks[chain.name] = _numerical_rank(block.reshape(-1, chain.n_parameters), rank_tolerance)
        column += chain.n_parameters
    # Eq. (21) as printed: one 6-row error per pose explained by [J_1, J_2]. Row changes within a
    # pose do not change a rank, so WORLD rows do.
    literal = system.jacobian[:, :_TWIST, : chains[0].n_parameters]
    literal = np.concatenate([literal, system.jacobian[:, _TWIST:, chains[0].n_parameters :]], axis=2)
    return Identifiability(
        n_parameters=len(system.parameter_names),
        rank_per_chain=MappingProxyType(ranks),
        rank_stacked=base.rank,
        rank_literal_eq21=_numerical_rank(literal.reshape(-1, literal.shape[2]), rank_tolerance),
        paper_bound=PAPER_IDENTIFIABLE_BOUND,
        base=base,
    )
