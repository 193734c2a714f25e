"""Real instruments' files: each format read, streams turned into static poses, poses paired with the
robot's log by order or by an estimated clock offset, `m3t1r convert` end to end, and a converted
campaign calibrating like the plain CSV.

Every sample file is written here from the format's public description, from one simulated
campaign: a UR10 whose tool carries a reflector (and a rigid body) 70 mm off the flange, seen by a
tracker in its own frame at 100 Hz with 50 um noise, dwelling 1.5 s at each posture and moving
1 s between them; the robot's clock runs 0.8 s ahead of the tracker's.
"""

from __future__ import annotations

import builtins
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from command_lines import serial_calibration_arguments
from scipy.spatial.transform import Rotation

from m3t1r.app.cli import main
from m3t1r.app.cli_serial import run_serial_calibration
from m3t1r.calibration import serial_robots, serial_simulation
from m3t1r.errors import DataFileError, InvalidInputError, MissingExtraError
from m3t1r.io.instruments import c3d as c3d_reader
from m3t1r.io.instruments.conversion import ConversionOptions, convert_campaign
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.dwells import pair_by_clock, pair_by_order, stationary_stretches
from m3t1r.io.instruments.formats import detect_format
from m3t1r.io.tables import read_table, table_text
from m3t1r.model.poe import SerialChain, tool_poses

RATE, DWELL, MOVE, NOISE, CLOCK_OFFSET = 100.0, 1.5, 1.0, 50e-6, 0.8
FRAME = pin.SE3(pin.utils.rotate("z", 2.2) @ pin.utils.rotate("x", 0.1), np.array([1.8, -0.6, 0.4]))
MARKER = np.array([0.01, -0.02, 0.07])
BODY = pin.SE3(pin.utils.rotate("y", 0.4), MARKER)


@dataclass(frozen=True)
class Campaign:
    """The simulated session: per frame the tracker time [s], joints, point [m] and body pose;
    per posture its joints and exact point; robot log times on the robot's clock."""

    chain: SerialChain
    times: np.ndarray
    joints: np.ndarray
    points: np.ndarray
    bodies: np.ndarray
    postures: np.ndarray
    exact: np.ndarray


@pytest.fixture(scope="module")
def session() -> Campaign:
    model = serial_robots.load_example_robot("ur10")
    chain = SerialChain.from_model(model, "tool0")
    rng = np.random.default_rng(11)
    data = serial_simulation.simulate_serial_measurements(model, chain, 24, rng, noise=None)
    postures = data.q_true
    times, joints = [], []
    t = 0.0
    for k, q in enumerate(postures):
        dwell = np.arange(0.0, DWELL, 1 / RATE)
        times.append(t + dwell)
        joints.append(np.tile(q, (len(dwell), 1)))
        t += DWELL
        if k + 1 < len(postures):
            move = np.arange(0.0, MOVE, 1 / RATE)
            s = 0.5 - 0.5 * np.cos(np.pi * move / MOVE)  # a smooth start and stop
            times.append(t + move)
            joints.append(q + s[:, None] * (postures[k + 1] - q))
            t += MOVE
    times, joints = np.concatenate(times), np.concatenate(joints)
    tool = FRAME.homogeneous @ tool_poses(chain, data.truth, joints)
    bodies = tool @ BODY.homogeneous
    points = bodies[:, :3, 3] + rng.normal(0.0, NOISE, (len(times), 3))
    bodies[:, :3, 3] = points
    exact = (FRAME.homogeneous @ tool_poses(chain, data.truth, postures) @ BODY.homogeneous)[:, :3, 3]
    return Campaign(chain, times, joints, points, bodies, postures, exact)


def robot_log(path: Path, session: Campaign) -> Path:
    """The robot's joint log on its own clock, as a controller records it."""
    columns = ["time", *session.chain.joint_names]
    path.write_text(table_text(columns, np.column_stack([session.times + CLOCK_OFFSET, session.joints])))
    return path


def _mm(values: np.ndarray) -> list[str]:
    return [f"{1e3 * v:.4f}" for v in values]


