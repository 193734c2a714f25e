"""The command line: round trips, row-numbered failures, atomic outputs, protected inputs."""

import json

import closed_form
import numpy as np
import pytest

from m3t1r.app.cli import main
from m3t1r.app.datasets import check_joint_readings, read_actuators
from m3t1r.errors import DataFileError
from m3t1r.io.poses import POSE_COLUMNS, poses_from_table
from m3t1r.io.tables import read_table
from m3t1r.model.description import Mechanism, nominal_model_paths
from m3t1r.model.design import NOMINAL
from m3t1r.model.examples import five_bar_files
from m3t1r.model.kinematics import yaw_of


def _write(path, text):
    path.write_text(text)
    return path


def test_help_lists_the_verbs(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for verb in ("fk", "ik", "simulate", "calibrate", "evaluate", "compensate", "view", "demo"):
        assert verb in out


def test_ik_then_fk_round_trip(tmp_path):
    poses = NOMINAL.workspace.sample(np.random.default_rng(0), 8)
    lines = ["# targets", "x,y,z,theta"] + [",".join(repr(float(v)) for v in row) for row in poses]
    targets = _write(tmp_path / "targets.csv", "\n".join(lines) + "\n")
    assert main(["ik", str(targets), "-o", str(tmp_path / "sliders.csv")]) == 0
    assert main(["fk", str(tmp_path / "sliders.csv"), "-o", str(tmp_path / "poses.csv")]) == 0
    reached = poses_from_table(read_table(tmp_path / "poses.csv", POSE_COLUMNS))
    np.testing.assert_allclose([p.translation for p in reached], poses[:, :3], atol=1e-10)
    np.testing.assert_allclose([yaw_of(p.rotation) for p in reached], poses[:, 3], atol=1e-10)
    sliders, _ = read_actuators(tmp_path / "sliders.csv", Mechanism.load())
    np.testing.assert_allclose(sliders, [closed_form.inverse(p) for p in poses], atol=1e-10)


def test_failing_rows_are_reported_by_line_and_nothing_is_written(tmp_path, capsys):
    targets = _write(tmp_path / "t.csv", "x,y,z,theta\n0.5,0.5,-0.1,0\n3.0,0.5,-0.1,0\n0.5,1.2,-0.1,0\n")
    output = _write(tmp_path / "out.csv", "precious\n")
    assert main(["ik", str(targets), "-o", str(output)]) == 1
    err = capsys.readouterr().err
    assert "2 row(s) failed" in err and "line 3:" in err and "line 4:" in err and "beyond its limit" in err
    assert output.read_text() == "precious\n"


def test_bad_actuator_file_names_line_and_column(tmp_path, capsys):
    sliders = _write(tmp_path / "s.csv", "q11,q11_B2,q21,q21_B4\n0,0,0,0\n0,0.9,0,0\n")
    assert main(["fk", str(sliders), "-o", str(tmp_path / "p.csv")]) == 2
    err = capsys.readouterr().err
    assert "line 3" in err and "q11_B2" in err and "beyond the joint limit" in err
    assert not (tmp_path / "p.csv").exists()
    other = _write(tmp_path / "o.csv", "shoulder,elbow,q21,q21_B4\n0,0,0,0\n")
    assert main(["fk", str(other), "-o", str(tmp_path / "p.csv")]) == 2
    assert "unknown columns" in capsys.readouterr().err


def test_simulate_calibrate_evaluate(tmp_path, capsys):
    meas, truth, cal = tmp_path / "m.csv", tmp_path / "truth.urdf", tmp_path / "cal.urdf"
    assert main(["simulate", "-n", "50", "--seed", "3", "-o", str(meas), "--truth-urdf", str(truth)]) == 0
    assert main(["calibrate", str(meas), "-o", str(cal), "--report", str(tmp_path / "r.json")]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["identifiable"]["count"] == 56 and len(report["parameters"]) == 204
    assert report["residual_rms"]["after"]["position_m"] < 3e-5 < report["residual_rms"]["before"]["position_m"]
    assert len(report["input"]["sha256"]) == 64
    reloaded = Mechanism.load(cal, tmp_path / "cal.closures.yaml")  # the pair loads and its home closes
    assert reloaded.model.nq == 20
    capsys.readouterr()
    assert main(["evaluate", "--truth", str(truth), "--calibrated", str(cal), "-n", "50"]) == 0
    out = capsys.readouterr().out
    calibrated_mean = float(out.split("calibrated")[1].split()[0])
    nominal_mean = float(out.split("nominal")[1].split()[0])
    assert calibrated_mean < 3e-5 and nominal_mean > 1e-3


def test_calibrate_never_overwrites_its_inputs(tmp_path, capsys):
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "12", "-o", str(meas)]) == 0
    before = meas.read_bytes()
    nominal_urdf, _ = nominal_model_paths()
    nominal_bytes = nominal_urdf.read_bytes()
    assert main(["calibrate", str(meas), "-o", str(meas)]) == 2
    assert main(["calibrate", str(meas), "-o", str(nominal_urdf)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert meas.read_bytes() == before and nominal_urdf.read_bytes() == nominal_bytes


def test_calibrate_refuses_a_plots_folder_that_is_a_file_before_writing_anything(tmp_path, capsys):
    """`--plots` naming an existing file (here the measurements): refused by name before the fit, the
    file and everything else left alone, where it failed with 'File exists' after writing the fit."""
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "12", "-o", str(meas)]) == 0
    before = meas.read_bytes()
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--plots", str(meas)]) == 2
    assert f"{meas}: exists and is not a folder (the plots go into a folder)" in capsys.readouterr().err
    assert meas.read_bytes() == before and not (tmp_path / "c.urdf").exists()


