"""A tracker campaign on the closed-loop machine, as a user runs it (issue 9's acceptance).

The truth machine has 1 mm / 1 mrad errors on every placement; the tracker stands metres away at
any heading, exports millimetres, and sees a reflector 50-100 mm off the platform frame whose CAD
position is known to 0.5 mm; two measurements are spoiled by 3-5 mm gross errors.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.app.cli import main
from m3t1r.app.datasets import write_measurements
from m3t1r.calibration.closed_loop import calibrate_closed_loop, cross_validate
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.identification import forward_selection
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise, assembled_from_home, measure
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.repeats import grouped_blocks, grouped_folds, pose_groups
from m3t1r.calibration.simulation import (
    SimulatedStudy,
    StudyOptions,
    actual_machine,
    random_placement_errors,
    simulate_study,
)
from m3t1r.calibration.validation import validate
from m3t1r.errors import InvalidInputError
from m3t1r.io.poses import measurement_column
from m3t1r.io.tables import table_text
from m3t1r.metrics import pose_errors_between
from m3t1r.model.description import Mechanism
from m3t1r.model.workspace import workspace_actuators


def _random_setup(rng: np.random.Generator) -> MeasurementSetup:
    axis = rng.normal(size=3)
    rotation = pin.exp3(axis / np.linalg.norm(axis) * rng.uniform(0.5, np.pi))
    direction = rng.normal(size=3)
    translation = direction / np.linalg.norm(direction) * rng.uniform(1.0, 5.0)
    offset = rng.normal(size=3)
    marker = pin.SE3(pin.exp3(rng.normal(size=3)), offset / np.linalg.norm(offset) * rng.uniform(0.05, 0.1))
    return MeasurementSetup(pin.SE3(rotation, translation), marker)


def _campaign(tmp_path: Path, seed: int, position_only: bool) -> tuple[SimulatedStudy, Path, list[str]]:
    nominal = Mechanism.load()
    rng = np.random.default_rng(1000 + seed)
    setup = _random_setup(rng)
    study = simulate_study(
        nominal,
        60,
        200,
        seed,
        noise=TrackerNoise(),
        options=StudyOptions(setup=setup, position_only=position_only, outliers=2),
    )
    path = tmp_path / "campaign.csv"
    write_measurements(path, nominal, study.measurements, units="mm")
    given = setup.marker.translation + rng.normal(size=3) * 0.5e-3 / np.sqrt(3)  # the CAD's marker, 0.5 mm off
    return study, path, ["--marker", *map(str, given), "--units", "mm"]


def _calibrate_in_tracker_frame(tmp_path: Path, path: Path, *options: str) -> dict:
    """`m3t1r calibrate PATH -o cal.urdf --report cal.json --frame estimate OPTIONS...` in tmp_path,
    which must succeed; the report, read as strict JSON (no NaN or Infinity)."""
    report_path, urdf = tmp_path / "cal.json", tmp_path / "cal.urdf"
    written = ["-o", str(urdf), "--report", str(report_path)]
    assert main(["calibrate", str(path), *written, "--frame", "estimate", *options]) == 0
    return json.loads(report_path.read_text(), parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))


@pytest.mark.parametrize("seed, position_only", [(0, False), (1, True)])
def test_tracker_campaign_is_calibrated_in_the_tracker_frame(tmp_path, capsys, seed, position_only):
    study, path, options = _campaign(tmp_path, seed, position_only)
    report = _calibrate_in_tracker_frame(tmp_path, path, *options)
    assert report["outliers"] == [i + 2 for i in study.outliers]  # line 1 is the header
    assert report["converged"] and 0.5 < report["variance_factor"] < 1.5
    assert str(study.outliers[0] + 2) in capsys.readouterr().out
    calibrated, estimated = Mechanism.load(tmp_path / "cal.urdf"), MeasurementSetup.from_report(report)
    truth = measure(study.truth, study.holdout_actuators, setup=study.setup).poses
    predicted = measure(calibrated, study.holdout_actuators, setup=estimated).poses
    errors = pose_errors_between(predicted, truth)
    assert errors.position_mean <= (35e-6 if position_only else 20e-6)
    if not position_only:
        assert errors.rotation_mean <= 30e-6
    # What `validate` shows on a fresh noisy set of the same machine, against the report's k-fold figure.
    rng = np.random.default_rng(seed)
    fresh_actuators = workspace_actuators(study.nominal, 100, rng)
    fresh = measure(study.truth, fresh_actuators, rng, TrackerNoise(), position_only, study.setup)
    validation = pose_errors_between(measure(calibrated, fresh.actuators, setup=estimated).poses, fresh.poses)
    ratio = report["cross_validation"]["position_mean_m"] / validation.position_mean
    assert 0.67 <= ratio <= 1.5


def test_calibrated_urdf_holds_the_machine_alone(tmp_path):
    study, path, options = _campaign(tmp_path, 2, False)
    report = _calibrate_in_tracker_frame(tmp_path, path, *options)
    calibrated = Mechanism.load(tmp_path / "cal.urdf")
    # The platform frame stays the platform (the reflector's 50-100 mm went to the marker) and the
    # base stays the base (the tracker's metres went to the frame): placements move by build errors.
    for name in (calibrated.platform_frame, "q11", "q21"):
        model, nominal = calibrated.model, study.nominal.model
        if model.existFrame(name) and not model.existJointName(name):
            a, b = model.frames[model.getFrameId(name)].placement, nominal.frames[nominal.getFrameId(name)].placement
        else:
            a, b = model.jointPlacements[model.getJointId(name)], nominal.jointPlacements[nominal.getJointId(name)]
        moved = pin.log6(a.actInv(b)).vector  # gauge-fixed build errors: a few mm / mrad, not 50 mm or metres
        assert np.linalg.norm(moved[:3]) < 0.02 and np.linalg.norm(moved[3:]) < 0.02
    marker = np.array(report["marker"]["translation"])
    assert np.linalg.norm(marker[:2] - study.setup.marker.translation[:2]) < 5e-3


@pytest.mark.parametrize(
    "mistake, cause, status",
    [
        ("frame base", "--frame estimate", 1),
        ("millimetres read as metres", "--units mm", 2),
        ("slider columns swapped", "'q11' and 'q21' look swapped", 1),
    ],
)
def test_mistakes_are_refused_with_their_likely_cause(tmp_path, capsys, mistake, cause, status):
    study, path, options = _campaign(tmp_path, 3, False)
    arguments = ["calibrate", str(path), "-o", str(tmp_path / "cal.urdf"), "--report", str(tmp_path / "r.json")]
    if mistake == "frame base":
        arguments += options
    elif mistake == "millimetres read as metres":
        arguments += ["--frame", "estimate"] + options[:4]
    else:
        lines = path.read_text().splitlines()
        header = lines[0].split(",")
        a, b = header.index("q11"), header.index("q21")
        swapped = [lines[0]]
        for line in lines[1:]:
            fields = line.split(",")
            fields[a], fields[b] = fields[b], fields[a]
            swapped.append(",".join(fields))
        path.write_text("\n".join(swapped) + "\n")
        arguments += ["--frame", "estimate"] + options
    assert main(arguments) == status
    assert cause in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["campaign.csv"]


def test_linearised_cross_validation_agrees_with_refitting_every_fold():
    nominal = Mechanism.load()
    study = simulate_study(nominal, 50, 0, 7, noise=TrackerNoise(), options=StudyOptions(outliers=1))
    calibration = calibrate_closed_loop(
        nominal, study.measurements, CalibrationOptions(noise=TrackerNoise(), select=True)
    )
    assert calibration.outliers == study.outliers
    quick, refitted = cross_validate(calibration), cross_validate(calibration, refit=True)
    assert len(quick.errors.position) == 49
    assert quick.errors.position_mean == pytest.approx(refitted.errors.position_mean, rel=0.01)
    assert quick.errors.rotation_mean == pytest.approx(refitted.errors.rotation_mean, rel=0.01)
    # Noise included: the held-back measurements' own noise (10 um per axis) is part of the figure.
    assert 10e-6 < quick.errors.position_mean < 30e-6


def test_fixed_and_prior_parameters_are_honoured_and_reported(tmp_path):
    study, path, options = _campaign(tmp_path, 4, False)
    fixed_and_priors = ["--fix", "q12", "q22.dt[5]", "--prior", "q13=1e-4", "--prior", "q23.dt[0]=1e-5"]
    report = _calibrate_in_tracker_frame(tmp_path, path, *fixed_and_priors, *options)
    assert report["fixed"] == ["q12", "q22.dt[5]"] and report["priors"] == {"q13": 1e-4, "q23.dt[0]": 1e-5}
    values = {p["name"]: p for p in report["parameters"]}
    assert all(values[f"q12.dt[{k}]"]["value"] == 0.0 and not values[f"q12.dt[{k}]"]["fitted"] for k in range(6))
    assert values["q22.dt[5]"]["value"] == 0.0
    assert abs(values["q23.dt[0]"]["value"]) < 5e-5  # held within a few sigmas of nominal by its prior
    for bad in (["--fix", "q99"], ["--prior", "q13=-1"], ["--prior", "q13"]):
        assert (
            main(["calibrate", str(path), "-o", str(tmp_path / "x.urdf"), "--frame", "estimate", *bad, *options]) == 2
        )
    assert not (tmp_path / "x.urdf").exists()


def test_a_reflector_without_marker_is_named_as_baked_into_the_platform_frame(tmp_path, capsys):
    study, path, options = _campaign(tmp_path, 5, True)  # one reflector, positions only
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.urdf"), "--frame", "estimate", "--units", "mm"]) == 0
    out = capsys.readouterr().out
    assert "moved implausibly far" in out and "P_I itself moved" in out and "--marker X Y Z" in out


def test_a_probe_frame_without_marker_is_refused_naming_the_marker(tmp_path, capsys):
    study, path, options = _campaign(tmp_path, 5, False)  # a 6-D probe at an unknown orientation
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.urdf"), "--frame", "estimate", "--units", "mm"]) == 1
    assert "give its position with --marker X Y Z" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["campaign.csv"]


@pytest.mark.parametrize("option", [["--folds", "1"], ["--outlier-sigma", "-3"], ["--outlier-sigma", "0.5"]])
def test_campaign_options_are_checked_before_any_work(tmp_path, capsys, option):
    path = tmp_path / "m.csv"
    path.write_text("not read\n")
    with pytest.raises(SystemExit) as exited:
        main(["calibrate", str(path), "-o", str(tmp_path / "c.urdf"), *option])
    assert exited.value.code == 2 and option[0] in capsys.readouterr().err


def test_auto_noise_finds_the_tracker_noise_and_keeps_the_outlier_gate(tmp_path, capsys):
    """10 um / 20 urad of tracker noise and two gross errors, the noise left to the data: the estimate
    is within 20 % of the truth, the gross readings are still flagged, and the report says so."""
    study, path, options = _campaign(tmp_path, 6, False)
    report = _calibrate_in_tracker_frame(tmp_path, path, "--noise-pos", "auto", "--noise-rot", "auto", *options)
    assert report["noise_source"]["position"] == report["noise_source"]["rotation"] == "estimated"
    assert 8e-6 < report["noise_model"]["position_m"] < 12e-6 and 16e-6 < report["noise_model"]["rotation_rad"] < 24e-6
    assert report["outliers"] == [i + 2 for i in study.outliers] and report["warnings"] == []
    assert "(estimated from the residual)" in capsys.readouterr().out


def test_a_gross_reading_is_left_out_before_the_noise_is_estimated(tmp_path, capsys):
    """A reading 1 m off among the campaign's 60 (tracker frame unknown, a 70 mm marker given 0.5 mm
    off, two 3-5 mm gross errors), the noise left to the data: the start check, registering frame and
    marker on the poses that fit, leaves it out by line before the noise is estimated; the estimate
    is still within 20 % of the truth and the outliers are the gate's two and that line."""
    study, path, options = _campaign(tmp_path, 6, False)
    row = next(k for k in range(30, 60) if k not in study.outliers)
    lines = path.read_text().splitlines()
    x = lines[0].split(",").index("x")  # line 1 is the header
    fields = lines[1 + row].split(",")
    fields[x] = repr(float(fields[x]) + 1000.0)  # mm
    lines[1 + row] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    report = _calibrate_in_tracker_frame(tmp_path, path, "--noise-pos", "auto", "--noise-rot", "auto", *options)
    assert f"note: line {row + 2}: the measured point is " in capsys.readouterr().out
    assert report["outliers"] == sorted([i + 2 for i in study.outliers] + [row + 2])
    assert 8e-6 < report["noise_model"]["position_m"] < 12e-6 and 16e-6 < report["noise_model"]["rotation_rad"] < 24e-6
    assert report["input"]["poses"] == 60 and report["warnings"] == []


