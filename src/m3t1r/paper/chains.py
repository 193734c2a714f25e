"""The paper's chains i = 1, 2 (B1 -> P and B3 -> P) as serial chains of the mechanism's tree, and
the readings and measured poses they are fitted to.

On this repository's machine (`docs/design.md`, "The mechanism") the paper's "equivalent" revolute
joints q_i2, q_i3 are parallelograms: chain B1 is (q11, q12, q12_pa, q13, q13_pa, q14, P_I), the
coupling joints q_i2_pa, q_i3_pa being read like every other joint of the chain. Chain B3 ends
at P_II, the second copy of the platform frame, welded to P_I by the platform closure.

Readings are full Pinocchio configurations (N, nq) of the mechanism's tree (or {joint: values});
only the entries of the joints that are read matter.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r.errors import InvalidInputError, ModelFileError
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.poe import SerialChain, forward_and_error_jacobians

__all__ = ["PaperChain", "paper_chains"]

_TWIST = 6
_CHAIN_LENGTH = 7  # q_i1, q_i2, q_i2_pa, q_i3, q_i3_pa, q_i4, tool frame


@dataclass(frozen=True)
class PaperChain:
    """Chain i of the paper (B1 -> P or B3 -> P) as a serial chain of the mechanism's tree.

    Roles come from the position of each joint in the mechanism's `principal_chains` entry
    (slider, upper crank, its coupling joint, lower crank, its coupling joint, platform hinge,
    tool frame), never from joint names. The paper's q_i1..q_i4 are slider, upper_crank,
    lower_crank, platform_hinge. The foot A_i of section 4 is the origin of the lower coupling
    joint's frame: that joint's axis passes through it, so its position does not depend on the
    coupling angle.
    """

    name: str
    serial: SerialChain
    slider: str
    upper_crank: str
    upper_coupling: str
    lower_crank: str
    lower_coupling: str
    platform_hinge: str
    tool_frame: str

    @property
    def n_parameters(self) -> int:
        return self.serial.n_parameters

    def coordinates(self, configurations: np.ndarray) -> np.ndarray:
        """Chain coordinates (N, 6) (m for the slider, rad otherwise) from configurations (N, nq).

        One column per joint: a `Mechanism` only has one-DoF joints with nq = 1.
        """
        return configurations[:, list(self.serial.idx_q)]


def paper_chains(mechanism: Mechanism) -> tuple[PaperChain, PaperChain]:
    """The paper's chains i = 1, 2, in the order of `mechanism.principal_chains` (B1, B3).

    Raises ModelFileError when the description does not declare exactly two principal chains of
    six one-DoF joints and a tool frame, or when a listed chain is not the tree path from the base
    to its tool frame (the serial POE needs the listed joints to be exactly that path).
    """
    entries = mechanism.principal_chains
    where = mechanism.closures_path
    if len(entries) != 2:
        raise ModelFileError(
            where,
            f"principal_chains: the paper's two-chain method is specific to the M machine's "
            f"structure and needs its 2 principal chains, found {len(entries)}; other "
            "mechanisms calibrate with the closed-loop method (`m3t1r calibrate`)",
        )
    chains = []
    for name, items in entries.items():
        if len(items) != _CHAIN_LENGTH:
            raise ModelFileError(where, f"principal_chains.{name}: expected 6 joints and a tool frame, got {items}")
        serial = SerialChain.from_model(mechanism.model, items[-1])
        if serial.joint_names != tuple(items[:-1]):
            raise ModelFileError(
                where,
                f"principal_chains.{name}: the tree path to '{items[-1]}' is {serial.joint_names}, "
                f"not the listed {tuple(items[:-1])}",
            )
        chains.append(PaperChain(name, serial, *items))
    return chains[0], chains[1]


def _as_configurations(mechanism: Mechanism, readings: ArrayLike | Mapping[str, ArrayLike]) -> np.ndarray:
    """Readings as configurations (N, nq): an array as is, or {joint: (N,)} over the home pose."""
    model = mechanism.model
    if isinstance(readings, Mapping):
        columns = {}
        for name, values in readings.items():
            if not model.existJointName(name):
                raise InvalidInputError(f"readings: no joint named '{name}' in the model")
            columns[name] = np.asarray(values, dtype=float).reshape(-1)
        sizes = {v.size for v in columns.values()}
        if len(sizes) != 1:
            raise InvalidInputError(f"readings: joints have different numbers of values {sorted(sizes)}")
        q = np.tile(mechanism.home, (sizes.pop(), 1))
        for name, values in columns.items():
            q[:, model.idx_qs[model.getJointId(name)]] = values
    else:
        q = np.array(readings, dtype=float)
        if q.ndim != 2 or q.shape[1] != model.nq:
            raise InvalidInputError(f"readings: expected configurations of shape (N, {model.nq}), got {q.shape}")
    if q.shape[0] < 1:
        raise InvalidInputError("readings: no pose")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"readings: non-finite value in row {int(np.flatnonzero(~np.isfinite(q).all(1))[0])}")
    return q


def _per_chain_poses(
    chains: Sequence[PaperChain], measured: Sequence[pin.SE3] | Mapping[str, Sequence[pin.SE3]], n_poses: int
) -> tuple[tuple[pin.SE3, ...], ...]:
    if isinstance(measured, Mapping):
        if set(measured) != {c.name for c in chains}:
            raise InvalidInputError(
                f"measured_poses: keys {sorted(measured)} are not the chains {[c.name for c in chains]}"
            )
        per_chain = [tuple(measured[c.name]) for c in chains]
    else:
        per_chain = [tuple(measured)] * len(chains)
    for chain, poses in zip(chains, per_chain):
        if len(poses) != n_poses:
            raise InvalidInputError(f"chain {chain.name}: {len(poses)} measured poses for {n_poses} readings")
        if not all(isinstance(g, pin.SE3) for g in poses):
            raise InvalidInputError(f"chain {chain.name}: measured poses must be pinocchio.SE3")
    return tuple(per_chain)


def _pose_differences(poses: Sequence[pin.SE3], references: Sequence[pin.SE3]) -> PoseErrors:
    """Position distance (m) and rotation angle of R_ref^T R (rad), pose by pose (the paper's Fig. 4)."""
    position = np.array([np.linalg.norm(g.translation - h.translation) for g, h in zip(poses, references)])
    rotation = np.array([np.linalg.norm(pin.log3(h.rotation.T @ g.rotation)) for g, h in zip(poses, references)])
    return PoseErrors(position, rotation)


def _chain_poses(chain: PaperChain, model: pin.Model, configurations: np.ndarray) -> tuple[pin.SE3, ...]:
    return tuple(forward_and_error_jacobians(chain.serial, model, chain.coordinates(configurations))[0])
