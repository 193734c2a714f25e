"""Write a calibrated Pinocchio model back into its URDF, changing only the joint origins.

How Pinocchio's URDF parser maps a URDF onto a model, and so how each origin is recovered:

- A non-fixed joint J (revolute, continuous, prismatic, planar, floating) becomes a model
  joint whose `model.jointPlacements[J]` is relative to the parent *joint* frame, while the
  URDF origin is relative to the parent *link* frame. The parent link's BODY frame sits at
  `B_parent` relative to that same parent joint, hence

      origin(J) = B_parent^-1 * jointPlacements[J].

  `B_parent` is the identity unless the parent link hangs off its joint through fixed joints.

- A fixed joint F from link P to link C becomes two frames on P's parent joint with the same
  placement: a FIXED_JOINT frame named F and a BODY frame named C. Hence

      origin(F) = B_P^-1 * B_C.

  When a calibrated model has the two disagree, the BODY frame of C is authoritative and the
  FIXED_JOINT frame is not read: the BODY frame is the link frame that calibration identifies
  (the frame a measured target is fixed to) and that descendants are placed against. A model
  reloaded from the written file has its FIXED_JOINT frame equal to that BODY frame again.

- In a URDF a link frame coincides with the frame of the joint that moves it. So the BODY
  frame of the child of a non-fixed joint, that joint's JOINT frame, and the BODY frame of the
  root link must sit at the identity on their joint. An offset there has no URDF form: it is
  refused with an error rather than dropped from the output.

Frames of other types (OP_FRAME, SENSOR) are not URDF content and are not written.

The output keeps the nominal file byte for byte outside the rewritten `xyz` and `rpy`
attribute values (comments, attribute order, quoting, indentation, meshes, limits, inertias).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
from lxml import etree

from m3t1r.errors import ModelFileError
from m3t1r.io.outputs import atomic_write_bytes
from m3t1r.io.pairing import with_closures_sha256
from m3t1r.io.paths import StrPath, ensure_not_protected
from m3t1r.io.tables import format_float

IDENTITY_TOLERANCE = 1e-12
"""m and rad. A link frame closer than this to its joint frame counts as on it: far below any
identifiable offset, far above the rounding of a few SE3 products."""


@dataclass(frozen=True)
class _UrdfJoint:
    """A `<joint>` element directly under `<robot>`, with the attributes that matter here."""

    name: str
    kind: str
    parent: str
    child: str
    element: etree._Element

    @property
    def is_fixed(self) -> bool:
        return self.kind == "fixed"


def write_calibrated_urdf(
    nominal_urdf: StrPath,
    model: pin.Model,
    out_path: StrPath,
    protect: Iterable[StrPath] = (),
) -> None:
    """Write `nominal_urdf` with every joint `<origin>` taken from the calibrated `model`.

    Args:
        nominal_urdf: the URDF that `model` was built from (with or without a root joint).
        model: that model after calibration changed its joint placements and link BODY frames.
        out_path: the calibrated URDF to write, atomically; never `nominal_urdf`.
        protect: further input files that `out_path` must not be.

    `xyz` (m) and `rpy` (rad, URDF convention R = Rz(yaw) Ry(pitch) Rx(roll)) are written as
    the shortest decimals that parse back to the same doubles. A joint without `<origin>` gets
    one. See the module docstring for how each origin is computed and which frame wins.
    A closures-pairing comment copied from the nominal file is dropped: the output is a URDF
    on its own (`Mechanism.save` writes pairs).

    Raises:
        ModelFileError: the nominal file is unreadable or not a URDF, or `model` does not have
            this file's structure (a joint or link missing, attached elsewhere), or a link
            frame is offset from its joint frame, which a URDF cannot express.
        OutputPathError: `out_path` is the nominal file or in `protect`, or the write failed.
    """
    nominal = Path(nominal_urdf)
    protected = (nominal, *protect)
    ensure_not_protected(out_path, protected)  # before any work, not only at the final write
    atomic_write_bytes(out_path, calibrated_urdf_bytes(nominal, model), protect=protected)


def calibrated_urdf_bytes(nominal_urdf: StrPath, model: pin.Model, closures_sha256: str | None = None) -> bytes:
    """The bytes `write_calibrated_urdf` writes, with the pairing comment for `closures_sha256` if given.

    Raises ModelFileError as `write_calibrated_urdf` does.
    """
    nominal = Path(nominal_urdf)
    try:
        raw = nominal.read_bytes()
    except OSError as exc:
        raise ModelFileError(nominal, f"cannot read: {exc.strerror or exc}") from None
    root = _parse(nominal, raw)
    joints = _urdf_joints(nominal, root)
    children = {joint.child for joint in joints}
    root_links = [name for link in root.iterchildren("link") if (name := link.get("name")) and name not in children]
    _check_joint_sets(nominal, model, joints, root_links)
    for link in root_links:
        _require_on_joint(nominal, model, _link_frame(nominal, model, link), f"root link '{link}'")
    origins = {
        joint.name: _fixed_origin(nominal, model, joint) if joint.is_fixed else _moving_origin(nominal, model, joint)
        for joint in joints
    }
    output = _rewrite_origins(raw, root, joints, {name: _origin_attributes(m) for name, m in origins.items()})
    return with_closures_sha256(output, closures_sha256)


def revolute_urdf_text(urdf: StrPath, raw: bytes) -> str | None:
    """The URDF text with each continuous joint made a revolute one without limits, or None if it has none.

    Pinocchio builds a continuous joint as a unit-circle joint (nq = 2: cos, sin), a revolute one
    with nq = 1; the closure solvers take one coordinate per joint, and an unbounded revolute joint
    moves the same way. A `<limit>` without `lower`/`upper` reads as [0, 0], which `Mechanism.load`
    takes as "not given" (unbounded). None too for a file that is not a URDF: Pinocchio then says why.
    """
    if b"continuous" not in raw:
        return None
    try:
        root = _parse(Path(urdf), raw)
    except ModelFileError:
        return None
    continuous = [joint for joint in root.iterchildren("joint") if joint.get("type") == "continuous"]
    if not continuous:
        return None
    for joint in continuous:
        joint.set("type", "revolute")
        limit = joint.find("limit")
        if limit is None:
            limit = etree.SubElement(joint, "limit")
        for key in ("effort", "velocity"):
            limit.set(key, limit.get(key, "0"))
        for key in ("lower", "upper"):
            limit.attrib.pop(key, None)
    return etree.tostring(root, encoding="unicode")


# --------------------------------------------------------------------------------------------
# Reading the nominal URDF
# --------------------------------------------------------------------------------------------


def _parser() -> etree.XMLParser:
    # Keep everything a user may have written (comments, CDATA) and never fetch anything.
    return etree.XMLParser(remove_comments=False, strip_cdata=False, resolve_entities=False, no_network=True)


def _parse(nominal: Path, raw: bytes) -> etree._Element:
    try:
        root = etree.fromstring(raw, _parser())
    except etree.XMLSyntaxError as exc:
        raise ModelFileError(nominal, f"not well-formed XML: {exc}") from None
    if root.tag != "robot":
        raise ModelFileError(nominal, f"root element is <{root.tag}>, a URDF has <robot>")
    return root


def _urdf_joints(nominal: Path, root: etree._Element) -> list[_UrdfJoint]:
    joints: list[_UrdfJoint] = []
    for element in root.iterchildren("joint"):
        where = f"line {element.sourceline}: <joint name={element.get('name')!r}>"
        parent, child = element.find("parent"), element.find("child")
        name, kind = element.get("name"), element.get("type")
        if name is None or kind is None:
            raise ModelFileError(nominal, f"{where} lacks a name or a type")
        if parent is None or child is None or parent.get("link") is None or child.get("link") is None:
            raise ModelFileError(nominal, f"{where} lacks <parent link=...> or <child link=...>")
        if len(element.findall("origin")) > 1:
            raise ModelFileError(nominal, f"{where} has more than one <origin>")
        if any(joint.name == name for joint in joints):
            raise ModelFileError(nominal, f"{where}: a joint of that name appears earlier")
        joints.append(_UrdfJoint(name, kind, parent.get("link"), child.get("link"), element))
    return joints


# --------------------------------------------------------------------------------------------
# Origins from the model
# --------------------------------------------------------------------------------------------


def _check_joint_sets(nominal: Path, model: pin.Model, joints: list[_UrdfJoint], root_links: list[str]) -> None:
    moving = {joint.name for joint in joints if not joint.is_fixed}
    # A root joint added when building the model (a free flyer, say) moves the root link and is
    # not in the file; any other model joint missing from the file means another model.
    root_joints = {
        model.frames[model.getFrameId(link, pin.FrameType.BODY)].parentJoint
        for link in root_links
        if model.existFrame(link, pin.FrameType.BODY)
    }
    fixed = {joint.name for joint in joints if joint.is_fixed}
    extra = [
        f"{model.names[j]} (fixed in the URDF)" if model.names[j] in fixed else model.names[j]
        for j in range(1, model.njoints)
        if model.names[j] not in moving and j not in root_joints
    ]
    if extra:
        raise ModelFileError(nominal, f"the model has joints the URDF does not: {', '.join(extra)}")


def _link_frame(nominal: Path, model: pin.Model, link: str) -> pin.Frame:
    if not model.existFrame(link, pin.FrameType.BODY):
        raise ModelFileError(nominal, f"link '{link}' has no BODY frame in the model: was it built from this file?")
    return model.frames[model.getFrameId(link, pin.FrameType.BODY)]


def _require_on_joint(nominal: Path, model: pin.Model, frame: pin.Frame, what: str) -> None:
    offset = _placement_distance(pin.SE3.Identity(), frame.placement)
    if offset > IDENTITY_TOLERANCE:
        raise ModelFileError(
            nominal,
            f"{what}: its frame is {offset:.3g} m or rad away from joint '{model.names[frame.parentJoint]}'; "
            "a URDF link frame coincides with its joint frame, so this offset cannot be written",
        )


def _moving_origin(nominal: Path, model: pin.Model, joint: _UrdfJoint) -> pin.SE3:
    if not model.existJointName(joint.name):
        raise ModelFileError(nominal, f"{joint.kind} joint '{joint.name}' is not in the model")
    index = model.getJointId(joint.name)
    parent = _link_frame(nominal, model, joint.parent)
    if parent.parentJoint != model.parents[index]:
        raise ModelFileError(
            nominal,
            f"joint '{joint.name}' hangs off joint '{model.names[model.parents[index]]}' in the model, but its "
            f"URDF parent link '{joint.parent}' is on joint '{model.names[parent.parentJoint]}'",
        )
    child = _link_frame(nominal, model, joint.child)
    if child.parentJoint != index:
        raise ModelFileError(nominal, f"link '{joint.child}' is not moved by joint '{joint.name}' in the model")
    _require_on_joint(nominal, model, child, f"link '{joint.child}'")
    if model.existFrame(joint.name, pin.FrameType.JOINT):
        _require_on_joint(
            nominal,
            model,
            model.frames[model.getFrameId(joint.name, pin.FrameType.JOINT)],
            f"JOINT frame '{joint.name}'",
        )
    return parent.placement.actInv(model.jointPlacements[index])


def _fixed_origin(nominal: Path, model: pin.Model, joint: _UrdfJoint) -> pin.SE3:
    parent = _link_frame(nominal, model, joint.parent)
    child = _link_frame(nominal, model, joint.child)
    if parent.parentJoint != child.parentJoint:
        raise ModelFileError(
            nominal,
            f"fixed joint '{joint.name}': the model puts link '{joint.parent}' on joint "
            f"'{model.names[parent.parentJoint]}' and link '{joint.child}' on joint '{model.names[child.parentJoint]}'",
        )
    # Child BODY frame, not the FIXED_JOINT frame: see the module docstring.
    return parent.placement.actInv(child.placement)


def _origin_attributes(placement: pin.SE3) -> dict[str, str]:
    # + 0.0 turns -0.0 into 0.0, which only spares readers a "-0.0".
    def text(values: np.ndarray) -> str:
        return " ".join(format_float(value + 0.0) for value in values)

    return {"xyz": text(placement.translation), "rpy": text(pin.rpy.matrixToRpy(placement.rotation))}


# --------------------------------------------------------------------------------------------
# Writing the origins back
# --------------------------------------------------------------------------------------------

# Lexical tokens of well-formed XML, enough to find tags without being fooled by comments,
# CDATA, processing instructions or a '>' inside an attribute value.
_XML_TOKEN = re.compile(
    rb"<!--.*?-->"
    rb"|<!\[CDATA\[.*?\]\]>"
    rb"|<\?.*?\?>"
    rb"|<!DOCTYPE(?:[^\[>]|\[.*?\])*>"
    rb"|</(?P<end>[^\s>]+)\s*>"
    rb"|<(?P<start>[^\s/>]+)(?:[^>\"']|\"[^\"]*\"|'[^']*')*?(?P<empty>/?)>",
    re.DOTALL,
)
_WHITESPACE = re.compile(rb"\s*")


def _rewrite_origins(
    raw: bytes, root: etree._Element, joints: list[_UrdfJoint], attributes: dict[str, dict[str, str]]
) -> bytes:
    """The nominal file with each joint origin set to `attributes[joint name]`.

    The edit is made twice: on the lxml tree, whose meaning is certain, and as a splice into
    the original bytes, which keeps the rest of the file as it was. The splice is used only if
    it parses to the same canonical XML as the edited tree; otherwise (an exotic document the
    tokenizer does not follow) the tree is serialized by lxml, which is equally correct but
    reformats the prolog and the root tag.
    """
    for joint in joints:
        origin = joint.element.find("origin")
        if origin is None:
            origin = etree.Element("origin")
            # The new first child takes over the indentation that preceded the old one.
            origin.tail = joint.element.text
            joint.element.insert(0, origin)
        for key, value in attributes[joint.name].items():
            origin.set(key, value)

    tree = root.getroottree()
    spliced = _splice_origins(raw, [attributes[joint.name] for joint in joints])
    try:
        same = spliced is not None and _canonical(spliced) == etree.tostring(tree, method="c14n")
    except etree.C14NError:  # unexpanded entity references cannot be canonicalised: serialise the tree
        same = False
    if same and spliced is not None:
        return spliced
    encoding = tree.docinfo.encoding or "UTF-8"
    return etree.tostring(tree, xml_declaration=True, encoding=encoding) + "\n".encode(encoding)


def _splice_origins(raw: bytes, attributes: list[dict[str, str]]) -> bytes | None:
    """`raw` with the origin of the i-th top-level joint set to `attributes[i]`, or None if lost."""
    stack: list[bytes] = []
    # Per top-level joint: (offset just past its start tag, (start, end) of its origin tag or None).
    joints: list[tuple[int, tuple[int, int] | None]] = []
    for token in _XML_TOKEN.finditer(raw):
        if token["end"] is not None:
            if not stack or stack.pop() != token["end"]:
                return None
        elif token["start"] is not None:
            name = token["start"]
            if name == b"joint" and stack == [b"robot"]:
                joints.append((token.end(), None))
            elif name == b"origin" and stack == [b"robot", b"joint"]:
                if joints[-1][1] is not None:
                    return None
                joints[-1] = (joints[-1][0], (token.start(), token.end()))
            if not token["empty"]:
                stack.append(name)
    if stack or len(joints) != len(attributes):
        return None

    output = bytearray(raw)
    # From the end backwards, so that earlier offsets stay valid.
    for (after_joint_tag, origin_span), values in reversed(list(zip(joints, attributes))):
        if origin_span is None:
            whitespace = _WHITESPACE.match(raw, after_joint_tag)
            assert whitespace is not None, "it matches the empty string"
            indent = whitespace[0]
            tag = b"<origin" + b"".join(b' %s="%s"' % (k.encode(), v.encode()) for k, v in values.items()) + b"/>"
            output[after_joint_tag:after_joint_tag] = indent + tag
        else:
            start, end = origin_span
            tag = raw[start:end]
            for key, value in values.items():
                tag = _with_attribute(tag, key.encode(), value.encode())
            output[start:end] = tag
    return bytes(output)


def _with_attribute(tag: bytes, name: bytes, value: bytes) -> bytes:
    """Start tag `tag` with attribute `name` set to `value`, in place and quoted as it was if present."""
    pattern = re.compile(rb"(\s" + re.escape(name) + rb"\s*=\s*)([\"'])(.*?)\2", re.DOTALL)
    replaced, count = pattern.subn(lambda m: m[1] + m[2] + value + m[2], tag, count=1)
    if count:
        return replaced
    end = re.search(rb"\s*/?>$", tag)
    assert end is not None, "a start tag ends in >"
    close = end.start()
    return tag[:close] + b' %s="%s"' % (name, value) + tag[close:]


def _canonical(document: bytes) -> bytes | None:
    try:
        return etree.tostring(etree.fromstring(document, _parser()).getroottree(), method="c14n")
    except etree.XMLSyntaxError:
        return None


def _placement_distance(a: pin.SE3, b: pin.SE3) -> float:
    """max(translation distance in m, rotation angle in rad) between placements a and b.

    The angle comes from the chord |R_a - R_b|_F = 2 sqrt(2) sin(angle / 2) rather than from
    log3(R_a^T R_b): no product, so equal placements give exactly 0 and tiny angles keep
    their digits.
    """
    translation = float(np.linalg.norm(a.translation - b.translation))
    chord = float(np.linalg.norm(a.rotation - b.rotation)) / (2.0 * np.sqrt(2.0))
    return max(translation, 2.0 * float(np.arcsin(min(chord, 1.0))))


def mimic_joints(urdf: bytes) -> dict[str, str]:
    """{joint name: the joint it mimics} of the `<mimic>` tags of URDF bytes (empty when the bytes
    do not parse: Pinocchio then names the problem). Pinocchio reads a mimic joint as an
    independent one, which a fit would then move on its own while the written URDF keeps the tag."""
    try:
        root = etree.fromstring(urdf, _parser())
    except etree.XMLSyntaxError:
        return {}
    return {
        str(joint.get("name")): str(mimic.get("joint"))
        for joint in root.iter("joint")
        for mimic in joint.findall("mimic")
    }


def refuse_mimic_joints(path: StrPath, urdf: bytes, joints: Iterable[str]) -> None:
    """ModelFileError naming the first of `joints` that the URDF makes a `<mimic>` of another."""
    mimics = mimic_joints(urdf)
    for name in joints:
        if name in mimics:
            raise ModelFileError(
                path,
                f"joint '{name}' mimics joint '{mimics[name]}' (<mimic>): m3t1r moves and "
                "calibrates every joint on its own, so a coupled joint is not supported; "
                "remove the tag (an independent joint) or make the joint fixed",
            )


def tree_urdf_bytes(
    model: pin.Model, robot: str, closures_sha256: str | None = None, skip_frames: Iterable[str] = ()
) -> bytes:
    """A URDF of `model`'s tree, for a model that has no URDF of its own (one read from MJCF).

    Each moving joint's child link is the BODY frame that sits on it (a link `<joint>_link` when
    none does), its other BODY frames and its operational frames (MJCF sites) are fixed links named
    as the frames, on fixed joints `<frame>_fixed`; `skip_frames` (the frames a closures file
    declares) are left out. Revolute joints without limits are continuous; a prismatic joint
    without limits gets `<limit>` without bounds, which `Mechanism.load` reads as unbounded.
    The link inertias are the model's. Loaded back, the tree has the same joints, placements and
    frame names.
    """
    skipped = set(skip_frames)
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    links = _joint_links(model)
    robot_element = etree.Element("robot", name=robot)
    used = set(links.values())
    etree.SubElement(robot_element, "link", name=links[0])
    for j in range(1, model.njoints):
        _inertial(etree.SubElement(robot_element, "link", name=links[j]), model.inertias[j])
        _moving_joint(robot_element, model, data, j, links)
    for frame in model.frames:
        if (
            frame.name in used
            or frame.name in skipped
            or frame.type not in (pin.FrameType.BODY, pin.FrameType.OP_FRAME)
        ):
            continue
        used.add(frame.name)
        etree.SubElement(robot_element, "link", name=frame.name)
        joint = etree.SubElement(robot_element, "joint", name=f"{frame.name}_fixed", type="fixed")
        etree.SubElement(joint, "origin", **_origin_attributes(frame.placement))
        etree.SubElement(joint, "parent", link=links[frame.parentJoint])
        etree.SubElement(joint, "child", link=frame.name)
    etree.indent(robot_element, space="  ")
    text = etree.tostring(robot_element, xml_declaration=True, encoding="UTF-8") + b"\n"
    return with_closures_sha256(text, closures_sha256)


def _joint_links(model: pin.Model) -> dict[int, str]:
    """The link of each joint: the BODY frame at the identity on it, else a new name."""
    taken = {frame.name for frame in model.frames}
    links = {}
    for j in range(model.njoints):
        on_joint = [
            f.name
            for f in model.frames
            if f.parentJoint == j
            and f.type == pin.FrameType.BODY
            and _placement_distance(f.placement, pin.SE3.Identity()) <= IDENTITY_TOLERANCE
        ]
        fallback = "world" if j == 0 else f"{model.names[j]}_link"
        while not on_joint and fallback in taken:
            fallback += "_"
        links[j] = on_joint[0] if on_joint else fallback
    return links


def _moving_joint(robot: etree._Element, model: pin.Model, data: pin.Data, j: int, links: dict[int, str]) -> None:
    subspace = np.asarray(data.joints[j].S).reshape(6)
    prismatic = float(np.linalg.norm(subspace[:3])) > 0.5
    k = model.idx_qs[j]
    lower, upper = float(model.lowerPositionLimit[k]), float(model.upperPositionLimit[k])
    bounded = np.isfinite(lower) and np.isfinite(upper) and lower < upper
    kind = "prismatic" if prismatic else ("revolute" if bounded else "continuous")
    joint = etree.SubElement(robot, "joint", name=model.names[j], type=kind)
    etree.SubElement(joint, "origin", **_origin_attributes(model.jointPlacements[j]))
    etree.SubElement(joint, "parent", link=links[model.parents[j]])
    etree.SubElement(joint, "child", link=links[j])
    axis = subspace[:3] if prismatic else subspace[3:]
    etree.SubElement(joint, "axis", xyz=" ".join(format_float(float(v) + 0.0) for v in axis))

    def finite(value: float) -> str:
        return format_float(value) if np.isfinite(value) else "0"

    limit = {
        "effort": finite(float(model.effortLimit[model.idx_vs[j]])),
        "velocity": finite(float(model.velocityLimit[model.idx_vs[j]])),
    }
    if bounded:
        limit.update(lower=format_float(lower), upper=format_float(upper))
    if kind != "continuous" or bounded:
        etree.SubElement(joint, "limit", **limit)


def _inertial(link: etree._Element, inertia: pin.Inertia) -> None:
    if inertia.mass <= 0.0:
        return
    element = etree.SubElement(link, "inertial")
    etree.SubElement(element, "origin", xyz=" ".join(format_float(float(v) + 0.0) for v in inertia.lever), rpy="0 0 0")
    etree.SubElement(element, "mass", value=format_float(float(inertia.mass)))
    matrix = np.asarray(inertia.inertia)
    entries = {"ixx": (0, 0), "ixy": (0, 1), "ixz": (0, 2), "iyy": (1, 1), "iyz": (1, 2), "izz": (2, 2)}
    etree.SubElement(
        element, "inertia", **{key: format_float(float(matrix[i, j]) + 0.0) for key, (i, j) in entries.items()}
    )
