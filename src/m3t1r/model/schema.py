"""The closures file's fields, read and checked against the URDF's tree (schema: models/README.md).

Version 1 has actuated_joints, closures, platform_frame, principal_chains and home; version 2 adds
`task` (what inverse kinematics commands) and `workspace` (where simulations sample). Either may
declare `frames` (points the URDF does not name, added to the model as operational frames) and
`locked_joints` (passive joints held at home, as `Mechanism.save` records them). Every error is a
ModelFileError naming the file and the field, joint or frame at fault.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
import yaml

from m3t1r.errors import InvalidInputError, ModelFileError
from m3t1r.model.closures import ROW_COUNT, ClosureSpec
from m3t1r.model.task import TaskSpec, WorkspaceSpec

__all__ = [
    "Description",
    "read_description",
    "add_declared_frames",
    "declared_frame_entries",
    "load_closures_yaml",
    "SCHEMA_VERSIONS",
    "FIELDS",
    "CLOSURE_FIELDS",
]

SCHEMA_VERSIONS = (1, 2)
#: The fields of a closures file, of one closure entry, of `task` and of `workspace`: any other key
#: is refused (a typo such as `row:` would otherwise fall back to a default silently).
FIELDS = (
    "schema_version",
    "actuated_joints",
    "closures",
    "principal_chains",
    "platform_frame",
    "task",
    "workspace",
    "home",
    "frames",
    "locked_joints",
)
CLOSURE_FIELDS = ("name", "type", "frame_a", "frame_b", "rows")
_NESTED_FIELDS = {"task": ("frame", "position", "rotation"), "workspace": ("actuators", "task")}
_MERGE_TAG = "tag:yaml.org,2002:merge"


def load_closures_yaml(text: str, path: Path) -> object:
    """The YAML document of a closures file, with every mapping's keys checked first: a key given
    twice (a second `rows:` or `workspace:` would silently replace the first) and a field the
    schema does not know are ModelFileErrors naming the key and its line. yaml.YAMLError as
    PyYAML raises it for text that is not YAML."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _refuse_duplicate_keys(node, path, set())
        _refuse_unknown_fields(node, path)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _where(node: yaml.Node) -> str:
    return f"line {node.start_mark.line + 1}, column {node.start_mark.column + 1}"


def _refuse_duplicate_keys(node: yaml.Node, path: Path, seen: set[int]) -> None:
    if id(node) in seen:  # an alias: checked where its anchor is (and a recursive one ends here)
        return
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        first: dict[tuple[str, str], yaml.Node] = {}
        for key, value in node.value:
            if isinstance(key, yaml.ScalarNode) and key.tag != _MERGE_TAG:
                earlier = first.setdefault((key.tag, key.value), key)
                if earlier is not key:
                    raise ModelFileError(
                        path,
                        f"{_where(key)}: key '{key.value}' given twice (first on line "
                        f"{earlier.start_mark.line + 1}); YAML would keep only the last",
                    )
            _refuse_duplicate_keys(key, path, seen)
            _refuse_duplicate_keys(value, path, seen)
    elif isinstance(node, yaml.SequenceNode):
        for item in node.value:
            _refuse_duplicate_keys(item, path, seen)


def _refuse_unknown_fields(root: yaml.Node, path: Path) -> None:
    if not isinstance(root, yaml.MappingNode):
        return  # `read_description` refuses a document that is not a mapping
    _known_keys(root, FIELDS, "", path)
    for key, value in root.value:
        if not isinstance(key, yaml.ScalarNode):
            continue
        if key.value in _NESTED_FIELDS and isinstance(value, yaml.MappingNode):
            _known_keys(value, _NESTED_FIELDS[key.value], f"{key.value}: ", path)
        if key.value == "closures" and isinstance(value, yaml.SequenceNode):
            for k, entry in enumerate(value.value):
                if isinstance(entry, yaml.MappingNode):
                    names = [v.value for n, v in entry.value if isinstance(v, yaml.ScalarNode) and n.value == "name"]
                    _known_keys(entry, CLOSURE_FIELDS, f"closure '{names[0]}': " if names else f"closures[{k}]: ", path)


