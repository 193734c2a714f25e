"""Calibrated URDF writing: origins recovered through fixed-link chains, round trips, safety."""

from __future__ import annotations

import hashlib
import importlib.metadata
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yourdfpy
from lxml import etree

from m3t1r.errors import ModelFileError, OutputPathError
from m3t1r.io.pairing import recorded_closures_sha256
from m3t1r.model import urdf_io
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files
from m3t1r.model.kinematics import rehomed
from m3t1r.model.urdf_io import (
    IDENTITY_TOLERANCE,
    calibrated_urdf_bytes,
    write_calibrated_urdf,
)

UR5_IN_PACKAGE = "cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"


def max_placement_difference(model_a: pin.Model, model_b: pin.Model) -> float:
    """Largest max(distance [m], angle [rad]) between same-named joint and frame placements of two
    models of one structure (same joints on the same parents, same frames on the same joints)."""
    joints_a = {model_a.names[j]: j for j in range(1, model_a.njoints)}
    joints_b = {model_b.names[j]: j for j in range(1, model_b.njoints)}
    assert joints_a.keys() == joints_b.keys()
    assert all(
        model_a.names[model_a.parents[joints_a[n]]] == model_b.names[model_b.parents[j]] for n, j in joints_b.items()
    )
    frames_a = {(f.name, f.type): f for f in model_a.frames}
    frames_b = {(f.name, f.type): f for f in model_b.frames}
    assert len(frames_a) == len(model_a.frames) and frames_a.keys() == frames_b.keys()
    assert all(model_a.names[f.parentJoint] == model_b.names[frames_b[k].parentJoint] for k, f in frames_a.items())
    pairs = [(model_a.jointPlacements[joints_a[n]], model_b.jointPlacements[j]) for n, j in joints_b.items()]
    pairs += [(f.placement, frames_b[k].placement) for k, f in frames_a.items()]

    def difference(a: pin.SE3, b: pin.SE3) -> float:  # the angle from the chord: exactly 0 for equal rotations
        chord = np.linalg.norm(a.rotation - b.rotation) / (2.0 * np.sqrt(2.0))
        return max(float(np.linalg.norm(a.translation - b.translation)), 2.0 * float(np.arcsin(min(chord, 1.0))))

    return max(difference(a, b) for a, b in pairs)


# A chain with fixed links between moving joints (l1 -f1- l2 -f2- l3 -j2-), a fixed branch
# (l2 -f4- sensor), a joint without <origin> (j3) and one with only xyz (f3).
CHAIN_URDF = """<?xml version="1.0"?>
<!-- synthetic chain for the URDF writer tests -->
<robot name="chain">
  <link name="base"/>
  <joint name="j1" type="revolute">
    <parent link="base"/>
    <child link="l1"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.1 -0.2 0.3"/>
    <axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="1"/>
  </joint>
  <link name="l1"/>
  <joint name="f1" type="fixed">
    <parent link="l1"/>
    <child link="l2"/>
    <origin xyz="0.4 0 0.05" rpy="0 0.5 0"/>
  </joint>
  <link name="l2"/>
  <joint name="f2" type="fixed">
    <parent link="l2"/>
    <child link="l3"/>
    <origin rpy='0.7 0 -0.2' xyz='0 0.3 0' />
  </joint>
  <link name="l3"/>
  <joint name="j2" type="prismatic">
    <parent link="l3"/>
    <child link="l4"/>
    <origin xyz="0.05 -0.02 0.2" rpy="-0.3 0.4 1.2"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.1" upper="0.1" effort="10" velocity="1"/>
  </joint>
  <link name="l4"/>
  <joint name="j3" type="continuous">
    <parent link="l4"/>
    <child link="l5"/>
    <axis xyz="0 1 0"/>
  </joint>
  <link name="l5"/>
  <joint name="f3" type="fixed">
    <parent link="l5"/>
    <child link="tool"/>
    <origin xyz="0 0 0.1"/>
  </joint>
  <link name="tool"/>
  <joint name="f4" type="fixed">
    <parent link="l2"/>
    <child link="sensor"/>
    <origin xyz="-0.1 0 0.02" rpy="3.0 0 0"/>
  </joint>
  <link name="sensor"/>
</robot>
"""


@pytest.fixture(scope="module")
def ur5_urdf() -> Path:
    path = Path(importlib.metadata.distribution("example-robot-data").locate_file(UR5_IN_PACKAGE))
    assert path.is_file(), f"example-robot-data (a dependency) does not ship {UR5_IN_PACKAGE}"
    return path


