"""PNG figures: written atomically, never onto an input, readable, and refusing malformed data."""

import struct

import matplotlib.image
import numpy as np
import pytest
from matplotlib.figure import Figure

from m3t1r.app.plots import (
    PlotFile,
    plot_error_vs_poses,
    plot_pose_errors_before_after,
    plot_predicted_std_map,
    plot_workspace_error_map,
)
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.errors import InvalidInputError, OutputPathError
from m3t1r.metrics import PoseErrors

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(path) -> tuple[int, int]:
    """(width, height) in pixels from the IHDR chunk, which must follow the magic bytes."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def assert_real_png(path, min_bytes: int = 15_000) -> None:
    assert path.is_file() and path.stat().st_size > min_bytes
    width, height = png_size(path)
    assert width > 400 and height > 300
    pixels = matplotlib.image.imread(path)
    assert pixels.shape[:2] == (height, width)
    assert pixels[..., :3].std() > 0.05  # not a blank canvas


def assert_only(directory, *names) -> None:
    """No temporary file left behind by the atomic write."""
    assert sorted(p.name for p in directory.iterdir()) == sorted(names)


@pytest.fixture()
def errors():
    rng = np.random.default_rng(0)
    before = PoseErrors(rng.uniform(5e-3, 2e-2, 50), rng.uniform(1e-2, 0.1, 50))
    after = PoseErrors(rng.uniform(1e-6, 3e-5, 50), rng.uniform(2e-6, 5e-5, 50))
    return before, after


@pytest.fixture()
def workspace_points():
    rng = np.random.default_rng(1)
    lo, hi = np.array([0.40, 0.225, -0.211, -0.785]), np.array([0.60, 0.825, -0.011, 0.785])
    return lo + (hi - lo) * rng.random((120, 4))


def test_pose_errors_before_after(tmp_path, errors):
    import matplotlib
    import matplotlib.pyplot as plt

    backend = matplotlib.get_backend()
    target = tmp_path / "fig4.png"
    target.write_bytes(b"an older file")  # replaced whole
    out = plot_pose_errors_before_after(*errors, target)
    assert out == target
    assert_real_png(out)
    assert_only(tmp_path, "fig4.png")
    # Built without pyplot: no open figure, no backend switch in the caller's process.
    assert plt.get_fignums() == [] and matplotlib.get_backend() == backend


def test_pose_errors_with_exact_zeros_are_drawn_not_crashing(tmp_path, errors):
    before, _ = errors
    exact = PoseErrors(np.zeros(50), np.r_[np.zeros(10), np.full(40, 1e-9)])
    assert_real_png(plot_pose_errors_before_after(before, exact, tmp_path / "zeros.png"))


def test_position_only_errors_get_the_position_panel_alone(tmp_path, errors):
    """A position-only tracker measures no orientation (rotation NaN at every pose, before and after):
    one panel; a NaN among measured rotations is still refused."""
    before, after = errors
    nan = np.full(len(before.position), np.nan)
    out = plot_pose_errors_before_after(
        PoseErrors(before.position, nan), PoseErrors(after.position, nan), tmp_path / "position.png"
    )
    assert_real_png(out)
    with pytest.raises(InvalidInputError, match="before.rotation: non-finite"):
        plot_pose_errors_before_after(
            PoseErrors(before.position, np.r_[before.rotation[:-1], np.nan]), after, tmp_path / "x.png"
        )
    with pytest.raises(InvalidInputError, match="before.rotation: non-finite"):  # orientation after but not before
        plot_pose_errors_before_after(PoseErrors(before.position, nan), after, tmp_path / "x.png")


def test_error_vs_poses_with_and_without_prediction(tmp_path):
    n = [20, 50, 100, 200]
    position, rotation = [2.1e-5, 8.5e-6, 5.7e-6, 3.9e-6], [3.0e-5, 1.3e-5, 9.2e-6, 6.1e-6]
    predicted = ([1.9e-5, 9.0e-6, 6.0e-6, 4.1e-6], [2.8e-5, 1.2e-5, 8.8e-6, 6.3e-6])
    a = plot_error_vs_poses(n, position, rotation, tmp_path / "a.png", predicted=predicted)
    b = plot_error_vs_poses(n, position, None, tmp_path / "b.png")  # a position-only study
    assert_real_png(a)
    assert_real_png(b, min_bytes=10_000)
    assert png_size(a)[0] > png_size(b)[0]  # two panels vs one
    assert_only(tmp_path, "a.png", "b.png")


def test_workspace_error_map_and_predicted_std_map(tmp_path, errors, workspace_points):
    before = np.linspace(5e-3, 2e-2, 120)
    after = np.linspace(1e-6, 4e-5, 120)
    map_path = plot_workspace_error_map(workspace_points, before, after, tmp_path / "map.png")
    yaw_path = plot_workspace_error_map(
        workspace_points, before * 5, after, tmp_path / "yaw.png", kind="yaw", shared_scale=True
    )
    std = PoseErrors(np.linspace(4e-6, 2e-5, 120), np.linspace(8e-6, 3e-5, 120))
    std_path = plot_predicted_std_map(workspace_points, std, tmp_path / "std.png")
    for path in (map_path, yaw_path, std_path):
        assert_real_png(path)
    assert_only(tmp_path, "map.png", "yaw.png", "std.png")


def test_refuses_to_overwrite_a_protected_input(tmp_path, errors, workspace_points):
    measurements = tmp_path / "measurements.csv"
    measurements.write_text("q11,q21\n0.1,0.2\n")
    alias = tmp_path / "link.csv"
    alias.symlink_to(measurements)
    calls = [
        lambda p: plot_pose_errors_before_after(*errors, PlotFile(p, protect=(measurements,))),
        lambda p: plot_error_vs_poses([10, 20], [1e-5, 5e-6], [2e-5, 1e-5], PlotFile(p, protect=(measurements,))),
        lambda p: plot_workspace_error_map(
            workspace_points, np.ones(120), np.ones(120), PlotFile(p, protect=(measurements,))
        ),
        lambda p: plot_predicted_std_map(
            workspace_points,
            PoseErrors(np.ones(120), np.ones(120)),
            PlotFile(p, protect=(measurements,)),
        ),
    ]
    for call in calls:
        for path in (measurements, alias):
            with pytest.raises(OutputPathError, match="refusing to overwrite"):
                call(path)
    assert measurements.read_text() == "q11,q21\n0.1,0.2\n"
    assert_only(tmp_path, "measurements.csv", "link.csv")


def test_missing_directory_is_an_output_error(tmp_path, errors):
    with pytest.raises(OutputPathError, match="does not exist"):
        plot_pose_errors_before_after(*errors, tmp_path / "nowhere" / "fig.png")


def test_malformed_data_is_refused_and_nothing_written(tmp_path, errors, workspace_points):
    before, after = errors
    bad = PoseErrors(np.r_[before.position[:-1], np.nan], before.rotation)
    with pytest.raises(InvalidInputError, match="before.position: non-finite"):
        plot_pose_errors_before_after(bad, after, tmp_path / "x.png")
    with pytest.raises(InvalidInputError, match="same poses"):
        plot_pose_errors_before_after(before, PoseErrors(after.position[:10], after.rotation[:10]), tmp_path / "x.png")
    with pytest.raises(InvalidInputError, match="negative"):
        plot_pose_errors_before_after(before, PoseErrors(-after.position, after.rotation), tmp_path / "x.png")
    with pytest.raises(InvalidInputError, match="3 values for 2"):
        plot_error_vs_poses([10, 20], [1e-5, 5e-6, 1e-6], None, tmp_path / "x.png")
    with pytest.raises(InvalidInputError, match="one error of each per target"):
        plot_workspace_error_map(workspace_points, np.ones(119), np.ones(120), tmp_path / "x.png")
    with pytest.raises(InvalidInputError, match="kind"):
        plot_workspace_error_map(workspace_points, np.ones(120), np.ones(120), tmp_path / "x.png", kind="roll")
    assert_only(tmp_path)


def test_legends_and_ticks_give_each_value_in_its_own_unit(tmp_path, monkeypatch):
    """Errors span decades: each legend mean and each tick label reads in the unit that suits it."""
    drawn: list[Figure] = []
    savefig = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda figure, *a, **k: (drawn.append(figure), savefig(figure, *a, **k)))
    before = PoseErrors(np.full(5, 0.0235), np.full(5, 0.14))
    after = PoseErrors(np.full(5, 1e-5), np.full(5, 3e-10))
    plot_pose_errors_before_after(before, after, tmp_path / "e.png")
    (figure,) = drawn
    legends = [[t.get_text() for t in ax.get_legend().get_texts()] for ax in figure.axes]
    assert legends == [
        ["before: mean 140 mrad", "after: mean 0.3 nrad"],
        ["before: mean 23.5 mm", "after: mean 10 µm"],
    ]
    ticks = {t.get_text() for t in figure.axes[1].yaxis.get_ticklabels() if t.get_text()}
    assert {"10 µm", "1 mm", "10 mm"} <= ticks


@pytest.mark.parametrize("estimate_frame", [False, True])
def test_calibration_plots_title_the_map_by_what_it_shows(tmp_path, monkeypatch, estimate_frame):
    """The predicted map shows what the tracker would measure, in its frame: with the tracker frame
    estimated it is titled so and stays at the tracker-noise level (the platform's std in the base
    would be millimetres, the base placement being the gauge); without a setup it is the platform's
    error, as before. Every map point is an assembled workspace target."""
    import pinocchio as pin

    from m3t1r.app import reporting
    from m3t1r.calibration.closed_loop import calibrate_closed_loop
    from m3t1r.calibration.measurement_setup import MeasurementSetup
    from m3t1r.calibration.measurements import TrackerNoise
    from m3t1r.calibration.simulation import StudyOptions, simulate_study
    from m3t1r.model.description import Mechanism

    mechanism = Mechanism.load()
    frame = pin.SE3(pin.utils.rotate("z", 2.0), np.array([1.5, -0.8, 0.3])) if estimate_frame else pin.SE3.Identity()
    study = simulate_study(
        mechanism,
        n_poses=40,
        n_holdout=0,
        seed=5,
        noise=TrackerNoise(),
        options=StudyOptions(setup=MeasurementSetup(frame)),
    )
    calibration = calibrate_closed_loop(
        mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise(), estimate_frame=estimate_frame)
    )
    maps = []
    monkeypatch.setattr(reporting, "cross_validation_curve", lambda *args, **kwargs: ([], [], []))
    monkeypatch.setattr(
        reporting,
        "plot_predicted_std_map",
        lambda targets, std, path, title, plane: maps.append((targets, std, title)) or path,
    )
    reporting.write_calibration_plots(mechanism, calibration, tmp_path)
    ((targets, std, title),) = maps
    assert 250 < len(targets) <= 300 and len(std.position) == len(targets)
    if estimate_frame:
        assert title.startswith("Predicted error of the measured point in the measurement frame (1 sigma)")
    else:
        assert title == "Predicted error after compensation (1 sigma)"
    assert 1e-6 < float(np.mean(std.position)) < 30e-6  # not the millimetres of the base gauge


def test_calibration_plots_of_a_position_only_tracker(tmp_path, monkeypatch):
    """A tracker without orientation, its frame estimated: every plot is written (the per-pose plot
    with its position panel alone), where the orientation panel used to refuse the NaN rotations."""
    import pinocchio as pin

    from m3t1r.app import reporting
    from m3t1r.calibration.closed_loop import calibrate_closed_loop
    from m3t1r.calibration.measurement_setup import MeasurementSetup
    from m3t1r.calibration.measurements import TrackerNoise
    from m3t1r.calibration.simulation import StudyOptions, simulate_study
    from m3t1r.model.description import Mechanism

    mechanism = Mechanism.load()
    setup = MeasurementSetup(pin.SE3(pin.utils.rotate("z", -1.0), np.array([1.5, 2.0, -0.3])))
    study = simulate_study(
        mechanism,
        n_poses=40,
        n_holdout=0,
        seed=6,
        noise=TrackerNoise(),
        options=StudyOptions(setup=setup, position_only=True),
    )
    calibration = calibrate_closed_loop(
        mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise(), estimate_frame=True)
    )
    monkeypatch.setattr(reporting, "cross_validation_curve", lambda *args, **kwargs: ([], [], []))
    written = reporting.write_calibration_plots(mechanism, calibration, tmp_path)
    assert [path.name for path in written] == ["pose_errors_before_after.png", "predicted_error_map.png"]
    for path in written:
        assert_real_png(path)


@pytest.mark.parametrize("kind", ["five_bar", "spherical_wrist"])
def test_calibration_plots_of_other_mechanisms_map_their_own_workspace(tmp_path, monkeypatch, kind):
    """The map's poses come from the mechanism's declared workspace and are drawn over its task's first
    two coordinates (five-bar: x, y; orientation wrist: roll, pitch), where the M machine's (x, y, z,
    theta) box used to be fed to their inverse kinematics and refused."""
    from m3t1r.app import reporting
    from m3t1r.calibration.closed_loop import calibrate_closed_loop
    from m3t1r.calibration.measurements import TrackerNoise
    from m3t1r.calibration.simulation import simulate_study
    from m3t1r.model.description import Mechanism
    from m3t1r.model.examples import five_bar_files, spherical_wrist_files

    files = (five_bar_files if kind == "five_bar" else spherical_wrist_files)(tmp_path / "model")
    mechanism = Mechanism.load(*files)
    study = simulate_study(mechanism, n_poses=30, n_holdout=0, seed=2, noise=TrackerNoise())
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise()))
    maps = []
    monkeypatch.setattr(reporting, "cross_validation_curve", lambda *args, **kwargs: ([], [], []))
    monkeypatch.setattr(
        reporting,
        "plot_predicted_std_map",
        lambda where, std, path, title, plane: maps.append((where, std, plane)) or path,
    )
    reporting.write_calibration_plots(mechanism, calibration, tmp_path / "plots")
    ((where, std, plane),) = maps
    frame = mechanism.task.frame
    assert plane == (
        (f"{frame} x [m]", f"{frame} y [m]") if kind == "five_bar" else (f"{frame} roll [rad]", f"{frame} pitch [rad]")
    )
    assert 250 < len(where) <= 300 and len(std.position) == len(where) and np.all(np.isfinite(where))
    assert np.ptp(where, axis=0).min() > 0.1  # spread over the workspace, not one point


# ------------------------------------------------------------------------------------------------
# Outliers shown, not dropped


def png_description(path) -> str:
    """The PNG's Description text chunk: what the figure marks, in words."""
    from PIL import Image

    with Image.open(path) as image:
        return image.text.get("Description", "")


