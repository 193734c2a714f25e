"""Simulated measurements of a serial robot: sampled configurations and measured poses, with tracker
noise (`TrackerNoise`) and joint-reading noise."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import pinocchio as pin

from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.simulation import PlacementErrorScale
from m3t1r.errors import InvalidInputError
from m3t1r.model.poe import Placement, SerialChain, perturb, tool_poses

__all__ = ["SerialMeasurements", "sample_configurations", "simulate_serial_measurements"]


# --------------------------------------------------------------------------------------------------
# Simulation


def _checked_joint_noise(joint_noise: float) -> float:
    """`joint_noise`, the standard deviation of a serial robot's joint readings (rad or m, the same
    for every joint), as a float; InvalidInputError unless finite and >= 0."""
    value = float(joint_noise)
    if not (np.isfinite(value) and value >= 0.0):
        raise InvalidInputError(f"joint_noise: must be finite and >= 0, got {joint_noise}")
    return value


@dataclass(frozen=True)
class SerialMeasurements:
    """A simulated calibration experiment.

    truth: the "real" robot, nominal placements T(0) exp6(dt) exp6(S dq) (offsets folded in).
    placement_errors: the dt per placement (m, rad); joint_offsets: dq (n,) (rad or m).
    q_true: (N, n) noise-free joint readings; the truth model takes them directly.
    q_readings: (N, n) q_true plus reading noise. measured_poses: tool poses g_{B,P} in {B}, with
    the tracker noise. noise: that tracker noise (None: exact poses); joint_noise: the reading
    noise (rad or m, 0: exact readings).
    """

    truth: pin.Model
    placement_errors: Mapping[Placement, np.ndarray]
    joint_offsets: np.ndarray
    q_true: np.ndarray
    q_readings: np.ndarray
    measured_poses: tuple[pin.SE3, ...]
    noise: TrackerNoise | None
    joint_noise: float = 0.0


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
    errors: PlacementErrorScale = PlacementErrorScale(),
    joint_offset: float = 1e-3,
    noise: TrackerNoise | None = TrackerNoise(),
    joint_noise: float = 0.0,
) -> SerialMeasurements:
    """Draw a true robot and `n_poses` noisy measurements of its tool pose.

    Placement errors: dt ~ N(0, diag(errors.position^2 I3, errors.rotation^2 I3)) (m, rad) on each
    placement of `chain.placements()`. Joint offsets: dq_k ~ N(0, joint_offset^2) (rad or m).
    Measured poses: the tracker's position noise N(0, noise.position^2 I3) (m) in {B} and rotation
    noise R_meas = R exp3(e), e ~ N(0, noise.rotation^2 I3) (rad); exact with noise=None
    (`noise.actuator` is not used). Joint readings: q_true plus N(0, joint_noise^2) per joint
    (rad or m); exact with joint_noise=0.

    A joint offset needs no parameter of its own: T(0) exp(S (q + dq)) = [T(0) exp(S dq)] exp(S q)
    exactly, because exp(S dq) and exp(S q) share their twist and commute. The offset is therefore a
    right-multiplied error exp6(S dq) of the same placement, along the joint twist, and that is how
    the truth model carries it.
    """
    if n_poses < 1:
        raise InvalidInputError(f"n_poses must be >= 1, got {n_poses}")
    joint_noise = _checked_joint_noise(joint_noise)
    sigma = np.r_[np.full(3, errors.position), np.full(3, errors.rotation)]
    placements = chain.placements()
    drawn = {p: rng.normal(0.0, 1.0, 6) * sigma for p in placements}
    offsets = rng.normal(0.0, joint_offset, chain.n_joints)
    truth = perturb(perturb(model, drawn), {p: chain.twists[k] * offsets[k] for k, p in enumerate(placements[:-1])})
    q_true = sample_configurations(model, chain, n_poses, rng)
    q_readings = q_true + rng.normal(0.0, joint_noise, q_true.shape) if joint_noise > 0.0 else q_true.copy()
    measured = []
    for g in tool_poses(chain, truth, q_true):
        if noise is None:
            measured.append(pin.SE3(g[:3, :3], g[:3, 3]))
            continue
        rotation = g[:3, :3] @ pin.exp3(rng.normal(0.0, noise.rotation, 3))
        measured.append(pin.SE3(rotation, g[:3, 3] + rng.normal(0.0, noise.position, 3)))
    frozen_errors = MappingProxyType({p: _readonly(v) for p, v in drawn.items()})
    return SerialMeasurements(
        truth=truth,
        placement_errors=frozen_errors,
        joint_offsets=_readonly(offsets),
        q_true=_readonly(q_true),
        q_readings=_readonly(q_readings),
        measured_poses=tuple(measured),
        noise=noise,
        joint_noise=joint_noise,
    )


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=float)
    array.flags.writeable = False
    return array
