"""Passive-joint readings against a machine model: the paper's cross-validation with the idle chains.

`m3t1r calibrate` reports it when the measurement file has encoder columns (`m3t1r simulate
--with-passive` writes those of `model.design.IDLE_CHAIN_JOINTS`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from m3t1r.calibration.measurements import assembled_from_home
from m3t1r.model.description import Mechanism

__all__ = ["PassiveJointResiduals", "passive_joint_residuals"]


@dataclass(frozen=True)
class PassiveJointResiduals:
    """Measured minus predicted passive-joint angles [rad] (or positions [m]) at the measured sliders.

    An encoder's zero is not observable from platform poses (a rotation of a joint placement
    about its own axis is absorbed by the next placement), so each joint's constant offset is
    removed first: `offsets` (k,) is it, `residuals` (N, k) what is left, `rms` (k,) their RMS.
    """

    joints: tuple[str, ...]
    offsets: np.ndarray
    residuals: np.ndarray

    @property
    def rms(self) -> np.ndarray:
        return np.sqrt(np.mean(self.residuals**2, axis=0))


def passive_joint_residuals(
    machine: Mechanism, actuators: np.ndarray, joints: tuple[str, ...], readings: np.ndarray
) -> PassiveJointResiduals:
    """How well a machine model predicts passive-joint readings it was not fitted to.

    With readings of the idle chains' hinges (IDLE_CHAIN_JOINTS) this is the paper's
    cross-validation with the idle pair of branched chains: closed-loop FK of the model at each
    slider set predicts those angles; a good model leaves only encoder noise.
    """
    model = machine.model
    columns = [model.idx_qs[model.getJointId(name)] for name in joints]
    predicted = assembled_from_home(machine, actuators).q[:, columns]
    difference = np.asarray(readings, dtype=float) - predicted
    offsets = difference.mean(axis=0)
    return PassiveJointResiduals(tuple(joints), offsets, difference - offsets)
