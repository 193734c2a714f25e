"""The model files: generated consistently, loadable by Pinocchio and yourdfpy, validated on load."""

import importlib.resources
import os
import re
import shutil
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml
import yourdfpy
from model_files import edit_text, edit_yaml, strip_position_limits, welded_double_hinge

from m3t1r.errors import ModelFileError, ModelWarning, OutputPathError
from m3t1r.io.pairing import closures_sha256, recorded_closures_sha256, sha256_bytes, with_closures_sha256
from m3t1r.model import description
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.description import (
    HOME_TOLERANCE,
    Mechanism,
    nominal_model_paths,
    paired_closures,
)
from m3t1r.model.design import NOMINAL, build_closures, build_urdf
from m3t1r.model.examples import five_bar_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.task import TaskSpec


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
    with pytest.warns(
        ModelWarning,
        match="home does not close: closure 'platform' residual 2.105e-01 > 1e-09; "
        "assembled by Newton .* moved by q13 -?\\+?0.347",
    ):
        loaded = Mechanism.load(urdf, closures)
    assert np.abs(loaded.home - mechanism.home).max() < 1e-9
    report = loaded.home_assembly
    assert [name for name, _ in report.moved] == ["q13"] and report.residual < 1e-12
    assert report.moved[0][1] == pytest.approx(
        mechanism.home[loaded.model.idx_qs[loaded.model.getJointId("q13")]] - 0.7, abs=1e-9
    )
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


@pytest.mark.parametrize(
    "edit",
    [
        lambda data: b"# checked out on Windows, commented by hand\n" + data.replace(b"\n", b"\r\n"),
        lambda data: data.replace(b"\n", b"  # a trailing comment\n", 3),
        lambda data: yaml.safe_dump(yaml.safe_load(data), default_flow_style=True).encode(),  # re-laid out
    ],
)
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


@pytest.mark.parametrize("joint, leader", [("elbow_1", "motor_1"), ("motor_1", "motor_2")])  # motor_1: the first joint
def test_a_mimic_joint_is_refused_by_name(tmp_path, joint, leader):
    """Pinocchio reads a <mimic> joint as an independent one: the closures would solve it on its own
    and a calibration would move it apart while the written URDF kept the tag."""
    urdf, closures = five_bar_files(tmp_path)
    text = urdf.read_text()
    start = text.index(f'<joint name="{joint}"')
    end = text.index("</joint>", start)
    urdf.write_text(text[:end] + f'<mimic joint="{leader}" multiplier="1" offset="0"/>' + text[end:])
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == (
        f"{urdf}: joint '{joint}' mimics joint '{leader}' (<mimic>): m3t1r moves and "
        "calibrates every joint on its own, so a coupled joint is not supported; remove the "
        "tag (an independent joint) or make the joint fixed"
    )


# ==================================================================================================
# Home closure checks and every refusal of the files, word for word
#
# The home-closure check must look at every enforced row (a bad home that breaks only the last one is
# caught), at no unenforced row, and at HOME_TOLERANCE exactly. Then the files: every refusal of reading,
# pairing, assembling and checking word for word with the file named, the nominal files' lookup, and the
# bytes `pair_bytes` and `save` write.
# ==================================================================================================


def _with_closure_frame_moved(mechanism: Mechanism, closure: str, row: int, amount: float) -> Mechanism:
    """frame_b of `closure` moved so that only component `row` of its residual changes, by `amount`
    (3D: R_a^T (p_b - p_a); 6D: log6(aMb), rows 3-5 a rotation about frame_a's axes)."""
    spec = next(c for c in mechanism.closures if c.name == closure)
    model = mechanism.model.copy()
    data = model.createData()
    pin.framesForwardKinematics(model, data, mechanism.home)
    oMa, oMb = data.oMf[spec.frame_a_id], data.oMf[spec.frame_b_id]
    frame = model.frames[spec.frame_b_id]
    axis = np.zeros(3)
    axis[row % 3] = amount
    if row < 3:  # translate b along frame_a's axis `row`, in b's parent-joint coordinates
        parent = data.oMi[frame.parentJoint]
        shift = parent.rotation.T @ (oMa.rotation @ axis)
        frame.placement = pin.SE3(frame.placement.rotation, frame.placement.translation + shift)
    else:  # rotate b about frame_a's axis, i.e. about R_b^T R_a axis in b's own frame
        frame.placement = frame.placement * pin.SE3(pin.exp3(oMb.rotation.T @ oMa.rotation @ axis), np.zeros(3))
    model.frames[spec.frame_b_id] = frame
    return replace(mechanism, model=model)


