import subprocess
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


@pytest.fixture(scope="session")
def tool_machine(mechanism, tmp_path_factory) -> Mechanism:
    """The M machine with a 'tool' link fixed to P_I (5 cm, 2 cm, -10 cm, yawed 0.3 rad) as its task
    frame: the tracker still measures P_I, IK and compensation command the tool."""
    import yaml

    folder = tmp_path_factory.mktemp("tool_machine")
    joint = (
        '<link name="tool"/><joint name="tool_joint" type="fixed"><parent link="P_I"/><child link="tool"/>'
        '<origin xyz="0.05 0.02 -0.1" rpy="0 0 0.3"/></joint></robot>'
    )
    (folder / "m.urdf").write_text(mechanism.urdf_path.read_text().replace("</robot>", joint))
    closures = yaml.safe_load(mechanism.closures_path.read_text())
    closures["task"]["frame"] = "tool"
    (folder / "m.closures.yaml").write_text(yaml.safe_dump(closures))
    return Mechanism.load(folder / "m.urdf", folder / "m.closures.yaml")


def frame_coordinates(machine: Mechanism, q: np.ndarray, name: str) -> np.ndarray:
    """Task coordinates of frame `name` of `machine` at configuration q, by Pinocchio alone."""
    data = machine.model.createData()
    pin.framesForwardKinematics(machine.model, data, q)
    return machine.task.coordinates(data.oMf[machine.model.getFrameId(name)].homogeneous[None])[0]


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


def process_holding_flock(path: Path) -> subprocess.Popen:
    """A child process that holds `path`'s flock, as a live writer (here, in another container or on
    another host) does, until killed."""
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys, time; f = open(sys.argv[1], 'rb+'); "
            "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)",
            str(path),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert child.stdout.readline().strip() == "held"
    return child