@pytest.fixture()
def chain_urdf(tmp_path: Path) -> Path:
    path = tmp_path / "chain.urdf"
    path.write_text(CHAIN_URDF)
    return path


def small_motion(rng: np.random.Generator, translation: float = 1e-3, rotation: float = 1e-3) -> pin.SE3:
    """A placement `translation` m and `rotation` rad away from the identity, in random directions."""
    linear, angular = rng.normal(size=3), rng.normal(size=3)
    return pin.exp6(
        pin.Motion(linear / np.linalg.norm(linear) * translation, angular / np.linalg.norm(angular) * rotation)
    )


def set_link_frame(model: pin.Model, link: str, placement: pin.SE3) -> None:
    """Move a fixed-joint child link's BODY frame and the FIXED_JOINT frame Pinocchio made with it."""
    body = model.frames[model.getFrameId(link, pin.FrameType.BODY)]
    body.placement = placement
    fixed_joint = model.frames[body.parentFrame]
    assert fixed_joint.type == pin.FrameType.FIXED_JOINT
    fixed_joint.placement = placement


def fixed_children(model: pin.Model) -> list[str]:
    """Links hanging off a fixed joint (their BODY frame's parent frame is a FIXED_JOINT)."""
    return [
        frame.name
        for frame in model.frames
        if frame.type == pin.FrameType.BODY
        and frame.parentFrame != 0  # the root link hangs off the universe frame, not a fixed joint
        and model.frames[frame.parentFrame].type == pin.FrameType.FIXED_JOINT
    ]


def calibrate_randomly(model: pin.Model, rng: np.random.Generator) -> pin.Model:
    """A copy of `model` with every joint placement and fixed-joint link frame moved by 1 mm / 1 mrad."""
    calibrated = model.copy()
    for joint in range(1, calibrated.njoints):
        # jointPlacements[j] is a reference into the model: build a new SE3 instead of editing it.
        calibrated.jointPlacements[joint] = pin.SE3(calibrated.jointPlacements[joint]) * small_motion(rng)
    for link in fixed_children(calibrated):
        nominal = pin.SE3(calibrated.frames[calibrated.getFrameId(link, pin.FrameType.BODY)].placement)
        set_link_frame(calibrated, link, nominal * small_motion(rng))
    return calibrated


