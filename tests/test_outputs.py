"""Outputs that can be trusted (issue 10): file pairs, collisions, special files, strict JSON, row errors.

Library-level tests of `m3t1r.io.outputs.OutputSet` and the pair loader, and CLI tests of the verbs that
use them.
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import shutil
import socket
import stat
import subprocess
import sys
import threading
from pathlib import Path, PurePosixPath

import numpy as np
import pytest
from conftest import process_holding_flock

from m3t1r.app.cli import main
from m3t1r.errors import ModelFileError, OutputPathError
from m3t1r.io import outputs as outputs_module
from m3t1r.io import progress as progress_module
from m3t1r.io.outputs import Output, OutputSet, atomic_write_bytes
from m3t1r.io.pairing import (
    closures_sha256,
    paired_closures_path,
    recorded_closures_sha256,
    sha256_bytes,
    with_closures_sha256,
)
from m3t1r.io.progress import Heartbeat, Progress, set_quiet
from m3t1r.io.strict_json import json_text
from m3t1r.io.temporaries import _LIVE_TEMPORARIES, folder_lock, sweep_locked, temporary_path
from m3t1r.model.description import Mechanism


def _strict_json(text: str) -> object:
    def refuse(token):
        raise ValueError(f"non-standard JSON constant {token}")

    return json.loads(text, parse_constant=refuse)


def _no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if ".m3t1r-" in p.name]


@pytest.fixture(scope="module")
def machines(tmp_path_factory):
    """A perturbed machine saved as a pair, and 20 measurements of it."""
    from m3t1r.app.datasets import write_measurements
    from m3t1r.calibration.measurements import TrackerNoise
    from m3t1r.calibration.simulation import simulate_study

    folder = tmp_path_factory.mktemp("machines")
    nominal = Mechanism.load()
    study = simulate_study(nominal, n_poses=20, n_holdout=0, seed=0, noise=TrackerNoise())
    study.truth.save(folder / "truth.urdf")
    write_measurements(folder / "m.csv", nominal, study.measurements)
    return folder


# ------------------------------------------------------------------------------------------------
# 1. File pairs
def test_pair_name_replaces_only_the_final_urdf():
    assert paired_closures_path("machine.v1.urdf") == Path("machine.v1.closures.yaml")
    assert paired_closures_path("machine.v2.urdf") == Path("machine.v2.closures.yaml")
    assert paired_closures_path("dir.x/robot.URDF") == Path("dir.x/robot.closures.yaml")
    assert paired_closures_path("robot") == Path("robot.closures.yaml")


def test_versions_of_a_machine_do_not_share_a_closures_file(tmp_path, machines):
    truth = Mechanism.load(machines / "truth.urdf")
    truth.save(tmp_path / "machine.v1.urdf")
    Mechanism.load().save(tmp_path / "machine.v2.urdf")  # writing v2 must not touch v1's closures
    v1 = Mechanism.load(tmp_path / "machine.v1.urdf")
    assert v1.closures_path == tmp_path / "machine.v1.closures.yaml"
    np.testing.assert_array_equal(v1.home, truth.home)
    assert not (tmp_path / "machine.closures.yaml").exists()


def test_cli_derives_v2_from_v1(tmp_path, machines, capsys):
    Mechanism.load(machines / "truth.urdf").save(tmp_path / "machine.v1.urdf")
    code = main(
        ["ik", str(_targets(tmp_path)), "--model", str(tmp_path / "machine.v1.urdf"), "-o", str(tmp_path / "s.csv")]
    )
    assert code == 0, capsys.readouterr().err


def test_a_urdf_with_another_machines_closures_is_refused_by_name(tmp_path, machines):
    Mechanism.load(machines / "truth.urdf").save(tmp_path / "a.urdf")
    Mechanism.load().save(tmp_path / "b.urdf")
    shutil.copy(tmp_path / "b.closures.yaml", tmp_path / "a.closures.yaml")
    with pytest.raises(ModelFileError, match=r"not the closures file of .*a\.urdf.*records closures sha256") as caught:
        Mechanism.load(tmp_path / "a.urdf")
    assert "home does not close" not in str(caught.value)
    with pytest.raises(ModelFileError, match="not the closures file"):
        Mechanism.load(tmp_path / "a.urdf", tmp_path / "b.closures.yaml")


def test_the_urdf_records_its_closures_sha256(tmp_path, machines):
    Mechanism.load(machines / "truth.urdf").save(tmp_path / "t.urdf")
    digest = closures_sha256((tmp_path / "t.closures.yaml").read_bytes())
    assert f"closures sha256 {digest}" in (tmp_path / "t.urdf").read_text()
    # Saved again from a paired URDF: one pairing comment, the new one.
    Mechanism.load(tmp_path / "t.urdf").save(tmp_path / "u.urdf")
    assert (tmp_path / "u.urdf").read_text().count("closures sha256") == 1


def test_staged_closures_of_an_interrupted_commit_load_and_are_completed_by_the_next_writer(tmp_path, machines):
    Mechanism.load().save(tmp_path / "c.urdf")
    old_closures = (tmp_path / "c.closures.yaml").read_bytes()
    truth = Mechanism.load(machines / "truth.urdf")
    urdf_bytes, closures_bytes = truth.pair_bytes(tmp_path / "c.urdf")
    # The state a SIGKILL between the two renames leaves (pid 2**22 + 1 is never alive).
    (tmp_path / "c.urdf").write_bytes(urdf_bytes)
    staged = tmp_path / f".c.closures.yaml.m3t1r-{2**22 + 1}-00aa.tmp"
    staged.write_bytes(closures_bytes)
    np.testing.assert_array_equal(Mechanism.load(tmp_path / "c.urdf").home, truth.home)
    assert (tmp_path / "c.closures.yaml").read_bytes() == old_closures
    with folder_lock(tmp_path):
        notes = sweep_locked(tmp_path)
    assert any("completed the interrupted write" in note for note in notes)
    assert (tmp_path / "c.closures.yaml").read_bytes() == closures_bytes and not staged.exists()


# ------------------------------------------------------------------------------------------------
# 2. Collisions and folders, before any work
def test_outputs_colliding_with_each_other_are_refused(tmp_path):
    outputs = OutputSet()
    outputs.add_machine(tmp_path / "c.urdf")
    outputs.add(tmp_path / "c.closures.yaml", "--report")
    with pytest.raises(OutputPathError, match="--report is the same file as closures file of -o"):
        outputs.check()
    outputs = OutputSet()
    outputs.add_machine(tmp_path / "c.urdf")
    outputs.add(tmp_path / "sub" / ".." / "c.urdf", "--report")
    (tmp_path / "sub").mkdir()
    with pytest.raises(OutputPathError, match="same file"):
        outputs.check()


def test_collisions_through_symlinks_and_hard_links(tmp_path):
    data = tmp_path / "in.csv"
    data.write_text("x\n1\n")
    os.link(data, tmp_path / "hard.csv")
    os.symlink(data, tmp_path / "soft.csv")
    for name in ("hard.csv", "soft.csv", "in.csv"):
        outputs = OutputSet(inputs=[data])
        outputs.add(tmp_path / name, "-o")
        with pytest.raises(OutputPathError, match="refusing to overwrite the input file"):
            outputs.check()
    (tmp_path / "a.txt").write_text("a")
    os.link(tmp_path / "a.txt", tmp_path / "b.txt")
    outputs = OutputSet()
    outputs.add(tmp_path / "a.txt", "-o")
    outputs.add(tmp_path / "b.txt", "--report")
    with pytest.raises(OutputPathError, match="same file"):
        outputs.check()


def test_missing_or_read_only_folders_are_refused_before_any_work(tmp_path):
    outputs = OutputSet()
    outputs.add(tmp_path / "nodir" / "r.json", "--report")
    with pytest.raises(OutputPathError, match="--report: folder .*nodir does not exist"):
        outputs.check()
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o555)
        outputs = OutputSet()
        outputs.add(locked / "r.json", "--report")
        with pytest.raises(OutputPathError, match="not writable"):
            outputs.check()


def test_cli_refuses_a_missing_output_folder_before_computing(tmp_path, capsys):
    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    assert main(["fk", str(sliders), "-o", str(tmp_path / "nodir" / "p.csv")]) == 2
    assert "folder" in capsys.readouterr().err


def test_calibrate_report_onto_its_own_urdf_or_closures_is_refused(tmp_path, machines, capsys):
    for report in ("c.urdf", "c.closures.yaml", "nodir/r.json"):
        code = main(
            [
                "calibrate",
                str(machines / "m.csv"),
                "-o",
                str(tmp_path / "c.urdf"),
                "--report",
                str(tmp_path / report),
                "--quiet",
            ]
        )
        assert code == 2, report
        assert not (tmp_path / "c.urdf").exists() and not (tmp_path / "c.closures.yaml").exists(), report
    capsys.readouterr()


def test_simulate_output_onto_its_truth_urdf_is_refused(tmp_path, capsys):
    x = tmp_path / "x"
    assert main(["simulate", "-n", "5", "-o", str(x), "--truth-urdf", str(x)]) == 2
    assert not x.exists()
    capsys.readouterr()


# ------------------------------------------------------------------------------------------------
# 3. A unit: temporary files removed on errors
def test_an_error_before_commit_removes_every_temporary_file(tmp_path):
    with pytest.raises(RuntimeError):
        with OutputSet() as outputs:
            first = outputs.add(tmp_path / "a.csv")
            outputs.add_machine(tmp_path / "m.urdf")
            outputs.check()
            outputs.stage(first, "x\n1\n")
            raise RuntimeError("computation failed")
    assert list(tmp_path.iterdir()) == []


def test_leftovers_of_killed_runs_are_removed_and_live_ones_kept(tmp_path):
    """A leftover is a temporary file nobody holds the lock of. A live writer's file names a pid
    that means nothing here (2**22 + 1: in another PID namespace, or on another host sharing the
    folder); it is kept because its lock is held, where the pid probe used to delete it."""
    dead = tmp_path / f".r.json.m3t1r-{os.getpid()}-0a.tmp"  # a reused pid: this very process
    live = tmp_path / f".r.json.m3t1r-{2**22 + 1}-0b.tmp"
    dead.write_text("{")
    live.write_text("{")
    writer = process_holding_flock(live)
    try:
        outputs = OutputSet(announce=None)
        outputs.add(tmp_path / "q.json")
        with outputs:
            outputs.check()
            assert not dead.exists() and live.exists()
        assert any("temporary file left by an interrupted run" in note for note in outputs.notes)
    finally:
        writer.kill()
        writer.wait()


_SECOND_WRITER = """
import sys
from m3t1r.errors import OutputPathError
from m3t1r.io.outputs import OutputSet
outputs = OutputSet(announce=None)
outputs.add(sys.argv[1] + "/r.json", "--report")
outputs.add_machine(sys.argv[1] + "/c.urdf")
try:
    outputs.check()
    print("passed")
