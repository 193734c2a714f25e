"""Serial calibration from a tracker campaign: measurement frame and marker, outliers, refusal,
model selection with gravity-compliance candidates, and the `calibrate --serial` command path."""

from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pinocchio as pin
import pytest
from command_lines import serial_calibration_arguments

from m3t1r.app.cli import main
from m3t1r.app.cli_common import RowFailures
from m3t1r.app.cli_serial import run_serial_calibration
from m3t1r.calibration import serial as S
from m3t1r.calibration import serial_evaluation, serial_robots, serial_simulation, validation
from m3t1r.calibration.assessment import FitRejected
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.validation import validate
from m3t1r.errors import DataFileError, IdentificationError, InvalidInputError, ModelFileError
from m3t1r.io.tables import read_table, table_text
from m3t1r.model.poe import SerialChain, perturb, tool_poses

NOISE = TrackerNoise(position=1e-5, rotation=2e-5)  # 10 um / 20 urad tracker, exact joint readings
MARKER = pin.SE3(pin.utils.rotate("y", 0.3), np.array([0.0, 0.02, 0.067]))  # 70 mm from the flange
FRAMES = {
    "z180": pin.SE3(pin.utils.rotate("z", np.pi), np.array([2.5, -1.2, 0.8])),
    "x90": pin.SE3(pin.utils.rotate("x", np.pi / 2), np.array([-1.5, 3.0, 0.4])),
}


@pytest.fixture(scope="module")
def ur10():
    model = serial_robots.load_example_robot("ur10")
    return model, SerialChain.from_model(model, "tool0")


def campaign(model, chain, frame: pin.SE3, seed: int, n_poses: int = 60):
    """A 1 mm / 1 mrad UR10 measured as frame . g(q) . MARKER with NOISE: (data, measured (N, 4, 4))."""
    rng = np.random.default_rng(seed)
    data = serial_simulation.simulate_serial_measurements(model, chain, n_poses, rng, noise=None)
    exact = frame.homogeneous @ tool_poses(chain, data.truth, data.q_true) @ MARKER.homogeneous
    measured = exact.copy()
    measured[:, :3, 3] += rng.normal(0.0, NOISE.position, (n_poses, 3))
    measured[:, :3, :3] = exact[:, :3, :3] @ np.array(
        [pin.exp3(rng.normal(0.0, NOISE.rotation, 3)) for _ in range(n_poses)]
    )
    return data, measured


def as_rows(measured: np.ndarray) -> np.ndarray:
    return np.array([pin.SE3ToXYZQUAT(pin.SE3(m)) for m in measured])


def off_gauge(twist: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """The part of `twist` (6,) outside the span of the rows of `allowed` (k, 6)."""
    coefficients = np.linalg.lstsq(allowed.T, twist, rcond=None)[0]
    return twist - allowed.T @ coefficients


def commuting(twist: np.ndarray) -> np.ndarray:
    """Twists commuting with a revolute joint's S = [v; w]: S itself and the translation along w."""
    return np.array([twist, np.r_[twist[3:], 0.0, 0.0, 0.0]])


@pytest.mark.parametrize("turn", sorted(FRAMES))
def test_frame_and_marker_are_recovered_up_to_the_robot_gauge(ur10, turn: str) -> None:
    model, chain = ur10
    frame = FRAMES[turn]
    data, measured = campaign(model, chain, frame, seed=3)
    given = MeasurementSetup(marker=MARKER * pin.SE3(np.eye(3), np.array([3e-4, -3e-4, 3e-4])))  # 0.5 mm off
    calibration = S.calibrate_serial(
        model,
        chain,
        data.q_readings,
        as_rows(measured),
        CalibrationOptions(noise=NOISE, setup=given, estimate_frame=True, estimate_marker=True),
    )
    assert calibration.converged and calibration.termination in ("cost", "step", "gradient")
    assert 0.7 < calibration.variance_factor < 1.4 and calibration.outliers == ()
    # The robot alone: the first placement (all of whose errors the frame takes) and the tool
    # placement (the marker's) stay nominal; the others move by the robot's own mm / mrad errors.
    placements = chain.placements()
    assert not np.any(calibration.deltas[placements[0]]) and not np.any(calibration.deltas[placements[-1]])
    assert max(np.abs(d).max() for d in calibration.deltas.values()) < 1e-2
    # Gauge: the estimated frame F carries the truth's first placement T_1 (F_est T_1,nom = F T_1,true)
    # up to what commutes with joint 1 (rotation about, translation along its axis), which placement
    # 2 may take instead. Off that 2-D set the match is at the noise level (measured ~2 um / 2 urad).
    j1 = chain.joint_ids[0]
    d_frame = pin.log6(
        (frame * data.truth.jointPlacements[j1]).actInv(calibration.setup.frame * model.jointPlacements[j1])
    ).vector
    assert np.abs(off_gauge(d_frame, commuting(chain.twists[0]))).max() < 2e-5
    # Likewise the marker carries the tool placement's error, up to what commutes with joint 6.
    tool_nominal = model.frames[chain.tool_frame_id].placement
    tool_true = data.truth.frames[chain.tool_frame_id].placement
    d_marker = pin.log6((tool_true * MARKER).actInv(tool_nominal * calibration.setup.marker)).vector
    allowed = np.array([(tool_nominal * MARKER).toActionMatrixInverse() @ c for c in commuting(chain.twists[-1])])
    assert np.abs(off_gauge(d_marker, allowed)).max() < 2e-5
    # Overall the frame and marker are those of the truth to within the robot's own base / tool
    # errors (1 mm, 1 mrad per component, joint offsets 1 mrad): a few mm and mrad, not metres or pi.
    for estimate, truth in ((calibration.setup.frame, frame), (calibration.setup.marker, MARKER)):
        difference = truth.actInv(estimate)
        assert np.linalg.norm(difference.translation) < 1e-2 and np.linalg.norm(pin.log3(difference.rotation)) < 1e-2
    # And it predicts fresh measurements at the noise level.
    q = serial_simulation.sample_configurations(model, chain, 50, np.random.default_rng(4))
    exact = frame.homogeneous @ tool_poses(chain, data.truth, q) @ MARKER.homogeneous
    error = np.linalg.norm(serial_evaluation.predict_measurements(calibration, q)[:, :3, 3] - exact[:, :3, 3], axis=1)
    assert error.mean() < 2e-5


def test_gross_outliers_are_flagged_exactly(ur10) -> None:
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=5)
    rows = as_rows(measured)
    rows[[11, 42], :3] += np.array([[3e-3, 0.0, 0.0], [0.0, -2.5e-3, 3e-3]])  # 3 and 3.9 mm
    calibration = S.calibrate_serial(
        model,
        chain,
        data.q_readings,
        rows,
        CalibrationOptions(
            noise=NOISE, setup=MeasurementSetup(marker=MARKER), estimate_frame=True, estimate_marker=True
        ),
    )
    assert calibration.outliers == (11, 42)
    assert calibration.converged and calibration.variance_factor < 1.4
    validation = serial_evaluation.cross_validate_serial(calibration, folds=4)
    assert validation.errors.position.shape == (58,) and validation.errors.position_mean < 5e-5