def _known_keys(node: yaml.MappingNode, known: tuple[str, ...], where: str, path: Path) -> None:
    for key, _ in node.value:
        if key.tag == _MERGE_TAG:
            continue
        if not isinstance(key, yaml.ScalarNode) or key.value not in known:
            name = key.value if isinstance(key, yaml.ScalarNode) else "a non-scalar key"
            raise ModelFileError(path, f"{_where(key)}: {where}unknown field '{name}' (known: {', '.join(known)})")


@dataclass(frozen=True)
class Description:
    """The checked fields of a closures file (home as given, not yet assembled)."""

    closures: tuple[ClosureSpec, ...]
    actuated_joints: tuple[str, ...]
    principal_chains: dict[str, tuple[str, ...]]
    platform_frame: str
    home: np.ndarray
    task: TaskSpec
    workspace: WorkspaceSpec | None
    locked_joints: tuple[str, ...] = ()


def read_description(model: pin.Model, doc: dict, urdf_path: Path, path: Path) -> Description:
    """Check a parsed closures document against `model` (built from `urdf_path`), after adding to
    `model` the frames the document declares (`frames`: `add_declared_frames`)."""
    version = doc.get("schema_version", 1)
    if version not in SCHEMA_VERSIONS:
        raise ModelFileError(path, f"schema_version {version!r} is not supported (known: 1, 2)")
    add_declared_frames(model, doc.get("frames"), path)
    actuated = _actuated(model, doc["actuated_joints"], urdf_path, path)
    platform = doc["platform_frame"]
    _frame_id(model, platform, path, "platform_frame")
    task = _task(model, doc.get("task"), platform, path)
    workspace = _workspace(doc.get("workspace"), actuated, task, path)
    return Description(
        _closures(model, doc["closures"], path),
        actuated,
        _chains(model, doc, path),
        platform,
        _home(model, doc["home"], path),
        task,
        workspace,
        _locked(model, doc.get("locked_joints", []), actuated, path),
    )


def add_declared_frames(model: pin.Model, entries: object, path: Path) -> None:
    """Add to `model` the closures file's `frames`: {name: {link: L, xyz: [x, y, z], rpy: [r, p, y]}},
    each an operational frame at that placement in frame L (a link or any frame of the URDF) [m, rad;
    rpy as URDF: R = Rz(y) Ry(p) Rx(r)]. For points a URDF does not name (a simulator's anchor)."""
    if entries is None:
        return
    if not isinstance(entries, dict):
        raise ModelFileError(path, "frames must map frame names to {link, xyz, rpy}")
    for name, entry in entries.items():
        where = f"frames.{name}"
        if not isinstance(name, str) or model.existFrame(name):
            raise ModelFileError(path, f"{where}: a frame of that name already exists in the URDF")
        if not isinstance(entry, dict) or set(entry) - {"link", "xyz", "rpy"} or "link" not in entry:
            raise ModelFileError(
                path, f"{where} must be a mapping with 'link' and optional 'xyz', 'rpy', got {entry!r}"
            )
        parent = model.frames[_frame_id(model, entry["link"], path, f"{where}.link")]
        xyz, rpy = (_triple(entry.get(key, [0.0, 0.0, 0.0]), f"{where}.{key}", path) for key in ("xyz", "rpy"))
        local = pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)
        model.addFrame(
            pin.Frame(
                name,
                parent.parentJoint,
                model.getFrameId(parent.name, parent.type),
                parent.placement * local,
                pin.FrameType.OP_FRAME,
            )
        )


def _triple(values: object, where: str, path: Path) -> np.ndarray:
    if (
        not isinstance(values, list)
        or len(values) != 3
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in values)
    ):
        raise ModelFileError(path, f"{where} must be three finite numbers, got {values!r}")
    return np.array(values, dtype=float)


def declared_frame_entries(model: pin.Model, doc: dict) -> dict:
    """The closures document's `frames` entries with `xyz`, `rpy` re-read from `model` (relative to
    their link), for writing a model whose frame placements calibration changed."""
    out = {}
    for name, entry in (doc.get("frames") or {}).items():
        parent = model.frames[_named_frame(model, entry["link"])]
        local = parent.placement.actInv(model.frames[model.getFrameId(name, pin.FrameType.OP_FRAME)].placement)
        out[name] = {
            "link": entry["link"],
            "xyz": [float(v) + 0.0 for v in local.translation],
            "rpy": [float(v) + 0.0 for v in pin.rpy.matrixToRpy(local.rotation)],
        }
    return out


