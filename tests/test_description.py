"""The model files: generated consistently, loadable by Pinocchio and yourdfpy, validated on load."""

import shutil

import numpy as np
import pinocchio as pin
import pytest
import yaml
import yourdfpy

from m3t1r.errors import ModelFileError, ModelWarning
from m3t1r.io.pairing import sha256_bytes, with_closures_sha256
from m3t1r.model.description import Mechanism, nominal_model_paths
from m3t1r.model.design import NOMINAL, build_closures, build_urdf
from m3t1r.model.examples import five_bar_files
from m3t1r.model.kinematics import ClosedLoopSolver


def test_committed_model_files_match_the_generator():
    urdf, closures = nominal_model_paths()
    assert urdf.read_text() == build_urdf(NOMINAL), "run `make models`"
    assert yaml.safe_load(closures.read_text()) == build_closures(NOMINAL), "run `make models`"


def test_committed_five_bar_matches_its_generator(tmp_path):
    packaged = nominal_model_paths()[0].parent
    for written in five_bar_files(tmp_path):
        assert (packaged / written.name).read_bytes() == written.read_bytes(), "run `make models`"


def test_urdf_loads_in_pinocchio_and_yourdfpy():
    urdf, _ = nominal_model_paths()
    model = pin.buildModelFromUrdf(str(urdf))
    visual = pin.buildGeomFromUrdf(model, str(urdf), pin.GeometryType.VISUAL)
    assert (model.nq, model.nv, model.njoints - 1) == (20, 20, 20)
    assert visual.ngeoms > 15
    robot = yourdfpy.URDF.load(str(urdf), build_scene_graph=True, load_meshes=False)
    assert len(robot.actuated_joint_names) == 20
    assert robot.base_link == "base"


def test_mechanism_summary(mechanism):
    assert mechanism.actuated_joints == ("q11", "q11_B2", "q21", "q21_B4")
    assert mechanism.n_constraints == 16 and len(mechanism.passive_ids) == 16
    assert [c.type for c in mechanism.closures].count("3D") == 6
    assert mechanism.principal_chains["B1"][-1] == mechanism.platform_frame == "P_I"


def _copy_model(tmp_path):
    urdf, closures = nominal_model_paths()
    shutil.copy(urdf, tmp_path / "m.urdf")
    shutil.copy(closures, tmp_path / "m.yaml")
    return tmp_path / "m.urdf", tmp_path / "m.yaml"


def _edit_closures(path, edit):
    doc = yaml.safe_load(path.read_text())
    edit(doc)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def test_missing_file_is_named(tmp_path):
    _, closures = nominal_model_paths()
    with pytest.raises(ModelFileError, match="nope.urdf: file not found"):
        Mechanism.load(tmp_path / "nope.urdf", closures)


def test_urdf_rejected_by_pinocchio(tmp_path):
    urdf, closures = _copy_model(tmp_path)
    urdf.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'>")
    with pytest.raises(ModelFileError, match="Pinocchio rejected the URDF"):
        Mechanism.load(urdf, closures)


def test_closure_naming_an_unknown_frame(tmp_path):
    urdf, closures = _copy_model(tmp_path)
    _edit_closures(closures, lambda d: d["closures"][2].update(frame_b="lower_pt_X"))
    with pytest.raises(ModelFileError, match=r"closure 'lower_parallelogram_I': frame 'lower_pt_X' does not exist"):
        Mechanism.load(urdf, closures)


def test_actuated_joint_must_be_a_slider_or_hinge(tmp_path):
    urdf, closures = _copy_model(tmp_path)
    _edit_closures(closures, lambda d: d["actuated_joints"].__setitem__(0, "P_I_fixed"))
    with pytest.raises(ModelFileError, match="'P_I_fixed' is a fixed joint, not prismatic or revolute"):
        Mechanism.load(urdf, closures)
    _edit_closures(closures, lambda d: d["actuated_joints"].__setitem__(0, "q99"))
    with pytest.raises(ModelFileError, match="joint 'q99' does not exist"):
        Mechanism.load(urdf, closures)