@pytest.mark.parametrize(
    "mutate,message",
    [
        (lambda rows: rows.__setitem__(2, rows[2].replace(rows[2].split(",")[4], "nan", 1)), "is not finite"),
        (lambda rows: rows.insert(3, rows[2]), "row repeats line"),
        (lambda rows: rows.__setitem__(2, ",".join(rows[2].split(",")[:-1] + ["0.5"])), "quaternion"),
        (lambda rows: rows.__setitem__(1, rows[1].replace("q21_B4", "q99")), "q99"),
    ],
)
def test_bad_measurement_files_write_nothing(tmp_path, capsys, mutate, message):
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "12", "-o", str(meas)]) == 0
    rows = [line for line in meas.read_text().splitlines() if not line.startswith("#")]
    rows.insert(0, "# edited")
    mutate(rows)
    meas.write_text("\n".join(rows) + "\n")
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "c.urdf").exists() and not (tmp_path / "c.closures.yaml").exists()


def test_too_few_poses(tmp_path, capsys):
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "6", "-o", str(meas)]) == 0
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf")]) == 2
    assert "identify only" in capsys.readouterr().err
    assert not (tmp_path / "c.urdf").exists()


def test_paper_closed_refuses_a_passive_source_it_would_ignore(capsys):
    assert main(["paper", "--closed", "--passive-from", "distance"]) == 2
    assert "--passive-from applies to the two-chain study only" in capsys.readouterr().err


@pytest.fixture(scope="module")
def old_calibration(tmp_path_factory):
    """30 simulated measurements and a finished calibration of them (pair and report) to protect."""
    folder = tmp_path_factory.mktemp("old_calibration")
    meas = folder / "m.csv"
    assert main(["simulate", "-n", "30", "--seed", "4", "-o", str(meas)]) == 0
    assert main(["calibrate", str(meas), "-o", str(folder / "c.urdf"), "--report", str(folder / "c.json")]) == 0
    return folder


