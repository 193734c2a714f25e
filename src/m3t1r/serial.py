"""Calibration of any serial chain of a Pinocchio model (base frame to tool frame), local POE model.

Error model (Zhang et al., Symmetry 2020, section 3.1): every kinematic error is a right-multiplied
error twist on an initial pose, T(0) <- T(0) exp6(dt) (eq. 33), for each joint placement of the
chain and the tool placement. Joint twists and joint readings are taken as exact; a joint zero
offset needs no parameter of its own (see `simulate_serial_measurements`).

Measurement model and residual, per pose i (one choice, used everywhere here):
    position    r_p = p_model - p_meas          (m, in WORLD = the chain's base frame {B})
    orientation r_R = log3(R_meas^T R_model)    (rad, in the LOCAL tool frame)
with measurement noise p_meas = p + e_p, e_p ~ N(0, sigma_p^2 I) and R_meas = R exp3(e_R),
e_R ~ N(0, sigma_R^2 I), and joint-reading noise sigma_q per joint. Residuals are whitened by the
Cholesky factor of their predicted covariance, which includes the joint noise propagated through the
joint Jacobian. Unlike the paper's spatial log6 error (eq. 18), whose linear part is the motion of
the point at {B}'s origin, these rows have the physical units of the sensor's noise, so whitening
by the tracker's specification is meaningful. Their exact Jacobians follow from the WORLD error
Jacobian of `m3t1r.poe` (eq. 17): d p = v + w x p and d r_R = Jlog3(R_meas^T R) R^T w.
Position-only mode drops the orientation rows.
"""

from __future__ import annotations

import functools
import importlib.metadata
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Literal

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.errors import InvalidInputError, ModelFileError
from m3t1r.identification import BaseParameters, batch_least_squares, levenberg_marquardt, select_base_parameters
from m3t1r.poe import Placement, SerialChain, forward_and_error_jacobians, perturb, placement_of

__all__ = [
    "MeasurementNoise",
    "PoseErrorRMS",
    "PoseErrors",
    "PredictedPoseStd",
    "RobotName",
    "SerialCalibration",
    "SerialMeasurements",
    "calibrate_serial",
    "example_robot_data_dir",
    "example_tool_frame",
    "load_example_robot",
    "pose_errors",
    "predicted_pose_std",
    "sample_configurations",
    "simulate_serial_measurements",
]

RobotName = Literal["ur3", "ur5", "ur10", "panda"]


@dataclass(frozen=True)
class _ExampleRobot:
    urdf: tuple[str, ...]  # path under example-robot-data's robots/ directory
    tool_frame: str
    locked_joints: tuple[str, ...] = ()


_EXAMPLE_ROBOTS: Mapping[str, _ExampleRobot] = MappingProxyType(
    {
        "ur3": _ExampleRobot(("ur_description", "urdf", "ur3_robot.urdf"), "tool0"),
        "ur5": _ExampleRobot(("ur_description", "urdf", "ur5_robot.urdf"), "tool0"),
        "ur10": _ExampleRobot(("ur_description", "urdf", "ur10_robot.urdf"), "tool0"),
        # The fingers are a separate branch; the calibrated chain ends at the hand's TCP frame.
        "panda": _ExampleRobot(
            ("panda_description", "urdf", "panda.urdf"),
            "panda_hand_tcp",
            ("panda_finger_joint1", "panda_finger_joint2"),
        ),
    }
)


def _example_robot(name: str) -> _ExampleRobot:
    try:
        return _EXAMPLE_ROBOTS[name]
    except KeyError:
        known = ", ".join(sorted(_EXAMPLE_ROBOTS))
        raise InvalidInputError(f"unknown example robot '{name}' (known: {known})") from None


@functools.cache
def example_robot_data_dir() -> Path:
    """The installed `robots/` directory of the example-robot-data distribution.

    Version 6 ships data files only (under its cmeel prefix, no Python module), so the directory
    is located through the distribution's file list rather than an import.
    """
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        raise ModelFileError("example-robot-data", "distribution not installed") from None
    marker = ("share", "example-robot-data", "robots")
    for file in dist.files or ():
        parts = file.parts
        for i in range(len(parts) - len(marker)):
            if parts[i : i + len(marker)] == marker:
                return Path(dist.locate_file(Path(*parts[: i + len(marker)])))
    raise ModelFileError("example-robot-data", "no share/example-robot-data/robots directory in the distribution")


