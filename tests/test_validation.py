"""`m3t1r validate` and `m3t1r.calibration.validation`: predictions through the measurement frame and marker,
units, flags, failed rows, PRED.csv, and typed errors for bad reports and files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import scipy.special
import scipy.stats
from command_lines import run_campaign_verb as run

from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurement_setup import MeasurementSetup, se3_to_report
from m3t1r.calibration.measurements import TrackerNoise, measure
from m3t1r.calibration.serial_robots import example_robot_data_dir, load_example_robot
from m3t1r.calibration.serial_simulation import sample_configurations
from m3t1r.calibration.simulation import actual_machine, random_placement_errors
from m3t1r.calibration.validation import read_report, sigma_equivalent, validate
from m3t1r.errors import DataFileError, InvalidInputError, ModelFileError
from m3t1r.io.poses import POSE_COLUMNS, pose_rows
from m3t1r.io.tables import read_table, write_table
from m3t1r.model.poe import SerialChain, tool_poses
from m3t1r.model.workspace import workspace_actuators

N_ROWS = 12
SETUP = MeasurementSetup(
    pin.SE3(pin.utils.rpyToMatrix(0.1, -0.2, 2.5), np.array([3.0, -1.5, 0.8])),
    pin.SE3(pin.utils.rpyToMatrix(0.3, 0.0, -0.4), np.array([0.05, -0.02, 0.11])),
)


def validate_argv(measurements: Path, calibrated: Path, report: Path, *options: object) -> list[str]:
    """`m3t1r validate MEASUREMENTS --calibrated URDF --report JSON OPTIONS...` as an argument list."""
    return ["validate", str(measurements), "--calibrated", str(calibrated), "--report", str(report), *map(str, options)]


def report_document(kind: str = "closed_loop", units: str = "m", **nominal) -> dict:
    return {
        "kind": kind,
        "input": {"path": "cal.csv", "sha256": "0" * 64, "poses": 40, "position_only": False, "units": units},
        "nominal_model": nominal or {"urdf": "nominal.urdf", "closures": "nominal.closures.yaml"},
        "measured_frame": "P_I" if kind == "closed_loop" else nominal.get("tool"),
        "measurement_frame": {**se3_to_report(SETUP.frame), "estimated": True},
        "marker": {**se3_to_report(SETUP.marker), "estimated": True},
        "noise_model": {"position_m": 10e-6, "rotation_rad": 20e-6, "actuator_m": 1e-6},
        "converged": True,
        "variance_factor": 1.0,
        "outliers": [],
        "cross_validation": {"position_mean_m": 1e-5, "rotation_mean_rad": 2e-5, "folds": 5},
    }


def write_campaign(
    path: Path,
    columns,
    readings,
    poses: np.ndarray,
    scale: float = 1.0,
    position_only: bool = False,
    extra: dict[int, str] | None = None,
) -> None:
    """A measurement CSV: readings (N, n) and poses (N, 4, 4) [m], lengths divided by `scale` (1e-3: mm)."""
    rows = pose_rows([pin.SE3(p) for p in poses])
    rows[:, :3] /= scale
    data = np.hstack((readings, rows[:, :3] if position_only else rows))
    names = list(columns) + list(POSE_COLUMNS[:3] if position_only else POSE_COLUMNS)
    write_table(path, names, data, ["a tracker campaign, " + ("mm" if scale != 1.0 else "m")])


@pytest.fixture(scope="module")
def machine(tmp_path_factory, mechanism):
    """A truth machine saved as the 'calibrated' model, its report, and noise-free measurements of it."""
    folder = tmp_path_factory.mktemp("validate")
    rng = np.random.default_rng(7)
    truth = actual_machine(mechanism, random_placement_errors(ClosedLoopErrorModel(mechanism), rng, 1e-3, 1e-3))
    truth.save(folder / "cal.urdf", folder / "cal.closures.yaml")
    sliders = workspace_actuators(mechanism, N_ROWS, rng)
    exact = measure(truth, sliders, setup=SETUP)
    poses = np.array([p.homogeneous for p in exact.poses])
    (folder / "report.json").write_text(json.dumps(report_document()))
    write_campaign(folder / "exact.csv", mechanism.actuated_joints, sliders, poses)
    noisy = measure(truth, sliders, rng, TrackerNoise(), setup=SETUP)
    return folder, truth, sliders, poses, noisy


def test_noise_free_rows_are_predicted_exactly_through_frame_and_marker(machine, capsys) -> None:
    folder, _, _, poses, _ = machine
    assert (
        run(
            validate_argv(
                folder / "exact.csv", folder / "cal.urdf", folder / "report.json", "--predictions", folder / "pred.csv"
            )
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "position [m]" in out and "heading |yaw| [rad]" in out and "rows beyond 5 sigma" in out
    assert "FLAGGED" not in out
    table = read_table(folder / "pred.csv", required=POSE_COLUMNS)
    np.testing.assert_allclose(
        np.column_stack([table.column(c) for c in POSE_COLUMNS]), pose_rows([pin.SE3(p) for p in poses]), atol=1e-9
    )
    result = validate(folder / "exact.csv", folder / "cal.urdf", folder / "report.json")
    assert result.predictions.shape == (N_ROWS, 4, 4) and result.failures == () and result.flagged == ()
    assert result.errors.position_max < 1e-9 and result.errors.rotation_max < 1e-9
    assert np.max(np.abs(result.heading)) < 1e-9
    with pytest.raises(AttributeError):
        result.flagged = (1,)  # frozen


def test_without_the_setup_every_row_is_off_by_metres(machine, tmp_path) -> None:
    folder, *_ = machine
    document = report_document()
    document["measurement_frame"] = {**se3_to_report(pin.SE3.Identity()), "estimated": False}
    (tmp_path / "identity.json").write_text(json.dumps(document))
    result = validate(folder / "exact.csv", folder / "cal.urdf", tmp_path / "identity.json")
    assert result.errors.position_mean > 1.0 and len(result.flagged) == N_ROWS


def test_millimetre_file_gives_the_same_errors_and_predictions_in_mm(machine, tmp_path, mechanism, capsys) -> None:
    folder, _, sliders, poses, noisy = machine
    noisy_poses = np.array([p.homogeneous for p in noisy.poses])
    write_campaign(tmp_path / "m.csv", mechanism.actuated_joints, sliders, noisy_poses)
    write_campaign(tmp_path / "mm.csv", mechanism.actuated_joints, sliders * 1e3, noisy_poses, scale=1e-3)
    in_m = validate(tmp_path / "m.csv", folder / "cal.urdf", folder / "report.json")
    in_mm = validate(tmp_path / "mm.csv", folder / "cal.urdf", folder / "report.json", units="mm")
    np.testing.assert_allclose(in_mm.errors.position, in_m.errors.position, rtol=1e-6, atol=1e-12)
    assert 3e-6 < in_m.errors.position_mean < 4e-5 and 5e-6 < in_m.errors.rotation_mean < 8e-5  # ~1.6 sigma
    assert (
        run(
            validate_argv(
                tmp_path / "mm.csv",
                folder / "cal.urdf",
                folder / "report.json",
                "--units",
                "mm",
                "--predictions",
                tmp_path / "pred.csv",
            )
        )
        == 0
    )
    assert "position [mm]" in capsys.readouterr().out
    table = read_table(tmp_path / "pred.csv", required=POSE_COLUMNS)
    np.testing.assert_allclose(table.column("x"), poses[:, 0, 3] * 1e3, atol=1e-6)
    # Without --units, the unit of the calibration input (the report's input.units) applies.
    document = report_document(units="mm")
    (tmp_path / "mm.json").write_text(json.dumps(document))
    default = validate(tmp_path / "mm.csv", folder / "cal.urdf", tmp_path / "mm.json")
    assert default.units == "mm" and default.errors.position_mean == pytest.approx(in_m.errors.position_mean)


def test_gross_errors_are_flagged_by_line_and_exit_status_stays_zero(machine, tmp_path, mechanism, capsys) -> None:
    folder, _, sliders, _, noisy = machine
    poses = np.array([p.homogeneous for p in noisy.poses])
    poses[[2, 7], :3, 3] += np.array([[2e-4, 0, 0], [0, 0, -3e-4]])
    write_campaign(tmp_path / "spoiled.csv", mechanism.actuated_joints, sliders, poses)
    assert run(validate_argv(tmp_path / "spoiled.csv", folder / "cal.urdf", folder / "report.json")) == 0
    out = capsys.readouterr().out
    lines = read_table(tmp_path / "spoiled.csv", required=mechanism.actuated_joints, optional=POSE_COLUMNS).line_numbers
    assert out.count("FLAGGED") == 2
    result = validate(tmp_path / "spoiled.csv", folder / "cal.urdf", folder / "report.json")
    assert result.flagged == (int(lines[2]), int(lines[7]))
    assert np.all(result.sigmas[[2, 7]] > 5) and np.all(np.delete(result.sigmas, [2, 7]) < 5)
    assert result.gate == pytest.approx(scipy.stats.chi2.isf(2 * scipy.stats.norm.sf(5.0), 6))


def test_position_only_gate_is_chi_square_with_three_dof(machine, tmp_path, mechanism) -> None:
    folder, _, sliders, _, noisy = machine
    poses = np.array([p.homogeneous for p in noisy.poses])
    poses[4, :3, 3] += np.array([0.0, 6.2e-5, 0.0])  # ~6 sigma_p on top of noise: beyond 5.64, below 8.66
    write_campaign(tmp_path / "xyz.csv", mechanism.actuated_joints, sliders, poses, position_only=True)
    result = validate(tmp_path / "xyz.csv", folder / "cal.urdf", folder / "report.json")
    assert result.position_only and np.all(np.isnan(result.errors.rotation)) and result.heading is None
    assert result.gate == pytest.approx(31.81, abs=0.01)
    assert int(result.lines[4]) in result.flagged


def test_rows_that_do_not_assemble_are_listed_and_the_rest_assessed(machine, tmp_path, mechanism, capsys) -> None:
    folder, _, sliders, poses, _ = machine
    bad = sliders.copy()
    bad[3, 0] = 0.75  # beyond the slider limit 0.6 m
    write_campaign(tmp_path / "bad.csv", mechanism.actuated_joints, bad, poses)
    line = int(
        read_table(tmp_path / "bad.csv", required=mechanism.actuated_joints, optional=POSE_COLUMNS).line_numbers[3]
    )
    common = validate_argv(tmp_path / "bad.csv", folder / "cal.urdf", folder / "report.json")
    assert run(common) == 0
    out = capsys.readouterr().out
    assert f"line {line} not predicted" in out and f"{N_ROWS - 1} of {N_ROWS} rows predicted" in out
    result = validate(tmp_path / "bad.csv", folder / "cal.urdf", folder / "report.json")
    assert [f[0] for f in result.failures] == [line] and np.all(np.isnan(result.predictions[3]))
    assert result.errors.position_max < 1e-9
    assert run(common + ["--predictions", str(tmp_path / "pred.csv")]) == 1
    assert f"line {line}" in capsys.readouterr().out and not (tmp_path / "pred.csv").exists()


def test_the_reports_variance_factor_widens_the_gate(machine, tmp_path, mechanism) -> None:
    folder, _, sliders, _, noisy = machine
    poses = np.array([p.homogeneous for p in noisy.poses])
    poses[5, :3, 3] += np.array([1.2e-4, 0.0, 0.0])  # about 12 sigma_p
    write_campaign(tmp_path / "one.csv", mechanism.actuated_joints, sliders, poses)
    assert len(validate(tmp_path / "one.csv", folder / "cal.urdf", folder / "report.json").flagged) == 1
    document = report_document()
    document["variance_factor"] = 9.0  # the calibration saw 3x the stated noise
    (tmp_path / "wide.json").write_text(json.dumps(document))
    wide = validate(tmp_path / "one.csv", folder / "cal.urdf", tmp_path / "wide.json")
    assert wide.scale == pytest.approx(3.0) and wide.flagged == ()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.update(kind="paper"), "'kind'"),
        (lambda d: d.pop("kind"), "'kind' is missing"),
        (lambda d: d["noise_model"].pop("position_m"), "'noise_model.position_m' is missing"),
        (lambda d: d["noise_model"].update(rotation_rad=-1), "'noise_model.rotation_rad' must be a positive"),
        (lambda d: d.pop("marker"), "'marker' is missing"),
        (lambda d: d["measurement_frame"].update(quaternion=[0, 0, 0, 2]), "measurement_frame"),
        (lambda d: d.update(measured_frame="tool0"), "'measured_frame'"),
        (lambda d: d.update(variance_factor="big"), "'variance_factor'"),
    ],
)
def test_bad_reports_are_refused_naming_file_and_field(machine, tmp_path, edit, message, capsys) -> None:
    folder, *_ = machine
    document = report_document()
    edit(document)
    (tmp_path / "bad.json").write_text(json.dumps(document))
    with pytest.raises(InvalidInputError, match=message) as caught:
        validate(folder / "exact.csv", folder / "cal.urdf", tmp_path / "bad.json")
    assert "bad.json" in str(caught.value)
    assert run(validate_argv(folder / "exact.csv", folder / "cal.urdf", tmp_path / "bad.json")) == 2


def test_missing_files_are_typed_errors_naming_the_file(machine, tmp_path) -> None:
    folder, *_ = machine
    with pytest.raises(InvalidInputError, match="nowhere.json"):
        validate(folder / "exact.csv", folder / "cal.urdf", tmp_path / "nowhere.json")
    with pytest.raises(DataFileError, match="nowhere.csv"):
        validate(tmp_path / "nowhere.csv", folder / "cal.urdf", folder / "report.json")
    with pytest.raises(ModelFileError, match="nowhere.urdf"):
        validate(folder / "exact.csv", tmp_path / "nowhere.urdf", folder / "report.json")
    (tmp_path / "text.json").write_text("not json")
    with pytest.raises(InvalidInputError, match="text.json: not a JSON report"):
        read_report(tmp_path / "text.json")


def test_predictions_never_overwrite_an_input(machine, capsys) -> None:
    folder, *_ = machine
    before = (folder / "exact.csv").read_bytes()
    assert (
        run(
            validate_argv(
                folder / "exact.csv", folder / "cal.urdf", folder / "report.json", "--predictions", folder / "exact.csv"
            )
        )
        == 2
    )
    assert (folder / "exact.csv").read_bytes() == before
    assert "refusing to overwrite the input" in capsys.readouterr().out


@pytest.fixture(scope="module")
def serial_robot():
    urdf = example_robot_data_dir() / "ur_description" / "urdf" / "ur5_robot.urdf"
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    return urdf, model, chain


def test_serial_rows_are_predicted_through_the_reports_chain(serial_robot, tmp_path, capsys) -> None:
    urdf, model, chain = serial_robot
    q = sample_configurations(model, chain, 10, np.random.default_rng(3))
    measured = SETUP.measured_poses(tool_poses(chain, model, q))
    write_campaign(tmp_path / "ur5.csv", chain.joint_names, q, measured, scale=1e-3)
    document = report_document("serial", "mm", robot="ur5", base=None, tool="tool0", chain=list(chain.joint_names))
    (tmp_path / "report.json").write_text(json.dumps(document))
    result = validate(tmp_path / "ur5.csv", urdf, tmp_path / "report.json")
    assert result.kind == "serial" and result.heading is None
    assert result.errors.position_max < 1e-9 and result.errors.rotation_max < 1e-9
    assert (
        run(validate_argv(tmp_path / "ur5.csv", urdf, tmp_path / "report.json", "--predictions", tmp_path / "pred.csv"))
        == 0
    )
    assert "heading" not in capsys.readouterr().out
    table = read_table(tmp_path / "pred.csv", required=POSE_COLUMNS)
    np.testing.assert_allclose(table.column("z"), measured[:, 2, 3] * 1e3, atol=1e-6)
    document["nominal_model"]["chain"] = list(chain.joint_names[:-1])
    (tmp_path / "short.json").write_text(json.dumps(document))
    with pytest.raises(InvalidInputError, match="'nominal_model.chain'"):
        validate(tmp_path / "ur5.csv", urdf, tmp_path / "short.json")
    document["nominal_model"]["tool"] = "no_such_frame"
    document["measured_frame"] = "no_such_frame"
    (tmp_path / "tool.json").write_text(json.dumps(document))
    with pytest.raises(ModelFileError, match="no_such_frame"):
        validate(tmp_path / "ur5.csv", urdf, tmp_path / "tool.json")


def test_sigma_equivalent_inverts_the_gate() -> None:
    gate3 = scipy.stats.chi2.isf(2 * scipy.stats.norm.sf(5.0), 3)
    np.testing.assert_allclose(sigma_equivalent(np.array([gate3, 1.0]), 3)[0], 5.0, rtol=1e-9)
    assert sigma_equivalent(np.array([1e6]), 6)[0] == pytest.approx(1e3)  # beyond double range: sqrt(d^2)
    z = sigma_equivalent(np.array([scipy.stats.chi2.isf(2 * scipy.stats.norm.sf(2.0), 6)]), 6)
    assert z[0] == pytest.approx(2.0, rel=1e-9)


@pytest.mark.parametrize("dof", [3, 6])
def test_sigma_equivalent_follows_the_chi2_tail_below_and_above_its_median(dof: int) -> None:
    d2 = np.array([0.05, 0.5, 0.9 * dof, 1.1 * dof, 3.0 * dof, 200.0])  # the median of chi^2_k is near k
    expected = -scipy.special.ndtri_exp(scipy.stats.chi2.logsf(d2, dof) - np.log(2.0))
    np.testing.assert_allclose(sigma_equivalent(d2, dof), expected, rtol=1e-10)
    assert np.all(np.diff(sigma_equivalent(d2, dof)) > 0)


def test_exit_statuses_through_the_main_command_line(machine, tmp_path, mechanism, capsys) -> None:
    from m3t1r.app.cli import main

    folder, _, sliders, poses, _ = machine
    common = ["validate", str(folder / "exact.csv"), "--calibrated", str(folder / "cal.urdf"), "--report"]
    assert main(["-q", *common, str(folder / "report.json"), "--predictions", str(tmp_path / "pred.csv")]) == 0
    assert main([*common, str(tmp_path / "nowhere.json")]) == 2
    bad = sliders.copy()
    bad[0, 0] = 0.75
    write_campaign(tmp_path / "bad.csv", mechanism.actuated_joints, bad, poses)
    assert (
        main(
            validate_argv(
                tmp_path / "bad.csv",
                folder / "cal.urdf",
                folder / "report.json",
                "--predictions",
                tmp_path / "bad_pred.csv",
            )
        )
        == 1
    )
    assert not (tmp_path / "bad_pred.csv").exists()
    assert "m3t1r: error:" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # refused by argparse, with the usage line
        main(["plan", "-n", "0", "-o", str(tmp_path / "plan.csv")])
    assert exit_info.value.code == 2 and "argument -n: expected at least 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda text: text.replace('"kind": "closed_loop"', '"kind": "serial", "kind": "closed_loop"', 1),
            "key 'kind' given twice in one object",
        ),
        (lambda text: text.replace('"variance_factor": ', '"variance_factor": NaN, "x": ', 1), "'NaN' is not JSON"),
    ],
)
def test_a_report_with_a_key_twice_or_nan_is_refused(machine, tmp_path, edit, message) -> None:
    """Python's reader let the last of two keys win silently and read NaN."""
    folder, *_ = machine
    text = json.dumps(report_document())
    assert edit(text) != text
    (tmp_path / "bad.json").write_text(edit(text))
    with pytest.raises(InvalidInputError, match=message):
        validate(folder / "exact.csv", folder / "cal.urdf", tmp_path / "bad.json")


