"""io.temporaries tests that kill mutants the behaviour tests let through (docs/mutation.md): which
leftover completes an interrupted pair commit and which is removed, live writers' files kept
(including another user's, simulated), the temporary name, the new file's mode, failures while
creating or writing a temporary, `pending_temporaries` with symlinks and vanishing entries, and
`print_notice`."""

from __future__ import annotations

import errno
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from m3t1r.errors import OutputPathError
from m3t1r.io import temporaries
from m3t1r.io.pairing import sha256_bytes, with_closures_sha256
from m3t1r.io.temporaries import (
    _LIVE_TEMPORARIES,
    _write_temporary,
    pending_temporaries,
    print_notice,
    sweep,
    temporary_path,
)

DEAD_PID = 2**22 + 1  # above any pid_max: never a live process


def _leftover(folder: Path, name: str, data: bytes = b"staged", pid: int = DEAD_PID) -> Path:
    path = folder / f".{name}.m3t1r-{pid}-0a.tmp"
    path.write_bytes(data)
    return path


def _urdf_recording(folder: Path, data: bytes, name: str = "m.urdf") -> Path:
    path = folder / name
    path.write_bytes(with_closures_sha256(b"<robot/>", sha256_bytes(data)))
    return path


# -- sweep and pair completion ------------------------------------------------------------------------


def test_a_staged_closures_file_named_by_its_urdf_completes_the_commit(tmp_path):
    _urdf_recording(tmp_path, b"new")
    (tmp_path / "m.closures.yaml").write_bytes(b"old")
    leftover = _leftover(tmp_path, "m.closures.yaml", b"new")
    notes = sweep(tmp_path, announce=None)
    assert (tmp_path / "m.closures.yaml").read_bytes() == b"new" and not leftover.exists()
    assert notes == [f"completed the interrupted write of {tmp_path / 'm.closures.yaml'} (its URDF already named it)"]


def test_a_staged_closures_file_completes_a_pair_whose_closures_file_is_missing(tmp_path):
    _urdf_recording(tmp_path, b"new")
    _leftover(tmp_path, "m.closures.yaml", b"new")
    sweep(tmp_path, announce=None)
    assert (tmp_path / "m.closures.yaml").read_bytes() == b"new"


@pytest.mark.parametrize("case", ["other digest", "no digest", "no urdf", "already in place"])
def test_other_closures_leftovers_are_removed(tmp_path, case):
    if case == "other digest":
        _urdf_recording(tmp_path, b"something else")
    elif case == "no digest":
        (tmp_path / "m.urdf").write_bytes(b"<robot/>")
    elif case == "already in place":
        _urdf_recording(tmp_path, b"new")
    (tmp_path / "m.closures.yaml").write_bytes(b"new" if case == "already in place" else b"old")
    leftover = _leftover(tmp_path, "m.closures.yaml", b"new")
    notes = sweep(tmp_path, announce=None)
    assert not leftover.exists()
    assert (tmp_path / "m.closures.yaml").read_bytes() == (b"new" if case == "already in place" else b"old")
    assert notes == [f"removed {leftover}, a temporary file left by an interrupted run"]


def test_only_closures_files_are_ever_completed(tmp_path):
    # "r.json" minus the closures suffix is "", whose URDF would be ".urdf": even if that names
    # the leftover, a report's leftover is removed.
    _urdf_recording(tmp_path, b"new", name=".urdf")
    leftover = _leftover(tmp_path, "r.json", b"new")
    sweep(tmp_path, announce=None)
    assert not leftover.exists() and not (tmp_path / "r.json").exists()


def test_a_leftover_that_cannot_be_removed_is_noted_and_announced(tmp_path):
    stuck = tmp_path / f".r.json.m3t1r-{DEAD_PID}-0b.tmp"
    stuck.mkdir()  # unlink of a directory fails
    announced: list[str] = []
    notes = sweep(tmp_path, announce=announced.append)
    assert notes == [f"could not clean up {stuck}: Is a directory"] and announced == notes