def motive_csv(path: Path, session: Campaign, occluded: slice = slice(0, 0)) -> Path:
    """A Motive take: rigid body 'tool' (quaternion X, Y, Z, W, position) and a marker, mm."""
    n = len(session.times)
    lines = [
        f"Format Version,1.23,Take Name,calibration,Capture Frame Rate,{RATE:.6f},Export Frame Rate,{RATE:.6f},"
        f"Total Frames in Take,{n},Total Exported Frames,{n},Rotation Type,Quaternion,Length Units,Millimeters,"
        "Coordinate Space,Global",
        "",
        ",,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,"
        "Marker,Marker,Marker",
        ",,tool,tool,tool,tool,tool,tool,tool,tool,spare,spare,spare",
        ",,1,1,1,1,1,1,1,1,2,2,2",
        ",,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Mean Marker Error,Position,Position,Position",
        "Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,,X,Y,Z",
    ]
    quaternions = Rotation.from_matrix(session.bodies[:, :3, :3]).as_quat()
    hidden = np.zeros(n, bool)
    hidden[occluded] = True
    for k in range(n):
        body = [""] * 8 if hidden[k] else [f"{v:.8f}" for v in quaternions[k]] + _mm(session.points[k]) + ["0.1"]
        lines.append(",".join([str(k), f"{session.times[k]:.6f}", *body, "1.0", "2.0", "3.0"]))
    path.write_text("\n".join(lines) + "\n")
    return path


def vicon_csv(path: Path, session: Campaign) -> Path:
    """A Nexus export: a Trajectories block with two markers of subject 'robot', mm."""
    lines = [
        "Trajectories",
        f"{RATE:g}",
        ",,robot:BL,,,robot:TR,,",
        "Frame,Sub Frame,X,Y,Z,X,Y,Z",
        ",,mm,mm,mm,mm,mm,mm",
    ]
    for k in range(len(session.times)):
        lines.append(",".join([str(k + 1), "0", *_mm(session.points[k]), *_mm(session.points[k] + 0.05)]))
    path.write_text("\n".join(lines + [""]) + "\n")
    return path


def semicolon_csv(path: Path, session: Campaign) -> Path:
    """The project's columns plus a time, `;`-separated with decimal commas, joints in the same file."""
    columns = ["time", *session.chain.joint_names, "x", "y", "z", "operator"]
    lines = [";".join(columns)]
    for t, q, p in zip(session.times, session.joints, session.points):
        lines.append(";".join([repr(float(v)).replace(".", ",") for v in (t, *q, *p)] + ["ana"]))
    path.write_text("\n".join(lines) + "\n")
    return path


def plain_csv(path: Path, session: Campaign, rng_seed: int = 3) -> Path:
    """The project's own format: one averaged pose per posture (the same noise as a 1 s dwell)."""
    rng = np.random.default_rng(rng_seed)
    points = session.exact + rng.normal(0.0, NOISE / 10.0, session.exact.shape)
    path.write_text(table_text([*session.chain.joint_names, "x", "y", "z"], np.hstack([session.postures, points])))
    return path


def test_each_export_is_recognised_from_its_content(session, tmp_path) -> None:
    assert detect_format(motive_csv(tmp_path / "take.csv", session)) == "motive"
    assert detect_format(vicon_csv(tmp_path / "nexus.csv", session)) == "vicon"
    assert detect_format(semicolon_csv(tmp_path / "log.csv", session)) == "csv"
    sa = tmp_path / "points.txt"
    sa.write_text("// SpatialAnalyzer export\n// Units: Millimeters\nA\tCal\tP1\t1.0\t2.0\t3.0\n")
    assert detect_format(sa) == "spatial-analyzer"
    unknown = tmp_path / "unknown.csv"
    unknown.write_text("alpha,beta\n1,2\n")
    with pytest.raises(DataFileError, match="give --format"):
        detect_format(unknown)


