"""The paper's method on the full closed-chain machine, against the closed-loop calibration of the
same data (`closed_chain_study`).

On the closed-chain machine the chain ending at the measured frame fits exactly, but only while
every passive joint is read: predicting from the sliders needs the passive angles, and with the
nominal model's the result is no better than the uncalibrated machine. The other chain cannot
follow the measured frame at all.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.closed_loop import ClosedLoopCalibration, calibrate_closed_loop, pose_errors
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.simulation import PlacementErrorScale, simulate_study
from m3t1r.errors import KinematicsError
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver, rehomed
from m3t1r.model.poe import perturb
from m3t1r.paper.chains import PaperChain, _chain_poses, _pose_differences, paper_chains
from m3t1r.paper.identification import PaperCalibration, calibrate_two_chains
from m3t1r.paper.passive_angles import estimate_lower_crank_angles
from m3t1r.paper.simulation import TwoChainStudyOptions, _checked_passive_encoder_noise, _observe, sensor_readings

__all__ = ["ClosedChainStudyResult", "closed_chain_study"]


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
    noise, passive_encoder_noise: the sensors' noise (None and 0 when every reading is exact).
    """

    seed: int
    noise: TrackerNoise | None
    passive_encoder_noise: float
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


def _calibrated_trees(
    nominal: Mechanism, truth: Mechanism, calibration: PaperCalibration, first: PaperChain, actuators: np.ndarray
) -> tuple[PoseErrors | None, bool]:
    """(held-out errors of the tree with chain `first`'s calibrated placements, None if it does not
    assemble; whether the tree with both chains' calibrated placements assembles)."""
    calibrated_tree: PoseErrors | None = None
    try:
        own = {p: calibration.deltas[p] for p in first.serial.placements()}
        tree = rehomed(nominal.with_model(perturb(nominal.model, own)))
        calibrated_tree = pose_errors(truth, tree, actuators)
    except KinematicsError:
        pass
    try:
        rehomed(nominal.with_model(calibration.model))
        both_chains_assemble = True
    except KinematicsError:
        both_chains_assemble = False
    return calibrated_tree, both_chains_assemble


def _crank_errors(nominal: Mechanism, q_held: np.ndarray) -> dict[str, np.ndarray]:
    """{method: estimated minus true lower-crank angles} at the held-out configurations."""
    crank_error = {}
    for method in ("distance", "platform", "sliders"):
        estimate = estimate_lower_crank_angles(nominal, q_held, method=method)
        crank_error[method] = estimate.angles - q_held[:, list(estimate.idx_q)]
    return crank_error


@on_one_blas_thread
def closed_chain_study(
    seed: int = 0,
    *,
    noise: TrackerNoise | None = None,
    n_poses: int = 20,
    n_holdout: int = 50,
    errors: PlacementErrorScale = PlacementErrorScale(),
    compare_closed_loop: bool = True,
    mechanism: Mechanism | None = None,
    options: TwoChainStudyOptions = TwoChainStudyOptions(),
) -> ClosedChainStudyResult:
    """Calibrate the paper's two chains on a simulated closed-chain machine and judge the result
    on held-out slider sets, against the closed-loop calibration of the same data.

    Data per calibration pose: the slider readings, the readings of every joint of both chains
    (the truth's assembled configuration, plus noise), and the measured pose of the platform
    frame P_I (plus tracker noise), which is the target of both chains. Noise as in `paper_study`:
    `noise` for the tracker and the sliders, `options.passive_encoder_noise` [rad] for the other
    joints, none at all with noise=None. Held-out poses use exact readings for every method. The
    truth's placement errors are drawn with `errors` (`simulate_study`).

    The paper's premise y_1 = y_2 (eq. 21) is a rigid platform that both chains end on. On a
    machine with errors the closure cannot hold in every direction: the truth keeps P_I and P_II
    together in position and yaw, and its roll and pitch differ by tens of milliradians, varying
    with the pose (the strain a real machine takes up in joint play and elasticity). Chain B1
    ends at the measured frame and fits it exactly; chain B3 cannot, and its undamped iteration
    can wander along weakly identifiable directions.
    options: as in `paper_study`.
    """
    nominal = Mechanism.load() if mechanism is None else mechanism
    chains = paper_chains(nominal)
    study = simulate_study(
        nominal,
        n_poses=n_poses,
        n_holdout=n_holdout,
        seed=seed,
        errors=errors,
        noise=None,
    )
    truth = study.truth
    rng = np.random.default_rng([seed, 1])  # the noise, independent of the machine's draw
    truth_solver = ClosedLoopSolver(truth)
    fit_forward = [truth_solver.forward(a, q_init=truth.home) for a in study.measurements.actuators]
    held_forward = [truth_solver.forward(a, q_init=truth.home) for a in study.holdout_actuators]
    q_fit = np.array([r.q for r in fit_forward])
    q_held = np.array([r.q for r in held_forward])
    held_truth = tuple(r.pose for r in held_forward)

    passive_encoder_noise = _checked_passive_encoder_noise(options.passive_encoder_noise) if noise is not None else 0.0
    readings = sensor_readings(nominal, chains, q_fit, noise, passive_encoder_noise, rng)
    measured = _observe([r.pose for r in fit_forward], noise, rng)
    tracker = noise if noise is not None else TrackerNoise()
    fit_options = options.fit_options(noisy=noise is not None)
    calibration = calibrate_two_chains(nominal, readings, measured, noise=tracker, options=fit_options)

    first, second = chains
    sensors_before = _pose_differences(_chain_poses(first, nominal.model, q_held), held_truth)
    sensors_after = _pose_differences(calibration.predict(first.name, q_held), held_truth)
    second_before = _pose_differences(_chain_poses(second, nominal.model, q_held), held_truth)
    second_after = _pose_differences(calibration.predict(second.name, q_held), held_truth)
    nominal_solver = ClosedLoopSolver(nominal)
    q_nominal = np.array([nominal_solver.forward(a, q_init=nominal.home).q for a in study.holdout_actuators])
    sliders_only = _pose_differences(calibration.predict(first.name, q_nominal), held_truth)
    calibrated_tree, both_chains_assemble = _calibrated_trees(
        nominal, truth, calibration, first, study.holdout_actuators
    )

    closed_loop = closed_loop_errors = None
    if compare_closed_loop:
        sliders = readings[:, nominal.actuated_ids]
        closed_loop = calibrate_closed_loop(
            nominal, PoseMeasurements(sliders, measured), CalibrationOptions(noise=tracker)
        )
        closed_loop_errors = pose_errors(truth, closed_loop.mechanism, study.holdout_actuators)

    crank_error = _crank_errors(nominal, q_held)
    return ClosedChainStudyResult(
        seed=seed,
        noise=noise,
        passive_encoder_noise=passive_encoder_noise,
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
