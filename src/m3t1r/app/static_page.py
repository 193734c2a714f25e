"""The static meshcat page: a scene recorded into one self-contained HTML file (no server, no network)."""

from __future__ import annotations

import base64
import html
import json
import math
import os
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import umsgpack

with warnings.catch_warnings():
    # meshcat 0.3.2 imports pyzmq's deprecated zmq.eventloop.ioloop; nothing we can act on.
    warnings.simplefilter("ignore", DeprecationWarning)
    import meshcat

from m3t1r.app.scene import (
    DEFAULT_CAMERA,
    Camera,
    MachineView,
    PosedMachine,
    ViewerError,
    _draw,
    _marker_positions,
    automatic_magnification,
    check_magnification,
    pose_machines,
)
from m3t1r.errors import InvalidInputError
from m3t1r.io.outputs import atomic_write_text
from m3t1r.io.paths import ensure_not_protected
from m3t1r.model.kinematics import yaw_of

__all__ = ["build_scene", "scene_html", "magnification_of", "write_static_html"]


# --------------------------------------------------------------------------------------------
# Recording a scene
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class _Recording:
    """Stands in for meshcat's `ViewerWindow`: keeps the commands instead of sending them.

    `meshcat.Visualizer(window=_Recording())` then builds a scene with no server and no socket;
    its `static_html()` returns the self-contained page.
    """

    messages: list[dict[str, Any]] = field(default_factory=list)
    legend: str = ""
    title: str = "m3t1r"
    magnification: float = 1.0  # the factor the scene was drawn with (the legend states it)
    web_url: str | None = None  # meshcat's Visualizer.url() reads it; there is no server

    def send(self, command: Any) -> None:
        self.messages.append(command.lower())

    def get_scene(self) -> str:
        return _page(self.messages, self.title, self.legend)


def build_scene(
    views: Sequence[MachineView],
    pose: Sequence[float] | None = None,
    sliders: Sequence[float] | None = None,
    markers: Iterable[pin.SE3] | np.ndarray | None = None,
    viewer: meshcat.Visualizer | None = None,
    camera: Camera | None = DEFAULT_CAMERA,
    magnification: float | None = None,
) -> meshcat.Visualizer:
    """Draw every machine, posed at one command, into `viewer` and return it.

    views: the machines, drawn in order (put the translucent ones last so the opaque ones show
    through them); pose / sliders: the command (see `pose_machines`); markers: measured platform
    poses (pin.SE3) or an (n, 3) array of positions [m], drawn as spheres; viewer: a meshcat
    Visualizer to draw into (a live one, say), or None for an offline recording whose
    `static_html()` is the shareable page; camera: the initial view, None to leave the viewer's;
    magnification: every machine after the first is drawn with its deviation from the first
    multiplied by this factor (>= 1; 1 for true scale; see `scene.magnified_placement`), None to
    choose it from the scene (`scene.automatic_magnification`); the factor is stated in the page's
    legend. Markers are drawn where they were measured.

    Every machine is solved before anything is drawn, so a failure leaves `viewer` untouched.
    Raises what `pose_machines` raises, and InvalidInputError for malformed markers or magnification.
    """
    posed = pose_machines(views, pose, sliders)
    magnification = automatic_magnification(posed) if magnification is None else check_magnification(magnification)
    points = _marker_positions(markers)
    if viewer is None:
        viewer = meshcat.Visualizer(
            window=_Recording(
                legend=_legend(posed, pose, sliders, magnification), title=_title(posed), magnification=magnification
            )
        )
    _draw(viewer, posed, points, camera, magnification)
    return viewer


# --------------------------------------------------------------------------------------------
# Static page
# --------------------------------------------------------------------------------------------


def _viewer_script() -> str:
    # The viewer bundle ships inside the meshcat Python package; it is read, never fetched.
    path = Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js"
    try:
        script = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ViewerError(f"meshcat's viewer bundle is unreadable at {path}: {exc}") from None
    if "</script" in script.lower():  # would end the inline <script> element early
        raise ViewerError(f"{path} contains '</script' and cannot be inlined")
    return script


def _page(messages: Sequence[dict[str, Any]], title: str, legend: str) -> str:
    # Commands are msgpack, base64-encoded and decoded synchronously in order: no fetch(), not
    # even of data: URLs, so the page works from file:// and offline in any browser.
    encoded = [base64.b64encode(umsgpack.packb(message)).decode("ascii") for message in messages]
    return _PAGE.format(
        title=html.escape(title),
        legend=legend,
        viewer=_viewer_script(),
        commands=json.dumps(encoded, separators=(",", ":")),
    )


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>
html, body {{ margin: 0; height: 100%; overflow: hidden; font: 13px/1.35 sans-serif; }}
#meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
#m3t1r-legend {{ position: absolute; left: 8px; bottom: 8px; padding: 6px 9px; max-width: 60vw;
  background: rgba(255, 255, 255, 0.85); border-radius: 4px; color: #222; }}
#m3t1r-legend .swatch {{ display: inline-block; width: 0.9em; height: 0.9em; margin-right: 0.4em;
  vertical-align: -0.1em; border: 1px solid #555; }}
