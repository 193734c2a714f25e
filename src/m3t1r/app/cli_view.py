"""`m3t1r view`: the nominal and calibrated machines in meshcat, live or as a static page.

`m3t1r.app.cli` imports this module only to run the verb (meshcat and Pinocchio's visualisers are
the slowest imports of the package).
"""

from __future__ import annotations

import argparse

from m3t1r.app.cli_common import load_mechanism, say
from m3t1r.app.datasets import read_measurements
from m3t1r.app.live_viewer import open_viewer
from m3t1r.app.scene import comparison_views
from m3t1r.app.static_page import build_scene, scene_html
from m3t1r.io.outputs import OutputSet

__all__ = ["cmd_view"]


def cmd_view(args: argparse.Namespace) -> None:
    """`m3t1r view`: the nominal and calibrated machines in meshcat."""
    nominal = load_mechanism(args.nominal, args.closures)
    calibrated = load_mechanism(args.calibrated, args.calibrated_closures) if args.calibrated else None
    outputs = OutputSet(inputs=(nominal.urdf_path, nominal.closures_path, args.measurements,
                                *((calibrated.urdf_path, calibrated.closures_path) if calibrated else ())))
    output = outputs.add(args.html, "--html")
    outputs.check()
    views = comparison_views(nominal, calibrated)
    markers = None
    if args.measurements:
        markers = read_measurements(args.measurements, nominal).measurements.poses
    if output is not None:
        with outputs:
            outputs.stage(output, scene_html(build_scene(views, pose=args.pose, markers=markers)))
            outputs.commit()
        say(outputs, f"wrote {output.name} (self-contained: open it in any browser, no network needed)")
        return
    with open_viewer(views, pose=args.pose, markers=markers) as viewer:
        print(f"meshcat viewer at {viewer.url} (Ctrl-C to stop)", flush=True)
        viewer.wait()