# --------------------------------------------------------------------------------------------------
# Joint compliance under gravity: model selection and prediction outside the training postures

COMPLIANCE = -np.array([1e-5, 2e-5, 3e-5, 6e-5, 6e-5, 6e-5])  # rad/Nm; c = -1/k for a stiffness k


def compliant_campaign(model, chain, rng, q: np.ndarray, truth: pin.Model, frame: pin.SE3, noisy: bool):
    g = tool_poses(chain, truth, q + COMPLIANCE * S.gravity_torques(model, chain, q))
    measured = frame.homogeneous @ g @ MARKER.homogeneous
    if noisy:
        measured[:, :3, 3] += rng.normal(0.0, NOISE.position, (len(q), 3))
        measured[:, :3, :3] = measured[:, :3, :3] @ np.array(
            [pin.exp3(rng.normal(0.0, NOISE.rotation, 3)) for _ in range(len(q))]
        )
    return measured


def postures(rng, n: int, training: bool) -> np.ndarray:
    """Shoulder-lift and elbow in a narrow band for training, outside it for testing (rad)."""
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    q[:, 1] = rng.uniform(-2.0, -1.2, n) if training else rng.uniform(-0.8, -0.2, n)
    q[:, 2] = rng.uniform(0.8, 1.6, n) if training else rng.uniform(1.8, 2.6, n)
    return q


def test_selection_with_compliance_predicts_outside_the_training_postures(ur10) -> None:
    model, chain = ur10
    rng = np.random.default_rng(0)
    truth = perturb(model, {p: rng.normal(0.0, 2e-4, 6) for p in chain.placements()})  # small geometric errors
    frame = pin.SE3(pin.utils.rotate("z", 2.0), np.array([2.0, 1.0, 0.3]))
    train, test = postures(rng, 60, True), postures(rng, 200, False)
    measured = compliant_campaign(model, chain, rng, train, truth, frame, noisy=True)
    exact = compliant_campaign(model, chain, rng, test, truth, frame, noisy=False)
    sag = (
        tool_poses(chain, truth, test + COMPLIANCE * S.gravity_torques(model, chain, test))[:, :3, 3]
        - tool_poses(chain, truth, test)[:, :3, 3]
    )
    assert 5e-4 < np.linalg.norm(sag, axis=1).mean() < 1e-3  # the compliance effect: 0.5 - 1 mm
    everything = list(chain.joint_names) + [chain.tool_frame]
    variants = {"registration": dict(fixed=everything), "full": dict(), "selected": dict(select=True, compliance=True)}
    mean_error = {}
    for name, options in variants.items():
        calibration = S.calibrate_serial(
            model,
            chain,
            train,
            as_rows(measured),
            CalibrationOptions(
                noise=NOISE, setup=MeasurementSetup(marker=MARKER), estimate_frame=True, estimate_marker=True, **options
            ),
        )
        predicted = serial_evaluation.predict_measurements(calibration, test)
        mean_error[name] = np.linalg.norm(predicted[:, :3, 3] - exact[:, :3, 3], axis=1).mean()
        if name == "selected":
            assert set(calibration.compliance) >= {"shoulder_lift_joint", "elbow_joint"}
            assert calibration.compliance["shoulder_lift_joint"] == pytest.approx(COMPLIANCE[1], rel=0.1)
    # Measured (seed 0): registration 1.12 mm, full POE 1.63 mm, selected with compliance 0.019 mm.
    assert mean_error["full"] > mean_error["registration"]  # the full geometric model extrapolates worse
    assert mean_error["selected"] <= mean_error["registration"]
    assert mean_error["selected"] < 0.1 * mean_error["full"]


