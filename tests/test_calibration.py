"""Closed-loop calibration: sensitivities, identifiability and reachable accuracy (docs/results.md)."""

import copy
import dataclasses
import re
import warnings
from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest
import scipy.special

from m3t1r.calibration import closed_loop, pipeline
from m3t1r.calibration.closed_loop import (
    ClosedLoopProblem,
    ClosedLoopState,
    _registered_setup,
    _residual_rows_batch,
    calibrate_closed_loop,
    cross_validate,
    default_iterations,
    pose_errors,
    predicted_measurement_std,
    predicted_pose_std,
    setup_parameter_names,
)
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.identification import forward_selection, outlier_gate, select_base_parameters
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise, assembled_from_home, measure
from m3t1r.calibration.pipeline import CalibrationOptions, LMSettings, pose_error_rms
from m3t1r.calibration.repeats import inlier_folds
from m3t1r.calibration.simulation import (
    PlacementErrorScale,
    StudyOptions,
    actual_machine,
    random_placement_errors,
    simulate_study,
)
from m3t1r.errors import BranchChangeError, IdentificationError, InvalidInputError, PoorExcitationWarning
from m3t1r.metrics import pose_errors_between
from m3t1r.model.batch_kinematics import RowFailure
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import Placement
from m3t1r.model.workspace import workspace_actuators


@pytest.fixture(scope="module")
def error_model(mechanism):
    return ClosedLoopErrorModel(mechanism)


def test_parameter_layout(error_model):
    # 20 joint placements, 12 closure point frames, P_I and P_II: 204 parameters (docs/results.md).
    assert len(error_model.placements) == 34 and error_model.n_parameters == 204
    assert error_model.names[:2] == ("q11.dt[0]", "q11.dt[1]")
    assert "P_I.dt[5]" in error_model.names and "fivebar_tip_II.dt[3]" in error_model.names


def test_platform_sensitivity_matches_finite_differences_through_the_closures(mechanism, error_model):
    """d xi_P / dp by implicit differentiation vs central differences of the closed-loop FK."""
    rng = np.random.default_rng(7)
    truth = simulate_study(mechanism, n_poses=1, n_holdout=0, seed=3).truth  # a perturbed machine
    sliders = workspace_actuators(mechanism, 1, rng)[0]
    solver = ClosedLoopSolver(truth)
    q = solver.forward(sliders, q_init=truth.home).q
    one = error_model.platform_sensitivities(solver, [q])
    pose, dxi = pin.SE3(one.poses[0]), one.twist_jacobians[0]
    step = 1e-6
    columns = rng.choice(error_model.n_parameters, 60, replace=False)
    for k in columns:
        twists = []
        for sign in (1.0, -1.0):
            vector = np.zeros(error_model.n_parameters)
            vector[k] = sign * step
            moved = ClosedLoopSolver(truth.with_model(error_model.perturbed(truth.model, vector)))
            twists.append(pin.log6(moved.forward(sliders, q_init=q).pose * pose.inverse()).vector)
        fd = (twists[0] - twists[1]) / (2 * step)
        assert np.allclose(dxi[:, k], fd, atol=1e-6 * max(1.0, np.abs(dxi).max())), error_model.names[k]


def test_batched_sensitivities_equal_the_full_computation_column_by_column(mechanism, error_model):
    """Restricting the columns (LM asks only for the base parameters) changes nothing but the width;
    the batch equals pose-by-pose calls."""
    truth = simulate_study(mechanism, n_poses=1, n_holdout=0, seed=4).truth
    solver = ClosedLoopSolver(truth)
    configurations = [
        solver.forward(s, q_init=truth.home).q for s in workspace_actuators(mechanism, 3, np.random.default_rng(8))
    ]
    full = error_model.platform_sensitivities(solver, configurations)
    columns = np.random.default_rng(9).choice(error_model.n_parameters, 70, replace=False)
    part = error_model.platform_sensitivities(solver, configurations, columns)
    np.testing.assert_allclose(part.twist_jacobians, full.twist_jacobians[:, :, columns], atol=1e-12)
    np.testing.assert_allclose(part.closure_jacobians, full.closure_jacobians[:, :, columns], atol=1e-12)
    for i, q in enumerate(configurations):
        alone = error_model.platform_sensitivities(solver, [q], columns)
        np.testing.assert_allclose(alone.poses[0], part.poses[i], atol=1e-15)
        np.testing.assert_allclose(alone.twist_jacobians[0], part.twist_jacobians[i], atol=1e-12)
        np.testing.assert_allclose(alone.passive_jacobians[0], part.passive_jacobians[i], atol=1e-12)
        np.testing.assert_allclose(alone.closure_jacobians[0], part.closure_jacobians[i], atol=1e-12)


def test_joint_twists_are_pinocchio_regressors(mechanism, error_model):
    solver = ClosedLoopSolver(mechanism)
    q = solver.forward([0.1, 0.05, -0.05, 0.1]).q
    solver.closure_sensitivity(q)
    joints = np.array([[placement.homogeneous for placement in solver.data.oMi.tolist()]])
    G = error_model.joint_twist_matrices(solver.model, joints)[0]
    for frame in ("P_I", "P_II", "fivebar_tip_I", "lower_tip_II"):
        fid = solver.model.getFrameId(frame)
        regressor = pin.computeFrameKinematicRegressor(solver.model, solver.data, fid, pin.WORLD)
        support = np.abs(regressor).sum(axis=0) > 0
        np.testing.assert_allclose(G[:, support], regressor[:, support], atol=1e-14)


@pytest.fixture(scope="module")
def noise_free_1mm(mechanism):
    study = simulate_study(mechanism, n_poses=50, n_holdout=200, seed=11)
    return study, calibrate_closed_loop(mechanism, study.measurements)


def test_identifiable_parameters_at_nominal(noise_free_1mm):
    _, calibration = noise_free_1mm
    base = calibration.base
    assert base.rank == 56  # docs/results.md: 56 of 204 at the nominal geometry
    assert base.r_diag_ratio[-2] > 1e-6 and base.r_diag_ratio[-1] < 1e-12  # a clean QR gap
    # Columns with no effect at all: e.g. a closure frame's motion along its loop's unenforced axis.
    # (The reference implementation reports 96 with its own frame conventions; ours gives 90.)
    assert len(base.zero_columns) == 90


def test_noise_free_1mm_machine_is_recovered_below_a_micrometre(noise_free_1mm):
    study, calibration = noise_free_1mm
    before = pose_errors(study.nominal, study.truth, study.holdout_actuators)
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    assert before.position_mean > 3e-3  # a badly built machine: millimetres off
    assert after.position_mean < 1e-6 and after.rotation_mean < 5e-6
    assert calibration.lm.converged


def test_noise_free_0_1mm_machine_is_recovered_to_nanometres(mechanism):
    study = simulate_study(mechanism, n_poses=50, n_holdout=200, seed=12, errors=PlacementErrorScale(1e-4, 1e-4))
    calibration = calibrate_closed_loop(mechanism, study.measurements)
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    assert after.position_mean < 1e-8 and after.rotation_mean < 1e-7


def test_noisy_calibration_sits_at_the_predicted_floor(mechanism):
    noise = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)
    study = simulate_study(mechanism, n_poses=50, n_holdout=200, seed=13, noise=noise)
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=noise))
    before = pose_errors(study.nominal, study.truth, study.holdout_actuators)
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    predicted = predicted_pose_std(calibration, study.holdout_actuators)
    rms = lambda values: float(np.sqrt(np.mean(values**2)))  # noqa: E731
    assert rms(after.position) <= 1.3 * rms(predicted.position)
    assert rms(after.rotation) <= 1.3 * rms(predicted.rotation)
    assert before.position_mean / after.position_mean > 100
    assert 4e-6 < after.position_mean < 15e-6 and after.rotation_mean < 20e-6
    # Standard deviations are reported for the identified base parameters only.
    assert sum(1 for v in calibration.std.values() if v > 0) == calibration.base.rank


def test_predicted_measurement_std_is_the_tracker_frame_error_of_a_frame_estimating_fit(mechanism, error_model):
    """A tracker 3 m away, rotated, and a reflector 6 cm off the platform; the frame estimated with
    the machine. What the calibrated model predicts the tracker sees at 300 held-out slider sets is
    off by about what predicted_measurement_std says (9.3 um / 14.8 urad predicted, 10.9 um /
    14.8 urad actual, RMS), while the platform's std in the machine's base is millimetres: the base
    placement is the gauge that the estimated frame leaves free."""
    rng = np.random.default_rng(1)
    truth = actual_machine(mechanism, random_placement_errors(error_model, rng, 1e-3, 1e-3))
    setup = MeasurementSetup(
        pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 2.0), np.array([3.0, -1.0, 0.5])),
        pin.SE3(np.eye(3), np.array([0.05, -0.02, 0.03])),
    )
    noise = TrackerNoise(10e-6, 20e-6)
    measured = measure(truth, workspace_actuators(mechanism, 60, rng), rng, noise, setup=setup)
    calibration = calibrate_closed_loop(
        mechanism,
        measured,
        CalibrationOptions(noise=noise, setup=MeasurementSetup(marker=setup.marker), estimate_frame=True),
    )
    held_out = workspace_actuators(mechanism, 300, np.random.default_rng(101))
    actual = pose_errors_between(
        calibration.setup.measured_poses(assembled_from_home(calibration.mechanism, held_out).poses),
        setup.measured_poses(assembled_from_home(truth, held_out).poses),
    )
    predicted = predicted_measurement_std(calibration, held_out)
    rms = lambda values: float(np.sqrt(np.mean(values**2)))  # noqa: E731
    assert 0.8 < rms(actual.position) / rms(predicted.position) < 1.5
    assert 0.8 < rms(actual.rotation) / rms(predicted.rotation) < 1.5
    assert rms(predicted_pose_std(calibration, held_out).position) > 100 * rms(predicted.position)


def test_predicted_measurement_std_without_a_setup_is_the_platform_std(mechanism):
    """No frame, no marker: the measured frame is the platform in the base, so both predictions agree."""
    noise = TrackerNoise(position=10e-6, rotation=20e-6)
    study = simulate_study(mechanism, n_poses=40, n_holdout=20, seed=3, noise=noise)
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=noise))
    measured = predicted_measurement_std(calibration, study.holdout_actuators)
    platform = predicted_pose_std(calibration, study.holdout_actuators)
    np.testing.assert_allclose(measured.position, platform.position, rtol=1e-10)
    np.testing.assert_allclose(measured.rotation, platform.rotation, rtol=1e-10)
    empty = predicted_measurement_std(calibration, np.zeros((0, 4)))
    assert empty.position.shape == (0,) and empty.rotation.shape == (0,)


def test_position_only_measurements(mechanism):
    noise = TrackerNoise(position=10e-6, rotation=20e-6)
    study = simulate_study(
        mechanism, n_poses=60, n_holdout=100, seed=14, noise=noise, options=StudyOptions(position_only=True)
    )
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=noise))
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    predicted = predicted_pose_std(calibration, study.holdout_actuators)
    assert np.sqrt(np.mean(after.position**2)) <= 1.5 * np.sqrt(np.mean(predicted.position**2))
    assert after.position_mean < 3e-5
    assert np.isnan(calibration.rms_after[1])


def test_too_few_poses_is_refused(mechanism):
    study = simulate_study(mechanism, n_poses=5, n_holdout=0, seed=15)
    with pytest.raises(
        IdentificationError,
        match="30 residual rows for 56 identifiable parameters and identify only 30: "
        r"add poses \(each gives 6 rows\)",
    ):
        calibrate_closed_loop(mechanism, study.measurements)


def _advised_holding(message: str) -> list[str]:
    held = re.search(r"\(--fix ([^)]+)\)$", message)
    assert held is not None, message
    return held.group(1).split()


@pytest.mark.parametrize(
    "files, leg", [(five_bar_files, ("motor_1", "elbow_1")), (spherical_wrist_files, ("motor_1", "elbow_1", "wrist_1"))]
)
def test_a_motor_that_never_moves_is_named_and_the_advice_works(files, leg, tmp_path):
    """40 poses give rows to spare, but motor 1 never moves: the refusal names its leg's parameters
    and asks for poses that move them, not for more poses like these; holding the parameters it
    names at nominal then gives a calibration."""
    machine = Mechanism.load(*files(tmp_path))
    sliders = workspace_actuators(machine, 40, np.random.default_rng(0))
    sliders[:, 0] = sliders[0, 0]
    measurements = measure(machine, sliders)
    with pytest.raises(IdentificationError) as refusal:
        calibrate_closed_loop(machine, measurements)
    message = str(refusal.value)
    assert re.match(
        r"40 poses give 240 residual rows for (\d+) identifiable parameters and identify only (\d+): "
        r"these poses do not excite ",
        message,
    ), message
    assert "add poses" not in message and "poses that move them, over more of the workspace" in message
    held = _advised_holding(message)
    assert held and all(name.split(".dt[")[0] in leg for name in held), held
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calibration = calibrate_closed_loop(machine, measurements, CalibrationOptions(fixed=held))
    assert calibration.converged and not set(held) & set(calibration.base.names)