def _contents(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def test_calibrate_plots_that_cannot_be_written_are_refused_before_the_fit(old_calibration, tmp_path, capsys):
    """A plot file the plots folder cannot take (here a directory in its place) is refused before the
    fit, like any output, where the pair and the report used to be replaced first and exit 2 follow."""
    before = _contents(old_calibration)
    plots = tmp_path / "plots"
    (plots / "error_vs_poses.png").mkdir(parents=True)
    capsys.readouterr()
    assert (
        main(
            [
                "calibrate",
                str(old_calibration / "m.csv"),
                "-o",
                str(old_calibration / "c.urdf"),
                "--report",
                str(old_calibration / "c.json"),
                "--plots",
                str(plots),
            ]
        )
        == 2
    )
    out, err = capsys.readouterr()
    assert f"{plots / 'error_vs_poses.png'}: --plots is a directory, expected a file path" in err
    assert "calibrating from" not in out and _contents(old_calibration) == before


def test_calibrate_plots_failing_after_the_fit_leave_every_old_file(old_calibration, tmp_path, capsys, monkeypatch):
    """A plot that fails to render or write after the fit (a full disk, say): nothing is written, the
    old pair, report and plots folder stay as they were, and a new plots folder is removed again."""
    from m3t1r.app import reporting
    from m3t1r.errors import OutputPathError

    def failing(*args, **kwargs):
        raise OutputPathError(
            kwargs.get("path", "map.png"), "write failed, file left unchanged: No space left on device"
        )

    before = _contents(old_calibration)
    monkeypatch.setattr(reporting, "plot_predicted_std_map", failing)
    assert (
        main(
            [
                "calibrate",
                str(old_calibration / "m.csv"),
                "-o",
                str(old_calibration / "c.urdf"),
                "--report",
                str(old_calibration / "c.json"),
                "--plots",
                str(tmp_path / "new" / "plots"),
            ]
        )
        == 2
    )
    assert "No space left on device" in capsys.readouterr().err
    assert _contents(old_calibration) == before and list(tmp_path.iterdir()) == []


def test_calibrate_report_on_stdout_is_the_json_alone(old_calibration, tmp_path, capsys):
    """`--report -`: stdout is the report and nothing else (status lines on stderr), where the status
    lines used to come first on stdout and no JSON parser could read it."""
    capsys.readouterr()
    assert main(["calibrate", str(old_calibration / "m.csv"), "-o", str(tmp_path / "c.urdf"), "--report", "-"]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert report["kind"] == "closed_loop" and report["input"]["poses"] == 30
    assert "calibrating from 30 poses" in err and f"wrote {tmp_path / 'c.urdf'}" in err


@pytest.mark.parametrize(
    "argv,message",
    [
        (["plan", "-n", "5", "--seed", "-1", "-o", "p.csv"], "a seed is a whole number of at least 0, got -1"),
        (["simulate", "--seed", "-1", "-o", "m.csv"], "a seed is a whole number of at least 0, got -1"),
        (["evaluate", "--truth", "t.urdf", "--calibrated", "c.urdf", "--seed", "-1"], "a seed is a whole number"),
        (["simulate", "--marker", "nan", "0", "0", "-o", "m.csv"], "--marker: expected a finite number, got 'nan'"),
        (["calibrate", "m.csv", "-o", "c.urdf", "--marker", "0", "inf", "0"], "--marker: expected a finite number"),
        (["calibrate", "m.csv", "-o", "c.urdf", "--marker", "0.1+1j", "0", "0"], "--marker: expected a number"),
        (["calibrate", "m.csv", "-o", "c.urdf", "--max-iterations", "0"], "--max-iterations: expected at least 1"),
        (["calibrate", "m.csv", "-o", "c.urdf", "--noise-pos", "0"], "--noise-pos: expected a number above 0"),
        (["simulate", "-n", "0", "-o", "m.csv"], "-n: expected at least 1"),
    ],
)
def test_bad_arguments_are_refused_by_argparse_before_any_work(tmp_path, capsys, monkeypatch, argv, message):
    """Seeds, noises, counts and the marker are checked as they are parsed: usage and exit 2, where a
    negative seed was a ValueError traceback and `--marker nan` was refused later as a column mix-up."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_an_endless_or_huge_input_is_refused_by_size_not_read_into_memory(tmp_path, capsys):
    assert main(["fk", "/dev/zero", "-o", str(tmp_path / "p.csv")]) == 2
    assert "/dev/zero: larger than 256 MiB (or a device that never ends)" in capsys.readouterr().err
    assert not (tmp_path / "p.csv").exists()


def _moved_x(meas, data_row: int, value) -> int:
    """Set column x of data row `data_row` (0-based) of a measurement file to value(x); its file line."""
    lines = meas.read_text().splitlines()
    header = next(k for k, line in enumerate(lines) if not line.startswith("#"))
    fields = lines[header + 1 + data_row].split(",")
    column = lines[header].split(",").index("x")
    fields[column] = value(fields[column])
    lines[header + 1 + data_row] = ",".join(fields)
    meas.write_text("\n".join(lines) + "\n")
    return header + 2 + data_row


@pytest.mark.parametrize("value", [lambda x: repr(float(x) + 1.0), lambda x: "12345.6"])
def test_one_gross_reading_is_an_outlier_named_by_line_not_a_verdict_on_the_machine(tmp_path, capsys, value):
    """One row 1 m (or 12 km) off among 30 made the start check refuse the whole fit as 'data from
    another machine, or the wrong model files', without naming the line."""
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "30", "--seed", "3", "-o", str(meas)]) == 0
    line = _moved_x(meas, 12, value)
    capsys.readouterr()
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--outlier-sigma", "0"]) == 1
    err = capsys.readouterr().err
    assert f"line {line}: the measured point is " in err and "a gross reading" in err and "another machine" not in err
    assert not (tmp_path / "c.urdf").exists()
    assert (
        main(
            [
                "calibrate",
                str(meas),
                "-o",
                str(tmp_path / "c.urdf"),
                "--frame",
                "estimate",
                "--select",
                "none",
                "--report",
                str(tmp_path / "r.json"),
            ]
        )
        == 0
    )
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["outliers"] == [line] and report["residual_rms"]["after"]["position_m"] < 3e-5