def test_a_noise_stated_too_small_gives_a_written_machine_and_a_warning(tmp_path, capsys):
    """10 um of tracker noise stated as 2 um: nothing the checks know explains the residual, so the
    machine is written, and the warning gives the variance factor and the noise the residual implies."""
    study, path, options = _campaign(tmp_path, 7, True)
    report = _calibrate_in_tracker_frame(tmp_path, path, "--noise-pos", "2e-6", *options)
    assert report["variance_factor"] > 15 and len(report["warnings"]) == 1
    implied = float(report["warnings"][0].split("imply a noise of ")[1].split(" m")[0])
    assert 7e-6 < implied < 13e-6
    assert "none of the usual mistakes explains it" in capsys.readouterr().err
    assert (tmp_path / "cal.urdf").exists()


def test_outliers_by_source_repeats_held_out_together_and_a_held_out_file_scored(tmp_path, capsys):
    """The campaign as `convert` writes it (a source column), its first 10 poses measured twice (same
    sliders, another tracker reading), its last 20 kept back and given to --validate: the outliers are
    named by source too, the cross-validation deals whole postures to its folds, and the held-out
    file is scored exactly as `m3t1r validate` scores it with the written pair and report."""
    study, path, options = _campaign(tmp_path, 6, False)
    lines = path.read_text().splitlines()
    x = lines[0].split(",").index("x")

    def reread(row: str) -> str:
        fields = row.split(",")
        fields[x] = repr(float(fields[x]) + 0.004)  # 4 um (mm file): the same posture read again
        return ",".join(fields)

    rows = [f"{row},{1000 + i}" for i, row in enumerate(lines[1:41])]
    rows += [f"{reread(row)},{2000 + i}" for i, row in enumerate(lines[1:11])]
    path.write_text("\n".join([lines[0] + ",source", *rows]) + "\n")
    held = tmp_path / "held.csv"
    held.write_text("\n".join([lines[0], *lines[41:]]) + "\n")
    report = _calibrate_in_tracker_frame(tmp_path, path, "--validate", str(held), *options)
    out = capsys.readouterr().out
    fitted_outliers = sorted(i for i in study.outliers if i < 40)
    assert fitted_outliers, "the seed spoils a fitted pose"
    sources = [1000 + i for i in fitted_outliers] + [2000 + i for i in fitted_outliers if i < 10]
    assert report["outlier_sources"] == sorted(sources)
    assert "outliers in the tracker's file (the source column): " + ", ".join(map(str, sorted(sources))) in out
    postures = 40 - len(fitted_outliers)
    assert report["cross_validation"]["groups"] == postures
    assert f"{postures} distinct poses, each held out whole" in out and " m RMS " in out
    scored = validate(held, tmp_path / "cal.urdf", tmp_path / "cal.json")
    entry = report["held_out"]
    assert entry["poses"] == 20 and entry["failed_lines"] == []
    assert entry["position_mean_m"] == pytest.approx(scored.errors.position_mean, rel=1e-6)
    assert entry["position_rms_m"] == pytest.approx(float(np.sqrt(np.mean(scored.errors.position**2))), rel=1e-6)
    assert entry["rotation_rms_rad"] == pytest.approx(float(np.sqrt(np.mean(scored.errors.rotation**2))), rel=1e-6)
    assert f"held-out file {held} (20 poses): position error per pose" in out


