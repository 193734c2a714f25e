"""Evaluation of a serial calibration: pose errors against a reference, predicted measurements and pose
standard deviations, cross-validation.
"""

from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.pipeline import fit
from m3t1r.calibration.repeats import CrossValidation, fold_errors, inlier_folds
from m3t1r.calibration.serial import SerialCalibration, _placement_rows, compliant_readings, gravity_torques
from m3t1r.errors import InvalidInputError
from m3t1r.metrics import PoseErrors, pose_errors_between
from m3t1r.model.poe import SerialChain, placement_poses, tool_poses

__all__ = [
    "SerialCrossValidation",
    "cross_validate_serial",
    "held_out_errors",
    "pose_errors",
    "predict_measurements",
    "predict_points",
    "predicted_pose_std",
]


# --------------------------------------------------------------------------------------------------
# Evaluation


def pose_errors(model: pin.Model, reference: pin.Model, chain: SerialChain, q_chain: ArrayLike) -> PoseErrors:
    """Tool pose errors of `model` against `reference` (e.g. the truth) at chain configurations (M, n):
    position distance (m, in {B}) and rotation angle of R_ref^T R_model (rad), per configuration."""
    return pose_errors_between(tool_poses(chain, model, q_chain), tool_poses(chain, reference, q_chain))


def _compliant_coordinates(calibration: SerialCalibration, q_chain: ArrayLike) -> np.ndarray:
    """q + c tau(q) (M, n) with the calibration's compliances (q itself without any)."""
    return compliant_readings(calibration.model, calibration.chain, q_chain, calibration.compliance)


def predict_measurements(calibration: SerialCalibration, q_readings: ArrayLike) -> np.ndarray:
    """The measured frames (M, 4, 4) the calibration predicts at joint readings (M, n), in the
    measurement frame: F g_c(q + c tau(q)) K with the calibrated robot, compliance and setup (m)."""
    chain = calibration.chain
    g = tool_poses(chain, calibration.model, _compliant_coordinates(calibration, q_readings))
    return calibration.setup.frame.homogeneous @ g @ calibration.setup.marker.homogeneous


def predict_points(calibration: SerialCalibration, q_readings: ArrayLike) -> np.ndarray:
    """The measured points (M, P, 3) [m] a calibration of several points per pose predicts at joint
    readings (M, n), in the measurement frame: F g_c(q + c tau(q)) p_k."""
    if not calibration.setup.points:
        raise InvalidInputError("predict_points: the calibration measured one frame per pose, not several points")
    chain = calibration.chain
    return calibration.setup.measured_points(
        tool_poses(chain, calibration.model, _compliant_coordinates(calibration, q_readings))
    )


def held_out_errors(
    calibration: SerialCalibration, q_readings: ArrayLike, measured: ArrayLike, position_only: bool
) -> PoseErrors:
    """Errors of the calibration's predictions of measurements it was not fitted to.

    measured: the measured frames (M, 4, 4) [m] in the measurement frame (their rotations unused
    when position_only), or with several points per pose (M, P, 3) [m], NaN where not seen.
    Returns per pose position |p_pred - p_meas| [m] and rotation angle [rad] (NaN when
    position_only); with points, per point seen (rotation NaN). Raises InvalidInputError when the
    file's kind (one frame or P points) is not the calibration's.
    """
    values = np.asarray(measured, dtype=float)
    points = len(calibration.setup.points)
    if values.ndim == 3 and values.shape[1:] != (4, 4):
        if values.shape[1] != points:
            raise InvalidInputError(
                f"the held-out file has {values.shape[1]} points per pose; the calibration "
                + (f"measured {points}" if points else "measured one frame")
            )
        predicted = predict_points(calibration, q_readings)
        seen = np.all(np.isfinite(values), axis=2)
        position = np.linalg.norm(predicted - np.where(seen[:, :, None], values, 0.0), axis=2)[seen]
        return PoseErrors(position, np.full(len(position), np.nan))
    if points:
        raise InvalidInputError(
            f"the held-out file has one measured frame per pose; the calibration measured {points} points"
        )
    errors = pose_errors_between(predict_measurements(calibration, q_readings), values)
    if position_only or calibration.position_only:
        return PoseErrors(errors.position, np.full(len(errors.position), np.nan))
    return errors


