"""The nominal design of the M-shaped 3T1R machine and the generator of its model files.

One source for every number: `MechanismDesign` holds the paper's dimensions and the design
choices explained in `docs/design.md` ("The mechanism"); `build_urdf` and `build_closures` turn it into the
URDF (four open chains from `base`) and the closures file. `models/generate.py` writes both.

Geometry (base frame B at rail-axis height, z up, SI units):
- rail I along y at x = 0, rail II at x = b; sliders B1, B2 on rail I, B3, B4 on rail II;
- chain B1 follows the paper's eq. (5): T_B,11 = transl(0, 0.03, 0), prismatic y (q11); upper
  crank about x (q12, home alpha); T_12,13 = [Rx(-alpha), (0, l_u, 0)]; lower crank about y
  (q13, home beta); T_13,14 = [Ry(-beta), (l_d, 0, 0)]; platform hinge about z (q14);
  T_14,P = transl(a/2, 0, 0);
- each of the paper's "equivalent" revolute joints q_i2, q_i3 is a parallelogram: the crank, a
  dependent coupling joint (q12_pa = alpha - q12 at the paper's T_12,13) that keeps the knee
  level, and a second bar hinged at a fixed offset, closed by a 3D point closure;
- B2 carries a plain link of length l_u hinged about x at the slider and at the knee D1;
- chain B3 mirrors B1 about x = b/2 and ends in a massless copy of the platform; the 6D
  platform closure welds P_I to P_II.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = ["MechanismDesign", "WorkspaceBox", "NOMINAL", "IDLE_CHAIN_JOINTS", "build_urdf", "build_closures"]


@dataclass(frozen=True)
class WorkspaceBox:
    """Axis-aligned box of platform poses (P in base frame B; yaw theta about z), SI units."""

    x: tuple[float, float] = (0.40, 0.60)
    y: tuple[float, float] = (0.225, 0.825)
    z: tuple[float, float] = (-0.211, -0.011)
    theta: tuple[float, float] = (-math.pi / 4, math.pi / 4)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Return n uniform samples as rows (x, y, z, theta) [m, m, m, rad]."""
        lo = np.array([self.x[0], self.y[0], self.z[0], self.theta[0]])
        hi = np.array([self.x[1], self.y[1], self.z[1], self.theta[1]])
        return lo + (hi - lo) * rng.random((n, 4))


@dataclass(frozen=True)
class MechanismDesign:
    """Nominal dimensions [m, rad] of the machine (paper section 6 plus the choices of docs/design.md)."""

    l_u: float = 0.7  # upper link length (slider hinge to knee D)
    l_d: float = 0.7  # lower link length (knee D to foot A)
    a: float = 0.3  # platform hinge distance |A1 A2|
    b: float = 1.0  # rail spacing
    rail_y0: float = 0.03  # y of slider B1 (B3) at zero stroke: T_B,11 = transl(0, 0.03, 0)
    alpha: float = math.pi / 4  # home angle of the upper links (best-conditioned home)
    upper_bar_offset: float = 0.08  # distance between the two bars of an upper parallelogram
    lower_bar_offset: float = 0.06  # same for a lower parallelogram
    slider_limit: float = 0.6  # |stroke| allowed by the URDF limits; the workspace box needs 0.584
    workspace: WorkspaceBox = field(default_factory=WorkspaceBox)

    @property
    def beta(self) -> float:
        """Home angle of the lower links: the centred home closes iff cos(beta) = (b - a) / (2 l_d)."""
        return math.acos((self.b - self.a) / (2.0 * self.l_d))

    @property
    def b2_rail_y(self) -> float:
        """y of slider B2 (B4) at zero stroke, so that the home five-bar is symmetric."""
        return self.rail_y0 + 2.0 * self.l_u * math.cos(self.alpha)

    def upper_offset_vector(self) -> np.ndarray:
        """Second-bar hinge offset of an upper parallelogram, in the slider frame.

        Perpendicular to the crank at home, so the parallelogram stays far from its flat
        (singular) shape over the whole crank range of the workspace.
        """
        return self.upper_bar_offset * np.array([0.0, -math.sin(self.alpha), math.cos(self.alpha)])

    def lower_offset_vector(self, side: int) -> np.ndarray:
        """Second-bar hinge offset of a lower parallelogram in the knee frame (side 1 or 2)."""
        sign = 1.0 if side == 1 else -1.0
        return self.lower_bar_offset * np.array([sign * math.sin(self.beta), 0.0, math.cos(self.beta)])

    def home(self) -> dict[str, float]:
        """Joint values [m, rad] of the assembled home pose (all sliders at zero stroke)."""
        q = {}
        for side, roman in ((1, "I"), (2, "II")):
            s = str(side)
            lower = self.beta if side == 1 else math.pi - self.beta
            q.update(
                {
                    f"q{s}1": 0.0,
                    f"q{s}2": self.alpha,
                    f"q{s}2_pa": 0.0,
                    f"q{s}2_bar": self.alpha,
                    f"q{s}3": lower,
                    f"q{s}3_pa": 0.0,
                    f"q{s}3_bar": lower,
                    f"q{s}4": 0.0,
                    f"q{s}1_B{2 * side}": 0.0,
                    f"q{s}2_B{2 * side}": math.pi - self.alpha,
                }
            )
        return q