def test_barely_identifiable_directions_are_not_answered_with_more_poses(mechanism):
    """With positions only, the M machine has directions at 1.2e-4 of the strongest even on poses spread
    over the whole workspace; at a rank tolerance of 1e-4 these 40 poses miss two of them. More poses
    are no remedy, and the refusal says so; the parameters it says to hold make the fit go through."""
    sliders = workspace_actuators(mechanism, 40, np.random.default_rng(1))
    measurements = measure(mechanism, sliders, position_only=True)
    with pytest.raises(IdentificationError) as refusal:
        calibrate_closed_loop(mechanism, measurements, CalibrationOptions(rank_tolerance=1e-4, outlier_sigma=None))
    message = str(refusal.value)
    assert message.startswith("40 poses give 120 residual rows for 53 identifiable parameters and identify only ")
    assert "barely identifiable on any poses" in message and "more poses are unlikely to help" in message
    assert "add poses" not in message
    held = _advised_holding(message)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calibration = calibrate_closed_loop(
            mechanism, measurements, CalibrationOptions(fixed=held, rank_tolerance=1e-4, outlier_sigma=None)
        )
    assert calibration.converged and not set(held) & set(calibration.base.names)


def test_a_shortfall_says_what_is_missing_and_the_advice_that_can_help():
    """The refusal's wording, from its counts and ranks (rank tolerance 1e-8, so a direction is
    marginal below a ratio of 1e-6): more poses only when the rows are fewer than the identifiable
    parameters (each pose's rows named); else the first eight missing names, "..." beyond, and either
    "barely identifiable" (no more missing than marginal directions of the reference set) or "do not
    excite"; the holding advice with the parameters found to work, or without them."""
    shortfall, tolerance = closed_loop._shortfall, 1e-8

    def ranks(rank, ratios=()):
        return SimpleNamespace(rank=rank, r_diag_ratio=np.r_[np.ones(rank - len(ratios)), ratios])

    head = "1 poses give 6 residual rows for 24 identifiable parameters and identify only 6"
    assert shortfall(ranks(6), ranks(24), ["a"], [], (1, 6), tolerance) == (
        f"{head}: add poses (each gives 6 rows), spread over the workspace"
    )
    names = [f"p{k}" for k in range(9)]
    exact = shortfall(ranks(22), ranks(24), names[:8], [], (4, 24), tolerance)
    assert exact == (
        "4 poses give 24 residual rows for 24 identifiable parameters and identify only 22: these poses do "
        "not excite p0, p1, p2, p3, p4, p5, p6, p7; poses that move them, over more of the workspace, "
        "would, or hold the weakest at nominal (--fix)"
    )
    more = shortfall(ranks(22), ranks(24), names, ["p0", "p8"], (4, 24), tolerance)
    assert more.endswith(
        "p6, p7 ...; poses that move them, over more of the workspace, would, or hold them at nominal (--fix p0 p8)"
    )
    assert shortfall(ranks(22), ranks(24, (1e-7, 9.99e-7)), names[:2], ["p0"], (4, 24), tolerance) == (
        "4 poses give 24 residual rows for 24 identifiable parameters and identify only 22: p0, p1 are barely "
        "identifiable on any poses (on poses spread over the whole workspace, within 100 times the rank "
        "tolerance), so more poses are unlikely to help: hold them at nominal (--fix p0)"
    )
    # Two missing against two marginal reference directions (a ratio at 1e-6 is not marginal).
    for ratios, barely in (((1e-7, 9.99e-7), True), ((1e-7, 1e-6), False), ((1e-7,), False)):
        message = shortfall(ranks(22), ranks(24, ratios), names[:2], [], (4, 24), tolerance)
        assert ("barely identifiable on any poses" in message) is barely
        assert ("these poses do not excite p0, p1;" in message) is not barely


def test_measurement_that_does_not_assemble_is_refused(mechanism):
    study = simulate_study(mechanism, n_poses=12, n_holdout=0, seed=16)
    actuators = study.measurements.actuators.copy()
    actuators[4] = [-0.3, 0.3, 0.0, 0.0]  # the five-bar cannot close
    bad = PoseMeasurements(actuators, study.measurements.poses)
    with pytest.raises(IdentificationError, match="does not assemble"):
        calibrate_closed_loop(mechanism, bad)


def test_measurements_validate_their_shape():
    with pytest.raises(InvalidInputError, match="actuator rows for 2 poses"):
        PoseMeasurements(np.zeros((3, 4)), (pin.SE3.Identity(), pin.SE3.Identity()))
    with pytest.raises(InvalidInputError, match="non-finite"):
        PoseMeasurements(np.full((1, 4), np.nan), (pin.SE3.Identity(),))


def test_idle_chains_cross_validate_a_noise_free_calibration(mechanism, noise_free_1mm):
    """The paper's cross-validation with the idle chains: encoders on the B2/B4 hinges, unused by
    the fit, are predicted 10x better by the calibrated model (offsets removed)."""
    from m3t1r.app.reporting import IDLE_CHAIN_JOINTS, passive_joint_residuals

    study = simulate_study(
        mechanism, n_poses=50, n_holdout=200, seed=11, options=StudyOptions(passive_joints=IDLE_CHAIN_JOINTS)
    )
    _, calibration = noise_free_1mm  # same seed, same truth and poses
    actuators = study.measurements.actuators
    before = passive_joint_residuals(mechanism, actuators, IDLE_CHAIN_JOINTS, study.passive_readings)
    after = passive_joint_residuals(calibration.mechanism, actuators, IDLE_CHAIN_JOINTS, study.passive_readings)
    assert np.all(after.rms < before.rms / 10)
    assert np.all(after.rms < 1e-4)


@pytest.mark.parametrize(
    "options,message",
    [
        ({"outlier_sigma": -5.0}, "outlier_sigma: None or 0"),
        ({"outlier_sigma": 0.5}, "outlier_sigma: None or 0"),
        ({"outlier_sigma": float("nan")}, "^outlier_sigma: expected a finite number, got nan$"),  # not "number finite"
        ({"fixed": "q12"}, r"fixed parameter: expected a list of names such as \['q12'\], got 'q12'"),
        ({"max_iterations": 0}, "max_iterations: expected a whole number of at least 1"),
    ],
)
def test_calibration_options_are_checked_at_the_call(mechanism, options, message):
    """A negative or NaN gate silently disabled outlier rejection; fixed="q12" was read letter by letter."""
    study = simulate_study(mechanism, n_poses=12, n_holdout=0, seed=16)
    with pytest.raises(InvalidInputError, match=message):
        calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(**options))


def test_calibration_options_hold_their_settings_in_one_form():
    """Whole numbers as int, names as a tuple, priors as a read-only mapping, groups as an array, a
    zero outlier gate as None (keep every pose)."""
    options = CalibrationOptions(
        max_iterations=np.int64(7), fixed=["q11", "q12"], priors={"q12.dt[0]": 1e-3}, groups=[0, 0, 1], outlier_sigma=0
    )
    assert options.max_iterations == 7 and type(options.max_iterations) is int
    assert options.fixed == ("q11", "q12") and options.outlier_sigma is None
    assert dict(options.priors) == {"q12.dt[0]": 1e-3}
    with pytest.raises(TypeError):
        options.priors["q11.dt[0]"] = 1.0  # type: ignore[index]
    assert isinstance(options.groups, np.ndarray) and options.groups.tolist() == [0, 0, 1]
    assert CalibrationOptions(outlier_sigma=3).outlier_sigma == 3.0


def test_complex_readings_and_seeds_below_zero_are_refused(mechanism):
    study = simulate_study(mechanism, n_poses=4, n_holdout=0, seed=16)
    with pytest.raises(InvalidInputError, match="actuator readings: complex values given"):
        PoseMeasurements(study.measurements.actuators + 1j, study.measurements.poses)
    with pytest.raises(InvalidInputError, match="seed: expected a whole number of at least 0"):
        simulate_study(mechanism, n_poses=4, n_holdout=0, seed=-1)


# ==================================================================================================
# Fit pieces, refusals and the predicted standard deviation, exactly
#
# The predicted pose standard deviation is checked against finite differences of the calibrated machine
# (exact) and against the held-out error from both sides (statistical); the LM stop rule is checked on the
# iteration that fired it.
# ==================================================================================================


NOISE = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)


@pytest.fixture(scope="module")
def noisy(mechanism):
    study = simulate_study(mechanism, n_poses=50, n_holdout=100, seed=13, noise=NOISE)
    return study, calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=NOISE))


def _fitted_names(calibration) -> tuple[str, ...]:
    """Names of the covariance's rows and columns."""
    fitted = getattr(calibration, "fitted", None)
    return tuple(fitted) if fitted is not None else tuple(calibration.base.names)


def _finite_difference_pose_std(calibration, sliders):
    """sqrt(trace(J C J^T)) for position and orientation, J from central differences of the
    calibrated machine's FK over its fitted machine parameters (of its own error model)."""
    mechanism = calibration.mechanism
    error_model = ClosedLoopErrorModel(mechanism, calibration.error_model.placements)
    index = {name: i for i, name in enumerate(error_model.names)}
    names = _fitted_names(calibration)
    machine = [k for k, name in enumerate(names) if name in index]
    covariance = np.asarray(calibration.covariance)[np.ix_(machine, machine)]
    reference = ClosedLoopSolver(mechanism)
    starts = [reference.forward(s).q for s in sliders]
    eps = 1e-7
    position_rows = np.zeros((len(sliders), 3, len(machine)))
    rotation_rows = np.zeros((len(sliders), 3, len(machine)))
    for column, k in enumerate(machine):
        moved = []
        for sign in (1.0, -1.0):
            vector = np.zeros(error_model.n_parameters)
            vector[index[names[k]]] = sign * eps
            solver = ClosedLoopSolver(mechanism.with_model(error_model.perturbed(mechanism.model, vector)))
            moved.append([solver.forward(s, q_init=q).pose for s, q in zip(sliders, starts)])
        for i, (plus, minus) in enumerate(zip(*moved)):
            position_rows[i, :, column] = (plus.translation - minus.translation) / (2 * eps)
            rotation_rows[i, :, column] = pin.log3(minus.rotation.T @ plus.rotation) / (2 * eps)
    return (
        np.sqrt(np.einsum("nij,jk,nik->n", position_rows, covariance, position_rows)),
        np.sqrt(np.einsum("nij,jk,nik->n", rotation_rows, covariance, rotation_rows)),
    )


def test_predicted_pose_std_is_the_covariance_through_finite_differences(noisy):
    """sqrt(trace(J C J^T)) with J from central differences of the calibrated machine's FK."""
    study, calibration = noisy
    sliders = study.holdout_actuators[:3]
    expected_position, expected_rotation = _finite_difference_pose_std(calibration, sliders)
    predicted = predicted_pose_std(calibration, sliders)
    np.testing.assert_allclose(predicted.position, expected_position, rtol=1e-3)
    np.testing.assert_allclose(predicted.rotation, expected_rotation, rtol=1e-3)
    # 600 slider sets, in blocks of 512 poses: every set predicted as alone.
    many = predicted_pose_std(calibration, np.tile(sliders, (200, 1)))
    np.testing.assert_allclose(many.position, np.tile(predicted.position, 200), rtol=1e-9)
    np.testing.assert_allclose(many.rotation, np.tile(predicted.rotation, 200), rtol=1e-9)
    # No slider set: nothing predicted; a set beyond a limit: refused, naming it.
    empty = predicted_pose_std(calibration, np.zeros((0, 4)))
    assert empty.position.shape == empty.rotation.shape == (0,)
    with pytest.raises(
        InvalidInputError,
        match=r"^slider set 1 .* does not assemble on the machine from its home: "
        r"actuator 'q11' = 9 is beyond its joint limit",
    ):
        predicted_pose_std(calibration, np.vstack((sliders[:1], [[9.0, 0.0, 0.0, 0.0]])))
    with pytest.raises(InvalidInputError) as error:
        predicted_pose_std(dataclasses.replace(calibration, problem=None), sliders)
    assert str(error.value) == "a predicted std needs a calibration made by calibrate_closed_loop"


def test_predicted_std_of_a_fit_with_its_own_placements(noisy):
    """A fit over the joint placements alone, listed last joint first (a custom error model whose
    columns are not the default model's): both predictions propagate its own parameters, as finite
    differences of its FK say."""
    study, _ = noisy
    mechanism = study.nominal
    joints_only = ClosedLoopErrorModel(
        mechanism, tuple(Placement.joint(mechanism.model.names[j]) for j in reversed(range(1, mechanism.model.njoints)))
    )
    calibration = calibrate_closed_loop(
        mechanism, study.measurements, CalibrationOptions(noise=NOISE), error_model=joints_only
    )
    sliders = study.holdout_actuators[:2]
    expected_position, expected_rotation = _finite_difference_pose_std(calibration, sliders)
    for predicted in (predicted_pose_std(calibration, sliders), predicted_measurement_std(calibration, sliders)):
        np.testing.assert_allclose(predicted.position, expected_position, rtol=1e-3)
        np.testing.assert_allclose(predicted.rotation, expected_rotation, rtol=1e-3)