def test_a_motive_take_with_a_clock_offset_converts_to_one_pose_per_dwell(session, tmp_path) -> None:
    take = motive_csv(tmp_path / "take.csv", session, occluded=slice(40, 70))  # 0.3 s unseen in the first dwell
    log = robot_log(tmp_path / "robot.csv", session)
    conversion = convert_campaign(take, log, ConversionOptions())
    assert conversion.format == "motive" and conversion.clock_offset == pytest.approx(CLOCK_OFFSET, abs=0.02)
    columns = conversion.columns
    assert columns[:6] == session.chain.joint_names and columns[6:] == (
        "x",
        "y",
        "z",
        "qx",
        "qy",
        "qz",
        "qw",
        "source",
        "position_std",
    )
    rows = conversion.rows
    assert len(rows) == len(session.postures)
    assert np.allclose(rows[:, :6], session.postures, atol=1e-9)  # each stop's joints, not mid-move
    error = np.linalg.norm(rows[:, 6:9] - session.exact, axis=1)
    assert error.max() < 5 * NOISE / np.sqrt(50)  # averaged over 50+ frames
    assert np.all((rows[:, -1] > 0.5 * NOISE) & (rows[:, -1] < 3 * NOISE))  # each dwell's scatter
    rotation = Rotation.from_quat(rows[:, 9:13]).as_matrix()
    truth = Rotation.from_matrix(session.bodies[0, :3, :3]).as_matrix()
    assert np.linalg.norm(pin.log3(rotation[0].T @ truth)) < 1e-6
    assert rows[0, 13] == 8  # the first dwell starts on the file's line 8
    assert any("clock offset: robot clock = tracker clock +0.8" in note for note in conversion.notes)


def test_a_vicon_trajectory_and_a_semicolon_log_give_the_same_poses(session, tmp_path) -> None:
    nexus = vicon_csv(tmp_path / "nexus.csv", session)
    log = robot_log(tmp_path / "robot.csv", session)
    vicon = convert_campaign(nexus, log, ConversionOptions(read=ReadOptions(body="robot:BL")))
    own = convert_campaign(semicolon_csv(tmp_path / "own.csv", session), None, ConversionOptions())
    assert vicon.columns[6:] == own.columns[6:] == ("x", "y", "z", "source", "position_std")
    assert np.allclose(vicon.rows[:, 6:9], own.rows[:, 6:9], atol=5e-5)
    assert np.allclose(own.rows[:, :6], session.postures, atol=1e-9)
    with pytest.raises(DataFileError, match="robot:BL \\(Trajectories\\), robot:TR"):
        convert_campaign(nexus, log, ConversionOptions())


def test_several_markers_in_figaroh_s_layout_are_read_one_at_a_time(session, tmp_path) -> None:
    names = list(session.chain.joint_names)
    columns = (
        [f"{a}{k}" for k in range(1, 5) for a in "xyz"] + names + ["shipped_row", "t_start_robot", "marker_std_mm"]
    )
    values = np.hstack(
        [session.exact + 0.01 * k for k in range(4)]
        + [
            session.postures,
            np.arange(len(session.postures))[:, None],
            1e9 + np.arange(len(session.postures))[:, None],
            np.full((len(session.postures), 1), 0.2),
        ]
    )
    path = tmp_path / "figaroh.csv"
    path.write_text(table_text(columns, values))
    first = convert_campaign(path, None, ConversionOptions())
    third = convert_campaign(path, None, ConversionOptions(read=ReadOptions(body="3")))
    assert np.allclose(third.rows[:, 6:9] - first.rows[:, 6:9], 0.02) and first.columns[:6] == tuple(names)
    assert np.allclose(first.rows[:, -1], 2e-4)  # the scatter column, mm -> m
    assert any("markers 1, 2, 3, 4" in n for n in first.notes)
    assert any("shipped_row, t_start_robot" in n for n in first.notes)
    with pytest.raises(DataFileError, match="markers 1, 2, 3, 4"):
        convert_campaign(path, None, ConversionOptions(read=ReadOptions(body="7")))