# --------------------------------------------------------------------------------------------------
# The command path


def namespace(tmp_path, measurements, **overrides) -> argparse.Namespace:
    """`calibrate --serial` of `measurements` with the report in tmp_path and MARKER's CAD position 0.3 mm off."""
    return serial_calibration_arguments(
        measurements, tmp_path / "report.json", **{"marker": list(MARKER.translation + 3e-4), **overrides}
    )


def write_campaign(path, chain, q, rows: np.ndarray) -> None:
    columns = list(chain.joint_names) + ["x", "y", "z", "qx", "qy", "qz", "qw"]
    path.write_text(table_text(columns, np.hstack([q, rows]), ["a tracker campaign", "tracker frame, metres"]))


def test_command_writes_a_strict_report_and_names_outlier_lines(ur10, tmp_path, capsys) -> None:
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=6, n_poses=40)
    rows = as_rows(measured)
    rows[7, :3] += np.array([0.0, 4e-3, 0.0])  # a 4 mm gross error
    path = tmp_path / "campaign.csv"
    write_campaign(path, chain, data.q_readings, rows)
    urdf = serial_robots.example_robot_data_dir() / "ur_description" / "urdf" / "ur10_robot.urdf"
    run_serial_calibration(namespace(tmp_path, path, serial=str(urdf), output=str(tmp_path / "ur10.urdf")))
    out = capsys.readouterr().out
    assert "file lines: 11" in out  # 2 comment lines and the header before the data: row 7 is line 11
    report = json.loads((tmp_path / "report.json").read_text(), parse_constant=pytest.fail)
    assert report["kind"] == "serial" and report["outliers"] == [11] and report["converged"] is True
    assert report["nominal_model"]["tool"] == "tool0" and report["nominal_model"]["base"] is None
    assert report["measurement_frame"]["estimated"] and report["marker"]["estimated"]
    frame = pin.XYZQUATToSE3(
        np.r_[report["measurement_frame"]["translation"], report["measurement_frame"]["quaternion"]]
    )
    assert np.linalg.norm(FRAMES["z180"].actInv(frame).translation) < 1e-2
    assert report["input"]["sha256"] and report["cross_validation"]["folds"] == 4
    assert report["residual_rms"]["after"]["position_m"] < 3e-5 and report["selection"]["method"] == "forward_loo"
    assert {p["name"] for p in report["parameters"]} >= set(chain.parameter_names())
    # The URDF is the robot alone: its base joint's origin is nominal, not the tracker frame.
    calibrated = pin.buildModelFromUrdf(str(tmp_path / "ur10.urdf"))
    j1 = chain.joint_ids[0]
    assert calibrated.jointPlacements[j1].isApprox(model.jointPlacements[j1], 1e-12)


@pytest.mark.parametrize("mistake, cause", [("frame", "another frame"), ("millimetres", "millimetres")])
def test_command_refuses_with_the_likely_cause(ur10, tmp_path, mistake: str, cause: str) -> None:
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=7, n_poses=30)
    rows = as_rows(measured)
    overrides: dict = {"frame": "base"} if mistake == "frame" else {}
    if mistake == "millimetres":
        rows[:, :3] *= 1e3  # a file in mm read as m
    path = tmp_path / "campaign.csv"
    write_campaign(path, chain, data.q_readings, rows)
    with pytest.raises(FitRejected, match=cause):
        run_serial_calibration(namespace(tmp_path, path, **overrides))
    assert not (tmp_path / "report.json").exists()
    if mistake == "millimetres":  # the same file with --units mm is accepted
        run_serial_calibration(namespace(tmp_path, path, units="mm"))
        assert json.loads((tmp_path / "report.json").read_text())["input"]["units"] == "mm"


def _noisy_campaign(ur10, tmp_path, noise: float):
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["x90"], seed=9, n_poses=40)
    rows = as_rows(measured)[:, :3] + np.random.default_rng(4).normal(0.0, noise, (40, 3))
    path = tmp_path / "campaign.csv"
    path.write_text(table_text(list(chain.joint_names) + ["x", "y", "z"], np.hstack([data.q_readings, rows])))
    return path