def test_predicted_pose_std_in_blocks_is_the_one_block_result(noisy, monkeypatch):
    """Blocks of 2 poses (5 poses: a partial last block) give what one block gives."""
    study, calibration = noisy
    sliders = study.holdout_actuators[:5]
    whole = predicted_pose_std(calibration, sliders)
    monkeypatch.setattr(closed_loop, "_BLOCK", 2)
    blocks = predicted_pose_std(calibration, sliders)
    np.testing.assert_allclose(blocks.position, whole.position, rtol=1e-12)
    np.testing.assert_allclose(blocks.rotation, whole.rotation, rtol=1e-12)
    assert np.all(whole.position > 0) and np.all(whole.rotation > 0)


def test_held_out_error_matches_the_prediction_from_both_sides(noisy):
    """One draw of the parameter error: RMS ratio held-out / predicted in (0.6, 1.6), not just <= 1.3."""
    study, calibration = noisy
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    predicted = predicted_pose_std(calibration, study.holdout_actuators)
    assert 0.6 < after.position_rms / predicted.position_rms < 1.6
    assert 0.6 < after.rotation_rms / predicted.rotation_rms < 1.6
    assert 2e-6 < predicted.position_rms < 2e-5 and 2e-6 < predicted.rotation_rms < 4e-5


def test_lm_stops_on_the_statistical_significance_rule(noisy):
    """The last accepted step lowered 1/2 chi^2 by at most step_significance * s^2 (0.01 s^2)."""
    study, calibration = noisy
    lm = calibration.lm
    assert lm.converged and lm.termination == "cost"
    history = np.array(lm.cost_history)
    rows = 6 * len(study.measurements)
    dof = rows - len(_fitted_names(calibration))
    s2_before = 2.0 * history[:-1] / dof  # a-posteriori variance before each accepted step
    decrease = history[:-1] - history[1:]
    assert decrease[-1] <= 0.01 * s2_before[-1]
    assert np.all(decrease[:-1] > 0.01 * s2_before[:-1])  # and it did not fire earlier
    assert 6 <= lm.iterations <= 30
    # The fit sits at the noise: chi^2 / dof near one, from both sides.
    assert 0.7 < 2.0 * history[-1] / dof < 1.4


# --------------------------------------------------------------------------------------------------
# Small pieces, without a fit: names, residual rows, iteration cap, refusals before the fit


def test_setup_parameter_names():
    frame = tuple(f"measurement_frame.dt[{k}]" for k in range(6))
    marker = tuple(f"marker.dt[{k}]" for k in range(6))
    assert setup_parameter_names(False, False, False) == () and setup_parameter_names(False, False, True) == ()
    assert setup_parameter_names(True, False, False) == frame == setup_parameter_names(True, False, True)
    assert setup_parameter_names(False, True, False) == marker
    assert setup_parameter_names(False, True, True) == marker[:3]
    assert setup_parameter_names(True, True, False) == frame + marker
    assert setup_parameter_names(True, True, True) == frame + marker[:3]


@pytest.mark.parametrize("position_only", [False, True])
def test_residual_rows_are_the_derivatives_for_spatial_twists(position_only):
    """e = [p - p_meas; log3(R_meas^T R)] and de/dxi for pose <- exp6(xi) pose, by central differences."""
    rng = np.random.default_rng(60)
    poses = np.array([pin.SE3.Random().homogeneous for _ in range(3)])
    measured = poses @ np.array([pin.exp6(rng.normal(0.0, 0.1, 6)).homogeneous for _ in range(3)])
    rotations = None if position_only else measured[:, :3, :3]
    residual, rows = _residual_rows_batch(poses, measured[:, :3, 3], rotations)
    k = 3 if position_only else 6
    assert residual.shape == (3, k) and rows.shape == (3, k, 6)
    np.testing.assert_allclose(residual[:, :3], poses[:, :3, 3] - measured[:, :3, 3], atol=1e-15)
    if not position_only:
        expected = [pin.log3(m[:3, :3].T @ p[:3, :3]) for p, m in zip(poses, measured)]
        np.testing.assert_allclose(residual[:, 3:], expected, atol=1e-12)
    numeric = np.empty_like(rows)
    for j in range(6):
        xi = np.zeros(6)
        xi[j] = 1e-7
        plus = _residual_rows_batch(pin.exp6(xi).homogeneous @ poses, measured[:, :3, 3], rotations, False)
        minus = _residual_rows_batch(pin.exp6(-xi).homogeneous @ poses, measured[:, :3, 3], rotations, False)
        assert plus[1] is None and minus[1] is None
        numeric[:, :, j] = (plus[0] - minus[0]) / 2e-7
    np.testing.assert_allclose(rows, numeric, atol=1e-7)
    again, none = _residual_rows_batch(poses, measured[:, :3, 3], rotations, with_jacobian=False)
    assert none is None
    np.testing.assert_array_equal(again, residual)


def test_iteration_cap_is_60_or_5_per_parameter():
    assert [default_iterations(n) for n in (0, 11, 12, 13, 56, 100)] == [60, 60, 60, 65, 280, 500]


#: One Levenberg-Marquardt iteration, LM's own defaults otherwise: the pipeline's steps on tiny problems.
ONE_STEP = LMSettings(max_iterations=1, cost_tolerance=1e-12, absolute_cost_tolerance=0.0, initial_damping=1e-3)