def test_repeats_of_a_posture_share_a_group_and_a_fold():
    """Rows group by equal joint readings (within REPEAT_TOLERANCE) or by a shared source, transitively;
    folds take whole groups, and with every row its own group they are the plain permutation's."""
    q = np.array([[0.1, 0.2], [0.3, 0.4], [0.1 + 2e-6, 0.2 - 3e-6], [0.5, 0.6], [0.7, 0.8], [0.3, 0.4 + 0.01]])
    assert pose_groups(q).tolist() == [0, 1, 0, 2, 3, 4]
    # Rows 4 and 5 share row 1's source: one group of three.
    groups = pose_groups(q, np.array([7, 8, 9, 10, 8, 8]))
    assert groups.tolist() == [0, 1, 0, 2, 1, 1]
    folds = grouped_folds(groups, 3, np.random.default_rng(0))
    assert folds[0] == folds[2] and folds[1] == folds[4] == folds[5] and len(set(folds.tolist())) == 3
    singletons = np.arange(12)
    assert (
        grouped_folds(singletons, 4, np.random.default_rng(5)).tolist()
        == (np.random.default_rng(5).permutation(12) % 4).tolist()
    )
    with pytest.raises(InvalidInputError, match="5 folds need at least 5 distinct poses"):
        grouped_folds(groups, 5, np.random.default_rng(0))


