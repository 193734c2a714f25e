"""The calibration pipeline that closed-loop and serial fits share.

A fit is a whitened least-squares problem over a manifold of states (`CalibrationProblem`): the
closed-loop machine's (`m3t1r.calibration.closed_loop`) or a serial chain's
(`m3t1r.calibration.serial`). Everything after the problem is built runs here, in this order:

1. base parameters: column-pivoted QR of the whitened Jacobian at the start, fixed columns zeroed,
   the measurement setup's columns kept first (the gauge); the problem judges a shortfall;
2. Levenberg-Marquardt over them; while the rank is below the problem's structural bound, the base
   parameters are chosen again at the estimate and the fit resumed;
3. outliers: poses beyond `outlier_sigma` noise sigmas are dropped and the fit restarted from the
   start, every pose re-judged each round, until the flagged set is stable;
4. model selection: forward selection of the fitted parameters scored by leave-one-pose-out
   prediction (PRESS, `identification.forward_selection`); a smaller set is refitted from the start;
5. past the nominal's rank (`m3t1r.calibration.generic_rank`): where the fit is within the stated noise
   and the estimate identifies significantly more than the start (a nominal of special geometry),
   LM continues over every column with an effect, damped in the parameters' own units;
6. refinement (exact data only): the base parameters chosen again at the estimate with a looser
   tolerance, and a long damped fit from there;
7. the summary (`PipelineFit`): covariance from the noise model, variance factor, RMS before and after.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from types import MappingProxyType
from typing import Any, Generic, NamedTuple, Protocol, TypeVar

import numpy as np

from m3t1r.calibration.generic_rank import explained, significant
from m3t1r.calibration.identification import (
    IDENTIFIABILITY_TOLERANCE,
    OUTLIER_SIGMA,
    BaseParameters,
    LMResult,
    LMSettings,
    ParameterSelection,
    checked_outlier_sigma,
    forward_selection,
    levenberg_marquardt,
    outlier_poses,
    parameter_columns,
    select_base_parameters,
    triangular_factor,
)
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.repeats import grouped_blocks
from m3t1r.errors import IdentificationError, InvalidInputError, PoorExcitationWarning, require_count

__all__ = [
    "CalibrationOptions",
    "CalibrationProblem",
    "FitSummary",
    "LMSettings",
    "PipelineFit",
    "PoseErrorRMS",
    "choose_base",
    "fit",
    "fit_base",
    "fit_past_nominal_rank",
    "pose_error_rms",
    "prior_columns",
    "refine",
    "reject_outliers",
    "run_pipeline",
    "select_parameters",
    "summary_fields",
]

State = TypeVar("State")

#: Refits while the set of flagged outlier poses changes.
MAX_OUTLIER_ROUNDS = 5
#: Re-selections of the base parameters at the estimate, after the one at the start.
MAX_RESELECTIONS = 2
# Millimetre errors on metre links: the model is nearly linear over the whole correction, so start
# close to Gauss-Newton (Madsen & Nielsen's advice for a good starting point). With the textbook
# 1e-3, Marquardt's column scaling over-damps the weak directions (about twice the iterations).
INITIAL_DAMPING = 1e-6


@dataclass(frozen=True)
class CalibrationOptions:
    """The settings of a calibration, closed-loop or serial (`calibrate_closed_loop`, `calibrate_serial`).

    noise: the tracker's position [m] and orientation [rad] standard deviations, which whiten the
        residuals. setup: the measurement frame and marker to start from (None: identity, i.e. the
        platform or tool measured in the base frame). estimate_frame: fit the frame, started by
        rigid registration of the nominal predictions; estimate_marker: fit the marker (its
        translation alone with positions only); with several points per pose, every point's offset
        is estimated instead.
    outlier_sigma: the gate for outlier poses in noise sigmas (None or 0: keep every pose).
    select: model selection by leave-one-pose-out prediction; groups: (N,) a label per pose,
        repeats of one pose sharing one (`repeats.pose_groups`), left out together by the selection.
    fixed: parameter or placement names held at the start; priors: {name: sigma} adds a row
        x / sigma pulling the parameter toward its start [m, rad or rad/Nm].
    rank_tolerance: the identifiability threshold of the base-parameter choice.
    max_iterations: Levenberg-Marquardt's cap (None: the problem's default, 60 or 5 per base
        parameter for a closed loop, 30 for a serial chain).
    cost_tolerance: LM stops when an accepted step lowers the cost by less than this relatively
        (None: 1e-10 closed-loop, 1e-12 serial); absolute_cost_tolerance: ... by less than this
        absolutely, a noise variance (1e-6 moves the estimate by ~1e-3 of its std);
        step_significance: ... by less than this times the a-posteriori noise variance (None: 0.01
        closed-loop, 0 serial; 0.01 moves the estimate by at most 0.14 of its std).
    refine: exact data only (simulation studies): after convergence, choose the base parameters
        again at the estimate with `refine_rank_tolerance` and continue with damped LM for at most
        `refine_iterations` iterations.
    joint_noise: a serial robot's joint-reading standard deviation [rad or m], propagated into the
        whitening (0: exact readings); compliance: fit a serial joint's compliance under gravity.
        A closed-loop fit takes neither (its readings are the sliders, its passive joints solved).
    stream_jacobian: a closed-loop fit accumulates Levenberg-Marquardt's least-squares problem
        pose block by pose block (the QR of [J r], `ClosedLoopProblem.streamed`), so that its
        memory is bounded by the parameters, not the poses; False holds the whole whitened
        Jacobian instead (the same fit to rounding: the reference the streamed one is checked
        against). A serial fit holds its Jacobian either way.
    """

    noise: TrackerNoise = TrackerNoise()
    setup: MeasurementSetup | None = None
    estimate_frame: bool = False
    estimate_marker: bool = False
    outlier_sigma: float | None = OUTLIER_SIGMA
    select: bool = False
    groups: np.ndarray | None = field(default=None, compare=False, repr=False)
    fixed: Sequence[str] = ()
    priors: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    rank_tolerance: float = IDENTIFIABILITY_TOLERANCE
    max_iterations: int | None = None
    cost_tolerance: float | None = None
    absolute_cost_tolerance: float = 1e-6
    step_significance: float | None = None
    refine: bool = False
    refine_rank_tolerance: float = 1e-7
    refine_iterations: int = 400
    joint_noise: float = 0.0
    compliance: bool = False
    stream_jacobian: bool = True

    def __post_init__(self) -> None:
        # Checked once here, so that every fit refuses the same bad settings with the same message.
        object.__setattr__(self, "outlier_sigma", checked_outlier_sigma(self.outlier_sigma))
        if self.max_iterations is not None:
            object.__setattr__(self, "max_iterations", require_count(self.max_iterations, "max_iterations"))
        if isinstance(self.fixed, (str, bytes)):
            raise InvalidInputError(f"fixed parameter: expected a list of names such as ['q12'], got {self.fixed!r}")
        object.__setattr__(self, "fixed", tuple(self.fixed))
        object.__setattr__(self, "priors", MappingProxyType(dict(self.priors or {})))
        if self.groups is not None:
            object.__setattr__(self, "groups", np.asarray(self.groups))

    @property
    def start_setup(self) -> MeasurementSetup:
        """The setup the fit starts from (identity when none is given)."""
        return self.setup or MeasurementSetup()


class PoseErrorRMS(NamedTuple):
    """Root mean square over poses of the position error norm [m] and rotation angle [rad; nan when
    orientation was not measured]; with several points per pose, over the points seen."""

    position: float
    rotation: float


def pose_error_rms(residual: np.ndarray, seen: np.ndarray | None = None) -> PoseErrorRMS:
    """RMS of the pose errors of unwhitened residual blocks (N, k); with `seen` (N, 3 P), of every point seen."""
    if seen is not None:
        squared = np.sum(residual.reshape(len(residual), -1, 3) ** 2, axis=2)[seen[:, ::3]]
        return PoseErrorRMS(float(np.sqrt(np.mean(squared))), float("nan"))
    position = float(np.sqrt(np.mean(np.sum(residual[:, :3] ** 2, axis=1))))
    rotation = float(np.sqrt(np.mean(np.sum(residual[:, 3:] ** 2, axis=1)))) if residual.shape[1] == 6 else math.nan
    return PoseErrorRMS(position, rotation)


def prior_columns(names: Sequence[str], priors: Mapping[str, float] | None) -> dict[int, float]:
    """The column of each parameter a prior of sigma (m, rad or rad/Nm) names, by parameter or placement."""
    out: dict[int, float] = {}
    for name, sigma in (priors or {}).items():
        if not (np.isfinite(sigma) and sigma > 0.0):
            raise InvalidInputError(f"prior of '{name}': sigma must be a positive number (m, rad or rad/Nm)")
        out.update({c: float(sigma) for c in parameter_columns(names, [name], "prior")})
    return out


class CalibrationProblem(Protocol[State]):
    """What the pipeline needs of a fit: the whitened residual over the fitted `columns` of every
    candidate parameter (`names`), with the rows of flagged poses (`active` False) zero and one row
    x_c / sigma_c after the pose rows per fitted column with a prior.

    Pose rows come first, `rows_per_pose` per pose, pose after pose; `seen` (N, rows_per_pose) says
    which were measured (a point not seen gives zero rows); `n_points` is the points per pose (0:
    one measured frame). `setup_columns` are the measurement setup's, kept first by the base choice.
    """

    names: tuple[str, ...]
    columns: np.ndarray
    active: np.ndarray
    priors: dict[int, float]

    @property
    def rows_per_pose(self) -> int: ...

    @property
    def seen(self) -> np.ndarray: ...

    @property
    def n_points(self) -> int: ...

    @property
    def setup_columns(self) -> np.ndarray: ...

    def residual(self, state: State) -> np.ndarray:
        """The whitened residual alone (LM's trial steps)."""
        ...

    def residual_and_jacobian(self, state: State) -> tuple[np.ndarray, np.ndarray]:
        """The whitened residual and its Jacobian over `columns`, r(retract(state, dx)) = r + J dx + O(dx^2)."""
        ...

    def retract(self, state: State, step: np.ndarray) -> State:
        """The state moved by a step over `columns` (T(0) <- T(0) exp6(dx) per placement, eq. 33)."""
        ...

    def release(self, state: State) -> None:
        """Drop what `state` caches for a step: LM calls it on an iterate it leaves."""
        ...

    def restart(self, state: State) -> State:
        """`state` without its cached evaluation, for a fit over other columns or poses."""
        ...

    def accumulated(self, state: State) -> np.ndarray:
        """The steps taken since the start (len(names),), the priors' pull."""
        ...

    def pose_blocks(self, state: State) -> np.ndarray:
        """Whitened residual blocks (N, rows_per_pose) of every pose, flagged ones included."""
        ...

    def raw_blocks(self, state: State) -> np.ndarray:
        """Unwhitened residual blocks (N, rows_per_pose) of every pose [m, rad]."""
        ...

    def pose_rows(self, state: State) -> tuple[np.ndarray, np.ndarray]:
        """The inlier poses' whitened residual rows and their Jacobian over `columns`, a new
        column-major array the caller may overwrite (the selection projects it in place)."""
        ...

    def jacobian_factor(self, state: State, with_residual: bool = False) -> np.ndarray:
        """A writable matrix F over every column with F^T F = J^T J of the whitened pose rows (the
        Jacobian itself or its triangular factor): what the base-parameter choice reads. with_residual:
        instead the triangular factor of the inliers' [J r] (its last column Q^T r)."""
        ...

    def check_base(self, base: BaseParameters, factor: np.ndarray, fixed: Sequence[int]) -> None:
        """Refuse (IdentificationError, saying what would help) base parameters that the data identify
        fewer of than the model and setup can; `factor` is the start's, fixed columns zeroed."""
        ...

    def reselection_bound(self) -> int:
        """The rank the structure allows: while the fit's base is smaller, it is chosen again at the
        estimate (0: never)."""
        ...

    def default_iterations(self, n_parameters: int) -> int: ...

    @property
    def default_cost_tolerance(self) -> float: ...

    @property
    def default_step_significance(self) -> float: ...


@dataclass(frozen=True, kw_only=True)
class FitSummary(Generic[State]):
    """What every calibration reports of its fit: the pipeline's summary (`PipelineFit`) and the
    closed-loop and serial results built on it (`ClosedLoopCalibration`, `SerialCalibration`).

    start: the registered start; lm: the last Levenberg-Marquardt run (its state is the estimate);
    iterations: LM iterations over every run; base: the identifiable set at the start (or at a
    re-selection); selection: the forward-selection record (None when not run); covariance over the
    columns finally fitted, from the noise model, (J^T J)^-1 with J whitened; variance_factor:
    chi^2 / degrees of freedom of the inliers' rows and priors (about 1 when the model explains the
    data under the stated noise); rms_before / rms_after: the inliers' residual RMS at the start and
    the end; outliers: the indices of the poses flagged and left out; settings: LM's, for refits of
    the same kind (cross-validation).
    """

    start: State = field(repr=False)
    lm: LMResult[State] = field(repr=False)
    iterations: int
    base: BaseParameters
    selection: ParameterSelection | None = field(default=None, repr=False)
    covariance: np.ndarray = field(repr=False)
    variance_factor: float
    rms_before: PoseErrorRMS
    rms_after: PoseErrorRMS
    outliers: tuple[int, ...]
    settings: LMSettings = field(repr=False)

    @property
    def converged(self) -> bool:
        """The last Levenberg-Marquardt run met one of its convergence tests."""
        return bool(self.lm.converged)

    @property
    def termination(self) -> str:
        """The test that stopped the last Levenberg-Marquardt run (`LMResult.termination`)."""
        return self.lm.termination


def summary_fields(summary: FitSummary[State]) -> dict[str, Any]:
    """The `FitSummary` fields of `summary` by name: what a calibration result copies from its pipeline fit."""
    return {f.name: getattr(summary, f.name) for f in fields(FitSummary)}


@dataclass(frozen=True, kw_only=True)
class PipelineFit(FitSummary[State]):
    """What `run_pipeline` ends on: the `FitSummary`, with the columns finally fitted and std, the
    root of the covariance's diagonal."""

    columns: tuple[int, ...]
    std: np.ndarray


def fit(problem: CalibrationProblem[State], state: State, settings: LMSettings) -> LMResult[State]:
    """`levenberg_marquardt` with `settings`; IdentificationError when it ends on a state whose residual
    is not finite (a closed loop that does not assemble)."""
    result = levenberg_marquardt(problem, state, settings)
    if not math.isfinite(result.cost):
        raise IdentificationError("calibration ended on a model that does not assemble")
    return result


def choose_base(
    problem: CalibrationProblem[State], state: State, rank_tolerance: float, fixed: Sequence[int]
) -> tuple[BaseParameters, np.ndarray]:
    """Base parameters of the whitened Jacobian at `state`, `fixed` columns zeroed, the setup's columns
    kept first; and the factor they were chosen on."""
    factor = problem.jacobian_factor(state)
    factor[:, list(fixed)] = 0.0
    return select_base_parameters(factor, problem.names, rank_tolerance, forced=problem.setup_columns), factor


def fit_base(
    problem: CalibrationProblem[State], start: State, options: CalibrationOptions, fixed: Sequence[int]
) -> tuple[BaseParameters, LMResult[State], int, LMSettings]:
    """Steps 1 and 2 of the module docstring: the base at the start, judged; LM; re-selections."""
    base, factor = choose_base(problem, start, options.rank_tolerance, fixed)
    problem.check_base(base, factor, fixed)
    problem.columns = np.array(base.indices)
    degrees_of_freedom = max(len(problem.active) * problem.rows_per_pose - base.rank, 1)
    significance = options.step_significance
    significance = problem.default_step_significance if significance is None else significance
    cost_tolerance = problem.default_cost_tolerance if options.cost_tolerance is None else options.cost_tolerance
    settings = LMSettings(
        max_iterations=options.max_iterations or problem.default_iterations(base.rank),
        cost_tolerance=max(cost_tolerance, 2.0 * significance / degrees_of_freedom),
        absolute_cost_tolerance=options.absolute_cost_tolerance,
        initial_damping=INITIAL_DAMPING,
    )
    result = fit(problem, problem.restart(start), settings)
    iterations = result.iterations
    # Nominal CAD geometry can hide parameters (e.g. UR's tool point on the last joint axis hides
    # two from position measurements); at the estimate they show.
    for _ in range(MAX_RESELECTIONS if base.rank < problem.reselection_bound() else 0):
        candidate, _ = choose_base(problem, result.state, options.rank_tolerance, fixed)
        if candidate.rank <= base.rank:
            break
        base = candidate
        problem.columns = np.array(base.indices)
        result = fit(problem, result.state, settings)
        iterations += result.iterations
    return base, result, iterations, settings


def reject_outliers(
    problem: CalibrationProblem[State], start: State, result: LMResult[State], sigma: float, settings: LMSettings
) -> tuple[LMResult[State], int]:
    """Flag poses beyond `sigma` noise sigmas (`outlier_poses`), refit without them from the start,
    re-judge every pose; until the flagged set is stable (at most MAX_OUTLIER_ROUNDS refits).
    Returns the last fit and the iterations of the refits. Resuming from the estimate instead
    stalls: the outliers pull it into a curved valley of the weak directions, where LM creeps."""
    iterations = 0
    for _ in range(MAX_OUTLIER_ROUNDS):
        blocks = problem.pose_blocks(result.state)
        measured_rows = problem.seen.sum(axis=1) if problem.n_points else None
        flagged, _scale = outlier_poses(blocks, sigma, measured_rows)
        if np.array_equal(~flagged, problem.active):
            break
        if np.count_nonzero(problem.seen[~flagged]) <= len(problem.columns):
            raise IdentificationError(
                f"{np.count_nonzero(flagged)} of {len(flagged)} poses are outliers: "
                "too few poses are left to fit the model"
            )
        problem.active = ~flagged
        problem.release(result.state)
        result = fit(problem, problem.restart(start), settings)
        iterations += result.iterations
    return result, iterations


def select_parameters(
    problem: CalibrationProblem[State],
    start: State,
    result: LMResult[State],
    settings: LMSettings,
    groups: np.ndarray | None = None,
) -> tuple[ParameterSelection, LMResult[State], int]:
    """Forward selection by leave-one-pose-out PRESS on the fit linearised at the estimate (the
    residual at the start is about r - J dx, dx the accumulated step), the setup's columns forced;
    a smaller set is refitted from the start. Returns the record, the fit and the refit's
    iterations. groups: (N,) labels whose poses are left out together (`repeats.grouped_blocks`)."""
    rows = problem.rows_per_pose
    r, J = problem.pose_rows(result.state)
    r0 = r - J @ problem.accumulated(result.state)[problem.columns]
    forced = np.flatnonzero(np.isin(problem.columns, problem.setup_columns))
    labels = None if groups is None else np.asarray(groups)[problem.active]
    J, r0, block = grouped_blocks(J, r0, rows, labels)
    # The only Jacobian of every pose the pipeline holds: projected in place, never copied.
    selection = forward_selection(J, r0, block, range(len(problem.columns)), forced, overwrite=True)
    del J
    if len(selection.indices) == len(problem.columns):
        return selection, result, 0
    problem.columns = problem.columns[list(selection.indices)]
    problem.release(result.state)
    refit = fit(problem, problem.restart(start), settings)
    return selection, refit, refit.iterations


def fit_past_nominal_rank(
    problem: CalibrationProblem[State],
    result: LMResult[State],
    nominal_rank: int,
    fixed: Sequence[int],
    rank_tolerance: float,
    settings: LMSettings,
) -> tuple[LMResult[State], int]:
    """Step 5 of the module docstring: the fit over every column with an effect, where the estimate
    identifies more than `nominal_rank` and the directions it adds explain the residual significantly
    (`generic_rank.significant`), kept when it converged and its own drop in chi^2 passes the same test.
    Returns the fit and the refit's iterations. A fit beyond the stated noise (chi^2 above its degrees
    of freedom) is left alone: its cause is a model error (a frame, a marker), which weak directions must
    not absorb into implausible placements."""
    chi2 = float(np.sum(problem.pose_blocks(result.state)[problem.active] ** 2))
    rows, fitted = int(np.count_nonzero(problem.seen[problem.active])), problem.columns
    if chi2 > rows - len(fitted):
        return result, 0
    augmented = problem.jacobian_factor(result.state, with_residual=True)
    factor, rotated = augmented[:, :-1], augmented[:, -1]
    factor[:, list(fixed)] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)  # the added directions are weak by nature
        here = select_base_parameters(factor, problem.names, rank_tolerance, forced=problem.setup_columns)
    extra, dof = here.rank - len(fitted), rows - here.rank
    if here.rank <= nominal_rank or not significant(chi2, chi2 - explained(factor, rotated, here.indices), extra, dof):
        return result, 0
    norms = np.linalg.norm(factor, axis=0)
    problem.columns = np.flatnonzero(norms > rank_tolerance * norms.max())
    # Unit damping creeps along the weak directions: 20 iterations per parameter (a leg with spherical
    # rods converges in 1151 at rank 72, the planar delta in about 370 at 50). The absolute stop is in units
    # of the base fit's own residual variance, not the stated noise's: on noise-free data (variance factor
    # 2e-6) a step lowering 1/2 chi^2 by 7e-7 stated variances is a real advance.
    variance_factor = min(chi2 / max(rows - len(fitted), 1), 1.0)
    unit_settings = replace(
        settings,
        max_iterations=4 * problem.default_iterations(here.rank),
        absolute_cost_tolerance=settings.absolute_cost_tolerance * variance_factor,
        unit_damping=True,
    )
    try:
        refit = fit(problem, problem.restart(result.state), unit_settings)
    except IdentificationError:  # a refit that leaves the assembly is not kept
        refit = None
    if refit is not None and refit.converged and significant(2.0 * result.cost, 2.0 * refit.cost, extra, dof):
        problem.release(result.state)
        return refit, refit.iterations
    problem.columns = fitted
    return result, 0 if refit is None else refit.iterations


