"""Serial-robot calibration with the local POE error model on example-robot-data arms."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration import pipeline, serial, serial_evaluation
from m3t1r.calibration import serial as S
from m3t1r.calibration.identification import forward_selection, levenberg_marquardt, select_base_parameters
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions, LMSettings, pose_error_rms, prior_columns
from m3t1r.calibration.repeats import grouped_blocks
from m3t1r.calibration.serial import calibrate_serial
from m3t1r.calibration.serial_evaluation import pose_errors, predicted_pose_std
from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
from m3t1r.calibration.serial_simulation import sample_configurations, simulate_serial_measurements
from m3t1r.errors import IdentificationError, InvalidInputError
from m3t1r.metrics import PoseErrors
from m3t1r.model.poe import Placement, SerialChain, forward_and_error_jacobians, perturb, tool_poses

# 10 um / 20 urad tracker, 1e-5 rad encoders: the test setting of the brief.
NOISE = TrackerNoise(position=1e-5, rotation=2e-5)
JOINT_NOISE = 1e-5
SENSORS = {"noise": NOISE, "joint_noise": JOINT_NOISE}  # simulated, and assumed by the fit
FIT = CalibrationOptions(**SENSORS)
N_POSES = 50
N_HELD_OUT = 150


@pytest.fixture(scope="module", params=["ur5", "panda"])
def robot(request: pytest.FixtureRequest) -> tuple[str, pin.Model, SerialChain]:
    model = load_example_robot(request.param)
    return request.param, model, SerialChain.from_model(model, example_tool_frame(request.param))


def test_load_example_robots() -> None:
    ur5 = load_example_robot("ur5")
    assert ur5.nq == 6 and ur5.existFrame("tool0")
    panda = load_example_robot("panda")
    # Fingers locked: 7 arm joints left, and the TCP frame hangs from the last one.
    assert panda.nq == 7 and not panda.existJointName("panda_finger_joint1")
    assert panda.frames[panda.getFrameId("panda_hand_tcp")].parentJoint == panda.getJointId("panda_joint7")
    with pytest.raises(InvalidInputError, match="unknown example robot 'kuka'"):
        load_example_robot("kuka")  # type: ignore[arg-type]


def nominal_rank(model: pin.Model, chain: SerialChain, rows: slice, seed: int = 0) -> int:
    q = sample_configurations(model, chain, N_POSES, np.random.default_rng(seed))
    poses, jacobians = forward_and_error_jacobians(chain, model, q)
    # Position rows are the LOCAL_WORLD_ALIGNED linear rows: v + w x p.
    p = np.array([g.translation for g in poses])
    position = jacobians[:, :3] + np.cross(jacobians[:, 3:], p[:, :, None], axis=1)
    stacked = np.concatenate([position, jacobians[:, 3:]], axis=1)[:, rows]
    return select_base_parameters(stacked.reshape(-1, chain.n_parameters), chain.parameter_names()).rank


def test_identifiable_parameter_counts() -> None:
    # Full pose: a revolute joint's placement error loses 2 of its 6 components (rotation about and
    # translation along its own axis commute with the joint motion and pass into the next
    # placement); the tool keeps all 6: 4 r + 2 p + 6 (paper section 3.2). UR5: 30 of 42, Panda: 34 of 48.
    ur5, panda = load_example_robot("ur5"), load_example_robot("panda")
    ur5_chain, panda_chain = SerialChain.from_model(ur5, "tool0"), SerialChain.from_model(panda, "panda_hand_tcp")
    assert nominal_rank(ur5, ur5_chain, slice(0, 6)) == 4 * 6 + 6
    assert nominal_rank(panda, panda_chain, slice(0, 6)) == 4 * 7 + 6
    # Position only: the tool orientation (3) is invisible, 4 r + 2 p + 3. At the nominal geometry
    # both tools sit exactly on the last joint axis, which hides 2 more (the axis can tilt about the
    # tool point); any real robot breaks that, and calibrate_serial re-selects at its estimate.
    assert nominal_rank(ur5, ur5_chain, slice(0, 3)) == 4 * 6 + 3 - 2
    assert nominal_rank(panda, panda_chain, slice(0, 3)) == 4 * 7 + 3 - 2


def run_calibration(
    model: pin.Model, chain: SerialChain, seed: int, *, exact: bool = False, position_only: bool = False
):
    """Simulated with SENSORS' noise (exact: none at all), fitted assuming SENSORS' noise."""
    rng = np.random.default_rng(seed)
    data = simulate_serial_measurements(
        model, chain, N_POSES, rng, noise=None if exact else NOISE, joint_noise=0.0 if exact else JOINT_NOISE
    )
    calibration = calibrate_serial(model, chain, data.q_readings, data.measured_poses, FIT, position_only=position_only)
    held_out = sample_configurations(model, chain, N_HELD_OUT, rng)
    before = pose_errors(model, data.truth, chain, held_out)
    after = pose_errors(calibration.model, data.truth, chain, held_out)
    return data, calibration, held_out, before, after


def test_full_pose_calibration_reaches_the_predicted_noise_floor(robot) -> None:
    name, model, chain = robot
    data, calibration, held_out, before, after = run_calibration(model, chain, seed=11)
    assert calibration.converged
    assert calibration.base.rank == 4 * chain.n_joints + 6
    assert before.position.mean() > 1e-3  # 1 mm / 1 mrad placement errors: millimetres at the tool
    assert before.position.mean() / after.position.mean() >= 50.0
    predicted = predicted_pose_std(calibration, held_out)
    # The held-out error is one draw of the parameter error: its RMS must match the prediction
    # from sigma^2 (J^T J)^-1 to within sampling scatter (0.67 to 1.38 over 30 seeds).
    assert 0.5 < after.position_rms / predicted.position_rms < 1.5
    assert 0.5 < after.rotation_rms / predicted.rotation_rms < 1.5
    assert 3e-6 < predicted.position_rms < 2e-5  # a few um from 10 um noise on 50 poses
    assert 0.8 < calibration.variance_factor < 1.25  # whitening incl. joint noise is consistent
    # The calibrated residual is at the measurement noise (10 um per axis, joint noise on top).
    assert calibration.rms_after.position < 2.5e-5 < 1e-3 < calibration.rms_before.position


def test_noise_free_calibration_is_exact(robot) -> None:
    _, model, chain = robot
    _, calibration, _, before, after = run_calibration(model, chain, seed=12, exact=True)
    assert before.position.max() > 1e-3
    assert after.position.max() < 1e-9 and after.rotation.max() < 1e-9
    # The deltas are the calibrated model: perturbing the nominal by them reproduces it.
    rebuilt = perturb(model, calibration.deltas)
    for j in chain.joint_ids:
        difference = rebuilt.jointPlacements[j].actInv(calibration.model.jointPlacements[j])
        assert np.linalg.norm(pin.log6(difference).vector) < 1e-12


def test_measurements_of_the_nominal_robot_fit_nothing_with_selection() -> None:
    """Exact measurements of the nominal robot: selection keeps no parameter (none lowers the
    prediction error), so the result is the nominal robot with nothing fitted, no covariance, zero
    predicted std and zero cross-validation error, not an error from the empty final fit."""
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    q = sample_configurations(model, chain, 30, np.random.default_rng(0))
    measured = [pin.SE3(h) for h in tool_poses(chain, model, q)]
    calibration = calibrate_serial(model, chain, q, measured, CalibrationOptions(select=True))
    assert calibration.converged and calibration.fitted == () and calibration.fitted_indices == ()
    assert calibration.covariance.shape == (0, 0) and calibration.parameter_std.shape == (0,)
    assert calibration.rms_after.position == 0.0 and calibration.outliers == ()
    for j in chain.joint_ids:
        assert calibration.model.jointPlacements[j].isApprox(model.jointPlacements[j], 1e-15)
    predicted = predicted_pose_std(calibration, q[:4])
    np.testing.assert_array_equal(predicted.position, np.zeros(4))
    assert serial_evaluation.cross_validate_serial(calibration).errors.position_mean == 0.0


def test_position_only_calibration(robot) -> None:
    _, model, chain = robot
    _, calibration, held_out, before, after = run_calibration(model, chain, seed=13, position_only=True)
    assert calibration.converged
    assert calibration.base.rank == 4 * chain.n_joints + 3
    tool_rotation = {6 * chain.n_joints + 3, 6 * chain.n_joints + 4, 6 * chain.n_joints + 5}
    assert not tool_rotation & set(calibration.base.indices)  # invisible to position measurements
    assert before.position.mean() / after.position.mean() >= 50.0
    predicted = predicted_pose_std(calibration, held_out)
    assert 0.5 < after.position_rms / predicted.position_rms < 1.5
    assert np.all(np.isnan(predicted.rotation))


def test_position_only_noise_free_is_exact() -> None:
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    _, _, _, _, after = run_calibration(model, chain, seed=14, exact=True, position_only=True)
    assert after.position.max() < 1e-9


def test_measurement_formats_and_validation() -> None:
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    data = simulate_serial_measurements(model, chain, 20, np.random.default_rng(15), **SENSORS)
    from_se3 = calibrate_serial(model, chain, data.q_readings, data.measured_poses, FIT)
    xyzquat = np.array([pin.SE3ToXYZQUAT(g) for g in data.measured_poses])
    from_array = calibrate_serial(model, chain, data.q_readings, xyzquat, FIT)
    q = sample_configurations(model, chain, 10, np.random.default_rng(16))
    assert pose_errors(from_se3.model, from_array.model, chain, q).position.max() < 1e-12
    positions = xyzquat[:, :3]
    position_only = calibrate_serial(model, chain, data.q_readings, positions, FIT, position_only=True)
    assert np.isnan(position_only.rms_after.rotation)
    with pytest.raises(InvalidInputError, match="position_only=True"):
        calibrate_serial(model, chain, data.q_readings, positions, FIT)
    with pytest.raises(InvalidInputError, match="20 joint readings but 19"):
        calibrate_serial(model, chain, data.q_readings, xyzquat[:19], FIT)
    with pytest.raises(InvalidInputError, match="expected shape"):
        calibrate_serial(model, chain, data.q_readings[:, :5], xyzquat, FIT)
    bad = xyzquat.copy()
    bad[4, 3:] *= 2.0
    with pytest.raises(InvalidInputError, match="row 4"):
        calibrate_serial(model, chain, data.q_readings, bad, FIT)
    for joint_noise in (-1e-5, float("nan")):
        with pytest.raises(InvalidInputError, match="joint_noise: must be finite and >= 0"):
            calibrate_serial(
                model, chain, data.q_readings, xyzquat, CalibrationOptions(noise=NOISE, joint_noise=joint_noise)
            )
        with pytest.raises(InvalidInputError, match="joint_noise: must be finite and >= 0"):
            simulate_serial_measurements(model, chain, 5, np.random.default_rng(17), joint_noise=joint_noise)


def test_serial_simulation_takes_the_tracker_noise_and_a_joint_noise() -> None:
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    exact = simulate_serial_measurements(model, chain, 30, np.random.default_rng(18), noise=None)
    assert exact.noise is None and exact.joint_noise == 0.0
    assert np.array_equal(exact.q_readings, exact.q_true)
    truth = [pin.SE3(g) for g in tool_poses(chain, exact.truth, exact.q_true)]
    assert max(np.linalg.norm(pin.log6(g.actInv(m)).vector) for g, m in zip(truth, exact.measured_poses)) < 1e-12
    noisy = simulate_serial_measurements(
        model, chain, 400, np.random.default_rng(19), noise=TrackerNoise(1e-4, 3e-4), joint_noise=2e-4
    )
    assert noisy.noise == TrackerNoise(1e-4, 3e-4) and noisy.joint_noise == 2e-4
    assert np.std(noisy.q_readings - noisy.q_true) == pytest.approx(2e-4, rel=0.05)
    truth = [pin.SE3(g) for g in tool_poses(chain, noisy.truth, noisy.q_true)]
    position = np.array([m.translation - g.translation for g, m in zip(truth, noisy.measured_poses)])
    rotation = np.array([pin.log3(g.rotation.T @ m.rotation) for g, m in zip(truth, noisy.measured_poses)])
    assert np.std(position) == pytest.approx(1e-4, rel=0.05) and np.std(rotation) == pytest.approx(3e-4, rel=0.05)


# --------------------------------------------------------------------------------------------------
# Batched residual internals against their Pinocchio / finite-difference references


@pytest.mark.parametrize("position_only", [False, True])
def test_residual_jacobian_matches_finite_differences(position_only: bool) -> None:
    # The analytic whitened Jacobian against central differences of the residual through the same
    # retraction T(0) <- T(0) exp6(dt) that the optimiser uses, at a perturbed (non-nominal) state.
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    data = simulate_serial_measurements(model, chain, 8, np.random.default_rng(31), **SENSORS)
    measurements = serial.parse_measurements(chain, data.q_readings, data.measured_poses, position_only)
    state = serial.nominal_state(chain, perturb(model, {p: np.full(6, 2e-3) for p in chain.placements()}))
    whitening = serial.pose_whitening(chain, state, measurements, NOISE, JOINT_NOISE)
    residual = serial.SerialResidual(chain, measurements, whitening)
    r, J = residual.residual_and_jacobian(state)
    np.testing.assert_array_equal(residual.residual(state), r)
    step = 1e-7
    numeric = np.empty_like(J)
    for i in range(chain.n_parameters):
        dt = np.zeros(chain.n_parameters)
        dt[i] = step
        plus, minus = residual.retract(state, dt), residual.retract(state, -dt)
        numeric[:, i] = (residual.residual(plus) - residual.residual(minus)) / (2 * step)
    assert np.linalg.norm(J - numeric) <= 1e-6 * np.linalg.norm(J)


def test_rank_bound_is_reached_at_a_generic_model(robot) -> None:
    # The structural bound 4 r + 2 p + 6 (+ 3 with positions only) used to skip a re-selection that
    # cannot find more parameters: it must be the rank wherever the geometry is not special.
    _, model, chain = robot
    rng = np.random.default_rng(32)
    generic = perturb(model, {p: rng.normal(0.0, 1e-2, 6) for p in chain.placements()})
    q = sample_configurations(model, chain, N_POSES, rng)
    for position_only, rows in ((False, slice(0, 6)), (True, slice(0, 3))):
        poses, jacobians = forward_and_error_jacobians(chain, generic, q)
        p = np.array([g.translation for g in poses])
        position = jacobians[:, :3] + np.cross(jacobians[:, 3:], p[:, :, None], axis=1)
        stacked = np.concatenate([position, jacobians[:, 3:]], axis=1)[:, rows].reshape(-1, chain.n_parameters)
        rank = select_base_parameters(stacked, chain.parameter_names()).rank
        assert rank == chain.rank_bound(position_only)


def test_stopping_one_iteration_earlier_changes_nothing() -> None:
    # absolute_cost_tolerance only saves the final iteration whose step is at rounding level.
    model = load_example_robot("ur10")
    chain = SerialChain.from_model(model, "tool0")
    noise = TrackerNoise(position=1e-5, rotation=2e-5)  # exact joint readings
    data = simulate_serial_measurements(model, chain, N_POSES, np.random.default_rng(33), noise=noise)
    default = calibrate_serial(model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=noise))
    exhaustive = calibrate_serial(
        model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=noise, absolute_cost_tolerance=0.0)
    )
    assert default.converged and exhaustive.converged
    assert default.iterations <= exhaustive.iterations <= default.iterations + 1
    q = sample_configurations(model, chain, N_HELD_OUT, np.random.default_rng(34))
    difference = pose_errors(default.model, exhaustive.model, chain, q)
    assert difference.position_max < 1e-10 and difference.rotation_max < 1e-10
    assert default.variance_factor == pytest.approx(exhaustive.variance_factor, rel=1e-9)


def test_evaluations_return_the_shared_pose_errors_type() -> None:
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    data = simulate_serial_measurements(model, chain, 20, np.random.default_rng(35), **SENSORS)
    calibration = calibrate_serial(model, chain, data.q_readings, data.measured_poses, FIT)
    q = sample_configurations(model, chain, 5, np.random.default_rng(36))
    assert isinstance(pose_errors(calibration.model, data.truth, chain, q), PoseErrors)
    predicted = predicted_pose_std(calibration, q)
    assert isinstance(predicted, PoseErrors) and predicted.position.shape == (5,)
    assert serial_evaluation.PoseErrors is PoseErrors


# ==================================================================================================
# Whitening, the column layout, outlier rounds and selection
#
# Whitening without joint noise is checked against the true noise (variance factor near one from both
# sides, parameter std against the scatter of repeated experiments), and the quaternion norm tolerance of
# array input at its boundary. Then, on small problems: the column layout and names, every column's
# Jacobian (placements, frame, marker, compliance) against finite differences, retraction, whitening with
# joint noise against its covariance, gravity torques, outlier masks and prior rows, the start's frame and
# marker registration, re-selection of the base at the estimate, outlier rounds, forward selection and the
# result's fields.
# ==================================================================================================


TRACKER = TrackerNoise(position=1e-5, rotation=2e-5)  # and exact joint readings (joint_noise 0, the default)


@pytest.fixture(scope="module")
def ur5():
    model = load_example_robot("ur5")
    return model, SerialChain.from_model(model, "tool0")


def _calibrate(model, chain, seed: int, n_poses: int = 40):
    data = simulate_serial_measurements(model, chain, n_poses, np.random.default_rng(seed), noise=TRACKER)
    calibration = calibrate_serial(
        model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=TRACKER)
    )
    return data, calibration


def test_whitening_without_joint_noise_gives_a_variance_factor_near_one(ur5):
    """Whitened by 1/sigma (not 1/sigma^2): chi^2 / dof is about 1 when the noise model is the truth."""
    model, chain = ur5
    factors = [_calibrate(model, chain, seed)[1].variance_factor for seed in (0, 1, 2)]
    assert all(0.75 < f < 1.3 for f in factors), factors
    assert 0.85 < np.mean(factors) < 1.15


def test_parameter_std_matches_the_scatter_of_repeated_experiments(ur5):
    """The same truth measured 12 times: the reported std of each estimate matches its scatter."""
    model, chain = ur5
    estimates, stds = [], []
    truth_rng_seed = 5
    for k in range(12):
        rng = np.random.default_rng(truth_rng_seed)  # same truth and configurations every time ...
        data = simulate_serial_measurements(model, chain, 40, rng, noise=None)
        noise_rng = np.random.default_rng(100 + k)  # ... fresh tracker noise
        measured = [
            pin.SE3(
                g.rotation @ pin.exp3(noise_rng.normal(0.0, TRACKER.rotation, 3)),
                g.translation + noise_rng.normal(0.0, TRACKER.position, 3),
            )
            for g in data.measured_poses
        ]
        calibration = calibrate_serial(model, chain, data.q_readings, measured, CalibrationOptions(noise=TRACKER))
        estimates.append(
            np.concatenate([calibration.deltas[p] for p in chain.placements()])[list(calibration.base.indices)]
        )
        stds.append(calibration.parameter_std)
    scatter = np.std(np.array(estimates), axis=0, ddof=1)
    ratio = scatter / np.mean(np.array(stds), axis=0)
    # 12 draws: the sample std is within a factor ~2 of the true one; the median ratio much closer.
    assert 0.7 < np.median(ratio) < 1.3, np.median(ratio)
    assert np.all((ratio > 0.3) & (ratio < 2.5))


def test_predicted_pose_std_without_joint_noise_is_micrometres(ur5):
    model, chain = ur5
    _, calibration = _calibrate(model, chain, 3)
    predicted = predicted_pose_std(calibration, sample_configurations(model, chain, 20, np.random.default_rng(4)))
    assert 2e-6 < predicted.position_rms < 2e-5 and 2e-6 < predicted.rotation_rms < 4e-5


@pytest.mark.parametrize("norm_error, refused", [(1e-4, True), (2e-6, True), (5e-7, False), (-5e-7, False)])
def test_quaternion_norm_tolerance_is_1e_6(ur5, norm_error, refused):
    model, chain = ur5
    data = simulate_serial_measurements(model, chain, 12, np.random.default_rng(7), noise=TRACKER)
    xyzquat = np.array([pin.SE3ToXYZQUAT(g) for g in data.measured_poses])
    xyzquat[5, 3:] *= 1.0 + norm_error
    if refused:
        with pytest.raises(InvalidInputError, match="quaternion of row 5 has norm"):
            calibrate_serial(model, chain, data.q_readings, xyzquat, CalibrationOptions(noise=TRACKER))
    else:
        calibration = calibrate_serial(model, chain, data.q_readings, xyzquat, CalibrationOptions(noise=TRACKER))
        assert calibration.converged


# --------------------------------------------------------------------------------------------------
# Internals: layout, Jacobian of every column, whitening, gravity torques, priors (fast, no fit)

MARKER = pin.SE3(pin.utils.rotate("y", 0.3) @ pin.utils.rotate("x", -0.2), np.array([0.01, 0.02, 0.067]))
FRAME = pin.SE3(pin.utils.rotate("z", 2.0) @ pin.utils.rotate("x", 0.4), np.array([2.0, -1.0, 0.3]))


def _assert_jacobian_is_the_retract_derivative(J, residual, state, layout):
    """J against central differences of the residual along `retract` (steps 1e-7, 1e-9 for the
    compliances), block by block (placements, frame, marker or points, compliance) to 1e-6 relative."""
    numeric = np.empty_like(J)
    for i in range(layout.size):
        dx = np.zeros(layout.size)
        dx[i] = 1e-7 if i < layout.compliance_slice.start else 1e-9
        numeric[:, i] = (
            residual.residual(residual.retract(state, dx)) - residual.residual(residual.retract(state, -dx))
        ) / (2 * dx[i])
    for block in (slice(0, 42), layout.frame_slice, layout.marker_slice, layout.compliance_slice):
        assert np.linalg.norm(J[:, block] - numeric[:, block]) <= 1e-6 * np.linalg.norm(J[:, block]), block


def _measurements(model, chain, position_only: bool = False, n_poses: int = 6, seed: int = 40):
    data = simulate_serial_measurements(model, chain, n_poses, np.random.default_rng(seed), noise=TRACKER)
    measured = FRAME.homogeneous @ np.array([g.homogeneous for g in data.measured_poses]) @ MARKER.homogeneous
    return S.parse_measurements(chain, data.q_readings, [pin.SE3(m) for m in measured], position_only)


def test_layout_columns_and_names(ur5):
    _, chain = ur5
    layout = S.SerialLayout(6, frame=True, marker=3, compliance=True)
    assert (layout.n_chain, layout.size) == (42, 42 + 6 + 3 + 6)
    assert layout.frame_slice == slice(42, 48) and layout.marker_slice == slice(48, 51)
    assert layout.compliance_slice == slice(51, 57)
    np.testing.assert_array_equal(layout.setup_columns, np.arange(42, 51))
    names = layout.names(chain)
    assert names[:42] == chain.parameter_names()
    assert names[42:] == tuple(f"measurement_frame.dt[{k}]" for k in range(6)) + (
        "marker.dt[0]",
        "marker.dt[1]",
        "marker.dt[2]",
    ) + tuple(f"compliance.{j}" for j in chain.joint_names)
    plain = S.SerialLayout(6)
    assert plain.size == 42 and plain.frame_slice == slice(42, 42) and plain.compliance_slice == slice(42, 42)
    assert plain.setup_columns.size == 0 and plain.names(chain) == chain.parameter_names()
    marker_only = S.SerialLayout(6, marker=6)
    assert marker_only.marker_slice == slice(42, 48) and marker_only.size == 48
    assert S.SerialLayout(6, compliance=True).compliance_slice == slice(42, 48)


@pytest.mark.parametrize("position_only", [False, True])
def test_jacobian_of_every_column_matches_finite_differences(ur5, position_only):
    """Placements, frame, marker and compliance columns at a non-nominal state with F, K and c set."""
    model, chain = ur5
    data = _measurements(model, chain, position_only)
    layout = S.SerialLayout(6, frame=True, marker=3 if position_only else 6, compliance=True)
    torques = S.gravity_torques(model, chain, data.q)
    rng = np.random.default_rng(41)
    whitening = np.linalg.inv(
        np.linalg.cholesky(  # any SPD covariance: the whitening is applied as a matrix
            np.array(
                [np.eye(data.rows_per_pose) + 0.3 * (a @ a.T) for a in rng.normal(size=(6, data.rows_per_pose, 2))]
            )
        )
    )
    residual = S.SerialResidual(chain, data, whitening, layout, torques)
    start = S.nominal_state(
        chain, perturb(model, {p: np.full(6, 2e-3) for p in chain.placements()}), MeasurementSetup(FRAME, MARKER)
    )
    state = residual.retract(
        start, np.r_[np.zeros(42), rng.normal(0.0, 1e-3, layout.size - 42 - 6), rng.normal(0.0, 1e-4, 6)]
    )
    np.testing.assert_array_equal(state.accumulated[:42], 0.0)
    assert state.compliance is not None and np.all(state.compliance != 0.0)
    r, J = residual.residual_and_jacobian(state)
    assert J.shape == (6 * data.rows_per_pose, layout.size)
    raw = residual.raw_residual(state)
    np.testing.assert_allclose(r, (whitening @ raw[:, :, None]).reshape(-1), rtol=1e-12, atol=1e-15)
    # The measured frame M = F g(q + c tau) K, as the raw residual's position part.
    g = tool_poses(
        chain, perturb(model, {p: np.full(6, 2e-3) for p in chain.placements()}), data.q + state.compliance * torques
    )
    predicted = state.frame @ g @ state.marker
    np.testing.assert_allclose(raw[:, :3], predicted[:, :3, 3] - data.positions, atol=1e-12)
    _assert_jacobian_is_the_retract_derivative(J, residual, state, layout)


def test_retract_accumulates_the_steps_in_layout_order(ur5):
    model, chain = ur5
    data = _measurements(model, chain)
    layout = S.SerialLayout(6, frame=True, marker=6, compliance=True)
    residual = S.SerialResidual(
        chain, data, np.broadcast_to(np.eye(6), (6, 6, 6)), layout, S.gravity_torques(model, chain, data.q)
    )
    start = S.nominal_state(chain, model)
    assert start.accumulated is None and start.compliance is None and start.plain
    a, b = np.linspace(1e-3, 2e-3, layout.size), np.linspace(-1e-3, 5e-4, layout.size)
    one = residual.retract(start, a)
    two = residual.retract(one, b)
    np.testing.assert_array_equal(one.accumulated, a)
    np.testing.assert_allclose(two.accumulated, a + b, rtol=0, atol=1e-18)
    np.testing.assert_allclose(two.compliance, a[layout.compliance_slice] + b[layout.compliance_slice], atol=1e-18)
    for j in range(7):
        expected = (
            start.transforms[j]
            @ pin.exp6(a[6 * j : 6 * j + 6]).homogeneous
            @ pin.exp6(b[6 * j : 6 * j + 6]).homogeneous
        )
        np.testing.assert_allclose(two.transforms[j], expected, atol=1e-14)
    np.testing.assert_allclose(two.frame, pin.exp6(a[42:48]).homogeneous @ pin.exp6(b[42:48]).homogeneous, atol=1e-14)
    np.testing.assert_allclose(two.marker, pin.exp6(a[48:54]).homogeneous @ pin.exp6(b[48:54]).homogeneous, atol=1e-14)
    assert not (two.transforms.flags.writeable or two.frame.flags.writeable or two.marker.flags.writeable)
    assert not (two.compliance.flags.writeable or two.accumulated.flags.writeable)
    # A zero twist leaves a placement's pose bit for bit; a 3-column marker moves the translation only.
    partial = residual.retract(start, np.r_[np.zeros(6), a[6:]])
    np.testing.assert_array_equal(partial.transforms[0], start.transforms[0])
    three = S.SerialResidual(chain, data, residual.whitening, S.SerialLayout(6, marker=3))
    moved = three.retract(start, np.r_[np.zeros(42), 1e-3, 2e-3, 3e-3])
    np.testing.assert_allclose(moved.marker, pin.exp6(np.r_[1e-3, 2e-3, 3e-3, 0, 0, 0]).homogeneous, atol=1e-15)
    np.testing.assert_array_equal(moved.frame, np.eye(4))
    assert moved.compliance is None


@pytest.mark.parametrize("position_only", [False, True])
def test_whitening_is_the_inverse_cholesky_factor_of_the_covariance(ur5, position_only):
    """Cov = diag(sigma^2) + sigma_q^2 J_q J_q^T, J_q by finite differences over the readings."""
    model, chain = ur5
    data = _measurements(model, chain, position_only)
    k, sigma_q = data.rows_per_pose, 3e-5
    state = S.nominal_state(chain, model, MeasurementSetup(FRAME, MARKER))
    sigmas = np.array([1e-5, 1e-5, 1e-5, 2e-5, 2e-5, 2e-5])[:k]
    exact = S.pose_whitening(chain, state, data, TRACKER, 0.0)
    np.testing.assert_array_equal(exact, np.broadcast_to(np.diag(1.0 / sigmas), (6, k, k)))
    assert exact.flags.writeable
    whitening = S.pose_whitening(chain, replace(state, compliance=np.zeros(6)), data, TRACKER, sigma_q)
    assert np.abs(np.tril(S.pose_whitening(chain, state, data, TRACKER, 1.0), -1)).max() > 0.0
    # The joint Jacobian of the residual at the state, F and K included.
    joint_jacobian = np.empty((6, k, 6))
    for j in range(6):
        shifted = []
        for h in (1e-7, -1e-7):
            q = data.q.copy()
            q[:, j] += h
            moved = S.SerialResidual(chain, replace(data, q=q), np.broadcast_to(np.eye(k), (6, k, k)))
            shifted.append(moved.raw_residual(state))
        joint_jacobian[:, :, j] = (shifted[0] - shifted[1]) / 2e-7
    covariance = np.diag(sigmas**2) + sigma_q**2 * joint_jacobian @ np.swapaxes(joint_jacobian, 1, 2)
    inverse = np.linalg.inv(whitening)
    np.testing.assert_allclose(inverse @ np.swapaxes(inverse, 1, 2), covariance, rtol=1e-6, atol=1e-16)
    assert np.abs(np.triu(whitening, 1)).max() < 1e-9 * np.abs(whitening).max()  # lower triangular: Cholesky's


def test_gravity_torques_are_pinocchios_on_the_chain_joints(ur5):
    model, chain = ur5
    q = sample_configurations(model, chain, 3, np.random.default_rng(42))
    torques = S.gravity_torques(model, chain, q)
    data = model.createData()
    for row, tau in zip(q, torques):
        np.testing.assert_array_equal(tau, pin.computeGeneralizedGravity(model, data, row))
    assert np.abs(torques).max() > 1.0
    single = S.gravity_torques(model, chain, list(q[1]))
    assert single.shape == (1, 6)
    np.testing.assert_array_equal(single[0], torques[1])


def test_compliant_readings_move_each_joint_by_its_compliance_times_pinocchios_gravity(ur5):
    model, chain = ur5
    q = sample_configurations(model, chain, 3, np.random.default_rng(43))
    compliance = {"shoulder_lift_joint": -2e-6, "elbow_joint": 3e-6}
    moved = S.compliant_readings(model, chain, q, compliance)
    data = model.createData()
    for row, read in zip(q, moved):
        tau = pin.computeGeneralizedGravity(model, data, row)
        np.testing.assert_allclose(read, row + np.array([0.0, -2e-6, 3e-6, 0.0, 0.0, 0.0]) * tau, rtol=0, atol=1e-15)
    assert np.all(moved[:, [0, 3, 4, 5]] == q[:, [0, 3, 4, 5]]) and np.all(moved[:, 1:3] != q[:, 1:3])
    np.testing.assert_array_equal(S.compliant_readings(model, chain, list(q[0]), {}), q[:1])
    assert S.moved_mass(model, chain) == pytest.approx(sum(model.inertias[j].mass for j in range(1, model.njoints)))


def test_a_chain_that_moves_no_mass_refuses_compliance_word_for_word(ur5):
    model, chain = ur5
    massless = model.copy()
    for j in range(massless.njoints):
        massless.inertias[j] = pin.Inertia.Zero()
    assert S.moved_mass(massless, chain) == 0.0
    message = (
        "the links that joints shoulder_pan_joint .. wrist_3_joint move have no mass (the URDF gives them no "
        "<inertial>): the gravity torques are zero in every posture, so joint compliance under gravity cannot be "
        "fitted or applied; use a URDF with the links' inertial elements, or leave out --compliance"
    )
    with pytest.raises(InvalidInputError) as caught:
        S.compliant_readings(massless, chain, np.zeros((1, 6)), {"elbow_joint": 1e-6})
    assert str(caught.value) == message
    np.testing.assert_array_equal(S.compliant_readings(massless, chain, np.zeros((1, 6)), {}), np.zeros((1, 6)))
    assert S.compliant_readings(massless, chain, [[0, 0, 0, 0, 0, 0]], {}).dtype == np.float64
    light = massless.copy()  # 0.1 kg per link: light, still loaded
    for j in range(1, light.njoints):
        light.inertias[j] = pin.Inertia(0.1, np.array([0.0, 0.0, 0.05]), np.eye(3) * 1e-4)
    assert S.moved_mass(light, chain) == pytest.approx(0.6)
    q = np.array([[0.0, -1.0, 1.0, 0.0, 0.0, 0.0]])
    moved = S.compliant_readings(light, chain, q, {"shoulder_lift_joint": 1e-3})
    np.testing.assert_allclose(moved, q + 1e-3 * np.array([[0, 1, 0, 0, 0, 0]]) * S.gravity_torques(light, chain, q))
    assert moved[0, 1] != q[0, 1]
    data = simulate_serial_measurements(model, chain, 5, np.random.default_rng(44), noise=TRACKER)
    with pytest.raises(InvalidInputError) as caught:
        calibrate_serial(massless, chain, data.q_readings, data.measured_poses, CalibrationOptions(compliance=True))
    assert str(caught.value) == message


def _plain_problem(model, chain, n_poses: int = 5, position_only: bool = False):
    data = _measurements(model, chain, position_only, n_poses=n_poses)
    state = S.nominal_state(chain, model, MeasurementSetup(FRAME, MARKER))
    residual = S.SerialResidual(chain, data, S.pose_whitening(chain, state, data, TRACKER, 0.0))
    return residual, state


def test_problem_masks_outlier_poses_and_appends_prior_rows(ur5):
    model, chain = ur5
    residual, state = _plain_problem(model, chain)  # 5 poses, 6 rows each
    plain = S.SerialProblem(residual, [3.0, 7.0])
    assert plain.columns.dtype.kind == "i" and plain.priors == {}
    assert plain.active.dtype == bool and plain.active.shape == (5,) and plain.active.all()
    r_full, J_full = residual.residual_and_jacobian(state)
    assert not (r_full.flags.writeable or J_full.flags.writeable or residual.raw_residual(state).flags.writeable)
    assert not S.nominal_state(chain, model).transforms.flags.writeable
    assert plain.residual(state) is r_full  # every pose, no prior: the residual itself
    r, J = plain.residual_and_jacobian(state)
    assert r is r_full
    np.testing.assert_array_equal(J, J_full[:, [3, 7]])

    priors = {7: 0.5, 20: 2e-3, 41: 1.0}  # column 41 is not fitted: no row
    problem = S.SerialProblem(residual, np.array([3, 7, 8, 20]), priors)
    assert problem.priors == priors and problem.priors is not priors
    r, J = problem.residual_and_jacobian(state)  # no step yet: the prior rows are zero
    assert r.shape == (32,) and J.shape == (32, 4)
    np.testing.assert_array_equal(r, np.r_[r_full, 0.0, 0.0])
    np.testing.assert_array_equal(J[:30], J_full[:, [3, 7, 8, 20]])
    np.testing.assert_array_equal(J[30:], [[0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 0.0, 500.0]])
    np.testing.assert_array_equal(problem.residual(state), r)

    moved = problem.retract(state, np.array([1e-3, 2e-3, -1e-3, 4e-3]))
    expected_step = np.zeros(42)
    expected_step[[3, 7, 8, 20]] = [1e-3, 2e-3, -1e-3, 4e-3]
    np.testing.assert_array_equal(moved.accumulated, expected_step)
    r_moved, J_moved = residual.residual_and_jacobian(moved)
    np.testing.assert_allclose(problem.residual(moved)[30:], [2e-3 / 0.5, 4e-3 / 2e-3], rtol=1e-15)

    problem.active = np.array([True, False, True, True, False])
    mask = np.repeat(problem.active, 6)
    r, J = problem.residual_and_jacobian(moved)
    np.testing.assert_array_equal(r[:30], np.where(mask, r_moved, 0.0))
    np.testing.assert_array_equal(J[:30], np.where(mask[:, None], J_moved[:, [3, 7, 8, 20]], 0.0))
    np.testing.assert_allclose(r[30:], [2e-3 / 0.5, 4e-3 / 2e-3], rtol=1e-15)
    np.testing.assert_array_equal(J[30:], [[0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 0.0, 500.0]])
    np.testing.assert_array_equal(problem.residual(moved), r)

    plain.active = problem.active.copy()  # outliers, no prior
    r, J = plain.residual_and_jacobian(moved)
    np.testing.assert_array_equal(r, np.where(mask, r_moved, 0.0))
    np.testing.assert_array_equal(J, np.where(mask[:, None], J_moved[:, [3, 7]], 0.0))
    np.testing.assert_array_equal(plain.residual(moved), r)


def test_rms_of_positions_and_rotations():
    residual = np.array([[3.0, 4.0, 0.0, 1.0, 2.0, 2.0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    rms = pose_error_rms(residual)
    assert rms.position == pytest.approx(np.sqrt(12.5), rel=1e-15)
    assert rms.rotation == pytest.approx(np.sqrt(4.5), rel=1e-15)
    positions = pose_error_rms(residual[:, :3])
    assert positions.position == pytest.approx(np.sqrt(12.5), rel=1e-15) and np.isnan(positions.rotation)


def test_prior_columns_by_parameter_or_placement(ur5):
    _, chain = ur5
    names = S.SerialLayout(6, compliance=True).names(chain)
    columns = prior_columns(
        names, {"shoulder_pan_joint": 1e-3, "compliance.elbow_joint": 0.5, "wrist_1_joint.dt[4]": 2}
    )
    assert columns == {**{c: 1e-3 for c in range(6)}, 44: 0.5, 22: 2.0}
    assert all(type(sigma) is float for sigma in columns.values())
    assert prior_columns(names, None) == {} and prior_columns(names, {}) == {}
    for sigma in (0.0, -1e-3, float("inf"), float("nan")):
        with pytest.raises(InvalidInputError) as error:
            prior_columns(names, {"elbow_joint": sigma})
        assert str(error.value) == "prior of 'elbow_joint': sigma must be a positive number (m, rad or rad/Nm)"
    with pytest.raises(
        InvalidInputError, match=r"^prior: 'nope' is neither a parameter \(e.g. shoulder_pan_joint.dt\[0\]\)"
    ):
        prior_columns(names, {"nope": 1.0})


def _exact_setup_data(model, chain, position_only: bool = False, n_poses: int = 8):
    """Measurements of the nominal robot through FRAME and MARKER, without noise."""
    q = sample_configurations(model, chain, n_poses, np.random.default_rng(43))
    measured = FRAME.homogeneous @ tool_poses(chain, model, q) @ MARKER.homogeneous
    return S.parse_measurements(chain, q, [pin.SE3(m) for m in measured], position_only)


def test_start_state_registers_the_frame_and_the_marker_rotation(ur5):
    model, chain = ur5
    data = _exact_setup_data(model, chain)
    given = S.start_state(chain, model, data, MeasurementSetup(FRAME, MARKER), False, False, False)
    np.testing.assert_array_equal(given.frame, FRAME.homogeneous)
    np.testing.assert_array_equal(given.marker, MARKER.homogeneous)
    np.testing.assert_array_equal(given.transforms, chain.initial_transforms(model))
    assert given.compliance is None and given.accumulated is None
    # The marker's position known, its axes not: the frame from the positions, then the rotation.
    axes_unknown = MeasurementSetup(marker=pin.SE3(np.eye(3), MARKER.translation))
    both = S.start_state(chain, model, data, axes_unknown, True, True, False)
    np.testing.assert_allclose(both.frame, FRAME.homogeneous, atol=1e-9)
    np.testing.assert_allclose(both.marker, MARKER.homogeneous, atol=1e-9)
    assert not (both.frame.flags.writeable or both.marker.flags.writeable)
    frame_only = S.start_state(chain, model, data, axes_unknown, True, False, True)
    np.testing.assert_array_equal(frame_only.marker, axes_unknown.marker.homogeneous)
    np.testing.assert_array_equal(frame_only.compliance, np.zeros(6))
    assert not frame_only.compliance.flags.writeable
    marker_only = S.start_state(
        chain, model, data, MeasurementSetup(FRAME, pin.SE3(np.eye(3), MARKER.translation)), False, True, False
    )
    np.testing.assert_array_equal(marker_only.frame, FRAME.homogeneous)
    np.testing.assert_allclose(marker_only.marker, MARKER.homogeneous, atol=1e-9)
    # Positions only: no rotation to register the marker's axes with.
    positions = _exact_setup_data(model, chain, position_only=True)
    kept = S.start_state(chain, model, positions, axes_unknown, True, True, False)
    np.testing.assert_array_equal(kept.marker, axes_unknown.marker.homogeneous)
    np.testing.assert_allclose(kept.frame, FRAME.homogeneous, atol=1e-9)


def _lm(calls):
    """Stands in for `pipeline.fit`: LM with the serial fit's settings, each call recorded."""

    def solve(problem, state, settings=None):
        result = levenberg_marquardt(
            problem,
            state,
            LMSettings(max_iterations=30, initial_damping=1e-6, absolute_cost_tolerance=1e-6),
        )
        calls.append((len(problem.columns), state, result))
        return result

    return solve