except OutputPathError as exc:
    print(exc)
"""


def _second_writer(folder: Path) -> str:
    return subprocess.run(
        [sys.executable, "-c", _SECOND_WRITER, str(folder)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
        check=True,
    ).stdout.strip()


def test_a_second_writer_of_an_output_is_refused_before_any_work(tmp_path):
    """Two runs writing the same pair: the second is refused at its check, naming the folder and the
    first run, and the first run's pair lands whole, where both used to exit 0 leaving B's URDF
    with A's closures file."""
    first = OutputSet(announce=None)
    machine = first.add_machine(tmp_path / "c.urdf")
    first.check()
    message = _second_writer(tmp_path)
    assert message.startswith(
        f"{tmp_path / 'c.urdf'}: -o: another m3t1r run is writing this file in {tmp_path} "
        f"(pid {os.getpid()} on {socket.gethostname()}, started "
    )
    assert message.endswith("nothing was written: wait for it to finish, or write elsewhere")
    assert not (tmp_path / "r.json").exists() and len(list(tmp_path.iterdir())) == 2  # the first's claims
    with first:
        first.stage_machine(machine, Mechanism.load())
        first.commit()
    assert Mechanism.load(tmp_path / "c.urdf").model.nq == 20 and _no_temporaries(tmp_path)
    assert _second_writer(tmp_path) == "passed"  # once the first is done, the next may write


def test_a_command_that_failed_before_its_commit_does_not_block_the_next_in_the_same_process(tmp_path):
    failed = OutputSet(announce=None)
    failed.add(tmp_path / "r.json")
    failed.check()  # ... and its command stops here, without discarding
    outputs = OutputSet(announce=None)
    report = outputs.add(tmp_path / "r.json")
    with outputs:
        outputs.check()
        outputs.stage(report, "{}")
        outputs.commit()
    assert (tmp_path / "r.json").read_text() == "{}" and _no_temporaries(tmp_path)