def random_velocity_configurations(model: pin.Model, rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Tangent vectors v (one value per 1-dof joint: rad or m); the configuration is neutral (+) v."""
    return [rng.uniform(-1.0, 1.0, model.nv) for _ in range(count)]


def frame_poses(model: pin.Model, v: np.ndarray) -> dict[tuple[str, pin.FrameType], pin.SE3]:
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.integrate(model, pin.neutral(model), v))
    return {(frame.name, frame.type): pin.SE3(data.oMf[i]) for i, frame in enumerate(model.frames)}


def assert_same_kinematics(expected: pin.Model, actual: pin.Model, rng: np.random.Generator, atol: float) -> None:
    """Every frame at the same world pose, by frame name and type, at random configurations."""
    assert expected.nv == actual.nv
    for v in random_velocity_configurations(expected, rng, 5):
        # Same joint order is not assumed: map the tangent vector joint by joint, by name.
        v_actual = np.zeros(actual.nv)
        for joint in range(1, expected.njoints):
            source = expected.joints[joint]
            target = actual.joints[actual.getJointId(expected.names[joint])]
            v_actual[target.idx_v : target.idx_v + target.nv] = v[source.idx_v : source.idx_v + source.nv]
        poses_expected, poses_actual = frame_poses(expected, v), frame_poses(actual, v_actual)
        assert poses_expected.keys() == poses_actual.keys()
        for key, pose in poses_expected.items():
            difference = pin.log6(pose.actInv(poses_actual[key])).vector
            assert np.abs(difference).max() < atol, f"frame {key[0]} ({key[1].name}) off by {difference}"


def origin_of(urdf: Path, joint: str) -> pin.SE3:
    """A joint's <origin> as written in the file (identity if absent)."""
    element = etree.parse(str(urdf)).getroot().find(f"joint[@name='{joint}']/origin")
    if element is None:
        return pin.SE3.Identity()
    xyz = np.array(element.get("xyz", "0 0 0").split(), dtype=float)
    rpy = np.array(element.get("rpy", "0 0 0").split(), dtype=float)
    return pin.SE3(pin.rpy.rpyToMatrix(rpy), xyz)


def placement_distance(a: pin.SE3, b: pin.SE3) -> float:
    """max(|translation|, rotation angle) of a^-1 b, in m and rad."""
    delta = a.actInv(b)
    return max(np.linalg.norm(delta.translation), np.linalg.norm(pin.log3(delta.rotation)))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --------------------------------------------------------------------------------------------
# UR5 from example-robot-data
# --------------------------------------------------------------------------------------------


def test_ur5_calibrated_round_trip(ur5_urdf: Path, tmp_path: Path) -> None:
    rng = np.random.default_rng(2024)
    nominal_hash = sha256(ur5_urdf)
    nominal = pin.buildModelFromUrdf(str(ur5_urdf))
    calibrated = calibrate_randomly(nominal, rng)
    assert max_placement_difference(nominal, calibrated) > 0.9e-3
    out = tmp_path / "ur5_calibrated.urdf"

    write_calibrated_urdf(ur5_urdf, calibrated, out)
    reloaded = pin.buildModelFromUrdf(str(out))

    assert sha256(ur5_urdf) == nominal_hash
    assert max_placement_difference(calibrated, reloaded) < 1e-12
    assert_same_kinematics(calibrated, reloaded, rng, atol=1e-9)
    yourdfpy.URDF.load(str(out), build_scene_graph=False, load_meshes=False)


def test_ur5_written_file_agrees_with_an_independent_parser(ur5_urdf: Path, tmp_path: Path) -> None:
    # yourdfpy has its own rpy and kinematic-tree code: link poses must match Pinocchio's BODY frames.
    rng = np.random.default_rng(5)
    calibrated = calibrate_randomly(pin.buildModelFromUrdf(str(ur5_urdf)), rng)
    out = tmp_path / "ur5_calibrated.urdf"
    write_calibrated_urdf(ur5_urdf, calibrated, out)

    robot = yourdfpy.URDF.load(str(out), build_scene_graph=True, load_meshes=False)
    v = rng.uniform(-np.pi, np.pi, calibrated.nv)
    robot.update_cfg(
        {name: v[calibrated.joints[calibrated.getJointId(name)].idx_v] for name in robot.actuated_joint_names}
    )
    poses = frame_poses(calibrated, v)
    base = poses[(robot.base_link, pin.FrameType.BODY)]
    for link in robot.link_map:
        expected = base.actInv(poses[(link, pin.FrameType.BODY)]).homogeneous
        np.testing.assert_allclose(robot.get_transform(link), expected, rtol=0.0, atol=1e-9, err_msg=link)


def test_ur5_unchanged_model_only_touches_joint_origins(ur5_urdf: Path, tmp_path: Path) -> None:
    out = tmp_path / "ur5_same.urdf"
    write_calibrated_urdf(ur5_urdf, pin.buildModelFromUrdf(str(ur5_urdf)), out)

    before, after = ur5_urdf.read_text().splitlines(), out.read_text().splitlines()
    joint_origin_lines = {origin.sourceline for origin in etree.parse(str(ur5_urdf)).getroot().iterfind("joint/origin")}
    changed = [number for number, (old, new) in enumerate(zip(before, after), start=1) if old != new]
    assert len(before) == len(after)
    # At least "0 0 -3.14159265359" comes back as an equivalent "0.0 0.0 3.1415926535895866".
    assert changed and set(changed) <= joint_origin_lines
    for number in changed:
        old, new = before[number - 1], after[number - 1]
        assert old[: old.index("<origin ")] == new[: new.index("<origin ")]  # indentation kept


def test_model_with_a_root_joint(ur5_urdf: Path, tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    floating = pin.buildModelFromUrdf(str(ur5_urdf), pin.JointModelFreeFlyer())
    calibrated = calibrate_randomly(floating, rng)
    # The root joint is not in the URDF; keep it at the identity so the comparison is meaningful.
    calibrated.jointPlacements[1] = pin.SE3.Identity()
    out = tmp_path / "ur5_floating.urdf"

    write_calibrated_urdf(ur5_urdf, calibrated, out)

    assert max_placement_difference(calibrated, pin.buildModelFromUrdf(str(out), pin.JointModelFreeFlyer())) < 1e-12


# --------------------------------------------------------------------------------------------
# Synthetic chain: origins through fixed links
# --------------------------------------------------------------------------------------------


def test_origin_after_fixed_links_is_relative_to_the_parent_link(chain_urdf: Path, tmp_path: Path) -> None:
    model = pin.buildModelFromUrdf(str(chain_urdf))
    out = tmp_path / "chain_out.urdf"

    write_calibrated_urdf(chain_urdf, model, out)

    # Pinocchio folds f1 and f2 into j2's placement; the file must get back j2's own origin.
    folded = origin_of(chain_urdf, "f1") * origin_of(chain_urdf, "f2") * origin_of(chain_urdf, "j2")
    assert placement_distance(model.jointPlacements[model.getJointId("j2")], folded) < 1e-15
    for joint in ["j1", "f1", "f2", "j2", "j3", "f3", "f4"]:
        assert placement_distance(origin_of(out, joint), origin_of(chain_urdf, joint)) < 1e-14, joint
    assert max_placement_difference(model, pin.buildModelFromUrdf(str(out))) < 1e-14


def test_chain_calibrated_round_trip(chain_urdf: Path, tmp_path: Path) -> None:
    rng = np.random.default_rng(99)
    calibrated = calibrate_randomly(pin.buildModelFromUrdf(str(chain_urdf)), rng)
    assert set(fixed_children(calibrated)) == {"l2", "l3", "tool", "sensor"}
    out = tmp_path / "chain_calibrated.urdf"

    write_calibrated_urdf(chain_urdf, calibrated, out)
    reloaded = pin.buildModelFromUrdf(str(out))

    assert max_placement_difference(calibrated, reloaded) < 1e-12
    assert_same_kinematics(calibrated, reloaded, rng, atol=1e-9)
    yourdfpy.URDF.load(str(out), build_scene_graph=False, load_meshes=False)


def test_moving_a_link_with_rigid_descendants_changes_only_its_own_origin(chain_urdf: Path, tmp_path: Path) -> None:
    # The convention of the calibration code: perturb l2's frame and carry everything on l2 along.
    model = pin.buildModelFromUrdf(str(chain_urdf))
    l2 = pin.SE3(model.frames[model.getFrameId("l2", pin.FrameType.BODY)].placement)
    moved = l2 * small_motion(np.random.default_rng(1), 2e-3, 2e-3)
    carry = moved * l2.inverse()
    for name, kind in [
        ("l2", pin.FrameType.BODY),
        ("f1", pin.FrameType.FIXED_JOINT),
        ("l3", pin.FrameType.BODY),
        ("f2", pin.FrameType.FIXED_JOINT),
        ("sensor", pin.FrameType.BODY),
        ("f4", pin.FrameType.FIXED_JOINT),
    ]:
        frame = model.frames[model.getFrameId(name, kind)]
        frame.placement = carry * pin.SE3(frame.placement)
    j2 = model.getJointId("j2")
    model.jointPlacements[j2] = carry * pin.SE3(model.jointPlacements[j2])
    out = tmp_path / "chain_rigid.urdf"

    write_calibrated_urdf(chain_urdf, model, out)

    assert placement_distance(origin_of(out, "f1"), origin_of(chain_urdf, "f1")) > 1e-3
    for joint in ["j1", "f2", "f4", "j2", "j3", "f3"]:
        assert placement_distance(origin_of(out, joint), origin_of(chain_urdf, joint)) < 1e-14, joint


def test_body_frame_wins_over_a_stale_fixed_joint_frame(chain_urdf: Path, tmp_path: Path) -> None:
    model = pin.buildModelFromUrdf(str(chain_urdf))
    shift = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.01]))
    stale = model.frames[model.getFrameId("f3", pin.FrameType.FIXED_JOINT)]
    stale.placement = pin.SE3(stale.placement) * shift  # ignored
    out = tmp_path / "chain_stale.urdf"
    write_calibrated_urdf(chain_urdf, model, out)
    assert placement_distance(origin_of(out, "f3"), origin_of(chain_urdf, "f3")) < 1e-15

    tool = model.frames[model.getFrameId("tool", pin.FrameType.BODY)]
    tool.placement = pin.SE3(tool.placement) * shift  # authoritative
    write_calibrated_urdf(chain_urdf, model, out)
    assert placement_distance(origin_of(out, "f3"), origin_of(chain_urdf, "f3") * shift) < 1e-15


