"""Compensation tests that kill mutants the behaviour tests let through (docs/mutation.md).

Warm-start failures are forced, SE3 targets are checked at the orthonormality tolerance, yaw
targets go beyond pi, and q^c beyond the nominal slider limits (a calibrated file with wider
limits) must be a per-target failure, not an aborted batch.
"""

import math

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.compensation import Compensator, _PathSolver, compensate, compensation_accuracy
from m3t1r.errors import InvalidInputError, NotConvergedError, OutOfWorkspaceError

PATH = np.array([[0.50, 0.50, -0.10, 0.0], [0.52, 0.55, -0.12, 0.1], [0.48, 0.60, -0.08, -0.2]])
# Needs q11 near 0.70 m: beyond the nominal 0.6 m stroke, within a 1 m one.
BEYOND_NOMINAL_STROKE = np.array([0.5, 1.2, -0.1, 0.0])


def _failing_warm_solves(solve, failures: list):
    """Wrap a solver method so that every warm call (no q_init) raises once per entry of `failures`."""
    calls = []

    def wrapped(argument, q_init=None):
        calls.append(q_init)
        if q_init is None and failures:
            failures.pop()
            raise NotConvergedError("forced warm-start failure", 1.0, 3)
        return solve(argument, q_init=q_init)

    return wrapped, calls


def test_a_failed_warm_start_is_retried_from_home(mechanism):
    path = _PathSolver(mechanism)
    path.inverse(PATH[0])  # now warm
    path.solver.inverse, calls = _failing_warm_solves(path.solver.inverse, [True])
    result = path.inverse(PATH[1])
    assert len(calls) == 2 and calls[0] is None
    np.testing.assert_array_equal(calls[1], mechanism.home)
    reference = _PathSolver(mechanism).inverse(PATH[1])
    np.testing.assert_allclose(result.actuators, reference.actuators, atol=1e-10)


def test_a_failed_cold_start_is_not_retried(mechanism):
    path = _PathSolver(mechanism)
    path.solver.forward, calls = _failing_warm_solves(path.solver.forward, [True])
    with pytest.raises(NotConvergedError, match="forced"):
        path.forward(np.zeros(4))
    assert calls == [None]  # home was the start already: nothing to retry from
    path.reset()
    assert not path._warm


def test_compensator_recovers_from_a_forced_warm_failure_in_a_batch(mechanism):
    compensator = Compensator(mechanism, mechanism)
    compensator.compensate(PATH[:1])
    failures = [True]
    compensator._inverse.solver.inverse, _ = _failing_warm_solves(compensator._inverse.solver.inverse, failures)
    batch = compensator.compensate(PATH[1:])
    assert batch.complete and not failures
    np.testing.assert_allclose(batch.command_targets, PATH[1:], atol=1e-9)


@pytest.mark.parametrize("shear, refused", [(1e-7, True), (1e-8, True), (1e-11, False)])
def test_se3_target_rotation_must_be_orthonormal_to_1e_9(mechanism, shear, refused):
    rotation = np.eye(3)
    rotation[0, 1] = shear  # R^T R - I has an off-diagonal entry of `shear`
    targets = [pin.SE3(np.eye(3), PATH[0, :3]), pin.SE3(rotation, PATH[1, :3])]
    if refused:
        with pytest.raises(InvalidInputError, match="target 1 .*not orthonormal"):
            compensate(mechanism, mechanism, targets)
    else:
        assert compensate(mechanism, mechanism, targets).complete


def test_tracking_yaw_error_is_wrapped(mechanism):
    """Targets given with theta + 2 pi are reached; their yaw error is zero, not 2 pi."""
    turned = PATH + [0.0, 0.0, 0.0, 2 * math.pi]
    result = compensation_accuracy(mechanism, mechanism, mechanism, turned)
    assert not result.failures
    assert result.before.yaw_max < 1e-10 and result.after.yaw_max < 1e-10
    assert result.after.position_max < 1e-10


def _wider_stroke(mechanism, limit: float = 1.0):
    model = mechanism.model.copy()
    for name in mechanism.actuated_joints:
        index = model.idx_qs[model.getJointId(name)]
        model.lowerPositionLimit[index] = -limit
        model.upperPositionLimit[index] = limit
    return mechanism.with_model(model)


def test_sliders_beyond_the_nominal_stroke_fail_one_target_not_the_batch(mechanism):
    wide = _wider_stroke(mechanism)
    targets = np.vstack((PATH[:2], BEYOND_NOMINAL_STROKE, PATH[2:]))
    batch = compensate(mechanism, wide, targets)
    assert [f.index for f in batch.failures] == [2]
    failure = batch.failures[0]
    assert failure.error is InvalidInputError
    assert failure.reason.startswith("forward kinematics of the nominal model") and "beyond its joint limit" in failure.reason
    np.testing.assert_array_equal(batch.indices, [0, 1, 3])
    with pytest.raises(InvalidInputError):
        compensate(mechanism, wide, targets, strict=True)


def test_accuracy_reports_sliders_beyond_the_truth_stroke_per_target(mechanism):
    wide = _wider_stroke(mechanism)
    targets = np.vstack((PATH[:2], BEYOND_NOMINAL_STROKE, PATH[2:]))
    # The calibrated (wide) model reaches the target; the nominal IK refuses it first.
    result = compensation_accuracy(mechanism, wide, mechanism, targets)
    assert [f.index for f in result.failures] == [2]
    assert result.failures[0].error is OutOfWorkspaceError
    # A nominal controller with the wide stroke: the truth FK is what refuses the sliders.
    result = compensation_accuracy(wide, wide, mechanism, targets)
    assert [f.index for f in result.failures] == [2]
    assert result.failures[0].error is InvalidInputError and "truth forward kinematics" in result.failures[0].reason
    np.testing.assert_array_equal(result.indices, [0, 1, 3])