@pytest.mark.parametrize("n", [1, 2])
def test_one_or_two_poses_are_too_few_not_readings_that_do_not_assemble(tmp_path, capsys, n):
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", str(n), "-o", str(meas)]) == 0
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf")]) == 2
    err = capsys.readouterr().err
    assert f"{meas}: {n} pose(s) are far too few to calibrate" in err and "assemble" not in err


def _scalar_first_under_scalar_last_names(meas):
    lines = meas.read_text().splitlines()
    header = next(k for k, line in enumerate(lines) if not line.startswith("#"))
    columns = [lines[header].split(",").index(c) for c in ("qx", "qy", "qz", "qw")]
    for k in range(header + 1, len(lines)):
        fields = lines[k].split(",")
        x, y, z, w = (fields[c] for c in columns)
        for c, value in zip(columns, (w, x, y, z)):
            fields[c] = value
        lines[k] = ",".join(fields)
    meas.write_text("\n".join(lines) + "\n")


def test_a_refused_fit_names_the_quaternion_order_not_the_marker(tmp_path, capsys):
    """Quaternions in w, x, y, z order were answered 'give its position with --marker X Y Z'."""
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "30", "--seed", "5", "-o", str(meas)]) == 0
    _scalar_first_under_scalar_last_names(meas)
    capsys.readouterr()
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--select", "none"]) == 1
    err = capsys.readouterr().err
    assert "the quaternion columns look like w, x, y, z (scalar first)" in err
    assert "--marker X Y Z" not in err and not (tmp_path / "c.urdf").exists()