def test_a_writer_in_another_process_is_refused_while_it_stages(tmp_path):
    target = tmp_path / "p.csv"
    script = (
        "import sys, time\nfrom m3t1r.io.outputs import OutputSet\n"
        "outputs = OutputSet(); outputs.add(sys.argv[1]); outputs.check(); print('claimed', flush=True); "
        "time.sleep(60)"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", script, str(target)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    try:
        assert child.stdout.readline().strip() == "claimed"
        outputs = OutputSet(announce=None)
        outputs.add(target, "-o")
        with pytest.raises(
            OutputPathError, match=f"another m3t1r run is writing this file in {tmp_path} \\(pid {child.pid} on "
        ):
            outputs.check()
    finally:
        child.kill()
        child.wait()
    outputs.check()  # its writer killed: the claim is a leftover, swept
    assert [note.startswith("removed ") for note in outputs.notes] == [True]
    outputs.discard()


def test_a_failed_rename_puts_back_the_outputs_already_renamed(tmp_path):
    """The report is renamed before the pair; when the URDF's rename then fails, the report is put
    back as it was: a failing commit leaves every old file, not a new report beside an old pair."""
    (tmp_path / "r.json").write_text("old report")
    outputs = OutputSet(announce=None)
    report = outputs.add(tmp_path / "r.json", "--report")
    machine = outputs.add_machine(tmp_path / "c.urdf")
    with outputs:
        outputs.check()
        outputs.stage(report, "new report")
        outputs.stage_machine(machine, Mechanism.load())
        (tmp_path / "c.urdf").mkdir()  # appears between check and commit
        (tmp_path / "c.urdf" / "inside").write_text("")
        with pytest.raises(
            OutputPathError,
            match="could not move the new file into place: Is a directory; "
            "the 1 output\\(s\\) renamed before it were put back",
        ):
            outputs.commit()
    assert (tmp_path / "r.json").read_text() == "old report" and not (tmp_path / "c.closures.yaml").exists()
    assert _no_temporaries(tmp_path)


def test_outputs_named_up_to_the_name_limit_are_written(tmp_path, capsys):
    """Output names of 230 to 255 bytes, legal on the file system, where the temporary name (the
    output's name plus 30 characters) used to fail with 'File name too long'."""
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    for length in (230, limit):
        poses = tmp_path / ("p" * (length - 4) + ".csv")
        assert main(["fk", str(sliders), "-o", str(poses)]) == 0
        assert "x,y,z,qx,qy,qz,qw" in poses.read_text() and _no_temporaries(tmp_path)
    urdf = tmp_path / ("m" * (limit - len(".closures.yaml")) + ".urdf")  # its closures file: 255 bytes
    Mechanism.load().save(urdf)
    assert Mechanism.load(urdf).model.nq == 20
    capsys.readouterr()


def test_a_long_named_pair_interrupted_between_its_renames_loads_and_is_completed(tmp_path, machines):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    urdf = tmp_path / ("m" * (limit - len(".closures.yaml")) + ".urdf")
    Mechanism.load().save(urdf)
    truth = Mechanism.load(machines / "truth.urdf")
    urdf_bytes, closures_bytes = truth.pair_bytes(urdf)
    urdf.write_bytes(urdf_bytes)  # the state a SIGKILL between the two renames leaves
    staged = temporary_path(paired_closures_path(urdf))
    assert len(os.fsencode(staged.name)) <= limit
    staged.write_bytes(closures_bytes)
    np.testing.assert_array_equal(Mechanism.load(urdf).home, truth.home)
    with folder_lock(tmp_path):
        assert any("completed the interrupted write" in note for note in sweep_locked(tmp_path))
    assert paired_closures_path(urdf).read_bytes() == closures_bytes and not staged.exists()


# ------------------------------------------------------------------------------------------------
# 4. Special files
def test_dash_writes_to_stdout(tmp_path, capfd):
    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    assert main(["fk", str(sliders), "-o", "-"]) == 0
    out, err = capfd.readouterr()
    assert "x,y,z,qx,qy,qz,qw" in out.splitlines() and "wrote 1 poses" in err
    assert not (tmp_path / "-").exists()


def test_a_named_pipe_is_written_through_not_replaced(tmp_path, capsys):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()))
    reader.start()
    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    assert main(["fk", str(sliders), "-o", str(fifo)]) == 0
    reader.join(timeout=30)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert b"x,y,z,qx,qy,qz,qw" in received[0]
    assert _no_temporaries(tmp_path)


def test_a_device_is_written_through_not_replaced(tmp_path, capsys):
    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    before = os.stat("/dev/null")
    assert main(["fk", str(sliders), "-o", "/dev/null"]) == 0
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and (after.st_ino, after.st_rdev) == (before.st_ino, before.st_rdev)


def test_a_machine_cannot_go_to_a_stream(tmp_path):
    with pytest.raises(OutputPathError, match="standard output"):
        OutputSet().add_machine("-")
    fifo = tmp_path / "pipe.urdf"
    os.mkfifo(fifo)
    outputs = OutputSet()
    outputs.add_machine(fifo)
    with pytest.raises(OutputPathError, match="pair of regular files"):
        outputs.check()


# ------------------------------------------------------------------------------------------------
# 5. Strict JSON
def test_json_text_is_strict():
    document = {"a": math.nan, "b": [np.float64(np.inf), np.float32(1.5), np.int64(3)], "c": np.array([1.0, np.nan])}
    assert _strict_json(json_text(document)) == {"a": None, "b": [None, 1.5, 3], "c": [1.0, None]}


def test_position_only_calibration_report_is_strict_json(tmp_path, capsys):
    meas = tmp_path / "m.csv"
    assert main(["simulate", "-n", "20", "--position-only", "-o", str(meas)]) == 0
    assert (
        main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--report", str(tmp_path / "r.json"), "--quiet"])
        == 0
    )
    _strict_json((tmp_path / "r.json").read_text())
    capsys.readouterr()


# ------------------------------------------------------------------------------------------------
# 6. Errors name the place; rows that fail do not stop the rest
def test_huge_values_are_refused_with_line_and_column(tmp_path, machines, capsys):
    lines = (machines / "m.csv").read_text().splitlines()
    header = [n for n, line in enumerate(lines) if line.startswith("q11,")][0]
    column = lines[header].split(",").index("x")
    fields = lines[header + 3].split(",")
    fields[column] = "1e300"
    lines[header + 3] = ",".join(fields)
    meas = tmp_path / "m.csv"
    meas.write_text("\n".join(lines) + "\n")
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"line {header + 4}, column 'x'" in err and "implausibly large" in err


def test_swapped_position_columns_are_named(tmp_path, machines, capsys):
    text = (machines / "m.csv").read_text().replace(",x,y,z,", ",y,x,z,")
    (tmp_path / "m.csv").write_text(text)
    assert main(["calibrate", str(tmp_path / "m.csv"), "-o", str(tmp_path / "c.urdf"), "--quiet"]) == 1
    assert "hold y, x, z in that order" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