NOMINAL = MechanismDesign()

# The hinges of the idle sub-branches B2 and B4 (paper section 2.4: the pair not used by its
# two-chain model, "used for cross-validation").
IDLE_CHAIN_JOINTS = ("q12_B2", "q22_B4")

# Visual style: one material per kind of body.
_MATERIALS = {
    "rail": (0.35, 0.35, 0.38, 1.0),
    "slider": (0.15, 0.35, 0.75, 1.0),
    "upper": (0.85, 0.55, 0.10, 1.0),
    "lower": (0.20, 0.65, 0.30, 1.0),
    "joint": (0.25, 0.25, 0.25, 1.0),
    "platform": (0.75, 0.15, 0.15, 1.0),
}


def _fmt(values: np.ndarray | tuple[float, ...]) -> str:
    return " ".join(format(float(v), ".17g") for v in values)


class _UrdfBuilder:
    def __init__(self, name: str) -> None:
        self.root = ET.Element("robot", name=name)
        self.root.append(ET.Comment(" Generated by models/generate.py from m3t1r.design: do not edit by hand. "))
        for mat, rgba in _MATERIALS.items():
            ET.SubElement(ET.SubElement(self.root, "material", name=mat), "color", rgba=_fmt(rgba))

    def link(self, name: str, visuals: Sequence[tuple[str, dict[str, str], tuple, tuple, str]] = ()) -> None:
        """visuals: (shape, shape attributes, xyz, rpy, material)."""
        link = ET.SubElement(self.root, "link", name=name)
        for shape, attrs, xyz, rpy, material in visuals:
            visual = ET.SubElement(link, "visual")
            ET.SubElement(visual, "origin", xyz=_fmt(xyz), rpy=_fmt(rpy))
            ET.SubElement(ET.SubElement(visual, "geometry"), shape, attrs)
            ET.SubElement(visual, "material", name=material)

    def joint(
        self,
        name: str,
        kind: str,
        parent: str,
        child: str,
        xyz,
        rpy=(0.0, 0.0, 0.0),
        axis=None,
        limits: tuple[float, float] | None = None,
    ) -> None:
        joint = ET.SubElement(self.root, "joint", name=name, type=kind)
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=child)
        ET.SubElement(joint, "origin", xyz=_fmt(xyz), rpy=_fmt(rpy))
        if axis is not None:
            ET.SubElement(joint, "axis", xyz=_fmt(axis))
        if limits is not None:
            ET.SubElement(joint, "limit", lower=_fmt(limits[:1]), upper=_fmt(limits[1:]), effort="1000", velocity="3")

    def point(self, name: str, parent: str, xyz, rpy=(0.0, 0.0, 0.0)) -> None:
        """A massless, geometry-free link on a fixed joint: a named frame for closures and measurements."""
        self.link(name)
        self.joint(f"{name}_fixed", "fixed", parent, name, xyz, rpy)

    def text(self) -> str:
        ET.indent(self.root, space="  ")
        return '<?xml version="1.0"?>\n' + ET.tostring(self.root, encoding="unicode") + "\n"


def _bar_visual(length: float, along: str, material: str, radius: float = 0.012):
    """A cylinder from the frame origin to `length` along local `along` (URDF cylinders lie along z)."""
    if along == "y":
        return (
            "cylinder",
            {"radius": _fmt((radius,)), "length": _fmt((length,))},
            (0.0, length / 2, 0.0),
            (-math.pi / 2, 0.0, 0.0),
            material,
        )
    return (
        "cylinder",
        {"radius": _fmt((radius,)), "length": _fmt((length,))},
        (length / 2, 0.0, 0.0),
        (0.0, math.pi / 2, 0.0),
        material,
    )