def example_tool_frame(name: RobotName) -> str:
    """The tool frame used for example robot `name` (e.g. 'tool0' for UR, 'panda_hand_tcp')."""
    return _example_robot(name).tool_frame


def load_example_robot(name: RobotName) -> pin.Model:
    """Kinematic model of an example-robot-data arm, offline, without geometry.

    Panda's two finger joints are locked at their neutral value (`pin.buildReducedModel`), leaving
    the 7 arm joints; its tool frame 'panda_hand_tcp' then hangs from panda_joint7.
    """
    spec = _example_robot(name)
    path = example_robot_data_dir().joinpath(*spec.urdf)
    if not path.is_file():
        raise ModelFileError(path, f"URDF of example robot '{name}' is missing")
    model = pin.buildModelFromUrdf(str(path))
    if spec.locked_joints:
        for joint in spec.locked_joints:
            if not model.existJointName(joint):
                raise ModelFileError(path, f"joint '{joint}' to lock is not in the model")
        ids = [model.getJointId(joint) for joint in spec.locked_joints]
        model = pin.buildReducedModel(model, ids, pin.neutral(model))
    return model


# --------------------------------------------------------------------------------------------------
# Simulation


@dataclass(frozen=True)
class MeasurementNoise:
    """Standard deviations of the calibration data, per axis.

    position: tool position (m), isotropic in WORLD. rotation: tool orientation (rad), isotropic,
    R_meas = R exp3(e). joint: joint readings (rad or m), independent per joint.
    """

    position: float = 1e-5
    rotation: float = 2e-5
    joint: float = 0.0

    def __post_init__(self) -> None:
        for name in ("position", "rotation", "joint"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise InvalidInputError(f"MeasurementNoise.{name}: must be finite and >= 0, got {value}")


@dataclass(frozen=True)
class SerialMeasurements:
    """A simulated calibration experiment.

    truth: the "real" robot, nominal placements T(0) exp6(dt) exp6(S dq) (offsets folded in).
    placement_errors: the dt per placement (m, rad); joint_offsets: dq (n,) (rad or m).
    q_true: (N, n) noise-free joint readings; the truth model takes them directly.
    q_readings: (N, n) q_true plus reading noise. measured_poses: noisy tool poses g_{B,P} in {B}.
    """

    truth: pin.Model
    placement_errors: Mapping[Placement, np.ndarray]
    joint_offsets: np.ndarray
    q_true: np.ndarray
    q_readings: np.ndarray
    measured_poses: tuple[pin.SE3, ...]
    noise: MeasurementNoise


def sample_configurations(
    model: pin.Model, chain: SerialChain, n: int, rng: np.random.Generator, *, margin: float = 0.05
) -> np.ndarray:
    """(n, n_joints) chain configurations uniform within the joint limits shrunk by `margin`
    (a fraction of each range, on each side)."""
    lower, upper = chain.position_limits(model)
    span = upper - lower
    return rng.uniform(lower + margin * span, upper - margin * span, size=(n, chain.n_joints))


def simulate_serial_measurements(
    model: pin.Model,
    chain: SerialChain,
    n_poses: int,
    rng: np.random.Generator,
    *,
    translation_error: float = 1e-3,
    rotation_error: float = 1e-3,
    joint_offset: float = 1e-3,
    noise: MeasurementNoise = MeasurementNoise(),
) -> SerialMeasurements:
    """Draw a true robot and `n_poses` noisy measurements of its tool pose.

    Placement errors: dt ~ N(0, diag(translation_error^2 I3, rotation_error^2 I3)) (m, rad) on each
    placement of `chain.placements()`. Joint offsets: dq_k ~ N(0, joint_offset^2) (rad or m).

    A joint offset needs no parameter of its own: T(0) exp(S (q + dq)) = [T(0) exp(S dq)] exp(S q)
    exactly, because exp(S dq) and exp(S q) share their twist and commute. The offset is therefore a
    right-multiplied error exp6(S dq) of the same placement, along the joint twist, and that is how
    the truth model carries it.
    """
    if n_poses < 1:
        raise InvalidInputError(f"n_poses must be >= 1, got {n_poses}")
    sigma = np.r_[np.full(3, translation_error), np.full(3, rotation_error)]
    placements = chain.placements()
    errors = {p: rng.normal(0.0, 1.0, 6) * sigma for p in placements}
    offsets = rng.normal(0.0, joint_offset, chain.n_joints)
    truth = perturb(perturb(model, errors), {p: chain.twists[k] * offsets[k] for k, p in enumerate(placements[:-1])})
    q_true = sample_configurations(model, chain, n_poses, rng)
    q_readings = q_true + rng.normal(0.0, noise.joint, q_true.shape) if noise.joint > 0.0 else q_true.copy()
    poses, _ = forward_and_error_jacobians(chain, truth, q_true)
    measured = []
    for g in poses:
        rotation = g.rotation @ pin.exp3(rng.normal(0.0, noise.rotation, 3))
        measured.append(pin.SE3(rotation, g.translation + rng.normal(0.0, noise.position, 3)))
    frozen_errors = MappingProxyType({p: _readonly(v) for p, v in errors.items()})
    return SerialMeasurements(
        truth=truth,
        placement_errors=frozen_errors,
        joint_offsets=_readonly(offsets),
        q_true=_readonly(q_true),
        q_readings=_readonly(q_readings),
        measured_poses=tuple(measured),
        noise=noise,
    )


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=float)
    array.flags.writeable = False
    return array


