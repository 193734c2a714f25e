"""Mechanisms published as MJCF: the tree and its loops read by Pinocchio's own MJCF parser.

`read_mjcf` turns an MJCF file into what a URDF and a closures file give `Mechanism.load`: the
Pinocchio tree, and a closures document (models/README.md) made from the file itself:

- each `<equality><connect>` is a 3D closure and each `<weld>` a 6D one, between two frames
  declared (`frames:`) at the constraint's ends as Pinocchio places them (a connect's second end,
  and a weld's relative pose when `relpose` is not given, are where the file's reference
  configuration qpos0 puts them, as in MuJoCo);
- the actuated joints are the joints of the `<actuator>` elements (joint transmission), in file order;
- the home is the keyframe named `home`, else the first keyframe, else qpos0 (assembled at load
  as any approximate home);
- limits are the joints' `range` as Pinocchio reads it.

What has no closures-file form is refused with the element and its line: ball and free joints, a
body with several joints, tendons in an equality or an actuator, other equality kinds. The
platform frame, task and workspace come from a sidecar closures file if there is one
(`NAME.closures.yaml` beside `NAME.xml`, without `closures`, `actuated_joints`), else the
platform frame is the file's only site.
"""

from __future__ import annotations

import math
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
from lxml import etree

from m3t1r.errors import ModelFileError

__all__ = ["MjcfTree", "is_mjcf", "read_mjcf", "mjcf_sidecar_path", "SIDECAR_FIELDS"]

#: Fields a sidecar closures file of an MJCF may give; the others come from the MJCF itself.
SIDECAR_FIELDS = (
    "schema_version",
    "platform_frame",
    "task",
    "workspace",
    "home",
    "frames",
    "principal_chains",
    "locked_joints",
)
_ONE_DOF = ("hinge", "slide")
_TRANSMISSIONS = ("joint", "jointinparent")
_OTHER_TRANSMISSIONS = ("tendon", "site", "body", "cranksite", "slidersite", "refsite")
#: What may precede the root element: a byte order mark, the XML declaration, comments, a doctype.
_PROLOG = re.compile(rb"\A(?:\xef\xbb\xbf|\s+|<\?.*?\?>|<!--.*?-->|<!DOCTYPE[^>]*>)*", re.DOTALL)


@dataclass(frozen=True)
class MjcfTree:
    """An MJCF file read for `Mechanism.load`: the tree, a closures document and what was assumed."""

    model: pin.Model
    document: dict
    notes: tuple[str, ...]


@dataclass(frozen=True)
class _Equality:
    key: str  # the name the parser is given (unique, sorts in file order)
    name: str  # the file's name, or `<kind>_<k>`
    kind: str  # connect or weld
    line: int


def is_mjcf(data: bytes) -> bool:
    """Whether file bytes are meant as an MJCF document: their first element is `<mujoco>` (a file
    cut short or malformed after it is still one, so that its reader names what is wrong)."""
    head = _PROLOG.sub(b"", data[:65536])
    return re.match(rb"\s*<mujoco[\s>/]", head) is not None


def mjcf_sidecar_path(mjcf: Path) -> Path:
    """`NAME.xml` -> `NAME.closures.yaml` beside it: the optional file naming the platform frame and task."""
    stem = mjcf.name[: -len(mjcf.suffix)] if mjcf.suffix.lower() in (".xml", ".mjcf") else mjcf.name
    return mjcf.with_name(stem + ".closures.yaml")


