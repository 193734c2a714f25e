"""The paper's simulation study (section 6), step by step: an actual chain with errors on T(0),
twists and joint variables (eq. 34-37), 20 poses from the mechanism's numerical forward
kinematics, calibrated by `calibrate_two_chains` and judged on held-out poses (the paper's Fig. 4).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

import numpy as np
import pinocchio as pin

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.errors import IdentificationError, InvalidInputError
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import workspace_actuators
from m3t1r.paper.chains import PaperChain, _chain_poses, _pose_differences, paper_chains
from m3t1r.paper.error_model import Identifiability, two_chain_identifiability
from m3t1r.paper.identification import PaperCalibration, calibrate_two_chains
from m3t1r.paper.passive_angles import LowerCrankEstimate, estimate_lower_crank_angles
from m3t1r.paper.simulation import (
    PresetErrors,
    PresetErrorScale,
    TwoChainStudyOptions,
    _checked_passive_encoder_noise,
    _observe,
    actual_chain_poses,
    preset_errors,
    sensor_readings,
)

__all__ = ["ChainErrors", "PassiveSource", "PaperStudyResult", "paper_study"]

#: Where a study takes q_i3 from: read by a sensor, or estimated by a `CrankMethod`.
PassiveSource = Literal["sensor", "distance", "platform", "sliders"]


def _with_passive(
    mechanism: Mechanism, readings: np.ndarray, source: PassiveSource, model: pin.Model
) -> tuple[np.ndarray, LowerCrankEstimate | None]:
    if source == "sensor":
        return readings, None
    if source not in ("distance", "platform", "sliders"):
        raise InvalidInputError(f"passive_from must be 'sensor', 'distance', 'platform' or 'sliders', got {source!r}")
    estimate = estimate_lower_crank_angles(mechanism, readings, method=source, model=model)
    return estimate.apply(readings), estimate


@dataclass(frozen=True)
class ChainErrors:
    """Pose errors of one chain's model against the truth, before and after calibration
    (after is None when the calibration failed)."""

    before: PoseErrors
    after: PoseErrors | None


@dataclass(frozen=True)
class PaperStudyResult:
    """The paper's simulation (section 6) on the two chains, and its Fig. 4.

    calibration_poses / holdout_poses: per chain, model pose against the actual chain's pose
    (eq. 37), before (nominal model) and after calibration. Calibration poses are evaluated at
    the readings the calibration used (noisy when `noise` is set); held-out poses at exact
    readings, so that they measure the identified model rather than the sensors. When
    passive_from is not "sensor", the lower cranks are estimated at both (with the nominal model).
    noise, passive_encoder_noise: the sensors' noise (None and 0 when every reading is exact).
    crank_error: (N, 2) estimated minus true q_13, q_23 (rad) on the calibration then held-out
        poses, None when read.
    calibration is None, and failure says why, when the identification raised IdentificationError
    (e.g. eq. 33 diverging on data no initial-pose error explains). With cranks from the paper's
    recursion it does not raise on the seeds tried, but it does not converge either
    (`PaperCalibration.converged`): the estimated angles are about 0.1 rad off.
    """

    seed: int
    noise: TrackerNoise | None
    passive_encoder_noise: float
    passive_from: PassiveSource
    preset: PresetErrors = field(repr=False)
    calibration: PaperCalibration | None = field(repr=False)
    failure: str | None
    identifiability: Identifiability = field(repr=False)
    calibration_poses: Mapping[str, ChainErrors] = field(repr=False)
    holdout_poses: Mapping[str, ChainErrors] = field(repr=False)
    crank_error: np.ndarray | None = field(repr=False)


def _paper_chain_errors(
    chains: Sequence[PaperChain],
    before: pin.Model,
    after: pin.Model | None,
    configurations: np.ndarray,
    truth: Sequence[Sequence[pin.SE3]],
) -> dict[str, ChainErrors]:
    def errors(model: pin.Model, chain: PaperChain, reference: Sequence[pin.SE3]) -> PoseErrors:
        return _pose_differences(_chain_poses(chain, model, configurations), reference)

    return {
        chain.name: ChainErrors(
            errors(before, chain, reference), None if after is None else errors(after, chain, reference)
        )
        for chain, reference in zip(chains, truth)
    }


@on_one_blas_thread
def paper_study(
    seed: int = 0,
    *,
    noise: TrackerNoise | None = None,
    passive_from: PassiveSource = "sensor",
    n_poses: int = 20,
    n_holdout: int = 50,
    scale: PresetErrorScale = PresetErrorScale(),
    mechanism: Mechanism | None = None,
    options: TwoChainStudyOptions = TwoChainStudyOptions(),
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

    With `noise` (the tracker's and slider encoders'), the tracker perturbs the measured poses, the
    slider encoders the slider readings and the passive joints' encoders, of standard deviation
    `options.passive_encoder_noise` [rad], every other reading; without, every reading is exact. With
    passive_from other than "sensor", q_13 and q_23 are estimated from the other readings with
    the nominal model instead of read. The first n_poses calibrate, the rest are held out.
    `options.fit_options` gives the settings of `calibrate_two_chains` (by default its own, with
    the rank threshold `EXACT_DATA_REL_TOL` without noise and `NOISY_READINGS_REL_TOL` with it).
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
    passive_encoder_noise = _checked_passive_encoder_noise(options.passive_encoder_noise) if noise is not None else 0.0
    readings = sensor_readings(nominal, chains, q_true[fit], noise, passive_encoder_noise, rng)
    readings, fit_estimate = _with_passive(nominal, readings, passive_from, nominal.model)
    measured = {chain.name: _observe(poses[fit], noise, rng) for chain, poses in zip(chains, truth)}
    tracker = noise if noise is not None else TrackerNoise()
    fit_options = options.fit_options(noisy=noise is not None)
    calibration: PaperCalibration | None = None
    failure = None
    try:
        calibration = calibrate_two_chains(nominal, readings, measured, noise=tracker, options=fit_options)
    except IdentificationError as exc:
        failure = str(exc)
    calibrated = None if calibration is None else calibration.model
    identifiability = two_chain_identifiability(
        nominal, readings, noise=tracker, rank_tolerance=fit_options.rank_tolerance
    )

    holdout, held_estimate = _with_passive(nominal, q_true[held], passive_from, nominal.model)
    crank_error = None
    if fit_estimate is not None and held_estimate is not None:
        true_angles = q_true[:, list(fit_estimate.idx_q)]
        crank_error = np.vstack([fit_estimate.angles, held_estimate.angles]) - true_angles
    return PaperStudyResult(
        seed=seed,
        noise=noise,
        passive_encoder_noise=passive_encoder_noise,
        passive_from=passive_from,
        preset=preset,
        calibration=calibration,
        failure=failure,
        identifiability=identifiability,
        calibration_poses=MappingProxyType(
            _paper_chain_errors(chains, nominal.model, calibrated, readings, [poses[fit] for poses in truth])
        ),
        holdout_poses=MappingProxyType(
            _paper_chain_errors(chains, nominal.model, calibrated, holdout, [poses[held] for poses in truth])
        ),
        crank_error=crank_error,
    )
