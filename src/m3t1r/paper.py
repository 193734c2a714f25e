"""The calibration method of Zhang et al. (Symmetry 2020), reproduced faithfully as a baseline.

The paper calibrates the machine as two serial chains, B1 -> P and B3 -> P (its chains i = 1, 2),
each read by sensors on every joint, and measures the platform pose with a tracker:

- error model (section 3): per chain the local POE of eq. (6), every error lumped into the initial
  poses T(0) (eq. 11), y_i = log6(g_meas g_i(q)^-1) (eq. 18) = J_i x_i (eq. 19-20), WORLD rows;
- identification (section 5): the m-pose stack (eq. 31) solved by least squares (eq. 32), batch or
  recursively one pose at a time, iterated with T(0) <- T(0) exp6(X) (eq. 33) until ||X|| < tol;
- passive angles (section 4): the lower crank q_i3 of each chain computed from the other readings
  through |A1 A2| = a by the Newton recursion of eq. (30), to save two sensors;
- simulation (section 6): an "actual" chain with errors on T(0), twists and joint variables
  (eq. 34-37), 20 poses from the mechanism's numerical forward kinematics.

On this repository's machine (`shared/design/mechanism.md`) the paper's "equivalent" revolute
joints q_i2, q_i3 are parallelograms: chain B1 is (q11, q12, q12_pa, q13, q13_pa, q14, P_I), the
coupling joints q_i2_pa, q_i3_pa being read like every other joint of the chain. Chain B3 ends
at P_II, the second copy of the platform frame, welded to P_I by the platform closure.

Choices this module makes where the paper is silent or inconsistent (each argued where it is made):

1. Eq. (21) is implemented in the stacked form [y1; y2] = blockdiag(J1, J2) [x1; x2], not as
   written (A = [J1, J2], Y = y1 = y2), which adds both chains' predictions of one error
   (`two_chain_error_model`).
2. The J^-1 of eq. (29)-(30) is 1 x 2: it can only be a pseudo-inverse, and the recursion is
   then ill-posed (`estimate_lower_crank_angles`).
3. Rows are weighted at the tool point, where the tracker's position and orientation noise are
   isotropic (`calibrate_two_chains`).

What the simulations show (seeds and numbers in tests/test_paper.py):
- The paper's own study (`paper_study`), every joint read, no noise: the calibrated chains
  reproduce the actual chains to 1e-15 m and rad, twist and offset errors included. With a
  10 um / 20 urad tracker and 10 urad encoders, errors fall from millimetres to about 10 um
  and 20 urad, a 100-700x reduction (the paper claims at least 10x).
- The lower cranks from the paper's recursion are off by about 0.1 rad; the calibration then
  leaves millimetres and tens of milliradians. The platform weld recovers them exactly.
- On the closed-chain machine (`closed_chain_study`) the chain ending at the measured frame
  fits exactly, but only while every passive joint is read: predicting from the sliders needs
  the passive angles, and with the nominal model's the result is no better than the
  uncalibrated machine. The other chain cannot follow the measured frame at all.

Conventions: Pinocchio's, [linear; angular] twists, SI units (m, rad); WORLD is the base frame {B}.
Readings are full Pinocchio configurations (N, nq) of the mechanism's tree (or {joint: values});
only the entries of the joints that are read matter.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.closed_loop import ClosedLoopCalibration, calibrate_closed_loop, pose_errors
from m3t1r.calibration.identification import (
    BaseParameters,
    RecursiveLeastSquares,
    batch_least_squares,
    select_base_parameters,
)
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise
from m3t1r.calibration.simulation import simulate_study
from m3t1r.errors import (
    IdentificationError,
    InvalidInputError,
    KinematicsError,
    ModelFileError,
    NotConvergedError,
    PoorExcitationWarning,
)
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import ClosureSpec, Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver, rehomed
from m3t1r.model.poe import Placement, SerialChain, forward_and_error_jacobians, perturb, placement_of
from m3t1r.model.workspace import workspace_actuators

__all__ = [
    "EXACT_DATA_REL_TOL",
    "NOISY_READINGS_REL_TOL",
    "PAPER_IDENTIFIABLE_BOUND",
    "ChainErrors",
    "ClosedChainStudyResult",
    "CrankMethod",
    "Identifiability",
    "LowerCrankEstimate",
    "PaperCalibration",
    "PaperChain",
    "PaperStudyResult",
    "PassiveSource",
    "PresetErrorScale",
    "PresetErrors",
    "SensorNoise",
    "TwoChainErrorModel",
    "actual_chain_poses",
    "calibrate_two_chains",
    "closed_chain_study",
    "estimate_lower_crank_angles",
    "paper_chains",
    "paper_study",
    "preset_errors",
    "two_chain_error_model",
    "two_chain_identifiability",
]

#: The paper's bound on identifiable parameters of the whole machine, 4r + 2p + 6 with its six
#: equivalent revolute and two prismatic joints (section 3.2): 4 * 6 + 2 * 2 + 6.
PAPER_IDENTIFIABLE_BOUND = 34

#: How the lower-crank angles q_i3 are obtained (see `estimate_lower_crank_angles`).
CrankMethod = Literal["distance", "platform", "sliders"]
#: Where a study takes q_i3 from: read by a sensor, or estimated by a `CrankMethod`.
PassiveSource = Literal["sensor", "distance", "platform", "sliders"]
Solver = Literal["batch", "recursive"]
Unidentifiable = Literal["base", "minimum_norm"]

_TWIST = 6
_CHAIN_LENGTH = 7  # q_i1, q_i2, q_i2_pa, q_i3, q_i3_pa, q_i4, tool frame
# Re-selections of the base parameters at the converged model (see `calibrate_two_chains`).
_MAX_RESELECTIONS = 2
# A step this many times larger than the first one means the linearisation has lost the data.
_DIVERGENCE = 1e3

#: Rank threshold for exact data: keeps the combinations that only a non-nominal geometry reveals
#: (relative singular values 1e-7 to 1e-9, see `calibrate_two_chains`), so an exact model fits exactly.
EXACT_DATA_REL_TOL = 1e-9
#: Rank threshold for noisy joint readings: above the level (~1e-5 for 1e-5 rad encoders) at which
#: reading noise breaks the parallelogram coupling and makes noise-driven combinations "identifiable".
NOISY_READINGS_REL_TOL = 1e-4


# --------------------------------------------------------------------------------------------------
# The paper's two chains on the tree


@dataclass(frozen=True)
class PaperChain:
    """Chain i of the paper (B1 -> P or B3 -> P) as a serial chain of the mechanism's tree.

    Roles come from the position of each joint in the mechanism's `principal_chains` entry
    (slider, upper crank, its coupling joint, lower crank, its coupling joint, platform hinge,
    tool frame), never from joint names. The paper's q_i1..q_i4 are slider, upper_crank,
    lower_crank, platform_hinge. The foot A_i of section 4 is the origin of the lower coupling
    joint's frame: that joint's axis passes through it, so its position does not depend on the
    coupling angle.
    """

    name: str
    serial: SerialChain
    slider: str
    upper_crank: str
    upper_coupling: str
    lower_crank: str
    lower_coupling: str
    platform_hinge: str
    tool_frame: str

    @property
    def n_parameters(self) -> int:
        return self.serial.n_parameters

    def coordinates(self, configurations: np.ndarray) -> np.ndarray:
        """Chain coordinates (N, 6) (m for the slider, rad otherwise) from configurations (N, nq).

        One column per joint: a `Mechanism` only has one-DoF joints with nq = 1.
        """
        return configurations[:, list(self.serial.idx_q)]


def paper_chains(mechanism: Mechanism) -> tuple[PaperChain, PaperChain]:
    """The paper's chains i = 1, 2, in the order of `mechanism.principal_chains` (B1, B3).

    Raises ModelFileError when the description does not declare exactly two principal chains of
    six one-DoF joints and a tool frame, or when a listed chain is not the tree path from the base
    to its tool frame (the serial POE needs the listed joints to be exactly that path).
    """
    entries = mechanism.principal_chains
    where = mechanism.closures_path
    if len(entries) != 2:
        raise ModelFileError(where, f"principal_chains: the paper's method needs 2 chains, found {len(entries)}")
    chains = []
    for name, items in entries.items():
        if len(items) != _CHAIN_LENGTH:
            raise ModelFileError(where, f"principal_chains.{name}: expected 6 joints and a tool frame, got {items}")
        serial = SerialChain.from_model(mechanism.model, items[-1])
        if serial.joint_names != tuple(items[:-1]):
            raise ModelFileError(
                where, f"principal_chains.{name}: the tree path to '{items[-1]}' is {serial.joint_names}, "
                       f"not the listed {tuple(items[:-1])}")
        chains.append(PaperChain(name, serial, *items))
    return chains[0], chains[1]


def _as_configurations(mechanism: Mechanism, readings: ArrayLike | Mapping[str, ArrayLike]) -> np.ndarray:
    """Readings as configurations (N, nq): an array as is, or {joint: (N,)} over the home pose."""
    model = mechanism.model
    if isinstance(readings, Mapping):
        columns = {}
        for name, values in readings.items():
            if not model.existJointName(name):
                raise InvalidInputError(f"readings: no joint named '{name}' in the model")
            columns[name] = np.asarray(values, dtype=float).reshape(-1)
        sizes = {v.size for v in columns.values()}
        if len(sizes) != 1:
            raise InvalidInputError(f"readings: joints have different numbers of values {sorted(sizes)}")
        q = np.tile(mechanism.home, (sizes.pop(), 1))
        for name, values in columns.items():
            q[:, model.idx_qs[model.getJointId(name)]] = values
    else:
        q = np.array(readings, dtype=float)
        if q.ndim != 2 or q.shape[1] != model.nq:
            raise InvalidInputError(f"readings: expected configurations of shape (N, {model.nq}), got {q.shape}")
    if q.shape[0] < 1:
        raise InvalidInputError("readings: no pose")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"readings: non-finite value in row {int(np.flatnonzero(~np.isfinite(q).all(1))[0])}")
    return q


def _per_chain_poses(chains: Sequence[PaperChain], measured: Sequence[pin.SE3] | Mapping[str, Sequence[pin.SE3]],
                     n_poses: int) -> tuple[tuple[pin.SE3, ...], ...]:
    if isinstance(measured, Mapping):
        if set(measured) != {c.name for c in chains}:
            raise InvalidInputError(f"measured_poses: keys {sorted(measured)} are not the chains "
                                    f"{[c.name for c in chains]}")
        per_chain = [tuple(measured[c.name]) for c in chains]
    else:
        per_chain = [tuple(measured)] * len(chains)
    for chain, poses in zip(chains, per_chain):
        if len(poses) != n_poses:
            raise InvalidInputError(f"chain {chain.name}: {len(poses)} measured poses for {n_poses} readings")
        if not all(isinstance(g, pin.SE3) for g in poses):
            raise InvalidInputError(f"chain {chain.name}: measured poses must be pinocchio.SE3")
    return tuple(per_chain)


def _pose_differences(poses: Sequence[pin.SE3], references: Sequence[pin.SE3]) -> PoseErrors:
    """Position distance (m) and rotation angle of R_ref^T R (rad), pose by pose (the paper's Fig. 4)."""
    position = np.array([np.linalg.norm(g.translation - h.translation) for g, h in zip(poses, references)])
    rotation = np.array([np.linalg.norm(pin.log3(h.rotation.T @ g.rotation)) for g, h in zip(poses, references)])
    return PoseErrors(position, rotation)


# --------------------------------------------------------------------------------------------------
# Error model (section 3)


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


def two_chain_error_model(model: pin.Model, chains: Sequence[PaperChain], configurations: np.ndarray,
                          measured: Sequence[Sequence[pin.SE3]]) -> TwoChainErrorModel:
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
        jacobian[:, rows, column:column + chain.n_parameters] = J
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


def _numerical_rank(matrix: np.ndarray, rel_tol: float) -> int:
    """Rank of the column-normalised matrix (the same scaling as `select_base_parameters`)."""
    norms = np.linalg.norm(matrix, axis=0)
    keep = norms > rel_tol * norms.max()
    singular = np.linalg.svd(matrix[:, keep] / norms[keep], compute_uv=False)
    return int(np.count_nonzero(singular > rel_tol * singular[0]))


@on_one_blas_thread
def two_chain_identifiability(mechanism: Mechanism, readings: ArrayLike | Mapping[str, ArrayLike], *,
                              noise: TrackerNoise = TrackerNoise(), rel_tol: float = 1e-9,
                              model: pin.Model | None = None) -> Identifiability:
    """Rank analysis of the stacked model at the given readings (N, nq) (measured poses do not
    enter the Jacobian). `model` defaults to the mechanism's (nominal) tree model."""
    model = mechanism.model if model is None else model
    chains = paper_chains(mechanism)
    q = _as_configurations(mechanism, readings)
    identity = tuple(pin.SE3.Identity() for _ in range(q.shape[0]))
    system = two_chain_error_model(model, chains, q, (identity, identity))
    _, jacobian = system.at_tool_points()
    weighted = jacobian * _row_weights(noise, len(chains))[None, :, None]
    base = select_base_parameters(weighted.reshape(-1, jacobian.shape[2]), system.parameter_names, rel_tol)
    ranks = {}
    column = 0
    for c, chain in enumerate(chains):
        block = weighted[:, _TWIST * c:_TWIST * (c + 1), column:column + chain.n_parameters]
        ranks[chain.name] = _numerical_rank(block.reshape(-1, chain.n_parameters), rel_tol)
        column += chain.n_parameters
    # Eq. (21) as printed: one 6-row error per pose explained by [J_1, J_2]. Row changes within a
    # pose do not change a rank, so WORLD rows do.
    literal = system.jacobian[:, :_TWIST, :chains[0].n_parameters]
    literal = np.concatenate([literal, system.jacobian[:, _TWIST:, chains[0].n_parameters:]], axis=2)
    return Identifiability(
        n_parameters=len(system.parameter_names),
        rank_per_chain=MappingProxyType(ranks),
        rank_stacked=base.rank,
        rank_literal_eq21=_numerical_rank(literal.reshape(-1, literal.shape[2]), rel_tol),
        paper_bound=PAPER_IDENTIFIABLE_BOUND,
        base=base,
    )


# --------------------------------------------------------------------------------------------------
# Identification (section 5)


@dataclass(frozen=True)
class PaperCalibration:
    """Result of `calibrate_two_chains`.

    model: the tree model with both chains' initial poses updated, T_c(0) = T(0) exp6(dt) (eq. 33);
        every other placement (parallelogram bars, B2/B4 links, closure frames) is as given.
    deltas: accumulated dt = log6(T(0)^-1 T_c(0)) ([v; w], m and rad) per placement of both chains.
    base: the identifiable subset at the last (re-)selection; the estimated parameters unless
        unidentifiable="minimum_norm", which estimates all 84 and leaves the unobservable
        combinations at zero through the minimum-norm solution.
    step_norms: ||X|| of each iteration's update (m and rad mixed, as in the paper's test).
    converged: the last ||X|| fell below the tolerance.
    residual_before / residual_after: per chain, model against measured pose at the calibration
        readings: position distance (m) and rotation angle (rad), pose by pose.
    """

    model: pin.Model = field(repr=False)
    chains: tuple[PaperChain, PaperChain] = field(repr=False)
    deltas: Mapping[Placement, np.ndarray] = field(repr=False)
    base: BaseParameters = field(repr=False)
    solver: Solver
    unidentifiable: Unidentifiable
    iterations: int
    step_norms: tuple[float, ...]
    converged: bool
    residual_before: Mapping[str, PoseErrors] = field(repr=False)
    residual_after: Mapping[str, PoseErrors] = field(repr=False)

    def chain(self, name: str) -> PaperChain:
        for chain in self.chains:
            if chain.name == name:
                return chain
        raise InvalidInputError(f"no chain named '{name}' (chains: {[c.name for c in self.chains]})")

    def predict(self, chain_name: str, configurations: np.ndarray) -> tuple[pin.SE3, ...]:
        """Calibrated tool poses g_i(q) in {B} of chain `chain_name` at configurations (N, nq)."""
        chain = self.chain(chain_name)
        poses, _ = forward_and_error_jacobians(chain.serial, self.model,
                                               chain.coordinates(np.atleast_2d(configurations)))
        return tuple(poses)


def _solve_step(A: np.ndarray, y: np.ndarray, weights: np.ndarray, solver: Solver) -> np.ndarray:
    """One least-squares update X of eq. (32) from per-pose blocks A (N, 12, p), y (N, 12)."""
    if solver == "batch":
        return batch_least_squares(A.reshape(-1, A.shape[2]), y.reshape(-1), np.tile(weights, A.shape[0])).x
    rls = RecursiveLeastSquares(A.shape[2])
    for A_k, y_k in zip(A, y):  # one pose at a time (section 5)
        rls.update(A_k, y_k, weights)
    return rls.estimate


@on_one_blas_thread
def calibrate_two_chains(
    mechanism: Mechanism,
    readings: ArrayLike | Mapping[str, ArrayLike],
    measured_poses: Sequence[pin.SE3] | Mapping[str, Sequence[pin.SE3]],
    *,
    noise: TrackerNoise = TrackerNoise(),
    solver: Solver = "recursive",
    unidentifiable: Unidentifiable = "base",
    tolerance: float = 1e-12,
    max_iterations: int = 30,
    rel_tol: float = EXACT_DATA_REL_TOL,
    model: pin.Model | None = None,
) -> PaperCalibration:
    """Identify both chains' initial-pose errors by the paper's iterated least squares.

    readings: (N, nq) configurations (or {joint: (N,)}) holding every joint of both chains as
        read by its sensor (or estimated, see `estimate_lower_crank_angles`).
    measured_poses: the measured platform poses in {B} (N SE3), used as the target of both
        chains, each chain's tool frame being a copy of the platform frame; or {chain name: N SE3}
        when each chain has its own measured end pose (the paper's simulation, eq. 37).
    noise: tracker standard deviations; the rows are weighted 1/sigma at each tool point
        (`TwoChainErrorModel.at_tool_points`). Joint-reading noise is not modelled (as in the paper).
    solver: "batch" (eq. 32 by SVD) or "recursive" (one pose at a time, square-root RLS); both
        give the same update to rounding.
    unidentifiable: "base" estimates the identifiable subset chosen by pivoted QR of the weighted
        Jacobian at the starting model (the others stay at zero); "minimum_norm" estimates all
        84 with the minimum-norm least-squares step.
    tolerance: stop when ||X|| < tolerance (eq. 33's "until ||X|| approaches zero"), or when the
        step moves no modelled pose by more than `tolerance` (m or rad): along combinations that
        the data see only weakly, rounding alone moves X by eps / sigma_min, far above any useful
        parameter tolerance, while the poses have long converged.
    max_iterations: per stage (see below).
    rel_tol: rank threshold of `select_base_parameters`.
    model: the starting tree model (default: the mechanism's nominal one).

    Each iteration linearises at the current model: X = argmin ||W (A X - Y)|| (eq. 31-32) and
    T(0) <- T(0) exp6(X) per placement (eq. 33). The Jacobian of eq. (19) is exact only at
    y = 0, so the iteration converges linearly, at a rate of the order of the remaining pose
    error (1e-3 per iteration for millimetre errors), to a zero of the weighted normal equations.

    Base parameters are re-selected at the converged model and the iteration resumed while the
    rank grows (at most twice), as in `m3t1r.serial`. The nominal geometry is special: each
    parallelogram's two axes are exactly parallel, and the nominal machine reads them at exactly
    coupled angles, which hides 4 combinations per chain (`Identifiability`). On a model with
    tilted axes (the fitted one) they become visible at second order in the errors, with relative
    singular values 1e-7 to 1e-9; without them an exact fit stalls at about 1e-9 rad.
    Reading noise also breaks the coupling, at its own level (relative singular values ~1e-5 for
    1e-5 rad encoders): the same combinations then pass any threshold below that, and their
    estimates are driven by the noise, up to tenths of a metre or radian, while moving the poses
    the machine can reach only at second order. rel_tol=1e-4 leaves them out with the same
    held-out accuracy and physically sized placement errors (`NOISY_READINGS_REL_TOL`).

    Raises IdentificationError when there are fewer rows than estimated parameters or when the
    iteration diverges.
    """
    if solver not in ("batch", "recursive"):
        raise InvalidInputError(f"solver must be 'batch' or 'recursive', got {solver!r}")
    if unidentifiable not in ("base", "minimum_norm"):
        raise InvalidInputError(f"unidentifiable must be 'base' or 'minimum_norm', got {unidentifiable!r}")
    if not (tolerance > 0.0 and max_iterations >= 1):
        raise InvalidInputError(f"need tolerance > 0 and max_iterations >= 1, got {tolerance}, {max_iterations}")
    start = mechanism.model if model is None else model
    chains = paper_chains(mechanism)
    q = _as_configurations(mechanism, readings)
    measured = _per_chain_poses(chains, measured_poses, q.shape[0])
    weights = _row_weights(noise, len(chains))
    placements = tuple(p for chain in chains for p in chain.serial.placements())

    def linearised(model_now: pin.Model) -> tuple[TwoChainErrorModel, np.ndarray, np.ndarray]:
        system = two_chain_error_model(model_now, chains, q, measured)
        return (system, *system.at_tool_points())

    def select(A: np.ndarray, names: tuple[str, ...]) -> BaseParameters:
        return select_base_parameters((A * weights[None, :, None]).reshape(-1, A.shape[2]), names, rel_tol)

    def iterate(model_now: pin.Model, system: TwoChainErrorModel, y: np.ndarray, A: np.ndarray,
                base: BaseParameters) -> tuple[pin.Model, TwoChainErrorModel, np.ndarray, np.ndarray, bool]:
        """Eq. (32)-(33) until the stopping test; returns the last linearisation."""
        if y.size < base.rank:
            raise IdentificationError(f"{q.shape[0]} poses give {y.size} rows for {base.rank} identifiable parameters")
        columns = np.array(base.indices) if unidentifiable == "base" else np.arange(A.shape[2])
        for _ in range(max_iterations):
            step = np.zeros(A.shape[2])
            step[columns] = _solve_step(A[:, :, columns], y, weights, solver)
            norm = float(np.linalg.norm(step))
            pose_change = float(np.max(np.abs(A @ step)))
            step_norms.append(norm)
            if not math.isfinite(norm) or norm > _DIVERGENCE * max(step_norms[0], tolerance):
                raise IdentificationError(f"the iteration of eq. (33) diverges: ||X|| = {norm:.3e}")
            model_now = perturb(model_now, {p: step[_TWIST * k:_TWIST * (k + 1)] for k, p in enumerate(placements)})
            system, y, A = linearised(model_now)
            if norm < tolerance or pose_change < tolerance:
                return model_now, system, y, A, True
        return model_now, system, y, A, False

    step_norms: list[float] = []
    system, y, A = linearised(start)
    residual_before = {c.name: _pose_differences(p, m) for c, p, m in zip(chains, system.poses, measured)}
    base = select(A, system.parameter_names)
    current, system, y, A, converged = iterate(start, system, y, A, base)
    # Special nominal geometry can hide parameters; re-select at the estimate, but never beyond the
    # structural bound 4 r + 2 p + 6 per chain (section 3.2): columns past it are rounding noise.
    bound = sum(chain.serial.rank_bound() for chain in chains)
    for _ in range(_MAX_RESELECTIONS if unidentifiable == "base" and base.rank < bound else 0):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            candidate = select(A, system.parameter_names)
        if not converged or candidate.rank <= base.rank or candidate.rank > bound:
            break
        base = candidate
        current, system, y, A, converged = iterate(current, system, y, A, base)

    deltas = {p: pin.log6(placement_of(start, p).actInv(placement_of(current, p))).vector for p in placements}
    for value in deltas.values():
        value.flags.writeable = False
    residual_after = {c.name: _pose_differences(p, m) for c, p, m in zip(chains, system.poses, measured)}
    return PaperCalibration(
        model=current,
        chains=chains,
        deltas=MappingProxyType(deltas),
        base=base,
        solver=solver,
        unidentifiable=unidentifiable,
        iterations=len(step_norms),
        step_norms=tuple(step_norms),
        converged=converged,
        residual_before=MappingProxyType(residual_before),
        residual_after=MappingProxyType(residual_after),
    )


# --------------------------------------------------------------------------------------------------
# Passive angles (section 4)


@dataclass(frozen=True)
class LowerCrankEstimate:
    """Estimated lower-crank angles q_i3 of both chains.

    joints: the two lower cranks (q13, q23), by identity from `paper_chains`.
    angles: (N, 2) rad, in `joints` order.
    method: see `estimate_lower_crank_angles`.
    iterations: (N,) Newton iterations per pose.
    residual: (N,) final constraint residual: | a - |A1 A2| | (m) for "distance", the largest
        platform-weld row (m or rad) for "platform", the largest closure row for "sliders".
    """

    joints: tuple[str, str]
    angles: np.ndarray
    method: CrankMethod
    iterations: np.ndarray
    residual: np.ndarray
    idx_q: tuple[int, int] = field(repr=False)

    def apply(self, configurations: np.ndarray) -> np.ndarray:
        """A copy of configurations (N, nq) with the lower cranks replaced by the estimate."""
        out = np.array(configurations, dtype=float)
        out[:, list(self.idx_q)] = self.angles
        return out


def _joint_index(model: pin.Model, name: str) -> tuple[int, int]:
    """(idx_q, idx_v) of a one-DoF joint."""
    j = model.getJointId(name)
    return model.idx_qs[j], model.idx_vs[j]


def _platform_weld(mechanism: Mechanism, chains: Sequence[PaperChain]) -> tuple[ClosureSpec, slice]:
    """The 6D closure between the two chains' tool frames and its slice of the enforced rows."""
    tools = {chain.tool_frame for chain in chains}
    offset = 0
    for spec in mechanism.closures:
        if spec.type == "6D" and {spec.frame_a, spec.frame_b} == tools:
            return spec, slice(offset, offset + len(spec.rows))
        offset += len(spec.rows)
    raise ModelFileError(mechanism.closures_path, f"no 6D closure welds the chains' tool frames {sorted(tools)}")


def _foot_distance_newton(model: pin.Model, data: pin.Data, q: np.ndarray, cranks: Sequence[tuple[int, int]],
                          feet: Sequence[int], distance: float, tolerance: float,
                          max_iterations: int) -> tuple[int, float]:
    """Eq. (25)-(30) on one configuration q (modified in place): q_3 <- q_3 + J^+ dd.

    J (1 x 2) = [-u . dP_1/dq_13, u . dP_2/dq_23] with u the unit vector A1 -> A2 and dP_i/dq_i3
    (eq. 28) the velocity of foot A_i per unit crank rate, i.e. the crank's column of the foot
    frame's LOCAL_WORLD_ALIGNED Jacobian. J^+ = J^T / (J J^T).
    """
    (q1, v1), (q2, v2) = cranks
    error = math.inf
    for iteration in range(max_iterations + 1):
        pin.computeJointJacobians(model, data, q)
        a1, a2 = data.oMi[feet[0]].translation, data.oMi[feet[1]].translation
        gap = a2 - a1
        length = float(np.linalg.norm(gap))
        error = distance - length  # dd of eq. (25)
        if abs(error) <= tolerance:
            return iteration, abs(error)
        if iteration == max_iterations:
            break
        u = gap / length
        dp1 = pin.getJointJacobian(model, data, feet[0], pin.LOCAL_WORLD_ALIGNED)[:3, v1]
        dp2 = pin.getJointJacobian(model, data, feet[1], pin.LOCAL_WORLD_ALIGNED)[:3, v2]
        row = np.array([-(u @ dp1), u @ dp2])
        q[[q1, q2]] += row * (error / (row @ row))
    raise NotConvergedError("the foot-distance recursion of eq. (30) did not converge", abs(error), max_iterations)


def _platform_newton(solver: ClosedLoopSolver, rows: slice, q: np.ndarray, cranks: Sequence[tuple[int, int]],
                     tolerance: float, max_iterations: int) -> tuple[int, float]:
    """Gauss-Newton on the platform weld P_I = P_II (its enforced rows) over the two cranks."""
    columns = [v for _, v in cranks]
    indices = [i for i, _ in cranks]
    residual = np.full(1, math.inf)
    for iteration in range(max_iterations + 1):
        full, jacobian, _ = solver.closure_sensitivity(q)
        residual = full[rows]
        step = np.linalg.lstsq(jacobian[rows][:, columns], residual, rcond=None)[0]
        q[indices] -= step
        if float(np.max(np.abs(step))) <= tolerance:
            return iteration + 1, float(np.max(np.abs(solver.closure_residual(q)[rows])))
    raise NotConvergedError("the platform-weld Gauss-Newton did not converge", float(np.max(np.abs(residual))),
                            max_iterations)


@on_one_blas_thread
def estimate_lower_crank_angles(
    mechanism: Mechanism,
    readings: ArrayLike | Mapping[str, ArrayLike],
    *,
    method: CrankMethod = "distance",
    model: pin.Model | None = None,
    initial: ArrayLike | None = None,
    foot_distance: float | None = None,
    tolerance: float = 1e-13,
    max_iterations: int = 50,
) -> LowerCrankEstimate:
    """Compute the lower-crank angles q_13, q_23 (the paper's q_i3) instead of reading them.

    method:
    - "distance", the paper's section 4: the feet A_1, A_2 (eq. 22-24, from every other reading
      and the chain model) must be `foot_distance` = a apart (eq. 25-26); Newton's recursion
      q <- q + J^-1 dd (eq. 29-30) from `initial`. This is one equation in two unknowns, so J is
      1 x 2 and its "inverse" can only be the pseudo-inverse J^T / (J J^T), the minimum-norm
      update. The recursion then converges to *a* point of the solution curve {|A1 A2| = a},
      to first order the one nearest to the initial guess, not to the true angles: the component
      of the initial error along the curve survives. On this machine the curve's tangent is both
      cranks turning the same way: the feet shift sideways together and one rises as the other
      drops, which leaves |A1 A2| unchanged to first order. So that part of the platform's x and
      z comes from the initial guess, not from the readings. The missing information is in the
      other rows of the platform closure: the feet must stay at the same height.
    - "platform", well posed from the same readings: Gauss-Newton on the platform weld
      P_I(q_13) = P_II(q_23) over its enforced rows (x, y, z, yaw; four equations in two
      unknowns). Exact on a machine that matches `model`.
    - "sliders", the full closure solve: the closed-loop forward kinematics of `mechanism` at
      the slider readings gives every passive joint (`model` is not used). Needs no passive
      reading at all, but only as good as the mechanism model's closures: on a real machine
      described by its nominal model it inherits the nominal geometry's errors.

    In this machine's chains the lower crank's coupling joint q_i3_pa is read too, and the
    parallelogram makes q_i3 = beta - q_i3_pa on the nominal machine; the paper's chain has no
    such joint, and "distance" does not use it (A_i lies on its axis).

    readings: (N, nq) configurations (or {joint: (N,)}); the lower-crank entries are ignored.
    model: chain model for "distance" and "platform" (default: the mechanism's).
    initial: (2,) or (N, 2) starting angles (rad) for "distance" and "platform"; default: the
        lower cranks of `mechanism.home`.
    foot_distance: a (m); default |A_1 A_2| of the mechanism model at its home.
    tolerance: "distance" stops when |dd| <= tolerance (m), "platform" when the step is
        <= tolerance (rad): its four rows need not vanish on a machine that differs from `model`.
    Raises NotConvergedError (or, for "sliders", the closed-loop solver's KinematicsError).
    """
    if method not in ("distance", "platform", "sliders"):
        raise InvalidInputError(f"method must be 'distance', 'platform' or 'sliders', got {method!r}")
    chains = paper_chains(mechanism)
    model = mechanism.model if model is None else model
    q_all = _as_configurations(mechanism, readings)
    n_poses = q_all.shape[0]
    joints = (chains[0].lower_crank, chains[1].lower_crank)
    cranks = [_joint_index(model, name) for name in joints]
    idx_q = (cranks[0][0], cranks[1][0])
    start = mechanism.home[list(idx_q)] if initial is None else np.asarray(initial, dtype=float)
    start = np.broadcast_to(start, (n_poses, 2)) if start.shape in ((2,), (1, 2), (n_poses, 2)) else None
    if start is None or not np.all(np.isfinite(start)):
        raise InvalidInputError(f"initial: expected 2 or ({n_poses}, 2) finite angles")
    angles = np.empty((n_poses, 2))
    iterations = np.zeros(n_poses, dtype=int)
    residual = np.empty(n_poses)
    if method == "distance":
        data = model.createData()
        feet = [model.getJointId(chain.lower_coupling) for chain in chains]
        if foot_distance is None:
            pin.forwardKinematics(model, data, mechanism.home)
            foot_distance = float(np.linalg.norm(data.oMi[feet[1]].translation - data.oMi[feet[0]].translation))
        for k in range(n_poses):
            q = q_all[k].copy()
            q[list(idx_q)] = start[k]
            iterations[k], residual[k] = _foot_distance_newton(model, data, q, cranks, feet, foot_distance,
                                                               tolerance, max_iterations)
            angles[k] = q[list(idx_q)]
    elif method == "platform":
        _, rows = _platform_weld(mechanism, chains)
        solver = ClosedLoopSolver(mechanism.with_model(model))
        for k in range(n_poses):
            q = q_all[k].copy()
            q[list(idx_q)] = start[k]
            iterations[k], residual[k] = _platform_newton(solver, rows, q, cranks, tolerance, max_iterations)
            angles[k] = q[list(idx_q)]
    else:
        solver = ClosedLoopSolver(mechanism)
        for k in range(n_poses):
            result = solver.forward(q_all[k, mechanism.actuated_ids], q_init=mechanism.home)
            angles[k] = result.q[list(idx_q)]
            iterations[k], residual[k] = result.iterations, result.residual
    return LowerCrankEstimate(joints, angles, method, iterations, residual, idx_q)


# --------------------------------------------------------------------------------------------------
# Simulation (section 6)


@dataclass(frozen=True)
class PresetErrorScale:
    """Standard deviations of the preset errors of Table 1 (the paper's table is missing; these
    are the orders its text implies: millimetres and milliradians on metre-size links).

    placement_position (m) and placement_rotation (rad): dt = [v; w] on every T(0) (eq. 34).
    twist: ds on every joint twist (dimensionless), before orthonormalisation (eq. 35).
    joint_offset: dq on every joint variable (m for the slider, rad otherwise) (eq. 36).
    """

    placement_position: float = 1e-3
    placement_rotation: float = 1e-3
    twist: float = 1e-3
    joint_offset: float = 1e-3


@dataclass(frozen=True)
class PresetErrors:
    """The actual chains' errors (Table 1 of the paper), keyed by placement or joint name.

    placement: dt (6,) per placement of both chains (T^a(0) = T(0) exp6(dt), eq. 34).
    twist: the actual twist s^a (6,) per joint, in the joint's frame (eq. 35), orthonormalised:
        revolute |w| = 1 and w . v = 0 (a pure rotation about a displaced, tilted axis);
        prismatic |v| = 1 and w = 0.
    twist_error: ds = s^a - s per joint.
    joint_offset: dq per joint (q^a = q + dq, eq. 36).
    """

    placement: Mapping[Placement, np.ndarray]
    twist: Mapping[str, np.ndarray]
    twist_error: Mapping[str, np.ndarray]
    joint_offset: Mapping[str, float]
    scale: PresetErrorScale

    def rows(self) -> tuple[tuple[str, str, tuple[float, ...]], ...]:
        """Table 1 as rows (name, quantity, values): 'dt' per placement, 'ds' and 'dq' per joint."""
        out: list[tuple[str, str, tuple[float, ...]]] = []
        for placement, dt in self.placement.items():
            out.append((placement.name, "dt", tuple(float(v) for v in dt)))
        for name, ds in self.twist_error.items():
            out.append((name, "ds", tuple(float(v) for v in ds)))
        for name, dq in self.joint_offset.items():
            out.append((name, "dq", (float(dq),)))
        return tuple(out)


def _orthonormal_twist(twist: np.ndarray, error: np.ndarray) -> np.ndarray:
    """s + ds projected back onto one-DoF joint twists of the same kind (section 6)."""
    v, w = twist[:3] + error[:3], twist[3:] + error[3:]
    if np.linalg.norm(twist[3:]) == 0.0:  # prismatic: a unit direction, no rotation
        return np.r_[v / np.linalg.norm(v), np.zeros(3)]
    w = w / np.linalg.norm(w)
    return np.r_[v - (w @ v) * w, w]  # zero pitch: a pure rotation


def preset_errors(chains: Sequence[PaperChain], rng: np.random.Generator,
                  scale: PresetErrorScale = PresetErrorScale()) -> PresetErrors:
    """Draw Table 1: Gaussian dt, ds, dq with the standard deviations of `scale`."""
    placement: dict[Placement, np.ndarray] = {}
    twist: dict[str, np.ndarray] = {}
    twist_error: dict[str, np.ndarray] = {}
    offset: dict[str, float] = {}
    sigma = np.r_[np.full(3, scale.placement_position), np.full(3, scale.placement_rotation)]
    for chain in chains:
        for p in chain.serial.placements():
            placement[p] = rng.normal(0.0, 1.0, _TWIST) * sigma
        for name, s in zip(chain.serial.joint_names, chain.serial.twists):
            actual = _orthonormal_twist(s, rng.normal(0.0, scale.twist, _TWIST))
            twist[name], twist_error[name] = actual, actual - s
            offset[name] = float(rng.normal(0.0, scale.joint_offset))
    for value in (*placement.values(), *twist.values(), *twist_error.values()):
        value.flags.writeable = False
    return PresetErrors(MappingProxyType(placement), MappingProxyType(twist), MappingProxyType(twist_error),
                        MappingProxyType(offset), scale)


def actual_chain_poses(chain: PaperChain, model: pin.Model, preset: PresetErrors,
                       configurations: np.ndarray) -> tuple[pin.SE3, ...]:
    """Tool poses of the actual chain i (eq. 37) at the true joint values of configurations (N, nq):

        g_i = T^a_B,1(0) exp(s^a_1 q^a_1) T^a_1,2(0) ... exp(s^a_n q^a_n) T^a_n,P(0)

    with T^a(0) = T(0) exp6(dt) (eq. 34), s^a (eq. 35) and q^a = q + dq (eq. 36).

    Why the paper's model, with errors on the initial poses only, can represent this chain
    exactly: an orthonormal twist s^a of the same kind as s is s moved by a constant rigid
    transform C (s^a = Ad_C s: the axis tilted and displaced), so exp(s^a q) = C exp(s q) C^-1
    and C, C^-1 merge into the neighbouring initial poses. An offset is a motion along the
    joint's own twist, exp(s (q + dq)) = exp(s dq) exp(s q), and exp(s dq) merges into the
    preceding initial pose. Neither needs a parameter of its own (section 3.1, eq. 11).
    """
    initial = chain.serial.initial_poses(model)
    actual = [T * pin.exp6(preset.placement[p]) for T, p in zip(initial, chain.serial.placements())]
    twists = [preset.twist[name] for name in chain.serial.joint_names]
    offsets = np.array([preset.joint_offset[name] for name in chain.serial.joint_names])
    poses = []
    for q in chain.coordinates(configurations) + offsets:
        g = pin.SE3.Identity()
        for T, s, value in zip(actual, twists, q):
            g = g * T * pin.exp6(s * value)
        poses.append(g * actual[-1])
    return tuple(poses)


@dataclass(frozen=True)
class SensorNoise:
    """Noise of a calibration experiment with passive-joint sensors: the tracker and slider
    encoders (`TrackerNoise`: m, rad, m) plus rotary encoders on the passive joints (rad)."""

    tracker: TrackerNoise = TrackerNoise()
    encoder: float = 1e-5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.encoder) and self.encoder >= 0.0):
            raise InvalidInputError(f"encoder noise must be finite and >= 0, got {self.encoder}")


