"""Meshcat scenes comparing machines: the nominal description next to a calibrated one.

Every machine is drawn by Pinocchio's `MeshcatVisualizer` under its own scene node,
`/meshcat/m3t1r/<name>` (geometry in `.../visuals`, the platform frame as an RGB triad in
`.../platform_frame`); measured poses, when given, are small spheres under
`/meshcat/m3t1r/measurements`. All machines are posed at one command:

- `pose=(x, y, z, theta)`: inverse kinematics on each machine, so each shows the slider values
  *it* needs to reach that platform pose (what compensation does);
- `sliders=(...)`: forward kinematics on each machine, so each shows where *it* puts the
  platform for the same slider values (what the machine does without compensation);
- neither: each machine at its own assembled `home` configuration.

Roll and pitch cannot be commanded (3T1R): they are whatever each machine's geometry gives.

A calibrated machine differs from its nominal by millimetres, invisible at the metre scale of the
machine: every machine after the first is drawn with its deviation from the first magnified by a
stated factor (`magnified_placement`): each body is drawn at its joint's nominal position plus
`factor` times its offset, turned by `factor` times its rotation deviation. By default the factor is
chosen from the scene (`automatic_magnification`: the largest offset drawn as a tenth of the
machine's size, 1 mm as 0.1 m on a metre-sized machine). The poses and slider values the page's
legend states are the true ones.
The camera orbits the machine, not the base origin: meshcat 0.3.2 cannot move its orbit centre,
so the scene (with the grid and axes) is shifted by -`Camera.target` instead; transforms below
`/meshcat/m3t1r` are still base-frame placements.

A scene is first recorded offline, without any server: the meshcat commands are kept in memory.
That recording becomes a self-contained HTML page (`write_static_html`: the viewer's bundled
JavaScript and every command are inlined, nothing is fetched) or is replayed into a live meshcat
server (`open_viewer`), whose process this module starts and stops itself.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, TypeAlias

import numpy as np
import pinocchio as pin

with warnings.catch_warnings():
    # meshcat 0.3.2 imports pyzmq's deprecated zmq.eventloop.ioloop; nothing we can act on.
    warnings.simplefilter("ignore", DeprecationWarning)
    import meshcat
    import meshcat.geometry as mg
    from pinocchio.visualize import MeshcatVisualizer


from m3t1r.errors import InvalidInputError, KinematicsError, M3t1rError, require_finite_vector
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver

__all__ = [
    "ROOT_NODE",
    "MEASUREMENTS_NODE",
    "NOMINAL_COLOR",
    "CALIBRATED_COLOR",
    "MARKER_COLOR",
    "MachineView",
    "Camera",
    "DEFAULT_CAMERA",
    "PosedMachine",
    "ViewerError",
    "comparison_views",
    "pose_machines",
    "magnified_placement",
    "check_magnification",
    "automatic_magnification",
]


Rgba: TypeAlias = "tuple[float, float, float, float]"

ROOT_NODE = "m3t1r"
"""Every node of ours lives under `/meshcat/m3t1r`, away from meshcat's own Lights, Grid, Cameras."""
MEASUREMENTS_NODE = f"{ROOT_NODE}/measurements"

NOMINAL_COLOR: Rgba | None = None  # the URDF's own materials
CALIBRATED_COLOR: Rgba = (0.85, 0.1, 0.75, 0.55)
"""Translucent magenta: no URDF material is close to it, and the nominal machine shows through."""
MARKER_COLOR: Rgba = (1.0, 0.8, 0.0, 1.0)
MARKER_RADIUS = 0.012  # [m] visible at the whole-machine scale, small next to the 0.1 m platform
TRIAD_LENGTH = 0.15  # [m] sticks out of the platform box so the axes stay visible
TRIAD_THICKNESS = 0.008  # [m] WebGL ignores line widths, so the axes are thin boxes, not lines
MAGNIFIED_SHARE = 0.1  # the largest offset drawn as this share of the machine's size
MAGNIFIED_ANGLE = 0.3  # [rad] and no body turned further: beyond, the magnified machine is a tangle
MAX_MAGNIFICATION = 1000.0  # 1 um drawn as 1 mm: below that a deviation is noise to look at
_BACKGROUND = ((0.96, 0.96, 0.98), (0.74, 0.77, 0.82))  # light, so every material colour stands out
_NAME = re.compile(r"[A-Za-z0-9_.-]+")  # one scene-node path element, safe in HTML too