def predicted_pose_std(calibration: SerialCalibration, q_chain: ArrayLike) -> PoseErrors:
    """Predicted standard deviation of the calibrated tool pose error at chain configurations (M, n).

    Cov(pose) = J_b Cov(x_b) J_b^T with J_b the position (WORLD) and orientation (LOCAL) rows of the
    robot's fitted parameters (placements, compliances; the setup's are marginalised out), at the
    calibrated model. This is the error expected against the truth from measurement noise alone,
    assuming the error model is complete. Returns position = sqrt(trace Cov(dp)) (m) and rotation =
    sqrt(trace Cov(dr)) (rad, NaN after a position-only calibration), the RMS of the error norms.
    """
    chain = calibration.chain
    q = _compliant_coordinates(calibration, q_chain)
    frames = placement_poses(chain, chain.initial_transforms(calibration.model), q)
    n_poses, n = frames.shape[0], chain.n_joints
    rows = _placement_rows(frames, orientation=True)
    fitted = np.array(calibration.fitted_indices, dtype=int)
    n_chain = 6 * (n + 1)
    machine = np.flatnonzero(fitted < n_chain)
    blocks = [rows[:, :, fitted[machine]]]
    compliant = [k for k, c in enumerate(fitted) if c >= n_chain and calibration.names[c].startswith("compliance.")]
    if compliant:
        joint_rows = np.einsum("nikj,kj->nik", rows[:, :, : 6 * n].reshape(n_poses, 6, n, 6), chain.twists)
        torques = gravity_torques(calibration.model, chain, q_chain)
        joints = [chain.joint_names.index(calibration.names[fitted[k]].partition(".")[2]) for k in compliant]
        blocks.append(joint_rows[:, :, joints] * torques[:, None, joints])
    picked = np.concatenate([machine, np.array(compliant, dtype=int)])
    covariance = calibration.covariance[np.ix_(picked, picked)]
    jacobian = np.concatenate(blocks, axis=2)
    variances = np.einsum("nii->ni", jacobian @ covariance @ np.swapaxes(jacobian, 1, 2))
    position = np.sqrt(variances[:, :3].sum(axis=1))
    rotation = np.full(n_poses, np.nan) if calibration.position_only else np.sqrt(variances[:, 3:].sum(axis=1))
    return PoseErrors(position=position, rotation=rotation)


#: The serial calibration's cross-validation record: the closed loop's (`repeats.CrossValidation`).
SerialCrossValidation = CrossValidation


@on_one_blas_thread
def cross_validate_serial(
    calibration: SerialCalibration, folds: int = 5, seed: int = 0, groups: ArrayLike | None = None
) -> SerialCrossValidation:
    """k-fold cross-validation of a serial calibration on its own inlier poses (`SerialCrossValidation`).

    groups: (N,) a label per pose the calibration was given (`repeats.pose_groups`); poses sharing
    one are held out together. None: every pose on its own."""
    problem, start, settings = calibration.problem, calibration.start, calibration.settings
    if problem is None or start is None or settings is None:
        raise InvalidInputError("cross_validate_serial needs a calibration made by calibrate_serial")
    inliers, fold_of, n_groups = inlier_folds(problem.active, folds, seed, groups)
    residuals = np.empty((len(inliers), problem.model.data.rows_per_pose))
    fold_problem = copy.copy(problem)
    fold_problem.columns = np.array(calibration.fitted_indices, dtype=int)
    for fold in range(folds):
        held = inliers[fold_of == fold]
        fold_problem.active = problem.active.copy()
        fold_problem.active[held] = False
        result = fit(fold_problem, start, settings)
        residuals[fold_of == fold] = problem.model.raw_residual(result.state)[held]
    data = problem.model.data
    seen_points = data.seen[inliers][:, ::3] if data.n_points else None  # one error per point seen
    return CrossValidation(fold_errors(residuals, seen_points), folds, n_groups)