def refine(
    problem: CalibrationProblem[State], result: LMResult[State], rank_tolerance: float, iterations: int
) -> LMResult[State]:
    """Choose the base parameters again at the estimate with `rank_tolerance` (no gauge kept first):
    some of the directions unidentifiable at the nominal geometry have become weakly identifiable
    (O(error^2) effects); if there are more, continue with lightly damped LM (exact data only)."""
    factor = problem.jacobian_factor(result.state)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)  # weak by construction
        refined = select_base_parameters(factor, problem.names, rank_tolerance=rank_tolerance)
    if refined.rank <= len(problem.columns):
        return result
    problem.columns = np.array(refined.indices)
    settings = LMSettings(iterations, cost_tolerance=1e-14, absolute_cost_tolerance=0.0, initial_damping=1e-9)
    return fit(problem, problem.restart(result.state), settings)


def _covariance(jacobian: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J^T J)^+ of a whitened Jacobian and the root of its diagonal, from the SVD of its triangular
    factor (the same singular values and right vectors, in memory independent of the rows) rather
    than pinv(J^T J): squaring the condition number of a weakly excited set can make the diagonal
    slightly negative. No columns (the start already explains the data): empty."""
    if jacobian.shape[1] == 0:
        return np.zeros((0, 0)), np.zeros(0)
    _, singular, vt = np.linalg.svd(triangular_factor(jacobian), full_matrices=False)
    kept = singular > 1e-12 * singular[0]
    covariance = (vt[kept].T / singular[kept] ** 2) @ vt[kept]
    return covariance, np.sqrt(np.sum((vt[kept] / singular[kept, None]) ** 2, axis=0))


def summarise(
    problem: CalibrationProblem[State],
    start: State,
    result: LMResult[State],
    counts: tuple[BaseParameters, ParameterSelection | None, int],
    settings: LMSettings,
) -> PipelineFit[State]:
    """The `PipelineFit` of a final fit (counts: the base, the selection and the iterations)."""
    base, selection, iterations = counts
    r, J = problem.residual_and_jacobian(result.state)
    covariance, std = _covariance(J)
    priors = sum(1 for c in problem.columns if c in problem.priors)
    dof = int(np.count_nonzero(problem.seen[problem.active])) + priors - len(problem.columns)
    inliers = problem.active
    seen = problem.seen[inliers] if problem.n_points else None
    return PipelineFit(
        start=start,
        lm=result,
        iterations=iterations,
        base=base,
        selection=selection,
        columns=tuple(int(c) for c in problem.columns),
        covariance=covariance,
        std=std,
        variance_factor=float(r @ r / dof) if dof > 0 else float("nan"),
        rms_before=pose_error_rms(problem.raw_blocks(start)[inliers], seen),
        rms_after=pose_error_rms(problem.raw_blocks(result.state)[inliers], seen),
        outliers=tuple(int(i) for i in np.flatnonzero(~inliers)),
        settings=settings,
    )


def run_pipeline(problem: CalibrationProblem[State], start: State, options: CalibrationOptions) -> PipelineFit[State]:
    """Steps 1 to 7 of the module docstring on `problem` from its registered `start`."""
    fixed = parameter_columns(problem.names, options.fixed, "fixed parameter")
    base, result, iterations, settings = fit_base(problem, start, options, fixed)
    if options.outlier_sigma is not None:
        result, more = reject_outliers(problem, start, result, options.outlier_sigma, settings)
        iterations += more
    selection = None
    if options.select:
        selection, result, more = select_parameters(problem, start, result, settings, options.groups)
        iterations += more
    result, more = fit_past_nominal_rank(problem, result, base.rank, fixed, options.rank_tolerance, settings)
    iterations += more
    if options.refine:
        refined = refine(problem, result, options.refine_rank_tolerance, options.refine_iterations)
        iterations += refined.iterations if refined is not result else 0
        result = refined
    return summarise(problem, start, result, (base, selection, iterations), settings)