class ViewerError(M3t1rError):
    """meshcat cannot be used: its server process did not start, or its viewer bundle is missing."""


@dataclass(frozen=True, eq=False)
class MachineView:
    """One machine in a scene: its node name, its description, and how it is coloured.

    name: the scene node under `/meshcat/m3t1r/` (letters, digits, `_`, `.`, `-`);
    color: RGBA in [0, 1] applied to every visual, or None to keep the URDF materials.
    An alpha below 1 makes the machine translucent, so another one shows through it.
    """

    name: str
    mechanism: Mechanism
    color: Rgba | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _NAME.fullmatch(self.name):
            raise InvalidInputError(
                f"machine name {self.name!r}: use letters, digits, '_', '.' or '-' (it becomes a meshcat scene node)"
            )
        if self.name == MEASUREMENTS_NODE.rsplit("/", 1)[1]:
            raise InvalidInputError(f"machine name '{self.name}' is reserved for the measured poses")
        if not isinstance(self.mechanism, Mechanism):
            raise InvalidInputError(f"machine '{self.name}': expected a Mechanism, got {type(self.mechanism).__name__}")
        if self.color is not None:
            rgba = require_finite_vector(self.color, 4, f"colour of machine '{self.name}' (r, g, b, a)")
            if np.any((rgba < 0.0) | (rgba > 1.0)):
                raise InvalidInputError(
                    f"colour of machine '{self.name}': components must be in [0, 1], got {tuple(rgba)}"
                )
            object.__setattr__(self, "color", tuple(float(c) for c in rgba))

    @property
    def node(self) -> str:
        """Absolute meshcat path of this machine's node."""
        return f"/meshcat/{ROOT_NODE}/{self.name}"


@dataclass(frozen=True)
class Camera:
    """Where the default camera looks from and at, in the base frame [m].

    The viewer's orbit controls turn around `target`, so a user rotating the view keeps the
    machine in the middle. For that the scene is drawn shifted by -target (see `_place_camera`).
    """

    position: tuple[float, float, float]
    target: tuple[float, float, float]

    def __post_init__(self) -> None:
        # Checked here, not when drawing, so a bad camera fails before any command is sent.
        position = require_finite_vector(self.position, 3, "camera position")
        target = require_finite_vector(self.target, 3, "camera target")
        if np.allclose(position, target):
            raise InvalidInputError("camera position and target coincide: no view direction")
        object.__setattr__(self, "position", tuple(float(v) for v in position))
        object.__setattr__(self, "target", tuple(float(v) for v in target))


DEFAULT_CAMERA = Camera(position=(1.6, -1.2, 1.0), target=(0.5, 0.5, 0.1))
"""Three-quarter view from the front right: both rails (along y at x = 0 and x = 1), the knees
(z about 0.5) and the platform (z about -0.1) are all in sight and the M of the legs reads."""


@dataclass(frozen=True, eq=False)
class PosedMachine:
    """A machine assembled at the scene's command: full configuration and platform pose."""

    view: MachineView
    q: np.ndarray
    platform: pin.SE3

    @property
    def sliders(self) -> np.ndarray:
        """Actuated joint values [m] in `actuated_joints` order."""
        return self.q[self.view.mechanism.actuated_ids].copy()


def comparison_views(nominal: Mechanism, calibrated: Mechanism | None = None) -> tuple[MachineView, ...]:
    """The usual pair: `nominal` in its URDF colours and `calibrated` in translucent magenta."""
    views = [MachineView("nominal", nominal, NOMINAL_COLOR)]
    if calibrated is not None:
        views.append(MachineView("calibrated", calibrated, CALIBRATED_COLOR))
    return tuple(views)


