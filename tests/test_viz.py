"""Meshcat scenes: node layout, posing modes, the self-contained page, the live server's lifecycle,
and a real render of the page in headless Chromium.

Set M3T1R_SCREENSHOT=<png path> to keep the two-machine render (docs/meshcat_scene.png is made so).
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import umsgpack

from m3t1r.app import live_viewer, scene, static_page
from m3t1r.calibration.simulation import PlacementErrorScale, simulate_study
from m3t1r.errors import InvalidInputError, KinematicsError, OutputPathError
from m3t1r.model.description import Mechanism

POSE = (0.55, 0.6, -0.1, 0.3)  # inside the design workspace box, with some yaw


@pytest.fixture(scope="module")
def study(mechanism):
    # 5 mm / 5 mrad errors (five times a real machine's) so the two machines differ visibly.
    return simulate_study(mechanism, n_poses=8, n_holdout=0, seed=1, errors=PlacementErrorScale(5e-3, 5e-3))


@pytest.fixture(scope="module")
def views(mechanism, study):
    return scene.comparison_views(mechanism, study.truth)


def page_messages(page: str) -> list[dict]:
    """The meshcat commands inlined in a page written by `scene_html`."""
    match = re.search(r"var commands = (\[.*?\]);", page)
    assert match, "no inlined command list in the page"
    return [umsgpack.unpackb(base64.b64decode(item)) for item in json.loads(match.group(1))]


def object_paths(messages: list[dict]) -> list[str]:
    return [m["path"] for m in messages if m["type"] == "set_object"]


def child_pids() -> set[int]:
    """Live child processes of this test process (Linux /proc)."""
    children = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == os.getpid() and fields[0] != "Z":
                children.add(int(entry.name))
    return children


def alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie left unreaped by a container's init does not count)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


needs_proc = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="process checks read Linux /proc")


# ------------------------------------------------------------------------------------------
# Scene content and posing


def test_page_has_both_machines_triads_and_markers(views, study):
    page = static_page.scene_html(static_page.build_scene(views, pose=POSE, markers=study.measurements.poses))
    paths = object_paths(page_messages(page))
    for view in views:
        visuals = [p for p in paths if p.startswith(f"{view.node}/visuals/")]
        assert len(visuals) == len(view.mechanism.visual_model.geometryObjects), view.name
        assert {f"{view.node}/platform_frame/{axis}" for axis in "xyz"} <= set(paths)
        assert f'data-node="{view.node}"' in page  # legend entry
    markers = [p for p in paths if p.startswith(f"/meshcat/{scene.MEASUREMENTS_NODE}/")]
    assert len(markers) == len(study.measurements.poses)
    assert "/meshcat/m3t1r/nominal" in views[0].node and "/meshcat/m3t1r/calibrated" in views[1].node


def test_calibrated_colour_overrides_every_material(views):
    messages = page_messages(static_page.scene_html(static_page.build_scene(views)))
    calibrated = [m for m in messages if m["type"] == "set_object" and "/calibrated/visuals/" in m["path"]]
    nominal = [m for m in messages if m["type"] == "set_object" and "/nominal/visuals/" in m["path"]]
    r, g, b, alpha = scene.CALIBRATED_COLOR
    wanted = (int(r * 255) << 16) + (int(g * 255) << 8) + int(b * 255)
    for message in calibrated:
        material = message["object"]["materials"][0]
        assert material["color"] == wanted and material["transparent"] and material["opacity"] == pytest.approx(alpha)
    assert len({m["object"]["materials"][0]["color"] for m in nominal}) > 3  # URDF materials kept


def test_pose_mode_reaches_the_same_pose_with_different_sliders(views):
    nominal, calibrated = scene.pose_machines(views, pose=POSE)
    for machine in (nominal, calibrated):
        assert machine.platform.translation == pytest.approx(POSE[:3], abs=1e-9)
    assert np.abs(nominal.sliders - calibrated.sliders).max() > 1e-3


def test_slider_mode_gives_the_same_sliders_and_different_poses(views):
    sliders = scene.pose_machines(views[:1], pose=POSE)[0].sliders
    nominal, calibrated = scene.pose_machines(views, sliders=sliders)
    assert calibrated.sliders == pytest.approx(sliders, abs=1e-12)
    assert np.linalg.norm(nominal.platform.translation - calibrated.platform.translation) > 1e-3


def test_scene_transforms_are_the_solved_configuration(views):
    messages = page_messages(static_page.scene_html(static_page.build_scene(views, pose=POSE, magnification=1)))
    last = {m["path"]: m["matrix"] for m in messages if m["type"] == "set_transform"}
    for machine in scene.pose_machines(views, pose=POSE):
        drawn = np.array(last[f"{machine.view.node}/platform_frame"]).reshape(4, 4).T
        assert drawn == pytest.approx(machine.platform.homogeneous, abs=1e-12)


def drawn_joint_placements(messages: list[dict], view: scene.MachineView) -> dict[int, pin.SE3]:
    """Joint placements the page draws, recovered from the last transform of each visual (its
    mesh scale and its placement on the joint taken off)."""
    last = {m["path"]: m["matrix"] for m in messages if m["type"] == "set_transform"}
    joints = {}
    for geometry in view.mechanism.visual_model.geometryObjects:
        matrix = np.array(last[f"{view.node}/visuals/{geometry.name}"]).reshape(4, 4).T
        matrix[:3, :3] /= np.asarray(geometry.meshScale)  # columns scaled by the mesh scale
        joints[geometry.parentJoint] = pin.SE3(matrix) * geometry.placement.inverse()
    return joints


def true_joint_placements(machine: scene.PosedMachine) -> list[pin.SE3]:
    model = machine.view.mechanism.model
    data = model.createData()
    pin.forwardKinematics(model, data, machine.q)
    return [pin.SE3(placement) for placement in data.oMi]


@pytest.mark.parametrize("factor", [1.0, 10.0, 100.0])
def test_calibrated_machine_is_drawn_with_its_deviation_magnified(views, factor):
    """Every body of the calibrated machine is drawn `factor` times as far from the nominal's, and turned
    `factor` times as much; the nominal machine and the stated figures stay true."""
    page = static_page.scene_html(static_page.build_scene(views, pose=POSE, magnification=factor))
    messages = page_messages(page)
    nominal, calibrated = scene.pose_machines(views, pose=POSE)
    reference, actual = true_joint_placements(nominal), true_joint_placements(calibrated)
    for joint, drawn in drawn_joint_placements(messages, views[0]).items():
        assert drawn.translation == pytest.approx(reference[joint].translation, abs=1e-9)
    drawn_joints = drawn_joint_placements(messages, views[1])
    true_offsets = []
    for joint, drawn in drawn_joints.items():
        ref, true = reference[joint], actual[joint]
        true_offsets.append(np.linalg.norm(true.translation - ref.translation))
        assert drawn.translation - ref.translation == pytest.approx(
            factor * (true.translation - ref.translation), abs=1e-9
        )
        turned = pin.exp3(factor * pin.log3(ref.rotation.T @ true.rotation))  # the deviation's angle, times factor
        assert ref.rotation.T @ drawn.rotation == pytest.approx(turned, abs=1e-9)
    assert max(true_offsets) > 1e-3  # the study's errors move the bodies: the check above is not 0 = 0
    assert f'data-magnification="{factor:g}"' in page
    assert ("magnified &times;100" in page) == (factor == 100.0) and ("true scale" in page) == (factor == 1.0)
    assert _fixed_mm(calibrated.platform.translation) in page  # the legend states the true platform


def _fixed_mm(position: np.ndarray) -> str:
    return ", ".join(f"{round(v * 1e3, 2) + 0.0:.2f}" for v in position)


def test_default_magnification_draws_the_largest_offset_as_a_tenth_of_the_machine(mechanism):
    """Chosen from the scene: a factor 1, 2 or 5 times a power of ten under which the largest joint offset
    is drawn as 4 % to 10 % of the machine's size (or no joint turned beyond 0.3 rad), and stated."""
    for sigma in (1e-4, 1e-3):
        truth = simulate_study(
            mechanism,
            n_poses=8,
            n_holdout=0,
            seed=1,
            errors=PlacementErrorScale(sigma, sigma),
        ).truth
        views = scene.comparison_views(mechanism, truth)
        recorded = static_page.build_scene(views)
        factor = static_page.magnification_of(recorded)
        nominal, calibrated = scene.pose_machines(views)
        reference, actual = true_joint_placements(nominal)[1:], true_joint_placements(calibrated)[1:]
        size = np.linalg.norm(np.ptp([m.translation for m in reference], axis=0))
        offset = max(np.linalg.norm(a.translation - r.translation) for r, a in zip(reference, actual))
        angle = max(np.linalg.norm(pin.log3(r.rotation.T @ a.rotation)) for r, a in zip(reference, actual))
        mantissa = factor / 10 ** np.floor(np.log10(factor))
        assert min(abs(mantissa - step) for step in (1, 2, 5)) < 1e-9
        assert factor * offset <= 0.1 * size * (1 + 1e-9) and factor * angle <= 0.3 * (1 + 1e-9)
        assert factor * offset > 0.04 * size or factor * angle > 0.12
        assert f'data-magnification="{factor:g}"' in static_page.scene_html(recorded)
        print(f"sigma {sigma:g}: factor {factor:g}, offset {offset:.2e} m of {size:.2f} m, angle {angle:.2e} rad")