def test_missing_origin_is_inserted_in_the_file_style(chain_urdf: Path, tmp_path: Path) -> None:
    model = pin.buildModelFromUrdf(str(chain_urdf))
    j3 = model.getJointId("j3")
    model.jointPlacements[j3] = pin.SE3(np.eye(3), np.array([0.0, 0.125, 0.0]))
    out = tmp_path / "chain_origin.urdf"

    write_calibrated_urdf(chain_urdf, model, out)

    text = out.read_text()
    assert (
        '<joint name="j3" type="continuous">\n    <origin xyz="0.0 0.125 0.0" rpy="0.0 0.0 0.0"/>\n'
        '    <parent link="l4"/>'
    ) in text
    assert re.search(r"<origin rpy='[-0-9. e]+' xyz='[-0-9. e]+' />", text)  # f2's quoting and spacing kept
    assert '<origin xyz="0.0 0.0 0.1" rpy="0.0 0.0 0.0"/>' in text  # f3 had no rpy
    assert text.startswith(
        '<?xml version="1.0"?>\n<!-- synthetic chain for the URDF writer tests -->\n<robot name="chain">'
    )
    assert max_placement_difference(model, pin.buildModelFromUrdf(str(out))) < 1e-15


def test_fallback_serialization_is_equivalent(
    chain_urdf: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # If the byte splice were wrong, the canonical-XML check must catch it and lxml write the tree.
    monkeypatch.setattr(urdf_io, "_splice_origins", lambda raw, attributes: raw)
    calibrated = calibrate_randomly(pin.buildModelFromUrdf(str(chain_urdf)), np.random.default_rng(4))
    out = tmp_path / "chain_fallback.urdf"

    write_calibrated_urdf(chain_urdf, calibrated, out)

    assert out.read_bytes().startswith(b"<?xml")
    assert max_placement_difference(calibrated, pin.buildModelFromUrdf(str(out))) < 1e-12


# --------------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------------


def test_never_writes_onto_the_nominal_or_a_protected_file(chain_urdf: Path, tmp_path: Path) -> None:
    model = calibrate_randomly(pin.buildModelFromUrdf(str(chain_urdf)), np.random.default_rng(0))
    measurements = tmp_path / "measurements.csv"
    measurements.write_text("x\n1\n")
    before = sha256(chain_urdf)

    with pytest.raises(OutputPathError, match="refusing to overwrite"):
        write_calibrated_urdf(chain_urdf, model, chain_urdf)
    with pytest.raises(OutputPathError, match="refusing to overwrite"):
        write_calibrated_urdf(chain_urdf, model, tmp_path / "." / "chain.urdf")
    with pytest.raises(OutputPathError, match="refusing to overwrite"):
        write_calibrated_urdf(chain_urdf, model, measurements, protect=[measurements])

    assert sha256(chain_urdf) == before
    assert measurements.read_text() == "x\n1\n"


@pytest.mark.parametrize(
    ("link", "kind"),
    [("l4", pin.FrameType.BODY), ("base", pin.FrameType.BODY), ("j2", pin.FrameType.JOINT)],
    ids=["moving-joint child", "root link", "joint frame"],
)
def test_link_frame_off_its_joint_is_refused(chain_urdf: Path, tmp_path: Path, link: str, kind: pin.FrameType) -> None:
    model = pin.buildModelFromUrdf(str(chain_urdf))
    frame = model.frames[model.getFrameId(link, kind)]
    frame.placement = pin.SE3(np.eye(3), np.array([1e-4, 0.0, 0.0]))
    out = tmp_path / "chain_bad.urdf"

    with pytest.raises(ModelFileError, match=f"'{link}'.*cannot be written"):
        write_calibrated_urdf(chain_urdf, model, out)
    assert not out.exists()


def test_model_of_another_urdf_is_refused(chain_urdf: Path, ur5_urdf: Path, tmp_path: Path) -> None:
    with pytest.raises(
        ModelFileError, match="the model has joints the URDF does not: shoulder_pan_joint, shoulder_lift_joint"
    ):
        write_calibrated_urdf(chain_urdf, pin.buildModelFromUrdf(str(ur5_urdf)), tmp_path / "x.urdf")

    other = tmp_path / "other.urdf"
    other.write_text(CHAIN_URDF.replace('"j2" type="prismatic"', '"j2" type="fixed"'))
    with pytest.raises(ModelFileError, match=r"joints the URDF does not: j2 \(fixed in the URDF\)"):
        write_calibrated_urdf(other, pin.buildModelFromUrdf(str(chain_urdf)), tmp_path / "x.urdf")

    broken = tmp_path / "broken.urdf"
    broken.write_text(CHAIN_URDF[:-20])
    with pytest.raises(ModelFileError, match="not well-formed XML"):
        write_calibrated_urdf(broken, pin.buildModelFromUrdf(str(chain_urdf)), tmp_path / "x.urdf")


def test_a_urdf_with_entity_references_is_written(tmp_path):
    """lxml cannot canonicalise unexpanded entities (C14NError): the writer serialises the tree instead."""
    urdf, closures = five_bar_files(tmp_path)
    urdf.write_text(
        urdf.read_text().replace(
            '<robot name="five_bar">',
            '<!DOCTYPE robot [<!ENTITY maker "m3t1r tests">]>\n<robot name="five_bar">\n'
            "  <description>&maker;</description>",
            1,
        )
    )
    mechanism = Mechanism.load(urdf, closures)
    model = pin.Model(mechanism.model)
    model.jointPlacements[2] = pin.SE3(model.jointPlacements[2].rotation, model.jointPlacements[2].translation + 1e-4)
    rehomed(mechanism.with_model(model)).save(tmp_path / "calibrated.urdf")  # a pair that closes
    written = (tmp_path / "calibrated.urdf").read_text()
    assert "<!ENTITY maker" in written and "&maker;" in written
    # Serialised by lxml (its declaration), not the byte splice the canonical check could not verify.
    assert written.startswith("<?xml version='1.0' encoding='UTF-8'?>")
    assert not urdf.read_text().startswith("<?xml version='1.0' encoding='UTF-8'?>")
    reloaded = Mechanism.load(tmp_path / "calibrated.urdf")
    assert max_placement_difference(reloaded.model, model) < 1e-12


# ==================================================================================================
# Refusals naming the nominal file, namesake links and joints, serialization
#
# Every refusal names the nominal file and says exactly what is wrong, link and joint names that coincide
# (a URDF keeps them apart), the identity tolerance at its value, the fallback serialization keeping
# comments, CDATA and the declared encoding.
# ==================================================================================================


def _file(tmp_path: Path, text: str, name: str = "nominal.urdf") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8") if isinstance(text, str) else text)
    return path


@pytest.fixture()
def chain(tmp_path: Path) -> tuple[Path, pin.Model]:
    path = _file(tmp_path, CHAIN_URDF, "chain.urdf")
    return path, pin.buildModelFromUrdf(str(path))


def _refusal(nominal: Path, model: pin.Model) -> str:
    with pytest.raises(ModelFileError) as caught:
        calibrated_urdf_bytes(nominal, model)
    assert caught.value.path == str(nominal)
    prefix = f"{nominal}: "
    assert str(caught.value).startswith(prefix)
    return str(caught.value)[len(prefix) :]


# -- the nominal file ----------------------------------------------------------------------------------


def test_unreadable_malformed_and_non_urdf_files(tmp_path, chain):
    _, model = chain
    folder = tmp_path / "folder.urdf"
    folder.mkdir()
    assert _refusal(folder, model) == "cannot read: Is a directory"
    assert _refusal(_file(tmp_path, "<robot>"), model).startswith("not well-formed XML: ")
    assert _refusal(_file(tmp_path, "<sdf/>"), model) == "root element is <sdf>, a URDF has <robot>"


@pytest.mark.parametrize(
    ("joint", "message"),
    [
        (
            '<joint name="a"><parent link="base"/><child link="x"/></joint>',
            "line 3: <joint name='a'> lacks a name or a type",
        ),
        (
            '<joint type="fixed"><parent link="base"/><child link="x"/></joint>',
            "line 3: <joint name=None> lacks a name or a type",
        ),
        (
            '<joint name="a" type="fixed"><child link="x"/></joint>',
            "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>",
        ),
        (
            '<joint name="a" type="fixed"><parent link="base"/></joint>',
            "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>",
        ),
        (
            '<joint name="a" type="fixed"><parent/><child link="x"/></joint>',
            "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>",
        ),
        (
            '<joint name="a" type="fixed"><parent link="base"/><child/></joint>',
            "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>",
        ),
        (
            '<joint name="a" type="fixed"><parent link="base"/><child link="x"/><origin/><origin/></joint>',
            "line 3: <joint name='a'> has more than one <origin>",
        ),
        (
            '<joint name="j1" type="fixed"><parent link="base"/><child link="x"/></joint>',
            "line 5: <joint name='j1'>: a joint of that name appears earlier",
        ),
    ],
)
def test_malformed_joints_are_named_by_line(tmp_path, chain, joint, message):
    _, model = chain
    text = CHAIN_URDF.replace('<link name="sensor"/>\n', '<link name="sensor"/>\n' + joint + "\n")
    text = text.replace('<robot name="chain">\n', '<robot name="chain">' + joint + "\n", 1)
    # The joint is now on line 3 (the first after <robot>) and again at the end.
    assert _refusal(_file(tmp_path, text), model) == message


# -- the model against the file ---------------------------------------------------------------------------


def test_another_models_joints(tmp_path, chain):
    nominal, model = chain
    other = _file(tmp_path, CHAIN_URDF.replace('"j3" type="continuous"', '"j3" type="fixed"'))
    assert _refusal(other, model) == "the model has joints the URDF does not: j3 (fixed in the URDF)"


def test_a_moving_joint_missing_from_the_model(tmp_path, chain):
    _, model = chain
    extra = (
        '<joint name="j4" type="revolute"><parent link="l5"/><child link="l6"/><axis xyz="0 0 1"/></joint>'
        '<link name="l6"/>'
    )
    nominal = _file(tmp_path, CHAIN_URDF.replace("</robot>", extra + "</robot>"))
    assert _refusal(nominal, model) == "revolute joint 'j4' is not in the model"


def test_a_joint_hanging_off_another_link(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace(
        '<parent link="l4"/>\n    <child link="l5"/>', '<parent link="l3"/>\n    <child link="l5"/>'
    )
    assert _refusal(_file(tmp_path, text), model) == (
        "joint 'j3' hangs off joint 'j2' in the model, but its URDF parent link 'l3' is on joint 'j1'"
    )


def test_a_joint_whose_child_another_joint_moves(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace(
        '<parent link="l4"/>\n    <child link="l5"/>', '<parent link="l4"/>\n    <child link="sensor"/>'
    )
    assert _refusal(_file(tmp_path, text), model) == "link 'sensor' is not moved by joint 'j3' in the model"


def test_a_fixed_joint_between_links_on_different_joints(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace(
        '<parent link="l5"/>\n    <child link="tool"/>', '<parent link="l4"/>\n    <child link="tool"/>'
    )
    assert _refusal(_file(tmp_path, text), model) == (
        "fixed joint 'f3': the model puts link 'l4' on joint 'j2' and link 'tool' on joint 'j3'"
    )


@pytest.mark.parametrize("link", ["base", "l3", "l4", "tool"])
def test_a_link_without_a_body_frame(chain, link):
    nominal, model = chain
    model.frames[model.getFrameId(link, pin.FrameType.BODY)].name = "renamed"
    assert _refusal(nominal, model) == f"link '{link}' has no BODY frame in the model: was it built from this file?"


def test_a_frame_of_another_type_does_not_stand_for_a_link(chain):
    nominal, model = chain
    model.frames[model.getFrameId("l3", pin.FrameType.BODY)].name = "renamed"
    model.frames[model.getFrameId("f2", pin.FrameType.FIXED_JOINT)].name = "l3"
    assert _refusal(nominal, model) == "link 'l3' has no BODY frame in the model: was it built from this file?"


@pytest.mark.parametrize(
    ("name", "kind", "what", "joint"),
    [
        ("base", pin.FrameType.BODY, "root link 'base'", "universe"),
        ("l4", pin.FrameType.BODY, "link 'l4'", "j2"),
        ("j2", pin.FrameType.JOINT, "JOINT frame 'j2'", "j2"),
    ],
)
def test_offset_link_frames_name_the_frame_and_the_joint(chain, name, kind, what, joint):
    nominal, model = chain
    model.frames[model.getFrameId(name, kind)].placement = pin.SE3(np.eye(3), np.array([0.0, 2e-4, 0.0]))
    assert _refusal(nominal, model) == (
        f"{what}: its frame is 0.0002 m or rad away from joint '{joint}'; "
        "a URDF link frame coincides with its joint frame, so this offset cannot be written"
    )


def test_identity_tolerance_is_inclusive(chain):
    nominal, model = chain
    frame = model.frames[model.getFrameId("l4", pin.FrameType.BODY)]
    frame.placement = pin.SE3(np.eye(3), np.array([IDENTITY_TOLERANCE, 0.0, 0.0]))
    calibrated_urdf_bytes(nominal, model)
    frame.placement = pin.SE3(np.eye(3), np.array([1.5 * IDENTITY_TOLERANCE, 0.0, 0.0]))
    assert "link 'l4': its frame is 1.5e-12 m or rad away" in _refusal(nominal, model)


# -- joints named like links ---------------------------------------------------------------------------------

# j1 renamed "l2": its JOINT frame comes before the BODY frame of link l2, on another placement.
# j2 renamed "l1": the BODY frame of link l1 comes before its JOINT frame, on another joint.
NAMESAKES = CHAIN_URDF.replace('<joint name="j1"', '<joint name="l2"').replace('<joint name="j2"', '<joint name="l1"')


def test_joints_named_like_links_round_trip(tmp_path):
    nominal = _file(tmp_path, NAMESAKES)
    calibrated = calibrate_randomly(pin.buildModelFromUrdf(str(nominal)), np.random.default_rng(3))
    out = _file(tmp_path, calibrated_urdf_bytes(nominal, calibrated), "out.urdf")
    assert max_placement_difference(calibrated, pin.buildModelFromUrdf(str(out))) < 1e-12


def test_a_joint_frame_named_like_an_earlier_link_is_checked(tmp_path):
    nominal = _file(tmp_path, NAMESAKES)
    model = pin.buildModelFromUrdf(str(nominal))
    model.frames[model.getFrameId("l1", pin.FrameType.JOINT)].placement = pin.SE3(np.eye(3), np.array([0, 0, 1e-3]))
    assert _refusal(nominal, model).startswith("JOINT frame 'l1': its frame is 0.001 m or rad away from joint 'l1'")


# -- output ---------------------------------------------------------------------------------------------------


def test_pairing_comment_is_written_when_asked(chain):
    nominal, model = chain
    digest = "0123456789abcdef" * 4
    assert recorded_closures_sha256(calibrated_urdf_bytes(nominal, model, closures_sha256=digest)) == digest
    assert recorded_closures_sha256(calibrated_urdf_bytes(nominal, model)) is None


def test_a_multiline_origin_attribute_is_spliced_in_place(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace(
        '<origin xyz="0.1 0.2 0.3" rpy="0.1 -0.2 0.3"/>',
        '<origin xyz="0.1\n      0.2 0.3" rpy="0.1 -0.2 0.3" note=" rpy=\'1\'"/>',
    )
    output = calibrated_urdf_bytes(_file(tmp_path, text), model)
    # The splice keeps the prolog and the comment as they were; lxml's fallback would not.
    assert output.startswith(b'<?xml version="1.0"?>\n<!-- synthetic chain for the URDF writer tests -->\n')
    assert re.search(rb"<origin xyz=\"0\.1 0\.2 0\.3\" rpy=\"[-0-9. e]+\" note=\" rpy='1'\"/>", output)


def test_fallback_serialization_keeps_comments_cdata_and_encoding(tmp_path, chain):
    """An entity reference sends the writer to lxml's serialisation (see above), which keeps the
    declared encoding, comments and CDATA."""
    _, model = chain
    text = CHAIN_URDF.replace(
        '<?xml version="1.0"?>',
        '<?xml version="1.0" encoding="ISO-8859-1"?>\n<!DOCTYPE robot [<!ENTITY maker "m3t1r tests">]>',
    )
    text = text.replace(
        '<link name="tool"/>',
        '<link name="tool"><!-- caf\u00e9 --><data><![CDATA[a<b]]></data><maker>&maker;</maker></link>',
    )
    nominal = _file(tmp_path, text.encode("latin-1"))
    output = calibrated_urdf_bytes(nominal, model)
    assert output.startswith(b"<?xml version='1.0' encoding='ISO-8859-1'?>\n")
    assert "<!-- caf\u00e9 --><data><![CDATA[a<b]]></data>".encode("latin-1") in output
    assert output.endswith(b"</robot>\n")


@pytest.mark.parametrize("link", ["l4", "l5"])
def test_a_parent_link_without_a_body_frame_in_a_file_listing_children_first(tmp_path, chain, link):
    from lxml import etree

    _, model = chain
    root = etree.fromstring(CHAIN_URDF.encode())
    joints = root.findall("joint")
    for joint in joints:
        root.remove(joint)
    root.extend(reversed(joints))  # f4, f3, j3, ...: l5 is first met as f3's parent, l4 as j3's
    nominal = _file(tmp_path, etree.tostring(root))
    model.frames[model.getFrameId(link, pin.FrameType.BODY)].name = "renamed"
    assert _refusal(nominal, model) == f"link '{link}' has no BODY frame in the model: was it built from this file?"