# --------------------------------------------------------------------------------------------
# Posing
# --------------------------------------------------------------------------------------------


def pose_machines(
    views: Sequence[MachineView], pose: Sequence[float] | None = None, sliders: Sequence[float] | None = None
) -> tuple[PosedMachine, ...]:
    """Assemble every machine at one command (see the module docstring for the three modes).

    pose: task coordinates (`TaskSpec.columns`; the M machine's x, y, z, theta [m, m, m, rad]),
    reached by IK on each machine;
    sliders: actuated joint values [m], applied by FK on each machine. At most one of them.
    Both solves start from each machine's home, so every machine is on its home branch.

    Raises InvalidInputError (no machine, duplicate names, machines whose joints differ, both
    commands given, a malformed command, sliders beyond one machine's limits: naming it) and the
    KinematicsError subclass of a failed solve, its message prefixed with the machine's name.
    """
    views = _check_views(views)
    if pose is not None and sliders is not None:
        raise InvalidInputError("give the platform pose or the slider values, not both")
    task = views[0].mechanism.task
    target = (
        None
        if pose is None
        else require_finite_vector(pose, len(task.columns), f"task pose ({', '.join(task.columns)})")
    )
    inputs = (
        None
        if sliders is None
        else require_finite_vector(sliders, len(views[0].mechanism.actuated_joints), "slider values")
    )
    posed = []
    for view in views:
        mechanism = view.mechanism
        try:
            if target is not None:
                q = ClosedLoopSolver(mechanism).inverse(target, q_init=mechanism.home).q
            elif inputs is not None:
                q = ClosedLoopSolver(mechanism).forward(inputs, q_init=mechanism.home).q
            else:
                q = mechanism.home.copy()
        except KinematicsError as exc:
            raise _for_machine(exc, view.name) from exc
        except InvalidInputError as exc:
            raise InvalidInputError(f"machine '{view.name}': {exc}") from exc
        data = mechanism.model.createData()
        pin.framesForwardKinematics(mechanism.model, data, q)
        posed.append(PosedMachine(view, q, pin.SE3(data.oMf[mechanism.platform_frame_id])))
    return tuple(posed)


def _for_machine(exc: KinematicsError, name: str) -> KinematicsError:
    # Same class, so callers catching OutOfWorkspaceError & co. still do; the base class appends
    # the residual to the message, so it is taken off before being appended again.
    suffix = f" (residual {exc.residual:.3e} after {exc.iterations} iterations)"
    message = str(exc).removesuffix(suffix)
    return type(exc)(f"machine '{name}': {message}", exc.residual, exc.iterations)


def _check_views(views: Sequence[MachineView]) -> tuple[MachineView, ...]:
    views = tuple(views)
    if not views:
        raise InvalidInputError("no machine to show")
    for view in views:
        if not isinstance(view, MachineView):
            raise InvalidInputError(f"expected MachineView objects, got {type(view).__name__}")
    names = [view.name for view in views]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise InvalidInputError(f"machine names must be unique, repeated: {', '.join(repeated)}")
    first = views[0]
    reference = set(first.mechanism.model.names[1:])
    for view in views[1:]:
        joints = set(view.mechanism.model.names[1:])
        if joints != reference:
            missing, extra = sorted(reference - joints), sorted(joints - reference)
            raise InvalidInputError(
                f"machines '{first.name}' and '{view.name}' have different joints: "
                f"only in '{first.name}': {', '.join(missing) or 'none'}; "
                f"only in '{view.name}': {', '.join(extra) or 'none'} "
                f"({first.mechanism.urdf_path} vs {view.mechanism.urdf_path})"
            )
        if view.mechanism.actuated_joints != first.mechanism.actuated_joints:
            # The same slider vector must mean the same joints on every machine.
            raise InvalidInputError(
                f"machines '{first.name}' and '{view.name}' actuate different joints: "
                f"{', '.join(first.mechanism.actuated_joints)} vs {', '.join(view.mechanism.actuated_joints)}"
            )
    return views