def test_a_spatial_analyzer_export_pairs_with_the_robot_s_stops_by_order(session, tmp_path) -> None:
    lines = ["// SpatialAnalyzer ASCII export", "// Units: Millimeters"]
    lines += [f"A\tCalibration\tP{k:03d}\t" + "\t".join(_mm(p)) for k, p in enumerate(session.exact)]
    export = tmp_path / "points.txt"
    export.write_text("\n".join(lines) + "\n")
    stops = tmp_path / "stops.csv"
    stops.write_text(table_text(session.chain.joint_names, session.postures))
    conversion = convert_campaign(export, stops, ConversionOptions())
    assert np.allclose(conversion.rows[:, 6:9], session.exact, atol=1e-7) and conversion.clock_offset is None
    assert conversion.rows[0, 9] == 3
    few = tmp_path / "few.csv"
    few.write_text(table_text(session.chain.joint_names, session.postures[:-1]))
    with pytest.raises(InvalidInputError, match="24 tracker dwells but 23 robot stops"):
        convert_campaign(export, few, ConversionOptions())
    unitless = tmp_path / "unitless.txt"
    unitless.write_text("\n".join(lines[2:]) + "\n")
    with pytest.raises(DataFileError, match="give --units"):
        convert_campaign(unitless, stops, ConversionOptions())


def test_still_stretches_and_clock_pairing_on_their_own() -> None:
    times = np.arange(0.0, 10.0, 0.01)
    values = np.cumsum(np.where((times % 2.5) >= 1.5, 0.001, 0.0))[:, None]  # still, then moving 0.1 m/s
    stretches = stationary_stretches(times, values, 5e-3, 0.5)
    assert len(stretches) == 4 and all(1.0 <= s.t_end - s.t_start <= 1.5 for s in stretches)
    shifted = [type(s)(s.start, s.stop, s.t_start + 1234.5, s.t_end + 1234.5) for s in stretches]
    pairing = pair_by_clock(stretches, shifted[1:])  # the robot log starts after the first stop
    assert pairing.offset == pytest.approx(1234.5) and pairing.pairs == (-1, 0, 1, 2)
    with pytest.raises(InvalidInputError, match="4 tracker dwells but 3 robot stops"):
        pair_by_order(4, 3)
    with pytest.raises(InvalidInputError, match="do not increase"):
        stationary_stretches(times[::-1], values, 5e-3, 0.5)


def test_the_c3d_reader_names_the_extra_it_needs(tmp_path, monkeypatch) -> None:
    real_import = builtins.__import__

    def without_ezc3d(name, *args, **kwargs):
        if name == "ezc3d":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", without_ezc3d)
    path = tmp_path / "session.c3d"
    path.write_bytes(b"\x02\x50" + bytes(510))
    with pytest.raises(MissingExtraError, match=r"pip install 'm3t1r\[formats\]'"):
        c3d_reader.read_c3d(path, ReadOptions(), [])


def test_a_c3d_file_converts_with_its_units(session, tmp_path) -> None:
    import ezc3d  # the m3t1r[formats] extra, which `make test` installs: missing, this fails, not skips

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [RATE]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ("BL", "TR")
    points = np.ones((4, 2, len(session.times)))
    points[:3, 0, :] = 1e3 * session.points.T
    points[:3, 1, :] = 1e3 * session.points.T + 50.0
    c3d["data"]["points"] = points
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    path = tmp_path / "session.c3d"
    c3d.write(str(path))
    conversion = convert_campaign(
        path, robot_log(tmp_path / "robot.csv", session), ConversionOptions(read=ReadOptions(body="BL"))
    )
    assert conversion.format == "c3d" and conversion.clock_offset == pytest.approx(CLOCK_OFFSET, abs=0.02)
    assert np.allclose(conversion.rows[:, 6:9], session.exact, atol=5e-5)