def test_magnification_bounds(views):
    single = static_page.scene_html(static_page.build_scene(views[:1]))
    assert "data-magnification" not in single  # one machine: nothing to magnify, nothing stated
    for bad in (0.5, float("nan"), float("inf")):
        with pytest.raises(InvalidInputError, match="magnification"):
            static_page.build_scene(views, magnification=bad)


def test_view_command_states_the_factor(views, study, tmp_path, capsys):
    from m3t1r.app.cli import main

    urdf = tmp_path / "calibrated.urdf"
    study.truth.save(urdf, tmp_path / "calibrated.closures.yaml")
    page = tmp_path / "scene.html"
    assert main(["view", "--calibrated", str(urdf), "--html", str(page), "--magnify", "20"]) == 0
    assert 'data-magnification="20"' in page.read_text(encoding="utf-8")
    assert "deviation drawn x20" in capsys.readouterr().out
    with pytest.raises(SystemExit) as refused:
        main(["view", "--calibrated", str(urdf), "--html", str(page), "--magnify", "0.5"])
    assert refused.value.code == 2
    assert "at least 1" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# Errors


def test_unreachable_pose_names_the_machine(views):
    with pytest.raises(KinematicsError, match="machine 'nominal'"):
        static_page.build_scene(views, pose=(0.5, 0.5, 3.0, 0.0))


