"""MJCF mechanisms (m3t1r.model.mjcf_io): loops read through Pinocchio's MJCF parser load as the
Mechanism a URDF and a closures file give, solve against independent references, write a URDF
pair that reloads as the same machine, and what has no closures-file form is refused by element."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from mjcf_mechanisms import (
    FIVE_BAR_BASE,
    FIVE_BAR_CRANK,
    FIVE_BAR_ROD,
    STRAIGHT_FOUR_BAR,
    STRAIGHT_GAP,
    five_bar_mjcf,
    slider_crank_mjcf,
    spatial_loop_mjcf,
    straight_four_bar_mjcf,
)

from m3t1r.app.cli import main
from m3t1r.calibration.closed_loop import pose_errors
from m3t1r.errors import ModelFileError, ModelWarning
from m3t1r.io.pairing import closures_sha256, recorded_closures_sha256
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver


def _load(path: Path, closures: Path | None = None) -> Mechanism:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        return Mechanism.load(path, closures)


def _five_bar_tip(actuators: np.ndarray) -> np.ndarray:
    """The five-bar's effector from two circles: centres at the crank tips, radius the rod's tip
    distance, the intersection of larger y (the mode of the reference configuration)."""
    radius = math.hypot(*FIVE_BAR_ROD)
    centres = [
        np.array([side * FIVE_BAR_BASE - FIVE_BAR_CRANK * math.sin(angle), FIVE_BAR_CRANK * math.cos(angle)])
        for side, angle in zip((-1, 1), actuators)
    ]
    half = (centres[1] - centres[0]) / 2
    normal = np.array([-half[1], half[0]]) / np.linalg.norm(half)
    tip = centres[0] + half + normal * math.sqrt(radius**2 - half @ half)
    return (
        tip
        if tip[1] > (centres[0] + half - normal)[1]
        else centres[0] + half - normal * math.sqrt(radius**2 - half @ half)
    )


def test_a_five_bar_connect_loads_as_a_3d_closure_with_motors_limits_and_home(tmp_path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ModelWarning)
        mechanism = Mechanism.load(five_bar_mjcf(tmp_path))
    assert mechanism.actuated_joints == ("motor_l", "motor_r")
    (closure,) = mechanism.closures
    assert (closure.name, closure.type, closure.rows) == ("tip", "3D", (0, 1))  # the planar z row dropped
    assert mechanism.platform_frame == "effector"
    lower, upper = mechanism.joint_limits()
    assert np.allclose(lower, -0.3) and np.allclose(upper, 0.3)
    assert np.array_equal(mechanism.home, np.zeros(4))  # qpos0 closes as published
    notes = [str(w.message) for w in caught]
    assert any("site 'effector', the file's only site" in n for n in notes)
    assert any("tip[2]" in n for n in notes)


def test_the_five_bar_solves_as_two_circles_intersect(tmp_path):
    solver = ClosedLoopSolver(_load(five_bar_mjcf(tmp_path)))
    for actuators in np.random.default_rng(3).uniform(-0.3, 0.3, size=(20, 2)):
        pose = solver.forward(actuators).pose
        assert np.abs(pose.translation[:2] - _five_bar_tip(actuators)).max() < 1e-9
        assert abs(pose.translation[2]) < 1e-12


def test_a_linkage_published_stretched_straight_assembles(tmp_path):
    """Every link on one line at qpos0 (the cut sites 4 cm apart along it): no joint motion shortens
    the gap at first order, so a solve from there stalls; load restarts from small offsets, and the
    home it reaches closes. Forward kinematics then gives a tracer at the coupler's length from the
    crank tip and the rocker's from its pivot, on one side of the line for every crank angle."""
    ground, crank, coupler, rocker = STRAIGHT_FOUR_BAR
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ModelWarning)
        mechanism = Mechanism.load(straight_four_bar_mjcf(tmp_path))
    notes = [str(w.message) for w in caught]
    assert any(f"closure 'loop' residual {STRAIGHT_GAP:.3e} > 1e-09; assembled" in n for n in notes), notes
    solver = ClosedLoopSolver(mechanism)
    sides = set()
    for angle in np.linspace(-0.4, 0.4, 9):
        tracer = solver.forward(np.array([angle])).pose.translation
        tip = crank * np.array([math.cos(angle), math.sin(angle), 0.0])
        assert np.linalg.norm(tracer - tip) == pytest.approx(coupler, abs=1e-12)
        assert np.linalg.norm(tracer - [ground, 0.0, 0.0]) == pytest.approx(rocker, abs=1e-12)
        arm, reach = tip[:2] - [ground, 0.0], tracer[:2] - [ground, 0.0]
        sides.add(bool(arm[0] * reach[1] - arm[1] * reach[0] > 0.0))
    assert len(sides) == 1