def test_a_ros2_bag_of_poses_and_joint_states_converts(session, tmp_path) -> None:
    from rosbags.rosbag2 import Writer  # the m3t1r[formats] extra, which `make test` installs
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    Time, Header = types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]
    Pose, Point, Quaternion = (
        types["geometry_msgs/msg/Pose"],
        types["geometry_msgs/msg/Point"],
        types["geometry_msgs/msg/Quaternion"],
    )
    PoseStamped, JointState = types["geometry_msgs/msg/PoseStamped"], types["sensor_msgs/msg/JointState"]

    def header(t: float) -> object:
        return Header(stamp=Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9))), frame_id="tracker")

    bag = tmp_path / "session_bag"
    quaternions = Rotation.from_matrix(session.bodies[:, :3, :3]).as_quat()
    with Writer(bag, version=8) as writer:
        poses = writer.add_connection("/tracker/tool", PoseStamped.__msgtype__, typestore=store)
        states = writer.add_connection("/joint_states", JointState.__msgtype__, typestore=store)
        for k, t in enumerate(session.times[::2]):  # 50 Hz is plenty here
            i = 2 * k
            x, y, z = session.points[i]
            qx, qy, qz, qw = quaternions[i]
            pose = PoseStamped(
                header=header(100.0 + t),
                pose=Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
            )
            writer.write(poses, int((100.0 + t) * 1e9), store.serialize_cdr(pose, PoseStamped.__msgtype__))
            state = JointState(
                header=header(100.0 + t + CLOCK_OFFSET),
                name=list(session.chain.joint_names),
                position=session.joints[i].copy(),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            )
            writer.write(states, int((100.0 + t) * 1e9), store.serialize_cdr(state, JointState.__msgtype__))
    conversion = convert_campaign(bag, bag, ConversionOptions())
    assert conversion.format == "rosbag" and conversion.clock_offset == pytest.approx(CLOCK_OFFSET, abs=0.03)
    assert len(conversion.rows) == len(session.postures)
    assert np.allclose(conversion.rows[:, :6], session.postures, atol=1e-9)
    assert np.allclose(conversion.rows[:, 6:9], session.exact, atol=5e-5)


def test_convert_writes_a_table_that_calibrates_like_the_plain_csv(session, tmp_path, capsys) -> None:
    take = motive_csv(tmp_path / "take.csv", session)
    lines = take.read_text().splitlines()
    first = 7 + int(12 * (DWELL + MOVE) * RATE)  # frame 0 is on line 8; posture 12 dwells from t = 30 s
    for k in range(first, first + int(DWELL * RATE)):  # 5 mm on x for the whole dwell: a gross reading
        fields = lines[k].split(",")
        fields[6] = f"{float(fields[6]) + 5.0:.4f}"
        lines[k] = ",".join(fields)
    take.write_text("\n".join(lines) + "\n")
    converted = tmp_path / "converted.csv"
    assert (
        main(
            [
                "convert",
                str(take),
                "--robot",
                str(robot_log(tmp_path / "robot.csv", session)),
                "--body",
                "tool",
                "-o",
                str(converted),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "clock offset: robot clock = tracker clock +0.8" in out and "wrote 24 poses" in out
    table = read_table(
        converted,
        required=("x", "y", "z", "source"),
        optional=(*session.chain.joint_names, "qx", "qy", "qz", "qw", "position_std"),
    )
    assert table.n_rows == 24 and np.all(np.diff(table.column("source")) > 0)
    plain = plain_csv(tmp_path / "plain.csv", session)
    reports = {}
    for name, path in (("plain", plain), ("converted", converted)):
        report = tmp_path / f"{name}.json"
        marker = [0.0, 0.0, 0.0]  # --marker 0 0 0: the body estimated from the flange
        run_serial_calibration(
            serial_calibration_arguments(path, report, noise_pos=NOISE, noise_rot=1e-4, marker=marker)
        )
        reports[name] = json.loads(report.read_text())
    out = capsys.readouterr().out
    gross = int(table.column("source")[12])
    assert reports["converted"]["outlier_sources"] == [gross]
    assert f"outliers in the tracker's file (the source column): {gross}" in out
    frames = [
        pin.XYZQUATToSE3(np.r_[r["measurement_frame"]["translation"], r["measurement_frame"]["quaternion"]])
        for r in reports.values()
    ]
    assert np.linalg.norm(frames[0].actInv(frames[1]).translation) < 2e-3  # the same frame, within the noise
    assert np.linalg.norm(frames[0].actInv(FRAME).translation) < 5e-3
    errors = [r["cross_validation"]["position_rms_m"] for r in reports.values()]
    assert errors[0] < 1e-4 and errors[1] < 1e-4  # both predict within a few noise sigmas


def test_calibrate_names_an_export_and_the_command_that_converts_it(session, tmp_path, capsys) -> None:
    take = motive_csv(tmp_path / "take.csv", session)
    assert main(["calibrate", str(take), "--serial", "ur10", "-o", str(tmp_path / "c.urdf")]) == 2
    err = capsys.readouterr().err
    assert "export (OptiTrack Motive CSV export), not a measurement table" in err and "m3t1r convert" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.csv"]


def test_three_markers_or_more_make_one_rigid_body(session, tmp_path) -> None:
    offsets = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.02], [0.0, 0.12, 0.0], [0.05, 0.05, 0.09]])
    bodies = session.bodies[::150][:12]  # one frame per dwell
    clouds = bodies[:, None, :3, :3] @ offsets[None, :, :, None]
    clouds = clouds[..., 0] + bodies[:, None, :3, 3]
    columns = [f"{a}{k}" for k in range(1, 5) for a in "xyz"] + list(session.chain.joint_names)
    path = tmp_path / "cluster.csv"
    path.write_text(table_text(columns, np.hstack([clouds.reshape(len(bodies), 12), session.postures[:12]])))
    rows = convert_campaign(path, None, ConversionOptions(read=ReadOptions(body="rigid"))).rows
    assert np.allclose(rows[:, 6:9], clouds.mean(axis=1), atol=1e-12)
    relative = Rotation.from_quat(rows[:, 9:13]).as_matrix()
    assert np.allclose(relative, bodies[:, :3, :3] @ bodies[0, :3, :3].T, atol=1e-9)  # axes of the first sample
    two = tmp_path / "two.csv"
    two.write_text(
        table_text(columns[:6] + columns[12:], np.hstack([clouds[:, :2].reshape(12, 6), session.postures[:12]]))
    )
    with pytest.raises(DataFileError, match="three markers or more"):
        convert_campaign(two, None, ConversionOptions(read=ReadOptions(body="rigid")))