def _problem(model, chain, data, layout, setup=MeasurementSetup()):
    start = S.start_state(chain, model, data, setup, layout.frame, bool(layout.marker), layout.compliance)
    torques = S.gravity_torques(model, chain, data.q) if layout.compliance else None
    residual = S.SerialResidual(chain, data, S.pose_whitening(chain, start, data, TRACKER, 0.0), layout, torques)
    return S.SerialProblem(residual, np.arange(layout.size)), start


@pytest.mark.parametrize("compliance", [False, True])
def test_fit_base_reselects_at_the_estimate_while_the_rank_grows(ur5, compliance, monkeypatch):
    """Positions only: the nominal UR5's tool on the last axis hides 2 parameters; one re-selection
    at the estimate finds them, a second one finds no more and stops."""
    model, chain = ur5
    simulated = simulate_serial_measurements(model, chain, 40, np.random.default_rng(44), noise=TRACKER)
    data = S.parse_measurements(chain, simulated.q_readings, simulated.measured_poses, True)
    layout = S.SerialLayout(6, compliance=compliance)
    problem, start = _problem(model, chain, data, layout)
    calls = []
    monkeypatch.setattr(pipeline, "fit", _lm(calls))
    base, result, iterations, _ = pipeline.fit_base(problem, start, CalibrationOptions(rank_tolerance=1e-9), [])
    extra = 3 if compliance else 0  # compliances seen from these poses (none for the vertical base axis)
    assert [c[0] for c in calls] == [25 + extra, 27 + extra]
    assert calls[0][1] is start and calls[1][1] is calls[0][2].state and result is calls[1][2]
    assert base.rank == chain.rank_bound(True) + extra
    assert iterations == calls[0][2].iterations + calls[1][2].iterations
    np.testing.assert_array_equal(problem.columns, base.indices)