def test_a_spatial_weld_closes_as_pinocchios_own_constraint_says(tmp_path):
    path = spatial_loop_mjcf(tmp_path)
    with pytest.raises(ModelFileError, match=r"name the platform frame .*platform, tool.* spatial_loop.closures.yaml"):
        Mechanism.load(path)
    (tmp_path / "spatial_loop.closures.yaml").write_text("platform_frame: platform\n")
    mechanism = _load(path)
    assert [(c.type, c.rows) for c in mechanism.closures] == [("6D", (0, 1, 2, 3, 4, 5))]
    assert mechanism.actuated_joints == ("j1",)
    # The file has one root body, so Pinocchio reads it as is: its weld is the independent reference.
    model, _, welds = pin.buildModelAndConstraintsFromMJCF(str(path))
    (weld,) = welds
    data = model.createData()
    solver = ClosedLoopSolver(mechanism)
    for angle in np.linspace(-0.3, 0.3, 7):
        q = solver.forward([angle]).q
        pin.forwardKinematics(model, data, q)
        placement = (data.oMi[weld.joint1_id] * weld.joint1_placement).actInv(
            data.oMi[weld.joint2_id] * weld.joint2_placement
        )
        assert np.abs(pin.log6(placement).vector).max() < 1e-9
        assert abs(q[0] - angle) < 1e-15


@pytest.mark.parametrize("refs", [False, True])
def test_ranges_are_qpos_values_slides_in_metres_under_degree_angles(tmp_path, refs):
    path = slider_crank_mjcf(tmp_path)
    if refs:  # a reference position on each joint, and a range from a default class
        text = path.read_text().replace('range="-0.05 0.05"', 'range="-0.05 0.05" ref="0.02"')
        text = text.replace('range="-90 90"', 'range="-90 90" ref="10"').replace(
            '<joint name="crank" type="hinge"', '<joint name="crank" class="c" ref="5"'
        )
        text = text.replace('<joint name="slide" type="slide"', '<joint name="slide" class="s"').replace(
            ' range="-0.05 0.05"', ""
        )
        path.write_text(
            text.replace(
                "<worldbody>",
                '<default><default class="c"><joint type="hinge" range="-45 45"/>'
                '</default><default class="s"><joint type="slide" '
                'range="-0.05 0.05"/></default></default><worldbody>',
            )
        )
    mechanism = _load(path)
    lower, upper = mechanism.joint_limits(("slide", "pin", "crank"))
    crank = math.pi / 4 if refs else math.inf
    assert np.allclose(lower, [-0.05, -math.pi / 2, -crank]) and np.allclose(upper, [0.05, math.pi / 2, crank])
    assert np.allclose(mechanism.home, [0.02, math.radians(10), math.radians(5)] if refs else 0.0)


def test_a_keyframe_named_home_is_assembled_from_its_motor_values(tmp_path):
    keys = '<keyframe><key name="first" qpos="0 0 0 0"/><key name="home" qpos="0.3 0 -0.2 0"/></keyframe>'
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ModelWarning)
        mechanism = Mechanism.load(five_bar_mjcf(tmp_path, keyframe=keys))
    assert mechanism.home_assembly is not None
    assert any("home does not close" in str(w.message) or "assembled" in str(w.message) for w in caught)
    home = mechanism.home
    assert (home[0], home[2]) == (0.3, -0.2)
    tip = ClosedLoopSolver(mechanism).forward([0.3, -0.2]).pose.translation
    assert np.abs(tip[:2] - _five_bar_tip(np.array([0.3, -0.2]))).max() < 1e-9