# ------------------------------------------------------------------------------------------
# Plots (validate --plots DIR)

VALIDATION_PLOTS = ("error_histogram.png", "normalised_errors_qq.png", "errors_over_workspace.png")


def png_description(path: Path) -> str:
    """The PNG's Description text chunk: what the figure marks, in words."""
    from PIL import Image

    with Image.open(path) as image:
        assert image.format == "PNG" and image.size[0] > 400 and image.size[1] > 300
        return image.text.get("Description", "")


def write_converted_campaign(path: Path, columns, readings, poses: np.ndarray) -> None:
    """A measurement CSV as `m3t1r convert` writes it: with the tracker file's `source` of every pose."""
    rows = pose_rows([pin.SE3(p) for p in poses])
    sources = 1000.0 + 5.0 * np.arange(len(rows))[:, None]
    write_table(path, [*columns, *POSE_COLUMNS, "source"], np.hstack((readings, rows, sources)), ["converted"])


def test_plots_name_the_flagged_rows_by_source_and_are_written_as_a_unit(machine, tmp_path, mechanism, capsys) -> None:
    folder, _, sliders, _, noisy = machine
    poses = np.array([p.homogeneous for p in noisy.poses])
    poses[[2, 7], :3, 3] += np.array([[2e-4, 0, 0], [0, 0, -3e-4]])
    write_converted_campaign(tmp_path / "converted.csv", mechanism.actuated_joints, sliders, poses)
    lines = read_table(
        tmp_path / "converted.csv", required=mechanism.actuated_joints, optional=(*POSE_COLUMNS, "source")
    ).line_numbers
    common = validate_argv(tmp_path / "converted.csv", folder / "cal.urdf", folder / "report.json")
    assert run(common + ["--plots", str(tmp_path / "plots"), "--predictions", str(tmp_path / "pred.csv")]) == 0
    out = capsys.readouterr().out
    assert "wrote 12 predicted measurements" in out and "error_histogram.png" in out
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == sorted(VALIDATION_PLOTS)
    named = f"flagged: source 1010 (line {lines[2]}), source 1035 (line {lines[7]})"
    for name in VALIDATION_PLOTS:
        assert png_description(tmp_path / "plots" / name) == named, name

    result = validate(tmp_path / "converted.csv", folder / "cal.urdf", folder / "report.json")
    assert result.sources == pytest.approx(1000.0 + 5.0 * np.arange(N_ROWS))
    assert result.noise == (10e-6, 20e-6) and result.residuals.shape == (N_ROWS, 6)
    np.testing.assert_allclose(np.sum(result.residuals**2, axis=1), result.statistic, rtol=1e-9)
    sound = np.delete(result.residuals, [2, 7], axis=0)
    assert 0.4 < np.mean(sound**2) < 2.0  # the simulated noise is the report's: N(0, 1) coordinates
    assert np.abs(result.residuals[2, 0]) > 15 and np.abs(result.residuals[7, 2]) > 25

    # A file that cannot be predicted whole refuses its predictions, and the plots with them.
    bad = sliders.copy()
    bad[3, 0] = 0.75  # beyond the slider limit
    write_converted_campaign(tmp_path / "bad.csv", mechanism.actuated_joints, bad, poses)
    common[1] = str(tmp_path / "bad.csv")
    assert run(common + ["--plots", str(tmp_path / "again"), "--predictions", str(tmp_path / "bad_pred.csv")]) == 1
    assert not (tmp_path / "bad_pred.csv").exists() and not list((tmp_path / "again").glob("*"))
    # Without --predictions, the plots show the rows that were predicted.
    assert run(common + ["--plots", str(tmp_path / "again")]) == 0
    assert png_description(tmp_path / "again" / VALIDATION_PLOTS[0]).startswith("flagged: source 1010")