def test_a_vicon_object_s_helical_angles_become_its_orientation(session, tmp_path) -> None:
    rotvec = np.degrees(Rotation.from_matrix(session.bodies[:, :3, :3]).as_rotvec())
    lines = ["Objects", f"{RATE:g}", ",,tool,,,,,", "Frame,Sub Frame,RX,RY,RZ,TX,TY,TZ", ",,deg,deg,deg,mm,mm,mm"]
    for k in range(len(session.times)):
        occluded = 200 <= k < 210
        fields = [""] * 6 if occluded else [f"{v:.8f}" for v in rotvec[k]] + _mm(session.points[k])
        lines.append(",".join([str(k + 1), "0", *fields]))
    path = tmp_path / "tracker.csv"
    path.write_text("\n".join(lines) + "\n")
    conversion = convert_campaign(path, robot_log(tmp_path / "robot.csv", session), ConversionOptions())
    assert conversion.format == "vicon" and len(conversion.rows) == len(session.postures)
    dwell_middle = (np.arange(len(session.postures)) * (DWELL + MOVE) * RATE + 75).astype(int)
    truth = session.bodies[dwell_middle, :3, :3]
    found = Rotation.from_quat(conversion.rows[:, 9:13]).as_matrix()
    assert max(np.linalg.norm(pin.log3(a.T @ b)) for a, b in zip(found, truth)) < 1e-6


def test_rotation_vectors_and_matrices_convert_to_the_same_quaternions(tmp_path) -> None:
    """Trackers and robot controllers log orientations as a rotation vector (UR's rx, ry, rz) or a
    matrix: read by explicit flag or unambiguous names, as the quaternions they are."""
    rotations = Rotation.random(6, random_state=2)
    points = np.random.default_rng(1).normal(size=(6, 3))
    joints = np.linspace(-1, 1, 6)[:, None]
    files = {
        "rv": (["rx", "ry", "rz"], np.degrees(rotations.as_rotvec()), ["--rotation-vector", "--degrees"]),
        "rvx": (["rvx", "rvy", "rvz"], rotations.as_rotvec(), []),
        "matrix": ([f"r{i}{j}" for i in "123" for j in "123"], rotations.as_matrix().reshape(6, 9), []),
    }
    for name, (columns, values, flags) in files.items():
        source = tmp_path / f"{name}.csv"
        source.write_text(table_text(["j1", "x", "y", "z", *columns], np.hstack([joints, points, values])))
        assert main(["convert", str(source), *flags, "-o", str(tmp_path / f"{name}_q.csv")]) == 0
        table = read_table(
            tmp_path / f"{name}_q.csv",
            required=("j1", "x", "y", "z", "qx", "qy", "qz", "qw"),
            optional=("source", "position_std"),
        )
        found = Rotation.from_quat(np.column_stack([table.column(c) for c in ("qx", "qy", "qz", "qw")]))
        assert np.max((found.inv() * rotations).magnitude()) < 1e-9, name
        assert np.allclose(table.column("j1"), joints[:, 0], atol=1e-12)
    with pytest.raises(DataFileError, match="--rotation-vector"):  # rx, ry, rz alone: Euler or a vector, say which
        convert_campaign(tmp_path / "rv.csv", None, ConversionOptions())
    skewed = rotations.as_matrix().reshape(6, 9)
    skewed[3, 0] += 0.01
    (tmp_path / "bad.csv").write_text(
        table_text(["j1", "x", "y", "z", *files["matrix"][0]], np.hstack([joints, points, skewed]))
    )
    with pytest.raises(DataFileError, match=r"line 5: r11 ... r33 are not a rotation matrix"):
        convert_campaign(tmp_path / "bad.csv", None, ConversionOptions())