def _frame_id(model: pin.Model, name: object, path: Path, where: str) -> int:
    if not isinstance(name, str) or not model.existFrame(name):
        raise ModelFileError(path, f"{where}: frame '{name}' does not exist in the URDF")
    return _named_frame(model, name)


def _named_frame(model: pin.Model, name: str) -> int:
    """The frame of that name; the link (BODY frame) when a joint has the same name (MJCF bodies often do)."""
    return (
        model.getFrameId(name, pin.FrameType.BODY)
        if model.existFrame(name, pin.FrameType.BODY)
        else model.getFrameId(name)
    )


def _actuated(model: pin.Model, actuated: object, urdf_path: Path, path: Path) -> tuple[str, ...]:
    if not isinstance(actuated, list) or not actuated:
        raise ModelFileError(path, "actuated_joints must be a non-empty list of joint names")
    for name in actuated:
        if isinstance(name, str) and model.existFrame(name, pin.FrameType.FIXED_JOINT):
            raise ModelFileError(path, f"actuated_joints: '{name}' is a fixed joint, not prismatic or revolute")
        if not isinstance(name, str) or not model.existJointName(name):
            raise ModelFileError(path, f"actuated_joints: joint '{name}' does not exist in {urdf_path.name}")
        # Every other joint is 1-DoF revolute or prismatic: `Mechanism.load` refuses the rest first.
    if len(set(actuated)) != len(actuated):
        raise ModelFileError(path, "actuated_joints: a joint is listed twice")
    return tuple(actuated)


def _locked(model: pin.Model, names: object, actuated: tuple[str, ...], path: Path) -> tuple[str, ...]:
    """`locked_joints`: passive joints held at their home value (written by `Mechanism.save`)."""
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise ModelFileError(path, f"locked_joints must be a list of joint names, got {names!r}")
    for name in names:
        if not model.existJointName(name):
            raise ModelFileError(path, f"locked_joints: joint '{name}' does not exist")
        if name in actuated:
            raise ModelFileError(path, f"locked_joints: '{name}' is an actuated joint")
    if len(set(names)) != len(names):
        raise ModelFileError(path, "locked_joints: a joint is listed twice")
    return tuple(names)


def _closures(model: pin.Model, entries: object, path: Path) -> tuple[ClosureSpec, ...]:
    if entries is not None and not isinstance(entries, list):
        raise ModelFileError(path, f"closures must be a list of closures, got {entries!r}")
    closures = []
    seen = set()
    for k, entry in enumerate(entries or []):
        where = f"closures[{k}]"
        if not isinstance(entry, dict):
            raise ModelFileError(path, f"{where}: expected a mapping")
        name = entry.get("name", where)
        where = f"closure '{name}'"
        if name in seen:
            raise ModelFileError(path, f"{where}: duplicate closure name")
        seen.add(name)
        kind = entry.get("type")
        if kind not in ROW_COUNT:
            raise ModelFileError(path, f"{where}: type must be 3D or 6D, got {kind!r}")
        ia = _frame_id(model, entry.get("frame_a"), path, where)
        ib = _frame_id(model, entry.get("frame_b"), path, where)
        body = model.frames[ia].parentJoint
        if body == model.frames[ib].parentJoint:
            what = "the same frame" if ia == ib else f"both fixed to the body of joint '{model.names[body]}'"
            raise ModelFileError(
                path,
                f"{where}: frame_a '{entry['frame_a']}' and frame_b '{entry['frame_b']}' are "
                f"{what}: the closure constrains no joint",
            )
        rows = entry.get("rows", list(range(ROW_COUNT[kind])))
        if (
            not isinstance(rows, list)
            or not rows
            or len(set(rows)) != len(rows)
            or not all(isinstance(r, int) and 0 <= r < ROW_COUNT[kind] for r in rows)
        ):
            raise ModelFileError(
                path, f"{where}: rows must be distinct indices in 0..{ROW_COUNT[kind] - 1}, got {rows!r}"
            )
        closures.append(ClosureSpec(name, kind, entry["frame_a"], entry["frame_b"], tuple(sorted(rows)), ia, ib))
    if not closures:
        raise ModelFileError(path, "closures: at least one closure is required")
    return tuple(closures)