# --------------------------------------------------------------------------------------------------
# Residuals


def _pose_rows(
    jacobians: np.ndarray, poses: Sequence[pin.SE3], log_jacobians: np.ndarray | None
) -> np.ndarray:
    """Map WORLD twist rows (N, 6, m) to residual rows: the tool origin displacement v + w x p
    (WORLD) and, when log_jacobians (N, 3, 3) is given, the orientation rows Jlog3 R^T w (LOCAL)."""
    p = np.array([g.translation for g in poses])
    position = jacobians[:, :3, :] + np.cross(jacobians[:, 3:, :], p[:, :, None], axis=1)
    if log_jacobians is None:
        return position
    rotation_t = np.array([g.rotation.T for g in poses])
    orientation = log_jacobians @ rotation_t @ jacobians[:, 3:, :]
    return np.concatenate([position, orientation], axis=1)


@dataclass(frozen=True)
class _Measurements:
    q: np.ndarray  # (N, n)
    positions: np.ndarray  # (N, 3)
    rotations: np.ndarray | None  # (N, 3, 3), None in position-only mode


class _SerialProblem:
    """The whitened calibration residual over the base parameters, for `levenberg_marquardt`."""

    def __init__(
        self,
        chain: SerialChain,
        data: _Measurements,
        columns: np.ndarray,
        whitening: np.ndarray,
    ) -> None:
        self.chain = chain
        self.data = data
        self.columns = columns
        self.whitening = whitening  # (N, k, k): inverse Cholesky factor of each pose's covariance
        self.placements = chain.placements()

    def residual_and_jacobian(self, model: pin.Model) -> tuple[np.ndarray, np.ndarray]:
        residual, jacobian = _raw_residual_and_jacobian(self.chain, model, self.data)
        r = np.einsum("nij,nj->ni", self.whitening, residual).reshape(-1)
        J = np.einsum("nij,njm->nim", self.whitening, jacobian[:, :, self.columns]).reshape(r.size, -1)
        return r, J

    def retract(self, model: pin.Model, step: np.ndarray) -> pin.Model:
        full = np.zeros(self.chain.n_parameters)
        full[self.columns] = step
        return perturb(model, {p: full[6 * k : 6 * k + 6] for k, p in enumerate(self.placements)})


def _orientation_errors(measured: np.ndarray, poses: Sequence[pin.SE3]) -> tuple[np.ndarray, np.ndarray]:
    """log3(R_meas^T R_model) (N, 3) and its Jlog3 (N, 3, 3) for measured rotations (N, 3, 3)."""
    errors = np.swapaxes(measured, 1, 2) @ np.array([g.rotation for g in poses])
    return np.array([pin.log3(e) for e in errors]), np.array([pin.Jlog3(e) for e in errors])


def _raw_residual_and_jacobian(
    chain: SerialChain, model: pin.Model, data: _Measurements
) -> tuple[np.ndarray, np.ndarray]:
    """Unwhitened residuals (N, k) and their Jacobians (N, k, 6(n+1)) over all placement errors."""
    poses, jacobians = forward_and_error_jacobians(chain, model, data.q)
    residual = np.array([g.translation for g in poses]) - data.positions
    if data.rotations is None:
        return residual, _pose_rows(jacobians, poses, None)
    logs, log_jacobians = _orientation_errors(data.rotations, poses)
    return np.concatenate([residual, logs], axis=1), _pose_rows(jacobians, poses, log_jacobians)