def read_mjcf(path: Path, data: bytes, sidecar: dict | None, sidecar_path: Path) -> MjcfTree:
    """The tree of MJCF bytes `data` (file `path`) and its closures document, merged with `sidecar`.

    Raises ModelFileError naming the element and its line for what cannot be mapped, an equality
    or actuator naming a body, site or joint that does not exist, a keyframe of the wrong size,
    and naming the sidecar for a field it may not give or a platform frame it does not name.
    """
    try:
        root = etree.fromstring(data, _parser())
    except etree.XMLSyntaxError as exc:
        raise ModelFileError(path, f"not well-formed XML: {exc}") from None
    _refuse_unmappable(root, path)
    equalities, notes = _named_equalities(root, path)
    keyframe = _named_keyframes(root, path)
    _wrap_world(root)
    model, points, welds = _parse(path, root)
    _fix_limits(root, model)
    frames, closures = _closure_entries(model, equalities, points, welds, path)
    doc: dict = {
        "schema_version": 2,
        "actuated_joints": _actuated(root, model, path),
        "closures": closures,
        "frames": frames,
        "home": _home(model, keyframe),
    }
    notes += _merge_sidecar(doc, sidecar, sidecar_path, root, path)
    return MjcfTree(model, doc, tuple(notes))


def _parser() -> etree.XMLParser:
    return etree.XMLParser(remove_comments=True, resolve_entities=False, no_network=True)


def _where(element: etree._Element) -> str:
    name = element.get("name")
    return f"line {element.sourceline}: <{element.tag}{f' name={name!r}' if name else ''}>"


def _refuse_unmappable(root: etree._Element, path: Path) -> None:
    """Elements without a closures-file form: multi-DoF joints, several joints on a body, tendon loops."""
    worldbody = root.find("worldbody")
    if worldbody is None or worldbody.find("body") is None:
        raise ModelFileError(path, "the MJCF has no <worldbody> with a <body>: there is no mechanism")
    for element in root.iter("freejoint"):
        raise ModelFileError(
            path, f"{_where(element)}: a free joint; m3t1r models fixed-base mechanisms of 1-DoF joints (hinge, slide)"
        )
    for element in root.iter("joint"):
        kind = element.get("type", "hinge")
        if element.getparent().tag == "body" and kind not in _ONE_DOF:
            raise ModelFileError(
                path,
                f"{_where(element)}: a {kind} joint; m3t1r models 1-DoF joints only "
                "(hinge, slide): write a ball joint as three hinges with intersecting axes",
            )
    for body in root.iter("body"):
        joints = body.findall("joint")
        if len(joints) > 1:
            raise ModelFileError(
                path,
                f"{_where(body)}: {len(joints)} joints on one body; m3t1r takes one joint per "
                "body (put each joint on a body of its own)",
            )
    for equality in root.iter("equality"):
        for element in equality:
            if isinstance(element.tag, str) and element.tag not in ("connect", "weld"):
                raise ModelFileError(
                    path,
                    f"{_where(element)}: a {element.tag} equality has no closure form "
                    "(m3t1r maps connect to a 3D closure and weld to a 6D one)",
                )
    for actuator in root.iter("actuator"):
        for element in actuator:
            if not isinstance(element.tag, str):
                continue
            other = [key for key in _OTHER_TRANSMISSIONS if element.get(key) is not None]
            if other:
                raise ModelFileError(
                    path,
                    f"{_where(element)}: a {other[0]} transmission; m3t1r actuates joints "
                    '(an actuator with joint="...")',
                )


