import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from m3t1r.model.description import Mechanism  # noqa: E402
from m3t1r.model.kinematics import ClosedLoopSolver  # noqa: E402


@pytest.fixture(scope="session")
def mechanism() -> Mechanism:
    return Mechanism.load()


@pytest.fixture()
def solver(mechanism) -> ClosedLoopSolver:
    return ClosedLoopSolver(mechanism)


def perturb_every_origin(model: pin.Model, rng: np.random.Generator, sigma_m: float, sigma_rad: float) -> pin.Model:
    """A copy with every joint placement and every frame placement right-multiplied by a random error."""
    out = model.copy()
    scale = np.r_[np.full(3, sigma_m), np.full(3, sigma_rad)]
    for j in range(1, model.njoints):
        out.jointPlacements[j] = pin.SE3(model.jointPlacements[j]) * pin.exp6(rng.normal(0, 1, 6) * scale)
    for frame in out.frames:
        if frame.type in (pin.FrameType.BODY, pin.FrameType.OP_FRAME) and frame.parentFrame != 0:
            frame.placement = frame.placement * pin.exp6(rng.normal(0, 1, 6) * scale)
    return out