def _whitening(chain: SerialChain, model: pin.Model, data: _Measurements, noise: MeasurementNoise) -> np.ndarray:
    """Inverse Cholesky factors (N, k, k) of the residual covariance of each pose.

    Cov = diag(sigma_p^2 I3 [, sigma_R^2 I3]) + J_q sigma_q^2 J_q^T, with J_q the residual's
    Jacobian with respect to the joint readings. Computed once at the starting model so that the
    cost function does not change under the optimiser's feet; the joint Jacobian barely moves over
    millimetre-size corrections.
    """
    n_poses = data.q.shape[0]
    k = 3 if data.rotations is None else 6
    sigmas = np.full(k, noise.position)
    if data.rotations is not None:
        sigmas[3:] = noise.rotation
    if np.any(sigmas <= 0.0):
        raise InvalidInputError("MeasurementNoise: position (and rotation, for full poses) must be > 0 to whiten")
    if noise.joint == 0.0:
        return np.broadcast_to(np.diag(1.0 / sigmas), (n_poses, k, k)).copy()
    poses, jacobians = forward_and_error_jacobians(chain, model, data.q)
    n = chain.n_joints
    # Column k of the joint Jacobian is block k of the error Jacobian applied to S_k:
    # Ad(g_{B,k-1} T_{k-1,k}(0)) S_k = Ad(g_{B,k}) S_k because Ad(exp(S_k q_k)) S_k = S_k.
    blocks = jacobians[:, :, : 6 * n].reshape(n_poses, 6, n, 6)
    joint_world = np.einsum("nikj,kj->nik", blocks, chain.twists)
    log_jacobians = None if data.rotations is None else _orientation_errors(data.rotations, poses)[1]
    joint_rows = _pose_rows(joint_world, poses, log_jacobians)
    covariance = np.diag(sigmas**2) + noise.joint**2 * joint_rows @ np.swapaxes(joint_rows, 1, 2)
    return np.linalg.inv(np.linalg.cholesky(covariance))


# --------------------------------------------------------------------------------------------------
# Calibration

# Re-selections of the base parameters at the estimate, after the one at the nominal model.
_MAX_RESELECTIONS = 2
# Millimetre errors on metre links: the model is nearly linear over the whole correction, so start
# close to Gauss-Newton (Madsen & Nielsen's advice for a good starting point). With the textbook
# 1e-3, Marquardt's column scaling over-damps the weak combinations found by a re-selection.
_INITIAL_DAMPING = 1e-6


@dataclass(frozen=True)
class PoseErrorRMS:
    """Root mean square over poses of the position error norm (m) and rotation angle (rad;
    nan when orientation was not measured)."""

    position: float
    rotation: float


@dataclass(frozen=True)
class SerialCalibration:
    """Result of `calibrate_serial`.

    model: calibrated copy of the input model, T_c(0) = T(0) exp6(dt) per placement (eq. 33).
    deltas: identified dt = log6(T(0)^-1 T_c(0)) per placement of `chain.placements()` ([v; w], m, rad).
    base: the identifiable parameters the final run estimated (see `calibrate_serial`); the other
        components are not estimated and stay at their nominal value.
    covariance: (rank, rank) covariance of the base parameters (m^2, rad^2, ordered as base.names)
        from the noise model, (J_w^T J_w)^-1 with the whitened Jacobian at the solution.
    parameter_std: sqrt(diag(covariance)).
    variance_factor: chi^2 / (rows - rank) of the whitened residual at the solution; ~1 when the
        noise model is right and the error model explains the data.
    iterations: Levenberg-Marquardt iterations over all runs; converged: the last run converged.
    residual_before / residual_after: RMS of the measurement residuals at the nominal and the
        calibrated model (the data used for calibration, not held-out poses).
    """

    model: pin.Model
    chain: SerialChain
    deltas: Mapping[Placement, np.ndarray]
    base: BaseParameters
    covariance: np.ndarray
    parameter_std: np.ndarray
    variance_factor: float
    iterations: int
    converged: bool
    residual_before: PoseErrorRMS
    residual_after: PoseErrorRMS
    position_only: bool