def test_a_base_at_the_structural_bound_is_not_chosen_again_at_the_estimate(ur5, monkeypatch):
    """Full poses: the start identifies the bound 4 r + 2 p + 6 = 30 already, so the base is chosen once
    (one Jacobian factor, at the start) and LM runs once; positions only (25 of 27 at the start), twice."""
    model, chain = ur5
    simulated = simulate_serial_measurements(model, chain, 20, np.random.default_rng(44), noise=TRACKER)
    for position_only, factors, fits in ((False, 1, 1), (True, 3, 2)):
        data = S.parse_measurements(chain, simulated.q_readings, simulated.measured_poses, position_only)
        problem, start = _problem(model, chain, data, S.SerialLayout(6))
        taken = []
        jacobian_factor = problem.jacobian_factor
        monkeypatch.setattr(
            problem, "jacobian_factor", lambda state, *args: taken.append(state) or jacobian_factor(state)
        )
        calls = []
        monkeypatch.setattr(pipeline, "fit", _lm(calls))
        base = pipeline.fit_base(problem, start, CalibrationOptions(rank_tolerance=1e-9), [])[0]
        assert base.rank == problem.reselection_bound() == (27 if position_only else 30)
        assert len(taken) == factors and taken[0] is start and len(calls) == fits


def test_lm_stops_at_the_step_significance_per_degree_of_freedom_and_the_serial_defaults(ur5):
    """The relative cost test is the larger of `cost_tolerance` and `step_significance` noise variances:
    1/2 chi^2 of N k rows over r base parameters is about (N k - r) / 2 variances, so a decrease of s
    variances is 2 s / (N k - r) of the cost (at least one degree of freedom). A serial fit's defaults:
    30 iterations, a relative tolerance of 1e-12 and no significance; the absolute tolerance is passed on."""
    model, chain = ur5

    def settings(n_poses: int, **options) -> LMSettings:
        data = simulate_serial_measurements(model, chain, n_poses, np.random.default_rng(56), noise=TRACKER)
        options = {"noise": TRACKER, "outlier_sigma": None, **options}
        calibration = calibrate_serial(
            model, chain, data.q_readings, data.measured_poses, CalibrationOptions(**options)
        )
        assert calibration.base.rank == 30  # 4 r + 2 p + 6 of the UR5's revolute joints, full poses
        return calibration.settings

    assert settings(12) == LMSettings(30, 1e-12, 1e-6, 1e-6)
    assert settings(12, absolute_cost_tolerance=1e-3, max_iterations=7) == LMSettings(7, 1e-12, 1e-3, 1e-6)
    assert settings(12, step_significance=0.5).cost_tolerance == pytest.approx(2.0 * 0.5 / (12 * 6 - 30), rel=1e-12)
    assert settings(12, step_significance=0.5, cost_tolerance=0.1).cost_tolerance == 0.1
    assert settings(12, step_significance=1e-3, cost_tolerance=1e-5).cost_tolerance == pytest.approx(2e-3 / 42)
    # 5 poses, 30 rows for 30 parameters: no degree of freedom, counted as one.
    assert settings(5, step_significance=0.5).cost_tolerance == pytest.approx(1.0, rel=1e-12)


