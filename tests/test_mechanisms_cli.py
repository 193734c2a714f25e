"""The command line on mechanisms other than the M machine (`--model --closures`): a planar five-bar
(task x, y), a spherical wrist (task: full orientation) and two five-bars with the traits of
published models (continuous joints, joints named x, y, z, empty passive limits, a weld of coaxial
hinges, a rod with a spherical joint at each end, declared frames), from simulation to compensation."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from m3t1r.app.cli import main
from m3t1r.app.datasets import read_actuators
from m3t1r.calibration.closed_loop import pose_errors
from m3t1r.calibration.validation import read_report
from m3t1r.io.poses import POSE_COLUMNS, poses_from_table
from m3t1r.io.tables import read_table
from m3t1r.model.description import Mechanism, nominal_model_paths
from m3t1r.model.examples import (
    first_time_five_bar_files,
    published_five_bar_files,
    rod_five_bar_files,
    spherical_wrist_files,
)
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.workspace import workspace_actuators

TOOLS = Path(__file__).resolve().parents[1] / "tools"
_WRITERS = {
    "spherical_wrist": spherical_wrist_files,
    "published_five_bar": published_five_bar_files,
    "rod_five_bar": rod_five_bar_files,
}


@pytest.fixture(params=["five_bar", *_WRITERS])
def files(request, tmp_path):
    if request.param == "five_bar":
        urdf = nominal_model_paths()[0].parent / "five_bar.urdf"
        return urdf, urdf.with_name("five_bar.closures.yaml")
    return _WRITERS[request.param](tmp_path / "model")


def _model(files) -> list[str]:
    return ["--model", str(files[0]), "--closures", str(files[1])]


def _simulate(files, measurements: Path, n: int, seed: int, *options: str) -> None:
    """`m3t1r simulate` of `n` poses of the machine with 0.1 mm / 0.1 mrad placement errors (seed `seed`)."""
    errors = ["--sigma-pos", "1e-4", "--sigma-rot", "1e-4"]
    argv = ["simulate", *_model(files), "-n", str(n), "--seed", str(seed), *errors, *options]
    assert main([*argv, "-o", str(measurements)]) == 0


def _calibrate(measurements: Path, files, calibrated: Path, *options: str) -> int:
    """The exit status of `m3t1r calibrate MEASUREMENTS --model --closures -o CALIBRATED OPTIONS...`."""
    return main(["calibrate", str(measurements), *_model(files), "-o", str(calibrated), *options])


@pytest.mark.parametrize("noise_free", [True, False])
def test_simulate_calibrate_evaluate(files, tmp_path, noise_free, capsys):
    measurements, truth_urdf, calibrated = tmp_path / "m.csv", tmp_path / "truth.urdf", tmp_path / "cal.urdf"
    noise = ["--noise-free"] if noise_free else []
    _simulate(files, measurements, 50, 4, *noise, "--truth-urdf", str(truth_urdf))
    assert _calibrate(measurements, files, calibrated, "--report", str(tmp_path / "cal.json")) == 0
    nominal, truth, fitted = Mechanism.load(*files), Mechanism.load(truth_urdf), Mechanism.load(calibrated)
    holdout = workspace_actuators(nominal, 100, np.random.default_rng(9))
    before, after = pose_errors(nominal, truth, holdout), pose_errors(fitted, truth, holdout)
    if noise_free:
        assert after.position_max < 1e-7 and after.rotation_max < 1e-6, (after.position_max, after.rotation_max)
    else:
        assert after.position_rms < 0.1 * before.position_rms and after.rotation_rms < 0.1 * before.rotation_rms
        assert after.position_max < 3e-5 and after.rotation_max < 1e-4
        report = json.loads((tmp_path / "cal.json").read_text())
        assert 0.5 < report["variance_factor"] < 1.5
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                "--truth",
                str(truth_urdf),
                "--calibrated",
                str(calibrated),
                "--model",
                str(files[0]),
                "--closures",
                str(files[1]),
                "-n",
                "50",
            ]
        )
        == 0
    )
    assert "calibrated" in capsys.readouterr().out


def test_ik_fk_compensate_and_view_use_the_task_columns(files, tmp_path):
    nominal = Mechanism.load(*files)
    task = nominal.task
    solver = ClosedLoopSolver(nominal)
    sliders = workspace_actuators(nominal, 6, np.random.default_rng(1))
    poses = solver.forward_batch(sliders).poses
    targets = tmp_path / "targets.csv"
    targets.write_text(
        ",".join(task.columns)
        + "\n"
        + "\n".join(",".join(repr(float(v)) for v in row) for row in task.coordinates(poses))
        + "\n"
    )
    assert main(["ik", str(targets), *_model(files), "-o", str(tmp_path / "s.csv")]) == 0
    read_sliders, _ = read_actuators(tmp_path / "s.csv", nominal)
    np.testing.assert_allclose(read_sliders, sliders, atol=1e-8)
    assert main(["fk", str(tmp_path / "s.csv"), *_model(files), "-o", str(tmp_path / "p.csv")]) == 0
    back = np.array([p.homogeneous for p in poses_from_table(read_table(tmp_path / "p.csv", POSE_COLUMNS))])
    np.testing.assert_allclose(task.coordinates(back), task.coordinates(poses), atol=1e-9)
    # Compensating with the nominal model as "calibrated" changes nothing; the header names the task.
    assert (
        main(
            [
                "compensate",
                str(targets),
                *_model(files),
                "--calibrated",
                str(files[0]),
                "--calibrated-closures",
                str(files[1]),
                "-o",
                str(tmp_path / "c.csv"),
            ]
        )
        == 0
    )
    text = (tmp_path / "c.csv").read_text()
    assert (
        ",".join(task.columns) in text.splitlines()[[line.startswith("#") for line in text.splitlines()].index(False)]
    )
    assert (
        main(
            [
                "view",
                "--model",
                str(files[0]),
                "--closures",
                str(files[1]),
                "--pose",
                *map(str, task.coordinates(poses)[0]),
                "--html",
                str(tmp_path / "page.html"),
            ]
        )
        == 0
    )
    assert "reached by IK on each machine" in (tmp_path / "page.html").read_text()


def test_a_target_file_of_another_task_is_refused(files, tmp_path, capsys):
    targets = tmp_path / "targets.csv"
    targets.write_text("x,y,z,theta\n0.5,0.5,-0.1,0.0\n")
    assert main(["ik", str(targets), *_model(files), "-o", str(tmp_path / "s.csv")]) == 2
    assert "unknown column" in capsys.readouterr().err
    assert not (tmp_path / "s.csv").exists()


def test_plan_draws_in_the_declared_workspace(files, tmp_path):
    plan = tmp_path / "plan.csv"
    assert main(["plan", *_model(files), "-n", "12", "--seed", "2", "-o", str(plan)]) == 0
    nominal = Mechanism.load(*files)
    sliders, _ = read_actuators(plan, nominal)
    assert sliders.shape == (12, len(nominal.actuated_joints))
    lower, upper = nominal.workspace.bounds(nominal.actuated_joints)
    assert np.all(sliders >= lower) and np.all(sliders <= upper)


@pytest.mark.parametrize("writer", [published_five_bar_files, rod_five_bar_files])
def test_joints_named_like_pose_columns_are_recorded_and_read_back(writer, tmp_path, capsys):
    files = writer(tmp_path / "model")
    measurements = tmp_path / "m.csv"
    _simulate(files, measurements, 30, 2, "--with-passive")
    header = next(line for line in measurements.read_text().splitlines() if not line.startswith("#")).split(",")
    assert "joint:x" in header and "joint:y" in header and header[-7:] == ["x", "y", "z", "qx", "qy", "qz", "qw"]
    assert _calibrate(measurements, files, tmp_path / "cal.urdf", "--report", str(tmp_path / "cal.json")) == 0
    assert "passive-joint readings" in capsys.readouterr().out
    assert (
        main(
            [
                "validate",
                str(measurements),
                "--calibrated",
                str(tmp_path / "cal.urdf"),
                "--report",
                str(tmp_path / "cal.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "30 of 30 rows predicted" in out and "heading" not in out  # the task commands no yaw


def test_compensate_report_targets_of_the_measured_point_on_a_position_task(tmp_path, capsys):
    files = published_five_bar_files(tmp_path / "model")
    measurements, calibrated, report = tmp_path / "m.csv", tmp_path / "cal.urdf", tmp_path / "cal.json"
    marker = ["--marker", "0.01", "0.0", "0.005"]
    _simulate(files, measurements, 30, 3, *marker)
    assert _calibrate(measurements, files, calibrated, "--report", str(report), *marker) == 0
    nominal, fitted = Mechanism.load(*files), Mechanism.load(calibrated)
    sliders = workspace_actuators(nominal, 5, np.random.default_rng(4))
    setup = read_report(report).setup
    platform = ClosedLoopSolver(fitted).forward_batch(sliders).poses
    points = [setup.frame.act(pin.SE3(pose).act(setup.marker.translation)) for pose in platform]  # tracker's view [m]
    targets = tmp_path / "t.csv"
    targets.write_text(
        "x,y,z,qx,qy,qz,qw\n" + "".join(",".join(map(repr, map(float, p))) + ",0,0,0,1\n" for p in points)
    )
    out = tmp_path / "c.csv"
    assert (
        main(
            [
                "compensate",
                str(targets),
                *_model(files),
                "--calibrated",
                str(calibrated),
                "--report",
                str(report),
                "--output-kind",
                "actuators",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    assert "tilt" not in capsys.readouterr().out
    np.testing.assert_allclose(read_actuators(out, nominal)[0], sliders, atol=1e-8)


def test_a_stated_noise_below_the_models_floor_is_named_as_the_cause(tmp_path, capsys):
    files = published_five_bar_files(tmp_path / "model")
    measurements = tmp_path / "m.csv"
    _simulate(files, measurements, 30, 3, "--noise-free")
    capsys.readouterr()
    stated = ["--noise-pos", "1e-15", "--noise-rot", "1e-15", "--noise-act", "1e-15"]
    assert _calibrate(measurements, files, tmp_path / "cal.urdf", *stated) == 1
    err = capsys.readouterr().err
    assert "is below what the model can fit" in err and "--marker" not in err, err
    assert not (tmp_path / "cal.urdf").exists()
    # The rotation noise estimated (`auto`): the cause names the stated position noise alone, as a number.
    assert _calibrate(measurements, files, tmp_path / "cal.urdf", "--noise-pos", "1e-15", "--noise-rot", "auto") == 1
    err = capsys.readouterr().err
    assert "likely cause: the stated noise (1e-15 m) is below what the model can fit" in err, err
    assert not (tmp_path / "cal.urdf").exists()


def test_view_draws_a_machine_published_without_its_meshes(tmp_path, capsys):
    urdf, closures = rod_five_bar_files(tmp_path / "model")
    urdf.write_text(
        urdf.read_text().replace(
            '<link name="rod"/>',
            '<link name="rod"><visual><geometry><mesh filename="package://meshes/rod.stl"/></geometry></visual></link>',
        )
    )
    page = tmp_path / "page.html"
    assert main(["view", "--model", str(urdf), "--closures", str(closures), "--html", str(page)]) == 0
    assert "drawing rod_five_bar.urdf as spheres at its joints" in capsys.readouterr().err
    assert page.stat().st_size > 0


# ------------------------------------------------------------------------------------------------
# tools/check_mechanism.py: every verb on a mechanism folder, judged against the done-when figures


def _check_mechanism_tool():
    spec = importlib.util.spec_from_file_location("check_mechanism", TOOLS / "check_mechanism.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses resolve their annotations there
    spec.loader.exec_module(module)
    return module


def _in_process(tool, work: Path):
    class InProcess(tool.Runner):  # the same verbs through cli.main, without a Python start per command
        def __call__(self, *args: str) -> str:
            out, err = io.StringIO(), io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                status = main(list(args))
            if status != 0:
                raise tool.CommandFailed(f"m3t1r {args[0]} exited {status}: {err.getvalue().strip()}")
            return out.getvalue() + err.getvalue()

    return InProcess([], work)


def _checked_in(work: Path, monkeypatch, tool, urdf: Path, closures: Path) -> list:
    """`tool.check` of a pair, every verb run in process from a fresh working folder `work`."""
    work.mkdir()
    monkeypatch.chdir(work)
    return tool.check(urdf, closures, _in_process(tool, work))


def test_check_mechanism_passes_every_verb_on_a_first_time_five_bar(tmp_path, monkeypatch):
    tool = _check_mechanism_tool()
    urdf, closures = first_time_five_bar_files(tmp_path / "model")
    figures = _checked_in(tmp_path / "work", monkeypatch, tool, urdf, closures)
    printed = tool.table("first_time_five_bar", figures)
    assert len(figures) == 12 and all(f.passed for f in figures), printed
    fk = next(f for f in figures if f.check.startswith("fk vs independent"))
    assert fk.value <= 1e-9 and "pass" in printed and "FAIL" not in printed


def test_check_mechanism_from_actuator_values_alone_checks_the_home_then_every_verb(tmp_path, monkeypatch):
    """A closures file whose home gives only the actuators, with no assembled one beside it: the
    tool checks the home m3t1r assembled (it closes under the independent rows, and is no farther
    from the given values than a least-squares assembly), then every verb from it."""
    tool = _check_mechanism_tool()
    urdf, closures = first_time_five_bar_files(tmp_path / "model")
    document = yaml.safe_load(closures.read_text())
    document["home"] = {name: document["home"][name] for name in document["actuated_joints"]}
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    figures = _checked_in(tmp_path / "work", monkeypatch, tool, urdf, closures)
    printed = tool.table("rough five_bar", figures)
    assert len(figures) == 14 and all(f.passed for f in figures), printed
    assert figures[0].check.startswith("home by m3t1r") and figures[0].value <= 1e-9


def test_check_mechanism_reports_a_file_that_does_not_load_as_a_failed_line(tmp_path):
    """A closures file the verbs refuse (the first-time five-bar's loop cut to its x row, which leaves
    the effector free) is one failed `load` line with the refusal, not a traceback of the tool."""
    tool = _check_mechanism_tool()
    urdf, closures = first_time_five_bar_files(tmp_path / "model")
    document = yaml.safe_load(closures.read_text())
    document["closures"][0]["rows"] = [0]
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    (figure,) = tool.check(urdf, closures, _in_process(tool, tmp_path))
    assert (figure.check, figure.passed) == ("load", False) and "degree(s) of freedom" in figure.detail


def test_check_mechanism_fails_a_figure_out_of_its_rule():
    tool = _check_mechanism_tool()
    assert not tool.within("held-out max [m]", 2e-7, None, 1e-7).passed
    assert tool.within("ratio", 0.7, 0.67, 1.5).passed and not tool.within("ratio", 0.6, 0.67, 1.5).passed
    assert not tool.within("nan", float("nan"), None, 1.0).passed
    assert "FAIL" in tool.table("t", [tool.Figure("plan", None, "runs", False, "exited 2")])
