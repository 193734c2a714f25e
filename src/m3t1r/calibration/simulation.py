"""Simulated machines and measurements (paper section 6), for studies, tests and the demo.

An "actual" machine is the nominal description with right-multiplied errors on its initial poses
(paper eq. 34). The paper also perturbs joint twists (eq. 35) and joint variables (eq. 36); in the
local POE model both are absorbed by initial poses (a twist error conjugates the joint motion, an
offset is a motion along the joint's own twist), so random placement errors on every joint and
frame already span what a real machine can be, and that is what `actual_machine` applies.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise, assembled_from_home, measure
from m3t1r.errors import InvalidInputError, require_count
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import rehomed
from m3t1r.model.workspace import workspace_actuators

__all__ = [
    "PlacementErrorScale",
    "StudyOptions",
    "SimulatedStudy",
    "random_placement_errors",
    "actual_machine",
    "with_joint_errors",
    "orthonormal_twist",
    "simulate_study",
    "with_outliers",
]


@dataclass(frozen=True)
class PlacementErrorScale:
    """Standard deviations of the errors drawn on a simulated machine's placements, dt = [v; w]:
    position [m] on v and rotation [rad] on w."""

    position: float = 1e-3
    rotation: float = 1e-3


@dataclass(frozen=True)
class StudyOptions:
    """The rarer settings of `simulate_study`: what the truth is measured with and what else is read.

    setup: the truth measurement frame and marker; position_only: the tracker sees positions only;
    passive_joints: joints whose encoders are also read at the measured poses, with Gaussian noise of
    `encoder_noise` [rad] when the study is noisy; outliers: how many measurements get a 3-5 mm gross
    error (drawn last).
    """

    setup: MeasurementSetup = field(default_factory=MeasurementSetup)
    position_only: bool = False
    passive_joints: tuple[str, ...] = ()
    encoder_noise: float = 1e-5
    outliers: int = 0


def random_placement_errors(
    error_model: ClosedLoopErrorModel, rng: np.random.Generator, sigma_position: float, sigma_rotation: float
) -> np.ndarray:
    """Gaussian errors dt = [v; w] for every parameter: sigma_position [m] on v, sigma_rotation [rad] on w."""
    scale = np.tile(np.r_[np.full(3, sigma_position), np.full(3, sigma_rotation)], len(error_model.placements))
    return rng.normal(0.0, 1.0, error_model.n_parameters) * scale


def actual_machine(
    nominal: Mechanism,
    errors: np.ndarray,
    error_model: ClosedLoopErrorModel | None = None,
    twist_errors: Mapping[str, np.ndarray] | None = None,
    joint_offsets: Mapping[str, float] | None = None,
) -> Mechanism:
    """The nominal machine with placement errors dt (eq. 34), and optionally twist errors ds
    (eq. 35) and joint offsets dq (eq. 36) per joint name, with its home re-assembled."""
    error_model = error_model or ClosedLoopErrorModel(nominal)
    model = error_model.perturbed(nominal.model, errors)
    if twist_errors or joint_offsets:
        model = with_joint_errors(model, twist_errors or {}, joint_offsets or {})
    return rehomed(nominal.with_model(model))


def orthonormal_twist(twist: np.ndarray, error: np.ndarray) -> np.ndarray:
    """s + ds projected back onto 1-DoF twists of the same kind (paper section 6): a revolute
    keeps |w| = 1 and w . v = 0 (zero pitch), a prismatic |v| = 1 and w = 0."""
    v, w = twist[:3] + error[:3], twist[3:] + error[3:]
    if not np.any(twist[3:]):
        return np.r_[v / np.linalg.norm(v), np.zeros(3)]
    w = w / np.linalg.norm(w)
    return np.r_[v - (w @ v) * w, w]


def with_joint_errors(
    model: pin.Model, twist_errors: Mapping[str, np.ndarray], joint_offsets: Mapping[str, float]
) -> pin.Model:
    """A copy of `model` whose joints move along actual twists s^a = orthonormal(s + ds) with
    actual values q + dq, expressed through placements only (the local POE model's claim).

    s^a = Ad_C s for the rigid transform C that carries the nominal axis onto the actual one
    (through the joint origin for Pinocchio's joints), so
        T(0) exp(s^a (q + dq)) = [T(0) C exp(s dq)] exp(s q) C^-1,
    i.e. the joint placement becomes T(0) C exp(s dq) and C^-1 moves onto everything the joint
    carries: its child joints' placements and its frames.
    """
    out = pin.Model(model)
    data = out.createData()
    for name in set(twist_errors) | set(joint_offsets):
        if not out.existJointName(name):
            raise InvalidInputError(f"joint '{name}' does not exist")
        j = out.getJointId(name)
        motion = np.array(data.joints[j].S).reshape(6)  # the joint's twist in its own frame, [v; w]
        actual = orthonormal_twist(motion, np.asarray(twist_errors.get(name, np.zeros(6)), dtype=float))
        axis, moved = (motion[3:], actual[3:]) if np.any(motion[3:]) else (motion[:3], actual[:3])
        rotation = pin.Quaternion.FromTwoVectors(axis, moved).matrix()
        point = np.cross(actual[3:], actual[:3]) if np.any(motion[3:]) else np.zeros(3)
        carry = pin.SE3(rotation, point)
        offset = pin.exp6(motion * float(joint_offsets.get(name, 0.0)))
        out.jointPlacements[j] = pin.SE3(out.jointPlacements[j]) * carry * offset
        inverse = carry.inverse()
        for child in range(j + 1, out.njoints):
            if out.parents[child] == j:
                out.jointPlacements[child] = inverse * out.jointPlacements[child]
        for frame in out.frames:
            if frame.parentJoint == j and frame.type != pin.FrameType.JOINT:
                frame.placement = inverse * frame.placement
    return out


def with_outliers(
    measurements: PoseMeasurements, rng: np.random.Generator, count: int, size: tuple[float, float] = (3e-3, 5e-3)
) -> tuple[PoseMeasurements, tuple[int, ...]]:
    """`count` poses moved by a gross error of uniform length in `size` [m] in a random direction
    (a broken beam, a reflector not seated); returns the measurements and the spoiled indices."""
    if not 0 <= count <= len(measurements):
        raise InvalidInputError(f"outliers: {count} of {len(measurements)} poses")
    spoiled = tuple(sorted(int(i) for i in rng.choice(len(measurements), count, replace=False)))
    poses = list(measurements.poses)
    for i in spoiled:
        direction = rng.normal(size=3)
        shift = rng.uniform(*size) * direction / np.linalg.norm(direction)
        poses[i] = pin.SE3(poses[i].rotation, poses[i].translation + shift)
    return PoseMeasurements(measurements.actuators, tuple(poses), measurements.position_only), spoiled


@dataclass(frozen=True)
class SimulatedStudy:
    """A truth machine, calibration measurements on it, and held-out slider sets to judge a model.

    setup: the truth measurement frame and marker the measurements were taken with; outliers:
    indices of the measurements spoiled by gross errors. passive_joints / passive_readings:
    encoder readings (N, k) of those joints of the truth at the measured poses (noisy with
    `StudyOptions.encoder_noise` [rad] when the study is noisy), for cross-validation; the
    calibration does not use them.
    """

    nominal: Mechanism
    truth: Mechanism
    errors: np.ndarray
    measurements: PoseMeasurements
    holdout_actuators: np.ndarray
    seed: int
    passive_joints: tuple[str, ...] = ()
    passive_readings: np.ndarray | None = None
    setup: MeasurementSetup = field(default_factory=MeasurementSetup)
    outliers: tuple[int, ...] = ()


def simulate_study(
    nominal: Mechanism,
    n_poses: int = 50,
    n_holdout: int = 200,
    seed: int = 0,
    *,
    errors: PlacementErrorScale = PlacementErrorScale(),
    noise: TrackerNoise | None = None,
    options: StudyOptions = StudyOptions(),
) -> SimulatedStudy:
    """Draw a truth machine (`errors` on every joint and closure/platform frame), n_poses noisy (or
    exact, noise=None) measurements taken as `options` says and n_holdout other slider sets, all from
    one seed; `options.outliers` of the measurements get a 3-5 mm gross error (drawn last)."""
    if n_poses < 1 or n_holdout < 0:
        raise InvalidInputError(f"n_poses must be >= 1 and n_holdout >= 0, got {n_poses}, {n_holdout}")
    rng = np.random.default_rng(require_count(seed, "seed", minimum=0))
    error_model = ClosedLoopErrorModel(nominal)
    drawn = random_placement_errors(error_model, rng, errors.position, errors.rotation)
    truth = actual_machine(nominal, drawn, error_model)
    actuators = workspace_actuators(nominal, n_poses + n_holdout, rng)
    setup = options.setup
    measurements = measure(truth, actuators[:n_poses], rng, noise, options.position_only, setup)
    passive_joints = tuple(options.passive_joints)
    readings = None
    if passive_joints:
        # Drawn after everything else, so adding encoders does not change the rest of the study.
        columns = [truth.model.idx_qs[truth.model.getJointId(name)] for name in passive_joints]
        readings = assembled_from_home(truth, actuators[:n_poses]).q[:, columns]
        if noise is not None:
            readings = readings + rng.normal(0.0, options.encoder_noise, readings.shape)
    spoiled: tuple[int, ...] = ()
    if options.outliers:
        measurements, spoiled = with_outliers(measurements, rng, options.outliers)
    return SimulatedStudy(
        nominal, truth, drawn, measurements, actuators[n_poses:], seed, passive_joints, readings, setup, spoiled
    )