def test_select_base_keeps_the_setup_first_and_leaves_fixed_columns_out(ur5):
    model, chain = ur5
    data = _exact_setup_data(model, chain, n_poses=20)
    layout = S.SerialLayout(6, frame=True, marker=6)
    problem, start = _problem(model, chain, data, layout, MeasurementSetup(FRAME, MARKER))
    base = pipeline.choose_base(problem, start, 1e-9, [])[0]
    assert set(range(42, 54)) <= set(base.indices) and base.rank == 4 * 6 + 6
    assert not set(base.indices) & (set(range(6)) | set(range(36, 42)))  # first and tool placements: the gauge
    elbow = list(range(12, 18))
    fixed = pipeline.choose_base(problem, start, 1e-9, elbow)[0]
    assert not set(fixed.indices) & set(elbow)
    assert fixed.rank < base.rank
    assert np.all(np.abs(problem.model.residual_and_jacobian(start)[1][:, elbow]).max(axis=0) > 0.0)  # not zeroed
    loose = pipeline.choose_base(problem, start, float(np.median(base.r_diag_ratio)), [])[0]
    assert loose.rank < base.rank  # the tolerance is passed on


class _Fixed:
    """A solver stand-in returning given states in turn, with given iteration counts."""

    def __init__(self, states, iterations):
        self.outcomes = [SimpleNamespace(state=s, iterations=i) for s, i in zip(states, iterations)]
        self.calls = []

    def __call__(self, problem, state, settings=None):
        self.calls.append((problem.active.copy(), state))
        return self.outcomes[len(self.calls) - 1]