def test_plots_of_a_position_only_file_without_sources(machine, tmp_path, mechanism) -> None:
    folder, _, sliders, _, noisy = machine
    poses = np.array([p.homogeneous for p in noisy.poses])
    poses[4, :3, 3] += np.array([0.0, 2e-4, 0.0])
    write_campaign(tmp_path / "xyz.csv", mechanism.actuated_joints, sliders, poses, position_only=True)
    table = read_table(tmp_path / "xyz.csv", required=mechanism.actuated_joints, optional=("x", "y", "z"))
    line = table.line_numbers[4]
    assert (
        run(
            validate_argv(
                tmp_path / "xyz.csv", folder / "cal.urdf", folder / "report.json", "--plots", tmp_path / "plots"
            )
        )
        == 0
    )
    for name in VALIDATION_PLOTS:
        assert png_description(tmp_path / "plots" / name) == f"flagged: line {line}", name
    assert validate(tmp_path / "xyz.csv", folder / "cal.urdf", folder / "report.json").residuals.shape == (N_ROWS, 3)


def test_plots_into_a_file_are_refused_before_any_work(machine, capsys) -> None:
    folder, *_ = machine
    inputs = {p: p.read_bytes() for p in folder.iterdir() if p.is_file()}
    assert (
        run(
            validate_argv(
                folder / "exact.csv", folder / "cal.urdf", folder / "report.json", "--plots", folder / "exact.csv"
            )
        )
        == 2
    )
    out = capsys.readouterr().out
    assert "exact.csv" in out and "rows predicted" not in out  # refused before the prediction
    assert {p: p.read_bytes() for p in folder.iterdir() if p.is_file()} == inputs
