"""The actual chains and sensors of the paper's simulation (section 6): the preset errors of Table 1
on initial poses, twists and joint variables (eq. 34-36), the actual chains' tool poses (eq. 37),
and what noisy sensors and a noisy tracker read of them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import pinocchio as pin

from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.errors import InvalidInputError
from m3t1r.model.description import Mechanism
from m3t1r.model.poe import Placement
from m3t1r.paper.chains import _TWIST, PaperChain
from m3t1r.paper.identification import EXACT_DATA_REL_TOL, NOISY_READINGS_REL_TOL, TwoChainOptions

__all__ = [
    "PASSIVE_ENCODER_NOISE",
    "PresetErrorScale",
    "PresetErrors",
    "TwoChainStudyOptions",
    "actual_chain_poses",
    "preset_errors",
    "sensor_readings",
]

#: Standard deviation [rad] of the rotary encoders on the chains' passive joints, which the paper's
#: method reads (every joint of both chains), in a study with noise. The tracker and the slider
#: encoders are a `TrackerNoise`.
PASSIVE_ENCODER_NOISE = 1e-5


@dataclass(frozen=True)
class TwoChainStudyOptions:
    """The rarer settings of `paper_study` and `closed_chain_study`.

    passive_encoder_noise: standard deviation [rad] of the passive joints' encoders in a study with
        noise (a study without noise reads every joint exactly).
    fit: the settings of `calibrate_two_chains`; None: its defaults with the rank threshold chosen
        by the data, `EXACT_DATA_REL_TOL` without noise and `NOISY_READINGS_REL_TOL` with it.
    """

    passive_encoder_noise: float = PASSIVE_ENCODER_NOISE
    fit: TwoChainOptions | None = None

    def fit_options(self, noisy: bool) -> TwoChainOptions:
        """The settings of the study's `calibrate_two_chains`, for noisy or exact readings."""
        if self.fit is not None:
            return self.fit
        return TwoChainOptions(rank_tolerance=NOISY_READINGS_REL_TOL if noisy else EXACT_DATA_REL_TOL)


@dataclass(frozen=True)
class PresetErrorScale:
    """Standard deviations of the preset errors of Table 1 (the paper's table is missing; these
    are the orders its text implies: millimetres and milliradians on metre-size links).

    placement_position (m) and placement_rotation (rad): dt = [v; w] on every T(0) (eq. 34).
    twist: ds on every joint twist (dimensionless), before orthonormalisation (eq. 35).
    joint_offset: dq on every joint variable (m for the slider, rad otherwise) (eq. 36).
    """

    placement_position: float = 1e-3
    placement_rotation: float = 1e-3
    twist: float = 1e-3
    joint_offset: float = 1e-3


@dataclass(frozen=True)
class PresetErrors:
    """The actual chains' errors (Table 1 of the paper), keyed by placement or joint name.

    placement: dt (6,) per placement of both chains (T^a(0) = T(0) exp6(dt), eq. 34).
    twist: the actual twist s^a (6,) per joint, in the joint's frame (eq. 35), orthonormalised:
        revolute |w| = 1 and w . v = 0 (a pure rotation about a displaced, tilted axis);
        prismatic |v| = 1 and w = 0.
    twist_error: ds = s^a - s per joint.
    joint_offset: dq per joint (q^a = q + dq, eq. 36).
    """

    placement: Mapping[Placement, np.ndarray]
    twist: Mapping[str, np.ndarray]
    twist_error: Mapping[str, np.ndarray]
    joint_offset: Mapping[str, float]
    scale: PresetErrorScale

    def rows(self) -> tuple[tuple[str, str, tuple[float, ...]], ...]:
        """Table 1 as rows (name, quantity, values): 'dt' per placement, 'ds' and 'dq' per joint."""
        out: list[tuple[str, str, tuple[float, ...]]] = []
        for placement, dt in self.placement.items():
            out.append((placement.name, "dt", tuple(float(v) for v in dt)))
        for name, ds in self.twist_error.items():
            out.append((name, "ds", tuple(float(v) for v in ds)))
        for name, dq in self.joint_offset.items():
            out.append((name, "dq", (float(dq),)))
        return tuple(out)


def _orthonormal_twist(twist: np.ndarray, error: np.ndarray) -> np.ndarray:
    """s + ds projected back onto one-DoF joint twists of the same kind (section 6)."""
    v, w = twist[:3] + error[:3], twist[3:] + error[3:]
    if np.linalg.norm(twist[3:]) == 0.0:  # prismatic: a unit direction, no rotation
        return np.r_[v / np.linalg.norm(v), np.zeros(3)]
    w = w / np.linalg.norm(w)
    return np.r_[v - (w @ v) * w, w]  # zero pitch: a pure rotation


