"""Closed-loop calibration: sensitivities, identifiability and reachable accuracy (docs/results.md)."""

import re
import warnings

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.closed_loop import (
    calibrate_closed_loop,
    pose_errors,
    predicted_measurement_std,
    predicted_pose_std,
)
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise, assembled_from_home, measure
from m3t1r.calibration.simulation import actual_machine, random_placement_errors, simulate_study
from m3t1r.errors import IdentificationError, InvalidInputError
from m3t1r.metrics import pose_errors_between
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver
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
    pose, dxi, _ = error_model.platform_sensitivity(solver, q)
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
    the batch equals pose-by-pose calls, and passive_sensitivities equals -J_c,pas^-1 dr_c/dp."""
    truth = simulate_study(mechanism, n_poses=1, n_holdout=0, seed=4).truth
    solver = ClosedLoopSolver(truth)
    configurations = [solver.forward(s, q_init=truth.home).q
                      for s in workspace_actuators(mechanism, 3, np.random.default_rng(8))]
    full = error_model.platform_sensitivities(solver, configurations)
    columns = np.random.default_rng(9).choice(error_model.n_parameters, 70, replace=False)
    part = error_model.platform_sensitivities(solver, configurations, columns)
    np.testing.assert_allclose(part.twist_jacobians, full.twist_jacobians[:, :, columns], atol=1e-12)
    np.testing.assert_allclose(part.closure_jacobians, full.closure_jacobians[:, :, columns], atol=1e-12)
    for i, q in enumerate(configurations):
        pose, dxi, dq_dp = error_model.platform_sensitivity(solver, q, columns)
        np.testing.assert_allclose(pose.homogeneous, part.poses[i], atol=1e-15)
        np.testing.assert_allclose(dxi, part.twist_jacobians[i], atol=1e-12)
        step = np.linspace(-1e-3, 1e-3, len(columns))
        np.testing.assert_allclose(part.passive_sensitivities()[i] @ step, dq_dp @ step, atol=1e-12)


def test_joint_twists_are_pinocchio_regressors(mechanism, error_model):
    solver = ClosedLoopSolver(mechanism)
    q = solver.forward([0.1, 0.05, -0.05, 0.1]).q
    solver.closure_sensitivity(q)
    joints = np.array([[placement.homogeneous for placement in solver.data.oMi.tolist()]])
    G = error_model._joint_twist_matrices(solver.model, joints)[0]
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
    study = simulate_study(mechanism, n_poses=50, n_holdout=200, seed=12, sigma_position=1e-4, sigma_rotation=1e-4)
    calibration = calibrate_closed_loop(mechanism, study.measurements)
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    assert after.position_mean < 1e-8 and after.rotation_mean < 1e-7


def test_noisy_calibration_sits_at_the_predicted_floor(mechanism):
    noise = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)
    study = simulate_study(mechanism, n_poses=50, n_holdout=200, seed=13, noise=noise)
    calibration = calibrate_closed_loop(mechanism, study.measurements, noise)
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
    setup = MeasurementSetup(pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 2.0), np.array([3.0, -1.0, 0.5])),
                             pin.SE3(np.eye(3), np.array([0.05, -0.02, 0.03])))
    noise = TrackerNoise(10e-6, 20e-6)
    measured = measure(truth, workspace_actuators(mechanism, 60, rng), rng, noise, setup=setup)
    calibration = calibrate_closed_loop(mechanism, measured, noise, setup=MeasurementSetup(marker=setup.marker),
                                        estimate_frame=True)
    held_out = workspace_actuators(mechanism, 300, np.random.default_rng(101))
    actual = pose_errors_between(calibration.setup.measured_poses(assembled_from_home(calibration.mechanism, held_out).poses),
                                 setup.measured_poses(assembled_from_home(truth, held_out).poses))
    predicted = predicted_measurement_std(calibration, held_out)
    rms = lambda values: float(np.sqrt(np.mean(values**2)))  # noqa: E731
    assert 0.8 < rms(actual.position) / rms(predicted.position) < 1.5
    assert 0.8 < rms(actual.rotation) / rms(predicted.rotation) < 1.5
    assert rms(predicted_pose_std(calibration, held_out).position) > 100 * rms(predicted.position)


def test_predicted_measurement_std_without_a_setup_is_the_platform_std(mechanism):
    """No frame, no marker: the measured frame is the platform in the base, so both predictions agree."""
    noise = TrackerNoise(position=10e-6, rotation=20e-6)
    study = simulate_study(mechanism, n_poses=40, n_holdout=20, seed=3, noise=noise)
    calibration = calibrate_closed_loop(mechanism, study.measurements, noise)
    measured = predicted_measurement_std(calibration, study.holdout_actuators)
    platform = predicted_pose_std(calibration, study.holdout_actuators)
    np.testing.assert_allclose(measured.position, platform.position, rtol=1e-10)
    np.testing.assert_allclose(measured.rotation, platform.rotation, rtol=1e-10)
    empty = predicted_measurement_std(calibration, np.zeros((0, 4)))
    assert empty.position.shape == (0,) and empty.rotation.shape == (0,)

def test_position_only_measurements(mechanism):
    noise = TrackerNoise(position=10e-6, rotation=20e-6)
    study = simulate_study(mechanism, n_poses=60, n_holdout=100, seed=14, noise=noise, position_only=True)
    calibration = calibrate_closed_loop(mechanism, study.measurements, noise)
    after = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    predicted = predicted_pose_std(calibration, study.holdout_actuators)
    assert np.sqrt(np.mean(after.position**2)) <= 1.5 * np.sqrt(np.mean(predicted.position**2))
    assert after.position_mean < 3e-5
    assert np.isnan(calibration.rms_after[1])


def test_too_few_poses_is_refused(mechanism):
    study = simulate_study(mechanism, n_poses=5, n_holdout=0, seed=15)
    with pytest.raises(IdentificationError, match="30 residual rows for 56 identifiable parameters and identify only 30: "
                                                  r"add poses \(each gives 6 rows\)"):
        calibrate_closed_loop(mechanism, study.measurements)


def _advised_holding(message: str) -> list[str]:
    held = re.search(r"\(--fix ([^)]+)\)$", message)
    assert held is not None, message
    return held.group(1).split()


@pytest.mark.parametrize("files, leg", [(five_bar_files, ("motor_1", "elbow_1")),
                                        (spherical_wrist_files, ("motor_1", "elbow_1", "wrist_1"))])
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
    assert re.match(r"40 poses give 240 residual rows for (\d+) identifiable parameters and identify only (\d+): "
                    r"these poses do not excite ", message), message
    assert "add poses" not in message and "poses that move them, over more of the workspace" in message
    held = _advised_holding(message)
    assert held and all(name.split(".dt[")[0] in leg for name in held), held
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calibration = calibrate_closed_loop(machine, measurements, fixed=held)
    assert calibration.converged and not set(held) & set(calibration.base.names)


def test_barely_identifiable_directions_are_not_answered_with_more_poses(mechanism):
    """With positions only, the M machine has directions at 1.2e-4 of the strongest even on poses spread
    over the whole workspace; at a rank tolerance of 1e-4 these 40 poses miss two of them. More poses
    are no remedy, and the refusal says so; the parameters it says to hold make the fit go through."""
    sliders = workspace_actuators(mechanism, 40, np.random.default_rng(1))
    measurements = measure(mechanism, sliders, position_only=True)
    with pytest.raises(IdentificationError) as refusal:
        calibrate_closed_loop(mechanism, measurements, rank_tolerance=1e-4, outlier_sigma=None)
    message = str(refusal.value)
    assert message.startswith("40 poses give 120 residual rows for 53 identifiable parameters and identify only ")
    assert "barely identifiable on any poses" in message and "more poses are unlikely to help" in message
    assert "add poses" not in message
    held = _advised_holding(message)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calibration = calibrate_closed_loop(mechanism, measurements, fixed=held, rank_tolerance=1e-4,
                                            outlier_sigma=None)
    assert calibration.converged and not set(held) & set(calibration.base.names)


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

    study = simulate_study(mechanism, n_poses=50, n_holdout=200, seed=11, passive_joints=IDLE_CHAIN_JOINTS)
    _, calibration = noise_free_1mm  # same seed, same truth and poses
    actuators = study.measurements.actuators
    before = passive_joint_residuals(mechanism, actuators, IDLE_CHAIN_JOINTS, study.passive_readings)
    after = passive_joint_residuals(calibration.mechanism, actuators, IDLE_CHAIN_JOINTS, study.passive_readings)
    assert np.all(after.rms < before.rms / 10)
    assert np.all(after.rms < 1e-4)


@pytest.mark.parametrize("options,message", [
    ({"outlier_sigma": -5.0}, "outlier_sigma: None or 0"),
    ({"outlier_sigma": 0.5}, "outlier_sigma: None or 0"),
    ({"outlier_sigma": float("nan")}, "outlier_sigma: expected a finite number"),
    ({"fixed": "q12"}, r"fixed parameter: expected a list of names such as \['q12'\], got 'q12'"),
    ({"max_iterations": 0}, "max_iterations: expected a whole number of at least 1"),
])
def test_calibration_options_are_checked_at_the_call(mechanism, options, message):
    """A negative or NaN gate silently disabled outlier rejection; fixed="q12" was read letter by letter."""
    study = simulate_study(mechanism, n_poses=12, n_holdout=0, seed=16)
    with pytest.raises(InvalidInputError, match=message):
        calibrate_closed_loop(mechanism, study.measurements, **options)


def test_complex_readings_and_seeds_below_zero_are_refused(mechanism):
    study = simulate_study(mechanism, n_poses=4, n_holdout=0, seed=16)
    with pytest.raises(InvalidInputError, match="actuator readings: complex values given"):
        PoseMeasurements(study.measurements.actuators + 1j, study.measurements.poses)
    with pytest.raises(InvalidInputError, match="seed: expected a whole number of at least 0"):
        simulate_study(mechanism, n_poses=4, n_holdout=0, seed=-1)
