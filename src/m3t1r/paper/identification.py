"""The paper's identification (section 5): the m-pose stack (eq. 31) solved by least squares
(eq. 32), batch or recursively one pose at a time, iterated with T(0) <- T(0) exp6(X) (eq. 33)
until ||X|| < tol.

Rows are weighted at the tool point, where the tracker's position and orientation noise are
isotropic (`calibrate_two_chains`).
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
from m3t1r.calibration.identification import (
    BaseParameters,
    RecursiveLeastSquares,
    batch_least_squares,
    select_base_parameters,
)
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.errors import IdentificationError, InvalidInputError, PoorExcitationWarning
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.poe import Placement, forward_and_error_jacobians, perturb, placement_of
from m3t1r.paper.chains import _TWIST, PaperChain, _as_configurations, _per_chain_poses, _pose_differences, paper_chains
from m3t1r.paper.error_model import TwoChainErrorModel, _row_weights, two_chain_error_model

__all__ = [
    "EXACT_DATA_REL_TOL",
    "NOISY_READINGS_REL_TOL",
    "PaperCalibration",
    "TwoChainOptions",
    "calibrate_two_chains",
]

Solver = Literal["batch", "recursive"]
Unidentifiable = Literal["base", "minimum_norm"]

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
        poses, _ = forward_and_error_jacobians(
            chain.serial, self.model, chain.coordinates(np.atleast_2d(configurations))
        )
        return tuple(poses)


@dataclass(frozen=True)
class TwoChainOptions:
    """Settings of `calibrate_two_chains`' iteration.

    solver: "batch" (eq. 32 by SVD) or "recursive" (one pose at a time, square-root RLS); both
        give the same update to rounding.
    unidentifiable: "base" estimates the identifiable subset chosen by pivoted QR of the weighted
        Jacobian at the starting model (the others stay at zero); "minimum_norm" estimates all
        84 with the minimum-norm least-squares step.
    tolerance: stop when ||X|| < tolerance (eq. 33's "until ||X|| approaches zero"), or when the
        step moves no modelled pose by more than `tolerance` (m or rad): along combinations that
        the data see only weakly, rounding alone moves X by eps / sigma_min, far above any useful
        parameter tolerance, while the poses have long converged.
    max_iterations: per stage (see `calibrate_two_chains`).
    rank_tolerance: rank threshold of `select_base_parameters`.
    """

    solver: Solver = "recursive"
    unidentifiable: Unidentifiable = "base"
    tolerance: float = 1e-12
    max_iterations: int = 30
    rank_tolerance: float = EXACT_DATA_REL_TOL


def _solve_step(A: np.ndarray, y: np.ndarray, weights: np.ndarray, solver: Solver) -> np.ndarray:
    """One least-squares update X of eq. (32) from per-pose blocks A (N, 12, p), y (N, 12)."""
    if solver == "batch":
        return batch_least_squares(A.reshape(-1, A.shape[2]), y.reshape(-1), np.tile(weights, A.shape[0])).x
    rls = RecursiveLeastSquares(A.shape[2])
    for A_k, y_k in zip(A, y):  # one pose at a time (section 5)
        rls.update(A_k, y_k, weights)
    return rls.estimate


def _check_options(solver: Solver, unidentifiable: Unidentifiable, tolerance: float, max_iterations: int) -> None:
    if solver not in ("batch", "recursive"):
        raise InvalidInputError(f"solver must be 'batch' or 'recursive', got {solver!r}")
    if unidentifiable not in ("base", "minimum_norm"):
        raise InvalidInputError(f"unidentifiable must be 'base' or 'minimum_norm', got {unidentifiable!r}")
    if not (tolerance > 0.0 and max_iterations >= 1):
        raise InvalidInputError(f"need tolerance > 0 and max_iterations >= 1, got {tolerance}, {max_iterations}")


def _accumulated_deltas(
    start: pin.Model, current: pin.Model, placements: Sequence[Placement]
) -> dict[Placement, np.ndarray]:
    """dt = log6(T(0)^-1 T_c(0)) per placement, read-only."""
    deltas = {p: pin.log6(placement_of(start, p).actInv(placement_of(current, p))).vector for p in placements}
    for value in deltas.values():
        value.flags.writeable = False
    return deltas


@on_one_blas_thread
def calibrate_two_chains(
    mechanism: Mechanism,
    readings: ArrayLike | Mapping[str, ArrayLike],
    measured_poses: Sequence[pin.SE3] | Mapping[str, Sequence[pin.SE3]],
    *,
    noise: TrackerNoise = TrackerNoise(),
    options: TwoChainOptions = TwoChainOptions(),
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
    options: the iteration's settings (`TwoChainOptions`).
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
    the machine can reach only at second order. rank_tolerance=1e-4 leaves them out with the same
    held-out accuracy and physically sized placement errors (`NOISY_READINGS_REL_TOL`).

    Raises IdentificationError when there are fewer rows than estimated parameters or when the
    iteration diverges.
    """
    solver, unidentifiable, tolerance = options.solver, options.unidentifiable, options.tolerance
    max_iterations, rank_tolerance = options.max_iterations, options.rank_tolerance
    _check_options(solver, unidentifiable, tolerance, max_iterations)
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
        return select_base_parameters((A * weights[None, :, None]).reshape(-1, A.shape[2]), names, rank_tolerance)

    def iterate(
        model_now: pin.Model, system: TwoChainErrorModel, y: np.ndarray, A: np.ndarray, base: BaseParameters
    ) -> tuple[pin.Model, TwoChainErrorModel, np.ndarray, np.ndarray, bool]:
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
            model_now = perturb(model_now, {p: step[_TWIST * k : _TWIST * (k + 1)] for k, p in enumerate(placements)})
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

    deltas = _accumulated_deltas(start, current, placements)
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