def _read(mechanism: Mechanism, chains: Sequence[PaperChain], configurations: np.ndarray,
          noise: SensorNoise | None, rng: np.random.Generator) -> np.ndarray:
    """What the sensors of both chains read: sliders with the slider noise, every other chain
    joint with the encoder noise."""
    readings = configurations.copy()
    if noise is None:
        return readings
    actuated = set(mechanism.actuated_joints)
    for chain in chains:
        for name, index in zip(chain.serial.joint_names, chain.serial.idx_q):
            sigma = noise.tracker.actuator if name in actuated else noise.encoder
            readings[:, index] += rng.normal(0.0, sigma, readings.shape[0])
    return readings


def _observe(poses: Sequence[pin.SE3], noise: SensorNoise | None, rng: np.random.Generator) -> tuple[pin.SE3, ...]:
    """Tracker measurements: position noise in {B}, rotation noise right-multiplied (m, rad)."""
    if noise is None:
        return tuple(poses)
    tracker = noise.tracker
    return tuple(pin.SE3(g.rotation @ pin.exp3(rng.normal(0.0, tracker.rotation, 3)),
                         g.translation + rng.normal(0.0, tracker.position, 3)) for g in poses)


def _with_passive(mechanism: Mechanism, readings: np.ndarray, source: PassiveSource,
                  model: pin.Model) -> tuple[np.ndarray, LowerCrankEstimate | None]:
    if source == "sensor":
        return readings, None
    if source not in ("distance", "platform", "sliders"):
        raise InvalidInputError(f"passive_from must be 'sensor', 'distance', 'platform' or 'sliders', got {source!r}")
    estimate = estimate_lower_crank_angles(mechanism, readings, method=source, model=model)
    return estimate.apply(readings), estimate