def check_magnification(factor: float) -> float:
    """`factor` as a float, or InvalidInputError when it is not a finite number of at least 1."""
    value = float(require_finite_vector([factor], 1, "magnification")[0])
    if value < 1.0:
        raise InvalidInputError(f"magnification {value:g}: at least 1 (1 draws the machines at true scale)")
    return value


def magnified_placement(reference: pin.SE3, actual: pin.SE3, factor: float) -> pin.SE3:
    """`actual` with its deviation from `reference` multiplied by `factor` (both in the base frame [m]).

    Position: p_ref + factor (p - p_ref); rotation: R_ref exp(factor log(R_ref^T R)), the deviation
    taken in the reference body's frame. factor 1 returns `actual`.
    """
    rotation = reference.rotation @ pin.exp3(factor * pin.log3(reference.rotation.T @ actual.rotation))
    return pin.SE3(rotation, reference.translation + factor * (actual.translation - reference.translation))


def automatic_magnification(posed: Sequence[PosedMachine]) -> float:
    """The factor that draws the largest joint offset of the machines after the first from it as
    `MAGNIFIED_SHARE` of the first machine's size (the diagonal of its joints' bounding box [m]), no
    joint turned beyond `MAGNIFIED_ANGLE`: rounded down to 1, 2 or 5 times a power of ten, within
    [1, `MAX_MAGNIFICATION`]. 1 for a single machine or machines that coincide."""
    reference = _joint_placements(posed[0])
    size = float(np.linalg.norm(np.ptp([m.translation for m in reference.values()], axis=0))) if reference else 0.0
    offset = angle = 0.0
    for machine in posed[1:]:
        for name, placement in _joint_placements(machine).items():
            offset = max(offset, float(np.linalg.norm(placement.translation - reference[name].translation)))
            angle = max(angle, float(np.linalg.norm(pin.log3(reference[name].rotation.T @ placement.rotation))))
    limits = [
        share / value for share, value in ((MAGNIFIED_SHARE * size, offset), (MAGNIFIED_ANGLE, angle)) if value > 0
    ]
    if not limits:
        return 1.0
    factor = min(min(limits), MAX_MAGNIFICATION)
    decade = 10.0 ** math.floor(math.log10(factor))
    return max(1.0, max(step * decade for step in (1.0, 2.0, 5.0) if step * decade <= factor * (1 + 1e-12)))


def _joint_placements(machine: PosedMachine) -> dict[str, pin.SE3]:
    """Every joint's placement in the base frame [m] at the machine's configuration, by joint name."""
    model = machine.view.mechanism.model
    data = model.createData()
    pin.forwardKinematics(model, data, machine.q)
    return {model.names[j]: pin.SE3(data.oMi[j]) for j in range(1, model.njoints)}


def _magnified_joints(reference: PosedMachine, machine: PosedMachine, data: pin.Data, factor: float) -> None:
    """Replace `data.oMi` (the machine's joint placements at its configuration) by their magnified
    deviation from the reference machine's joints of the same names."""
    joints = _joint_placements(reference)
    model = machine.view.mechanism.model
    for j in range(1, model.njoints):
        data.oMi[j] = magnified_placement(joints[model.names[j]], data.oMi[j], factor)


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


class _Lowered:
    """A command already lowered to its message form, so a recording can be sent again."""

    __slots__ = ("message",)

    def __init__(self, message: dict[str, Any]) -> None:
        self.message = message

    def lower(self) -> dict[str, Any]:
        return self.message