def test_rms():
    residual = np.array([[3.0, 4.0, 0.0, 1.0, 2.0, 2.0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    assert pose_error_rms(residual) == pytest.approx((np.sqrt(12.5), np.sqrt(4.5)), rel=1e-15)
    position, rotation = pose_error_rms(residual[:, :3])
    assert position == pytest.approx(np.sqrt(12.5), rel=1e-15) and np.isnan(rotation) and type(rotation) is float


@pytest.fixture(scope="module")
def few_poses(mechanism):
    actuators = workspace_actuators(mechanism, 4, np.random.default_rng(61))
    return measure(mechanism, actuators)


def test_names_and_priors_are_checked_before_any_fit(mechanism, few_poses):
    for sigma in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(InvalidInputError) as error:
            calibrate_closed_loop(mechanism, few_poses, CalibrationOptions(priors={"q11.dt[0]": sigma}))
        assert str(error.value) == "prior of 'q11.dt[0]': sigma must be a positive number (m, rad or rad/Nm)"
    with pytest.raises(InvalidInputError, match=r"^prior: 'nope' is neither a parameter \(e.g. q11.dt\[0\]\)"):
        calibrate_closed_loop(mechanism, few_poses, CalibrationOptions(priors={"nope": 1.0}))
    with pytest.raises(InvalidInputError, match=r"^fixed parameter: 'nope' is neither a parameter"):
        calibrate_closed_loop(mechanism, few_poses, CalibrationOptions(fixed=["nope"]))


def test_identifiable_count_on_the_reference_poses(mechanism, few_poses, monkeypatch):
    """`structural_rank` from an empty cache (a fit would find it filled by earlier fits): 56 of 204
    with full poses (docs/results.md), 53 with positions only, fewer with fixed columns or a looser
    tolerance; the marker's rotation shows at a loose tolerance. Each distinct key is counted once."""
    cache = {}
    monkeypatch.setattr(closed_loop, "_STRUCTURAL_RANKS", cache)
    error_model = ClosedLoopErrorModel(mechanism)
    full = ClosedLoopProblem(error_model, few_poses, np.arange(204), CalibrationOptions(noise=NOISE))
    positions = ClosedLoopProblem(
        error_model,
        measure(mechanism, few_poses.actuators, position_only=True),
        np.arange(204),
        CalibrationOptions(noise=NOISE),
    )
    identity, turned = pin.SE3.Identity(), pin.SE3(pin.utils.rotate("x", 0.5), np.array([0.0, 0.0, 0.05]))
    assert closed_loop.structural_rank(full, identity, [], 1e-8) == 56
    assert closed_loop.structural_rank(full, identity, list(range(12)), 1e-8) == 52
    with_setup = ClosedLoopProblem(
        error_model,
        few_poses,
        np.arange(216),
        CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True),
    )
    assert closed_loop.structural_rank(with_setup, turned, [], 1e-8) == 56
    assert closed_loop.structural_rank(positions, identity, [], 1e-8) == 53
    assert closed_loop.structural_rank(positions, identity, [], 1e-3) == 47
    assert closed_loop.structural_rank(positions, turned, [], 1e-3) == 48
    assert len(cache) == 6 and sorted(base.rank for base in cache.values()) == [47, 48, 52, 53, 56, 56]
    assert closed_loop.structural_rank(positions, identity, [], 1e-3) == 47 and len(cache) == 6


def _assert_same_selection(selection, expected):
    """The same choices, and scores equal to rounding (the rows come from other products, and exact
    data score at rounding level)."""
    assert (selection.indices, selection.order, selection.tied) == (expected.indices, expected.order, expected.tied)
    np.testing.assert_allclose(selection.path, expected.path, rtol=1e-9, atol=1e-20)
    np.testing.assert_allclose(
        [selection.press, selection.press_all], [expected.press, expected.press_all], rtol=1e-9, atol=1e-20
    )


def test_selection_scores_the_fit_linearised_at_the_estimate(noisy):
    """Forward selection on r - J x at the estimate over the inliers; all kept: the same fit."""
    _, calibration = noisy
    problem = copy.copy(calibration.problem)
    state = calibration.lm.state
    r, J = problem.evaluate(state, problem.columns)  # every pose row (the fit holds them compressed)
    rows = len(problem.weights)
    keep = np.repeat(problem.active, 6)
    columns = problem.columns.copy()
    expected = forward_selection(
        J[:rows][keep],
        (r[:rows] - J[:rows] @ state.accumulated[columns])[keep],
        6,
        range(len(columns)),
        np.flatnonzero(columns >= 204),  # the setup's columns, forced: none here
    )
    selection, result, _ = pipeline.select_parameters(problem, calibration.start, calibration.lm, calibration.settings)
    _assert_same_selection(selection, expected)
    if len(selection.indices) == len(columns):
        assert result is calibration.lm
    else:
        np.testing.assert_array_equal(problem.columns, columns[list(selection.indices)])
        assert result.state.model is not None and result is not calibration.lm


def test_refine_reselects_at_the_estimate_and_continues(noisy):
    """At the estimate more directions are identifiable: the columns grow and LM continues from the
    estimate (capped here at 2 iterations); a tolerance that finds no more returns the fit as is."""
    _, calibration = noisy
    problem = copy.copy(calibration.problem)
    problem.active = problem.active.copy()
    problem.active[0] = False  # an outlier's rows: zero weights in the re-selection
    assert pipeline.refine(problem, calibration.lm, 0.5, 2) is calibration.lm
    problem.active = calibration.problem.active
    np.testing.assert_array_equal(problem.columns, calibration.problem.columns)
    before = len(problem.columns)
    # The iterate's setup is carried into the refit (here a marker 0.1 mm off: a higher cost).
    moved = MeasurementSetup(marker=pin.SE3(np.eye(3), np.array([1e-4, 0.0, 0.0])))
    start = dataclasses.replace(calibration.lm, state=dataclasses.replace(calibration.lm.state, setup=moved))
    refined = pipeline.refine(problem, start, 1e-7, 2)
    assert len(problem.columns) > before and refined.iterations <= 2
    shifted = problem.residual(dataclasses.replace(calibration.lm.state, setup=moved))
    assert refined.cost_history[0] == pytest.approx(0.5 * shifted @ shifted, rel=1e-9)
    assert refined.cost_history[0] > 10 * calibration.lm.cost_history[-1]
    np.testing.assert_array_equal(
        refined.state.accumulated[:204] != 0.0,
        np.isin(np.arange(204), problem.columns) | (calibration.lm.state.accumulated[:204] != 0),
    )


def test_prior_rows_and_a_trial_that_does_not_assemble(mechanism, few_poses):
    """Prior rows x_c / sigma_c in the columns' order; a trial step whose model did not assemble
    (model None, nothing accumulated) is all infinite, prior rows included (it used to raise
    TypeError with priors)."""
    error_model = ClosedLoopErrorModel(mechanism)
    in_memory = CalibrationOptions(noise=NOISE, stream_jacobian=False)
    problem = ClosedLoopProblem(
        error_model, few_poses, np.array([0, 5, 7]), in_memory, priors={5: 0.5, 7: 2e-3, 100: 1.0}
    )
    accumulated = np.zeros(204)
    accumulated[[0, 5, 7]] = [1.0, 1e-3, -4e-3]
    values, jacobian = problem.prior_rows(
        ClosedLoopState(mechanism.model, np.zeros((0, 20)), np.zeros((0, 4, 4)), accumulated=accumulated)
    )
    np.testing.assert_allclose(values, [1e-3 / 0.5, -4e-3 / 2e-3], rtol=1e-15)
    np.testing.assert_array_equal(jacobian, [[0.0, 2.0, 0.0], [0.0, 0.0, 500.0]])
    failed = ClosedLoopState(None, np.zeros((0, 20)), np.zeros((0, 4, 4)))
    residual = problem.residual(failed)
    assert residual.shape == (4 * 6 + 2,) and np.all(residual == np.inf)
    r, J = problem.residual_and_jacobian(failed)
    assert r.shape == (26,) and np.all(r == np.inf)
    np.testing.assert_array_equal(J, np.zeros((26, 3)))
    plain = ClosedLoopProblem(error_model, few_poses, np.array([0, 5, 7]), in_memory)
    assert plain.residual(failed).shape == (24,)
    streamed = ClosedLoopProblem(error_model, few_poses, np.array([0, 5, 7]), priors={5: 0.5, 7: 2e-3})
    r, J = streamed.residual_and_jacobian(failed)  # the compressed rows: 3 columns + 1, and the 2 priors
    assert r.shape == (6,) and np.all(r == np.inf) and J.shape == (6, 3)


def test_the_streamed_fit_is_the_in_memory_fit(mechanism):
    """Levenberg-Marquardt on the QR of [J r] accumulated pose block by pose block (memory bounded by
    the parameters) and on every row of J give the same fit to rounding: the same base, outliers and
    selection, the calibrated machines within 1e-9 m and rad of each other, the same uncertainty and
    the same cross-validation. 600 poses span two blocks of the streamed accumulation."""
    frame = pin.SE3(pin.utils.rotate("z", 0.7), np.array([1.2, -0.4, 0.3]))
    study = simulate_study(
        mechanism,
        n_poses=600,
        n_holdout=50,
        seed=23,
        noise=NOISE,
        options=StudyOptions(setup=MeasurementSetup(frame=frame), outliers=2),
    )
    options = CalibrationOptions(noise=NOISE, estimate_frame=True, select=True, priors={"q12.dt[0]": 1e-3})
    fits = {
        stream: calibrate_closed_loop(
            mechanism, study.measurements, dataclasses.replace(options, stream_jacobian=stream)
        )
        for stream in (True, False)
    }
    streamed, in_memory = fits[True], fits[False]
    assert len(streamed.problem.residual_and_jacobian(streamed.lm.state)[0]) <= len(streamed.fitted) + 2
    assert len(in_memory.problem.residual_and_jacobian(in_memory.lm.state)[0]) >= 600 * 6  # every pose row
    assert streamed.base.indices == in_memory.base.indices and streamed.fitted == in_memory.fitted
    assert streamed.outliers == in_memory.outliers == tuple(study.outliers)
    assert streamed.lm.iterations == in_memory.lm.iterations and streamed.converged and in_memory.converged
    between = pose_errors(streamed.mechanism, in_memory.mechanism, study.holdout_actuators)
    assert between.position_max < 1e-9 and between.rotation_max < 1e-9
    frames = streamed.setup.frame.actInv(in_memory.setup.frame)
    assert np.linalg.norm(frames.translation) < 1e-9 and np.linalg.norm(pin.log3(frames.rotation)) < 1e-9
    np.testing.assert_allclose(
        streamed.covariance, in_memory.covariance, rtol=1e-6, atol=1e-9 * np.abs(in_memory.covariance).max()
    )
    assert streamed.variance_factor == pytest.approx(in_memory.variance_factor, rel=1e-9)
    assert streamed.rms_after == pytest.approx(in_memory.rms_after, rel=1e-9)
    a, b = cross_validate(streamed, folds=4), cross_validate(in_memory, folds=4)
    np.testing.assert_allclose(a.errors.position, b.errors.position, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(a.errors.rotation, b.errors.rotation, rtol=1e-6, atol=1e-12)
    # Each fold's prediction is the Gauss-Newton step on every other row (the outliers' weigh nothing)
    # from the estimate, applied to the fold's rows and unwhitened: the same over both pose blocks.
    problem = in_memory.problem
    r, J = problem.residual_and_jacobian(in_memory.lm.state)
    assert J.shape[0] == 600 * 6  # no prior on a fitted column
    inliers, fold = inlier_folds(problem.active, 4, 0)[:2]
    pose_fold = np.full(600, -1)
    pose_fold[inliers] = fold
    row_fold = np.repeat(pose_fold, 6)
    predicted = np.zeros(len(r))
    for f in range(4):
        held = row_fold == f
        step = -np.linalg.lstsq(J[~held], r[~held], rcond=None)[0]
        predicted[held] = (r[held] + J[held] @ step) / problem.weights[held]
    expected = predicted.reshape(-1, 6)[inliers]
    np.testing.assert_allclose(b.errors.position, np.linalg.norm(expected[:, :3], axis=1), rtol=1e-6)
    np.testing.assert_allclose(b.errors.rotation, np.linalg.norm(expected[:, 3:], axis=1), rtol=1e-6)


def test_a_fit_from_a_state_whose_factor_was_taken_evaluates_no_pose_for_its_first_step(mechanism, few_poses):
    """After `jacobian_factor` at a state (the base choice, at the start), the streamed problem over
    any columns at that state, restarted, comes from that factor without evaluating a pose: the same
    cost, gradient and normal equations as evaluated afresh, priors included. Once the weights change
    (a pose flagged) the factor no longer applies and the poses are evaluated again."""
    error_model = ClosedLoopErrorModel(mechanism)
    problem = ClosedLoopProblem(error_model, few_poses, np.array([0, 5, 7, 30, 101]), priors={5: 0.5})
    evaluations = []
    problem.on_evaluate = lambda: evaluations.append(1)
    offset = 1e-3 * np.random.default_rng(62).normal(size=204)
    start = problem.assemble(error_model.perturbed(mechanism.model, offset), None)

    def normal_equations(state):
        r, J = problem.residual_and_jacobian(problem.restart(state))
        return r @ r, J.T @ r, J.T @ J

    fresh = normal_equations(start)
    assert len(evaluations) == 1 and np.linalg.norm(fresh[1]) > 0.0
    factor = problem.jacobian_factor(start)
    assert factor.shape[1] == 204 and len(evaluations) == 2
    reused = normal_equations(start)
    assert len(evaluations) == 2  # no pose evaluated
    for a, b in zip(reused, fresh):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())
    problem.active = np.array([True, False, True, True])
    flagged = normal_equations(start)
    assert len(evaluations) == 3 and flagged[0] < fresh[0]


def test_campaign_with_setup_outliers_priors_and_fixed_parameters(mechanism, monkeypatch):
    """One fit with every option: the frame and marker estimated (the setup's 12 columns kept),
    one gross outlier flagged, a placement held, a prior, progress reported; then cross-validation
    and its refusals."""
    frame = pin.SE3(pin.utils.rotate("z", 2.0), np.array([1.5, -0.8, 0.3]))
    marker = pin.SE3(pin.utils.rotate("y", 0.3), np.array([0.01, 0.0, 0.05]))
    study = simulate_study(
        mechanism,
        n_poses=40,
        n_holdout=0,
        seed=17,
        noise=NOISE,
        options=StudyOptions(setup=MeasurementSetup(frame, marker), outliers=1),
    )
    calls, runs = [], []
    fit = pipeline.fit
    monkeypatch.setattr(pipeline, "fit", lambda *args: runs.append(fit(*args)) or runs[-1])
    calibration = calibrate_closed_loop(
        mechanism,
        study.measurements,
        CalibrationOptions(
            noise=NOISE,
            setup=MeasurementSetup(marker=pin.SE3(np.eye(3), marker.translation)),
            estimate_frame=True,
            estimate_marker=True,
            fixed=["q11"],
            priors={"q12.dt[0]": 1e-3},
            select=True,
        ),
        progress=lambda: calls.append(1),
    )
    assert calibration.selection is not None and len(calibration.selection.indices) == len(calibration.fitted)
    assert calibration.outliers == tuple(study.outliers) and len(calibration.outliers) == 1
    assert calibration.converged is bool(calibration.lm.converged) is True
    setup_names = setup_parameter_names(True, True, False)
    assert set(setup_names[:6]) <= set(calibration.fitted) and len(set(setup_names) & set(calibration.fitted)) >= 11
    assert not any(name.startswith("q11.") for name in calibration.fitted)
    assert all(calibration.parameters[f"q11.dt[{k}]"] == 0.0 for k in range(6))
    assert list(calibration.parameters) == list(calibration.error_model.names)
    assert list(calibration.std) == list(calibration.error_model.names) + list(setup_names)
    assert all(calibration.std[name] > 0.0 for name in calibration.fitted)
    assert 0.6 < calibration.variance_factor < 1.6
    assert calibration.rms_after[0] < 3e-5 < 1e-3 < calibration.rms_before[0]
    assert len(calls) >= calibration.lm.iterations + 1
    # The iterations are those of every LM run: the base fit, the refit without the outlier, the rest.
    assert len(runs) >= 2 and calibration.iterations == sum(run.iterations for run in runs)
    for estimate, truth in ((calibration.setup.frame, frame), (calibration.setup.marker, marker)):
        difference = truth.actInv(estimate)
        assert np.linalg.norm(difference.translation) < 1e-2 and np.linalg.norm(pin.log3(difference.rotation)) < 1e-2
    validation = cross_validate(calibration, folds=3)
    assert validation.folds == 3 and validation.errors.position.shape == (39,)
    assert validation.errors.position_mean < 5e-5 and validation.errors.rotation_mean < 1e-4
    with pytest.raises(InvalidInputError) as error:
        cross_validate(calibration, folds=20)
    assert str(error.value) == "cross-validation: 20 folds need at least 40 inlier poses"
    with pytest.raises(InvalidInputError, match="^cross-validation: 1 folds need at least 2 inlier poses$"):
        cross_validate(calibration, folds=1)
    with pytest.raises(InvalidInputError) as error:
        cross_validate(dataclasses.replace(calibration, problem=None))
    assert str(error.value) == "cross_validate needs a calibration made by calibrate_closed_loop"


def test_pose_errors_name_the_first_set_that_does_not_assemble(mechanism, few_poses):
    good = few_poses.actuators[:2]
    bad = np.vstack((good, [[-0.3, 0.3, 0.0, 0.0]], good))  # the five-bar cannot close at row 2
    with pytest.raises(
        InvalidInputError,
        match=rf"^pose_errors: actuator set 2 does not assemble on "
        rf"{mechanism.urdf_path.name}: ",
    ):
        pose_errors(mechanism, mechanism, bad)
    same = pose_errors(mechanism, mechanism, good)
    assert same.position.shape == (2,) and np.all(same.position == 0.0) and np.all(same.rotation == 0.0)
    empty = pose_errors(mechanism, mechanism, np.zeros((0, 4)))
    assert empty.position.shape == (0,) and empty.rotation.shape == (0,)


def test_registered_setup_is_exact_on_the_nominal_machine(mechanism):
    frame = pin.SE3(pin.utils.rotate("z", 2.0) @ pin.utils.rotate("x", 0.3), np.array([1.5, -0.8, 0.3]))
    marker = pin.SE3(pin.utils.rotate("y", 0.3), np.array([0.01, 0.0, 0.05]))
    actuators = workspace_actuators(mechanism, 6, np.random.default_rng(62))
    error_model = ClosedLoopErrorModel(mechanism)
    axes_unknown = pin.SE3(np.eye(3), marker.translation)
    for position_only in (False, True):
        measurements = measure(mechanism, actuators, position_only=position_only, setup=MeasurementSetup(frame, marker))
        problem = ClosedLoopProblem(
            error_model,
            measurements,
            np.arange(204),
            CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True),
        )
        start = problem.assemble(mechanism.model, None)
        both = _registered_setup(problem, start, MeasurementSetup(marker=axes_unknown), True, True)
        np.testing.assert_allclose(both.frame.homogeneous, frame.homogeneous, atol=1e-9)
        expected_marker = axes_unknown if position_only else marker  # no orientation data: axes as given
        np.testing.assert_allclose(both.marker.homogeneous, expected_marker.homogeneous, atol=1e-9)
        frame_only = _registered_setup(problem, start, MeasurementSetup(marker=axes_unknown), True, False)
        np.testing.assert_allclose(frame_only.frame.homogeneous, frame.homogeneous, atol=1e-9)
        assert frame_only.marker == axes_unknown
        given = MeasurementSetup(frame, axes_unknown)
        marker_only = _registered_setup(problem, start, given, False, True)
        assert marker_only.frame == frame
        np.testing.assert_allclose(marker_only.marker.homogeneous, expected_marker.homogeneous, atol=1e-9)
        assert _registered_setup(problem, start, given, False, False) == given


def test_outlier_rounds_and_too_few_poses_left(mechanism):
    """4 exact poses of the nominal machine, one 1 m off: with 18 columns the 3 left are too few
    (18 rows), with 17 the pose is dropped and the fit restarted from the start."""
    actuators = workspace_actuators(mechanism, 4, np.random.default_rng(63))
    exact = measure(mechanism, actuators)
    poses = list(exact.poses)
    poses[1] = pin.SE3(poses[1].rotation, poses[1].translation + np.array([1.0, 0.0, 0.0]))
    measurements = PoseMeasurements(exact.actuators, tuple(poses))
    problem = ClosedLoopProblem(
        ClosedLoopErrorModel(mechanism), measurements, np.arange(18), CalibrationOptions(noise=NOISE)
    )
    start = problem.assemble(mechanism.model, None)
    fit = SimpleNamespace(state=start)
    with pytest.raises(IdentificationError) as error:
        pipeline.reject_outliers(problem, start, fit, 5.0, ONE_STEP)
    assert str(error.value) == "1 of 4 poses are outliers: too few poses are left to fit the model"
    assert problem.active.all()
    problem.columns = np.arange(17)
    result, iterations = pipeline.reject_outliers(problem, start, fit, 5.0, ONE_STEP)
    np.testing.assert_array_equal(problem.active, [True, False, True, True])
    assert result is not fit and iterations == result.iterations <= 1 and result.state.model is not None
    assert pipeline.reject_outliers(problem, start, result, 1e9, ONE_STEP)[0].state is not None  # gate: none
    np.testing.assert_array_equal(problem.active, [True, True, True, True])


def test_covariance_std_and_variance_factor_from_the_final_jacobian(noisy):
    """(J^T J)^-1 of the whitened Jacobian at the solution, its diagonal's square root per fitted
    name (zero for the others), and chi^2 over rows less fitted columns."""
    _, calibration = noisy
    problem = calibration.problem
    r, J = problem.residual_and_jacobian(calibration.lm.state)
    covariance = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(calibration.covariance, covariance, rtol=1e-6, atol=1e-6 * np.abs(covariance).max())
    std = np.array([calibration.std[name] for name in calibration.fitted])
    np.testing.assert_allclose(std, np.sqrt(np.diag(covariance)), rtol=1e-6)
    assert all(calibration.std[name] == 0.0 for name in set(problem.names) - set(calibration.fitted))
    dof = np.count_nonzero(problem.weights) - len(problem.columns)  # the measured inlier rows, no priors
    assert calibration.variance_factor == pytest.approx(r @ r / dof, rel=1e-12)


# --------------------------------------------------------------------------------------------------
# Fast pieces of the fit, each on a few exact poses or a stand-in problem (kept small: a module's
# mutation run reruns every test that reaches a changed function)


class _Recorder:
    """Stands in for `levenberg_marquardt`: records its call and returns a given result."""

    def __init__(self, result):
        self.result, self.calls = result, []

    def __call__(self, problem, state, settings):
        self.calls.append((problem, state, settings))
        return self.result


def test_fit_passes_its_settings_and_refuses_a_model_that_does_not_assemble(monkeypatch):
    problem, state = object(), object()
    settings = LMSettings(max_iterations=7, cost_tolerance=0.25, absolute_cost_tolerance=1e-3)
    good = SimpleNamespace(cost=2.0)
    recorder = _Recorder(good)
    monkeypatch.setattr(pipeline, "levenberg_marquardt", recorder)
    assert pipeline.fit(problem, state, settings) is good
    assert len(recorder.calls) == 1
    called_problem, called_state, called_settings = recorder.calls[0]
    assert called_problem is problem and called_state is state and called_settings is settings
    recorder.result = SimpleNamespace(cost=float("inf"))  # every pose row infinite: a model that does not assemble
    with pytest.raises(IdentificationError) as error:
        pipeline.fit(problem, state, settings)
    assert str(error.value) == "calibration ended on a model that does not assemble"


def test_refine_options_weights_and_an_equal_rank(mechanism, few_poses, monkeypatch):
    """`pipeline.refine` re-selects on the whitened Jacobian of every parameter at the iterate (zero rows
    for outliers), keeps the fit when no more columns are identifiable (equal count included), and
    otherwise continues with damped LM (1e-9, cost tolerance 1e-14) from the iterate's model,
    assembly, setup and accumulated steps; the weak-excitation warning is silenced."""
    error_model = ClosedLoopErrorModel(mechanism)
    problem = ClosedLoopProblem(error_model, few_poses, np.arange(3), CalibrationOptions(noise=NOISE))
    problem.active = np.array([True, False, True, True])
    setup = MeasurementSetup(marker=pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.02])))
    accumulated = np.linspace(-1e-4, 1e-4, 204)
    state = problem.assemble(mechanism.model, None, setup=setup, accumulated=accumulated)
    _, jacobian = problem.evaluate(state, np.arange(204))  # whitened, zero rows for the outlier
    assert np.all(jacobian[6:12] == 0.0) and np.any(jacobian[:6] != 0.0)
    expected = select_base_parameters(jacobian, problem.names, rank_tolerance=1e-3)
    assert 3 < expected.rank < 24
    result = SimpleNamespace(state=state)
    continued_fit = SimpleNamespace(cost=0.0)
    recorder = _Recorder(continued_fit)
    monkeypatch.setattr(pipeline, "levenberg_marquardt", recorder)
    problem.columns = np.arange(expected.rank)  # as many as identifiable: the fit is kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert pipeline.refine(problem, result, 1e-3, 5) is result
        assert recorder.calls == [] and len(problem.columns) == expected.rank
        problem.columns = np.arange(3)
        assert pipeline.refine(problem, result, 1e-3, 5) is continued_fit
    np.testing.assert_array_equal(problem.columns, expected.indices)
    ((called_problem, continued, settings),) = recorder.calls
    assert called_problem is problem
    assert settings == LMSettings(
        max_iterations=5, cost_tolerance=1e-14, absolute_cost_tolerance=0.0, initial_damping=1e-9
    )
    assert (settings.step_tolerance, settings.gradient_tolerance, settings.unit_damping) == (1e-12, 1e-12, False)
    assert continued.model is state.model and continued.setup is setup and continued.accumulated is accumulated
    for q, q0 in zip(continued.configurations, state.configurations):
        np.testing.assert_allclose(q, q0, atol=1e-12)
    assert continued.whitened is None
    # Orientation weighted 1e5 below position: the re-selection warns of weak excitation, which
    # the refinement silences.
    weak = ClosedLoopProblem(
        error_model, few_poses, np.arange(3), CalibrationOptions(noise=TrackerNoise(position=1e-5, rotation=1.0))
    )
    with pytest.warns(PoorExcitationWarning):
        select_base_parameters(weak.evaluate(state, np.arange(204))[1], weak.names, rank_tolerance=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert pipeline.refine(weak, result, 1e-9, 5) is continued_fit


def test_select_parameters_scores_the_pose_rows_only(mechanism, few_poses, monkeypatch):
    """With priors the residual has prior rows after the pose rows; the selection sees the pose
    rows of the inliers, at r - J x."""
    error_model = ClosedLoopErrorModel(mechanism)
    columns = np.array([0, 1, 2, 6, 7, 8])
    in_memory = CalibrationOptions(noise=NOISE, stream_jacobian=False)  # every row, to read them
    problem = ClosedLoopProblem(error_model, few_poses, columns, in_memory, priors={1: 1e-3, 7: 2e-3})
    problem.active = np.array([True, True, False, True])
    accumulated = np.zeros(204)
    accumulated[columns] = [1e-5, -2e-5, 3e-5, 1e-5, 0.0, -1e-5]
    state = problem.assemble(mechanism.model, None, accumulated=accumulated)
    r, J = problem.residual_and_jacobian(dataclasses.replace(state))
    assert len(r) == 24 + 2
    keep = np.repeat(problem.active, 6)
    expected = forward_selection(J[:24][keep], (r[:24] - J[:24] @ accumulated[columns])[keep], 6, range(6), [])
    fits = []
    fit = pipeline.fit
    monkeypatch.setattr(pipeline, "fit", lambda *args: fits.append(args[1]) or fit(*args))
    start = dataclasses.replace(state)
    problem.residual_and_jacobian(start)  # the start's Jacobian cached over every column
    selection, result, iterations = pipeline.select_parameters(problem, start, SimpleNamespace(state=state), ONE_STEP)
    assert iterations == result.iterations
    _assert_same_selection(selection, expected)
    np.testing.assert_array_equal(problem.columns, columns[list(selection.indices)])
    assert len(selection.indices) < len(columns)
    (refit_start,) = fits  # a smaller set is refitted from the start, its Jacobian evaluated afresh
    assert refit_start is not start and refit_start.whitened is None and start.whitened is not None


def _problem_with_a_1_m_outlier(mechanism, columns: np.ndarray) -> ClosedLoopProblem:
    """Four exact poses of the nominal machine, pose 1 moved 1 m along x, fitting `columns`."""
    exact = measure(mechanism, workspace_actuators(mechanism, 4, np.random.default_rng(63)))
    poses = list(exact.poses)
    poses[1] = pin.SE3(poses[1].rotation, poses[1].translation + np.array([1.0, 0.0, 0.0]))
    return ClosedLoopProblem(
        ClosedLoopErrorModel(mechanism),
        PoseMeasurements(exact.actuators, tuple(poses)),
        columns,
        CalibrationOptions(noise=NOISE),
    )


def test_outlier_refit_starts_from_a_fresh_jacobian(mechanism):
    """The start's whitened residual and Jacobian, cached by the first fit with every pose, are not
    reused by the refit without the outlier: its first cost is that of the inliers."""
    problem = _problem_with_a_1_m_outlier(mechanism, np.arange(17))
    start = problem.assemble(mechanism.model, None)
    problem.residual_and_jacobian(start)  # cached with the outlier's rows
    fit = SimpleNamespace(state=dataclasses.replace(start))  # the first fit's final iterate (released)
    result, _ = pipeline.reject_outliers(problem, start, fit, 5.0, ONE_STEP)
    np.testing.assert_array_equal(problem.active, [True, False, True, True])
    assert fit.state.whitened is None and start.whitened is not None
    inliers = problem.residual(start)
    assert result.cost_history[0] == pytest.approx(0.5 * inliers @ inliers, rel=1e-12)
    assert result.cost_history[0] < 1.0


class _StandInProblem:
    """The parts of a problem that `pipeline.summarise` and `closed_loop._calibration` read, with a
    chosen final Jacobian: two poses of six rows, the second flagged, `measured` rows of the first seen."""

    def __init__(self, error_model, final_rows, measured, columns, blocks):
        self.error_model, self.columns, self.active = error_model, columns, np.array([True, False])
        self.names = error_model.names + setup_parameter_names(True, False, False)
        self.priors = {int(columns[0]): 1.0, int(columns[1]): 2.0}
        self.seen = np.zeros((2, 6), dtype=bool)
        self.seen[0, :measured] = True
        self.seen[1] = True
        self.n_points = 0
        self.final_rows, self.blocks_by_state = final_rows, blocks

    def residual_and_jacobian(self, state):
        return self.final_rows

    def raw_blocks(self, state):
        return self.blocks_by_state[id(state)]


def test_calibration_summary_from_a_known_final_jacobian(mechanism):
    """Covariance V S^-2 V^T over the singular values above 1e-12 of the largest (a 5e-10 one of 1e3
    is dropped, 0.5 is kept), std per fitted name and zero elsewhere, chi^2 / (measured inlier rows +
    prior rows - columns) and nan when that is not positive, the inliers' RMS before and after, the
    outliers, the identified machine errors; the result carries the fit's pieces as given."""
    error_model = ClosedLoopErrorModel(mechanism)
    rng = np.random.default_rng(64)
    u, _ = np.linalg.qr(rng.normal(size=(14, 3)))
    v, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    singular = np.array([1e3, 0.5, 5e-10])
    jacobian = (u * singular) @ v.T
    residual = rng.normal(size=14)
    errors = np.zeros(204)
    errors[[3, 40, 100]] = [2e-5, -1e-5, 3e-5]
    model = error_model.perturbed(mechanism.model, errors)
    setup = MeasurementSetup(frame=pin.SE3(np.eye(3), np.array([0.1, 0.0, 0.0])))
    end = ClosedLoopState(model, np.zeros((0, 20)), np.zeros((0, 4, 4)), setup)
    start = ClosedLoopState(mechanism.model, np.zeros((0, 20)), np.zeros((0, 4, 4)))
    before = np.arange(12.0).reshape(2, 6)
    after = before / 1000
    columns = np.array([3, 40, 205])
    base, selection = object(), object()
    lm = SimpleNamespace(state=end)
    outcomes, problems = {}, {}
    for measured in (6, 3, 2, 1):  # 2 prior rows, 3 columns: dof 5, 2, 1, 0
        problems[measured] = _StandInProblem(
            error_model, (residual, jacobian), measured, columns, {id(start): before, id(end): after}
        )
        summary = pipeline.summarise(problems[measured], start, lm, (base, selection, 7), ONE_STEP)
        outcomes[measured] = closed_loop._calibration(mechanism, problems[measured], summary)
    calibration = outcomes[6]
    expected = (v[:, :2] / singular[:2] ** 2) @ v[:, :2].T
    np.testing.assert_allclose(calibration.covariance, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    std = np.array([calibration.std[name] for name in calibration.problem.names])
    expected_std = np.zeros(210)
    expected_std[columns] = np.sqrt(np.diag(expected))
    np.testing.assert_allclose(std, expected_std, rtol=1e-9)
    assert list(calibration.std) == list(error_model.names) + list(setup_parameter_names(True, False, False))
    assert calibration.fitted == ("q11.dt[3]", error_model.names[40], "measurement_frame.dt[1]")
    assert calibration.variance_factor == pytest.approx(residual @ residual / 5, rel=1e-12)
    assert outcomes[3].variance_factor == pytest.approx(residual @ residual / 2, rel=1e-12)
    assert outcomes[2].variance_factor == pytest.approx(residual @ residual, rel=1e-12)
    assert np.isnan(outcomes[1].variance_factor) and type(outcomes[1].variance_factor) is float
    assert calibration.rms_before == pose_error_rms(before[:1]) and calibration.rms_after == pose_error_rms(after[:1])
    assert calibration.outliers == (1,) and type(calibration.outliers[0]) is int
    assert list(calibration.parameters) == list(error_model.names)
    np.testing.assert_allclose([calibration.parameters[name] for name in error_model.names], errors, atol=1e-12)
    assert calibration.setup is setup and calibration.error_model is error_model
    assert calibration.base is base and calibration.selection is selection and calibration.lm is lm
    assert calibration.problem is problems[6] and calibration.iterations == 7 and calibration.settings is ONE_STEP
    for placement, expected_placement in zip(calibration.mechanism.model.jointPlacements, model.jointPlacements):
        np.testing.assert_allclose(placement.homogeneous, expected_placement.homogeneous, atol=1e-15)


def test_identifiable_count_weights_fixed_columns_and_the_setup_gauge(mechanism, few_poses):
    """`structural_rank` whitens the reference Jacobian with the problem's own noise weights
    (orientation 1e5 times less trusted than position: 56 still), zeroes the fixed columns (all but
    4 machine columns fixed: 8 with the frame), and keeps the setup's columns first: 29 at a
    tolerance of 1e-5 with position 1e5 times less trusted than orientation (30 without that gauge)."""
    error_model = ClosedLoopErrorModel(mechanism)
    identity, turned = pin.SE3.Identity(), pin.SE3(pin.utils.rotate("x", 0.5), np.array([0.0, 0.0, 0.05]))
    skewed = ClosedLoopProblem(
        error_model, few_poses, np.arange(204), CalibrationOptions(noise=TrackerNoise(position=1e-5, rotation=1.0))
    )
    assert closed_loop.structural_rank(skewed, identity, [], 1e-8) == 56
    frame = ClosedLoopProblem(
        error_model, few_poses, np.arange(210), CalibrationOptions(noise=NOISE, estimate_frame=True)
    )
    assert closed_loop.structural_rank(frame, identity, list(range(200)), 1e-8) == 8
    both = ClosedLoopProblem(
        error_model,
        few_poses,
        np.arange(216),
        CalibrationOptions(noise=TrackerNoise(position=1.0, rotation=1e-5), estimate_frame=True, estimate_marker=True),
    )
    assert closed_loop.structural_rank(both, turned, [], 1e-5) == 29


def test_problem_layout_weights_and_measured_frames(mechanism, few_poses):
    """Names, setup slots, per-row noise weights, the measured positions and rotations, and the
    defaults (no setup columns, every pose active, no progress hook)."""
    error_model = ClosedLoopErrorModel(mechanism)
    plain = ClosedLoopProblem(
        error_model, few_poses, np.arange(204), CalibrationOptions(noise=TrackerNoise(position=1e-5, rotation=4e-5))
    )
    assert plain.names == error_model.names and plain.frame_slot is None and plain.marker_slot is None
    assert plain.n_machine == 204 and plain.priors == {} and plain.on_evaluate is None
    assert plain.active.dtype == bool and plain.active.tolist() == [True] * 4
    np.testing.assert_array_equal(plain.noise_weights, np.tile([1 / 1e-5] * 3 + [1 / 4e-5] * 3, 4))
    np.testing.assert_array_equal(plain.weights, plain.noise_weights)
    measured = np.array([pose.homogeneous for pose in few_poses.poses])
    np.testing.assert_array_equal(plain.measured_positions, measured[:, :3, 3])
    np.testing.assert_array_equal(plain.measured_rotations, measured[:, :3, :3])
    positions = measure(mechanism, few_poses.actuators[:1], position_only=True)
    marker = ClosedLoopProblem(
        error_model, positions, np.arange(207), CalibrationOptions(noise=NOISE, estimate_marker=True)
    )
    assert marker.names == error_model.names + ("marker.dt[0]", "marker.dt[1]", "marker.dt[2]")
    assert marker.frame_slot is None and marker.marker_slot == 204 and marker.measured_rotations is None
    np.testing.assert_array_equal(marker.noise_weights, [1 / NOISE.position] * 3)
    np.testing.assert_array_equal(marker.measured_positions, [positions.poses[0].translation])
    both = ClosedLoopProblem(
        error_model,
        few_poses,
        np.arange(216),
        CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True),
        priors={3: 0.5},
    )
    assert both.frame_slot == 204 and both.marker_slot == 210 and len(both.names) == 216 and both.priors == {3: 0.5}
    frame = ClosedLoopProblem(
        error_model, few_poses, np.arange(210), CalibrationOptions(noise=NOISE, estimate_frame=True)
    )
    assert frame.frame_slot == 204 and frame.marker_slot is None and len(frame.names) == 210
    both.active = np.array([True, False, True, True])
    np.testing.assert_array_equal(
        both.weights, np.tile([1 / NOISE.position] * 3 + [1 / NOISE.rotation] * 3, 4) * np.repeat(both.active, 6)
    )


class _FakeSolver:
    """Stands in for ClosedLoopSolver: records forward_batch's arguments, returns q = start + 1
    (start: q_init, or zeros from home), poses filled with each row's first slider, and the
    failures set on the class."""

    calls: list = []
    failures: tuple = ()

    def __init__(self, mechanism):
        self.mechanism = mechanism

    def forward_batch(self, actuators, q_init=None):
        _FakeSolver.calls.append((actuators, q_init))
        start = np.zeros((len(actuators), 20)) if q_init is None else q_init
        return SimpleNamespace(
            q=start + 1.0, poses=actuators[:, :1, None] * np.ones((1, 4, 4)), failures=_FakeSolver.failures
        )


def test_assemble_solves_every_pose_in_one_batch_from_its_start(mechanism, few_poses, monkeypatch):
    problem = ClosedLoopProblem(
        ClosedLoopErrorModel(mechanism), few_poses, np.arange(204), CalibrationOptions(noise=NOISE)
    )
    monkeypatch.setattr(closed_loop, "ClosedLoopSolver", _FakeSolver)
    _FakeSolver.calls, _FakeSolver.failures = [], ()
    starts = np.repeat(np.arange(4.0)[:, None], 20, axis=1)
    state = problem.assemble(mechanism.model, starts)
    ((actuators, q_init),) = _FakeSolver.calls
    assert actuators is few_poses.actuators and q_init is starts
    assert state.model is mechanism.model and state.setup == MeasurementSetup()
    np.testing.assert_array_equal(state.configurations, starts + 1.0)
    np.testing.assert_array_equal(state.poses[:, 2, 3], few_poses.actuators[:, 0])
    np.testing.assert_array_equal(state.accumulated, np.zeros(204))
    assert state.whitened is None
    setup, accumulated = MeasurementSetup(marker=pin.SE3(np.eye(3), np.ones(3))), np.ones(204)
    state = problem.assemble(mechanism.model, None, setup, accumulated)
    assert _FakeSolver.calls[-1][1] is None and state.setup is setup and state.accumulated is accumulated
    # The first failing pose named; a slider beyond its limit stays an input error; no state is made.
    _FakeSolver.failures = (
        RowFailure(2, "forward kinematics: branch change", BranchChangeError),
        RowFailure(3, "actuator 'q11' = 9 is beyond its joint limit", InvalidInputError),
    )
    with pytest.raises(IdentificationError) as error:
        problem.assemble(mechanism.model, starts)
    assert str(error.value) == "measured pose 2 (0-based) does not assemble: forward kinematics: branch change"
    _FakeSolver.failures = _FakeSolver.failures[1:]
    with pytest.raises(
        InvalidInputError, match=r"^measured pose 3 \(0-based\) does not assemble: actuator 'q11' = 9 is"
    ):
        problem.assemble(mechanism.model, starts)
    _FakeSolver.failures = ()


def test_retract_moves_model_and_setup_and_assembles_from_the_iterate(mechanism, few_poses, monkeypatch):
    """A step on machine, frame and marker columns: the model perturbed by the machine part, the
    frame and marker right-multiplied by exp6 of theirs (3 marker components with positions
    only), the steps accumulated; assembly starts from the iterate's configurations; a model that
    does not assemble gives a state without model or poses."""
    error_model = ClosedLoopErrorModel(mechanism)
    positions = measure(mechanism, few_poses.actuators, position_only=True)
    columns = np.array([2, 30, 204, 209, 210, 212])
    problem = ClosedLoopProblem(
        error_model, positions, columns, CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True)
    )
    frame = pin.SE3(pin.utils.rotate("z", 0.3), np.array([0.1, 0.2, 0.3]))
    marker = pin.SE3(pin.utils.rotate("x", 0.2), np.array([0.0, 0.0, 0.05]))
    configurations = np.repeat(0.01 * np.arange(4.0)[:, None], 20, axis=1)
    accumulated = np.linspace(0.0, 1.0, 213)
    state = ClosedLoopState("model", configurations, np.ones((4, 4, 4)), MeasurementSetup(frame, marker), accumulated)
    step = np.array([1e-3, -2e-3, 0.01, 0.02, 0.03, -0.04])
    calls = []
    monkeypatch.setattr(error_model, "perturbed", lambda model, vector: ("perturbed", model, vector.copy()))
    monkeypatch.setattr(problem, "assemble", lambda *args: calls.append(args) or "assembled")
    assert problem.retract(state, step) == "assembled"
    ((model, start, setup, total),) = calls
    vector = np.zeros(213)
    vector[columns] = step
    assert model[:2] == ("perturbed", "model")
    np.testing.assert_array_equal(model[2], vector[:204])
    assert start is configurations
    np.testing.assert_allclose(setup.frame.homogeneous, (frame * pin.exp6(vector[204:210])).homogeneous, atol=1e-15)
    dm = np.r_[0.03, 0.0, -0.04, 0.0, 0.0, 0.0]
    np.testing.assert_allclose(setup.marker.homogeneous, (marker * pin.exp6(dm)).homogeneous, atol=1e-15)
    np.testing.assert_array_equal(total, accumulated + vector)
    # No setup columns: the setup is carried as is.
    machine_only = ClosedLoopProblem(error_model, positions, np.array([2, 30]), CalibrationOptions(noise=NOISE))
    monkeypatch.setattr(machine_only, "assemble", lambda *args: calls.append(args) or "assembled")
    calls.clear()
    machine_only.retract(dataclasses.replace(state, accumulated=np.zeros(204)), step[:2])
    assert calls[0][2] is state.setup

    def fails(*args):
        raise IdentificationError("no assembly")

    monkeypatch.setattr(problem, "assemble", fails)
    failed = problem.retract(state, step)
    assert failed.model is None and failed.configurations is configurations and failed.poses.shape == (0, 4, 4)
    np.testing.assert_allclose(failed.setup.frame.homogeneous, setup.frame.homogeneous, atol=1e-15)
    np.testing.assert_allclose(failed.setup.marker.homogeneous, setup.marker.homogeneous, atol=1e-15)
    np.testing.assert_array_equal(failed.accumulated, accumulated + vector)