def test_home_that_does_not_close_is_assembled_at_the_nearest_assembly(tmp_path, mechanism):
    """q13 given 0.35 rad off: the assembly nearest the given values is the nominal home, and the note
    and `home_assembly` say which joint moved and by how much."""
    urdf, closures = _copy_model(tmp_path)
    _edit_closures(closures, lambda d: d["home"].update(q13=0.7))
    with pytest.warns(ModelWarning, match="home does not close: closure 'platform' residual 2.105e-01 > 1e-09; "
                                          "assembled by Newton .* moved by q13 -?\\+?0.347"):
        loaded = Mechanism.load(urdf, closures)
    assert np.abs(loaded.home - mechanism.home).max() < 1e-9
    report = loaded.home_assembly
    assert [name for name, _ in report.moved] == ["q13"] and report.residual < 1e-12
    assert report.moved[0][1] == pytest.approx(mechanism.home[loaded.model.idx_qs[loaded.model.getJointId("q13")]] - 0.7,
                                               abs=1e-9)
    assert Mechanism.load().home_assembly is None  # a home that closes is taken as given


def test_approximate_home_is_assembled_with_a_note(tmp_path, mechanism):
    urdf, closures = _copy_model(tmp_path)
    _edit_closures(closures, lambda d: d["home"].update(q13=d["home"]["q13"] + 1e-5, q22=d["home"]["q22"] - 0.03))
    with pytest.warns(ModelWarning, match="home does not close: closure .* assembled by Newton"):
        loaded = Mechanism.load(urdf, closures)
    assert len(loaded.notes) == 1
    assert np.abs(ClosedLoopSolver(loaded).closure_residual(loaded.home)).max() < 1e-12
    assert np.abs(loaded.home - mechanism.home).max() < 1e-9  # the sliders fix the assembly: the nominal home


def test_bad_rows(tmp_path):
    urdf, closures = _copy_model(tmp_path)
    _edit_closures(closures, lambda d: d["closures"][0].update(rows=[1, 3]))
    with pytest.raises(ModelFileError, match="rows must be distinct indices in 0..2"):
        Mechanism.load(urdf, closures)


def test_configuration_by_name(mechanism):
    q = mechanism.configuration({"q11": 0.1})
    assert q[mechanism.model.idx_qs[mechanism.model.getJointId("q11")]] == 0.1
    assert np.count_nonzero(q != mechanism.home) == 1


def _saved_five_bar_pair(folder):
    """A five-bar pair written by `save` (its URDF records its closures file), and the closures bytes."""
    Mechanism.load(*five_bar_files(folder / "source")).save(folder / "pair.urdf")
    closures = folder / "pair.closures.yaml"
    return folder / "pair.urdf", closures, closures.read_bytes()


@pytest.mark.parametrize("edit", [
    lambda data: b"# checked out on Windows, commented by hand\n" + data.replace(b"\n", b"\r\n"),
    lambda data: data.replace(b"\n", b"  # a trailing comment\n", 3),
    lambda data: yaml.safe_dump(yaml.safe_load(data), default_flow_style=True).encode(),  # re-laid out
])
def test_the_pair_survives_comments_line_ends_and_layout(tmp_path, edit):
    """Only a change of meaning breaks a pair: these edits were refused as 'not the closures file'."""
    urdf, closures, data = _saved_five_bar_pair(tmp_path)
    expected = Mechanism.load(urdf)
    closures.write_bytes(edit(data))
    loaded = Mechanism.load(urdf)
    assert loaded.closures == expected.closures and np.array_equal(loaded.home, expected.home)


def test_a_pair_recorded_with_the_raw_bytes_sha256_still_loads(tmp_path):
    """URDFs written before the digest covered the content record the bytes' sha256."""
    urdf, closures, data = _saved_five_bar_pair(tmp_path)
    urdf.write_bytes(with_closures_sha256(urdf.read_bytes(), sha256_bytes(data)))
    assert Mechanism.load(urdf).closures_path == closures
    closures.write_bytes(data + b"# edited\n")  # the old digest pins the bytes: a comment breaks it
    with pytest.raises(ModelFileError, match="not the closures file of"):
        Mechanism.load(urdf)


def test_a_mimic_joint_is_refused_by_name(tmp_path):
    """Pinocchio reads a <mimic> joint as an independent one: the closures would solve it on its own
    and a calibration would move it apart while the written URDF kept the tag."""
    urdf, closures = five_bar_files(tmp_path)
    text = urdf.read_text()
    start = text.index('<joint name="elbow_1"')
    end = text.index("</joint>", start)
    urdf.write_text(text[:end] + '<mimic joint="motor_1" multiplier="1" offset="0"/>' + text[end:])
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == (f"{urdf}: joint 'elbow_1' mimics joint 'motor_1' (<mimic>): m3t1r moves and "
                                 "calibrates every joint on its own, so a coupled joint is not supported; remove the "
                                 "tag (an independent joint) or make the joint fixed")
