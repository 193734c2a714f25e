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
from m3t1r.model.kinematics import ClosedLoopSolver

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


# ------------------------------------------------------------------------------------------------
# Exact refusals, limits at their bounds, every field of a command (mutation run of 2026-11-29)
FAR_AWAY = np.array([3.0, 3.0, 1.0, 0.0])  # no assembly reaches it


def test_a_strict_failure_names_its_target_in_a_note(mechanism):
    with pytest.raises(OutOfWorkspaceError) as caught:
        compensate(mechanism, mechanism, np.vstack((PATH[:2], FAR_AWAY)), strict=True)
    assert caught.value.__notes__ == ["while compensating target 2 (0-based) of the batch"]


def test_incompatible_models_are_refused_word_for_word(mechanism):
    import dataclasses

    renamed = dataclasses.replace(mechanism, actuated_joints=("a", "b", "c", "d"))
    with pytest.raises(InvalidInputError) as caught:
        Compensator(mechanism, renamed)
    assert str(caught.value) == (f"calibrated model actuates ('a', 'b', 'c', 'd'), the nominal one "
                                 f"{mechanism.actuated_joints}: not the same machine")
    other_frame = dataclasses.replace(mechanism, platform_frame="tool")
    with pytest.raises(InvalidInputError) as caught:
        Compensator(mechanism, other_frame)
    assert str(caught.value) == "calibrated platform frame 'tool' differs from the nominal 'P_I'"
    smaller = dataclasses.replace(mechanism, model=pin.Model())
    with pytest.raises(InvalidInputError) as caught:
        Compensator(mechanism, smaller)
    assert str(caught.value) == f"calibrated model has nq = 0, nominal {mechanism.model.nq}"


def test_malformed_targets_are_refused_word_for_word(mechanism):
    cases = [
        (pin.SE3.Identity(), "targets: a single pin.SE3; give a sequence of them (or use Compensator.command)"),
        ([[0.5, 0.5, -0.1, 0.0], pin.SE3.Identity()],
         "targets: mix of pin.SE3 and other rows; give all placements or an (N, 4) array"),
        (np.zeros((0, 4)), "targets: no rows"),
    ]
    for targets, message in cases:
        with pytest.raises(InvalidInputError) as caught:
            compensate(mechanism, mechanism, targets)
        assert str(caught.value) == message
    with pytest.raises(InvalidInputError) as caught:
        compensate(mechanism, mechanism, [[0.5, 0.5, -0.1, "x"]])
    assert str(caught.value).startswith("targets: not numeric rows (x, y, z, theta) (")


def test_targets_may_be_lists_of_any_real_numbers(mechanism):
    from decimal import Decimal

    rows = [[Decimal(str(v)) for v in row] for row in PATH]
    as_lists = compensate(mechanism, mechanism, rows)
    assert as_lists.complete
    np.testing.assert_allclose(as_lists.actuators, compensate(mechanism, mechanism, PATH).actuators, atol=1e-12)


def _solved(q: np.ndarray):
    from types import SimpleNamespace

    return SimpleNamespace(q=q, residual=1e-13, iterations=4)


def test_joint_limits_are_inclusive_and_a_violation_names_the_joint(mechanism):
    from m3t1r.compensation import check_joint_limits

    model = mechanism.model
    lower, upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
    check_joint_limits(mechanism, _solved(lower.copy()))  # every joint exactly at its lower stop
    check_joint_limits(mechanism, _solved(upper.copy()))  # and at its upper stop
    from m3t1r.compensation import joint_limit_violation  # its own test too: check_joint_limits reads lists first

    assert joint_limit_violation(model, lower.copy()) is None and joint_limit_violation(model, upper.copy()) is None
    q = (lower + upper) / 2.0
    q[0] = upper[0] + 1e-3  # the first joint, q11
    with pytest.raises(OutOfWorkspaceError) as caught:
        check_joint_limits(mechanism, _solved(q))
    assert str(caught.value) == ("target puts joint 'q11' at 0.601, beyond its limit [-0.6, 0.6] "
                                 "(residual 1.000e-13 after 4 iterations)")
    assert (caught.value.residual, caught.value.iterations) == (1e-13, 4)


def test_a_command_carries_every_field_of_the_batch(mechanism):
    compensator = Compensator(mechanism, mechanism)
    assert compensator.nominal is mechanism and compensator.calibrated is mechanism
    target = pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, 0.1), PATH[1, :3])
    command = compensator.command(target)
    batch = compensate(mechanism, mechanism, [target])
    assert command.command_pose.isApprox(batch.command_poses[0], 1e-10)
    assert command.reached_pose.isApprox(batch.reached_poses[0], 1e-10)
    np.testing.assert_allclose(command.tilt, batch.tilt[0], atol=1e-12)
    assert command.iterations == batch.iterations[0] and command.iterations > 0


def test_compensate_reports_progress_per_target(mechanism):
    seen = []
    compensate(mechanism, mechanism, PATH, progress=seen.append)
    assert seen == [0, 1, 2]


def test_accuracy_of_se3_targets_equals_that_of_their_rows(mechanism):
    poses = [pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, row[3]), row[:3]) for row in PATH]
    wide = _wider_stroke(mechanism, 0.7)
    from_poses = compensation_accuracy(mechanism, wide, mechanism, poses)
    from_rows = compensation_accuracy(mechanism, wide, mechanism, PATH)
    np.testing.assert_allclose(from_poses.after.position, from_rows.after.position, atol=1e-12)
    np.testing.assert_allclose(from_poses.after.yaw, from_rows.after.yaw, atol=1e-12)