def test_evaluate_in_blocks_reduced_with_extra_rows_and_progress(mechanism, few_poses, monkeypatch):
    """Blocks of 3 poses give what one block gives: the whitened residual and Jacobian (zero rows
    for an outlier); extra rows are appended for the caller; reduce=True gives R with
    R^T R = J^T J; each evaluation calls the progress hook once."""
    error_model = ClosedLoopErrorModel(mechanism)
    measurements = measure(mechanism, np.vstack((few_poses.actuators, few_poses.actuators[:3])))
    columns = np.array([0, 7, 33, 100, 203, 204, 209, 210, 215])
    problem = ClosedLoopProblem(
        error_model, measurements, columns, CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True)
    )
    problem.active = np.array([True, True, False, True, True, True, True])
    calls = []
    problem.on_evaluate = lambda: calls.append(1)
    setup = MeasurementSetup(
        pin.SE3(pin.utils.rotate("z", 0.4), np.array([0.2, 0.0, 0.1])),
        pin.SE3(pin.utils.rotate("y", 0.2), np.array([0.0, 0.01, 0.05])),
    )
    state = problem.assemble(mechanism.model, None, setup=setup)
    whole = problem.evaluate(state, columns)
    assert len(calls) == 1 and whole[1].shape == (42, 9)
    monkeypatch.setattr(closed_loop, "_BLOCK", 3)
    blocks = problem.evaluate(state, columns, extra_rows=2)
    assert len(calls) == 2 and blocks[0].shape == (44,) and blocks[1].shape == (44, 9)
    np.testing.assert_array_equal(blocks[0][:42], whole[0])
    np.testing.assert_array_equal(blocks[1][:42], whole[1])
    # The sensitivities' own FK pass against the batch assembly's poses: equal to rounding.
    np.testing.assert_allclose(
        whole[0], problem.pose_residuals(state).reshape(-1) * problem.weights, rtol=1e-12, atol=1e-9
    )
    assert np.all(whole[1][12:18] == 0.0) and np.all(whole[1][:12].any(axis=0))
    residual, factor = problem.evaluate(state, columns, reduce=True)
    assert len(calls) == 3
    np.testing.assert_array_equal(residual, whole[0])
    assert factor.shape == (9, 9)
    # One pose, 6 rows for 9 columns: a factor of 6 rows (nothing stacked on an empty start).
    one = ClosedLoopProblem(
        error_model,
        measure(mechanism, few_poses.actuators[:1]),
        columns,
        CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True),
    )
    assert one.evaluate(one.assemble(mechanism.model, None, setup=setup), columns, reduce=True)[1].shape == (6, 9)
    np.testing.assert_allclose(
        factor.T @ factor, whole[1].T @ whole[1], rtol=1e-9, atol=1e-9 * np.abs(whole[1]).max() ** 2
    )