def _box(size, material: str, xyz=(0.0, 0.0, 0.0)):
    return ("box", {"size": _fmt(size)}, xyz, (0.0, 0.0, 0.0), material)


def build_urdf(design: MechanismDesign = NOMINAL) -> str:
    """Return the URDF text: four open chains from `base`, one per actuator, at zero joint values.

    Joint names follow the paper: q_ij is joint j of principal chain i (B1: i = 1, B3: i = 2);
    `_pa` marks a parallelogram's coupling joint, `_bar` its second bar; q11_B2, q12_B2 (q21_B4,
    q22_B4) are the slider and link hinge of sub-branch B2 (B4). Zero joint values are not the
    assembled home: `design.home()` is.
    """
    d = design
    u = _UrdfBuilder("m3t1r")
    half_pi = math.pi / 2
    rail_len = 2 * d.slider_limit + d.b2_rail_y + 0.2
    u.link(
        "base",
        [
            _box((0.04, rail_len, 0.04), "rail", (0.0, d.b2_rail_y / 2 + d.rail_y0 / 2, 0.0)),
            _box((0.04, rail_len, 0.04), "rail", (d.b, d.b2_rail_y / 2 + d.rail_y0 / 2, 0.0)),
        ],
    )
    for side, roman in ((1, "I"), (2, "II")):
        s = str(side)
        x_rail = 0.0 if side == 1 else d.b
        lower_home = d.beta if side == 1 else math.pi - d.beta
        # T_13,14 rotation: Ry(-beta) on side I, Ry(pi + beta) on side II (paper section 6).
        lower_tip_pitch = -d.beta if side == 1 else math.pi + d.beta
        platform_dx = d.a / 2 if side == 1 else -d.a / 2
        slider_limits = (-d.slider_limit, d.slider_limit)

        # Principal chain B1 (B3).
        slider, upper, knee, upper2 = (
            f"slider_B{2 * side - 1}",
            f"upper_bar_{roman}",
            f"knee_{roman}",
            f"upper_bar2_{roman}",
        )
        lower, foot, lower2 = f"lower_bar_{roman}", f"foot_{roman}", f"lower_bar2_{roman}"
        platform = "platform" if side == 1 else "platform_II"
        o_u = d.upper_offset_vector()
        o_d = d.lower_offset_vector(side)
        u.link(slider, [_box((0.08, 0.12, 0.06), "slider")])
        u.joint(f"q{s}1", "prismatic", "base", slider, (x_rail, d.rail_y0, 0.0), axis=(0, 1, 0), limits=slider_limits)
        u.link(upper, [_bar_visual(d.l_u, "y", "upper")])
        u.joint(
            f"q{s}2",
            "revolute",
            slider,
            upper,
            (0, 0, 0),
            axis=(1, 0, 0),
            limits=(d.alpha - half_pi, d.alpha + half_pi),
        )
        u.link(knee, [_box((0.06, 0.06, 0.06), "joint")])
        u.joint(
            f"q{s}2_pa",
            "revolute",
            upper,
            knee,
            (0.0, d.l_u, 0.0),
            (-d.alpha, 0.0, 0.0),
            axis=(1, 0, 0),
            limits=(-half_pi, half_pi),
        )
        u.link(upper2, [_bar_visual(d.l_u, "y", "upper", radius=0.008)])
        u.joint(
            f"q{s}2_bar", "revolute", slider, upper2, o_u, axis=(1, 0, 0), limits=(d.alpha - half_pi, d.alpha + half_pi)
        )
        u.point(f"upper_tip_{roman}", upper2, (0.0, d.l_u, 0.0), (-d.alpha, 0.0, 0.0))
        u.point(f"upper_pt_{roman}", knee, o_u)
        u.point(f"D_{roman}", knee, (0.0, 0.0, 0.0))

        u.link(lower, [_bar_visual(d.l_d, "x", "lower")])
        u.joint(
            f"q{s}3",
            "revolute",
            knee,
            lower,
            (0, 0, 0),
            axis=(0, 1, 0),
            limits=(lower_home - half_pi, lower_home + half_pi),
        )
        u.link(foot, [_box((0.05, 0.05, 0.05), "joint")])
        u.joint(
            f"q{s}3_pa",
            "revolute",
            lower,
            foot,
            (d.l_d, 0.0, 0.0),
            (0.0, lower_tip_pitch, 0.0),
            axis=(0, 1, 0),
            limits=(-half_pi, half_pi),
        )
        u.link(lower2, [_bar_visual(d.l_d, "x", "lower", radius=0.008)])
        u.joint(
            f"q{s}3_bar",
            "revolute",
            knee,
            lower2,
            o_d,
            axis=(0, 1, 0),
            limits=(lower_home - half_pi, lower_home + half_pi),
        )
        u.point(f"lower_tip_{roman}", lower2, (d.l_d, 0.0, 0.0), (0.0, lower_tip_pitch, 0.0))
        u.point(f"lower_pt_{roman}", foot, o_d)

        # Chain B3 ends in a massless, invisible copy of the platform, welded by the 6D closure.
        u.link(platform, [_box((d.a + 0.06, 0.10, 0.02), "platform", (d.a / 2, 0.0, -0.01))] if side == 1 else [])
        u.joint(f"q{s}4", "revolute", foot, platform, (0, 0, 0), axis=(0, 0, 1), limits=(-half_pi, half_pi))
        u.point(f"P_{roman}", platform, (platform_dx, 0.0, 0.0))

        # Sub-branch B2 (B4): a plain link from its slider to the knee, one side of the five-bar.
        slider_b, link_b = f"slider_B{2 * side}", f"link_B{2 * side}"
        u.link(slider_b, [_box((0.08, 0.12, 0.06), "slider")])
        u.joint(
            f"q{s}1_B{2 * side}",
            "prismatic",
            "base",
            slider_b,
            (x_rail, d.b2_rail_y, 0.0),
            axis=(0, 1, 0),
            limits=slider_limits,
        )
        u.link(link_b, [_bar_visual(d.l_u, "y", "upper")])
        u.joint(
            f"q{s}2_B{2 * side}",
            "revolute",
            slider_b,
            link_b,
            (0, 0, 0),
            axis=(1, 0, 0),
            limits=(math.pi - d.alpha - half_pi, math.pi - d.alpha + half_pi),
        )
        u.point(f"fivebar_tip_{roman}", link_b, (0.0, d.l_u, 0.0), (-(math.pi - d.alpha), 0.0, 0.0))
    return u.text()


