"""model.urdf_io tests that kill mutants the behaviour tests let through (docs/mutation.md): every
refusal names the nominal file and says exactly what is wrong, link and joint names that coincide
(a URDF keeps them apart), the identity tolerance at its value, the fallback serialization keeping
comments, CDATA and the declared encoding, and `max_placement_difference`'s structure checks."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from test_urdf_io import CHAIN_URDF, calibrate_randomly

from m3t1r.errors import InvalidInputError, ModelFileError
from m3t1r.io.pairing import recorded_closures_sha256
from m3t1r.model import urdf_io
from m3t1r.model.urdf_io import IDENTITY_TOLERANCE, calibrated_urdf_bytes, max_placement_difference


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
    return str(caught.value)[len(prefix):]


# -- the nominal file ----------------------------------------------------------------------------------


def test_unreadable_malformed_and_non_urdf_files(tmp_path, chain):
    _, model = chain
    folder = tmp_path / "folder.urdf"
    folder.mkdir()
    assert _refusal(folder, model) == "cannot read: Is a directory"
    assert _refusal(_file(tmp_path, "<robot>"), model).startswith("not well-formed XML: ")
    assert _refusal(_file(tmp_path, "<sdf/>"), model) == "root element is <sdf>, a URDF has <robot>"


@pytest.mark.parametrize(("joint", "message"), [
    ('<joint name="a"><parent link="base"/><child link="x"/></joint>', "line 3: <joint name='a'> lacks a name or a type"),
    ('<joint type="fixed"><parent link="base"/><child link="x"/></joint>', "line 3: <joint name=None> lacks a name or a type"),
    ('<joint name="a" type="fixed"><child link="x"/></joint>',
     "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>"),
    ('<joint name="a" type="fixed"><parent link="base"/></joint>',
     "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>"),
    ('<joint name="a" type="fixed"><parent/><child link="x"/></joint>',
     "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>"),
    ('<joint name="a" type="fixed"><parent link="base"/><child/></joint>',
     "line 3: <joint name='a'> lacks <parent link=...> or <child link=...>"),
    ('<joint name="a" type="fixed"><parent link="base"/><child link="x"/><origin/><origin/></joint>',
     "line 3: <joint name='a'> has more than one <origin>"),
    ('<joint name="j1" type="fixed"><parent link="base"/><child link="x"/></joint>',
     "line 5: <joint name='j1'>: a joint of that name appears earlier"),
])
def test_malformed_joints_are_named_by_line(tmp_path, chain, joint, message):
    _, model = chain
    text = CHAIN_URDF.replace("<link name=\"sensor\"/>\n", "<link name=\"sensor\"/>\n" + joint + "\n")
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
    extra = ('<joint name="j4" type="revolute"><parent link="l5"/><child link="l6"/><axis xyz="0 0 1"/></joint>'
             '<link name="l6"/>')
    nominal = _file(tmp_path, CHAIN_URDF.replace("</robot>", extra + "</robot>"))
    assert _refusal(nominal, model) == "revolute joint 'j4' is not in the model"


def test_a_joint_hanging_off_another_link(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace('<parent link="l4"/>\n    <child link="l5"/>', '<parent link="l3"/>\n    <child link="l5"/>')
    assert _refusal(_file(tmp_path, text), model) == (
        "joint 'j3' hangs off joint 'j2' in the model, but its URDF parent link 'l3' is on joint 'j1'")


def test_a_joint_whose_child_another_joint_moves(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace('<parent link="l4"/>\n    <child link="l5"/>', '<parent link="l4"/>\n    <child link="sensor"/>')
    assert _refusal(_file(tmp_path, text), model) == "link 'sensor' is not moved by joint 'j3' in the model"


def test_a_fixed_joint_between_links_on_different_joints(tmp_path, chain):
    _, model = chain
    text = CHAIN_URDF.replace('<parent link="l5"/>\n    <child link="tool"/>', '<parent link="l4"/>\n    <child link="tool"/>')
    assert _refusal(_file(tmp_path, text), model) == (
        "fixed joint 'f3': the model puts link 'l4' on joint 'j2' and link 'tool' on joint 'j3'")


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


@pytest.mark.parametrize(("name", "kind", "what", "joint"), [
    ("base", pin.FrameType.BODY, "root link 'base'", "universe"),
    ("l4", pin.FrameType.BODY, "link 'l4'", "j2"),
    ("j2", pin.FrameType.JOINT, "JOINT frame 'j2'", "j2"),
])
def test_offset_link_frames_name_the_frame_and_the_joint(chain, name, kind, what, joint):
    nominal, model = chain
    model.frames[model.getFrameId(name, kind)].placement = pin.SE3(np.eye(3), np.array([0.0, 2e-4, 0.0]))
    assert _refusal(nominal, model) == (
        f"{what}: its frame is 0.0002 m or rad away from joint '{joint}'; "
        "a URDF link frame coincides with its joint frame, so this offset cannot be written")


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
    text = CHAIN_URDF.replace('<origin xyz="0.1 0.2 0.3" rpy="0.1 -0.2 0.3"/>',
                              "<origin xyz=\"0.1\n      0.2 0.3\" rpy=\"0.1 -0.2 0.3\" note=\" rpy='1'\"/>")
    output = calibrated_urdf_bytes(_file(tmp_path, text), model)
    # The splice keeps the prolog and the comment as they were; lxml's fallback would not.
    assert output.startswith(b'<?xml version="1.0"?>\n<!-- synthetic chain for the URDF writer tests -->\n')
    assert re.search(rb"<origin xyz=\"0\.1 0\.2 0\.3\" rpy=\"[-0-9. e]+\" note=\" rpy='1'\"/>", output)


def test_fallback_serialization_keeps_comments_cdata_and_encoding(tmp_path, chain, monkeypatch):
    _, model = chain
    text = CHAIN_URDF.replace('<?xml version="1.0"?>', '<?xml version="1.0" encoding="ISO-8859-1"?>')
    text = text.replace('<link name="tool"/>', '<link name="tool"><!-- caf\u00e9 --><data><![CDATA[a<b]]></data></link>')
    nominal = _file(tmp_path, text.encode("latin-1"))
    monkeypatch.setattr(urdf_io, "_splice_origins", lambda raw, attributes: None)
    output = calibrated_urdf_bytes(nominal, model)
    assert output.startswith(b"<?xml version='1.0' encoding='ISO-8859-1'?>\n")
    assert "<!-- caf\u00e9 --><data><![CDATA[a<b]]></data>".encode("latin-1") in output
    assert output.endswith(b"</robot>\n")


# -- max_placement_difference ------------------------------------------------------------------------------------


def test_the_first_joint_is_compared_too(chain):
    _, model = chain
    other = model.copy()
    other.jointPlacements[1] = pin.SE3(other.jointPlacements[1]) * pin.SE3(np.eye(3), np.array([0.0, 0.0, 7e-4]))
    assert max_placement_difference(model, other) == pytest.approx(7e-4, abs=1e-15)


def test_a_half_turn_is_pi_even_when_rounding_pushes_the_chord_past_1(chain):
    _, model = chain
    rng = np.random.default_rng(0)
    for _ in range(1000):  # half turns whose Frobenius chord rounds to just above its maximum
        axis = rng.normal(size=3)
        start = pin.exp3(rng.normal(size=3))
        end = start @ pin.exp3(axis / np.linalg.norm(axis) * np.pi)
        if np.linalg.norm(start - end) / (2.0 * np.sqrt(2.0)) > 1.0:
            break
    a, b = model.copy(), model.copy()
    for placed, rotation in ((a, start), (b, end)):
        placed.frames[placed.getFrameId("sensor", pin.FrameType.BODY)].placement = pin.SE3(rotation, np.zeros(3))
    assert max_placement_difference(a, b) == pytest.approx(np.pi, abs=1e-7)


def test_structure_differences_are_listed(chain):
    _, model = chain
    extra = model.copy()
    for name in ("mark_b", "mark_a"):
        extra.addFrame(pin.Frame(name, 1, 0, pin.SE3.Identity(), pin.FrameType.OP_FRAME))
    with pytest.raises(InvalidInputError, match=(
            r"^models differ in frames: only in the first: none; only in the second: mark_a \(OP_FRAME\), "
            r"mark_b \(OP_FRAME\)$")):
        max_placement_difference(model, extra)
    with pytest.raises(InvalidInputError, match=(
            r"^models differ in frames: only in the first: mark_a \(OP_FRAME\), mark_b \(OP_FRAME\); "
            r"only in the second: none$")):
        max_placement_difference(extra, model)


def test_parents_that_differ_are_listed(chain):
    _, model = chain
    moved = model.copy()
    for name in ("tool", "sensor"):
        moved.frames[moved.getFrameId(name, pin.FrameType.BODY)].parentJoint = 2
    with pytest.raises(InvalidInputError, match=(
            r"^frames on different parent joints in the two models: sensor \(BODY\), tool \(BODY\)$")):
        max_placement_difference(model, moved)
    rehung = model.copy()
    rehung.parents[3] = 1
    with pytest.raises(InvalidInputError, match=r"^joints on different parent joints in the two models: j3$"):
        max_placement_difference(model, rehung)


def test_two_frames_of_one_name_and_type_are_refused(chain):
    _, model = chain
    twice = model.copy()
    twice.frames[twice.getFrameId("tool", pin.FrameType.BODY)].name = "sensor"
    with pytest.raises(InvalidInputError, match=r"^model has two BODY frames named 'sensor'$"):
        max_placement_difference(twice, model)


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
