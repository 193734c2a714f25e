"""Actual machines: twist and offset errors are carried by placements exactly (paper eq. 34-37)."""

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurements import measure
from m3t1r.calibration.simulation import actual_machine, orthonormal_twist, with_joint_errors
from m3t1r.errors import InvalidInputError
from m3t1r.model.workspace import workspace_actuators


def test_orthonormal_twist_keeps_the_joint_kind():
    rng = np.random.default_rng(0)
    revolute = orthonormal_twist(np.r_[0, 0, 0, 1.0, 0, 0], rng.normal(0, 1e-2, 6))
    assert np.isclose(np.linalg.norm(revolute[3:]), 1) and abs(revolute[:3] @ revolute[3:]) < 1e-15
    prismatic = orthonormal_twist(np.r_[0, 1.0, 0, 0, 0, 0], rng.normal(0, 1e-2, 6))
    assert np.isclose(np.linalg.norm(prismatic[:3]), 1) and not np.any(prismatic[3:])


def test_joint_errors_equal_the_explicit_product_of_exponentials(mechanism):
    """Chain B1 with ds and dq through placements == T(0) exp(s^a (q + dq)) ... evaluated directly."""
    rng = np.random.default_rng(1)
    model = mechanism.model
    chain = ["q11", "q12", "q12_pa", "q13", "q13_pa", "q14"]
    twist_errors = {name: rng.normal(0, 1e-3, 6) for name in chain}
    offsets = {name: rng.normal(0, 1e-3) for name in chain}
    actual = with_joint_errors(model, twist_errors, offsets)
    q = mechanism.home + rng.normal(0, 0.1, model.nq)
    data = actual.createData()
    pin.framesForwardKinematics(actual, data, q)
    expected = pin.SE3.Identity()
    nominal_data = model.createData()
    for name in chain:
        j = model.getJointId(name)
        s = orthonormal_twist(np.array(nominal_data.joints[j].S).reshape(6), twist_errors[name])
        expected = expected * model.jointPlacements[j] * pin.exp6(s * (q[model.idx_qs[j]] + offsets[name]))
    expected = expected * model.frames[model.getFrameId("P_I")].placement
    assert np.max(np.abs((expected.inverse() * data.oMf[model.getFrameId("P_I")]).homogeneous - np.eye(4))) < 1e-12


def test_closed_loop_calibration_absorbs_twist_and_offset_errors(mechanism):
    """dt, ds and dq on every joint (the paper's Table 1 kinds): noise-free calibration still
    reaches the placement-only accuracy, since ds and dq are placement errors in disguise."""
    rng = np.random.default_rng(2)
    error_model = ClosedLoopErrorModel(mechanism)
    names = [mechanism.model.names[j] for j in range(1, mechanism.model.njoints)]
    truth = actual_machine(
        mechanism,
        rng.normal(0, 1e-3, error_model.n_parameters),
        error_model,
        {n: rng.normal(0, 1e-3, 6) for n in names},
        {n: rng.normal(0, 1e-3) for n in names},
    )
    actuators = workspace_actuators(mechanism, 250, rng)
    calibration = calibrate_closed_loop(mechanism, measure(truth, actuators[:50]))
    after = pose_errors(calibration.mechanism, truth, actuators[50:])
    assert pose_errors(mechanism, truth, actuators[50:]).position_mean > 3e-3
    assert after.position_mean < 1e-6


def test_unknown_joint_is_named(mechanism):
    with pytest.raises(InvalidInputError, match="joint 'q99' does not exist"):
        with_joint_errors(mechanism.model, {"q99": np.zeros(6)}, {})