def test_a_residual_beyond_the_stated_noise_is_written_with_a_warning_and_auto_states_the_noise(
    ur10, tmp_path, capsys
) -> None:
    """0.1 mm of tracker noise stated as 10 um: no mistake explains it, so the fit is written, with
    the variance factor, the noise the residual implies and the cross-validated error; `auto`
    estimates the noise from the residual instead, and the report says so."""
    path = _noisy_campaign(ur10, tmp_path, 1e-4)
    run_serial_calibration(namespace(tmp_path, path))
    captured = capsys.readouterr()
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["variance_factor"] > 30 and len(report["warnings"]) == 1
    implied = float(report["warnings"][0].split("imply a noise of ")[1].split(" m")[0])
    assert 0.7e-4 < implied < 1.4e-4
    assert "none of the usual mistakes explains it" in captured.err and "cross-validated error" in captured.err
    assert report["noise_source"]["position"] == "stated"
    run_serial_calibration(namespace(tmp_path, path, noise_pos="auto"))
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["noise_source"]["position"] == "estimated" and report["warnings"] == []
    assert 0.7e-4 < report["noise_model"]["position_m"] < 1.4e-4
    assert 0.7 < report["variance_factor"] < 1.4
    assert "(estimated from the residual)" in capsys.readouterr().out


def test_a_gross_reading_is_left_out_by_line_not_blamed_on_the_robot(ur10, tmp_path, capsys) -> None:
    """One pose 1 m off among 40 made the start check refuse the whole fit as 'data from another machine'."""
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=6, n_poses=40)
    rows = as_rows(measured)
    rows[7, :3] += np.array([1.0, 0.0, 0.0])
    path = tmp_path / "campaign.csv"
    write_campaign(path, chain, data.q_readings, rows)
    with pytest.raises(RowFailures, match=r"line 11: the measured point is 0.99\d m from the nominal prediction"):
        run_serial_calibration(namespace(tmp_path, path, outlier_sigma=0.0))
    run_serial_calibration(namespace(tmp_path, path))
    assert "note: line 11: the measured point is 0.99" in capsys.readouterr().out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["outliers"] == [11] and report["input"]["poses"] == 40
    assert report["residual_rms"]["after"]["position_m"] < 3e-5


def test_a_joint_reading_beyond_its_limits_is_refused_by_line(ur10, tmp_path) -> None:
    """10 rad on a joint limited to 2 pi was read, and blocked the fit as a fault of the model."""
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=6, n_poses=12)
    q = data.q_readings.copy()
    q[4, 2] = 10.0
    path = tmp_path / "campaign.csv"
    write_campaign(path, chain, q, as_rows(measured))
    with pytest.raises(DataFileError) as caught:
        run_serial_calibration(namespace(tmp_path, path))
    limit = float(model.upperPositionLimit[model.idx_qs[chain.joint_ids[2]]])
    assert str(caught.value) == (
        f"{path}, line 8, column '{chain.joint_names[2]}': 10 rad is beyond the joint limit "
        f"[{-limit:.6g}, {limit:.6g}] (SI units: rad)"
    )
    q = np.degrees(data.q_readings)  # a whole file in degrees
    write_campaign(path, chain, q, as_rows(measured))
    with pytest.raises(DataFileError, match="within the limits in degrees: give radians"):
        run_serial_calibration(namespace(tmp_path, path))


def test_a_joint_reading_just_past_its_urdf_limit_is_kept_with_a_note(ur10, tmp_path, capsys) -> None:
    """A real joint is read up to its stop, a hair past its nominal URDF limit (TIAGo's torso at
    0.350181 m on [0, 0.35]): kept, with a note naming it, not refused as a bad reading."""
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=6, n_poses=12)
    q = data.q_readings.copy()
    limit = float(model.upperPositionLimit[model.idx_qs[chain.joint_ids[2]]])
    q[4, 2] = limit + 1e-3
    path = tmp_path / "campaign.csv"
    write_campaign(path, chain, q, as_rows(measured))
    run_serial_calibration(namespace(tmp_path, path))
    out = capsys.readouterr().out
    assert (
        f"note: column '{chain.joint_names[2]}': 1 reading(s) up to 0.001 rad beyond the URDF limit "
        f"[{-limit:.6g}, {limit:.6g}] (file line 8 first), within 5% of its range: kept as read"
    ) in out


def test_a_serial_urdf_pinocchio_cannot_read_or_with_a_mimic_joint_is_refused_by_name(tmp_path) -> None:
    broken = tmp_path / "broken.urdf"
    broken.write_text("not xml at all\n")
    with pytest.raises(ModelFileError, match=f"{broken}: Pinocchio cannot read this URDF"):
        serial_robots.load_serial_urdf(broken)
    mimic = tmp_path / "mimic.urdf"
    limit = '<limit lower="-2.8" upper="2.8" effort="1" velocity="1"/>'
    mimic.write_text(
        '<robot name="m"><link name="base"/><link name="l1"/><link name="l2"/><link name="tool"/>'
        f'<joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>{limit}</joint>'
        f'<joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.3 0 0"/>'
        f'<axis xyz="0 1 0"/>{limit}<mimic joint="j1"/></joint>'
        '<joint name="t" type="fixed"><parent link="l2"/><child link="tool"/><origin xyz="0.3 0 0"/></joint></robot>'
    )
    model, urdf = serial_robots.load_serial_urdf(mimic)
    with pytest.raises(ModelFileError) as caught:
        serial_robots.serial_chain_of(model, urdf, mimic, "tool", None)
    assert str(caught.value) == (
        f"{mimic}: joint 'j2' mimics joint 'j1' (<mimic>): m3t1r moves and calibrates "
        "every joint on its own, so a coupled joint is not supported; remove the tag (an "
        "independent joint) or make the joint fixed"
    )