def _chain_poses(chain: PaperChain, model: pin.Model, configurations: np.ndarray) -> tuple[pin.SE3, ...]:
    return tuple(forward_and_error_jacobians(chain.serial, model, chain.coordinates(configurations))[0])


@dataclass(frozen=True)
class ChainErrors:
    """Pose errors of one chain's model against the truth, before and after calibration
    (after is None when the calibration failed)."""

    before: PoseErrors
    after: PoseErrors | None

    @property
    def reduction(self) -> tuple[float, float]:
        """(position, orientation) ratio of mean errors before / after (nan without `after`)."""
        if self.after is None:
            return math.nan, math.nan
        return (self.before.position_mean / self.after.position_mean,
                self.before.rotation_mean / self.after.rotation_mean)


@dataclass(frozen=True)
class PaperStudyResult:
    """The paper's simulation (section 6) on the two chains, and its Fig. 4.

    calibration_poses / holdout_poses: per chain, model pose against the actual chain's pose
    (eq. 37), before (nominal model) and after calibration. Calibration poses are evaluated at
    the readings the calibration used (noisy when `noise` is set); held-out poses at exact
    readings, so that they measure the identified model rather than the sensors. When
    passive_from is not "sensor", the lower cranks are estimated at both (with the nominal model).
    crank_error: (N, 2) estimated minus true q_13, q_23 (rad) on the calibration then held-out
        poses, None when read.
    calibration is None, and failure says why, when the identification raised IdentificationError
    (e.g. eq. 33 diverging on data no initial-pose error explains). With cranks from the paper's
    recursion it does not raise on the seeds tried, but it does not converge either
    (`PaperCalibration.converged`): the estimated angles are about 0.1 rad off.
    """

    seed: int
    noise: SensorNoise | None
    passive_from: PassiveSource
    preset: PresetErrors = field(repr=False)
    calibration: PaperCalibration | None = field(repr=False)
    failure: str | None
    identifiability: Identifiability = field(repr=False)
    calibration_poses: Mapping[str, ChainErrors] = field(repr=False)
    holdout_poses: Mapping[str, ChainErrors] = field(repr=False)
    crank_error: np.ndarray | None = field(repr=False)


