"""Simulated machines and measurements (paper section 6), for studies, tests and the demo.

An "actual" machine is the nominal description with right-multiplied errors on its initial poses
(paper eq. 34). The paper also perturbs joint twists (eq. 35) and joint variables (eq. 36); in the
local POE model both are absorbed by initial poses (a twist error conjugates the joint motion, an
offset is a motion along the joint's own twist), so random placement errors on every joint and
frame already span what a real machine can be, and that is what `actual_machine` applies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ._threads import on_one_blas_thread
from .calibration import ClosedLoopErrorModel, PoseMeasurements, TrackerNoise
from .description import Mechanism
from .errors import InvalidInputError, KinematicsError
from .kinematics import ClosedLoopSolver, rehomed

__all__ = ["SimulatedStudy", "random_placement_errors", "actual_machine", "workspace_actuators",
           "measure", "simulate_study"]


def random_placement_errors(error_model: ClosedLoopErrorModel, rng: np.random.Generator,
                            sigma_position: float, sigma_rotation: float) -> np.ndarray:
    """Gaussian errors dt = [v; w] for every parameter: sigma_position [m] on v, sigma_rotation [rad] on w."""
    scale = np.tile(np.r_[np.full(3, sigma_position), np.full(3, sigma_rotation)], len(error_model.placements))
    return rng.normal(0.0, 1.0, error_model.n_parameters) * scale


def actual_machine(nominal: Mechanism, errors: np.ndarray, error_model: ClosedLoopErrorModel | None = None) -> Mechanism:
    """The nominal machine with placement errors applied (eq. 34) and its home re-assembled."""
    error_model = error_model or ClosedLoopErrorModel(nominal)
    return rehomed(nominal.with_model(error_model.perturbed(nominal.model, errors)))


@on_one_blas_thread
def workspace_actuators(nominal: Mechanism, n: int, rng: np.random.Generator) -> np.ndarray:
    """n slider sets (n x 4) [m]: platform poses drawn uniformly in the design's workspace box,
    through the nominal model's IK (each from home, so every pose is on the home branch)."""
    from .design import NOMINAL

    solver = ClosedLoopSolver(nominal)
    rows = []
    for pose in NOMINAL.workspace.sample(rng, n):
        rows.append(solver.inverse(pose, q_init=nominal.home).actuators)
    return np.array(rows)


@on_one_blas_thread
def measure(machine: Mechanism, actuators: np.ndarray, rng: np.random.Generator | None = None,
            noise: TrackerNoise | None = None, position_only: bool = False) -> PoseMeasurements:
    """What a tracker sees on `machine` driven at `actuators`, and what the slider encoders read.

    With `noise`, the recorded poses get Gaussian position [m] and rotation (right-multiplied,
    [rad]) noise and the recorded slider readings Gaussian noise; without, both are exact.
    """
    solver = ClosedLoopSolver(machine)
    poses = []
    for sliders in actuators:
        try:
            poses.append(solver.forward(sliders).pose)
        except KinematicsError as exc:
            raise InvalidInputError(f"slider set {sliders} does not assemble on the machine: {exc}") from None
    readings = np.array(actuators, dtype=float)
    if noise is not None:
        if rng is None:
            raise InvalidInputError("measure: noise needs a random generator")
        poses = [pin.SE3(p.rotation @ pin.exp3(rng.normal(0.0, noise.rotation, 3)),
                         p.translation + rng.normal(0.0, noise.position, 3)) for p in poses]
        readings = readings + rng.normal(0.0, noise.actuator, readings.shape)
    return PoseMeasurements(readings, tuple(poses), position_only)


@dataclass(frozen=True)
class SimulatedStudy:
    """A truth machine, calibration measurements on it, and held-out slider sets to judge a model.

    passive_joints / passive_readings: encoder readings (N, k) of those joints of the truth at
    the measured poses (noisy with `encoder_noise` [rad] when the study is noisy), for
    cross-validation; the calibration does not use them.
    """

    nominal: Mechanism
    truth: Mechanism
    errors: np.ndarray
    measurements: PoseMeasurements
    holdout_actuators: np.ndarray
    seed: int
    passive_joints: tuple[str, ...] = ()
    passive_readings: np.ndarray | None = None


def simulate_study(nominal: Mechanism, n_poses: int = 50, n_holdout: int = 200, seed: int = 0,
                   sigma_position: float = 1e-3, sigma_rotation: float = 1e-3, noise: TrackerNoise | None = None,
                   position_only: bool = False, passive_joints: tuple[str, ...] = (),
                   encoder_noise: float = 1e-5) -> SimulatedStudy:
    """Draw a truth machine (errors on every joint and closure/platform frame), n_poses noisy (or
    exact, noise=None) measurements and n_holdout other slider sets, all from one seed."""
    if n_poses < 1 or n_holdout < 0:
        raise InvalidInputError(f"n_poses must be >= 1 and n_holdout >= 0, got {n_poses}, {n_holdout}")
    rng = np.random.default_rng(seed)
    error_model = ClosedLoopErrorModel(nominal)
    errors = random_placement_errors(error_model, rng, sigma_position, sigma_rotation)
    truth = actual_machine(nominal, errors, error_model)
    actuators = workspace_actuators(nominal, n_poses + n_holdout, rng)
    measurements = measure(truth, actuators[:n_poses], rng, noise, position_only)
    readings = None
    if passive_joints:
        # Drawn after everything else, so adding encoders does not change the rest of the study.
        solver = ClosedLoopSolver(truth)
        columns = [truth.model.idx_qs[truth.model.getJointId(name)] for name in passive_joints]
        readings = np.array([solver.forward(sliders).q[columns] for sliders in actuators[:n_poses]])
        if noise is not None:
            readings = readings + rng.normal(0.0, encoder_noise, readings.shape)
    return SimulatedStudy(nominal, truth, errors, measurements, actuators[n_poses:], seed, tuple(passive_joints),
                          readings)
