"""The closures file's fields (m3t1r.model.schema): every refusal word for word, with the file named,
and the defaults of what a file may leave out. On the packaged five-bar's files."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from m3t1r.errors import ModelFileError
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files
from m3t1r.model.task import TaskSpec


def _edited(folder: Path, change) -> tuple[Path, Path]:
    urdf, closures = five_bar_files(folder)
    document = yaml.safe_load(closures.read_text())
    change(document)
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    return urdf, closures


def _set(key, value):
    return lambda d: d.__setitem__(key, value)


def _closure(**fields):
    return lambda d: d["closures"][0].update(fields)


def _task(**fields):
    return lambda d: d["task"].update(fields)


REFUSALS = [
    (_set("schema_version", 3), "schema_version 3 is not supported (known: 1, 2)"),
    (_set("platform_frame", "nowhere"), "platform_frame: frame 'nowhere' does not exist in the URDF"),
    (_set("actuated_joints", []), "actuated_joints must be a non-empty list of joint names"),
    (_set("actuated_joints", "motor_1"), "actuated_joints must be a non-empty list of joint names"),
    (
        _set("actuated_joints", ["effector_fixed", "motor_2"]),
        "actuated_joints: 'effector_fixed' is a fixed joint, not prismatic or revolute",
    ),
    (_set("actuated_joints", ["motor_1", "nope"]), "actuated_joints: joint 'nope' does not exist in five_bar.urdf"),
    (_set("actuated_joints", ["motor_1", "motor_1"]), "actuated_joints: a joint is listed twice"),
    (_set("closures", []), "closures: at least one closure is required"),
    (_set("closures", ["loop"]), "closures[0]: expected a mapping"),
    (_set("closures", 5), "closures must be a list of closures, got 5"),
    (_set("closures", {"loop": None}), "closures must be a list of closures, got {'loop': None}"),
    (_closure(type="XD"), "closure 'loop': type must be 3D or 6D, got 'XD'"),
    (
        lambda d: d["closures"][0].pop("name") and _closure(type="2D")(d),
        "closure 'closures[0]': type must be 3D or 6D, got '2D'",
    ),
    (lambda d: d["closures"].append(dict(d["closures"][0])), "closure 'loop': duplicate closure name"),
    (_closure(frame_a="nowhere"), "closure 'loop': frame 'nowhere' does not exist in the URDF"),
    (_closure(frame_b="nowhere"), "closure 'loop': frame 'nowhere' does not exist in the URDF"),
    (_closure(rows=[0, 0]), "closure 'loop': rows must be distinct indices in 0..2, got [0, 0]"),
    (_closure(rows=[]), "closure 'loop': rows must be distinct indices in 0..2, got []"),
    (_closure(rows="01"), "closure 'loop': rows must be distinct indices in 0..2, got '01'"),
    (_closure(rows=[0, 3]), "closure 'loop': rows must be distinct indices in 0..2, got [0, 3]"),
    (_closure(type="6D", rows=[0, 6]), "closure 'loop': rows must be distinct indices in 0..5, got [0, 6]"),
    (_set("principal_chains", {"B": ["motor_1"]}), "principal_chains.B: expected joint names then a frame name"),
    (_set("principal_chains", {"B": "motor_1"}), "principal_chains.B: expected joint names then a frame name"),
    (
        _set("principal_chains", {"B": ["motor_1", "nope", "effector"]}),
        "principal_chains.B: joint 'nope' does not exist",
    ),
    (
        _set("principal_chains", {"B": ["nope", "motor_1", "effector"]}),
        "principal_chains.B: joint 'nope' does not exist",
    ),
    (
        _set("principal_chains", {"B": ["motor_1", "nowhere"]}),
        "principal_chains.B: frame 'nowhere' does not exist in the URDF",
    ),
    (
        _set("principal_chains", {"B": ["motor_1", "elbow_1", "nowhere"]}),
        "principal_chains.B: frame 'nowhere' does not exist in the URDF",
    ),
    (_set("home", [1.0]), "home must map joint names to values"),
    (lambda d: d["home"].update(nope=0.0), "home: joint 'nope' does not exist"),
    (lambda d: d["home"].update(motor_1="abc"), "home: joint 'motor_1' has non-numeric value 'abc'"),
    (lambda d: d["home"].update(motor_1=float("nan")), "home: joint 'motor_1' has non-finite value nan"),
    (_set("task", "xy"), "task must be a mapping with frame, position and rotation"),
    (_task(frame="nowhere"), "task.frame: frame 'nowhere' does not exist in the URDF"),
    (_task(position="xy"), "task.position must be a list of axes among x, y, z, got 'xy'"),
    (_task(rotation="roll"), "task rotation must be one of none, yaw, full, got 'roll'"),
    (lambda d: d.__setitem__("task", {}), "task: commands nothing (no position axis and rotation none)"),
    (_set("workspace", {}), "workspace must have exactly one of 'actuators' or 'task'"),
    (
        lambda d: d.__setitem__("workspace", {"actuators": d["workspace"]["actuators"], "task": {}}),
        "workspace must have exactly one of 'actuators' or 'task'",
    ),
    (
        lambda d: d["workspace"]["actuators"].pop("motor_2"),
        "workspace.actuators must give an interval [lo, hi] for each of motor_1, motor_2; got ['motor_1']",
    ),
    (
        lambda d: d["workspace"].update(actuators="box"),
        "workspace.actuators must give an interval [lo, hi] for each of motor_1, motor_2; got 'box'",
    ),
    (
        lambda d: d["workspace"]["actuators"].update(motor_1=[1, 2, 3]),
        "workspace.actuators.motor_1 must be [lo, hi] numbers, got [1, 2, 3]",
    ),
    (
        lambda d: d["workspace"]["actuators"].update(motor_1="12"),
        "workspace.actuators.motor_1 must be [lo, hi] numbers, got '12'",
    ),
    (
        lambda d: d["workspace"]["actuators"].update(motor_1=[True, 2]),
        "workspace.actuators.motor_1 must be [lo, hi] numbers, got [True, 2]",
    ),
    (
        lambda d: d["workspace"]["actuators"].update(motor_1=[2.0, 1.0]),
        "workspace: interval of 'motor_1' must be finite with lo <= hi, got [2.0, 1.0]",
    ),
    (
        _set("workspace", {"task": {"x": [-0.1, 0.1]}}),
        "workspace.task must give an interval [lo, hi] for each of x, y; got ['x']",
    ),
    (
        lambda d: _task(rotation="yaw")(d) or d.__setitem__("workspace", {"task": {"x": [0, 1], "y": [0, 1]}}),
        "workspace.task: the task commands 3 coordinates for 2 actuators; sample a task box only when they match "
        "(give an actuators box)",
    ),
]


@pytest.mark.parametrize("change, message", REFUSALS, ids=[m[:60] for _, m in REFUSALS])
def test_refusals_name_the_file_and_the_field(tmp_path, change, message):
    urdf, closures = _edited(tmp_path, change)
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == f"{closures}: {message}"


def test_what_a_file_may_leave_out(tmp_path):
    def minimal(document: dict) -> None:
        for key in ("schema_version", "task", "workspace"):
            document.pop(key)
        document["closures"][0].pop("rows")
        document["closures"][0]["type"] = "3D"

    urdf, closures = _edited(tmp_path, minimal)
    with pytest.warns(UserWarning):  # the z row holds by itself on a planar loop: dropped with a note
        mechanism = Mechanism.load(urdf, closures)
    # No task: the platform frame's coordinates the two motors command at home (a planar five-bar's x, y)
    assert mechanism.task == TaskSpec("effector", ("x", "y"), "none")
    assert any("no task declared" in note for note in mechanism.notes)
    assert mechanism.workspace is None
    assert mechanism.closures[0].rows == (0, 1)
    assert (mechanism.closures[0].frame_a, mechanism.closures[0].frame_b) == ("effector", "tip_2")


def test_task_defaults_and_the_chains_read(tmp_path):
    def change(document: dict) -> None:
        document["task"] = {"position": ["y", "x"]}  # frame: the platform frame; rotation: none
        document["principal_chains"] = {"B1": ["motor_1", "elbow_1", "effector"], "B2": ["motor_2", "tip_2"]}
        document["workspace"] = {"task": {"x": [-0.05, 0.05], "y": [0.35, 0.45]}}

    mechanism = Mechanism.load(*_edited(tmp_path, change))
    assert mechanism.task == TaskSpec("effector", ("x", "y"), "none")
    assert mechanism.principal_chains == {"B1": ("motor_1", "elbow_1", "effector"), "B2": ("motor_2", "tip_2")}
    assert mechanism.workspace.kind == "task"
    assert mechanism.workspace.bounds(("x", "y"))[1].tolist() == [0.05, 0.45]


def _written(folder: Path, data: bytes) -> tuple[Path, Path]:
    urdf, closures = five_bar_files(folder)
    closures.write_bytes(data)
    return urdf, closures


READ_REFUSALS = [
    (b"a: 1\nb: \xff\n", "line 2: not UTF-8 text (byte 0xff)"),
    (b"\xef\xbb\xbfa: [1, 2\n", "line 2, column 1: not valid YAML: expected ',' or ']', but got '<stream end>'"),
    (b"home: 2001-13-01\n", "cannot read closures YAML: ValueError: month must be in 1..12"),
    (b"- 1\n- 2\n", "closures file must be a YAML mapping"),
    (b"actuated_joints: [motor_1]\nclosures: []\nhome: {}\n", "missing field 'platform_frame'"),
    (b"closures: []\nplatform_frame: effector\nhome: {}\n", "missing field 'actuated_joints'"),
    (b"actuated_joints: [motor_1]\nplatform_frame: effector\nhome: {}\n", "missing field 'closures'"),
    (b"actuated_joints: [motor_1]\nclosures: []\nplatform_frame: effector\n", "missing field 'home'"),
]


@pytest.mark.parametrize("data, message", READ_REFUSALS, ids=[m[:40] for _, m in READ_REFUSALS])
def test_unreadable_closures_files_are_named(tmp_path, data, message):
    urdf, closures = _written(tmp_path, data)
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == f"{closures}: {message}"


def test_missing_files_are_named(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    missing = tmp_path / "none.closures.yaml"
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, missing)
    assert str(caught.value) == f"{missing}: file not found"
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, tmp_path)
    assert str(caught.value) == f"{tmp_path}: is a directory, expected a file"
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(tmp_path / "none.urdf", closures)
    assert str(caught.value) == f"{tmp_path / 'none.urdf'}: file not found"
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(tmp_path, closures)
    assert str(caught.value) == f"{tmp_path}: not a regular file"


def _line_of(text: str, start: str, after: int = 0) -> int:
    """1-based line of the first line starting with `start` after line `after`."""
    return next(k for k, line in enumerate(text.splitlines(), start=1) if k > after and line.startswith(start))


# (edit of the five-bar's closures text, start of the refused line, start of the first occurrence, message)
KEY_REFUSALS = [
    # A second `rows:` replaced the first; a `row:` typo fell back to every row; a second
    # `workspace:` replaced the first; an unknown field was ignored.
    (
        lambda t: t.replace("  rows: [0, 1]\n", "  rows: [0, 1]\n  rows: [0]\n", 1),
        "  rows: [0]",
        "  rows:",
        "key 'rows' given twice (first on line {first}); YAML would keep only the last",
    ),
    (
        lambda t: t.replace("  rows: [0, 1]\n", "  row: [0, 1]\n", 1),
        "  row:",
        None,
        "closure 'loop': unknown field 'row' (known: name, type, frame_a, frame_b, rows)",
    ),
    (
        lambda t: t + "workspace:\n  actuators: {motor_1: [2.0, 2.1], motor_2: [0.5, 0.6]}\n",
        "workspace:",
        "workspace:",
        "key 'workspace' given twice (first on line {first}); YAML would keep only the last",
    ),
    (
        lambda t: t + "platfrom_frame: effector\n",
        "platfrom_frame",
        None,
        "unknown field 'platfrom_frame' (known: schema_version, actuated_joints, closures, principal_chains, "
        "platform_frame, task, workspace, home, frames, locked_joints)",
    ),
    (
        lambda t: t.replace("task:\n", "task:\n  speed: 1\n", 1),
        "  speed",
        None,
        "task: unknown field 'speed' (known: frame, position, rotation)",
    ),
    (
        lambda t: t.replace("workspace:\n", "workspace:\n  box: {}\n", 1),
        "  box",
        None,
        "workspace: unknown field 'box' (known: actuators, task)",
    ),
]


@pytest.mark.parametrize("edit, refused, first, message", KEY_REFUSALS, ids=[m[:40] for *_, m in KEY_REFUSALS])
def test_duplicate_and_unknown_keys_are_refused_with_their_line(tmp_path, edit, refused, first, message):
    """Each of these edits used to load: as another mechanism (the closures' rows, the workspace) or
    ignoring a typo."""
    urdf, closures = five_bar_files(tmp_path)
    edited = edit(closures.read_text())
    assert edited != closures.read_text()
    closures.write_text(edited)
    first_line = _line_of(edited, first) if first else 0
    line = _line_of(edited, refused, after=first_line)
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    column = len(refused) - len(refused.lstrip()) + 1
    assert str(caught.value) == f"{closures}: line {line}, column {column}: " + message.format(first=first_line)


def test_a_closure_of_a_frame_with_itself_is_refused_by_name(tmp_path):
    """It made every row dependent and ended in an IndexError inside ClosedLoopSolver."""
    urdf, closures = _edited(
        tmp_path,
        _closure(frame_b=yaml.safe_load(five_bar_files(tmp_path / "x")[1].read_text())["closures"][0]["frame_a"]),
    )
    frame = yaml.safe_load(closures.read_text())["closures"][0]["frame_a"]
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == (
        f"{closures}: closure 'loop': frame_a '{frame}' and frame_b '{frame}' are the same "
        "frame: the closure constrains no joint"
    )