def _paper_chain_errors(chains: Sequence[PaperChain], before: pin.Model, after: pin.Model | None,
                        configurations: np.ndarray, truth: Sequence[Sequence[pin.SE3]]) -> dict[str, ChainErrors]:
    def errors(model: pin.Model, chain: PaperChain, reference: Sequence[pin.SE3]) -> PoseErrors:
        return _pose_differences(_chain_poses(chain, model, configurations), reference)

    return {chain.name: ChainErrors(errors(before, chain, reference),
                                    None if after is None else errors(after, chain, reference))
            for chain, reference in zip(chains, truth)}


@on_one_blas_thread
def paper_study(
    seed: int = 0,
    *,
    noise: SensorNoise | None = None,
    passive_from: PassiveSource = "sensor",
    n_poses: int = 20,
    n_holdout: int = 50,
    scale: PresetErrorScale = PresetErrorScale(),
    solver: Solver = "recursive",
    rel_tol: float | None = None,
    mechanism: Mechanism | None = None,
) -> PaperStudyResult:
    """The paper's simulation, step by step (section 6):

    1. n_poses + n_holdout slider sets drawn in the workspace; the nominal mechanism's closed-loop
       forward kinematics gives every joint value (the paper's "numerical forward kinematics");
    2. Table 1 errors dt, ds, dq drawn with `scale` (`preset_errors`);
    3-5. each chain's measured pose is its own actual chain's pose at those joint values
       (eq. 34-37). The two actual chains have independent errors, so their end poses differ:
       the paper's simulation does not close the loop, and neither does this one (see
       `closed_chain_study` for a machine that does);
    6. `calibrate_two_chains` with the local POE model (initial-pose errors only).

    With noise, the tracker perturbs the measured poses and the sensors the readings. With
    passive_from other than "sensor", q_13 and q_23 are estimated from the other readings with
    the nominal model instead of read. The first n_poses calibrate, the rest are held out.
    solver and rel_tol are passed to `calibrate_two_chains`; rel_tol defaults to
    `EXACT_DATA_REL_TOL` without noise and `NOISY_READINGS_REL_TOL` with it.
    """
    if n_poses < 1 or n_holdout < 1:
        raise InvalidInputError(f"need n_poses >= 1 and n_holdout >= 1, got {n_poses}, {n_holdout}")
    nominal = Mechanism.load() if mechanism is None else mechanism
    rng = np.random.default_rng(seed)
    chains = paper_chains(nominal)
    actuators = workspace_actuators(nominal, n_poses + n_holdout, rng)
    solver_fk = ClosedLoopSolver(nominal)
    q_true = np.array([solver_fk.forward(a, q_init=nominal.home).q for a in actuators])
    preset = preset_errors(chains, rng, scale)
    truth = [actual_chain_poses(chain, nominal.model, preset, q_true) for chain in chains]

    fit, held = slice(0, n_poses), slice(n_poses, None)
    readings = _read(nominal, chains, q_true[fit], noise, rng)
    readings, fit_estimate = _with_passive(nominal, readings, passive_from, nominal.model)
    measured = {chain.name: _observe(poses[fit], noise, rng) for chain, poses in zip(chains, truth)}
    tracker = noise.tracker if noise is not None else TrackerNoise()
    if rel_tol is None:
        rel_tol = EXACT_DATA_REL_TOL if noise is None else NOISY_READINGS_REL_TOL
    calibration: PaperCalibration | None = None
    failure = None
    try:
        calibration = calibrate_two_chains(nominal, readings, measured, noise=tracker, solver=solver, rel_tol=rel_tol)
    except IdentificationError as exc:
        failure = str(exc)
    calibrated = None if calibration is None else calibration.model
    identifiability = two_chain_identifiability(nominal, readings, noise=tracker, rel_tol=rel_tol)

    holdout, held_estimate = _with_passive(nominal, q_true[held], passive_from, nominal.model)
    crank_error = None
    if fit_estimate is not None and held_estimate is not None:
        true_angles = q_true[:, list(fit_estimate.idx_q)]
        crank_error = np.vstack([fit_estimate.angles, held_estimate.angles]) - true_angles
    return PaperStudyResult(
        seed=seed,
        noise=noise,
        passive_from=passive_from,
        preset=preset,
        calibration=calibration,
        failure=failure,
        identifiability=identifiability,
        calibration_poses=MappingProxyType(_paper_chain_errors(
            chains, nominal.model, calibrated, readings, [poses[fit] for poses in truth])),
        holdout_poses=MappingProxyType(_paper_chain_errors(
            chains, nominal.model, calibrated, holdout, [poses[held] for poses in truth])),
        crank_error=crank_error,
    )