# --------------------------------------------------------------------------------------------------
# The fitted compliance, applied by validate and compensate; constant joints; what stays nominal

UR10_URDF = serial_robots.example_robot_data_dir() / "ur_description" / "urdf" / "ur10_robot.urdf"
SAGGING = 3 * COMPLIANCE  # a 2-4 mm sag at the tool: far beyond the tracker's 10 um


def _sagging_campaign(model, chain, path, n: int, seed: int, constant: dict | None = None, compliance=SAGGING):
    """A UR10 with small geometric errors and joints that comply under gravity, measured in its base
    frame (tool0 itself, 10 um / 20 urad): (truth, q (n, 6))."""
    rng = np.random.default_rng(seed)
    truth = perturb(model, {p: rng.normal(0.0, 2e-4, 6) for p in chain.placements()})
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    q[:, 1], q[:, 2] = rng.uniform(-2.5, -0.5, n), rng.uniform(0.5, 2.5, n)
    for k, value in (constant or {}).items():
        q[:, chain.joint_names.index(k)] = value
    measured = tool_poses(chain, truth, q + compliance * S.gravity_torques(model, chain, q))
    measured[:, :3, 3] += rng.normal(0.0, NOISE.position, (n, 3))
    columns = [j for j in chain.joint_names if j not in (constant or {})]
    logged = q[:, [chain.joint_names.index(j) for j in columns]]
    header = columns + ["x", "y", "z", "qx", "qy", "qz", "qw"]
    path.write_text(table_text(header, np.hstack([logged, as_rows(measured)])))
    return truth, q


def test_the_fitted_compliance_is_applied_by_validate_and_compensate(ur10, tmp_path) -> None:
    """calibrate --compliance fitted a 1.99 mm model that validate then predicted at 13.4 mm: the
    compliance lives in the report, and validate and compensate apply it."""
    model, chain = ur10
    path, urdf, report_path = tmp_path / "campaign.csv", tmp_path / "ur10.urdf", tmp_path / "report.json"
    truth, _ = _sagging_campaign(model, chain, path, 60, seed=3)
    run_serial_calibration(
        namespace(
            tmp_path,
            path,
            serial=str(UR10_URDF),
            output=str(urdf),
            frame="base",
            marker=None,
            noise_rot=1e-4,
            compliance=True,
        )
    )
    report = json.loads(report_path.read_text())
    assert {"shoulder_lift_joint", "elbow_joint"} <= set(report["compliance"])
    fit = report["residual_rms"]["after"]["position_m"]
    assert fit < 3e-5
    validated = validation.validate(path, urdf, report_path)
    assert validated.errors.position_rms == pytest.approx(fit, rel=0.1)  # measured: 15.9 um against 15.7 um
    report["compliance"] = {}  # what validate predicted before: the geometry without its compliance
    (tmp_path / "rigid.json").write_text(json.dumps(report))
    assert validation.validate(path, urdf, tmp_path / "rigid.json").errors.position_rms > 30 * fit  # 3.56 mm
    # compensate: a joint program's nominal tool poses, reached by the sagging robot to the fit's accuracy
    program = np.random.default_rng(8).uniform([-3, -2.3, 0.6, -3, -3, -3], [3, -0.6, 2.4, 3, 3, 3], (15, 6))
    (tmp_path / "program.csv").write_text(table_text(chain.joint_names, program))
    assert (
        main(
            [
                "compensate",
                str(tmp_path / "program.csv"),
                "--calibrated",
                str(urdf),
                "--report",
                str(report_path),
                "--output-kind",
                "actuators",
                "-o",
                str(tmp_path / "commands.csv"),
            ]
        )
        == 0
    )
    table = read_table(tmp_path / "commands.csv", required=chain.joint_names)
    commands = np.column_stack([table.column(j) for j in chain.joint_names])
    target = tool_poses(chain, model, program)[:, :3, 3]

    def reached(q: np.ndarray) -> np.ndarray:
        return tool_poses(chain, truth, q + SAGGING * S.gravity_torques(model, chain, q))[:, :3, 3]

    uncompensated = np.linalg.norm(reached(program) - target, axis=1).mean()
    compensated = np.linalg.norm(reached(commands) - target, axis=1).mean()
    assert uncompensated > 1e-3 and compensated < 5e-5  # measured: 2.5 mm -> 5.9 um


def test_a_compliance_of_the_wrong_sign_is_not_called_a_stiffness(ur10, tmp_path, capsys) -> None:
    """On real data (TIAGo's wrist) the fit chose c > 0, a joint giving way against gravity: the note says
    the column stands for another effect."""
    model, chain = ur10
    path = tmp_path / "campaign.csv"
    _sagging_campaign(model, chain, path, 40, seed=3, compliance=-SAGGING)
    run_serial_calibration(
        namespace(tmp_path, path, serial=str(UR10_URDF), frame="base", marker=None, noise_rot=1e-4, compliance=True)
    )
    out = capsys.readouterr().out
    assert "fitted compliance of the wrong sign" in out and "elbow_joint +" in out
    assert any("not a stiffness" in note for note in json.loads((tmp_path / "report.json").read_text())["notes"])


