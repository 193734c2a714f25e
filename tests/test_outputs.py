"""Outputs that can be trusted (issue 10): file pairs, collisions, special files, strict JSON, row errors.

Library-level tests of `m3t1r.io.outputs.OutputSet` and the pair loader, and CLI tests of the verbs that
use them.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import stat
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from m3t1r.app.cli import main
from m3t1r.errors import ModelFileError, OutputPathError
from m3t1r.io.outputs import OutputSet
from m3t1r.io.pairing import closures_sha256, paired_closures_path
from m3t1r.io.progress import Heartbeat, Progress, set_quiet
from m3t1r.io.strict_json import json_text
from m3t1r.io.temporaries import sweep, temporary_path
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
    code = main(["ik", str(_targets(tmp_path)), "--model", str(tmp_path / "machine.v1.urdf"), "-o",
                 str(tmp_path / "s.csv")])
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
    notes = sweep(tmp_path, announce=None)
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
        code = main(["calibrate", str(machines / "m.csv"), "-o", str(tmp_path / "c.urdf"), "--report",
                     str(tmp_path / report), "--quiet"])
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


def _locked_elsewhere(path: Path) -> subprocess.Popen:
    """Another process holding `path`'s flock, as a live writer in another container or host would."""
    child = subprocess.Popen([sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'rb+'); "
                              "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)", str(path)],
                             stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "held"
    return child


def test_leftovers_of_killed_runs_are_removed_and_live_ones_kept(tmp_path):
    """A leftover is a temporary file nobody holds the lock of. A live writer's file names a pid
    that means nothing here (2**22 + 1: in another PID namespace, or on another host sharing the
    folder); it is kept because its lock is held, where the pid probe used to delete it."""
    dead = tmp_path / f".r.json.m3t1r-{os.getpid()}-0a.tmp"  # a reused pid: this very process
    live = tmp_path / f".r.json.m3t1r-{2**22 + 1}-0b.tmp"
    dead.write_text("{")
    live.write_text("{")
    writer = _locked_elsewhere(live)
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
    return subprocess.run([sys.executable, "-c", _SECOND_WRITER, str(folder)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}, check=True).stdout.strip()


def test_a_second_writer_of_an_output_is_refused_before_any_work(tmp_path):
    """Two runs writing the same pair: the second is refused at its check, naming the folder and the
    first run, and the first run's pair lands whole, where both used to exit 0 leaving B's URDF
    with A's closures file."""
    first = OutputSet(announce=None)
    machine = first.add_machine(tmp_path / "c.urdf")
    first.check()
    message = _second_writer(tmp_path)
    assert message.startswith(f"{tmp_path / 'c.urdf'}: -o: another m3t1r run is writing this file in {tmp_path} "
                              f"(pid {os.getpid()} on {socket.gethostname()}, started ")
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
    script = ("import sys, time\nfrom m3t1r.io.outputs import OutputSet\n"
              "outputs = OutputSet(); outputs.add(sys.argv[1]); outputs.check(); print('claimed', flush=True); "
              "time.sleep(60)")
    child = subprocess.Popen([sys.executable, "-c", script, str(target)], stdout=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert child.stdout.readline().strip() == "claimed"
        outputs = OutputSet(announce=None)
        outputs.add(target, "-o")
        with pytest.raises(OutputPathError, match=f"another m3t1r run is writing this file in {tmp_path} "
                                                  f"\\(pid {child.pid} on "):
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
        with pytest.raises(OutputPathError, match="could not move the new file into place: Is a directory; "
                                                  "the 1 output\\(s\\) renamed before it were put back"):
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
    assert any("completed the interrupted write" in note for note in sweep(tmp_path, announce=None))
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
    assert main(["calibrate", str(meas), "-o", str(tmp_path / "c.urdf"), "--report", str(tmp_path / "r.json"),
                 "--quiet"]) == 0
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
    code = main(["compensate", str(targets), "--unordered", "--calibrated", str(machines / "truth.urdf"), "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and not out.exists()
    assert "t.csv, line 3" in err and "beyond its limit" in err and "line 2" not in err


def test_compensate_unordered_targets_gives_the_path_commands(tmp_path, machines, capsys):
    """--unordered solves every target from home in one batch: the same commands as the path
    (warm-started) solve to 1e-9 m, for targets in no particular order."""
    rng = np.random.default_rng(5)
    rows = np.column_stack((rng.uniform(0.3, 0.7, 12), rng.uniform(0.3, 0.7, 12), rng.uniform(-0.15, -0.05, 12),
                            rng.uniform(-0.4, 0.4, 12)))
    targets = tmp_path / "t.csv"
    targets.write_text("x,y,z,theta\n" + "\n".join(",".join(f"{v:.6f}" for v in row) for row in rows) + "\n")
    outputs = []
    for extra in ([], ["--unordered"]):
        out = tmp_path / f"c{len(extra)}.csv"
        assert main(["compensate", str(targets), *extra, "--output-kind", "actuators", "--calibrated",
                     str(machines / "truth.urdf"), "-o", str(out)]) == 0
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