</style>
</head>
<body>
<div id="meshcat-pane"></div>
<div id="m3t1r-legend">{legend}</div>
<script>
{viewer}
</script>
<script>
(function () {{
  var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
  var commands = {commands};
  for (var i = 0; i < commands.length; i++) {{
    var text = atob(commands[i]);
    var bytes = new Uint8Array(text.length);
    for (var k = 0; k < text.length; k++) bytes[k] = text.charCodeAt(k);
    viewer.handle_command_bytearray(bytes);
  }}
  window.viewer = viewer;
}})();
</script>
</body>
</html>
"""


def _task_text(columns: Sequence[str], values: Sequence[float]) -> str:
    """Task coordinates for people: positions in mm, the heading in degrees, a quaternion as is."""
    parts = []
    for name, value in zip(columns, values):
        if name in ("x", "y", "z"):
            parts.append(f"{name} {_fixed(float(value) * 1e3, 1)} mm")
        elif name == "theta":
            parts.append(f"&theta; {_fixed(math.degrees(float(value)), 2)}&deg;")
        else:
            parts.append(f"{name} {_fixed(float(value), 4)}")
    return ", ".join(parts)


def _actuator_text(mechanism, values: Sequence[float] | np.ndarray) -> str:
    """Prismatic actuators in mm, revolute ones in degrees."""
    model = mechanism.model
    prismatic = [
        model.joints[model.getJointId(name)].shortname().startswith("JointModelP") for name in mechanism.actuated_joints
    ]
    return ", ".join(_fixed(v * 1e3, 2) if slide else _fixed(math.degrees(v), 3) for v, slide in zip(values, prismatic))


def _title(posed: Sequence[PosedMachine]) -> str:
    return "m3t1r: " + " vs ".join(machine.view.name for machine in posed)


def _legend(
    posed: Sequence[PosedMachine],
    pose: Sequence[float] | None,
    sliders: Sequence[float] | None,
    magnification: float = 1.0,
) -> str:
    mechanism = posed[0].view.mechanism
    if pose is not None:
        command = f"task pose {_task_text(mechanism.task.columns, pose)} reached by IK on each machine"
    elif sliders is not None:
        command = "same actuator values on each machine (FK)"
    else:
        command = "each machine at its home configuration"
    names = ", ".join(html.escape(name) for name in mechanism.actuated_joints)
    lines = [f"<div>{command}; actuators ({names}) in mm or &deg;</div>"]
    if len(posed) > 1:
        first = html.escape(posed[0].view.name)
        scale = (
            "drawn at true scale"
            if magnification == 1.0
            else f"drawn with their deviation from {first} magnified &times;{magnification:g} "
            f"(every body's offset and rotation; the figures below are true values)"
        )
        lines.append(f'<div data-magnification="{magnification:g}">machines after {first} {scale}</div>')
    for machine in posed:
        view = machine.view
        if view.color is None:  # a strip of the URDF's main material colours
            swatch = "background: linear-gradient(90deg, #3a5cbf, #d98c1a, #33a64d, #bf2626)"
        else:
            r, g, b, a = view.color
            swatch = f"background: rgba({r * 255:.0f}, {g * 255:.0f}, {b * 255:.0f}, {a:.2f})"
        p = [_fixed(v * 1e3, 2) for v in machine.platform.translation]
        lines.append(
            f'<div data-node="{html.escape(view.node)}"><span class="swatch" style="{swatch}"></span>'
            f"<b>{html.escape(view.name)}</b> ({html.escape(view.mechanism.urdf_path.name)}): "
            f"platform {', '.join(p)} mm, yaw {_fixed(math.degrees(yaw_of(machine.platform.rotation)), 3)}&deg;; "
            f"actuators {_actuator_text(view.mechanism, machine.sliders)}</div>"
        )
    return "\n".join(lines)


def _fixed(value: float, digits: int) -> str:
    # Rounding first keeps a -1e-17 from showing as "-0.000".
    return f"{round(value, digits) + 0.0:.{digits}f}"


def scene_html(viewer: meshcat.Visualizer) -> str:
    """The self-contained page of a scene recorded offline by `build_scene(..., viewer=None)`."""
    if not isinstance(viewer.window, _Recording):
        raise InvalidInputError("scene_html needs a scene built offline (build_scene with viewer=None)")
    return viewer.window.get_scene()


def magnification_of(viewer: meshcat.Visualizer) -> float:
    """The factor a scene recorded offline by `build_scene(..., viewer=None)` magnifies deviations by."""
    if not isinstance(viewer.window, _Recording):
        raise InvalidInputError("magnification_of needs a scene built offline (build_scene with viewer=None)")
    return viewer.window.magnification


def write_static_html(
    views: Sequence[MachineView],
    path: str | os.PathLike[str],
    pose: Sequence[float] | None = None,
    sliders: Sequence[float] | None = None,
    markers: Iterable[pin.SE3] | np.ndarray | None = None,
    camera: Camera | None = DEFAULT_CAMERA,
    protect: Iterable[str | os.PathLike[str]] = (),
    magnification: float | None = None,
) -> Path:
    """Write the scene as one shareable HTML file (opens offline, from file://) and return its path.

    No server is started. The model files of every machine are protected on top of `protect`,
    and the path is checked before solving, so a mistyped output fails fast and nothing is
    overwritten. The file is replaced atomically.

    Raises OutputPathError (protected path, missing directory, failed write) and what
    `build_scene` raises.
    """
    target = Path(path)
    views = tuple(views)
    protected = [
        *protect,
        *(p for v in views if isinstance(v, MachineView) for p in (v.mechanism.urdf_path, v.mechanism.closures_path)),
    ]
    ensure_not_protected(target, protected)
    viewer = build_scene(views, pose=pose, sliders=sliders, markers=markers, camera=camera, magnification=magnification)
    atomic_write_text(target, scene_html(viewer), protect=protected)
    return target