@dataclass(frozen=True)
class ClosedChainStudyResult:
    """The paper's method on the full closed-chain machine, judged on held-out slider sets.

    Truth: a `simulate_study` machine (errors on every joint placement, the parallelogram bars,
    the B2/B4 links and the closure frames). Every pose error is against the truth's measured
    platform frame P_I at the same slider values.

    nominal: the uncalibrated nominal machine (closed-loop FK at the sliders).
    sensors_before / sensors_after: chain B1 with the truth's passive readings given (a machine
        with sensors on every passive joint), nominal then calibrated chain model.
    second_chain_before / second_chain_after: the same for chain B3 (its tool P_II fitted to
        P_I's measured pose).
    sliders_only: the calibrated chain B1 at the passive angles the nominal closed-loop model
        computes from the sliders: what the paper's model predicts without passive sensors.
    calibrated_tree: chain B1's calibrated placements written into the tree, every other part
        nominal, closed-loop FK at the sliders (None if it does not assemble).
    both_chains_assemble: whether the tree with *both* chains' calibrated placements assembles
        at the nominal home's sliders; chain B3's placements are fitted to a frame its own end
        does not follow (see `closed_chain_study`).
    closed_loop: held-out errors of `calibrate_closed_loop` on the same sliders and measured
        poses, closed_loop_calibration its result (both None if skipped).
    crank_error: {method: (M, 2) estimated minus true q_13, q_23 (rad) at the held-out poses},
        "distance" and "platform" from the truth's other readings with the nominal chain model,
        "sliders" from the nominal closed-loop model.
    """

    seed: int
    noise: SensorNoise | None
    calibration: PaperCalibration = field(repr=False)
    nominal: PoseErrors = field(repr=False)
    sensors_before: PoseErrors = field(repr=False)
    sensors_after: PoseErrors = field(repr=False)
    second_chain_before: PoseErrors = field(repr=False)
    second_chain_after: PoseErrors = field(repr=False)
    sliders_only: PoseErrors = field(repr=False)
    calibrated_tree: PoseErrors | None = field(repr=False)
    both_chains_assemble: bool
    closed_loop: PoseErrors | None = field(repr=False)
    closed_loop_calibration: ClosedLoopCalibration | None = field(repr=False)
    crank_error: Mapping[str, np.ndarray] = field(repr=False)