@pytest.mark.parametrize("offset", ["0 0 0", "0.01 0.02 0"])
def test_a_written_mjcf_machine_reloads_as_a_urdf_pair_of_the_same_machine(tmp_path, offset):
    path = five_bar_mjcf(tmp_path)  # a hinge off its body's origin (MJCF joint pos) puts the body on a fixed joint
    path.write_text(
        path.read_text().replace('name="elbow_l" type="hinge"', f'name="elbow_l" pos="{offset}" type="hinge"')
    )
    mechanism = _load(path)
    mechanism.save(tmp_path / "five_bar.urdf")
    reloaded = _load(tmp_path / "five_bar.urdf")
    assert reloaded.source == "urdf" and reloaded.actuated_joints == mechanism.actuated_joints
    assert [(c.type, c.rows) for c in reloaded.closures] == [(c.type, c.rows) for c in mechanism.closures]
    actuators = np.random.default_rng(4).uniform(-0.3, 0.3, size=(10, 2))
    errors = pose_errors(reloaded, mechanism, actuators)
    assert errors.position_max < 1e-12 and errors.rotation_max < 1e-12
    assert np.allclose(reloaded.joint_limits()[0], -0.3)
    assert [reloaded.model.inertias[j].mass for j in range(1, 5)] == pytest.approx(
        [mechanism.model.inertias[j].mass for j in range(1, 5)], rel=1e-12
    )


@pytest.mark.parametrize(
    "change, message",
    [
        ({"actuators": ""}, r"no <actuator> on a joint"),
        ({"actuators": '<motor joint="motor_x"/>'}, r"line \d+: <motor>: joint 'motor_x' is not a joint of the file"),
        ({"actuators": '<motor tendon="belt"/>'}, r"line \d+: <motor>: a tendon transmission"),
        (
            {"equality": '<connect name="tip" body1="rod_l" body2="rod_x" anchor="0 0 0"/>'},
            r"line \d+: <connect name='tip'>: body2 'rod_x' is not a body of the file",
        ),
        (
            {"equality": '<tendon name="belt" tendon1="t"/>'},
            r"line \d+: <tendon name='belt'>: a tendon equality has no closure",
        ),
        (
            {"equality": '<connect body1="rod_l" body2="rod_r" anchor="0.1 0.15 0" active="false"/>'},
            r"no active <equality> connect or weld",
        ),
        (
            {"keyframe": '<keyframe><key qpos="0 0"/></keyframe>'},
            r"line \d+: <key>: qpos has 2 values for the file's 4",
        ),
    ],
)
def test_what_cannot_be_mapped_is_named_by_element_and_line(tmp_path, change, message):
    with pytest.raises(ModelFileError, match=message):
        Mechanism.load(five_bar_mjcf(tmp_path, **change))


def test_a_file_cut_short_is_named_as_mjcf_with_its_line(tmp_path):
    path = five_bar_mjcf(tmp_path)
    path.write_text(path.read_text()[:200])
    with pytest.raises(ModelFileError, match=r"five_bar.xml: not well-formed XML: .*line \d+"):
        Mechanism.load(path)


@pytest.mark.parametrize(
    "old, new, message",
    [
        (
            '<joint name="elbow_l" type="hinge" axis="0 0 1"/>',
            '<joint name="elbow_l" type="ball"/>',
            r"line \d+: <joint name='elbow_l'>: a ball joint",
        ),
        (
            '<joint name="elbow_l" type="hinge" axis="0 0 1"/>',
            '<freejoint name="loose"/>',
            r"<freejoint .*a free joint",
        ),
        (
            '<joint name="elbow_l" type="hinge" axis="0 0 1"/>',
            '<joint name="elbow_l" type="hinge" axis="0 0 1"/><joint name="twist" type="hinge" axis="1 0 0"/>',
            r"line \d+: <body name='rod_l'>: 2 joints on one body",
        ),
    ],
)
def test_joints_without_a_one_dof_form_are_refused(tmp_path, old, new, message):
    path = five_bar_mjcf(tmp_path)
    path.write_text(path.read_text().replace(old, new))
    with pytest.raises(ModelFileError, match=message):
        Mechanism.load(path)


def test_a_loop_without_enough_actuators_is_refused(tmp_path):
    with pytest.raises(ModelFileError, match=r"leave 1 degree\(s\) of freedom beyond the actuators"):
        Mechanism.load(five_bar_mjcf(tmp_path, actuators='<motor joint="motor_l"/>'))