def _chains(model: pin.Model, doc: dict, path: Path) -> dict[str, tuple[str, ...]]:
    chains = {}
    for chain_name, items in (doc.get("principal_chains") or {}).items():
        if not isinstance(items, list) or len(items) < 2:
            raise ModelFileError(path, f"principal_chains.{chain_name}: expected joint names then a frame name")
        for joint in items[:-1]:
            if not model.existJointName(joint):
                raise ModelFileError(path, f"principal_chains.{chain_name}: joint '{joint}' does not exist")
        _frame_id(model, items[-1], path, f"principal_chains.{chain_name}")
        chains[chain_name] = tuple(items)
    return chains


def _home(model: pin.Model, home_doc: object, path: Path) -> np.ndarray:
    if not isinstance(home_doc, dict):
        raise ModelFileError(path, "home must map joint names to values")
    home = pin.neutral(model)
    for name, value in home_doc.items():
        if not model.existJointName(name):
            raise ModelFileError(path, f"home: joint '{name}' does not exist")
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ModelFileError(path, f"home: joint '{name}' has non-numeric value {value!r}") from None
        if not np.isfinite(value):
            raise ModelFileError(path, f"home: joint '{name}' has non-finite value {value}")
        home[model.idx_qs[model.getJointId(name)]] = value
    return home


def _task(model: pin.Model, entry: object, platform: str, path: Path) -> TaskSpec:
    if entry is None:  # schema 1: the M machine's task
        return TaskSpec(platform)
    if not isinstance(entry, dict):
        raise ModelFileError(path, "task must be a mapping with frame, position and rotation")
    unknown = set(entry) - {"frame", "position", "rotation"}
    if unknown:
        raise ModelFileError(path, f"task: unknown field '{sorted(unknown)[0]}' (known: frame, position, rotation)")
    frame = entry.get("frame", platform)
    _frame_id(model, frame, path, "task.frame")
    position = entry.get("position", [])
    if not isinstance(position, list):
        raise ModelFileError(path, f"task.position must be a list of axes among x, y, z, got {position!r}")
    try:
        return TaskSpec(frame, tuple(position), entry.get("rotation", "none"))
    except InvalidInputError as exc:
        raise ModelFileError(path, str(exc)) from None


def _intervals(entry: object, names: tuple[str, ...], where: str, path: Path) -> tuple[tuple[str, float, float], ...]:
    if not isinstance(entry, dict) or set(entry) != set(names):
        given = sorted(entry) if isinstance(entry, dict) else entry
        raise ModelFileError(
            path, f"{where} must give an interval [lo, hi] for each of {', '.join(names)}; got {given!r}"
        )
    out = []
    for name in names:
        interval = entry[name]
        if (
            not isinstance(interval, list)
            or len(interval) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in interval)
        ):
            raise ModelFileError(path, f"{where}.{name} must be [lo, hi] numbers, got {interval!r}")
        out.append((name, float(interval[0]), float(interval[1])))
    return tuple(out)


def _workspace(entry: object, actuated: tuple[str, ...], task: TaskSpec, path: Path) -> WorkspaceSpec | None:
    if entry is None:
        return None
    if not isinstance(entry, dict) or len(entry) != 1 or next(iter(entry)) not in ("actuators", "task"):
        raise ModelFileError(path, "workspace must have exactly one of 'actuators' or 'task'")
    kind, box = next(iter(entry.items()))
    try:
        if kind == "actuators":
            return WorkspaceSpec(actuators=_intervals(box, actuated, "workspace.actuators", path))
        if task.dimension != len(actuated):
            raise ModelFileError(
                path,
                f"workspace.task: the task commands {task.dimension} coordinates for "
                f"{len(actuated)} actuators; sample a task box only when they match "
                "(give an actuators box)",
            )
        return WorkspaceSpec(task=_intervals(box, task.box_keys, "workspace.task", path))
    except InvalidInputError as exc:
        raise ModelFileError(path, str(exc)) from None