def test_a_noise_stated_ten_times_too_small_is_blamed_on_the_noise_not_the_marker(tmp_path, capsys):
    """It was refused with 'give its position with --marker X Y Z'. What the fit leaves is
    sub-millimetre, no setup mistake: the machine is written, with a warning that names a noisier
    tracker than stated and the noise the residual implies (the simulated 10 um / 20 urad)."""
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "30", "--seed", "5", "-o", str(meas)]) == 0
    capsys.readouterr()
    assert (
        main(
            [
                "calibrate",
                str(meas),
                "-o",
                str(tmp_path / "c.urdf"),
                "--select",
                "none",
                "--noise-pos",
                "1e-6",
                "--noise-rot",
                "2e-6",
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert "a noisier tracker than stated" in err and "--noise-pos auto" in err and "--marker X Y Z" not in err
    implied = float(err.split("imply a noise of ")[1].split(" m")[0])
    assert 7e-6 < implied < 13e-6 and (tmp_path / "c.urdf").exists()


@pytest.mark.parametrize("frame", ["base", "estimate"])
def test_metres_read_with_units_mm_are_told_to_drop_it(tmp_path, capsys, frame):
    """--units mm on a metre file was told to use --frame estimate (or, estimating the frame, to add poses)."""
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "30", "--seed", "5", "-o", str(meas)]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--units", "mm", "--frame", frame]) in (1, 2)
    err = capsys.readouterr().err
    assert "drop --units mm" in err and "--frame estimate" not in err and "add poses" not in err
    assert "--force" not in err


def test_hinge_readings_in_degrees_are_told_to_be_radians(tmp_path, capsys):
    urdf, closures = five_bar_files(tmp_path)
    sliders = _write(tmp_path / "s.csv", "motor_1,motor_2\n133.5,46.4\n127.8,40.1\n")  # degrees of 2.33, 0.81 rad
    assert main(["fk", str(sliders), "--model", str(urdf), "-o", str(tmp_path / "p.csv")]) == 2
    err = capsys.readouterr().err
    assert "line 2, column 'motor_1': 133.5 rad is beyond the joint limit [1.83, 2.83]" in err
    assert "within the limits in degrees: give radians" in err


def _joint_table(tmp_path, rows: str):
    table = read_table(_write(tmp_path / "joints.csv", "slide,hinge\n" + rows), required=["slide", "hinge"])
    return table, np.column_stack([table.column("slide"), table.column("hinge")])


def test_joint_readings_a_hair_past_a_limit_are_kept_with_a_note_only_within_the_margin(tmp_path):
    """One check for closed-loop (no margin) and serial readings (a share of the range past a
    nominal URDF limit is kept, with a note naming the column and its first line)."""
    table, readings = _joint_table(tmp_path, "0.1,0.0\n0.352,0.5\n0.2,-0.1\n")
    limits = np.array([0.0, -1.0]), np.array([0.35, 1.0])
    with pytest.raises(DataFileError) as caught:
        check_joint_readings(table, ("slide", "hinge"), readings, *limits, [True, False])
    assert str(caught.value).endswith(
        "line 3, column 'slide': 0.352 m is beyond the joint limit [0, 0.35] (SI units: m)"
    )
    notes = check_joint_readings(table, ("slide", "hinge"), readings, *limits, [True, False], margin=0.05)
    assert notes == [
        "column 'slide': 1 reading(s) up to 0.002 m beyond the URDF limit [0, 0.35] (file line 3 first), "
        "within 5% of its range: kept as read"
    ]
    with pytest.raises(DataFileError, match=r"line 3, column 'slide': 0.352 m is beyond the joint limit \[0, 0.3\]"):
        check_joint_readings(
            table, ("slide", "hinge"), readings, np.array([0.0, -1.0]), np.array([0.3, 1.0]), [True, False], margin=0.05
        )


def test_joint_limits_checked_are_the_usable_ones_and_the_hints_name_the_likely_unit(tmp_path):
    table, readings = _joint_table(tmp_path, "120.0,40.0\n150.0,-20.0\n")
    unbounded = np.array([-np.inf, 1.0]), np.array([np.inf, -1.0])  # no limits; an empty range is not checked
    assert check_joint_readings(table, ("slide", "hinge"), readings, *unbounded, [True, False]) == []
    with pytest.raises(DataFileError, match=r"line 2, column 'slide': 120 m is beyond the joint limit \[-inf, 0.1\]"):
        check_joint_readings(
            table, ("slide", "hinge"), readings, np.array([-np.inf, -1.0]), np.array([0.1, 1.0]), [True, False]
        )
    millimetres = np.array([0.1, -1.0]), np.array([0.2, 1.0])
    with pytest.raises(DataFileError, match=r"within the limits in millimetres: use --units mm\)$"):
        check_joint_readings(table, ("slide", "hinge"), readings, *millimetres, [True, False])
    with pytest.raises(DataFileError, match=r"0.12 m is beyond .* \(SI units: m\)$"):  # read as mm already
        check_joint_readings(
            table,
            ("slide", "hinge"),
            readings * 1e-3,
            np.array([0.0, -1.0]),
            np.array([0.1, 1.0]),
            [True, False],
            scales=[1e-3, 1.0],
        )
    degrees = np.array([-np.inf, -1.0]), np.array([np.inf, 1.0])
    with pytest.raises(
        DataFileError,
        match=r"column 'hinge': 40 rad .* in degrees: give radians; `m3t1r convert .* --joint-degrees all",
    ):
        check_joint_readings(table, ("slide", "hinge"), readings, *degrees, [True, False])
    with pytest.raises(DataFileError, match=r"column 'hinge': 40 rad .* \(SI units: rad\)$"):  # one of three: a fault
        table, readings = _joint_table(tmp_path, "0.0,40.0\n0.0,0.5\n0.0,-0.5\n")
        check_joint_readings(table, ("slide", "hinge"), readings, *degrees, [True, False])


def test_a_marker_given_in_millimetres_is_refused_with_the_metres(tmp_path, capsys):
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "12", "-o", str(meas)]) == 0
    capsys.readouterr()
    assert (
        main(
            [
                "calibrate",
                str(meas),
                "-o",
                str(tmp_path / "c.urdf"),
                "--marker",
                "70.3",
                "-20.2",
                "30.2",
                "--units",
                "mm",
            ]
        )
        == 2
    )
    assert (
        "--marker 70.3 -20.2 30.2: a point 79.1 m from the frame it is fixed to; --marker is in metres whatever "
        "--units says (in millimetres these are --marker 0.0703 -0.0202 0.0302)"
    ) in capsys.readouterr().err


