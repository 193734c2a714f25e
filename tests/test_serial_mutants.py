"""Serial calibration tests that kill mutants the behaviour tests let through (docs/mutation.md).

Whitening without joint noise is checked against the true noise (variance factor near one from
both sides, parameter std against the scatter of repeated experiments), and the quaternion norm
tolerance of array input at its boundary.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.serial import calibrate_serial
from m3t1r.calibration.serial_evaluation import predicted_pose_std
from m3t1r.calibration.serial_robots import load_example_robot
from m3t1r.calibration.serial_simulation import sample_configurations, simulate_serial_measurements
from m3t1r.errors import InvalidInputError
from m3t1r.model.poe import SerialChain

TRACKER = TrackerNoise(position=1e-5, rotation=2e-5)  # and exact joint readings (joint_noise 0, the default)


@pytest.fixture(scope="module")
def ur5():
    model = load_example_robot("ur5")
    return model, SerialChain.from_model(model, "tool0")


def _calibrate(model, chain, seed: int, n_poses: int = 40):
    data = simulate_serial_measurements(model, chain, n_poses, np.random.default_rng(seed), noise=TRACKER)
    calibration = calibrate_serial(model, chain, data.q_readings, data.measured_poses, noise=TRACKER)
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
        measured = [pin.SE3(g.rotation @ pin.exp3(noise_rng.normal(0.0, TRACKER.rotation, 3)),
                            g.translation + noise_rng.normal(0.0, TRACKER.position, 3))
                    for g in data.measured_poses]
        calibration = calibrate_serial(model, chain, data.q_readings, measured, noise=TRACKER)
        estimates.append(np.concatenate([calibration.deltas[p] for p in chain.placements()])[list(calibration.base.indices)])
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
            calibrate_serial(model, chain, data.q_readings, xyzquat, noise=TRACKER)
    else:
        calibration = calibrate_serial(model, chain, data.q_readings, xyzquat, noise=TRACKER)
        assert calibration.converged