def test_outlier_rounds_refit_only_when_the_flagged_set_changes(mechanism, monkeypatch):
    """One refit when the flagged set changes (then it is stable), none when it is stable from the
    start; a set that never settles stops after 5 refits."""
    problem = _problem_with_a_1_m_outlier(mechanism, np.arange(3))
    start = problem.assemble(mechanism.model, None)
    fits = []
    fit = pipeline.fit
    monkeypatch.setattr(pipeline, "fit", lambda *args: fits.append((args[1], args[1].whitened)) or fit(*args))
    first, _ = pipeline.reject_outliers(
        problem, start, SimpleNamespace(state=dataclasses.replace(start)), 5.0, ONE_STEP
    )
    assert len(fits) == 1 and fits[0][0] is not start and fits[0][1] is None
    np.testing.assert_array_equal(problem.active, [True, False, True, True])
    assert pipeline.reject_outliers(problem, start, first, 5.0, ONE_STEP) == (first, 0) and len(fits) == 1
    flips = iter([[False, False, False, False], [False, True, False, False]] * 3)
    monkeypatch.setattr(pipeline, "outlier_poses", lambda blocks, sigma, rows: (np.array(next(flips)), 1.0))
    pipeline.reject_outliers(problem, start, first, 5.0, ONE_STEP)
    assert len(fits) == 1 + 5