def test_sliders_beyond_limits_name_the_machine(views):
    with pytest.raises(InvalidInputError, match="machine 'nominal'.*q11"):
        scene.pose_machines(views, sliders=(5.0, 0.0, 0.0, 0.0))


def test_pose_and_sliders_together_are_refused(views):
    with pytest.raises(InvalidInputError, match="not both"):
        scene.pose_machines(views, pose=POSE, sliders=(0, 0, 0, 0))
    with pytest.raises(InvalidInputError, match="4 values"):
        scene.pose_machines(views, pose=(0.5, 0.5))


def test_machines_with_different_joints_are_refused(mechanism):
    model = mechanism.model.copy()
    model.names[3] = "renamed_joint"
    other = mechanism.with_model(model)
    with pytest.raises(InvalidInputError, match=r"only in 'nominal': q12_pa; only in 'other': renamed_joint"):
        static_page.build_scene([scene.MachineView("nominal", mechanism), scene.MachineView("other", other)])


def test_bad_views_and_markers_are_refused(mechanism):
    with pytest.raises(InvalidInputError, match="unique"):
        scene.pose_machines([scene.MachineView("a", mechanism), scene.MachineView("a", mechanism)])
    with pytest.raises(InvalidInputError, match="no machine"):
        scene.pose_machines([])
    with pytest.raises(InvalidInputError, match="scene node"):
        scene.MachineView("a/b", mechanism)
    with pytest.raises(InvalidInputError, match="reserved"):
        scene.MachineView("measurements", mechanism)
    with pytest.raises(InvalidInputError, match=r"\[0, 1\]"):
        scene.MachineView("a", mechanism, (1.0, 0.0, 2.0, 1.0))
    with pytest.raises(InvalidInputError, match=r"\(n, 3\)"):
        static_page.build_scene([scene.MachineView("a", mechanism)], markers=np.zeros((2, 7)))
    with pytest.raises(InvalidInputError, match="non-finite"):
        static_page.build_scene([scene.MachineView("a", mechanism)], markers=[[0.0, np.nan, 0.0]])
    with pytest.raises(InvalidInputError, match="coincide"):
        scene.Camera(position=(1.0, 1.0, 1.0), target=(1.0, 1.0, 1.0))