def _draw(
    viewer: meshcat.Visualizer,
    posed: Sequence[PosedMachine],
    points: np.ndarray,
    camera: Camera | None,
    magnification: float = 1.0,
) -> None:
    """Draw the machines (those after the first with their deviation from it magnified), the markers
    as measured, and place the camera."""
    viewer["/Background"].set_property("top_color", list(_BACKGROUND[0]))
    viewer["/Background"].set_property("bottom_color", list(_BACKGROUND[1]))
    for machine in posed:
        view, mechanism = machine.view, machine.view.mechanism
        drawer = MeshcatVisualizer(mechanism.model, None, mechanism.visual_model)
        drawer.initViewer(viewer=viewer)
        node = f"{ROOT_NODE}/{view.name}"
        drawer.loadViewerModel(rootNodeName=node, visual_color=None if view.color is None else list(view.color))
        drawer.display(machine.q)
        platform = machine.platform
        if machine is not posed[0] and magnification != 1.0:
            _magnified_joints(posed[0], machine, drawer.data, magnification)
            drawer.updatePlacements(pin.GeometryType.VISUAL)  # from data.oMi as magnified, no new FK
            platform = magnified_placement(posed[0].platform, platform, magnification)
        _draw_triad(viewer[f"{node}/platform_frame"], platform)
    for k, point in enumerate(points):
        marker = viewer[f"{MEASUREMENTS_NODE}/pose_{k:04d}"]
        marker.set_object(mg.Sphere(MARKER_RADIUS), _material(MARKER_COLOR))
        marker.set_transform(pin.SE3(np.eye(3), point).homogeneous)
    if camera is not None:
        _place_camera(viewer, camera)


def _material(rgba: Rgba) -> mg.MeshPhongMaterial:
    r, g, b, a = rgba
    color = (int(round(r * 255)) << 16) | (int(round(g * 255)) << 8) | int(round(b * 255))
    if a < 1.0:
        return mg.MeshPhongMaterial(color=color, transparent=True, opacity=a)
    return mg.MeshPhongMaterial(color=color)


def _draw_triad(node: meshcat.Visualizer, placement: pin.SE3) -> None:
    node.set_transform(placement.homogeneous)
    for axis, name in enumerate("xyz"):
        size = [TRIAD_THICKNESS] * 3
        size[axis] = TRIAD_LENGTH
        offset = np.eye(4)
        offset[axis, 3] = TRIAD_LENGTH / 2  # the box starts at the frame origin
        rgba = (float(axis == 0), float(axis == 1), float(axis == 2), 1.0)
        node[name].set_object(mg.Box(size), _material(rgba))
        node[name].set_transform(offset)


def _place_camera(viewer: meshcat.Visualizer, camera: Camera) -> None:
    position, target = np.array(camera.position), np.array(camera.target)
    # meshcat 0.3.2's orbit controls always turn about the scene origin (no command moves their
    # target), so the target is brought to the origin instead: our root node, the grid and the
    # axes are all shifted by -target. Node transforms below /meshcat/m3t1r stay in the base
    # frame, and the grid and axes still mark the base frame's z = 0 plane and origin.
    shift = pin.SE3(np.eye(3), -target).homogeneous
    for node in (ROOT_NODE, "/Grid", "/Axes"):  # ours relative to the viewer, meshcat's absolute
        viewer[node].set_transform(shift)
    # The camera sits in a node rotated +90 deg about x (three.js is y-up, meshcat z-up), where
    # an offset (dx, dy, dz) from the target reads (dx, dz, -dy).
    offset = position - target
    viewer["/Cameras/default/rotated/<object>"].set_property(
        "position", [float(offset[0]), float(offset[2]), float(-offset[1])]
    )


def _marker_positions(markers: Iterable[pin.SE3] | np.ndarray | None) -> np.ndarray:
    if markers is None:
        return np.empty((0, 3))
    if isinstance(markers, np.ndarray):
        if markers.ndim != 2 or markers.shape[1] != 3:
            raise InvalidInputError(f"markers: expected an (n, 3) array of positions, got shape {markers.shape}")
        rows: object = markers
    else:
        rows = [item.translation if isinstance(item, pin.SE3) else item for item in markers]
    try:
        points = np.asarray(rows, dtype=float).reshape(-1, 3)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"markers: expected pin.SE3 poses or (n, 3) positions ({exc})") from None
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        raise InvalidInputError(f"markers: non-finite position at index {bad[0]}: {points[bad[0]]}")
    return points