def test_structural_rank_cache_keys_on_the_noise_ratio_and_the_data_kind(mechanism, few_poses, monkeypatch):
    """Orientation trusted 1e5 times less than position (56) or more (52): different entries though
    the weights' product is the same; positions only (53) and full poses (56) with equal sigmas:
    different entries though the weight ratio is the same."""
    monkeypatch.setattr(closed_loop, "_STRUCTURAL_RANKS", {})
    error_model = ClosedLoopErrorModel(mechanism)
    identity = pin.SE3.Identity()
    positions = measure(mechanism, few_poses.actuators, position_only=True)
    rank = closed_loop.structural_rank
    counts = [
        rank(
            ClosedLoopProblem(error_model, measurements, np.arange(204), CalibrationOptions(noise=noise)),
            identity,
            [],
            1e-8,
        )
        for measurements, noise in (
            (few_poses, TrackerNoise(position=1e-5, rotation=1.0)),
            (few_poses, TrackerNoise(position=1.0, rotation=1e-5)),
            (few_poses, TrackerNoise(position=1e-5, rotation=1e-5)),
            (positions, TrackerNoise(position=1e-5, rotation=1e-5)),
        )
    ]
    assert counts == [56, 52, 56, 53]


def _retract_differences(problem, state, eps=1e-6):
    """Central differences of the pose residual rows along retract's update of each column."""
    numeric = np.empty((problem.pose_residuals(state).size, len(problem.columns)))
    for j in range(len(problem.columns)):
        step = np.zeros(len(problem.columns))
        step[j] = eps
        plus, minus = problem.retract(state, step), problem.retract(state, -step)
        numeric[:, j] = (problem.pose_residuals(plus) - problem.pose_residuals(minus)).reshape(-1) / (2 * eps)
    return numeric


@pytest.mark.parametrize("position_only", [False, True])
def test_jacobian_is_the_derivative_of_the_residual_along_retract(mechanism, few_poses, position_only):
    """Every column of evaluate's Jacobian (machine, measurement frame, marker) against central
    differences of the pose residual along retract's update of that parameter."""
    error_model = ClosedLoopErrorModel(mechanism)
    measurements = measure(mechanism, few_poses.actuators[:3], position_only=position_only)
    n_names = 204 + 6 + (3 if position_only else 6)
    columns = np.array([1, 40, 150, 203] + list(range(204, n_names)))
    problem = ClosedLoopProblem(
        error_model, measurements, columns, CalibrationOptions(noise=NOISE, estimate_frame=True, estimate_marker=True)
    )
    setup = MeasurementSetup(
        pin.SE3(pin.utils.rotate("z", 0.4) @ pin.utils.rotate("x", 0.2), np.array([0.2, -0.1, 0.1])),
        pin.SE3(pin.utils.rotate("y", 0.3), np.array([0.01, 0.02, 0.05])),
    )
    state = problem.assemble(mechanism.model, None, setup=setup)
    residual, jacobian = problem.evaluate(state, columns)
    np.testing.assert_allclose(
        residual, problem.pose_residuals(state).reshape(-1) * problem.weights, rtol=1e-12, atol=1e-9
    )
    jacobian = jacobian / problem.weights[:, None]  # every weight positive here
    np.testing.assert_allclose(jacobian, _retract_differences(problem, state), atol=1e-6)


_OFFSETS = np.array([[0.05, -0.02, 0.03], [-0.04, 0.03, 0.02], [0.01, 0.05, -0.01]])  # [m], platform frame
_TRACKER = pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 2.0), np.array([3.0, -1.0, 0.5]))


def _points_of(mechanism, actuators, hidden=()):
    """Three points on the platform seen through `_TRACKER` at `actuators`, exactly, with the
    (pose, point) pairs in `hidden` not seen (NaN)."""
    platform = assembled_from_home(mechanism, actuators).poses
    points = MeasurementSetup(_TRACKER, points=tuple(map(tuple, _OFFSETS))).measured_points(platform)
    for pose, point in hidden:
        points[pose, point] = np.nan
    first = [pin.SE3(np.eye(3), row[np.isfinite(row[:, 0])][0]) for row in points]
    return PoseMeasurements(actuators, tuple(first), True, points)


def test_point_jacobian_is_the_derivative_of_the_residual_along_retract(mechanism):
    """With three points per pose (one hidden): each seen point's residual is its model position
    minus the sighting, a hidden one's is zero, and every column of evaluate's Jacobian (machine,
    measurement frame, the points' offsets) matches central differences along retract."""
    actuators = workspace_actuators(mechanism, 3, np.random.default_rng(64))
    measurements = _points_of(mechanism, actuators, hidden=[(1, 2)])
    columns = np.array([1, 40, 150, 203] + list(range(204, 204 + 6 + 9)))
    problem = ClosedLoopProblem(
        ClosedLoopErrorModel(mechanism), measurements, columns, CalibrationOptions(noise=NOISE, estimate_frame=True)
    )
    assert problem.names[210:213] == ("marker.p1.dt[0]", "marker.p1.dt[1]", "marker.p1.dt[2]")
    moved = _OFFSETS + [[1e-3, 0.0, 0.0], [0.0, -2e-3, 0.0], [0.0, 0.0, 3e-3]]
    setup = MeasurementSetup(_TRACKER, points=tuple(map(tuple, moved)))
    state = problem.assemble(mechanism.model, None, setup=setup)
    expected = np.where(np.isfinite(measurements.points), setup.measured_points(state.poses) - measurements.points, 0)
    np.testing.assert_allclose(problem.pose_residuals(state).reshape(-1), expected.reshape(-1), atol=1e-12)
    offsets_in_tracker = (moved - _OFFSETS) @ state.poses[0, :3, :3].T @ _TRACKER.rotation.T
    np.testing.assert_allclose(expected[0], offsets_in_tracker, atol=1e-12)  # R_F R_platform (p_k' - p_k)
    residual, jacobian = problem.evaluate(state, columns)
    seen = problem.weights > 0
    assert np.count_nonzero(~seen) == 3 and not np.any(residual[~seen]) and not np.any(jacobian[~seen])
    np.testing.assert_allclose(residual[seen], expected.reshape(-1)[seen] / NOISE.position, rtol=1e-12)
    jacobian = jacobian[seen] / problem.weights[seen, None]
    np.testing.assert_allclose(jacobian, _retract_differences(problem, state)[seen], atol=1e-6)


def test_registered_points_are_the_mean_sightings_through_the_registered_frame(mechanism):
    """The start of a fit of points, on the machine that made them (some sightings hidden). With the
    tracker's frame given, each offset is the mean of its sightings mapped into the platform frame,
    (F T_platform)^-1 p, exact. With the frame estimated, five alternations of the frame's rigid
    registration and those means: the offsets are the means through the final frame, and the start
    explains the sightings to 2.2 mm RMS (from 4.9 mm after one alternation; LM refines the rest: a
    yaw-only platform leaves frame and offsets a gauge that many more alternations only creep along)."""
    actuators = workspace_actuators(mechanism, 12, np.random.default_rng(65))
    measurements = _points_of(mechanism, actuators, hidden=[(0, 0), (3, 1), (4, 2), (7, 0)])
    seen = np.isfinite(measurements.points[:, :, 0])
    reflector = pin.SE3(np.eye(3), np.array([0.07, -0.02, 0.03]))  # a marker of one-point data: points have none
    for estimate_frame, given in ((False, MeasurementSetup(_TRACKER, reflector)), (True, MeasurementSetup())):
        options = CalibrationOptions(noise=NOISE, estimate_frame=estimate_frame, setup=given)
        problem = ClosedLoopProblem(ClosedLoopErrorModel(mechanism), measurements, np.arange(204), options)
        start = problem.assemble(mechanism.model, None, setup=given)
        registered = closed_loop._registered_points(problem, start, given, estimate_frame)
        offsets = np.array(registered.points)
        assert registered.marker == pin.SE3.Identity()
        np.testing.assert_array_equal(problem.point_offsets, offsets)
        in_platform = np.einsum(
            "nji,npj->npi",
            (registered.frame.homogeneous @ start.poses)[:, :3, :3],
            measurements.points - (registered.frame.homogeneous @ start.poses)[:, None, :3, 3],
        )
        means = [in_platform[seen[:, k], k].mean(axis=0) for k in range(3)]
        np.testing.assert_allclose(offsets, means, atol=1e-12)
        start.setup = registered
        rms = np.sqrt(np.mean(problem.pose_residuals(start).reshape(12, 3, 3)[seen] ** 2))
        if not estimate_frame:
            assert registered.frame == _TRACKER
            np.testing.assert_allclose(offsets, _OFFSETS, atol=1e-12)
            assert rms < 1e-12
        else:
            assert 2.0e-3 < rms < 2.5e-3


# --------------------------------------------------------------------------------------------------
# Refinement through the whole calibration (`refine=True`): the fit, its columns and its iterations


def test_refinement_continues_over_the_columns_identifiable_at_the_estimate(mechanism, noisy):
    """refine=True re-selects at the estimate (tolerance 1e-7): more columns are fitted, LM continues
    for at most `refine_iterations`, and the iterations add up; a tolerance that finds no more
    columns (0.5) returns the fit without refinement, its iterations unchanged."""
    study, plain = noisy
    refined = calibrate_closed_loop(
        mechanism, study.measurements, CalibrationOptions(noise=NOISE, refine=True, refine_iterations=2)
    )
    assert len(refined.fitted) > len(plain.fitted)  # chosen anew at the estimate, no gauge kept first
    assert 1 <= refined.lm.iterations <= 2
    assert refined.iterations == plain.iterations + refined.lm.iterations
    assert refined.base.rank == plain.base.rank and refined.outliers == plain.outliers
    assert plain.selection is None and refined.selection is None  # no model selection asked for
    loose = calibrate_closed_loop(
        mechanism,
        study.measurements,
        CalibrationOptions(noise=NOISE, refine=True, refine_rank_tolerance=0.5, refine_iterations=2),
    )
    assert loose.fitted == plain.fitted and loose.iterations == plain.iterations
    assert loose.variance_factor == pytest.approx(plain.variance_factor, rel=1e-12)


# --------------------------------------------------------------------------------------------------
# Outlier rounds with several points per pose: each pose judged on the rows it measured


class _PointsProblem:
    """Ten poses of three points (nine rows), the last pose seeing its first point only: what
    `pipeline.reject_outliers` reads of a problem, with chosen whitened blocks."""

    def __init__(self, last_pose_chi2):
        self.n_points, self.columns = 3, np.arange(4)
        self.seen = np.ones((10, 9), dtype=bool)
        self.seen[9, 3:] = False
        self.blocks = np.where(self.seen, 1.0, 0.0)
        self.blocks[9, :3] = np.sqrt(last_pose_chi2 / 3.0)
        self.active = np.ones(10, dtype=bool)

    def pose_blocks(self, state):
        return self.blocks

    def release(self, state):
        pass

    def restart(self, state):
        return state


