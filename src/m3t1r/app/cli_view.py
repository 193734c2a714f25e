"""`m3t1r view`: the nominal and calibrated machines in meshcat, live or as a static page.

`m3t1r.app.cli` imports this module only to run the verb (meshcat and Pinocchio's visualisers are
the slowest imports of the package).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import pinocchio as pin

from m3t1r.app.cli_common import load_mechanism, say
from m3t1r.app.datasets import read_measurements
from m3t1r.app.live_viewer import open_viewer
from m3t1r.app.scene import comparison_views
from m3t1r.app.static_page import build_scene, magnification_of, scene_html
from m3t1r.errors import M3t1rError
from m3t1r.io.outputs import OutputSet

__all__ = ["cmd_view"]


def _skeleton_without_meshes(mechanism) -> None:
    """A machine whose URDF meshes are missing (published without them) is drawn as a skeleton: a
    sphere at every joint and a larger one at every closure frame and the platform frame."""
    try:
        mechanism.visual_model
        return
    except M3t1rError as exc:
        print(
            f"note: {str(exc).rstrip('.')}; drawing {mechanism.urdf_path.name} as spheres at its joints "
            "and closure frames",
            file=sys.stderr,
        )
    model = mechanism.model
    data = model.createData()
    pin.forwardKinematics(model, data, mechanism.home)
    reach = max((float(np.linalg.norm(data.oMi[j].translation)) for j in range(1, model.njoints)), default=0.1)
    radius = max(0.01 * reach, 1e-3)  # [m] visible at the scale of the machine
    geometry = pin.GeometryModel()
    for j in range(1, model.njoints):
        geometry.addGeometryObject(
            pin.GeometryObject(f"joint:{model.names[j]}", j, pin.SE3.Identity(), pin.coal.Sphere(radius))
        )
    frames = [spec.frame_a_id for spec in mechanism.closures] + [spec.frame_b_id for spec in mechanism.closures]
    for frame_id in dict.fromkeys(frames + [mechanism.platform_frame_id]):
        frame = model.frames[frame_id]
        sphere = pin.GeometryObject(
            f"frame:{frame.name}", frame.parentJoint, frame.placement, pin.coal.Sphere(1.5 * radius)
        )
        sphere.meshColor[:] = (0.8, 0.15, 0.15, 1.0)
        geometry.addGeometryObject(sphere)
    mechanism.visual_cache["geometry"] = geometry


def cmd_view(args: argparse.Namespace) -> None:
    """`m3t1r view`: the nominal and calibrated machines in meshcat."""
    nominal = load_mechanism(args.model, args.closures)
    calibrated = load_mechanism(args.calibrated, args.calibrated_closures) if args.calibrated else None
    for machine in (nominal, calibrated) if calibrated is not None else (nominal,):
        _skeleton_without_meshes(machine)
    outputs = OutputSet(
        inputs=(
            nominal.urdf_path,
            nominal.closures_path,
            args.measurements,
            *((calibrated.urdf_path, calibrated.closures_path) if calibrated else ()),
        )
    )
    output = outputs.add(args.html, "--html")
    outputs.check()
    views = comparison_views(nominal, calibrated)
    markers = None
    if args.measurements:
        measured = read_measurements(args.measurements, nominal).measurements
        markers = (
            measured.poses
            if measured.points is None
            else tuple(  # several points: every one seen
                pin.SE3(np.eye(3), point) for point in measured.points[np.isfinite(measured.points[:, :, 0])]
            )
        )
    if output is not None:
        with outputs:
            scene = build_scene(views, pose=args.pose, markers=markers, magnification=args.magnify)
            outputs.stage(output, scene_html(scene))
            outputs.commit()
        factor = magnification_of(scene)
        magnified = "" if calibrated is None else f"; the calibrated machine's deviation drawn x{factor:g}"
        say(outputs, f"wrote {output.name} (self-contained: open it in any browser, no network needed{magnified})")
        return
    with open_viewer(views, pose=args.pose, markers=markers, magnification=args.magnify) as viewer:
        print(f"meshcat viewer at {viewer.url} (Ctrl-C to stop)", flush=True)
        viewer.wait()