def _named_equalities(root: etree._Element, path: Path) -> tuple[list[_Equality], list[str]]:
    """The active connect and weld elements, renamed so that the parser's order is the file's.

    Pinocchio keeps its constraints sorted by name, without the name; unique keys that sort in
    file order tie each of them to its element. Inactive ones are removed (a note says so).
    """
    bodies = {b.get("name") for b in root.iter("body")}
    sites = {s.get("name") for s in root.iter("site")}
    found: list = []
    notes: list[str] = []
    inactive: list = []
    for k, element in enumerate(e for eq in root.iter("equality") for e in eq if isinstance(e.tag, str)):
        for attribute, known in (("body1", bodies), ("body2", bodies), ("site1", sites), ("site2", sites)):
            value = element.get(attribute)
            if value is not None and value not in known:
                kind = "body" if attribute.startswith("body") else "site"
                raise ModelFileError(path, f"{_where(element)}: {attribute} '{value}' is not a {kind} of the file")
        if element.get("body1") is None and element.get("site1") is None:
            raise ModelFileError(path, f"{_where(element)}: names neither body1 nor site1")
        name = element.get("name") or f"{element.tag}_{k}"
        if element.get("active", "true").strip().lower() == "false":
            inactive.append(name)
            element.getparent().remove(element)
            continue
        if any(e.name == name for e in found):
            raise ModelFileError(path, f"{_where(element)}: an equality of that name appears earlier")
        key = f"m3t1r_eq_{k:04d}"
        found.append(_Equality(key, name, element.tag, element.sourceline or 0))
        element.set("name", key)
    if inactive:
        notes.append(f'inactive equality constraint(s) {", ".join(inactive)} (active="false") left out')
    if not found:
        raise ModelFileError(
            path,
            "the MJCF has no active <equality> connect or weld: no loop to close "
            "(a serial robot is calibrated with --serial)",
        )
    return found, notes


def _named_keyframes(root: etree._Element, path: Path) -> str:
    """The reference configuration to take as home: the key named `home`, else the first, else qpos0.
    Keys are renamed (the parser drops unnamed ones) and their size checked against the joints."""
    count = sum(1 for j in root.iter("joint") if j.getparent().tag == "body")
    chosen = None
    for k, key in enumerate(root.iter("key")):
        values = (key.get("qpos") or "").split()
        if key.get("qpos") is not None and len(values) != count:
            raise ModelFileError(path, f"{_where(key)}: qpos has {len(values)} values for the file's {count} joints")
        if key.get("qpos") is None:
            key.set("qpos", " ".join(["0"] * count))  # MuJoCo's default is qpos0; the parser needs a value
            continue
        name = f"m3t1r_key_{k:04d}"
        if chosen is None or key.get("name") == "home":
            chosen = name
        key.set("name", name)
    return chosen or "qpos0"


def _wrap_world(root: etree._Element) -> None:
    """Put everything under <worldbody> into one fixed body: Pinocchio's parser reads only the first
    body of the world (and drops the world's own sites); a body without a joint is welded to the world."""
    worldbody = root.find("worldbody")
    children = [c for c in worldbody if isinstance(c.tag, str)]
    if len([c for c in children if c.tag == "body"]) == 1 and all(
        c.tag in ("body", "light", "camera") for c in children
    ):
        return
    names = {b.get("name") for b in root.iter("body")}
    name = next(n for n in ("base", "world_base", *(f"base_{k}" for k in range(len(names) + 1))) if n not in names)
    base = etree.SubElement(worldbody, "body", name=name)
    for child in children:
        worldbody.remove(child)
        base.append(child)


def _parse(path: Path, root: etree._Element) -> tuple[pin.Model, list, list]:
    """Pinocchio's MJCF parser on the prepared document (a temporary copy: the input is never written),
    with asset folders made absolute so that they resolve against the input's folder."""
    folder = path.resolve().parent
    compiler = root.find("compiler")
    if compiler is None:
        compiler = etree.Element("compiler")
        root.insert(0, compiler)
    assets = compiler.attrib.pop("assetdir", "")  # MJCF: the default of both folders below
    for key in ("meshdir", "texturedir"):
        compiler.set(key, str(folder / compiler.get(key, assets)) + "/")
    for include in root.iter("include"):
        include.set("file", str(folder / include.get("file", "")))
    with tempfile.TemporaryDirectory(prefix="m3t1r-mjcf-") as scratch:
        copy = Path(scratch) / "model.xml"
        copy.write_bytes(etree.tostring(root))
        try:
            model, points, welds = pin.buildModelAndConstraintsFromMJCF(str(copy))
        except Exception as exc:  # Pinocchio raises bare ValueError/RuntimeError for what it cannot read
            raise ModelFileError(path, f"Pinocchio's MJCF parser rejected the file: {exc}") from None
    for j in range(1, model.njoints):
        if model.nqs[j] != 1 or model.nvs[j] != 1:
            raise ModelFileError(path, f"joint '{model.names[j]}' is not a 1-DoF hinge or slide (nq={model.nqs[j]})")
    return model, list(points), list(welds)