def test_grouped_blocks_make_the_selection_score_leave_each_group_out_whole():
    """Leave-one-block-out PRESS on the grouped, zero-padded rows equals refitting without each group:
    sum over groups of |r_g + J_g dx_-g|^2, dx_-g the least-squares step of the other groups' rows."""
    rng = np.random.default_rng(3)
    k, n = 3, 14
    jacobian, residual = rng.normal(size=(n * k, 4)), rng.normal(size=n * k)
    groups = np.array([0, 1, 0, 2, 3, 3, 4, 5, 1, 6, 7, 8, 9, 9])
    grouped_j, grouped_r, block = grouped_blocks(jacobian, residual, k, groups)
    assert block == 2 * k and grouped_j.shape == (10 * 2 * k, 4)
    press = forward_selection(grouped_j, grouped_r, block, [], [0, 1, 2, 3]).press
    expected = 0.0
    for g in range(10):
        held = np.repeat(groups == g, k)
        step = np.linalg.lstsq(jacobian[~held], -residual[~held], rcond=None)[0]
        expected += float(np.sum((residual[held] + jacobian[held] @ step) ** 2))
    assert press == pytest.approx(expected, rel=1e-9)
    same = grouped_blocks(jacobian, residual, k, np.arange(n))
    assert same[0] is jacobian and same[1] is residual and same[2] == k