def test_workspace_helpers_start_at_the_low_corner_and_refuse_word_for_word():
    from m3t1r.compensation import workspace_grid, workspace_targets
    from m3t1r.model.design import NOMINAL

    box = NOMINAL.workspace
    grid = workspace_grid((2, 2, 2, 3))
    np.testing.assert_array_equal(grid[0], [box.x[0], box.y[0], box.z[0], box.theta[0]])
    np.testing.assert_array_equal(grid[3], [box.x[0], box.y[0], box.z[1], box.theta[1]])  # z step, theta back
    with pytest.raises(InvalidInputError) as caught:
        workspace_grid((2, 0, 2, 2))
    assert str(caught.value) == "workspace_grid: counts must be 4 integers >= 1, got (2, 0, 2, 2)"
    assert workspace_targets(1, np.random.default_rng(0)).shape == (1, 4)
    with pytest.raises(InvalidInputError) as caught:
        workspace_targets(0, np.random.default_rng(0))
    assert str(caught.value) == "workspace_targets: n must be >= 1, got 0"


def test_a_violation_names_a_joint_after_the_first(mechanism):
    """The joint name is read at 1 + the joint's position among the coordinates (joint 0 is the universe)."""
    from m3t1r.compensation import joint_limit_violation

    model = mechanism.model
    q = (model.lowerPositionLimit + model.upperPositionLimit) / 2.0
    k = 5
    q[k] = model.upperPositionLimit[k] + 0.25
    name = model.names[1 + list(model.idx_qs[1:]).index(k)]
    assert name != model.names[1 - list(model.idx_qs[1:]).index(k)]
    assert joint_limit_violation(model, q) == (f"target puts joint '{name}' at {q[k]:.6g}, beyond its limit "
                                               f"[{model.lowerPositionLimit[k]:.6g}, {model.upperPositionLimit[k]:.6g}]")


def test_models_with_different_tasks_are_refused_word_for_word(mechanism):
    import dataclasses

    from m3t1r.model.task import TaskSpec

    other = dataclasses.replace(mechanism, task=TaskSpec(frame=mechanism.task.frame, position=("x", "y", "z"),
                                                         rotation="none"))
    with pytest.raises(InvalidInputError) as caught:
        Compensator(mechanism, other)
    assert str(caught.value) == f"calibrated model's task {other.task} differs from the nominal {mechanism.task}"


def test_a_wrong_target_width_names_every_column(mechanism):
    with pytest.raises(InvalidInputError) as caught:
        compensate(mechanism, mechanism, np.zeros((2, 3)))
    assert str(caught.value) == "targets: shape (2, 3), expected (N, 4) rows (x, y, z, theta)"


def test_tracking_errors_of_a_full_rotation_task():
    """Position rows then the log3 angle of the target rotation's error, per reached pose."""
    from m3t1r.compensation import _tracking_errors
    from m3t1r.model.task import TaskSpec

    task = TaskSpec(frame="tool", position=("x",), rotation="full")
    goal_rotation = pin.rpy.rpyToMatrix(0.1, -0.2, 0.3)
    target = pin.SE3(goal_rotation, np.array([0.4, 0.0, 0.0]))
    reached = [pin.SE3(goal_rotation @ pin.exp3(np.array([0.0, 0.02, 0.0])), np.array([0.43, 1.0, 2.0])),
               pin.SE3(goal_rotation, np.array([0.4, 5.0, 5.0]))]
    errors = _tracking_errors(task, target, reached)
    np.testing.assert_allclose(errors, [(0.03, 0.02), (0.0, 0.0)], atol=1e-12)
    as_row = task.coordinates(target.homogeneous)[0]
    np.testing.assert_allclose(_tracking_errors(task, as_row, reached), errors, atol=1e-12)


def test_a_passive_hinge_past_its_stop_fails_the_target_in_every_compensation(mechanism):
    """A calibrated model whose hinge q13 may turn only to 1.05 rad (nominal: 2.62): targets needing more
    fail with the hinge named, in `command`, `compensate` and `compensate_batch` alike; the others are
    compensated."""
    model = mechanism.model.copy()
    k = model.idx_qs[model.getJointId("q13")]
    upper = model.upperPositionLimit.copy()
    upper[k] = 1.05
    model.upperPositionLimit = upper
    stiff = mechanism.with_model(model)
    solver = ClosedLoopSolver(stiff)
    angles = [solver.inverse(target, q_init=mechanism.home).q[k] for target in PATH]
    assert min(angles) <= 1.05 < max(angles)  # the path crosses the new stop
    compensator = Compensator(mechanism, stiff)
    failing = [i for i, angle in enumerate(angles) if angle > 1.05]
    for batch in (compensator.compensate(PATH), compensator.compensate_batch(PATH)):
        assert [f.index for f in batch.failures] == failing
        for failure in batch.failures:
            assert failure.error is OutOfWorkspaceError
            assert failure.reason.startswith("inverse kinematics of the calibrated model: target puts joint 'q13' "
                                             f"at {angles[failure.index]:.6g}, beyond its limit [-0.523599, 1.05]")
    compensator.reset()
    with pytest.raises(OutOfWorkspaceError, match="target puts joint 'q13' at 1.075"):
        compensator.command(PATH[failing[0]])