def _fix_limits(root: etree._Element, model: pin.Model) -> None:
    """The joints' limits as MJCF means them: `range` in qpos units (hinges in the compiler's angle
    unit, slides in metres), unbounded where `limited="false"`. Pinocchio 4.1 stores a range given
    on the joint minus its `ref`, and scales a slide's range as an angle under `<compiler
    angle="degree">` (MJCF's default): a range on the joint is read as written, one inherited from
    a default class (not shifted) is unscaled."""
    compiler = root.find("compiler")
    degrees = (compiler.get("angle", "degree") if compiler is not None else "degree") == "degree"
    elements = {j.get("name"): j for j in root.iter("joint") if j.getparent().tag == "body" and j.get("name")}
    lower, upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
    for j in range(1, model.njoints):
        k, slide = model.idx_qs[j], model.joints[j].shortname().startswith("JointModelP")
        element = elements.get(model.names[j])
        if element is not None and element.get("limited", "").strip().lower() == "false":
            lower[k], upper[k] = -np.inf, np.inf
        elif element is not None and element.get("range") is not None:
            scale = math.pi / 180.0 if degrees and not slide else 1.0
            lower[k], upper[k] = (float(v) * scale for v in element.get("range").split()[:2])
        elif degrees and slide and np.isfinite(lower[k]) and np.isfinite(upper[k]):
            lower[k], upper[k] = lower[k] * 180.0 / math.pi, upper[k] * 180.0 / math.pi
    model.lowerPositionLimit, model.upperPositionLimit = lower, upper


def _closure_entries(
    model: pin.Model, equalities: list[_Equality], points: list, welds: list, path: Path
) -> tuple[dict, list]:
    """Declared frames at both ends of each constraint, and the closures between them, in file order."""
    connects = sorted((e for e in equalities if e.kind == "connect"), key=lambda e: e.key)
    weld_elements = sorted((e for e in equalities if e.kind == "weld"), key=lambda e: e.key)
    if len(connects) != len(points) or len(weld_elements) != len(welds):
        raise ModelFileError(
            path,
            f"Pinocchio's parser made {len(points)} point and {len(welds)} frame constraints "
            f"of {len(connects)} connect and {len(weld_elements)} weld elements",
        )
    by_key = {e.key: c for e, c in zip(connects + weld_elements, points + welds)}
    frames: dict = {}
    closures = []
    for equality in equalities:
        constraint = by_key[equality.key]
        ends = []
        for suffix, joint, placement in (
            ("a", constraint.joint1_id, constraint.joint1_placement),
            ("b", constraint.joint2_id, constraint.joint2_placement),
        ):
            name = _free_name(model, frames, f"{equality.name}_{suffix}")
            frames[name] = _frame_entry(model, joint, placement)
            ends.append(name)
        if constraint.joint1_id == constraint.joint2_id:
            raise ModelFileError(
                path,
                f"line {equality.line}: <{equality.kind} name='{equality.name}'> joins two "
                "points of one rigid body: it constrains no joint",
            )
        closures.append(
            {
                "name": equality.name,
                "type": "3D" if equality.kind == "connect" else "6D",
                "frame_a": ends[0],
                "frame_b": ends[1],
            }
        )
    return frames, closures


def _free_name(model: pin.Model, taken: dict, wanted: str) -> str:
    name, k = wanted, 1
    while model.existFrame(name) or name in taken:
        name, k = f"{wanted}{k}", k + 1
    return name