def test_compliance_needs_the_links_masses_and_a_report(ur10, tmp_path) -> None:
    """--compliance on a URDF without inertias did nothing, silently: gravity torques are zero there."""
    model, chain = ur10
    path = tmp_path / "campaign.csv"
    _sagging_campaign(model, chain, path, 20, seed=4)
    massless = tmp_path / "massless.urdf"
    massless.write_text(re.sub(r"<inertial>.*?</inertial>", "", UR10_URDF.read_text(), flags=re.S))
    with pytest.raises(
        InvalidInputError,
        match=r"--compliance with .*massless.urdf: the links that joints "
        r"shoulder_pan_joint .. wrist_3_joint move have no mass",
    ):
        run_serial_calibration(
            namespace(tmp_path, path, serial=str(massless), frame="base", marker=None, compliance=True)
        )
    assert (
        main(
            [
                "calibrate",
                "--serial",
                str(UR10_URDF),
                "--tool",
                "tool0",
                "--compliance",
                str(path),
                "-o",
                str(tmp_path / "c.urdf"),
            ]
        )
        == 2
    )
    assert not (tmp_path / "c.urdf").exists() and not (tmp_path / "report.json").exists()


def test_a_chain_joint_that_is_not_logged_is_given_its_constant_value(ur10, tmp_path) -> None:
    """A tool changer never moves and is not logged: 'missing required columns' named no way out."""
    model, chain = ur10
    path, report_path = tmp_path / "campaign.csv", tmp_path / "report.json"
    _sagging_campaign(model, chain, path, 40, seed=5, constant={"wrist_3_joint": 0.3})
    with pytest.raises(
        DataFileError,
        match=r"missing required columns: wrist_3_joint; a chain joint that never "
        r"moves and is not logged \(a tool changer\) is given as "
        r"--joint wrist_3_joint=VALUE",
    ):
        run_serial_calibration(namespace(tmp_path, path, serial=str(UR10_URDF), frame="base", marker=None))
    urdf = tmp_path / "ur10.urdf"
    assert (
        main(
            [
                "calibrate",
                "--serial",
                str(UR10_URDF),
                "--tool",
                "tool0",
                str(path),
                "--joint",
                "wrist_3_joint=0.3",
                "--compliance",
                "--noise-rot",
                "1e-4",
                "-o",
                str(urdf),
                "--report",
                str(report_path),
            ]
        )
        == 0
    )
    report = json.loads(report_path.read_text())
    assert report["constant_joints"] == {"wrist_3_joint": 0.3}
    validated = validation.validate(path, urdf, report_path)  # the report's constant, the file without the column
    assert validated.errors.position_rms == pytest.approx(report["residual_rms"]["after"]["position_m"], rel=0.1)
    program = tmp_path / "program.csv"  # the program does not list the tool changer either
    program.write_text(table_text(chain.joint_names[:5], np.array([[0.3, -1.2, 1.4, -1.0, 1.1]])))
    assert (
        main(
            [
                "compensate",
                str(program),
                "--calibrated",
                str(urdf),
                "--report",
                str(report_path),
                "--output-kind",
                "actuators",
                "-o",
                str(tmp_path / "commands.csv"),
            ]
        )
        == 0
    )
    commands = read_table(tmp_path / "commands.csv", required=chain.joint_names)
    assert abs(commands.column("wrist_3_joint")[0] - 0.3) < 0.01  # the constant, corrected by milliradians
    with pytest.raises(InvalidInputError, match="--joint tool_changer: not a joint of the chain"):
        run_serial_calibration(namespace(tmp_path, path, joint={"tool_changer": 0.0}))


def test_every_placement_fixed_says_so_instead_of_not_separable(ur10, tmp_path, capsys) -> None:
    """'54 of 54 placement components are not separable' was printed when --fix held all of them."""
    model, chain = ur10
    data, measured = campaign(model, chain, FRAMES["z180"], seed=6, n_poses=30)
    path = tmp_path / "campaign.csv"
    write_campaign(path, chain, data.q_readings, as_rows(measured))
    everything = [*chain.joint_names, chain.tool_frame]
    run_serial_calibration(namespace(tmp_path, path, fix=everything, force=True))
    out = capsys.readouterr().out
    assert (
        "note: every placement component (42) is held at nominal by --fix: only the measurement setup was "
        "fitted, and the calibrated URDF keeps the nominal geometry" in out
    )
    assert "not separable" not in out and "barely moved" not in out
    run_serial_calibration(namespace(tmp_path, path, fix=everything[:2]))
    assert (
        "of 30 placement components left free (12 more are held at nominal by --fix) are not separable"
        in capsys.readouterr().out
    )
    _sagging_campaign(model, chain, path, 20, seed=4)  # in the base frame: with no marker, nothing left to fit
    with pytest.raises(IdentificationError, match="all 42 candidate parameters are held fixed: nothing is left"):
        run_serial_calibration(namespace(tmp_path, path, fix=everything, frame="base", marker=None))