def preset_errors(
    chains: Sequence[PaperChain], rng: np.random.Generator, scale: PresetErrorScale = PresetErrorScale()
) -> PresetErrors:
    """Draw Table 1: Gaussian dt, ds, dq with the standard deviations of `scale`."""
    placement: dict[Placement, np.ndarray] = {}
    twist: dict[str, np.ndarray] = {}
    twist_error: dict[str, np.ndarray] = {}
    offset: dict[str, float] = {}
    sigma = np.r_[np.full(3, scale.placement_position), np.full(3, scale.placement_rotation)]
    for chain in chains:
        for p in chain.serial.placements():
            placement[p] = rng.normal(0.0, 1.0, _TWIST) * sigma
        for name, s in zip(chain.serial.joint_names, chain.serial.twists):
            actual = _orthonormal_twist(s, rng.normal(0.0, scale.twist, _TWIST))
            twist[name], twist_error[name] = actual, actual - s
            offset[name] = float(rng.normal(0.0, scale.joint_offset))
    for value in (*placement.values(), *twist.values(), *twist_error.values()):
        value.flags.writeable = False
    return PresetErrors(
        MappingProxyType(placement),
        MappingProxyType(twist),
        MappingProxyType(twist_error),
        MappingProxyType(offset),
        scale,
    )


def actual_chain_poses(
    chain: PaperChain, model: pin.Model, preset: PresetErrors, configurations: np.ndarray
) -> tuple[pin.SE3, ...]:
    """Tool poses of the actual chain i (eq. 37) at the true joint values of configurations (N, nq):

        g_i = T^a_B,1(0) exp(s^a_1 q^a_1) T^a_1,2(0) ... exp(s^a_n q^a_n) T^a_n,P(0)

    with T^a(0) = T(0) exp6(dt) (eq. 34), s^a (eq. 35) and q^a = q + dq (eq. 36).

    Why the paper's model, with errors on the initial poses only, can represent this chain
    exactly: an orthonormal twist s^a of the same kind as s is s moved by a constant rigid
    transform C (s^a = Ad_C s: the axis tilted and displaced), so exp(s^a q) = C exp(s q) C^-1
    and C, C^-1 merge into the neighbouring initial poses. An offset is a motion along the
    joint's own twist, exp(s (q + dq)) = exp(s dq) exp(s q), and exp(s dq) merges into the
    preceding initial pose. Neither needs a parameter of its own (section 3.1, eq. 11).
    """
    initial = chain.serial.initial_poses(model)
    actual = [T * pin.exp6(preset.placement[p]) for T, p in zip(initial, chain.serial.placements())]
    twists = [preset.twist[name] for name in chain.serial.joint_names]
    offsets = np.array([preset.joint_offset[name] for name in chain.serial.joint_names])
    poses = []
    for q in chain.coordinates(configurations) + offsets:
        g = pin.SE3.Identity()
        for T, s, value in zip(actual, twists, q):
            g = g * T * pin.exp6(s * value)
        poses.append(g * actual[-1])
    return tuple(poses)


def _checked_passive_encoder_noise(passive_encoder_noise: float) -> float:
    value = float(passive_encoder_noise)
    if not (math.isfinite(value) and value >= 0.0):
        raise InvalidInputError(f"passive_encoder_noise must be finite and >= 0, got {passive_encoder_noise}")
    return value


def sensor_readings(
    mechanism: Mechanism,
    chains: Sequence[PaperChain],
    configurations: np.ndarray,
    noise: TrackerNoise | None,
    passive_encoder_noise: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """What the sensors of both chains read at `configurations` (N, nq) [m, rad]: sliders with the
    slider noise (`noise.actuator`, m) and every other chain joint with `passive_encoder_noise`
    (rad); joints of no chain, and every joint with noise=None, read exactly. (N, nq)."""
    readings = configurations.copy()
    if noise is None:
        return readings
    actuated = set(mechanism.actuated_joints)
    for chain in chains:
        for name, index in zip(chain.serial.joint_names, chain.serial.idx_q):
            sigma = noise.actuator if name in actuated else passive_encoder_noise
            readings[:, index] += rng.normal(0.0, sigma, readings.shape[0])
    return readings


def _observe(poses: Sequence[pin.SE3], noise: TrackerNoise | None, rng: np.random.Generator) -> tuple[pin.SE3, ...]:
    """Tracker measurements: position noise in {B}, rotation noise right-multiplied (m, rad)."""
    if noise is None:
        return tuple(poses)
    return tuple(
        pin.SE3(
            g.rotation @ pin.exp3(rng.normal(0.0, noise.rotation, 3)),
            g.translation + rng.normal(0.0, noise.position, 3),
        )
        for g in poses
    )