def test_calibrate_names_every_line_whose_sliders_do_not_assemble(tmp_path, machines, capsys):
    """Two rows whose sliders are within their limits but close no loop (the five-bars cannot
    reach): refused before any fit, each by its file line, nothing written."""
    lines = (machines / "m.csv").read_text().splitlines()
    data = [k for k, line in enumerate(lines) if line[:1].isdigit() or line[:1] == "-"]
    for k in (data[3], data[11]):
        values = lines[k].split(",")
        values[:2] = ["-0.3", "0.3"]
        lines[k] = ",".join(values)
    (tmp_path / "m.csv").write_text("\n".join(lines) + "\n")
    assert main(["calibrate", str(tmp_path / "m.csv"), "-o", str(tmp_path / "c.urdf"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "2 row(s) failed, nothing written" in err
    for k in (data[3], data[11]):
        assert f"m.csv, line {k + 1}: the slider readings do not assemble on the nominal machine" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


def test_compensate_refuses_a_hinge_beyond_its_limit_by_row(tmp_path, machines, capsys):
    targets = tmp_path / "t.csv"
    # Yaw just past pi/2: the platform hinges q14, q24 (limits +-pi/2) would pass their stops.
    targets.write_text("x,y,z,theta\n0.5,0.5,-0.1,0.0\n0.5,0.5,-0.1,1.6\n")
    out = tmp_path / "c.csv"
    code = main(["compensate", str(targets), "--calibrated", str(machines / "truth.urdf"), "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and not out.exists()
    assert "t.csv, line 3" in err and "beyond its limit" in err and "line 2" not in err
    code = main(
        ["compensate", str(targets), "--unordered", "--calibrated", str(machines / "truth.urdf"), "-o", str(out)]
    )
    err = capsys.readouterr().err
    assert code == 1 and not out.exists()
    assert "t.csv, line 3" in err and "beyond its limit" in err and "line 2" not in err


def test_compensate_unordered_targets_gives_the_path_commands(tmp_path, machines, capsys):
    """--unordered solves every target from home in one batch: the same commands as the path
    (warm-started) solve to 1e-9 m, for targets in no particular order."""
    rng = np.random.default_rng(5)
    rows = np.column_stack(
        (
            rng.uniform(0.3, 0.7, 12),
            rng.uniform(0.3, 0.7, 12),
            rng.uniform(-0.15, -0.05, 12),
            rng.uniform(-0.4, 0.4, 12),
        )
    )
    targets = tmp_path / "t.csv"
    targets.write_text("x,y,z,theta\n" + "\n".join(",".join(f"{v:.6f}" for v in row) for row in rows) + "\n")
    outputs = []
    for extra in ([], ["--unordered"]):
        out = tmp_path / f"c{len(extra)}.csv"
        assert (
            main(
                [
                    "compensate",
                    str(targets),
                    *extra,
                    "--output-kind",
                    "actuators",
                    "--calibrated",
                    str(machines / "truth.urdf"),
                    "-o",
                    str(out),
                ]
            )
            == 0
        )
        data = [line for line in out.read_text().splitlines() if not line.startswith("#")]
        assert data[0] == "q11,q11_B2,q21,q21_B4"
        outputs.append(np.array([[float(v) for v in line.split(",")] for line in data[1:]]))
    assert outputs[0].shape == (12, 4)
    np.testing.assert_allclose(outputs[1], outputs[0], atol=1e-9)


def test_evaluate_reports_a_failing_pose_and_goes_on(tmp_path, machines, capsys, monkeypatch):
    from m3t1r.errors import NotConvergedError
    from m3t1r.model import kinematics

    real = kinematics.ClosedLoopSolver.forward
    calls = {"n": 0}

    def flaky(self, sliders, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:
            raise NotConvergedError("does not assemble", 1.0, 50)
        return real(self, sliders, *args, **kwargs)

    monkeypatch.setattr(kinematics.ClosedLoopSolver, "forward", flaky)
    truth = str(machines / "truth.urdf")
    assert main(["evaluate", "--truth", truth, "--calibrated", truth, "-n", "10"]) == 0
    out, err = capsys.readouterr()
    assert "over 9 actuator sets" in out and "1 skipped" in out
    assert "actuator set 1" in err and "does not assemble" in err


# ------------------------------------------------------------------------------------------------
# 7. Progress
def test_progress_lines_and_quiet(tmp_path):
    import io

    stream = io.StringIO()
    with Progress("calibrating", total=4, stream=stream, delay=0.0, interval=0.0) as progress:
        for _ in range(4):
            progress.advance()
    assert "calibrating: 4/4" in stream.getvalue()
    set_quiet(True)
    try:
        quiet = io.StringIO()
        with Progress("calibrating", total=4, stream=quiet, delay=0.0, interval=0.0) as progress:
            progress.advance()
        assert quiet.getvalue() == ""
    finally:
        set_quiet(False)


def test_a_heartbeat_shows_a_step_without_a_count_while_it_runs(tmp_path):
    """A long step that reports no count (a plan's selection, a batch solve) shows its elapsed time
    from a background thread while the step runs, where such a step used to show nothing at all."""
    import io
    import time

    stream = io.StringIO()
    with Heartbeat("planning", "choosing 60 poses", stream=stream, delay=0.0, interval=0.05):
        time.sleep(0.5)
        during = stream.getvalue()
    assert during.startswith("planning: working (0 s) choosing 60 poses\n")
    set_quiet(True)
    try:
        quiet = io.StringIO()
        with Heartbeat("planning", stream=quiet, delay=0.0, interval=0.05):
            time.sleep(0.2)
        assert quiet.getvalue() == ""
    finally:
        set_quiet(False)


def test_quiet_is_accepted_before_and_after_the_verb(tmp_path, capsys):
    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    assert main(["--quiet", "fk", str(sliders), "-o", str(tmp_path / "a.csv")]) == 0
    assert main(["fk", str(sliders), "-o", str(tmp_path / "b.csv"), "--quiet"]) == 0


def _targets(folder: Path) -> Path:
    path = folder / "targets.csv"
    path.write_text("x,y,z,theta\n0.5,0.5,-0.1,0.0\n")
    return path


# ==================================================================================================
# OutputSet: every refusal, special files, staging and failed renames
#
# The exact error of every refusal (path and message), each special-file kind, what `OutputSet` records
# (kind, temporaries, notes, committed), lookups by path, staging through a file name, and the failures of
# a write-through and of a rename. Root writes anywhere, so a folder without write or search permission is
# simulated through `os.access`.
# ==================================================================================================


DEAD_PID = 2**22 + 1  # above any pid_max: never a live process


def _refusal(outputs: OutputSet) -> OutputPathError:
    with pytest.raises(OutputPathError) as caught:
        outputs.check()
    return caught.value


def _leftover(folder: Path, name: str) -> Path:
    path = folder / f".{name}.m3t1r-{DEAD_PID}-0a.tmp"
    path.write_text("old")
    return path


# -- Output ------------------------------------------------------------------------------------


def test_a_new_output_is_a_file_or_stdout_with_nothing_staged(tmp_path):
    output = Output(tmp_path / "a.csv", "--out")
    assert (output.kind, output.temporary, output.data, output.closures, output.pair_of) == (
        "file",
        None,
        None,
        None,
        None,
    )
    assert output.path == tmp_path / "a.csv" and output.label == "--out"
    stdout = Output("-", "--report")
    assert (stdout.kind, stdout.path, stdout.temporary, stdout.data, stdout.name) == (
        "stdout",
        None,
        None,
        None,
        "standard output",
    )


# -- declaring and looking up ---------------------------------------------------------------------


def test_a_new_set_is_not_committed_and_drops_stdout_and_none_inputs(tmp_path):
    outputs = OutputSet(inputs=["-", None, tmp_path / "in.csv"])
    assert outputs.committed is False
    assert outputs.inputs == [tmp_path / "in.csv"]
    outputs.add_input(None)
    outputs.add_input("-")
    outputs.add_input(str(tmp_path / "more.csv"))
    assert outputs.inputs == [tmp_path / "in.csv", tmp_path / "more.csv"]


def test_an_added_input_is_protected(tmp_path):
    data = tmp_path / "in.csv"
    data.write_text("x\n1\n")
    outputs = OutputSet(announce=None)
    outputs.add_input(data)
    outputs.add(data, "-o")
    error = _refusal(outputs)
    assert (error.path, str(error)) == (str(data), f"{data}: -o: refusing to overwrite the input file {data}")


def test_an_input_not_yet_existing_is_protected_by_its_path(tmp_path):
    future = tmp_path / "future.csv"
    outputs = OutputSet(inputs=[future], announce=None)
    outputs.add(future, "-o")
    assert "refusing to overwrite the input file" in str(_refusal(outputs))


def test_default_label_is_output(tmp_path):
    outputs = OutputSet()
    output = outputs.add(tmp_path)
    assert output.label == "output"
    assert str(_refusal(outputs)) == f"{tmp_path}: output is a directory, expected a file path"


def test_add_machine_labels_and_explicit_closures(tmp_path):
    outputs = OutputSet()
    machine = outputs.add_machine(tmp_path / "m.urdf", closures=tmp_path / "other.yaml")
    assert machine.label == "-o" and machine.closures.path == tmp_path / "other.yaml"
    assert machine.closures.label == "closures file of -o" and machine.closures.pair_of is machine
    with pytest.raises(OutputPathError) as caught:
        outputs.add_machine("-", "--machine")
    assert caught.value.path == "-"
    assert str(caught.value) == (
        "-: --machine: a machine is a URDF and its closures file; it cannot be written to standard output"
    )


def test_output_finds_each_declared_output_by_its_path(tmp_path):
    outputs = OutputSet()
    stdout = outputs.add("-", "--report")
    a = outputs.add(tmp_path / "a.csv", "-a")
    b = outputs.add(str(tmp_path / "b.csv"), "-b")
    assert outputs.output("-") is stdout
    assert outputs.output(tmp_path / "a.csv") is a
    assert outputs.output(str(tmp_path / "b.csv")) is b
    with pytest.raises(KeyError, match=f"{tmp_path / 'c.csv'} is not a declared output"):
        outputs.output(tmp_path / "c.csv")
    files_first = OutputSet()
    a = files_first.add(tmp_path / "a.csv")
    stdout = files_first.add("-")
    assert files_first.output("-") is stdout and files_first.output(tmp_path / "a.csv") is a


# -- check -------------------------------------------------------------------------------------------


def test_two_stdout_outputs_are_refused(tmp_path):
    outputs = OutputSet()
    outputs.add("-", "-o")
    outputs.add("-", "--report")
    error = _refusal(outputs)
    assert (error.path, str(error)) == ("-", "-: --report and -o both write to standard output")


def test_an_output_after_stdout_is_still_checked(tmp_path):
    data = tmp_path / "in.csv"
    data.write_text("x\n1\n")
    outputs = OutputSet(inputs=[data])
    outputs.add("-", "--report")
    outputs.add(data, "-o")
    assert "-o: refusing to overwrite the input file" in str(_refusal(outputs))


def test_same_file_refusal_names_both(tmp_path):
    outputs = OutputSet()
    outputs.add(tmp_path / "a.csv", "-o")
    outputs.add(tmp_path / "a.csv", "--report")
    error = _refusal(outputs)
    assert error.path == str(tmp_path / "a.csv")
    assert str(error) == (
        f"{tmp_path / 'a.csv'}: --report is the same file as -o ({tmp_path / 'a.csv'}): "
        "every output must be a different file"
    )


def test_a_new_file_is_classified_as_a_file(tmp_path):
    outputs = OutputSet()
    output = outputs.add(tmp_path / "new.csv")
    outputs.check()
    assert output.kind == "file"


def test_folder_that_is_a_file_is_refused(tmp_path):
    plain = tmp_path / "plain"
    plain.write_text("")
    outputs = OutputSet()
    outputs.add(plain / "r.json", "--report")
    error = _refusal(outputs)
    assert error.path == str(plain / "r.json")
    assert str(error) == f"{plain / 'r.json'}: --report: cannot inspect: Not a directory"
    missing = tmp_path / "missing" / "r.json"
    outputs = OutputSet()
    outputs.add(missing, "--report")
    error = _refusal(outputs)
    assert (error.path, str(error)) == (str(missing), f"{missing}: --report: folder {missing.parent} does not exist")


def test_check_folder_tells_a_file_from_a_missing_folder(tmp_path):
    # Through `check`, a file as folder already fails in `_classify` (ENOTDIR); `_check_folder`
    # still names it, for a folder replaced by a file in between.
    plain = tmp_path / "plain"
    plain.write_text("")
    output = Output(plain / "r.json", "--report")
    with pytest.raises(OutputPathError) as caught:
        outputs_module._check_folder(output, plain)
    assert (caught.value.path, str(caught.value)) == (
        str(plain / "r.json"),
        f"{plain / 'r.json'}: --report: folder {plain} is not a folder",
    )


@pytest.mark.parametrize("denied", [os.W_OK, os.X_OK])
def test_a_folder_without_write_or_search_permission_is_refused(tmp_path, monkeypatch, denied):
    real_access = os.access
    monkeypatch.setattr(
        outputs_module.os, "access", lambda path, mode: False if mode & denied else real_access(path, mode)
    )
    outputs = OutputSet()
    outputs.add(tmp_path / "r.json", "--report")
    error = _refusal(outputs)
    assert (error.path, str(error)) == (
        str(tmp_path / "r.json"),
        f"{tmp_path / 'r.json'}: --report: folder {tmp_path} is not writable",
    )


def test_check_sweeps_every_folder_and_announces(tmp_path):
    first, second = tmp_path / "one", tmp_path / "two"
    first.mkdir()
    second.mkdir()
    leftovers = [_leftover(first, "a.csv"), _leftover(second, "b.csv")]
    announced: list[str] = []
    outputs = OutputSet(announce=announced.append)
    outputs.add(first / "a.csv")
    outputs.add(second / "b.csv")
    outputs.check()
    assert len(outputs.notes) == 2 and announced == outputs.notes
    assert all(str(path) in note for path, note in zip(leftovers, outputs.notes))
    assert not any(path.exists() for path in leftovers)


def test_default_announce_prints_to_stderr(tmp_path, capsys):
    leftover = _leftover(tmp_path, "a.csv")
    outputs = OutputSet()
    outputs.add(tmp_path / "a.csv")
    outputs.check()
    assert capsys.readouterr().err == f"m3t1r: removed {leftover}, a temporary file left by an interrupted run\n"


def test_atomic_write_bytes_sweeps_silently(tmp_path, capsys):
    leftover = _leftover(tmp_path, "a.csv")
    atomic_write_bytes(tmp_path / "a.csv", b"new")
    assert (tmp_path / "a.csv").read_bytes() == b"new" and not leftover.exists()
    assert capsys.readouterr().err == ""


# -- special files -----------------------------------------------------------------------------------


def test_streams_are_special(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    outputs = OutputSet()
    device = outputs.add("/dev/null", "--report")
    pipe = outputs.add(fifo, "-o")
    outputs.check()
    assert (device.kind, pipe.kind) == ("special", "special")


def test_a_machine_on_a_pipe_or_a_device_is_refused_by_kind(tmp_path):
    fifo = tmp_path / "pipe.urdf"
    os.mkfifo(fifo)
    outputs = OutputSet()
    outputs.add_machine(fifo)
    error = _refusal(outputs)
    assert (error.path, str(error)) == (str(fifo), f"{fifo}: -o is a named pipe; a machine is a pair of regular files")
    outputs = OutputSet()
    outputs.add_machine("/dev/null", "--machine")
    assert str(_refusal(outputs)) == "/dev/null: --machine is a device; a machine is a pair of regular files"
    closures_fifo = tmp_path / "c.yaml"
    os.mkfifo(closures_fifo)
    outputs = OutputSet()
    outputs.add_machine(tmp_path / "m.urdf", closures=closures_fifo)
    assert str(_refusal(outputs)) == (
        f"{closures_fifo}: closures file of -o is a named pipe; a machine is a pair of regular files"
    )


def test_a_socket_is_refused(tmp_path):
    path = tmp_path / "s"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        server.bind(str(path))
        outputs = OutputSet()
        outputs.add(path, "--report")
        error = _refusal(outputs)
    finally:
        server.close()
    assert (error.path, str(error)) == (str(path), f"{path}: --report is a socket; refusing to write to it")


def test_a_block_device_is_refused(tmp_path):
    path = tmp_path / "blk"
    try:
        os.mknod(path, stat.S_IFBLK | 0o600, os.makedev(7, 0))
    except (PermissionError, OSError):
        pytest.skip("cannot create a block device node here")
    outputs = OutputSet()
    outputs.add(path, "--report")
    error = _refusal(outputs)
    assert (error.path, str(error)) == (str(path), f"{path}: --report is a block device; refusing to write to it")


def test_a_full_device_reports_the_write_failure():
    outputs = OutputSet()
    outputs.add("/dev/full", "--report")
    outputs.check()
    outputs.stage("/dev/full", b"x" * 100_000)
    with pytest.raises(OutputPathError) as caught:
        outputs.commit()
    assert (caught.value.path, str(caught.value)) == (
        "/dev/full",
        "/dev/full: --report: write failed: No space left on device",
    )


class _FailingStdout:
    def __init__(self, error: BaseException) -> None:
        self.buffer = self
        self.error = error

    def write(self, data):
        raise self.error

    def flush(self):
        pass


@pytest.mark.parametrize(
    ("error", "message"),
    [
        (BrokenPipeError(errno.EPIPE, "Broken pipe"), "--report: the reader closed the pipe"),
        (OSError(errno.EIO, "Input/output error"), "--report: write failed: Input/output error"),
    ],
)
def test_stdout_write_failures_name_standard_output(monkeypatch, error, message):
    monkeypatch.setattr(outputs_module.sys, "stdout", _FailingStdout(error))
    outputs = OutputSet()
    outputs.add("-", "--report")
    outputs.check()
    outputs.stage("-", "text")
    with pytest.raises(OutputPathError) as caught:
        outputs.commit()
    assert (caught.value.path, str(caught.value)) == ("standard output", f"standard output: {message}")


def test_stdout_gets_the_staged_bytes(monkeypatch):
    stream = io.BytesIO()
    monkeypatch.setattr(outputs_module.sys, "stdout", type("S", (), {"buffer": stream})())
    outputs = OutputSet()
    outputs.add("-")
    outputs.check()
    outputs.stage_json("-", {"a": float("nan")})
    assert outputs.commit() == ["standard output"]
    assert stream.getvalue() == b'{\n  "a": null\n}\n'


# -- staging, committing, discarding -------------------------------------------------------------------


def test_staged_json_is_the_document(tmp_path):
    outputs = OutputSet()
    outputs.add(tmp_path / "r.json")
    outputs.check()
    outputs.stage_json(tmp_path / "r.json", {"x": [1, 2]})
    outputs.stage_json(None, {"ignored": True})
    outputs.commit()
    assert (tmp_path / "r.json").read_text() == '{\n  "x": [\n    1,\n    2\n  ]\n}\n'


class _FakeMechanism:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def pair_bytes(self, urdf, closures):
        self.calls.append((urdf, closures))
        return b"<robot/>", b"closures"


def test_stage_machine_passes_both_paths(tmp_path):
    outputs = OutputSet()
    machine = outputs.add_machine(tmp_path / "m.urdf", closures=tmp_path / "c.yaml")
    plain = outputs.add(tmp_path / "r.json", "--report")
    outputs.check()
    mechanism = _FakeMechanism()
    outputs.stage_machine(machine, mechanism)
    assert mechanism.calls == [(tmp_path / "m.urdf", tmp_path / "c.yaml")]
    with pytest.raises(ValueError, match=f"^{tmp_path / 'r.json'} was not declared with add_machine$"):
        outputs.stage_machine(plain, mechanism)
    outputs.stage(plain, "{}")
    outputs.commit()
    assert (tmp_path / "c.yaml").read_bytes() == b"closures" and (tmp_path / "m.urdf").read_bytes() == b"<robot/>"


def test_discard_forgets_every_temporary(tmp_path):
    outputs = OutputSet()
    output = outputs.add(tmp_path / "a.csv")
    outputs.check()
    outputs.stage(output, "a")
    temporary = output.temporary
    assert temporary in _LIVE_TEMPORARIES
    outputs.discard()
    assert output.temporary is None and not temporary.exists() and temporary not in _LIVE_TEMPORARIES
    with pytest.raises(ValueError, match=f"^outputs declared but never staged: {tmp_path / 'a.csv'}$"):
        outputs.commit()


def test_commit_lists_every_output_never_staged(tmp_path):
    outputs = OutputSet()
    outputs.add(tmp_path / "a.csv")
    outputs.add(tmp_path / "b.csv")
    outputs.add("-")
    outputs.check()
    with pytest.raises(
        ValueError,
        match=(f"^outputs declared but never staged: {tmp_path / 'a.csv'}, {tmp_path / 'b.csv'}, standard output$"),
    ):
        outputs.commit()


def test_a_staged_file_deleted_before_commit_counts_as_never_staged(tmp_path):
    outputs = OutputSet()
    output = outputs.add(tmp_path / "a.csv")
    outputs.check()
    outputs.stage(output, "a")
    output.temporary.unlink()
    with pytest.raises(ValueError, match="never staged"):
        outputs.commit()
    assert not (tmp_path / "a.csv").exists()


def test_commit_renames_records_and_fsyncs_each_folder_once(tmp_path, monkeypatch):
    synced: list[Path] = []
    monkeypatch.setattr(outputs_module, "_fsync_directory", synced.append)
    sub = tmp_path / "sub"
    sub.mkdir()
    outputs = OutputSet()
    a = outputs.add(tmp_path / "a.csv")
    b = outputs.add(tmp_path / "b.csv")
    c = outputs.add(sub / "c.csv")
    outputs.check()
    for output in (a, b, c):
        outputs.stage(output, output.path.name)
    temporaries = [a.temporary, b.temporary, c.temporary]
    assert outputs.commit() == [str(a.path), str(b.path), str(c.path)]
    assert outputs.committed is True
    assert synced == [tmp_path, sub]
    assert (a.temporary, b.temporary, c.temporary) == (None, None, None)
    assert not any(t in _LIVE_TEMPORARIES for t in temporaries)
    assert (sub / "c.csv").read_text() == "c.csv"


def test_a_failed_rename_names_the_output_and_the_cause(tmp_path):
    target = tmp_path / "a.csv"
    outputs = OutputSet()
    outputs.add(target, "-o")
    outputs.check()
    outputs.stage(target, "a")
    target.mkdir()  # appears between check and commit
    (target / "inside").write_text("")
    with pytest.raises(OutputPathError) as caught:
        outputs.commit()
    assert caught.value.path == str(target)
    assert str(caught.value) == f"{target}: -o: could not move the new file into place: Is a directory"
    assert [p.name for p in tmp_path.iterdir()] == ["a.csv"]


@pytest.mark.parametrize("loop", [False, True])
def test_a_dangling_or_looping_symlink_is_replaced_not_followed(tmp_path, loop):
    link = tmp_path / "out.csv"
    target = link if loop else tmp_path / "nowhere.csv"
    link.symlink_to(target)
    outputs = OutputSet()
    output = outputs.add(link)
    outputs.check()
    assert output.kind == "file"
    outputs.stage(output, "new")
    outputs.commit()
    assert not link.is_symlink() and link.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]


# ==================================================================================================
# Pair names, recorded digests and the pairing comment
#
# Pair names at the edge of the `.urdf` suffix, two recorded digests, and the exact pairing comment with and
# without an XML declaration.
# ==================================================================================================


A = "a" * 64
B = "b" * 64
COMMENT = (
    b"<!-- m3t1r pair: closures sha256 "
    + A.encode()
    + b" (this URDF loads only with the closures file of that content; models/README.md) -->\n"
)


@pytest.mark.parametrize(
    ("urdf", "closures"),
    [
        ("m.urdf", "m.closures.yaml"),
        ("dir/M.URDF", "dir/M.closures.yaml"),
        (".urdf", ".urdf.closures.yaml"),  # nothing before the suffix: not a suffix
        ("machine.xml", "machine.xml.closures.yaml"),
        ("urdf", "urdf.closures.yaml"),
    ],
)
def test_pair_names(urdf, closures):
    assert paired_closures_path(urdf) == Path(closures)


def test_two_different_recorded_digests_are_refused():
    urdf = with_closures_sha256(b"<robot/>", A) + b"<!-- m3t1r pair: closures sha256 " + B.encode() + b" -->\n"
    with pytest.raises(ModelFileError) as caught:
        recorded_closures_sha256(urdf)
    assert caught.value.path == "URDF"
    assert str(caught.value) == "URDF: records two different closures sha256 digests"
    assert recorded_closures_sha256(with_closures_sha256(b"<robot/>", A) + COMMENT) == A


def test_comment_without_a_declaration_goes_first():
    assert with_closures_sha256(b"<robot/>\n", A) == COMMENT + b"<robot/>\n"


def test_comment_after_a_declaration_with_and_without_its_newline():
    assert (
        with_closures_sha256(b'<?xml version="1.0"?>\n<robot/>', A)
        == b'<?xml version="1.0"?>\n' + COMMENT + b"<robot/>"
    )
    assert with_closures_sha256(b'<?xml version="1.0"?><robot/>', A) == (
        b'<?xml version="1.0"?>\n' + COMMENT + b"<robot/>"
    )


def test_comment_is_replaced_and_removed():
    paired = with_closures_sha256(b"<robot/>", A)
    assert with_closures_sha256(paired, B) == COMMENT.replace(A.encode(), B.encode()) + b"<robot/>"
    assert with_closures_sha256(paired, None) == b"<robot/>"
    assert recorded_closures_sha256(b"<robot/>") is None


@pytest.mark.parametrize("digest", ["A" * 64, "a" * 63, sha256_bytes(b"x")[:-1] + "g"])
def test_a_digest_must_be_64_lowercase_hex(digest):
    with pytest.raises(ValueError, match=rf"^not a sha256 hex digest: '{digest}'$"):
        with_closures_sha256(b"<robot/>", digest)


# ==================================================================================================
# Strict JSON text: indent, final newline, booleans and paths
# ==================================================================================================


def test_exact_text_with_two_space_indent_and_a_final_newline():
    document = {"a": [1, 2.5], "b": {"c": None}}
    assert json_text(document) == '{\n  "a": [\n    1,\n    2.5\n  ],\n  "b": {\n    "c": null\n  }\n}\n'


def test_booleans_stay_booleans():
    text = json_text({"t": True, "f": False, "np_t": np.True_, "np_f": np.False_, "array": np.array([True, False])})
    assert json.loads(text) == {"t": True, "f": False, "np_t": True, "np_f": False, "array": [True, False]}
    assert '"t": true' in text and '"np_t": true' in text


def test_paths_become_their_string():
    assert json.loads(json_text({"file": Path("/tmp/a.csv"), "pure": PurePosixPath("b/c.urdf")})) == {
        "file": "/tmp/a.csv",
        "pure": "b/c.urdf",
    }


def test_non_finite_values_everywhere_become_null():
    document = {"x": float("nan"), 1: [np.float32("inf"), (-np.inf, 2)], "m": np.array([[np.nan, 1.0]])}
    assert json.loads(json_text(document)) == {"x": None, "1": [None, [None, 2]], "m": [[None, 1.0]]}


# ==================================================================================================
# Progress lines: terminal and plain output, delay, rate limit and failing streams
#
# The exact lines on a terminal and elsewhere, the delay and the rate limit at their boundaries (a fake
# clock), the bar, the estimate, notes, `close`, and streams without `isatty` or that fail.
# ==================================================================================================


class Clock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Stream:
    def __init__(self, tty: bool) -> None:
        self.tty = tty
        self.writes: list[str] = []
        self.flushes = 0

    def isatty(self) -> bool:
        return self.tty

    def write(self, text: str) -> None:
        self.writes.append(text)

    def flush(self) -> None:
        self.flushes += 1


@pytest.fixture()
def clock(monkeypatch) -> Clock:
    fake = Clock()
    monkeypatch.setattr(progress_module.time, "monotonic", fake)
    set_quiet(False)
    yield fake
    set_quiet(False)


def _at(clock: Clock, progress: Progress, t: float, done: int, note: str | None = None) -> None:
    clock.now = 100.0 + t
    progress.update(done, note)


def test_plain_lines_after_the_delay_and_every_5_s(clock):
    stream = Stream(tty=False)
    progress = Progress("fit", total=10, stream=stream)
    _at(clock, progress, 1.999, 1)
    assert stream.writes == []
    _at(clock, progress, 2.0, 1, note="cost 3")  # exactly the delay: shown
    assert stream.writes == ["fit: 1/10 (2 s, about 18 s left) cost 3\n"] and stream.flushes == 1
    _at(clock, progress, 2.1, 2)
    _at(clock, progress, 6.999, 2)
    assert len(stream.writes) == 1
    _at(clock, progress, 7.0, 2)  # exactly the interval after the last line
    assert stream.writes[-1] == "fit: 2/10 (7 s, about 28 s left) cost 3\n"
    clock.now = 109.0
    progress.advance(8)
    progress.close()
    assert stream.writes[-1] == "fit: 10/10 (9 s) cost 3\n"


def test_terminal_bar_every_tenth_of_a_second_and_a_final_newline(clock):
    stream = Stream(tty=True)
    progress = Progress("fit", total=4, stream=stream)
    _at(clock, progress, 2.0, 1, note="x")
    expected = "\rfit: [" + "#" * 6 + "-" * 18 + "] 1/4 (2 s, about 6 s left) x"
    assert stream.writes == [expected.ljust(80)]
    _at(clock, progress, 2.05, 2)  # within 0.1 s of the last line
    assert len(stream.writes) == 1
    _at(clock, progress, 2.2, 3)
    assert stream.writes[-1] == ("\rfit: [" + "#" * 18 + "-" * 6 + "] 3/4 (2 s, about 1 s left) x").ljust(80)
    clock.now = 103.0
    progress.advance(note="done")
    progress.close()
    assert stream.writes[-1] == ("\rfit: [" + "#" * 24 + "] 4/4 (3 s) done").ljust(80) + "\n"


def test_terminal_lines_are_cut_at_200_characters(clock):
    stream = Stream(tty=True)
    progress = Progress("L" * 300, total=None, stream=stream)
    _at(clock, progress, 2.0, 5)
    assert stream.writes == ["\r" + "L" * 199]


def test_without_total_a_count_only(clock):
    terminal, plain = Stream(tty=True), Stream(tty=False)
    for stream in (terminal, plain):
        progress = Progress("poses", stream=stream)
        clock.now = 100.0
        progress.start = 100.0
        progress.advance()
        progress.advance(2)
        _at(clock, progress, 2.0, progress.done + 2)
    assert terminal.writes == ["\rposes: 5 (2 s)".ljust(80)]
    assert plain.writes == ["poses: 5 (2 s)\n"]


def test_an_overrun_total_shows_a_full_bar_without_estimate(clock):
    plain, terminal = Stream(tty=False), Stream(tty=True)
    for stream in (plain, terminal):
        clock.now = 100.0
        _at(clock, Progress("fit", total=2, stream=stream), 3.0, 5)
    assert plain.writes == ["fit: 5/2 (3 s)\n"]
    assert terminal.writes == [("\rfit: [" + "#" * 24 + "] 5/2 (3 s)").ljust(80)]


def test_nothing_done_yet_has_no_estimate(clock):
    stream = Stream(tty=False)
    _at(clock, Progress("fit", total=10, stream=stream), 2.0, 0)
    assert stream.writes == ["fit: 0/10 (2 s)\n"]


def test_the_bar_rounds_its_filled_part_down(clock):
    stream = Stream(tty=True)
    _at(clock, Progress("fit", total=25, stream=stream), 2.0, 24)  # 23.04 of 24 cells
    assert stream.writes == [("\rfit: [" + "#" * 23 + "-] 24/25 (2 s, about 0 s left)").ljust(80)]


def test_explicit_interval(clock):
    stream = Stream(tty=False)
    progress = Progress("fit", total=10, stream=stream, delay=0.5, interval=1.0)
    _at(clock, progress, 0.4, 1)
    _at(clock, progress, 0.5, 1)
    _at(clock, progress, 1.4, 2)
    _at(clock, progress, 1.5, 3)
    assert [line.split(" (")[0] for line in stream.writes] == ["fit: 1/10", "fit: 3/10"]


def test_a_quick_loop_shows_nothing_even_at_close(clock):
    stream = Stream(tty=True)
    with Progress("quick", total=3, stream=stream) as progress:
        _at(clock, progress, 1.0, 3)
    assert stream.writes == [] and stream.flushes == 0


def test_quiet_silences_updates_and_close(clock):
    stream = Stream(tty=False)
    progress = Progress("fit", total=10, stream=stream)
    _at(clock, progress, 2.0, 1)
    set_quiet(True)
    _at(clock, progress, 9.0, 2)
    progress.close()
    assert len(stream.writes) == 1


def test_a_stream_without_isatty_gets_plain_lines(clock):
    class Bare:
        def __init__(self) -> None:
            self.text = ""

        def write(self, text):
            self.text += text

        def flush(self):
            pass

    stream = Bare()
    progress = Progress("fit", total=10, stream=stream)
    assert progress.tty is False and progress.interval == 5.0
    _at(clock, progress, 2.0, 1)
    assert stream.text == "fit: 1/10 (2 s, about 18 s left)\n"


def test_default_stream_is_stderr(clock, capsys):
    progress = Progress("fit", total=10)
    assert progress.stream is sys.stderr
    _at(clock, progress, 2.0, 1)
    assert capsys.readouterr().err == "fit: 1/10 (2 s, about 18 s left)\n"


def test_a_failing_stream_is_ignored_and_never_counts_as_shown(clock):
    class ClosedOnce(Stream):
        """Refuses the first write, as a closed file would, and takes the later ones."""

        def write(self, text):
            if not self.flushes and not self.writes and not getattr(self, "refused", False):
                self.refused = True
                raise ValueError("I/O operation on closed file")
            super().write(text)

    stream = ClosedOnce(tty=True)
    progress = Progress("fit", total=10, stream=stream)
    _at(clock, progress, 2.0, 1)  # refused: no line was shown
    progress.close()
    assert stream.writes == []  # so close has no line to finish