def _outlier_problem(model, chain, errors: dict[int, float], n_poses: int = 10):
    """Positions of the nominal robot, exact but for `errors` {pose: m along x}; 27 columns."""
    q = sample_configurations(model, chain, n_poses, np.random.default_rng(45))
    positions = tool_poses(chain, model, q)[:, :3, 3]
    for pose, error in errors.items():
        positions[pose, 0] += error
    data = S.parse_measurements(chain, q, positions, True)
    start = S.nominal_state(chain, model)
    residual = S.SerialResidual(chain, data, S.pose_whitening(chain, start, data, TRACKER, 0.0))
    return S.SerialProblem(residual, np.arange(27)), start


#: The settings the pipeline's steps pass on to `pipeline.fit` (stood in for by `_Fixed` and `_lm`).
SETTINGS = LMSettings(max_iterations=30, cost_tolerance=1e-12, absolute_cost_tolerance=1e-6, initial_damping=1e-6)


def _reject(monkeypatch, problem, start, result, sigma, solve):
    monkeypatch.setattr(pipeline, "fit", solve)
    return pipeline.reject_outliers(problem, start, result, sigma, SETTINGS)


def test_outliers_are_judged_at_the_fit_and_refitted_from_the_start(ur5, monkeypatch):
    model, chain = ur5
    problem, start = _outlier_problem(model, chain, {2: 1.0, 5: 1.5e-4}, 20)  # 1 m and 15 sigma
    # At a state whose marker is 0.1 mm off every pose is 10 sigma off: the robust scale widens the
    # gate, and the 15-sigma pose passes.
    marker = pin.SE3(np.eye(3), np.array([0.0, 0.0, 1e-4])).homogeneous
    marker.flags.writeable = False  # as the states' arrays are
    shifted = replace(start, marker=marker)
    solve = _Fixed([shifted, shifted], [7, 4])
    result, iterations = _reject(monkeypatch, problem, start, SimpleNamespace(state=start), 5.0, solve)
    flagged_first = np.isin(np.arange(20), [2, 5])
    assert [c[1] is start for c in solve.calls] == [True, True]
    np.testing.assert_array_equal(solve.calls[0][0], ~flagged_first)
    np.testing.assert_array_equal(solve.calls[1][0], np.arange(20) != 2)
    np.testing.assert_array_equal(problem.active, np.arange(20) != 2)
    assert result is solve.outcomes[1] and iterations == 11
    # The gate in sigmas is the caller's: at 20 sigma the 15-sigma pose stays; once stable, no refit.
    problem, start = _outlier_problem(model, chain, {2: 1.0, 5: 1.5e-4}, 20)
    solve = _Fixed([start], [3])
    result, iterations = _reject(monkeypatch, problem, start, SimpleNamespace(state=start), 20.0, solve)
    np.testing.assert_array_equal(problem.active, np.arange(20) != 2)
    assert len(solve.calls) == 1 and result is solve.outcomes[0] and iterations == 3
    problem, start = _outlier_problem(model, chain, {}, 20)
    given = SimpleNamespace(state=start)
    assert _reject(monkeypatch, problem, start, given, 5.0, _Fixed([], [])) == (given, 0)