def test_files_of_live_processes_are_kept_and_not_signalled(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        live = _leftover(tmp_path, "r.json", pid=child.pid)
        own = _leftover(tmp_path, "s.json", pid=os.getpid())
        assert sweep(tmp_path, announce=None) == []
        assert live.exists() and own.exists()
        with pytest.raises(subprocess.TimeoutExpired):  # the liveness probe is signal 0, not a real signal
            child.wait(timeout=0.2)
    finally:
        child.kill()
        child.wait()


@pytest.mark.parametrize("error", [PermissionError(errno.EPERM, "Operation not permitted"), OSError(errno.EINVAL, "x")])
def test_a_process_that_cannot_be_probed_counts_as_alive(tmp_path, monkeypatch, error):
    def kill(pid, signal):
        raise error

    monkeypatch.setattr(temporaries.os, "kill", kill)
    leftover = _leftover(tmp_path, "r.json")
    assert sweep(tmp_path, announce=None) == [] and leftover.exists()


# -- temporary names and writes ---------------------------------------------------------------------


def test_temporary_name_is_hidden_and_names_the_process(tmp_path):
    path = temporary_path(tmp_path / "out.csv")
    assert path.parent == tmp_path
    assert re.fullmatch(rf"\.out\.csv\.m3t1r-{os.getpid()}-[0-9a-f]{{12}}\.tmp", path.name)


def test_a_new_file_gets_the_umask_mode_and_is_registered(tmp_path):
    previous = os.umask(0o022)
    try:
        temporary = _write_temporary(tmp_path / "new.csv", b"data")
    finally:
        os.umask(previous)
    try:
        assert os.stat(temporary).st_mode & 0o777 == 0o644
        assert temporary.read_bytes() == b"data" and temporary in _LIVE_TEMPORARIES
    finally:
        temporary.unlink()
        _LIVE_TEMPORARIES.discard(temporary)


def test_an_existing_temporary_name_is_never_reused(tmp_path, monkeypatch):
    taken = tmp_path / ".out.csv.m3t1r-1-00.tmp"
    taken.write_bytes(b"someone else's")
    monkeypatch.setattr(temporaries, "temporary_path", lambda target: taken)
    with pytest.raises(OutputPathError) as caught:
        _write_temporary(tmp_path / "out.csv", b"mine")
    assert caught.value.path == str(tmp_path / "out.csv")
    assert str(caught.value) == f"{tmp_path / 'out.csv'}: cannot create a temporary file in {tmp_path}: File exists"
    assert taken.read_bytes() == b"someone else's"


def test_a_failed_write_removes_and_forgets_the_temporary(tmp_path, monkeypatch):
    def fsync(descriptor):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(temporaries.os, "fsync", fsync)
    before = set(_LIVE_TEMPORARIES)
    with pytest.raises(OutputPathError) as caught:
        _write_temporary(tmp_path / "out.csv", b"data")
    assert str(caught.value) == f"{tmp_path / 'out.csv'}: write failed, file left unchanged: Input/output error"
    assert list(tmp_path.iterdir()) == [] and set(_LIVE_TEMPORARIES) == before


def test_an_interrupted_write_removes_and_forgets_the_temporary(tmp_path, monkeypatch):
    def fsync(descriptor):
        raise KeyboardInterrupt

    monkeypatch.setattr(temporaries.os, "fsync", fsync)
    before = set(_LIVE_TEMPORARIES)
    with pytest.raises(KeyboardInterrupt):
        _write_temporary(tmp_path / "out.csv", b"data")
    assert list(tmp_path.iterdir()) == [] and set(_LIVE_TEMPORARIES) == before


# -- pending_temporaries ----------------------------------------------------------------------------


def test_pending_temporaries_include_a_dangling_symlink(tmp_path):
    link = tmp_path / f".out.csv.m3t1r-{DEAD_PID}-0c.tmp"
    link.symlink_to(tmp_path / "nowhere")
    assert pending_temporaries(tmp_path / "out.csv") == [link]


def test_pending_temporaries_skip_an_entry_that_vanished(tmp_path, monkeypatch):
    class Entry:
        def __init__(self, name: str, mtime: float | None) -> None:
            self.name, self.mtime = name, mtime

        def stat(self, follow_symlinks=True):
            if self.mtime is None:
                raise FileNotFoundError(errno.ENOENT, "gone")
            return os.stat_result((0, 0, 0, 0, 0, 0, 0, 0, self.mtime, 0))

    entries = [Entry(".out.csv.m3t1r-1-0a.tmp", 2.0), Entry(".out.csv.m3t1r-2-0b.tmp", None),
               Entry(".out.csv.m3t1r-3-0c.tmp", 1.0), Entry("out.csv", 0.0)]
    monkeypatch.setattr(temporaries.os, "scandir", lambda folder: iter(entries))
    assert pending_temporaries(tmp_path / "out.csv") == [tmp_path / ".out.csv.m3t1r-3-0c.tmp",
                                                          tmp_path / ".out.csv.m3t1r-1-0a.tmp"]


# -- print_notice --------------------------------------------------------------------------------------


def test_print_notice_writes_a_flushed_line_on_stderr(monkeypatch):
    class Stream:
        def __init__(self) -> None:
            self.events: list[str] = []

        def write(self, text):
            self.events.append(text)

        def flush(self):
            self.events.append("<flush>")

    stream = Stream()
    monkeypatch.setattr(sys, "stderr", stream)
    print_notice("removed x")
    assert "".join(stream.events[:-1]) == "m3t1r: removed x\n" and stream.events[-1] == "<flush>"