@on_one_blas_thread
def closed_chain_study(
    seed: int = 0,
    *,
    noise: SensorNoise | None = None,
    n_poses: int = 20,
    n_holdout: int = 50,
    sigma_position: float = 1e-3,
    sigma_rotation: float = 1e-3,
    compare_closed_loop: bool = True,
    rel_tol: float | None = None,
    mechanism: Mechanism | None = None,
) -> ClosedChainStudyResult:
    """Calibrate the paper's two chains on a simulated closed-chain machine and judge the result
    on held-out slider sets, against the closed-loop calibration of the same data.

    Data per calibration pose: the slider readings, the readings of every joint of both chains
    (the truth's assembled configuration, plus noise), and the measured pose of the platform
    frame P_I (plus tracker noise), which is the target of both chains. Held-out poses use exact
    readings for every method.

    The paper's premise y_1 = y_2 (eq. 21) is a rigid platform that both chains end on. On a
    machine with errors the closure cannot hold in every direction: the truth keeps P_I and P_II
    together in position and yaw, and its roll and pitch differ by tens of milliradians, varying
    with the pose (the strain a real machine takes up in joint play and elasticity). Chain B1
    ends at the measured frame and fits it exactly; chain B3 cannot, and its undamped iteration
    can wander along weakly identifiable directions.
    rel_tol: as in `paper_study`.
    """
    nominal = Mechanism.load() if mechanism is None else mechanism
    chains = paper_chains(nominal)
    study = simulate_study(nominal, n_poses=n_poses, n_holdout=n_holdout, seed=seed,
                           sigma_position=sigma_position, sigma_rotation=sigma_rotation, noise=None)
    truth = study.truth
    rng = np.random.default_rng([seed, 1])  # the noise, independent of the machine's draw
    truth_solver = ClosedLoopSolver(truth)
    fit_forward = [truth_solver.forward(a, q_init=truth.home) for a in study.measurements.actuators]
    held_forward = [truth_solver.forward(a, q_init=truth.home) for a in study.holdout_actuators]
    q_fit = np.array([r.q for r in fit_forward])
    q_held = np.array([r.q for r in held_forward])
    held_truth = tuple(r.pose for r in held_forward)

    readings = _read(nominal, chains, q_fit, noise, rng)
    measured = _observe([r.pose for r in fit_forward], noise, rng)
    tracker = noise.tracker if noise is not None else TrackerNoise()
    if rel_tol is None:
        rel_tol = EXACT_DATA_REL_TOL if noise is None else NOISY_READINGS_REL_TOL
    calibration = calibrate_two_chains(nominal, readings, measured, noise=tracker, rel_tol=rel_tol)

    first, second = chains
    sensors_before = _pose_differences(_chain_poses(first, nominal.model, q_held), held_truth)
    sensors_after = _pose_differences(calibration.predict(first.name, q_held), held_truth)
    second_before = _pose_differences(_chain_poses(second, nominal.model, q_held), held_truth)
    second_after = _pose_differences(calibration.predict(second.name, q_held), held_truth)
    nominal_solver = ClosedLoopSolver(nominal)
    q_nominal = np.array([nominal_solver.forward(a, q_init=nominal.home).q for a in study.holdout_actuators])
    sliders_only = _pose_differences(calibration.predict(first.name, q_nominal), held_truth)
    calibrated_tree: PoseErrors | None = None
    try:
        own = {p: calibration.deltas[p] for p in first.serial.placements()}
        tree = rehomed(nominal.with_model(perturb(nominal.model, own)))
        calibrated_tree = pose_errors(truth, tree, study.holdout_actuators)
    except KinematicsError:
        pass
    try:
        rehomed(nominal.with_model(calibration.model))
        both_chains_assemble = True
    except KinematicsError:
        both_chains_assemble = False

    closed_loop = closed_loop_errors = None
    if compare_closed_loop:
        sliders = readings[:, nominal.actuated_ids]
        closed_loop = calibrate_closed_loop(nominal, PoseMeasurements(sliders, measured), tracker)
        closed_loop_errors = pose_errors(truth, closed_loop.mechanism, study.holdout_actuators)

    crank_error = {}
    for method in ("distance", "platform", "sliders"):
        estimate = estimate_lower_crank_angles(nominal, q_held, method=method)
        crank_error[method] = estimate.angles - q_held[:, list(estimate.idx_q)]
    return ClosedChainStudyResult(
        seed=seed,
        noise=noise,
        calibration=calibration,
        nominal=pose_errors(truth, nominal, study.holdout_actuators),
        sensors_before=sensors_before,
        sensors_after=sensors_after,
        second_chain_before=second_before,
        second_chain_after=second_after,
        sliders_only=sliders_only,
        calibrated_tree=calibrated_tree,
        both_chains_assemble=both_chains_assemble,
        closed_loop=closed_loop_errors,
        closed_loop_calibration=closed_loop,
        crank_error=MappingProxyType(crank_error),
    )