def _frame_entry(model: pin.Model, joint: int, placement: pin.SE3) -> dict:
    """A declared frame at `placement` on `joint`, relative to a body (link) that joint moves."""
    bodies = [f for f in model.frames if f.parentJoint == joint and f.type == pin.FrameType.BODY]
    link = bodies[0] if bodies else model.frames[model.getFrameId("universe", pin.FrameType.FIXED_JOINT)]
    local = link.placement.actInv(placement)
    return {
        "link": link.name,
        "xyz": [float(v) + 0.0 for v in local.translation],
        "rpy": [float(v) + 0.0 for v in pin.rpy.matrixToRpy(local.rotation)],
    }


def _actuated(root: etree._Element, model: pin.Model, path: Path) -> list[str]:
    names: list[str] = []
    for actuator in root.iter("actuator"):
        for element in actuator:
            if not isinstance(element.tag, str):
                continue
            joint = next((element.get(key) for key in _TRANSMISSIONS if element.get(key) is not None), None)
            if joint is None:
                raise ModelFileError(path, f'{_where(element)}: names no joint (joint="...")')
            if not model.existJointName(joint):
                raise ModelFileError(path, f"{_where(element)}: joint '{joint}' is not a joint of the file")
            if joint in names:
                raise ModelFileError(path, f"{_where(element)}: joint '{joint}' is actuated twice")
            names.append(joint)
    if not names:
        raise ModelFileError(
            path,
            "the MJCF has no <actuator> on a joint: m3t1r needs the actuated joints "
            '(add <actuator><motor joint="..."/></actuator>, one per motor)',
        )
    return names


def _home(model: pin.Model, keyframe: str) -> dict:
    configurations = {entry.key(): entry.data() for entry in model.referenceConfigurations}
    q = np.asarray(configurations.get(keyframe, configurations.get("qpos0", pin.neutral(model))), dtype=float)
    return {model.names[j]: float(q[model.idx_qs[j]]) for j in range(1, model.njoints)}


def _merge_sidecar(doc: dict, sidecar: dict | None, sidecar_path: Path, root: etree._Element, path: Path) -> list[str]:
    """The sidecar's fields added to `doc` (its `home` values over the file's), or the platform frame
    defaulted to the file's only site."""
    sidecar = sidecar or {}
    for key in sidecar:
        if key not in SIDECAR_FIELDS:
            raise ModelFileError(
                sidecar_path,
                f"'{key}' comes from {path.name} for an MJCF model (a sidecar gives: {', '.join(SIDECAR_FIELDS)})",
            )
    frames = sidecar.get("frames") or {}
    if not isinstance(frames, dict):
        raise ModelFileError(sidecar_path, "frames must map frame names to {link, xyz, rpy}")
    doc["frames"] = {**doc["frames"], **frames}
    home = sidecar.get("home") or {}
    if not isinstance(home, dict):
        raise ModelFileError(sidecar_path, "home must map joint names to values")
    doc["home"] = {**doc["home"], **home}
    for key in ("task", "workspace", "principal_chains", "locked_joints"):
        if key in sidecar:
            doc[key] = sidecar[key]
    if "platform_frame" in sidecar:
        doc["platform_frame"] = sidecar["platform_frame"]
        return []
    sites = [s.get("name") for s in root.iter("site") if s.get("name")]
    if len(sites) != 1:
        raise ModelFileError(
            path,
            f"name the platform frame (a site or body of the file: {', '.join(sites[:8])}"
            f"{' ...' if len(sites) > 8 else ''}) in {sidecar_path.name} beside it: "
            "`platform_frame: NAME`"
            if sites
            else f"the file has no site to measure: name a body as `platform_frame: NAME` in "
            f"{sidecar_path.name} beside it",
        )
    doc["platform_frame"] = sites[0]
    return [f"platform frame: site '{sites[0]}', the file's only site (no {sidecar_path.name} names one)"]