def test_before_after_circles_and_names_the_outliers(tmp_path, errors):
    before, after = errors
    spoiled = PoseErrors(np.r_[after.position[:3], 4e-3, after.position[4:]], after.rotation)
    labels = [f"line {k + 2}" for k in range(50)]
    marked = plot_pose_errors_before_after(before, spoiled, tmp_path / "marked.png", outliers=[3], labels=labels)
    assert_real_png(marked)
    assert png_description(marked) == "outliers: line 5"
    plain = plot_pose_errors_before_after(before, after, tmp_path / "plain.png")
    assert png_description(plain) == "outliers: none"
    with pytest.raises(InvalidInputError, match="pose index 50 out of range"):
        plot_pose_errors_before_after(before, after, tmp_path / "bad.png", outliers=[50])
    with pytest.raises(InvalidInputError, match="labels: 2 for 50 poses"):
        plot_pose_errors_before_after(before, after, tmp_path / "bad.png", outliers=[1], labels=["a", "b"])
    assert not (tmp_path / "bad.png").exists()


def test_calibration_plots_show_the_outliers_the_fit_left_out(tmp_path, monkeypatch):
    """Two measurements spoiled by 4 mm: the fit leaves them out, and the per-pose plot still draws them,
    circled and named by the labels given (the file lines `calibrate --plots` passes)."""
    import pinocchio as pin

    from m3t1r.app import reporting
    from m3t1r.calibration.closed_loop import calibrate_closed_loop
    from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise
    from m3t1r.calibration.simulation import simulate_study
    from m3t1r.model.description import Mechanism

    mechanism = Mechanism.load()
    study = simulate_study(mechanism, n_poses=40, n_holdout=0, seed=5, noise=TrackerNoise())
    poses = list(study.measurements.poses)
    for k in (7, 22):
        poses[k] = pin.SE3(poses[k].rotation, poses[k].translation + np.array([4e-3, 0.0, 0.0]))
    measurements = PoseMeasurements(study.measurements.actuators, tuple(poses))
    calibration = calibrate_closed_loop(mechanism, measurements, CalibrationOptions(noise=TrackerNoise()))
    assert sorted(calibration.outliers) == [7, 22]
    drawn = []
    monkeypatch.setattr(reporting, "cross_validation_curve", lambda *args, **kwargs: ([], [], []))
    original = reporting.plot_pose_errors_before_after
    monkeypatch.setattr(
        reporting,
        "plot_pose_errors_before_after",
        lambda before, after, *args, **kwargs: (
            drawn.append((before, after)) or original(before, after, *args, **kwargs)
        ),
    )
    labels = [f"line {k + 3}" for k in range(40)]
    written = reporting.write_calibration_plots(mechanism, calibration, tmp_path, labels=labels)
    assert png_description(written[0]) == "outliers: line 10, line 25"
    ((before, after),) = drawn
    assert len(after.position) == 40  # every pose drawn, the outliers' included
    assert after.position[[7, 22]].min() > 3e-3 > 1e-4 > np.delete(after.position, [7, 22]).max()