# ------------------------------------------------------------------------------------------
# The static page


def test_page_is_self_contained(views, tmp_path):
    path = static_page.write_static_html(views, tmp_path / "scene.html", pose=POSE)
    page = path.read_text(encoding="utf-8")
    # Nothing the page would load: no src/href attribute, stylesheet import or <link>. The viewer
    # bundle holds two absolute URLs, neither fetched: the XHTML namespace name (an identifier) and
    # the server socket template of Viewer.connect(), which our page never calls.
    assert not re.search(r"""\b(?:src|href)\s*=""", page.split("<script>")[0], re.IGNORECASE)
    assert "@import" not in page and "<link" not in page.lower()
    urls = set(re.findall(r"(?:https?|wss?|ftp)://[^\s\"'`<>)]*", page))
    assert urls <= {"http://www.w3.org/1999/xhtml", "ws://${location.host}"}, urls
    assert re.search(r"(?<![:\w])//[a-z0-9-]+\.[a-z]{2,}/", page) is None  # protocol-relative URLs
    script = page.rsplit("<script>", 1)[1]  # ours, after the bundle
    assert "MeshCat.Viewer" in script
    for loader in ("fetch(", "XMLHttpRequest", "WebSocket", ".connect(", "import("):
        assert loader not in script  # the commands are inlined, not loaded


def test_write_refuses_protected_paths_and_leaves_them_intact(views, tmp_path):
    urdf = views[0].mechanism.urdf_path
    before = urdf.read_bytes()
    with pytest.raises(OutputPathError, match="refusing"):
        static_page.write_static_html(views, urdf)  # a model file is always protected
    assert urdf.read_bytes() == before
    data = tmp_path / "measured.csv"
    data.write_text("x\n1\n")
    with pytest.raises(OutputPathError, match="refusing"):
        static_page.write_static_html(views, data, protect=[data])
    assert data.read_text() == "x\n1\n"
    with pytest.raises(OutputPathError, match="does not exist"):
        static_page.write_static_html(views, tmp_path / "missing" / "scene.html")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["measured.csv"]  # no temporary left


@needs_proc
def test_static_page_starts_no_process(views, tmp_path):
    before = child_pids()
    static_page.write_static_html(views, tmp_path / "scene.html")
    assert child_pids() == before


def test_calibrated_machine_loaded_from_files(mechanism, study, tmp_path):
    urdf, closures = tmp_path / "calibrated.urdf", tmp_path / "calibrated.closures.yaml"
    study.truth.save(urdf, closures)
    views = scene.comparison_views(mechanism, Mechanism.load(urdf, closures))
    page = static_page.write_static_html(views, tmp_path / "scene.html", pose=POSE).read_text(encoding="utf-8")
    assert "(calibrated.urdf)" in page
    paths = object_paths(page_messages(page))
    assert sum(p.startswith("/meshcat/m3t1r/calibrated/visuals/") for p in paths) == len(
        views[1].mechanism.visual_model.geometryObjects
    )
    with pytest.raises(OutputPathError, match="refusing"):
        static_page.write_static_html(views, closures)  # every machine's model files are protected


# ------------------------------------------------------------------------------------------
# Live server


@needs_proc
def test_live_viewer_serves_the_scene_and_is_stopped(views):
    before = child_pids()
    with live_viewer.open_viewer(views, pose=POSE) as live:
        assert live.url.startswith("http://127.0.0.1:") and live.pid in child_pids()
        with urllib.request.urlopen(live.url, timeout=10) as response:
            assert b"main.min.js" in response.read()
        served = live.visualizer.static_html()  # the server's own copy of the scene
        blobs = re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", served)
        paths = {umsgpack.unpackb(base64.b64decode(blob)).get("path") for blob in blobs}
        assert any(p and p.startswith("/meshcat/m3t1r/calibrated/visuals/") for p in paths)
        pid = live.pid
    assert live.process.poll() is not None
    assert not alive(pid) and child_pids() == before
    live.close()  # idempotent