def test_a_pose_seeing_fewer_points_is_judged_on_its_own_rows(monkeypatch):
    """A pose seeing one point of three has 3 degrees of freedom, not 9: a chi^2 between the two
    gates (scaled by the robust variance factor, 9 / median chi^2_9 here) flags it, and the fit is
    redone without it from the start; judged on 9 rows it would be kept."""
    scale2 = 9.0 / (2.0 * float(scipy.special.gammaincinv(4.5, 0.5)))
    gate_3, gate_9 = outlier_gate(5.0, 3) * scale2, outlier_gate(5.0, 9) * scale2
    assert gate_3 < 0.9 * gate_9
    problem = _PointsProblem(0.5 * (gate_3 + gate_9))
    refit = SimpleNamespace(state="refit", iterations=3)
    monkeypatch.setattr(pipeline, "fit", lambda problem, state, settings: refit)
    result, iterations = pipeline.reject_outliers(problem, "start", SimpleNamespace(state="fit"), 5.0, ONE_STEP)
    assert result is refit and iterations == 3  # one refit: the flagged set is then stable
    np.testing.assert_array_equal(problem.active, np.arange(10) != 9)
    below = _PointsProblem(0.9 * gate_3)
    kept = SimpleNamespace(state="fit")
    assert pipeline.reject_outliers(below, "start", kept, 5.0, ONE_STEP) == (kept, 0)
    assert below.active.all()


def test_rms_of_points_is_over_the_points_seen():
    """With `seen` (N, 3 P), the position RMS is over every point seen, each point's error the norm of
    its three rows; orientation is not measured (nan)."""
    residual = np.array([[3.0, 4.0, 0.0, 9.0, 9.0, 9.0], [0.0, 1.0, 0.0, 2.0, 2.0, 1.0]])
    seen = np.array([[True] * 3 + [False] * 3, [True] * 6])
    position, rotation = pose_error_rms(residual, seen)
    assert position == pytest.approx(np.sqrt((25.0 + 1.0 + 9.0) / 3), rel=1e-15)
    assert np.isnan(rotation) and type(rotation) is float
    four = np.zeros((1, 12))
    four[0, 9] = 2.0  # the fourth point 2 off, the others exact, every point seen
    assert pose_error_rms(four, np.ones((1, 12), dtype=bool)).position == pytest.approx(1.0, rel=1e-15)


def test_calibration_summary_of_points_reports_the_rms_of_the_points_seen(mechanism):
    """A fit of two points per pose: the summary's RMS before and after are over the inliers' points
    seen (`pose_error_rms` with their `seen` rows), not over every row."""
    error_model = ClosedLoopErrorModel(mechanism)
    jacobian = np.eye(14, 3)
    before = np.array([[3.0, 4.0, 0.0, 9.0, 9.0, 9.0], [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]])
    start, end = object(), object()
    problem = _StandInProblem(
        error_model, (np.ones(14), jacobian), 3, np.array([3, 40, 205]), {id(start): before, id(end): before / 10}
    )
    problem.n_points = 2  # pose 0 sees its first point only; pose 1 (flagged) both
    summary = pipeline.summarise(problem, start, SimpleNamespace(state=end), (object(), None, 1), ONE_STEP)
    assert summary.rms_before.position == pytest.approx(5.0, rel=1e-15) and np.isnan(summary.rms_before.rotation)
    assert summary.rms_after.position == pytest.approx(0.5, rel=1e-15) and np.isnan(summary.rms_after.rotation)


# --------------------------------------------------------------------------------------------------
# The fit past the nominal's rank (`pipeline.fit_past_nominal_rank`) on a stand-in problem whose chi^2,
# Jacobian at the estimate and refit are given: the gate, both F tests with their parameter and
# degree-of-freedom counts (`generic_rank.significant`), the refit's columns and settings


#: 20 poses of one row: orthonormal directions q0 ... q3 of the residual space.
_Q = np.linalg.qr(np.random.default_rng(62).normal(size=(20, 4)))[0].T
#: The F test's critical ratio for 1 added parameter and 20 - 2 degrees of freedom at p = 1e-3.
_F_CRITICAL = float(scipy.special.fdtri(1, 18, 1.0 - 1e-3))
#: The base fit's settings handed on (its absolute tolerance scaled for the refit).
_BASE_SETTINGS = LMSettings(max_iterations=11, cost_tolerance=1e-10, absolute_cost_tolerance=1e-6, initial_damping=1e-6)


class _PastRankProblem:
    """The problem at the estimate: whitened Jacobian `jacobian` (20, p), residual `residual`, one fitted
    column (0); every row seen, every pose an inlier; `default_iterations` 5 per parameter."""

    rows_per_pose, n_points = 1, 0

    def __init__(self, jacobian, residual, setup_columns=()):
        self.jacobian, self.r = jacobian, residual
        self.names = tuple(f"p{j}" for j in range(jacobian.shape[1]))
        self.columns = np.array([0])
        self.active = np.ones(20, dtype=bool)
        self.seen = np.ones((20, 1), dtype=bool)
        self.setup_columns = np.array(setup_columns, dtype=int)
        self.priors = {}
        self.released = []

    def pose_blocks(self, state):
        return self.r.reshape(20, 1)

    def jacobian_factor(self, state, with_residual=False):
        assert with_residual
        return np.column_stack((self.jacobian, self.r))  # [J r] itself: F^T F = J^T J, and |P r|^2 the same

    def default_iterations(self, n_parameters):
        return 5 * n_parameters

    def restart(self, state):
        return ("restarted", state)

    def release(self, state):
        self.released.append(state)


def _past_rank(along, across, weak=1.0, setup_columns=()):
    """Column 0 along q0 (fitted), column 1 at `weak` from it towards q1, column 2 of no effect (1e-10 of the
    largest norm, above it with the tolerance divided by the norm); residual `along` q1 + `across` q3:
    chi^2 along^2 + across^2, of which the added direction explains along^2."""
    jacobian = 10.0 * np.column_stack((_Q[0], _Q[0] + weak * _Q[1], 1e-10 * _Q[2]))
    return _PastRankProblem(jacobian, along * _Q[1] + across * _Q[3], setup_columns)


def _residual_for(f_ratio, chi2):
    """(along, across) with chi^2 and the added direction's F ratio along^2 / (across^2 / 18)."""
    across2 = chi2 / (1.0 + f_ratio / 18.0)
    return np.sqrt(chi2 - across2), np.sqrt(across2)


def _run_past_rank(monkeypatch, problem, refit, nominal_rank=1, rank_tolerance=1e-8):
    calls = []

    def fit(problem, state, settings):
        calls.append((problem.columns.copy(), state, settings))
        if refit is None:
            raise IdentificationError("calibration ended on a model that does not assemble")
        return refit

    monkeypatch.setattr(pipeline, "fit", fit)
    chi2 = float(problem.r @ problem.r)
    result = SimpleNamespace(state="estimate", cost=0.5 * chi2)
    out = pipeline.fit_past_nominal_rank(problem, result, nominal_rank, [], rank_tolerance, _BASE_SETTINGS)
    return result, out, calls


def _refit_with(chi2, f_ratio, converged=True):
    """A refit whose drop in chi^2 from `chi2` has the F ratio `f_ratio` (1 parameter, 18 dof), 9 iterations."""
    after = chi2 / (1.0 + f_ratio / 18.0)
    return SimpleNamespace(cost=0.5 * after, converged=converged, iterations=9)


def test_a_fit_within_the_noise_is_refit_over_every_column_with_an_effect_damped_in_units(monkeypatch):
    """chi^2 = 10 of 20 rows: within the noise; the added direction's F ratio twice the critical one.
    The refit runs from the estimate over the columns above the tolerance times the largest norm, with
    4 x the default iterations of its rank, the absolute tolerance in units of the base fit's variance
    factor chi^2 / (rows - fitted) and unit damping; kept, it replaces the fit and its iterations count."""
    problem = _past_rank(*_residual_for(2.0 * _F_CRITICAL, 10.0))
    refit = _refit_with(10.0, 2.0 * _F_CRITICAL)
    result, (kept, iterations), calls = _run_past_rank(monkeypatch, problem, refit)
    assert kept is refit and iterations == 9
    ((columns, state, settings),) = calls
    np.testing.assert_array_equal(columns, [0, 1])
    np.testing.assert_array_equal(problem.columns, [0, 1])
    assert state == ("restarted", "estimate") and problem.released == ["estimate"]
    assert settings == dataclasses.replace(
        _BASE_SETTINGS,
        max_iterations=4 * 5 * 2,
        absolute_cost_tolerance=pytest.approx(1e-6 * 10.0 / 19),
        unit_damping=True,
    )


@pytest.mark.parametrize("chi2", [18.5, 19.5])
def test_the_fit_past_the_nominal_rank_is_tried_only_within_the_stated_noise(monkeypatch, chi2):
    """The gate: chi^2 at most its degrees of freedom, 20 rows less the 1 fitted column (a significant
    added direction either way)."""
    problem = _past_rank(*_residual_for(3.0 * _F_CRITICAL, chi2))
    refit = _refit_with(chi2, 3.0 * _F_CRITICAL)
    result, out, calls = _run_past_rank(monkeypatch, problem, refit)
    if chi2 < 19.0:
        assert out == (refit, 9) and len(calls) == 1
    else:
        assert out == (result, 0) and calls == [] and problem.columns.tolist() == [0]


@pytest.mark.parametrize("factor", [0.95, 1.05])
def test_the_added_directions_must_explain_the_residual_by_the_f_test_of_their_count(monkeypatch, factor):
    """The F test of the explained part, for here.rank - fitted = 1 parameter and rows - here.rank = 18
    degrees of freedom, on either side of its critical ratio: below it no refit is tried."""
    problem = _past_rank(*_residual_for(factor * _F_CRITICAL, 10.0))
    refit = _refit_with(10.0, 3.0 * _F_CRITICAL)
    result, out, calls = _run_past_rank(monkeypatch, problem, refit)
    assert out == ((refit, 9) if factor > 1.0 else (result, 0))
    assert len(calls) == (factor > 1.0)


@pytest.mark.parametrize("factor", [0.95, 1.05])
def test_a_refit_is_kept_only_when_its_own_drop_in_chi2_passes_the_f_test(monkeypatch, factor):
    """The refit's chi^2 = 2 cost against the fit's 2 cost, on either side of the critical ratio; a refit
    not kept leaves the fit and its columns, and its iterations still count."""
    problem = _past_rank(*_residual_for(3.0 * _F_CRITICAL, 10.0))
    refit = _refit_with(10.0, factor * _F_CRITICAL)
    result, out, calls = _run_past_rank(monkeypatch, problem, refit)
    assert len(calls) == 1
    if factor > 1.0:
        assert out == (refit, 9) and problem.columns.tolist() == [0, 1]
    else:
        assert out == (result, 9) and problem.columns.tolist() == [0] and problem.released == []


def test_a_refit_that_did_not_converge_or_does_not_assemble_is_dropped(monkeypatch):
    problem = _past_rank(*_residual_for(3.0 * _F_CRITICAL, 10.0))
    result, out, calls = _run_past_rank(monkeypatch, problem, _refit_with(10.0, 3.0 * _F_CRITICAL, converged=False))
    assert out == (result, 9) and len(calls) == 1 and problem.columns.tolist() == [0]
    result, out, calls = _run_past_rank(monkeypatch, problem, None)
    assert out == (result, 0) and len(calls) == 1 and problem.columns.tolist() == [0]


def test_the_rank_at_the_estimate_must_pass_the_nominals_and_is_judged_at_the_given_tolerance(monkeypatch):
    """No refit when the estimate identifies only the nominal's rank (2 of 2), or when the added
    direction (at 1e-5 from the fitted one) is below the given tolerance; above it, one."""
    along_across = _residual_for(3.0 * _F_CRITICAL, 10.0)
    refit = _refit_with(10.0, 3.0 * _F_CRITICAL)
    result, out, calls = _run_past_rank(monkeypatch, _past_rank(*along_across), refit, nominal_rank=2)
    assert out == (result, 0) and calls == []
    weak = _past_rank(*along_across, weak=1e-5)
    result, out, calls = _run_past_rank(monkeypatch, weak, refit, rank_tolerance=1e-4)
    assert out == (result, 0) and calls == []
    assert _run_past_rank(monkeypatch, weak, refit, rank_tolerance=1e-6)[1] == (refit, 9)


def test_the_setup_columns_are_kept_first_in_the_choice_at_the_estimate(monkeypatch):
    """At a tolerance of 0.8, a setup column along q0 + q1 kept first leaves the fitted column and the
    one along q1 at 1/sqrt(2) each: rank 1, no refit; not a setup column, the pivoted choice finds 2."""
    along, across = _residual_for(3.0 * _F_CRITICAL, 10.0)
    refit = _refit_with(10.0, 3.0 * _F_CRITICAL)
    jacobian = np.column_stack((_Q[0], _Q[1], (_Q[0] + _Q[1]) / np.sqrt(2.0)))
    residual = along * _Q[1] + across * _Q[3]
    plain = _PastRankProblem(jacobian, residual)
    assert _run_past_rank(monkeypatch, plain, refit, rank_tolerance=0.8)[1] == (refit, 9)
    gauge = _PastRankProblem(jacobian, residual, setup_columns=[2])
    result, out, calls = _run_past_rank(monkeypatch, gauge, refit, rank_tolerance=0.8)
    assert out == (result, 0) and calls == []