def test_too_few_poses_left_after_the_outliers(ur5, monkeypatch):
    model, chain = ur5
    # 10 poses of 3 rows: 9 left give 27 rows, too few for 27 columns, enough for 26.
    problem, start = _outlier_problem(model, chain, {1: 1.0})
    with pytest.raises(IdentificationError) as error:
        _reject(monkeypatch, problem, start, SimpleNamespace(state=start), 5.0, _Fixed([], []))
    assert str(error.value) == "1 of 10 poses are outliers: too few poses are left to fit the model"
    assert problem.active.all()
    problem.columns = np.arange(26)
    solve = _Fixed([start], [1])
    _reject(monkeypatch, problem, start, SimpleNamespace(state=start), 5.0, solve)
    assert len(solve.calls) == 1
    np.testing.assert_array_equal(problem.active, np.arange(10) != 1)


def _assert_same_selection(selection, expected):
    """The same choices, and scores equal to rounding (the pose rows are products of other BLAS calls)."""
    assert (selection.indices, selection.order, selection.tied) == (expected.indices, expected.order, expected.tied)
    np.testing.assert_allclose(selection.path, expected.path, rtol=1e-9)
    assert selection.press == pytest.approx(expected.press, rel=1e-9)
    assert selection.press_all == pytest.approx(expected.press_all, rel=1e-9)


def test_selection_scores_the_fit_linearised_at_the_estimate(ur5, monkeypatch):
    """Forward selection of the columns by PRESS of r - J x at the estimate, the frame forced, one pose
    left out; a smaller set is refitted from the start."""
    model, chain = ur5
    truth = perturb(model, {Placement.joint("elbow_joint"): np.array([1e-3, 0, 0, 0, 2e-3, 0])})
    q = sample_configurations(model, chain, 15, np.random.default_rng(46))
    rng = np.random.default_rng(47)
    measured = FRAME.homogeneous @ tool_poses(chain, truth, q) @ MARKER.homogeneous
    measured[:, :3, 3] += rng.normal(0.0, TRACKER.position, (15, 3))
    data = S.parse_measurements(chain, q, [pin.SE3(m) for m in measured], True)
    layout = S.SerialLayout(6, frame=True)
    problem, start = _problem(model, chain, data, layout, MeasurementSetup(marker=MARKER))
    calls = []
    monkeypatch.setattr(pipeline, "fit", _lm(calls))
    base, fit, _, _ = pipeline.fit_base(problem, start, CalibrationOptions(rank_tolerance=1e-9), [])
    problem.active[3] = False
    columns = problem.columns.copy()
    r, J = problem.model.residual_and_jacobian(fit.state)
    keep = np.repeat(problem.active, 3)
    forced = np.flatnonzero(columns >= 42)
    assert forced.size == 6
    expected = forward_selection(
        J[keep][:, columns], (r - J[:, columns] @ fit.state.accumulated[columns])[keep], 3, range(len(columns)), forced
    )
    calls.clear()
    selection, refit, iterations = pipeline.select_parameters(problem, start, fit, SETTINGS)
    _assert_same_selection(selection, expected)
    assert 6 < len(selection.indices) < len(columns)
    np.testing.assert_array_equal(problem.columns, columns[list(selection.indices)])
    assert len(calls) == 1 and calls[0][1] is start and refit is calls[0][2] and iterations == refit.iterations
    # Every column kept: no refit.
    problem.columns = columns[list(selection.indices)]
    again, same, none = pipeline.select_parameters(problem, start, refit, SETTINGS)
    assert len(again.indices) == len(problem.columns) and same is refit and none == 0 and len(calls) == 1


def test_result_reports_every_candidate_and_the_fitted_ones(ur5):
    model, chain = ur5
    rng = np.random.default_rng(48)
    truth = perturb(model, {p: rng.normal(0.0, 5e-4, 6) for p in chain.placements()})
    q = sample_configurations(model, chain, 30, rng)
    compliance = np.array([0.0, 2e-4, 3e-4, 0.0, 0.0, 0.0])  # rad/Nm, large enough to be seen
    measured = (
        FRAME.homogeneous
        @ tool_poses(chain, truth, q + compliance * S.gravity_torques(model, chain, q))
        @ MARKER.homogeneous
    )
    measured[:, :3, 3] += rng.normal(0.0, TRACKER.position, (30, 3))
    calibration = calibrate_serial(
        model,
        chain,
        q,
        [pin.SE3(m) for m in measured],
        CalibrationOptions(
            noise=TRACKER,
            setup=MeasurementSetup(marker=MARKER),
            estimate_frame=True,
            compliance=True,
            fixed=["wrist_3_joint"],
            priors={"elbow_joint": 1e-2},
        ),
    )
    layout = S.SerialLayout(6, frame=True, compliance=True)
    names = layout.names(chain)
    assert calibration.names == names and calibration.outliers == ()
    assert calibration.fitted == tuple(names[i] for i in calibration.fitted_indices)
    assert all(type(i) is int for i in calibration.fitted_indices)
    assert not set(calibration.fitted_indices) & set(range(30, 36))  # wrist_3_joint held
    assert calibration.converged and calibration.termination in ("gradient", "step", "cost")
    values = calibration.values
    assert values.shape == (layout.size,) and not values.flags.writeable
    np.testing.assert_array_equal(values[:42], np.concatenate([calibration.deltas[p] for p in chain.placements()]))
    fitted_compliance = {names[i].removeprefix("compliance.") for i in calibration.fitted_indices if i >= 48}
    assert (
        set(calibration.compliance) == fitted_compliance and {"shoulder_lift_joint", "elbow_joint"} <= fitted_compliance
    )
    for k, joint in enumerate(chain.joint_names):
        assert values[48 + k] == calibration.compliance.get(joint, 0.0)
    assert calibration.compliance["shoulder_lift_joint"] == pytest.approx(2e-4, rel=0.05)
    # The frame's value: the sum of its steps, the change from the registered start to first order.
    data = S.parse_measurements(chain, q, [pin.SE3(m) for m in measured], False)
    start_frame = pin.SE3(S.start_state(chain, model, data, MeasurementSetup(marker=MARKER), True, False, True).frame)
    change = pin.log6(start_frame.actInv(calibration.setup.frame)).vector
    assert np.abs(change).max() > 1e-4
    np.testing.assert_allclose(values[42:48], change, atol=1e-6 + 1e-2 * np.abs(change).max())
    np.testing.assert_array_equal(calibration.setup.marker.homogeneous, MARKER.homogeneous)
    assert np.abs(pin.log6(FRAME.actInv(calibration.setup.frame)).vector).max() < 1e-2
    std = calibration.std()
    assert list(std) == list(calibration.fitted) and all(type(s) is float for s in std.values())
    np.testing.assert_array_equal(list(std.values()), calibration.parameter_std)


def test_covariance_is_the_noise_models_not_the_residuals(ur5):
    """Twice the stated noise: four times the covariance, a quarter of the variance factor."""
    model, chain = ur5
    data = simulate_serial_measurements(model, chain, 20, np.random.default_rng(49), noise=TRACKER)
    one = calibrate_serial(model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=TRACKER))
    two = calibrate_serial(
        model,
        chain,
        data.q_readings,
        data.measured_poses,
        CalibrationOptions(noise=TrackerNoise(2 * TRACKER.position, 2 * TRACKER.rotation)),
    )
    assert one.fitted == two.fitted
    np.testing.assert_allclose(two.covariance, 4.0 * one.covariance, rtol=1e-6)
    np.testing.assert_allclose(two.parameter_std, 2.0 * one.parameter_std, rtol=1e-6)
    assert two.variance_factor == pytest.approx(one.variance_factor / 4.0, rel=1e-6)


def test_exact_nominal_measurements_take_no_step(ur5):
    model, chain = ur5
    q = sample_configurations(model, chain, 12, np.random.default_rng(50))
    calibration = calibrate_serial(
        model, chain, q, [pin.SE3(g) for g in tool_poses(chain, model, q)], CalibrationOptions(noise=TRACKER)
    )
    assert calibration.iterations == 0 and calibration.converged
    np.testing.assert_array_equal(calibration.values, np.zeros(42))
    assert calibration.compliance == {} and calibration.rms_after.position < 1e-12