def _reloaded(mechanism: Mechanism, folder: Path) -> Mechanism:
    """The machine as `Mechanism.load` settles it: saved as a pair in `folder`, loaded back (its notes,
    also warned, are in `notes`)."""
    urdf = folder / f"machine_{len(list(folder.glob('machine_*.urdf')))}.urdf"
    mechanism.save(urdf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        return Mechanism.load(urdf)


def _closures_of_reloaded(folder: Path) -> Path:
    """The closures file the next `_reloaded` in `folder` writes."""
    return folder / f"machine_{len(list(folder.glob('machine_*.urdf')))}.closures.yaml"


@pytest.mark.parametrize(
    "closure, rows", [("upper_parallelogram_I", (1, 2)), ("lower_parallelogram_II", (0, 2)), ("platform", (0, 1, 2, 5))]
)
def test_home_check_sees_every_enforced_row_alone(mechanism, closure, rows, tmp_path):
    spec = next(c for c in mechanism.closures if c.name == closure)
    assert spec.rows == rows
    for row in rows:
        broken = _with_closure_frame_moved(mechanism, closure, row, 1e-6)
        notes = _reloaded(broken, tmp_path).notes
        assert len(notes) == 1 and notes[0].startswith(f"home does not close: closure '{closure}' residual 1.000e-06")
        assert "assembled by Newton" in notes[0]


@pytest.mark.parametrize(
    "closure, row", [("upper_parallelogram_I", 0), ("lower_parallelogram_II", 1), ("platform", 3), ("platform", 4)]
)
def test_home_check_ignores_unenforced_rows(mechanism, closure, row, tmp_path):
    assert _reloaded(_with_closure_frame_moved(mechanism, closure, row, 1e-3), tmp_path).notes == ()


@pytest.mark.parametrize("amount, refused", [(1e-8, True), (2e-9, True), (5e-10, False)])
def test_home_tolerance_boundary(mechanism, amount, refused, tmp_path):
    assert HOME_TOLERANCE == 1e-9  # the documented value; the amounts straddle it
    moved = _with_closure_frame_moved(mechanism, "five_bar_I", 2, amount)
    notes = _reloaded(moved, tmp_path).notes
    assert (len(notes) == 1 and notes[0].startswith("home does not close")) == refused


# ----------------------------------------------------------------------------------------------
# Files, pairing and saving: every refusal word for word with the file named, on the five-bar.


def _five_bar(folder: Path) -> tuple[Path, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    return five_bar_files(folder)


def _refusal(call) -> str:
    with pytest.raises(ModelFileError) as caught:
        call()
    return str(caught.value)


def _saved_pair(folder: Path) -> tuple[Path, Path, bytes]:
    """A five-bar pair written by `save`: its URDF records the closures file's sha256."""
    mechanism = Mechanism.load(*_five_bar(folder / "source"))
    urdf = folder / "pair.urdf"
    mechanism.save(urdf)
    closures = folder / "pair.closures.yaml"
    return urdf, closures, closures.read_bytes()


def test_a_yaml_error_without_a_position_gives_the_reader_message(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    closures.write_bytes(b"a: \x07\n")
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == (
        f"{closures}: not valid YAML: unacceptable character #x0007: special characters are not allowed\n"
        '  in "<unicode string>", position 3'
    )


def test_an_unreadable_closures_path_is_named(tmp_path):
    urdf, _ = _five_bar(tmp_path)
    below_a_file = urdf / "five_bar.closures.yaml"
    assert _refusal(lambda: Mechanism.load(urdf, below_a_file)) == f"{below_a_file}: cannot read: Not a directory"


def test_an_unreadable_urdf_is_named_once(tmp_path):
    """paired_closures reads the URDF for its recorded sha256: its read errors name it once, even
    when the path holds ": " (it used to be split there, repeating part of the path)."""
    below_a_file = _five_bar(tmp_path)[0] / "m.urdf"
    assert _refusal(lambda: paired_closures(below_a_file)) == f"{below_a_file}: cannot read: Not a directory"
    odd = tmp_path / "run: 2"
    odd.mkdir()
    assert _refusal(lambda: paired_closures(odd / "m.urdf")) == f"{odd / 'm.urdf'}: file not found"


def test_a_urdf_recording_two_digests_is_named(tmp_path):
    urdf, closures = _five_bar(tmp_path / "run: 1")
    comment = "<!-- m3t1r pair: closures sha256 {} -->\n"
    urdf.write_text(urdf.read_text().replace("<robot", comment.format("a" * 64) + comment.format("b" * 64) + "<robot"))
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == f"{urdf}: records two different closures sha256 digests"


def test_a_paired_urdf_without_its_closures_file(tmp_path):
    urdf, closures, data = _saved_pair(tmp_path)
    closures.unlink()
    digest = closures_sha256(data)
    expected = (
        f"{closures}: file not found: pair.urdf records closures sha256 {digest[:16]}..., "
        "and no closures file with it is there"
    )
    assert _refusal(lambda: Mechanism.load(urdf)) == expected
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == expected


def test_a_paired_urdf_with_another_closures_file(tmp_path):
    urdf, closures, data = _saved_pair(tmp_path)
    other = tmp_path / "other.closures.yaml"
    document = yaml.safe_load(data)
    document["closures"][0]["rows"] = [0]  # a change of meaning
    other.write_text(yaml.safe_dump(document))
    expected = (
        f"{other}: not the closures file of {urdf}: the URDF records closures sha256 "
        f"{closures_sha256(data)[:16]}..., this file's content has {closures_sha256(other.read_bytes())[:16]}... "
        "The two files were not written together (one was rewritten by another run, or copied from another "
        "machine, or its content edited: comments, layout and line ends do not count); load the URDF with the "
        "closures file written with it; to pair these two deliberately, delete the line "
        "`<!-- m3t1r pair: ... -->` from the URDF (it then loads with any closures file; saving records a "
        "new pair)"
    )

    assert _refusal(lambda: Mechanism.load(urdf, other)) == expected
    closures.write_bytes(other.read_bytes())
    assert _refusal(lambda: paired_closures(urdf)) == expected.replace(str(other), str(closures), 1)


def test_paired_closures_reads_the_recorded_sha256_itself(tmp_path):
    urdf, closures, data = _saved_pair(tmp_path)
    assert paired_closures(urdf) == (closures, data)
    assert paired_closures(urdf, recorded=None) == (closures, data)


def test_a_staged_closures_file_of_an_interrupted_write_is_found(tmp_path):
    """The newest readable temporary with the recorded sha256 wins; an unreadable one is skipped."""
    urdf, closures, data = _saved_pair(tmp_path)
    closures.unlink()
    staged = tmp_path / ".pair.closures.yaml.m3t1r-11-aa.tmp"
    staged.write_bytes(data)
    unreadable = tmp_path / ".pair.closures.yaml.m3t1r-12-bb.tmp"
    unreadable.mkdir()
    os.utime(staged, (1_000_000, 1_000_000))
    os.utime(unreadable, (2_000_000, 2_000_000))
    assert paired_closures(urdf) == (closures, data)
    loaded = Mechanism.load(urdf)
    assert loaded.closures_path == closures and loaded.closures_document == yaml.safe_load(data)


def test_a_plain_urdf_alone_gets_the_nominal_closures(tmp_path):
    urdf = tmp_path / "alone.urdf"
    urdf.write_bytes(nominal_model_paths()[0].read_bytes())
    assert Mechanism.load(urdf).closures_path == nominal_model_paths()[1]


def test_the_nominal_urdf_with_given_closures(tmp_path):
    closures = tmp_path / "copy.yaml"
    closures.write_bytes(nominal_model_paths()[1].read_bytes())
    loaded = Mechanism.load(None, closures)
    assert (loaded.urdf_path, loaded.closures_path) == (nominal_model_paths()[0], closures)
    assert Mechanism.load().closures_path == nominal_model_paths()[1]


def test_a_cell_no_field_check_foresaw_is_refused_naming_the_file(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    edit_yaml(closures, lambda d: d["home"].update(motor_1=10**400))
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == (
        f"{closures}: malformed closures file: OverflowError: int too large to convert to float"
    )


def test_load_notes_are_warnings_attributed_to_the_caller(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    edit_yaml(closures, lambda d: d["closures"][0].update(rows=[0, 1, 2]))
    with pytest.warns(ModelWarning) as caught:
        Mechanism.load(urdf, closures)
    assert [str(w.message) for w in caught] == [
        "five_bar.closures.yaml: 1 closure row(s) dropped as dependent on the others: loop[2]"
    ]
    assert Path(caught[0].filename).name != Path(description.__file__).name


@pytest.mark.skipif(
    "/mutants/" in description.__file__, reason="mutmut's trampoline adds a frame between the caller and the warning"
)
def test_load_notes_point_at_the_caller_exactly(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    edit_yaml(closures, lambda d: d["closures"][0].update(rows=[0, 1, 2]))
    with pytest.warns(ModelWarning) as caught:
        Mechanism.load(urdf, closures)
    assert caught[0].filename == __file__


def test_a_continuous_first_joint_is_an_unbounded_revolute_one(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    urdf.write_text(
        urdf.read_text().replace('<joint name="motor_1" type="revolute">', '<joint name="motor_1" type="continuous">')
    )
    with pytest.warns(ModelWarning, match="actuator 'motor_1' has no usable URDF limits; the workspace box's"):
        mechanism = Mechanism.load(urdf, closures)
    assert (mechanism.model.nq, mechanism.model.nv) == (4, 4)
    assert mechanism.joint_units() == ("rad", "rad")


@pytest.mark.parametrize(
    "joint, kind, nq", [("elbow_2", "floating", 7), ("motor_1", "floating", 7), ("elbow_1", "planar", 4)]
)  # motor_1: the tree's first joint
def test_a_multi_dof_joint_is_refused(tmp_path, joint, kind, nq):
    urdf, closures = _five_bar(tmp_path)
    urdf.write_text(
        urdf.read_text().replace(f'<joint name="{joint}" type="revolute">', f'<joint name="{joint}" type="{kind}">')
    )
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == (
        f"{urdf}: joint '{joint}' is not a 1-DoF revolute/prismatic/continuous joint (nq={nq}); multi-DoF joints "
        "are not supported"
    )


def test_a_urdf_pinocchio_rejects_is_named(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    urdf.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'>")
    assert _refusal(lambda: Mechanism.load(urdf, closures)).startswith(f"{urdf}: Pinocchio rejected the URDF: ")


_TRIANGLE_STL = (
    "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 0.01 0 0\nvertex 0 0.01 0\n"
    "endloop\nendfacet\nendsolid t\n"
)


def test_visual_meshes_resolve_next_to_the_urdf(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    (tmp_path / "fb_meshes").mkdir()
    mesh = tmp_path / "fb_meshes" / "tri.stl"
    mesh.write_text(_TRIANGLE_STL)
    urdf.write_text(
        urdf.read_text().replace(
            '<geometry><sphere radius="0.01"/></geometry>',
            '<geometry><mesh filename="package://fb_meshes/tri.stl"/></geometry>',
        )
    )
    mechanism = Mechanism.load(urdf, closures)
    assert [g.meshPath for g in mechanism.visual_model.geometryObjects].count(str(mesh)) == 1
    mesh.unlink()
    assert _refusal(lambda: Mechanism.load(urdf, closures).visual_model) == (
        f"{urdf}: cannot load the visual geometry: Mesh package://fb_meshes/tri.stl could not be found."
    )


def test_nominal_model_paths_prefers_the_installed_package(tmp_path, monkeypatch):
    installed = tmp_path / "site" / "m3t1r"
    (installed / "models").mkdir(parents=True)
    checkout = tmp_path / "checkout"
    (checkout / "models").mkdir(parents=True)
    names = ("m3t1r.urdf", "m3t1r.closures.yaml")
    for name in names:
        (checkout / "models" / name).write_text("checkout")
    monkeypatch.setattr(importlib.resources, "files", lambda package: installed if package == "m3t1r" else None)
    monkeypatch.setattr(description, "__file__", str(checkout / "src" / "m3t1r" / "model" / "description.py"))
    assert nominal_model_paths() == tuple(checkout / "models" / name for name in names)
    (installed / "models" / names[0]).write_text("installed")  # a URDF alone is not a model
    assert nominal_model_paths() == tuple(checkout / "models" / name for name in names)
    (installed / "models" / names[1]).write_text("installed")
    assert nominal_model_paths() == tuple(installed / "models" / name for name in names)
    for name in names:
        (installed / "models" / name).unlink()
        (checkout / "models" / name).unlink()
    assert _refusal(nominal_model_paths) == f"{checkout / 'models'}: the packaged nominal model files are missing"


def test_an_actuator_without_limits_and_no_workspace_is_unbounded(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    urdf.write_text(
        re.sub(
            r'(<joint name="motor_2" type="revolute">(?:(?!</joint>).)*?)<limit[^>]*/>',
            r'\1<limit effort="10" velocity="10"/>',
            urdf.read_text(),
            flags=re.S,
        )
    )
    edit_yaml(closures, lambda d: d.pop("workspace"))
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    assert [str(w.message) for w in caught] == [
        "five_bar.closures.yaml: actuator 'motor_2' has no usable URDF limits; no limits [-inf, inf] used instead"
    ]
    lower, upper = mechanism.joint_limits()
    assert lower.tolist() == [1.83, -np.inf] and upper.tolist() == [2.83, np.inf]


def test_joint_limits_and_configuration_by_name(mechanism):
    model = mechanism.model
    k = model.idx_qs[model.getJointId("q12")]
    lower, upper = mechanism.joint_limits(("q12",))
    assert (lower.tolist(), upper.tolist()) == ([model.lowerPositionLimit[k]], [model.upperPositionLimit[k]])
    assert mechanism.joint_limits(())[0].shape == (0,)
    with pytest.raises(KeyError) as caught:
        mechanism.configuration({"nope": 0.0})
    assert caught.value.args == (f"no joint named 'nope' in {mechanism.urdf_path}",)


def test_a_mechanism_made_directly_commands_its_platform_frame(mechanism):
    made = Mechanism(
        mechanism.model,
        mechanism.closures,
        mechanism.actuated_joints,
        mechanism.principal_chains,
        mechanism.platform_frame,
        mechanism.home,
        mechanism.urdf_path,
        mechanism.closures_path,
    )
    assert made.task == TaskSpec("P_I")


def test_with_home_and_with_model_copy_the_home(mechanism):
    moved = mechanism.with_home([0] * mechanism.model.nq)
    assert moved.home.dtype == np.float64 and moved.home.tolist() == [0.0] * mechanism.model.nq
    other = mechanism.with_model(mechanism.model.copy())
    assert other.home is not mechanism.home and np.array_equal(other.home, mechanism.home)
    other.home[0] += 1.0
    assert other.home[0] != mechanism.home[0]


def test_pair_bytes(tmp_path):
    source_urdf, source_closures = _five_bar(tmp_path)
    mechanism = Mechanism.load(source_urdf, source_closures).with_home(
        Mechanism.load(source_urdf, source_closures).home + 0.25
    )
    urdf_bytes, closures_bytes = mechanism.pair_bytes(tmp_path / "out" / "machine.urdf")
    header, body = closures_bytes.decode("utf-8").split("\n", 1)
    assert header == (
        "# Closures of machine.urdf (written with it as a pair; its URDF records this file's sha256); "
        "home re-assembled for its geometry; rows and locked joints as load derived them. "
        "Schema: models/README.md"
    )
    document, source = yaml.safe_load(body), yaml.safe_load(source_closures.read_text())
    assert list(document) == list(source)  # the source's order, not sorted
    assert list(document["home"].items()) == [
        (name, float(mechanism.configuration({})[k]))
        for k, name in enumerate(("motor_1", "elbow_1", "motor_2", "elbow_2"))
    ]
    assert {k: v for k, v in document.items() if k != "home"} == {k: v for k, v in source.items() if k != "home"}
    assert recorded_closures_sha256(urdf_bytes) == closures_sha256(closures_bytes)
    assert mechanism.pair_bytes("machine.urdf", "elsewhere.yaml") == (urdf_bytes, closures_bytes)


def test_pair_bytes_use_the_document_read_at_load(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    mechanism = Mechanism.load(urdf, closures)
    expected = mechanism.pair_bytes("m.urdf")
    assert replace(mechanism, closures_document=None).pair_bytes("m.urdf") == expected  # read again: same file
    closures.write_text("schema_version: [\n")  # rewritten after the load
    assert mechanism.pair_bytes("m.urdf") == expected
    assert _refusal(lambda: replace(mechanism, closures_document=None).pair_bytes("m.urdf")) == (
        f"{closures}: line 2, column 1: not valid YAML: expected the node content, but found '<stream end>'"
    )


def test_save_writes_the_pair_where_asked(tmp_path):
    mechanism = Mechanism.load(*_five_bar(tmp_path / "source"))
    urdf, closures = tmp_path / "out.urdf", tmp_path / "out.yaml"
    mechanism.save(urdf, closures)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.urdf", "out.yaml", "source"]
    assert (urdf.read_bytes(), closures.read_bytes()) == mechanism.pair_bytes(urdf, closures)
    assert Mechanism.load(urdf, closures).closures_path == closures


def test_save_refuses_to_overwrite_its_sources(tmp_path):
    mechanism = Mechanism.load(*_five_bar(tmp_path))
    with pytest.raises(OutputPathError) as caught:
        mechanism.save(mechanism.urdf_path)
    assert (
        str(caught.value) == f"{mechanism.urdf_path}: URDF: refusing to overwrite the input file {mechanism.urdf_path}"
    )
    with pytest.raises(OutputPathError) as caught:
        mechanism.save(tmp_path / "new.urdf", mechanism.closures_path)
    assert str(caught.value) == (
        f"{mechanism.closures_path}: closures file of URDF: refusing to overwrite the input "
        f"file {mechanism.closures_path}"
    )


# Home assembly and the closure checks, refused naming the closures file.


def test_a_home_newton_cannot_close_is_refused(mechanism, tmp_path):
    broken = _with_closure_frame_moved(mechanism, "five_bar_I", 2, 5.0)
    closures = _closures_of_reloaded(tmp_path)
    message = _refusal(lambda: _reloaded(broken, tmp_path))
    # Newton diverges here: the residual it stops at depends on rounding (4.4 or 4.6 on different
    # BLAS kernels), so only that it is a number that did not close is checked, not its digits.
    prefix = (
        f"{closures}: home does not close: closure 'five_bar_I' residual 5.000e+00 > 1e-09, "
        "and Newton from the given values reached only "
    )
    found = re.fullmatch(
        re.escape(prefix) + r"(\S+); with every joint free it closes only with joint '(\w+)' at (\S+), beyond its "
        r"URDF limits \[(\S+), (\S+)\]: the closures may not all hold on this model \(check each closure's type, "
        r"3D or 6D, its rows and frames, .*\), or the given values are far from any assembly",
        message,
    )
    assert found is not None, message
    assert float(found.group(1)) > 1e-9  # 5 m off: only a slider beyond its 0.6 m would close the loop
    assert not float(found.group(4)) <= float(found.group(3)) <= float(found.group(5))
    lower, upper = mechanism.joint_limits((found.group(2),))  # the joint's own interval, lower bound first
    assert (found.group(4), found.group(5)) == (f"{lower[0]:.4g}", f"{upper[0]:.4g}") and lower[0] < upper[0]


def test_a_home_whose_actuator_values_cannot_close_says_which_would(tmp_path):
    """The M machine with slider q11_B2 0.5 m from q11, farther than side I's five-bar link can span:
    with the actuators held no assembly exists, and the refusal gives actuator values, within the
    sliders' limits, that close every loop; a little inside them (towards the nominal home), the
    file loads."""
    source_urdf, source_closures = nominal_model_paths()
    urdf, closures = tmp_path / "m.urdf", tmp_path / "m.closures.yaml"
    urdf.write_bytes(source_urdf.read_bytes())
    closures.write_bytes(source_closures.read_bytes())
    home = yaml.safe_load(closures.read_text())["home"]
    edit_yaml(closures, lambda d: d["home"].update(q11_B2=home["q11"] + 0.5))
    message = _refusal(lambda: Mechanism.load(urdf, closures))
    found = re.fullmatch(
        re.escape(f"{closures}: home does not close: closure 'five_bar_I' residual 5.000e-01 > 1e-09, and Newton ")
        + r"from the given values reached only \S+; with the actuators free too, it closes with them at \{(.*)\}: "
        + re.escape(
            "give actuator home values near those, a little inside the actuators' reach (the nearest values "
            "that close are often at its edge, where the loops are singular)"
        ),
        message,
    )
    assert found is not None, message
    given = dict(entry.split(": ") for entry in found.group(1).split(", "))
    assert list(given) == ["q11", "q11_B2", "q21", "q21_B4"]
    lower, upper = Mechanism.load().joint_limits()
    assert np.all((lower < [float(v) for v in given.values()]) & ([float(v) for v in given.values()] < upper))
    inside = {name: 0.95 * float(value) + 0.05 * home[name] for name, value in given.items()}
    edit_yaml(closures, lambda d: d["home"].update(inside))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        loaded = Mechanism.load(urdf, closures)
    assert loaded.home_assembly is not None and loaded.home_assembly.residual <= 1e-9


def test_a_home_slider_beyond_its_limits_is_refused_assembled_or_not(tmp_path):
    """The five-bar with motor_1 at home beyond its URDF limit, whether home then needs assembling
    (motor_1 moved past the limit: the passive joints follow) or closes as given (the limit moved
    inside home): every solve would refuse that slider value, so load refuses it, naming both."""
    urdf, closures = five_bar_files(tmp_path)
    (lower,), (upper,) = Mechanism.load(urdf, closures).joint_limits(("motor_1",))
    edit_yaml(closures, lambda d: d["home"].update(motor_1=float(upper) + 0.17))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        message = _refusal(lambda: Mechanism.load(urdf, closures))
    assert message == (
        f"{closures}: home puts joint 'motor_1' at {upper + 0.17:.6g}, beyond its URDF limits "
        f"[{lower:.6g}, {upper:.6g}]: give a home inside them, or limits that hold it"
    )
    urdf, closures = five_bar_files(tmp_path / "closing")
    home = yaml.safe_load(closures.read_text())["home"]["motor_1"]

    def narrowed(text: str) -> str:
        start = text.index('<joint name="motor_1"')
        end = text.index("</joint>", start)
        joint = re.sub(r'upper="[^"]*"', f'upper="{home - 0.01!r}"', text[start:end])
        return text[:start] + joint + text[end:]

    edit_text(urdf, narrowed)
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == (
        f"{closures}: home puts joint 'motor_1' at {home:.6g}, beyond its URDF limits "
        f"[{lower:.6g}, {home - 0.01:.6g}]: give a home inside them, or limits that hold it"
    )


def test_a_home_far_from_an_assembly_is_assembled(mechanism, tmp_path):
    """Half a metre off: no refusal for being far; the loops close with the actuators held."""
    broken = _with_closure_frame_moved(mechanism, "five_bar_I", 2, 0.5)
    settled = _reloaded(broken, tmp_path)
    assert np.abs(ClosureSystem(settled.model, settled.closures).evaluate(settled.home, False)[0]).max() < 1e-12
    np.testing.assert_array_equal(settled.home[settled.actuated_ids], broken.home[broken.actuated_ids])
    assert max(abs(move) for _, move in settled.home_assembly.moved) > 0.1


def test_the_assembly_note_gives_every_move_largest_first(mechanism, tmp_path):
    broken = _with_closure_frame_moved(mechanism, "five_bar_I", 2, 0.05)
    settled = _reloaded(broken, tmp_path)
    change = settled.home - broken.home
    report = settled.home_assembly
    sizes = [abs(move) for _, move in report.moved]
    assert sizes[0] == pytest.approx(np.abs(change).max(), abs=1e-15)
    assert sizes == sorted(sizes, reverse=True) and len(sizes) == np.count_nonzero(np.abs(change) > 1e-9)
    name, move = report.moved[0]
    assert move == pytest.approx(change[settled.model.idx_qs[settled.model.getJointId(name)]], abs=1e-15)
    assert settled.notes == (report.note(1e-9),)
    assert settled.notes[0].startswith(
        f"home does not close: closure 'five_bar_I' residual 5.000e-02 > 1e-09; "
        f"assembled by Newton (damped, actuators held) at the assembly nearest the "
        f"given values: passive joints moved by {name} {move:+.3g}, "
    )


def test_a_nan_residual_names_its_closure(mechanism):
    """A NaN placement cannot come from the files (Pinocchio and the closures schema refuse it), so
    the load step is called on the model directly: a NaN residual is refused, not taken as closed."""
    from m3t1r.model.description import _settled

    spec = next(c for c in mechanism.closures if c.name == "platform")
    model = mechanism.model.copy()
    frame = model.frames[spec.frame_b_id]
    frame.placement = pin.SE3(frame.placement.rotation, np.array([np.nan, 0.0, 0.0]))
    model.frames[spec.frame_b_id] = frame
    assert _refusal(lambda: _settled(replace(mechanism, model=model))).startswith(
        f"{mechanism.closures_path}: home does not close: closure 'platform' residual nan > 1e-09, and Newton"
    )


def test_missing_rows_are_refused_naming_the_file(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    edit_yaml(closures, lambda d: d["closures"][0].update(rows=[0]))
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == (
        f"{closures}: the closures leave 1 degree(s) of freedom beyond the actuators: with the actuators held, "
        "frame 'effector' can still move along 1 of them (1 per unit joint speed; mostly joints elbow_1, elbow_2); "
        "rows or closures are missing"
    )


_THIRD_CUT_JOINT = """<joint name="cut_3" type="revolute"><parent link="cut_link_1"/><child link="cut_link_3"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-4" upper="4" effort="1" velocity="1"/></joint>
  <link name="cut_link_3"/>
</robot>"""


def test_the_locked_gauge_note_names_every_locked_joint(tmp_path):
    """The five-bar's distal hinge modelled three times (two in series on chain 1): two gauges."""
    urdf, closures = welded_double_hinge(tmp_path)
    urdf.write_text(urdf.read_text().replace("</robot>", _THIRD_CUT_JOINT))
    edit_yaml(closures, lambda d: d["home"].update(cut_3=0.0) or d["closures"][0].update(frame_a="cut_link_3"))
    with pytest.warns(ModelWarning):
        mechanism = Mechanism.load(urdf, closures)
    locked = mechanism.locked_joints
    assert len(locked) == 2 and set(locked) < {"cut_1", "cut_2", "cut_3"}
    assert (
        f"passive joint(s) {locked[0]}, {locked[1]} locked at their home value: their motion is already spanned "
        "by the other passive joints (a gauge, e.g. a cut joint modelled twice)" in mechanism.notes
    )


def test_a_home_assembled_beyond_a_passive_joints_limits_is_refused(tmp_path):
    """elbow_1 given inside [-1.62, 1] but closing only at -1.651 (and -1.651 + 2 pi is beyond too)."""
    urdf, closures = _five_bar(tmp_path)
    edit_text(
        urdf,
        lambda text: text.replace(
            '<limit lower="-3.141592653589793" upper="3.141592653589793"', '<limit lower="-1.62" upper="1.0"', 1
        ),
    )
    edit_yaml(closures, lambda d: d["home"].update(elbow_1=-1.6))
    assert _refusal(lambda: Mechanism.load(urdf, closures)) == (
        f"{closures}: home does not close: closure 'loop' residual 1.780e-02 > 1e-09; the assembly nearest the "
        "given values puts joint 'elbow_1' at -1.65087, beyond its URDF limits [-1.62, 1] (give home values of the "
        "passive joints near the assembly mode wanted)"
    )


# ----------------------------------------------------------------------------------------------
# What load says about joints: units, passive joints without limits, idle joints, missing rows.


def test_joint_units_are_metres_for_sliders_and_radians_for_hinges(mechanism):
    assert mechanism.joint_units() == ("m", "m", "m", "m")  # the M machine's four sliders
    assert mechanism.joint_units(("q12", "q21", "q13_bar")) == ("rad", "m", "rad")
    assert mechanism.joint_units(()) == ()


_IDLE_FIRST_JOINT = """<joint name="idle" type="revolute"><parent link="base"/><child link="idle_link"/>
    <axis xyz="0 0 1"/><limit effort="1" velocity="1"/></joint>
  <link name="idle_link"/>
</robot>"""


def test_a_passive_first_joint_without_limits_is_named_unbounded_and_locked(tmp_path):
    """A spin of a link on the base, listed first in the tree (joints of a link are ordered by name):
    velocity index 0, no range, moving nothing the closures see."""
    urdf, closures = _five_bar(tmp_path)
    edit_text(urdf, lambda text: text.replace("</robot>", _IDLE_FIRST_JOINT))
    edit_yaml(closures, lambda d: d["home"].update(idle=0.0))
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    assert mechanism.model.names[1] == "idle" and mechanism.locked_joints == ("idle",)
    assert [str(w.message) for w in caught] == [
        "five_bar.closures.yaml: 1 passive joint(s) without usable URDF limits (idle): taken as unbounded "
        "(an empty <limit/> or a continuous joint gives no range)",
        "five_bar.closures.yaml: passive joint(s) idle locked at their home value: their motion is already "
        "spanned by the other passive joints (a gauge, e.g. a cut joint modelled twice)",
    ]
    lower, upper = mechanism.joint_limits(("idle", "elbow_1"))
    assert (lower.tolist(), upper.tolist()) == ([-np.inf, -np.pi], [np.inf, np.pi])


_PASSIVE_IN_TREE_ORDER = ("q12", "q12_pa", "q13", "q13_pa", "q14", "q13_bar", "q12_bar")


@pytest.mark.parametrize(
    "count, shown",
    [(6, "q12, q12_pa, q13, q13_pa, q14, q13_bar"), (7, "q12, q12_pa, q13, q13_pa, q14, q13_bar and 1 more")],
)
def test_passive_joints_without_limits_are_listed_six_at_most(tmp_path, count, shown):
    urdf, closures = _copy_model(tmp_path)
    for name in _PASSIVE_IN_TREE_ORDER[:count]:
        strip_position_limits(urdf, re.escape(name))
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    assert [str(w.message) for w in caught] == [
        f"m.yaml: {count} passive joint(s) without usable URDF limits ({shown}): taken as unbounded "
        "(an empty <limit/> or a continuous joint gives no range)"
    ]
    lower, upper = mechanism.joint_limits(_PASSIVE_IN_TREE_ORDER)
    assert np.isinf(lower).tolist() == [True] * count + [False] * (7 - count)
    assert np.isinf(upper).tolist() == [True] * count + [False] * (7 - count)


def test_missing_rows_of_a_spatial_closure_are_counted_on_the_motion_they_leave(tmp_path):
    """The M machine's platform closure without its yaw row: one motion left, which turns P_I. Over
    every passive joint (the closures ignored) P_I could move along several directions, not 1."""
    urdf, closures = _copy_model(tmp_path)
    _edit_closures(closures, lambda d: d["closures"][6].update(rows=[0, 1, 2]))
    message = _refusal(lambda: Mechanism.load(urdf, closures))
    found = re.fullmatch(
        re.escape(
            f"{closures}: the closures leave 1 degree(s) of freedom beyond the actuators: with the actuators held, "
            "frame 'P_I' can still move along 1 of them ("
        )
        + r"(\S+) per unit joint speed; mostly joints (\w+), (\w+), (\w+)\); rows or closures are missing",
        message,
    )
    assert found is not None, message
    assert float(found.group(1)) > 0.1
    assert set(found.groups()[1:]) < set(_joint_names_of(Mechanism.load(), Mechanism.load().passive_ids))


def _joint_names_of(mechanism: Mechanism, velocity_indices) -> set[str]:
    model = mechanism.model
    return {model.names[j] for j in range(1, model.njoints) if model.idx_vs[j] in set(velocity_indices)}


# ----------------------------------------------------------------------------------------------
# What `pair_bytes` records of what load derived, and the note of a derived task.


def test_a_declared_task_is_written_as_the_file_gives_it(tmp_path):
    """A task without `frame:` (the platform frame's) is the source's entry in the written file: only a
    derived task is written out in full."""
    urdf, closures = _five_bar(tmp_path)
    edit_yaml(closures, lambda d: d["task"].pop("frame"))
    mechanism = Mechanism.load(urdf, closures)
    document = yaml.safe_load(mechanism.pair_bytes(tmp_path / "out.urdf")[1].decode().split("\n", 1)[1])
    assert document["task"] == {"position": ["x", "y"], "rotation": "none"}
    assert mechanism.task == TaskSpec("effector", ("x", "y"), "none")


def test_a_mechanism_with_other_closures_than_its_document_writes_the_documents(tmp_path):
    """`pair_bytes` writes load's rows into the document's closures only when they are the mechanism's
    one for one; a mechanism given other closures leaves the document's entries as read."""
    urdf, closures = welded_double_hinge(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        mechanism = Mechanism.load(urdf, closures)
    source = yaml.safe_load(closures.read_text())["closures"]
    written = yaml.safe_load(mechanism.pair_bytes(tmp_path / "out.urdf")[1].decode().split("\n", 1)[1])
    assert [entry["rows"] for entry in written["closures"]] == [list(spec.rows) for spec in mechanism.closures]
    other = replace(mechanism, closures=mechanism.closures + mechanism.closures)
    written = yaml.safe_load(other.pair_bytes(tmp_path / "out.urdf")[1].decode().split("\n", 1)[1])
    assert written["closures"] == source


def test_a_derived_task_is_noted_word_for_word(tmp_path):
    urdf, closures = _five_bar(tmp_path)
    edit_yaml(closures, lambda d: d.pop("task"))
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    assert [str(w.message) for w in caught] == [
        "five_bar.closures.yaml: no task declared: inverse kinematics, plans and reports take the x, y of frame "
        "'effector' (the coordinates the actuators command at home); declare `task:` to choose others "
        "(models/README.md)"
    ]
    assert mechanism.task == TaskSpec("effector", ("x", "y"), "none")