def test_joint_readings_in_degrees_are_named_not_blamed_on_another_machine(ur10, tmp_path) -> None:
    """On joints without usable limits (continuous), a log in degrees was refused as 'data from another
    machine'; the radians file calibrates (a continuous joint's limits bound cos and sin, not the angle)."""
    model, chain = ur10
    continuous = tmp_path / "continuous.urdf"
    continuous.write_text(UR10_URDF.read_text().replace('type="revolute"', 'type="continuous"'))
    path = tmp_path / "campaign.csv"
    _, q = _sagging_campaign(model, chain, path, 30, seed=6)
    options = dict(serial=str(continuous), frame="base", marker=None, noise_rot=1e-4, compliance=True)
    run_serial_calibration(namespace(tmp_path, path, **options))
    table = read_table(path, required=(*chain.joint_names, "x", "y", "z", "qx", "qy", "qz", "qw"))
    rows = np.column_stack([table.column(c) for c in ("x", "y", "z", "qx", "qy", "qz", "qw")])
    write_campaign(path, chain, np.degrees(q), rows)
    with pytest.raises(FitRejected) as caught:
        run_serial_calibration(namespace(tmp_path, path, **options))
    causes = " ".join(caught.value.causes)
    assert "the joint readings look like degrees (columns 'shoulder_pan_joint'" in causes
    assert "--joint-degrees all" in causes and "another machine" not in causes


@pytest.mark.parametrize(
    "columns, convert",
    [
        (("roll", "pitch", "yaw"), "--euler SEQ [--degrees]"),
        (("rx", "ry", "rz"), "--rotation-vector"),
        (tuple(f"r{i}{j}" for i in "123" for j in "123"), "-o measurements.csv"),
    ],
)
def test_orientation_columns_other_than_a_quaternion_name_the_conversion(ur10, tmp_path, columns, convert) -> None:
    model, chain = ur10
    data, _ = campaign(model, chain, FRAMES["z180"], seed=6, n_poses=5)
    path = tmp_path / "campaign.csv"
    path.write_text(
        table_text(
            [*chain.joint_names, "x", "y", "z", *columns], np.hstack([data.q_readings, np.zeros((5, 3 + len(columns)))])
        )
    )
    with pytest.raises(DataFileError) as caught:
        run_serial_calibration(namespace(tmp_path, path))
    message = str(caught.value)
    assert "look like an orientation as" in message and f"`m3t1r convert {path} " in message and convert in message
    assert "another model" not in message


# Several points per pose (x1, y1, z1 ... xK, yK, zK), repeats held out together, a held-out file

POINTS = np.array([[0.05, 0.0, 0.03], [-0.04, 0.05, 0.06], [0.0, -0.06, 0.09], [0.03, 0.04, -0.01]])  # tool frame [m]


def point_campaign(model, chain, frame: pin.SE3, seed: int, n_poses: int = 50):
    """A 1 mm / 1 mrad UR10 measured through POINTS with NOISE.position: (data, points (N, 4, 3) [m])."""
    rng = np.random.default_rng(seed)
    data = serial_simulation.simulate_serial_measurements(model, chain, n_poses, rng, noise=None)
    tool = frame.homogeneous @ tool_poses(chain, data.truth, data.q_true)
    exact = np.einsum("nij,pj->npi", tool[:, :3, :3], POINTS) + tool[:, None, :3, 3]
    return data, exact + rng.normal(0.0, NOISE.position, exact.shape), exact


def write_points(path, chain, q, points: np.ndarray, sources: np.ndarray | None = None) -> None:
    columns = list(chain.joint_names) + [f"{a}{k}" for k in range(1, points.shape[1] + 1) for a in "xyz"]
    blocks = [q, points.reshape(len(points), -1)]
    if sources is not None:
        columns.append("source")
        blocks.append(sources[:, None].astype(float))
    blank = [c for c in columns if c[0] in "xyz"]
    path.write_text(table_text(columns, np.hstack(blocks), ["four markers on the tool"], blank_allowed=blank))


def test_several_points_per_pose_calibrate_with_each_offset_and_predict_every_point(ur10) -> None:
    model, chain = ur10
    data, points, _ = point_campaign(model, chain, FRAMES["x90"], seed=8)
    points[[3, 17, 30], [1, 0, 3]] = np.nan  # occluded markers
    points[22, 2] += np.array([0.0, 3e-3, 0.0])  # a 3 mm gross reading of one marker
    calibration = S.calibrate_serial(
        model, chain, data.q_readings, points, CalibrationOptions(noise=NOISE, estimate_frame=True), position_only=True
    )
    assert calibration.converged and calibration.outliers == (22,)
    assert 0.6 < calibration.variance_factor < 1.5
    assert calibration.rms_before.position > 1e-3 and calibration.rms_after.position < 2e-5
    assert len(calibration.setup.points) == 4
    # The common part of the offsets is the tool placement's (the gauge); their differences are not.
    offsets = np.array(calibration.setup.points)
    assert np.max(np.abs((offsets - offsets[0]) - (POINTS - POINTS[0]))) < 2e-4
    fresh, _, exact = point_campaign(model, chain, FRAMES["x90"], seed=8, n_poses=80)
    predicted = serial_evaluation.predict_points(calibration, fresh.q_readings[50:])
    assert np.max(np.linalg.norm(predicted - exact[50:], axis=2)) < 6e-5
    validation = serial_evaluation.cross_validate_serial(calibration, folds=5)
    assert validation.errors.position.shape == (49 * 4 - 3,)  # every inlier point seen
    assert validation.errors.position_mean < 4e-5