def build_closures(design: MechanismDesign = NOMINAL) -> dict:
    """Return the closures document (schema in models/README.md) for `build_urdf(design)`.

    Only the 16 independent rows are enforced (docs/design.md, "The mechanism"): a planar loop's residual along its
    cut axis, and the platform weld's roll and pitch, hold by themselves at the nominal geometry
    and cannot all hold on a machine with manufacturing errors.
    """
    closures = []
    for roman in ("I", "II"):
        closures += [
            {
                "name": f"upper_parallelogram_{roman}",
                "type": "3D",
                "frame_a": f"upper_tip_{roman}",
                "frame_b": f"upper_pt_{roman}",
                "rows": [1, 2],
            },
            {
                "name": f"five_bar_{roman}",
                "type": "3D",
                "frame_a": f"fivebar_tip_{roman}",
                "frame_b": f"D_{roman}",
                "rows": [1, 2],
            },
            {
                "name": f"lower_parallelogram_{roman}",
                "type": "3D",
                "frame_a": f"lower_tip_{roman}",
                "frame_b": f"lower_pt_{roman}",
                "rows": [0, 2],
            },
        ]
    closures.append({"name": "platform", "type": "6D", "frame_a": "P_I", "frame_b": "P_II", "rows": [0, 1, 2, 5]})
    box = design.workspace
    return {
        "schema_version": 2,
        "actuated_joints": ["q11", "q11_B2", "q21", "q21_B4"],
        "closures": closures,
        "principal_chains": {
            "B1": ["q11", "q12", "q12_pa", "q13", "q13_pa", "q14", "P_I"],
            "B3": ["q21", "q22", "q22_pa", "q23", "q23_pa", "q24", "P_II"],
        },
        "platform_frame": "P_I",
        "task": {"frame": "P_I", "position": ["x", "y", "z"], "rotation": "yaw"},
        "workspace": {"task": {"x": list(box.x), "y": list(box.y), "z": list(box.z), "yaw": list(box.theta)}},
        "home": {name: float(value) for name, value in design.home().items()},
    }
