"""Serial-robot calibration with the local POE error model on example-robot-data arms."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration import serial, serial_evaluation
from m3t1r.calibration.identification import select_base_parameters
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.serial import calibrate_serial
from m3t1r.calibration.serial_evaluation import pose_errors, predicted_pose_std
from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
from m3t1r.calibration.serial_simulation import sample_configurations, simulate_serial_measurements
from m3t1r.errors import InvalidInputError
from m3t1r.metrics import PoseErrors
from m3t1r.model.poe import SerialChain, forward_and_error_jacobians, perturb, tool_poses

# 10 um / 20 urad tracker, 1e-5 rad encoders: the test setting of the brief.
NOISE = TrackerNoise(position=1e-5, rotation=2e-5)
JOINT_NOISE = 1e-5
SENSORS = {"noise": NOISE, "joint_noise": JOINT_NOISE}  # simulated, and assumed by the fit
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
    data = simulate_serial_measurements(model, chain, N_POSES, rng, noise=None if exact else NOISE,
                                        joint_noise=0.0 if exact else JOINT_NOISE)
    calibration = calibrate_serial(model, chain, data.q_readings, data.measured_poses, position_only=position_only,
                                   **SENSORS)
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
    assert calibration.residual_after.position < 2.5e-5 < 1e-3 < calibration.residual_before.position


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
    calibration = calibrate_serial(model, chain, q, measured, select=True)
    assert calibration.converged and calibration.fitted == () and calibration.fitted_indices == ()
    assert calibration.covariance.shape == (0, 0) and calibration.parameter_std.shape == (0,)
    assert calibration.residual_after.position == 0.0 and calibration.outliers == ()
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
    from_se3 = calibrate_serial(model, chain, data.q_readings, data.measured_poses, **SENSORS)
    xyzquat = np.array([pin.SE3ToXYZQUAT(g) for g in data.measured_poses])
    from_array = calibrate_serial(model, chain, data.q_readings, xyzquat, **SENSORS)
    q = sample_configurations(model, chain, 10, np.random.default_rng(16))
    assert pose_errors(from_se3.model, from_array.model, chain, q).position.max() < 1e-12
    positions = xyzquat[:, :3]
    position_only = calibrate_serial(model, chain, data.q_readings, positions, position_only=True, **SENSORS)
    assert np.isnan(position_only.residual_after.rotation)
    with pytest.raises(InvalidInputError, match="position_only=True"):
        calibrate_serial(model, chain, data.q_readings, positions, **SENSORS)
    with pytest.raises(InvalidInputError, match="20 joint readings but 19"):
        calibrate_serial(model, chain, data.q_readings, xyzquat[:19], **SENSORS)
    with pytest.raises(InvalidInputError, match="expected shape"):
        calibrate_serial(model, chain, data.q_readings[:, :5], xyzquat, **SENSORS)
    bad = xyzquat.copy()
    bad[4, 3:] *= 2.0
    with pytest.raises(InvalidInputError, match="row 4"):
        calibrate_serial(model, chain, data.q_readings, bad, **SENSORS)
    for joint_noise in (-1e-5, float("nan")):
        with pytest.raises(InvalidInputError, match="joint_noise: must be finite and >= 0"):
            calibrate_serial(model, chain, data.q_readings, xyzquat, noise=NOISE, joint_noise=joint_noise)
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
    noisy = simulate_serial_measurements(model, chain, 400, np.random.default_rng(19), noise=TrackerNoise(1e-4, 3e-4),
                                         joint_noise=2e-4)
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
    measurements = serial._parse_measurements(chain, data.q_readings, data.measured_poses, position_only)
    state = serial._readonly_state(chain, perturb(model, {p: np.full(6, 2e-3) for p in chain.placements()}))
    whitening = serial._whitening(chain, state, measurements, NOISE, JOINT_NOISE)
    residual = serial._SerialResidual(chain, measurements, whitening)
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
    default = calibrate_serial(model, chain, data.q_readings, data.measured_poses, noise=noise)
    exhaustive = calibrate_serial(model, chain, data.q_readings, data.measured_poses, noise=noise,
                                  absolute_cost_tolerance=0.0)
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
    calibration = calibrate_serial(model, chain, data.q_readings, data.measured_poses, **SENSORS)
    q = sample_configurations(model, chain, 5, np.random.default_rng(36))
    assert isinstance(pose_errors(calibration.model, data.truth, chain, q), PoseErrors)
    predicted = predicted_pose_std(calibration, q)
    assert isinstance(predicted, PoseErrors) and predicted.position.shape == (5,)
    assert serial_evaluation.PoseErrors is PoseErrors