def _parse_measurements(
    chain: SerialChain, q_readings: ArrayLike, measured_poses: Sequence[pin.SE3] | ArrayLike, position_only: bool
) -> _Measurements:
    q = np.asarray(q_readings, dtype=float)
    if q.ndim != 2 or q.shape[1] != chain.n_joints:
        raise InvalidInputError(f"q_readings: expected shape (N, {chain.n_joints}), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"q_readings: non-finite value in row {int(np.flatnonzero(~np.isfinite(q).all(1))[0])}")
    if isinstance(measured_poses, Sequence) and any(isinstance(g, pin.SE3) for g in measured_poses):
        not_se3 = [i for i, g in enumerate(measured_poses) if not isinstance(g, pin.SE3)]
        if not_se3:
            raise InvalidInputError(f"measured_poses: row {not_se3[0]} is not an SE3 like the others")
        positions = np.array([g.translation for g in measured_poses])
        rotations = np.array([g.rotation for g in measured_poses])
    else:
        array = np.asarray(measured_poses, dtype=float)
        if array.ndim != 2 or array.shape[1] not in (3, 7):
            raise InvalidInputError(
                f"measured_poses: expected SE3 objects, (N, 7) [x, y, z, qx, qy, qz, qw] or (N, 3) positions, "
                f"got shape {array.shape}"
            )
        if not np.all(np.isfinite(array)):
            raise InvalidInputError(
                f"measured_poses: non-finite value in row {int(np.flatnonzero(~np.isfinite(array).all(1))[0])}"
            )
        if array.shape[1] == 3 and not position_only:
            raise InvalidInputError("measured_poses: positions only (N, 3) need position_only=True")
        positions = array[:, :3].copy()
        rotations = None
        if array.shape[1] == 7:
            norms = np.linalg.norm(array[:, 3:], axis=1)
            bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-6)
            if bad.size:
                raise InvalidInputError(f"measured_poses: quaternion of row {bad[0]} has norm {norms[bad[0]]:.6g}")
            rotations = np.array([pin.XYZQUATToSE3(row).rotation for row in array])
    if positions.shape[0] != q.shape[0]:
        raise InvalidInputError(f"{q.shape[0]} joint readings but {positions.shape[0]} measured poses")
    return _Measurements(q=q, positions=positions, rotations=None if position_only else rotations)


def _rms(residual: np.ndarray) -> PoseErrorRMS:
    position = float(np.sqrt(np.mean(np.sum(residual[:, :3] ** 2, axis=1))))
    rotation = float(np.sqrt(np.mean(np.sum(residual[:, 3:] ** 2, axis=1)))) if residual.shape[1] == 6 else np.nan
    return PoseErrorRMS(position, rotation)


@on_one_blas_thread  # tiny matrices: BLAS threads only add wake-up latency
def calibrate_serial(
    model: pin.Model,
    chain: SerialChain,
    q_readings: ArrayLike,
    measured_poses: Sequence[pin.SE3] | ArrayLike,
    *,
    position_only: bool = False,
    noise: MeasurementNoise = MeasurementNoise(),
    rel_tol: float = 1e-9,
    max_iterations: int = 30,
) -> SerialCalibration:
    """Identify the placement errors of `chain` from measured tool poses (eq. 17-20, 32, 33).

    q_readings: (N, n) chain coordinates (rad or m) as read by the robot.
    measured_poses: tool poses g_{B,P} in the chain's base frame {B}: SE3 objects, or an (N, 7)
        array [x, y, z, qx, qy, qz, qw] (m), or (N, 3) positions (m) with position_only=True.
    position_only: use only the position rows (3 per pose); tool-orientation errors are then
        unobservable and stay at zero.
    noise: standard deviations used to whiten the residuals (see `MeasurementNoise`).

    Method: select the base parameters by pivoted QR of the whitened Jacobian at the nominal model
    and run Levenberg-Marquardt over them with multiplicative updates T(0) <- T(0) exp6(dx)
    (eq. 33); the set is fixed during a run, since re-selecting at every iterate makes the kept
    set, hence the steps, jump. Nominal CAD geometry can be special (e.g. UR's tool point lies on
    the last joint axis, which hides two parameters from position measurements), so the selection
    is repeated at the converged model, and the run resumed from there, while the rank grows.
    """
    chain.check_model(model)
    data = _parse_measurements(chain, q_readings, measured_poses, position_only)
    whitening = _whitening(chain, model, data, noise)
    residual0, _ = _raw_residual_and_jacobian(chain, model, data)
    names = chain.parameter_names()
    every_parameter = _SerialProblem(chain, data, np.arange(chain.n_parameters), whitening)
    base = select_base_parameters(every_parameter.residual_and_jacobian(model)[1], names, rel_tol)
    problem = _SerialProblem(chain, data, np.array(base.indices), whitening)
    result = levenberg_marquardt(problem, model, max_iterations=max_iterations, initial_damping=_INITIAL_DAMPING)
    iterations = result.iterations
    for _ in range(_MAX_RESELECTIONS):
        candidate = select_base_parameters(every_parameter.residual_and_jacobian(result.state)[1], names, rel_tol)
        if candidate.rank <= base.rank:
            break
        base = candidate
        problem = _SerialProblem(chain, data, np.array(base.indices), whitening)
        result = levenberg_marquardt(
            problem, result.state, max_iterations=max_iterations, initial_damping=_INITIAL_DAMPING
        )
        iterations += result.iterations
    calibrated: pin.Model = result.state
    r, J = problem.residual_and_jacobian(calibrated)
    fit = batch_least_squares(J, -r, covariance_from="noise_model")
    residual1, _ = _raw_residual_and_jacobian(chain, calibrated, data)
    deltas = {
        p: _readonly(pin.log6(placement_of(model, p).actInv(placement_of(calibrated, p))).vector)
        for p in chain.placements()
    }
    return SerialCalibration(
        model=calibrated,
        chain=chain,
        deltas=MappingProxyType(deltas),
        base=base,
        covariance=fit.covariance,
        parameter_std=fit.std,
        variance_factor=fit.variance_factor,
        iterations=iterations,
        converged=result.converged,
        residual_before=_rms(residual0),
        residual_after=_rms(residual1),
        position_only=position_only,
    )