@needs_proc
def test_failed_command_starts_no_server(views):
    before = child_pids()
    with pytest.raises(KinematicsError):
        live_viewer.open_viewer(views, pose=(0.5, 0.5, 3.0, 0.0))
    assert child_pids() == before


@needs_proc
def test_server_exits_when_its_owner_is_killed(tmp_path):
    # A CLI killed by SIGKILL runs no cleanup; the server's watchdog must notice on its own.
    script = tmp_path / "owner.py"
    script.write_text(
        "import time\n"
        "from m3t1r.model.description import Mechanism\n"
        "from m3t1r.app import live_viewer, scene\n"
        "live = live_viewer.open_viewer(scene.comparison_views(Mechanism.load()))\n"
        "print(live.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(
            filter(None, [str(Path(scene.__file__).parents[2]), os.environ.get("PYTHONPATH")])
        ),
    }
    owner = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        server = int(owner.stdout.readline())
        assert alive(server)
    finally:
        owner.kill()
        owner.wait()
    deadline = time.monotonic() + 5.0
    while alive(server) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not alive(server), f"meshcat server {server} outlived its owner"


# ------------------------------------------------------------------------------------------
# Render in headless Chromium

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",  # WebGL on the CPU; without it Chromium warns and may stop falling back
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--host-resolver-rules=MAP * ~NOTFOUND",  # no name resolves: the page must be offline
    "--window-size=1024,768",
    "--virtual-time-budget=2500",
    "--hide-scrollbars",
)


def screenshots(pages: dict[str, Path], folder: Path) -> dict[str, np.ndarray]:
    """Render each page (all at once, to halve the wait) and return its RGB pixels by label.

    Every process Chromium starts is ended afterwards: each browser leads its own process group.
    """
    from PIL import Image

    running = {}
    for label, page in pages.items():
        command = [
            CHROMIUM,
            *CHROMIUM_FLAGS,
            f"--user-data-dir={folder / ('profile-' + label)}",
            f"--screenshot={folder / (label + '.png')}",
            page.as_uri(),
        ]
        running[label] = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
        )
    outputs = {}
    try:
        for label, process in running.items():
            outputs[label] = process.communicate(timeout=60)[0]
    finally:
        for process in running.values():
            try:  # its renderer and GPU helpers are in the group it leads
                os.killpg(process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            process.wait()
    pixels = {}
    for label in pages:
        png = folder / f"{label}.png"
        assert png.is_file(), f"chromium wrote no screenshot:\n{outputs[label].decode(errors='replace')[-2000:]}"
        pixels[label] = np.asarray(Image.open(png).convert("RGB")).astype(int)
    return pixels


def magenta_pixels(rgb: np.ndarray) -> int:
    """Pixels of the translucent calibrated colour, over any background; no URDF material is like it."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return int(np.count_nonzero((r - g > 60) & (b - g > 50)))


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed: apt-get install chromium (.ci/run does)")
def test_page_renders_both_machines(views, study, tmp_path):
    started = time.monotonic()
    pages = {
        label: static_page.write_static_html(
            shown, tmp_path / f"{label}.html", pose=POSE, markers=study.measurements.poses
        )
        for label, shown in (("nominal", views[:1]), ("both", views))
    }
    # Above the HTML legend only: its swatches are colours too.
    scenes = {label: rgb[: int(rgb.shape[0] * 0.78)] for label, rgb in screenshots(pages, tmp_path).items()}
    nominal, both = scenes["nominal"], scenes["both"]
    for rgb in (nominal, both):
        assert rgb.std() > 10, "blank render"
        assert len(np.unique(rgb.reshape(-1, 3) // 32, axis=0)) >= 12, "too few colours: WebGL drew nothing?"
        urdf_orange = (np.abs(rgb - [217, 140, 26]).max(axis=-1) < 40).sum()  # the upper bars
        assert urdf_orange > 200, "the nominal machine's materials are not on screen"
    assert magenta_pixels(nominal) < 50
    assert magenta_pixels(both) > 2000, "the calibrated machine is not on screen"
    assert time.monotonic() - started < 60
    keep = os.environ.get("M3T1R_SCREENSHOT")
    if keep:
        shutil.copyfile(tmp_path / "both.png", keep)