def test_measurement_parsing_and_its_exact_refusals(ur5):
    model, chain = ur5
    data = simulate_serial_measurements(model, chain, 4, np.random.default_rng(51), noise=TRACKER)
    q, poses = data.q_readings, list(data.measured_poses)
    homogeneous = np.array([g.homogeneous for g in poses])
    rows = np.array([pin.SE3ToXYZQUAT(g) for g in poses])

    def refused(message, q_readings, measured, position_only=False):
        with pytest.raises(InvalidInputError) as error:
            S.parse_measurements(chain, q_readings, measured, position_only)
        assert str(error.value) == message

    from_se3 = S.parse_measurements(chain, q.tolist(), poses, False)
    assert from_se3.q.dtype == float and from_se3.rows_per_pose == 6
    np.testing.assert_array_equal(from_se3.q, q)
    np.testing.assert_array_equal(from_se3.positions, homogeneous[:, :3, 3])
    np.testing.assert_array_equal(from_se3.rotations, homogeneous[:, :3, :3])
    assert from_se3.positions.flags.c_contiguous and from_se3.rotations.flags.c_contiguous
    from_rows = S.parse_measurements(chain, q, rows, False)
    np.testing.assert_array_equal(from_rows.positions, rows[:, :3])
    np.testing.assert_allclose(from_rows.rotations, homogeneous[:, :3, :3], atol=1e-15)
    from_lists = S.parse_measurements(chain, q, rows.tolist(), False)  # a Sequence, but of rows
    np.testing.assert_array_equal(from_lists.rotations, from_rows.rotations)
    for measured in (poses, rows, rows[:, :3]):
        positions_only = S.parse_measurements(chain, q, measured, True)
        assert positions_only.rotations is None and positions_only.rows_per_pose == 3
        np.testing.assert_allclose(positions_only.positions, homogeneous[:, :3, 3], atol=1e-15)
    integers = S.parse_measurements(chain, q.astype(int), rows.round().astype(int)[:, :3], True)
    assert integers.q.dtype == float and integers.positions.dtype == float

    refused("q_readings: expected shape (N, 6), got (6,)", q[0], rows[:1])
    refused("q_readings: expected shape (N, 6), got (4, 5)", q[:, :5], rows)
    bad_q = q.copy()
    bad_q[2, 4] = np.inf
    refused("q_readings: non-finite value in row 2", bad_q, rows)
    refused("measured_poses: row 1 is not an SE3 like the others", q, [poses[0], rows[1], *poses[2:]])
    expected = "measured_poses: expected SE3 objects, (N, 7) [x, y, z, qx, qy, qz, qw] or (N, 3) positions, got shape "
    refused(expected + "(4, 6)", q, rows[:, :6])
    refused(expected + "(28,)", q, rows.reshape(-1))
    bad_rows = rows.copy()
    bad_rows[3, 0] = np.nan
    refused("measured_poses: non-finite value in row 3", q, bad_rows)
    refused("measured_poses: positions only (N, 3) need position_only=True", q, rows[:, :3])
    refused("4 joint readings but 3 measured poses", q, rows[:3])
    refused("4 joint readings but 3 measured poses", q, poses[:3])
    twice = rows.copy()
    twice[1, 3:] *= 2.0
    refused(f"measured_poses: quaternion of row 1 has norm {np.linalg.norm(twice[1, 3:]):.6g}", q, twice)
    complex_values = ": complex values given; joint values and coordinates are real numbers"
    refused("q_readings" + complex_values, q + 1e-3j, rows)
    refused("measured_poses" + complex_values, q, rows + 1e-3j)
    # (N, 4, 4) homogeneous matrices are not a format: refused as poses, not read as 4 points of 4 coordinates.
    refused(expected + "(4, 4, 4)", q, homogeneous)


@pytest.mark.parametrize(
    "layout", [S.SerialLayout(6, frame=True), S.SerialLayout(6, marker=6), S.SerialLayout(6, frame=True, marker=6)]
)
def test_setup_columns_at_the_identity_setup(ur5, layout):
    """An identity frame and marker (a plain state) still give the setup's columns."""
    model, chain = ur5
    data = S.parse_measurements(
        chain,
        *(lambda d: (d.q_readings, d.measured_poses))(
            simulate_serial_measurements(model, chain, 5, np.random.default_rng(52), noise=TRACKER)
        ),
        False,
    )
    residual = S.SerialResidual(chain, data, np.broadcast_to(np.eye(6), (5, 6, 6)), layout)
    state = S.nominal_state(chain, model)
    assert state.plain
    _, J = residual.residual_and_jacobian(state)
    columns = np.arange(42, layout.size)
    numeric = np.empty((30, columns.size))
    for i, c in enumerate(columns):
        dx = np.zeros(layout.size)
        dx[c] = 1e-7
        numeric[:, i] = (
            residual.residual(residual.retract(state, dx)) - residual.residual(residual.retract(state, -dx))
        ) / 2e-7
    assert np.linalg.norm(J[:, columns] - numeric) <= 1e-6 * np.linalg.norm(numeric)


def test_gravity_torques_of_a_chain_shorter_than_the_model(ur5):
    model, _ = ur5
    chain = SerialChain.from_model(model, "forearm_link")  # 3 of the 6 joints; the others at neutral
    q = np.array([[0.1, -1.0, 0.5], [0.0, -0.3, 1.2]])
    torques = S.gravity_torques(model, chain, q)
    assert torques.shape == (2, 3)
    data = model.createData()
    for row, tau in zip(q, torques):
        np.testing.assert_array_equal(tau, pin.computeGeneralizedGravity(model, data, np.r_[row, 0.0, 0.0, 0.0])[:3])


def test_degrees_of_freedom_zero_gives_no_variance_factor(ur5):
    """Positions only, 9 poses for 27 base parameters: no redundancy (nan); a prior adds one row."""
    model, chain = ur5
    data = simulate_serial_measurements(model, chain, 9, np.random.default_rng(53), noise=TRACKER)
    rows = np.array([g.translation for g in data.measured_poses])
    exact = calibrate_serial(
        model, chain, data.q_readings, rows, CalibrationOptions(noise=TRACKER, outlier_sigma=None), position_only=True
    )
    assert len(exact.fitted) == 27 and np.isnan(exact.variance_factor)
    one = calibrate_serial(
        model,
        chain,
        data.q_readings,
        rows,
        CalibrationOptions(noise=TRACKER, outlier_sigma=None, priors={"elbow_joint.dt[0]": 1e-3}),
        position_only=True,
    )
    assert len(one.fitted) == 27 and np.isfinite(one.variance_factor) and one.variance_factor > 0.0


def test_selection_and_outliers_reach_the_result(ur5):
    model, chain = ur5
    data = simulate_serial_measurements(model, chain, 20, np.random.default_rng(54), noise=TRACKER)
    measured = list(data.measured_poses)
    measured[7] = pin.SE3(measured[7].rotation, measured[7].translation + np.array([5e-3, 0.0, 0.0]))
    calibration = calibrate_serial(
        model, chain, data.q_readings, measured, CalibrationOptions(noise=TRACKER, select=True)
    )
    assert calibration.outliers == (7,)
    assert calibration.selection is not None
    assert len(calibration.selection.indices) == len(calibration.fitted)
    # Cross-validation reruns the fit, outliers and selection left as they were, on the inliers.
    folds = serial_evaluation.cross_validate_serial(calibration, folds=3)
    assert folds.folds == 3 and len(folds.errors.position) == 19 and np.all(np.isfinite(folds.errors.position))


def test_selection_at_the_start_scores_the_residual_itself(ur5):
    """No step taken yet (accumulated None): the linearised residual is the residual."""
    model, chain = ur5
    simulated = simulate_serial_measurements(model, chain, 15, np.random.default_rng(55), noise=TRACKER)
    data = S.parse_measurements(chain, simulated.q_readings, simulated.measured_poses, False)
    problem, start = _problem(model, chain, data, S.SerialLayout(6))
    problem.columns = np.arange(0, 42, 2)
    r, J = problem.model.residual_and_jacobian(start)
    expected = forward_selection(J[:, problem.columns], r, 6, range(21), np.array([], dtype=int))
    selection, _, _ = pipeline.select_parameters(problem, start, SimpleNamespace(state=start, iterations=0), SETTINGS)
    assert selection == expected


def test_selection_leaves_each_group_of_repeats_out_whole(ur5):
    """groups: poses sharing a label are left out together (`repeats.grouped_blocks` of the inliers'
    rows and labels, a flagged pose's label dropped with its rows): the PRESS of pairs left out."""
    model, chain = ur5
    simulated = simulate_serial_measurements(model, chain, 15, np.random.default_rng(55), noise=TRACKER)
    data = S.parse_measurements(chain, simulated.q_readings, simulated.measured_poses, False)
    problem, start = _problem(model, chain, data, S.SerialLayout(6))
    columns = np.arange(0, 42, 2)
    problem.active[4] = False
    groups = np.arange(15) // 2  # pairs of poses: 0 and 1, 2 and 3, ...
    r, J = problem.model.residual_and_jacobian(start)
    keep = np.repeat(problem.active, 6)
    grouped = grouped_blocks(J[keep][:, columns], r[keep], 6, groups[problem.active])
    expected = forward_selection(*grouped, range(21), np.array([], dtype=int))
    at_start = SimpleNamespace(state=start, iterations=0)
    problem.columns = columns
    selection, _, _ = pipeline.select_parameters(problem, start, at_start, SETTINGS, groups)
    _assert_same_selection(selection, expected)
    problem.columns = columns
    one_by_one = pipeline.select_parameters(problem, start, at_start, SETTINGS)[0]
    assert abs(one_by_one.press_all - selection.press_all) > 1e-3 * selection.press_all