_POINT_OFFSETS = ((0.05, -0.02, 0.03), (-0.04, 0.03, 0.02), (0.01, 0.05, -0.01))  # [m] on the platform


def _points_campaign(
    mechanism: Mechanism, truth: Mechanism, setup: MeasurementSetup, n: int, rng: np.random.Generator, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sliders (n, 4) and the three points (n, 3, 3) [m] a tracker sees through `setup`, a fifth of
    the sightings hidden (NaN; every row sees one point at least)."""
    actuators = workspace_actuators(mechanism, n, rng)
    platform = assembled_from_home(truth, actuators).poses
    points = replace(setup, points=_POINT_OFFSETS).measured_points(platform) + rng.normal(0.0, sigma, (n, 3, 3))
    hidden = rng.random((n, 3)) < 0.2
    hidden[np.all(hidden, axis=1), 0] = False
    points[hidden] = np.nan
    return actuators, points


@pytest.fixture(scope="module")
def points_truth(mechanism):
    rng = np.random.default_rng(1)
    truth = actual_machine(mechanism, random_placement_errors(ClosedLoopErrorModel(mechanism), rng, 1e-3, 1e-3))
    return truth, MeasurementSetup(pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 2.0), np.array([3.0, -1.0, 0.5])))


def test_three_points_on_the_platform_calibrate_the_machine_a_single_marker_does(mechanism, points_truth):
    """A tracker 3 m away sees three reflectors on the platform, each hidden on a fifth of 60 poses;
    the fit estimates the frame and each reflector's offset with the machine. At 200 held-out slider
    sets it predicts what the tracker sees of reflector 1 as well as the fit of a campaign of
    reflector 1 alone (marker estimated from a 1 cm wrong guess), both within the 10 um noise;
    only the points seen count: the degrees of freedom (variance factor about 1) and the
    cross-validation (one error per point seen, the linearised folds agreeing with refits)."""
    truth, frame = points_truth
    noise, rng = TrackerNoise(10e-6, 20e-6), np.random.default_rng(2)
    actuators, points = _points_campaign(mechanism, truth, frame, 60, rng, noise.position)
    seen = np.isfinite(points[:, :, 0])
    first = [pin.SE3(np.eye(3), row[np.isfinite(row[:, 0])][0]) for row in points]
    several = calibrate_closed_loop(
        mechanism,
        PoseMeasurements(actuators, tuple(first), True, points),
        CalibrationOptions(noise=noise, estimate_frame=True),
    )
    marker = pin.SE3(np.eye(3), np.array(_POINT_OFFSETS[0]))
    single = measure(truth, actuators, rng, noise, position_only=True, setup=replace(frame, marker=marker))
    guess = MeasurementSetup(marker=pin.SE3(np.eye(3), np.array(_POINT_OFFSETS[0]) + [0.01, 0.0, 0.0]))
    alone = calibrate_closed_loop(
        mechanism, single, CalibrationOptions(noise=noise, setup=guess, estimate_frame=True, estimate_marker=True)
    )
    assert several.converged and alone.converged and several.outliers == ()
    assert 0.7 < several.variance_factor < 1.4
    assert [n for n in several.fitted if n.startswith("marker.")][:3] == [f"marker.p1.dt[{k}]" for k in range(3)]
    held_out = workspace_actuators(mechanism, 200, np.random.default_rng(5))
    actual = replace(frame, points=_POINT_OFFSETS).measured_points(assembled_from_home(truth, held_out).poses)
    predicted = several.setup.measured_points(assembled_from_home(several.mechanism, held_out).poses)
    reflector = replace(alone.setup, points=(tuple(alone.setup.marker.translation),))
    predicted_alone = reflector.measured_points(assembled_from_home(alone.mechanism, held_out).poses)[:, 0]
    error = np.linalg.norm(predicted - actual, axis=2).mean(axis=0)
    assert np.all(error < 1.5e-5)
    assert np.linalg.norm(predicted_alone - actual[:, 0], axis=1).mean() < 2e-5
    assert np.linalg.norm(predicted[:, 0] - predicted_alone, axis=1).mean() < 2.5e-5
    validation = cross_validate(several)
    assert len(validation.errors.position) == np.count_nonzero(seen)
    assert 1e-5 < validation.errors.position_mean < 3e-5
    refitted = cross_validate(several, refit=True)
    assert refitted.errors.position_mean == pytest.approx(validation.errors.position_mean, rel=0.05)


def _write_points(path: Path, mechanism: Mechanism, actuators: np.ndarray, points: np.ndarray) -> Path:
    columns = [measurement_column(j) for j in mechanism.actuated_joints] + [f"{a}{k}" for k in (1, 2, 3) for a in "xyz"]
    path.write_text(
        table_text(columns, np.hstack([actuators, points.reshape(len(points), -1)]), blank_allowed=columns[4:])
    )
    return path


def test_calibrate_a_file_of_three_points_per_pose(mechanism, points_truth, tmp_path, capsys):
    """End to end: x1,y1,z1 ... x3,y3,z3 with blanks, the frame estimated, a 3 mm gross error on one
    point named by line, --validate scoring a held-out file per point, the report recording the
    points, --noise-pos auto finding the 10 um from the points seen; --marker, a held-out file of
    one frame per row and a half-blank point are refused."""
    truth, frame = points_truth
    rng = np.random.default_rng(3)
    actuators, points = _points_campaign(mechanism, truth, frame, 60, rng, 10e-6)
    row = int(np.flatnonzero(np.isfinite(points[:, 1, 0]))[5])
    points[row, 1, 0] += 3e-3
    path = _write_points(tmp_path / "points.csv", mechanism, actuators, points)
    held = _write_points(tmp_path / "held.csv", mechanism, *_points_campaign(mechanism, truth, frame, 30, rng, 10e-6))
    report_path = tmp_path / "cal.json"
    common = ["-o", str(tmp_path / "cal.urdf"), "--frame", "estimate", "--noise-pos", "1e-5"]
    assert main(["calibrate", str(path), *common, "--report", str(report_path), "--validate", str(held)]) == 0
    out = capsys.readouterr().out
    report = json.loads(report_path.read_text())
    assert report["input"]["points"] == 3 and report["outliers"] == [row + 2]
    assert 0.7 < report["variance_factor"] < 1.4
    distances = lambda p: np.linalg.norm(np.subtract(p, np.roll(p, 1, axis=0)), axis=1)  # noqa: E731
    # The offsets share the platform frame's build error; the distances between the points do not.
    np.testing.assert_allclose(distances(report["points"]), distances(_POINT_OFFSETS), atol=1e-4)
    assert report["held_out"]["per"] == "point" and report["held_out"]["position_rms_m"] < 2.5e-5
    assert "position error per point" in out
    auto = ["-o", str(tmp_path / "auto.urdf"), "--frame", "estimate", "--noise-pos", "auto"]
    assert main(["calibrate", str(path), *auto, "--report", str(report_path)]) == 0
    assert json.loads(report_path.read_text())["noise_model"]["position_m"] == pytest.approx(10e-6, rel=0.2)
    assert main(["calibrate", str(path), *common, "--marker", "0", "0", "0.1"]) == 2
    assert "3 points per row" in capsys.readouterr().err
    single = tmp_path / "single.csv"
    single.write_text("q11,q11_B2,q21,q21_B4,x,y,z\n0,0,0,0,1,2,3\n")
    assert main(["calibrate", str(path), *common, "--validate", str(single)]) == 2
    assert "one measured frame per row, but" in capsys.readouterr().err
    lines = path.read_text().splitlines()
    fields = lines[3].split(",")
    fields[5] = ""
    path.write_text("\n".join([*lines[:3], ",".join(fields), *lines[4:]]) + "\n")
    assert main(["calibrate", str(path), *common]) == 2
    err = capsys.readouterr().err
    assert "line 4" in err and "y1" in err and "some coordinates blank" in err