def test_a_points_residual_jacobian_matches_finite_differences(ur10) -> None:
    # Placements, frame, offsets and compliance columns against central differences, a point missing.
    model, chain = ur10
    data, points, _ = point_campaign(model, chain, FRAMES["z180"], seed=9, n_poses=6)
    points[2, 1] = np.nan
    measurements = S.parse_measurements(chain, data.q_readings, points, True)
    layout = S.SerialLayout(chain.n_joints, True, 12, True, 4)
    start = S.start_state(chain, model, measurements, MeasurementSetup(), True, True, True)
    whitening = S.pose_whitening(chain, start, measurements, NOISE, 1e-5)
    torques = S.gravity_torques(model, chain, data.q_readings)
    residual = S.SerialResidual(chain, measurements, whitening, layout, torques)
    state = residual.retract(start, np.full(layout.size, 1e-3))
    r, J = residual.residual_and_jacobian(state)
    assert np.all(r.reshape(6, 12)[2, 3:6] == 0.0) and np.all(J.reshape(6, 12, -1)[2, 3:6] == 0.0)
    step = 1e-7
    numeric = np.empty_like(J)
    for i in range(layout.size):
        dx = np.zeros(layout.size)
        dx[i] = step
        plus, minus = residual.retract(state, dx), residual.retract(state, -dx)
        numeric[:, i] = (residual.residual(plus) - residual.residual(minus)) / (2 * step)
    assert np.linalg.norm(J - numeric) <= 1e-6 * np.linalg.norm(J)


def test_the_command_reads_points_scores_a_held_out_file_and_holds_repeats_out_together(ur10, tmp_path, capsys):
    model, chain = ur10
    data, points, _ = point_campaign(model, chain, FRAMES["z180"], seed=10, n_poses=70)
    # Each of the first 24 postures measured twice (fresh noise, same joint readings): 48 rows, 24 postures.
    repeat = points[:24] + np.random.default_rng(1).normal(0.0, NOISE.position, points[:24].shape)
    points[5, 2] = np.nan
    points[12, 1] += np.array([4e-3, 0.0, 0.0])  # gross
    q = np.vstack([data.q_readings[:24], data.q_readings[:24], data.q_readings[24:40]])
    sources = np.arange(100, 100 + len(q))
    path, held = tmp_path / "campaign.csv", tmp_path / "held.csv"
    write_points(path, chain, q, np.vstack([points[:24], repeat, points[24:40]]), sources)
    write_points(held, chain, data.q_readings[40:], points[40:])
    run_serial_calibration(namespace(tmp_path, path, marker=None, validate=str(held)))
    out = capsys.readouterr().out
    assert "file lines: 15" in out and "outliers in the tracker's file (the source column): 112" in out
    assert "40 distinct postures, each held out whole" in out and "per point (4 per pose)" in out
    report = json.loads((tmp_path / "report.json").read_text(), parse_constant=pytest.fail)
    assert report["input"]["points"] == 4 and len(report["points"]) == 4 and report["outlier_sources"] == [112]
    assert report["cross_validation"]["groups"] == 40  # the outlier's repeat keeps its posture in
    assert report["cross_validation"]["position_rms_m"] < 5e-5
    held_out = report["held_out"]
    assert held_out["poses"] == 30 and held_out["per"] == "point" and held_out["position_rms_m"] < 5e-5
    assert held_out["position_mean_m"] <= held_out["position_rms_m"] <= held_out["position_max_m"]
    with pytest.raises(InvalidInputError, match="fitted 4 points per pose; validate reads one measured frame"):
        validate(held, tmp_path / "ur10.urdf", tmp_path / "report.json")


def test_points_with_a_marker_or_a_partly_blank_point_are_refused(ur10, tmp_path) -> None:
    model, chain = ur10
    data, points, _ = point_campaign(model, chain, FRAMES["z180"], seed=11, n_poses=20)
    path = tmp_path / "campaign.csv"
    write_points(path, chain, data.q_readings, points)
    with pytest.raises(InvalidInputError, match="each point's offset on the tool is estimated: --marker"):
        run_serial_calibration(namespace(tmp_path, path))
    frames = tmp_path / "frames.csv"
    write_campaign(frames, chain, data.q_readings, as_rows(campaign(model, chain, FRAMES["z180"], seed=11)[1][:20]))
    with pytest.raises(InvalidInputError, match="one measured frame per row, but .* has 4 points per row"):
        run_serial_calibration(namespace(tmp_path, path, marker=None, validate=str(frames)))
    assert not (tmp_path / "report.json").exists()
    text = path.read_text().splitlines()
    fields = text[-1].split(",")
    fields[7] = ""  # y1 of the last row blank, x1 and z1 given
    path.write_text("\n".join(text[:-1] + [",".join(fields)]) + "\n")
    with pytest.raises(DataFileError, match=f"line {len(text)}.*y1.*point 1 has some coordinates blank"):
        run_serial_calibration(namespace(tmp_path, path, marker=None))