def test_the_calibrations_selection_leaves_the_given_groups_out_whole(ur5):
    """`groups` reach the selection of a calibration: every pose measured twice and the pair labelled
    as one group gives each pair's leave-out error of the single set twice (PRESS doubled at every step
    of the same path); without the labels each copy is predicted by its twin, and the path differs."""
    model, chain = ur5
    data = simulate_serial_measurements(model, chain, 15, np.random.default_rng(57), noise=TRACKER)
    twice = np.repeat(data.q_readings, 2, axis=0), [pose for pose in data.measured_poses for _ in range(2)]
    once = calibrate_serial(
        model, chain, data.q_readings, data.measured_poses, CalibrationOptions(TRACKER, select=True)
    )
    paired = calibrate_serial(model, chain, *twice, CalibrationOptions(TRACKER, select=True, groups=np.arange(30) // 2))
    flat = calibrate_serial(model, chain, *twice, CalibrationOptions(TRACKER, select=True))
    assert once.selection is not None and paired.selection is not None and flat.selection is not None
    assert paired.selection.order == once.selection.order
    np.testing.assert_allclose(paired.selection.path, 2.0 * np.array(once.selection.path), rtol=1e-6)
    assert paired.selection.press == pytest.approx(2.0 * once.selection.press, rel=1e-6)
    assert np.abs(np.array(flat.selection.path) / paired.selection.path - 1.0).max() > 0.1


def test_orientation_residual_near_a_half_turn(ur5):
    """A marker whose axes are off by nearly pi: log3's fallback near pi, on the 3 x 3 rotation."""
    model, chain = ur5
    q = sample_configurations(model, chain, 3, np.random.default_rng(56))
    turned = tool_poses(chain, model, q) @ pin.SE3(pin.utils.rotate("x", 3.1), np.zeros(3)).homogeneous
    data = S.parse_measurements(chain, q, [pin.SE3(m) for m in turned], False)
    residual = S.SerialResidual(chain, data, np.broadcast_to(np.eye(6), (3, 6, 6)))
    raw = residual.raw_residual(S.nominal_state(chain, model))
    np.testing.assert_allclose(raw, np.tile([0.0, 0.0, 0.0, -3.1, 0.0, 0.0], (3, 1)), atol=1e-12)


# --------------------------------------------------------------------------------------------------
# Several points per pose: (N, P, 3) measured positions of P points on the tool

POINT_OFFSETS = np.array([[0.05, 0.0, 0.02], [-0.03, 0.04, 0.06], [0.0, -0.05, 0.1]])


def _point_measurements(model, chain, n_poses: int, seed: int, truth=None, offsets=POINT_OFFSETS):
    """Exact (N, P, 3) points F g(q) p_k of `truth` (default the nominal model) at sampled postures, P
    the offsets' (default the three of POINT_OFFSETS)."""
    q = sample_configurations(model, chain, n_poses, np.random.default_rng(seed))
    g = tool_poses(chain, model if truth is None else truth, q)
    return q, MeasurementSetup(FRAME, points=tuple(map(tuple, offsets))).measured_points(g)


def test_point_jacobian_of_every_column_matches_finite_differences(ur5):
    """Placements, frame, point offsets and compliance columns of a point fit at a non-nominal state."""
    model, chain = ur5
    q, points = _point_measurements(model, chain, 6, 60)
    data = S.parse_measurements(chain, q, points, False)
    assert data.n_points == 3 and data.rows_per_pose == 9
    layout = S.SerialLayout(6, frame=True, marker=9, compliance=True, points=3)
    assert layout.names(chain)[48:57] == tuple(f"marker.p{k}.dt[{j}]" for k in (1, 2, 3) for j in (0, 1, 2))
    assert layout.names(chain)[57:] == tuple(f"compliance.{joint}" for joint in chain.joint_names)
    residual = S.SerialResidual(
        chain, data, np.broadcast_to(np.eye(9), (6, 9, 9)), layout, S.gravity_torques(model, chain, q)
    )
    truth = perturb(model, {p: np.full(6, 2e-3) for p in chain.placements()})
    start = replace(S.nominal_state(chain, truth, MeasurementSetup(FRAME)), points=POINT_OFFSETS)
    rng = np.random.default_rng(61)
    state = residual.retract(start, np.r_[np.zeros(42), rng.normal(0.0, 1e-3, 15), rng.normal(0.0, 1e-4, 6)])
    assert state.compliance is not None and state.points is not None
    # The raw residual: F g(q + c tau) p_k - measured, point by point.
    g = tool_poses(chain, truth, q + state.compliance * S.gravity_torques(model, chain, q))
    predicted = np.einsum("nij,pj->npi", (state.frame @ g)[:, :3, :3], state.points) + (state.frame @ g)[:, None, :3, 3]
    np.testing.assert_allclose(residual.raw_residual(state), (predicted - points).reshape(6, 9), atol=1e-12)
    _, J = residual.residual_and_jacobian(state)
    _assert_jacobian_is_the_retract_derivative(J, residual, state, layout)


def test_point_whitening_decouples_the_points_not_seen(ur5):
    """A hidden point's rows are zero; the rows seen are whitened by the inverse Cholesky factor of
    their own covariance diag(sigma^2) + sigma_q^2 J_q J_q^T (J_q by finite differences)."""
    model, chain = ur5
    q, points = _point_measurements(model, chain, 4, 66)
    points[0, 0] = points[2, 1] = np.nan
    data = S.parse_measurements(chain, q, points, False)
    state = replace(S.nominal_state(chain, model, MeasurementSetup(FRAME)), points=POINT_OFFSETS)
    seen = np.isfinite(points).reshape(4, 9)
    exact = S.pose_whitening(chain, state, data, TRACKER, 0.0)
    np.testing.assert_array_equal(exact, np.eye(9)[None] * seen[:, :, None] / 1e-5)
    sigma_q = 3e-5
    whitening = S.pose_whitening(chain, state, data, TRACKER, sigma_q)
    unit = np.broadcast_to(np.eye(9), (4, 9, 9))
    joint_jacobian = np.empty((4, 9, 6))
    for j in range(6):
        shifted = []
        for h in (1e-7, -1e-7):
            moved = q.copy()
            moved[:, j] += h
            residual = S.SerialResidual(
                chain, S.parse_measurements(chain, moved, points, False), unit, S.SerialLayout(6)
            )
            shifted.append(np.nan_to_num(residual.raw_residual(state)))
        joint_jacobian[:, :, j] = (shifted[0] - shifted[1]) / 2e-7
    for n in range(4):
        rows = np.flatnonzero(seen[n])
        covariance = 1e-10 * np.eye(rows.size) + sigma_q**2 * joint_jacobian[n, rows] @ joint_jacobian[n, rows].T
        np.testing.assert_allclose(
            whitening[n][np.ix_(rows, rows)], np.linalg.inv(np.linalg.cholesky(covariance)), rtol=1e-6, atol=1e-3
        )
        np.testing.assert_array_equal(whitening[n][~seen[n]], 0.0)
        np.testing.assert_array_equal(whitening[n][:, ~seen[n]], 0.0)


def test_points_calibrate_exactly_from_an_unknown_frame(ur5):
    """Exact points of a perturbed UR5 seen from FRAME, one point hidden in some rows: the fit from the
    registered start predicts every point at held-out postures as the truth does."""
    model, chain = ur5
    truth = perturb(model, {p: np.full(6, 1e-3) for p in chain.placements()})
    q, points = _point_measurements(model, chain, 30, 62, truth)
    points[::4, 1] = np.nan
    calibration = calibrate_serial(model, chain, q, points, CalibrationOptions(noise=TRACKER, estimate_frame=True))
    assert calibration.converged and len(calibration.setup.points) == 3
    np.testing.assert_array_equal(calibration.setup.marker.homogeneous, np.eye(4))  # unused with points
    q_new, actual = _point_measurements(model, chain, 20, 63, truth)
    predicted = calibration.setup.measured_points(tool_poses(chain, calibration.model, q_new))
    np.testing.assert_allclose(predicted, actual, atol=1e-8)


def test_point_start_finds_the_offsets_and_the_frame_of_exact_points(ur5):
    """Given F, each offset in closed form; from the identity, the alternation of registrations and
    offsets nears F and the offsets (the truth of exact nominal points)."""
    model, chain = ur5
    q, points = _point_measurements(model, chain, 12, 65)
    points[::3, 0] = np.nan
    data = S.parse_measurements(chain, q, points, False)
    given = S.start_state(chain, model, data, MeasurementSetup(FRAME), False, False, True)
    np.testing.assert_allclose(given.points, POINT_OFFSETS, atol=1e-12)
    np.testing.assert_array_equal(given.frame, FRAME.homogeneous)
    np.testing.assert_array_equal(given.compliance, np.zeros(6))
    found = S.start_state(chain, model, data, MeasurementSetup(), True, False, False)
    assert found.compliance is None
    assert np.abs(found.frame - FRAME.homogeneous).max() < 1e-3  # a start within a millimetre and a mrad
    assert np.abs(found.points - POINT_OFFSETS).max() < 1e-3


@pytest.mark.parametrize("n_points", [1, 2, 4])
def test_any_number_of_points_is_parsed_and_started(ur5, n_points):
    """One point, two or four (not only three of three coordinates): P points give 3 P rows per pose,
    and the start given F finds every offset, so the nominal robot's exact points leave no residual."""
    model, chain = ur5
    offsets = np.r_[POINT_OFFSETS, [[0.02, 0.03, -0.04]]][:n_points]
    q, points = _point_measurements(model, chain, 8, 67, offsets=offsets)
    if n_points > 1:
        points[1::3, -1] = np.nan  # the last point hidden in some rows
    data = S.parse_measurements(chain, q, points, False)
    assert data.n_points == n_points and data.rows_per_pose == 3 * n_points
    np.testing.assert_array_equal(data.positions, points.reshape(8, 3 * n_points))
    start = S.start_state(chain, model, data, MeasurementSetup(FRAME), False, False, False)
    np.testing.assert_allclose(start.points, offsets, atol=1e-12)
    layout = S.SerialLayout(6, marker=3 * n_points, points=n_points)
    unit = np.broadcast_to(np.eye(3 * n_points), (8, 3 * n_points, 3 * n_points))
    residual = S.SerialResidual(chain, data, unit, layout)
    np.testing.assert_allclose(residual.raw_residual(start), 0.0, atol=1e-12)


def test_measured_points_are_refused_word_for_word(ur5):
    model, chain = ur5
    q, points = _point_measurements(model, chain, 4, 64)

    def refused(array, message, rows=q):
        with pytest.raises(InvalidInputError) as caught:
            S.parse_measurements(chain, rows, array, False)
        assert str(caught.value) == message

    refused(points[:, :, :2], "measured points: expected shape (N, P, 3), got (4, 3, 2)")
    refused(points[:, :0], "measured points: expected shape (N, P, 3), got (4, 0, 3)")
    refused(points, "3 joint readings but 4 rows of measured points", q[:3])
    partial = points.copy()
    partial[2, 1, 0] = np.nan
    refused(partial, "measured points: row 2 has a point with some coordinates missing")
    blind = points.copy()
    blind[1] = np.nan
    refused(blind, "measured points: row 1 sees no point")
    unseen = points.copy()
    unseen[:, 2] = np.nan
    refused(unseen, "measured points: point 3 is seen in no row")
    refused(points + 1e-3j, "measured points: complex values given; joint values and coordinates are real numbers")
    with pytest.raises(InvalidInputError, match=r"^measured points: not numeric \("):  # then numpy's words
        S.parse_measurements(chain, q, np.full(points.shape, "seen"), False)
    millimetres = S.parse_measurements(chain, q, np.round(points * 1e3).astype(int), False)  # integers read as floats
    assert millimetres.positions.dtype == float
    np.testing.assert_array_equal(millimetres.positions, np.round(points * 1e3).reshape(4, 9))
    seen = points.copy()
    seen[0, 0] = np.nan
    data = S.parse_measurements(chain, q, seen, False)
    assert data.n_points == 3 and data.rotations is None
    np.testing.assert_array_equal(data.positions, seen.reshape(4, 9))
    seen[1, 1] += 1.0  # the measurements are a copy: the caller's array stays theirs
    np.testing.assert_array_equal(data.positions[1, 3:6], points[1, 1])