def test_every_marker_of_a_stream_is_kept_as_points_and_calibrates(session, tmp_path, capsys) -> None:
    """Three markers on the tool in a timed stream, one hidden for part of a dwell and another for a
    whole dwell: `--body all` averages each marker over the frames that saw it and leaves a blank
    where none did; the table calibrates with each marker's offset estimated."""
    offsets = np.array([[0.0, 0.0, 0.0], [0.08, 0.0, 0.03], [0.0, 0.09, -0.02]])  # from the reflector, tool axes
    tool = session.bodies.copy()
    clouds = (tool[:, None, :3, :3] @ offsets[None, :, :, None])[..., 0] + tool[:, None, :3, 3]
    clouds[300:420, 1] = np.nan  # marker 2 hidden for part of posture 1's dwell (frames 250 to 399)
    dwell = slice(int(5 * (DWELL + MOVE) * RATE), int(5 * (DWELL + MOVE) * RATE + DWELL * RATE))
    clouds[dwell, 2] = np.nan  # marker 3 never seen at posture 5
    columns = ["time", *[f"{a}{k}" for k in range(1, 4) for a in "xyz"]]
    stream = tmp_path / "stream.csv"
    stream.write_text(
        table_text(columns, np.column_stack([session.times, clouds.reshape(len(clouds), 9)]), blank_allowed=columns[1:])
    )
    converted = tmp_path / "points.csv"
    assert (
        main(
            [
                "convert",
                str(stream),
                "--robot",
                str(robot_log(tmp_path / "robot.csv", session)),
                "--body",
                "all",
                "-o",
                str(converted),
            ]
        )
        == 0
    )
    assert "markers 1, 2, 3 as points" in capsys.readouterr().out
    names = session.chain.joint_names
    points = [f"{a}{k}" for k in range(1, 4) for a in "xyz"]
    table = read_table(
        converted, required=(*names, *points, "source"), optional=("position_std",), blank_allowed=points
    )
    assert table.n_rows == 24 and np.isnan(table.column("x3")[5]) and np.isfinite(table.column("x2")).all()
    exact = (
        FRAME.homogeneous
        @ tool_poses(
            session.chain,
            serial_simulation.simulate_serial_measurements(
                serial_robots.load_example_robot("ur10"), session.chain, 24, np.random.default_rng(11), noise=None
            ).truth,
            session.postures,
        )
        @ BODY.homogeneous
    )
    second = exact[:, :3, :3] @ offsets[1] + exact[:, :3, 3]
    assert np.max(np.abs(np.column_stack([table.column(c) for c in "x2 y2 z2".split()]) - second)) < 5 * NOISE
    run_serial_calibration(
        serial_calibration_arguments(converted, tmp_path / "points.json", noise_pos=NOISE, noise_rot=1e-4)
    )
    report = json.loads((tmp_path / "points.json").read_text())
    found = np.array(report["points"])  # in the tool frame, up to the tool placement's 1 mm / 1 mrad (the gauge)
    assert np.max(np.abs((found - found[0]) - (BODY.rotation @ offsets.T).T)) < 1e-3
    assert report["input"]["points"] == 3 and report["cross_validation"]["position_rms_m"] < 1e-4