# --------------------------------------------------------------------------------------------------
# Evaluation


@dataclass(frozen=True)
class PoseErrors:
    """Per-configuration tool pose errors of a model against a reference model.

    position: (M,) norm of the tool position difference (m). rotation: (M,) rotation angle of
    R_ref^T R_model (rad).
    """

    position: np.ndarray
    rotation: np.ndarray

    @property
    def position_rms(self) -> float:
        return float(np.sqrt(np.mean(self.position**2)))

    @property
    def rotation_rms(self) -> float:
        return float(np.sqrt(np.mean(self.rotation**2)))


def pose_errors(model: pin.Model, reference: pin.Model, chain: SerialChain, q_chain: ArrayLike) -> PoseErrors:
    """Tool pose errors of `model` against `reference` (e.g. the truth) at chain configurations (M, n)."""
    poses, _ = forward_and_error_jacobians(chain, model, q_chain)
    reference_poses, _ = forward_and_error_jacobians(chain, reference, q_chain)
    position = np.array([np.linalg.norm(g.translation - h.translation) for g, h in zip(poses, reference_poses)])
    rotation = np.array([np.linalg.norm(pin.log3(h.rotation.T @ g.rotation)) for g, h in zip(poses, reference_poses)])
    return PoseErrors(position=position, rotation=rotation)


@dataclass(frozen=True)
class PredictedPoseStd:
    """Predicted standard deviation of the calibrated model's tool pose error, per configuration.

    position: (M,) sqrt(trace Cov(dp)) (m), the RMS of the position error norm;
    rotation: (M,) sqrt(trace Cov(dr)) (rad), nan after a position-only calibration.
    """

    position: np.ndarray
    rotation: np.ndarray

    @property
    def position_rms(self) -> float:
        """RMS over configurations, to compare with `PoseErrors.position_rms`."""
        return float(np.sqrt(np.mean(self.position**2)))

    @property
    def rotation_rms(self) -> float:
        return float(np.sqrt(np.mean(self.rotation**2)))


def predicted_pose_std(calibration: SerialCalibration, q_chain: ArrayLike) -> PredictedPoseStd:
    """Propagate the parameter covariance to the tool pose at chain configurations (M, n).

    Cov(pose) = J_b Cov(x_b) J_b^T with J_b the position (WORLD) and orientation (LOCAL) rows of the
    error Jacobian restricted to the base parameters, at the calibrated model. This is the error
    expected against the truth from measurement noise alone, assuming the error model is complete.
    """
    chain = calibration.chain
    poses, jacobians = forward_and_error_jacobians(chain, calibration.model, q_chain)
    n_poses = len(poses)
    rows = _pose_rows(jacobians, poses, np.broadcast_to(np.eye(3), (n_poses, 3, 3)))
    rows = rows[:, :, np.array(calibration.base.indices)]
    covariance = rows @ calibration.covariance @ np.swapaxes(rows, 1, 2)
    variances = np.einsum("nii->ni", covariance)
    position = np.sqrt(variances[:, :3].sum(axis=1))
    rotation = np.full(n_poses, np.nan) if calibration.position_only else np.sqrt(variances[:, 3:].sum(axis=1))
    return PredictedPoseStd(position=position, rotation=rotation)
