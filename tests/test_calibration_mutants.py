"""Closed-loop calibration tests that kill mutants the behaviour tests let through (docs/mutation.md).

The predicted pose standard deviation is checked against finite differences of the calibrated
machine (exact) and against the held-out error from both sides (statistical); the LM stop rule is
checked on the iteration that fired it.
"""

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors, predicted_pose_std
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.simulation import simulate_study
from m3t1r.model.kinematics import ClosedLoopSolver

NOISE = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)


@pytest.fixture(scope="module")
def noisy(mechanism):
    study = simulate_study(mechanism, n_poses=50, n_holdout=100, seed=13, noise=NOISE)
    return study, calibrate_closed_loop(mechanism, study.measurements, NOISE)


def _fitted_names(calibration) -> tuple[str, ...]:
    """Names of the covariance's rows and columns."""
    fitted = getattr(calibration, "fitted", None)
    return tuple(fitted) if fitted is not None else tuple(calibration.base.names)


def test_predicted_pose_std_is_the_covariance_through_finite_differences(noisy):
    """sqrt(trace(J C J^T)) with J from central differences of the calibrated machine's FK."""
    study, calibration = noisy
    mechanism = calibration.mechanism
    error_model = ClosedLoopErrorModel(mechanism, calibration.error_model.placements)
    index = {name: i for i, name in enumerate(error_model.names)}
    names = _fitted_names(calibration)
    machine = [k for k, name in enumerate(names) if name in index]
    covariance = np.asarray(calibration.covariance)[np.ix_(machine, machine)]
    sliders = study.holdout_actuators[:3]
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
    expected_position = np.sqrt(np.einsum("nij,jk,nik->n", position_rows, covariance, position_rows))
    expected_rotation = np.sqrt(np.einsum("nij,jk,nik->n", rotation_rows, covariance, rotation_rows))
    predicted = predicted_pose_std(calibration, sliders)
    np.testing.assert_allclose(predicted.position, expected_position, rtol=1e-3)
    np.testing.assert_allclose(predicted.rotation, expected_rotation, rtol=1e-3)


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