def test_compensation_targets_in_millimetres_are_refused_with_the_unit(tmp_path, capsys):
    meas, cal, report = tmp_path / "m.csv", tmp_path / "c.urdf", tmp_path / "r.json"
    assert main(["simulate", "-n", "30", "--seed", "5", "-o", str(meas)]) == 0
    assert main(["calibrate", str(meas), "-o", str(cal), "--report", str(report), "--select", "none"]) == 0
    targets = _write(tmp_path / "t.csv", "x,y,z,qx,qy,qz,qw\n500.0,500.0,-100.0,0,0,0,1\n520.0,480.0,-90.0,0,0,0,1\n")
    capsys.readouterr()
    assert (
        main(
            [
                "compensate",
                str(targets),
                "--calibrated",
                str(cal),
                "--report",
                str(report),
                "-o",
                str(tmp_path / "out.csv"),
            ]
        )
        == 2
    )
    assert "look like millimetres (divide x, y, z by 1000)" in capsys.readouterr().err
    assert not (tmp_path / "out.csv").exists()


def test_an_input_too_large_for_memory_is_refused_without_a_traceback(tmp_path, capsys, monkeypatch):
    """numpy's MemoryError (a plan or file too large for the machine) ends as an error line, exit 2,
    nothing written, where it used to end in a traceback."""
    from m3t1r.app import cli_campaign

    def too_large(*args, **kwargs):
        raise MemoryError("Unable to allocate 1.16 TiB for an array")

    monkeypatch.setattr(cli_campaign, "plan_closed_loop", too_large)
    assert main(["plan", "-n", "20", "-o", str(tmp_path / "plan.csv")]) == 2
    err = capsys.readouterr().err
    assert "m3t1r: error: plan: not enough memory" in err and "Traceback" not in err
    assert not (tmp_path / "plan.csv").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["--fix", "q12", "q22.dt[5]", "m.csv"],
        ["--fix", "q12,q22.dt[5]", "m.csv"],
        ["m.csv", "--fix", "q12", "q22.dt[5]"],
        ["--fix", "q12", "--fix", "q22.dt[5]", "m.csv"],
    ],
)
def test_fix_and_prior_lists_leave_the_measurement_file_to_its_argument(argv):
    """`--fix A B file.csv` swallowed the file ('the following arguments are required: measurements')."""
    from m3t1r.app.cli import build_parser

    args = build_parser().parse_args(["calibrate", "-o", "c.urdf", "--prior", "q13=1e-4", "q23=2e-5", *argv])
    assert args.measurements == "m.csv" and args.fix == ["q12", "q22.dt[5]"] and args.prior == ["q13=1e-4", "q23=2e-5"]
    args = build_parser().parse_args(["calibrate", "-o", "c.urdf", "--prior", "q13=1e-4,q23=2e-5", "m.csv"])
    assert args.measurements == "m.csv" and args.prior == ["q13=1e-4", "q23=2e-5"]


def test_a_missing_measurement_file_is_still_a_usage_error(capsys):
    with pytest.raises(SystemExit) as caught:
        main(["calibrate", "-o", "c.urdf", "--fix", "q12", "q13"])
    assert caught.value.code == 2
    assert "the following arguments are required: measurements" in capsys.readouterr().err