def test_a_sidecar_gives_the_task_but_not_what_the_mjcf_gives(tmp_path):
    path = five_bar_mjcf(tmp_path)
    sidecar = tmp_path / "five_bar.closures.yaml"
    sidecar.write_text("platform_frame: effector\ntask: {position: [x, y]}\nhome: {motor_l: 0.2}\n")
    mechanism = _load(path)
    assert mechanism.task.dimension == 2 and mechanism.home[0] == 0.2 and mechanism.closures_path == sidecar
    sidecar.write_text("platform_frame: effector\nactuated_joints: [motor_l]\n")
    with pytest.raises(ModelFileError, match=r"five_bar.closures.yaml: 'actuated_joints' comes from five_bar.xml"):
        Mechanism.load(path)
    sidecar.write_text("platform_frame: nowhere\n")
    with pytest.raises(ModelFileError, match=r"platform_frame: frame 'nowhere' does not exist"):
        Mechanism.load(path)


def test_a_sidecar_named_on_load_is_read_wherever_it_is(tmp_path):
    path = five_bar_mjcf(tmp_path)
    (tmp_path / "five_bar.closures.yaml").write_text("platform_frame: effector\nhome: {motor_l: 0.2}\n")
    sidecar = tmp_path / "elsewhere" / "task.yaml"
    sidecar.parent.mkdir()
    sidecar.write_text("platform_frame: effector\ntask: {position: [x, y]}\nhome: {motor_l: 0.1}\n")
    mechanism = _load(path, sidecar)
    assert (mechanism.urdf_path, mechanism.closures_path, mechanism.home[0]) == (path, sidecar, 0.1)
    assert mechanism.task.dimension == 2
    sidecar.write_text("platform_frame: [\n")
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(path, sidecar)
    assert str(caught.value) == (
        f"{sidecar}: line 2, column 1: not valid YAML: expected the node content, but found '<stream end>'"
    )


def test_an_mjcf_machine_without_a_sidecar_is_its_own_closures_file(tmp_path):
    path = five_bar_mjcf(tmp_path)
    mechanism = _load(path)
    assert (mechanism.source, mechanism.urdf_path, mechanism.closures_path) == ("mjcf", path, path)
    with pytest.raises(ModelFileError) as caught:
        mechanism.visual_model  # noqa: B018
    assert str(caught.value) == f"{path}: the visual geometry of an MJCF model is not loaded"


@pytest.mark.parametrize("model, robot", [('model="five_bar"', "five_bar"), ("", "machine")])
def test_an_mjcf_machines_urdf_records_its_closures_and_is_named_as_the_model(tmp_path, model, robot):
    """The written URDF's robot is the MJCF's `model`, or without one the URDF's own name."""
    path = five_bar_mjcf(tmp_path)
    path.write_text(path.read_text().replace('<mujoco model="five_bar">', f"<mujoco {model}>"))
    urdf_bytes, closures_bytes = _load(path).pair_bytes(tmp_path / "out" / "machine.urdf")
    assert recorded_closures_sha256(urdf_bytes) == closures_sha256(closures_bytes)
    assert re.findall(rb"<robot [^>]*>", urdf_bytes) == [f'<robot name="{robot}">'.encode()]


def test_the_cli_takes_an_mjcf_as_model(tmp_path, capsys):
    path = five_bar_mjcf(tmp_path)
    (tmp_path / "five_bar.closures.yaml").write_text("platform_frame: effector\ntask: {position: [x, y]}\n")
    (tmp_path / "motors.csv").write_text("motor_l,motor_r\n0.1,-0.2\n")
    command = ["fk", str(tmp_path / "motors.csv"), "-o", str(tmp_path / "poses.csv"), "--model", str(path)]
    assert main(command) == 0
    row = (tmp_path / "poses.csv").read_text().strip().splitlines()[-1].split(",")
    assert np.abs(np.array(row[:2], dtype=float) - _five_bar_tip(np.array([0.1, -0.2]))).max() < 1e-9
    path.write_text(path.read_text().replace('type="hinge" axis="0 0 1"/>\n        <geom', 'type="ball"/>\n<geom', 2))
    capsys.readouterr()
    assert main(command) == 2
    stderr = capsys.readouterr().err
    assert "Traceback" not in stderr
    assert re.search(r"five_bar.xml: line \d+: <joint name='elbow_l'>: a ball joint", stderr), stderr
