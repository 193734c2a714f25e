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
    claim_temporary,
    folder_lock,
    pending_temporaries,
    print_notice,
    sweep,
    temporary_path,
    write_claimed,
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


def _held_by_child(path: Path) -> subprocess.Popen:
    """A child process that holds `path`'s flock, as a live writer does, until killed."""
    child = subprocess.Popen([sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'rb+'); "
                              "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)", str(path)],
                             stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "held"
    return child


def test_files_whose_lock_is_held_are_kept_whatever_pid_they_name(tmp_path):
    """Liveness is the writer's flock, not its pid: a file naming a pid that does not exist here (a
    writer in another container or on another host) is kept while its lock is held, and one naming
    this very process is removed when nobody holds it (a reused pid)."""
    elsewhere = _leftover(tmp_path, "r.json", pid=DEAD_PID)
    reused = _leftover(tmp_path, "s.json", pid=os.getpid())
    child = _held_by_child(elsewhere)
    try:
        assert sweep(tmp_path, announce=None) == [f"removed {reused}, a temporary file left by an interrupted run"]
        assert elsewhere.exists() and not reused.exists()
    finally:
        child.kill()
        child.wait()
    sweep(tmp_path, announce=None)  # its writer gone, the lock with it
    assert not elsewhere.exists()


@pytest.mark.parametrize("error", [OSError(errno.ENOLCK, "No locks available"), OSError(errno.EINVAL, "x")])
def test_a_file_whose_lock_cannot_be_probed_is_kept(tmp_path, monkeypatch, error):
    def flock(descriptor, operation):
        raise error

    leftover = _leftover(tmp_path, "r.json")
    with folder_lock(tmp_path):  # the folder's own lock first, then every probe fails
        monkeypatch.setattr(temporaries.fcntl, "flock", flock)
        assert temporaries.sweep_locked(tmp_path) == [] and leftover.exists()


# -- temporary names and writes ---------------------------------------------------------------------


def test_temporary_name_is_hidden_and_names_the_process(tmp_path):
    path = temporary_path(tmp_path / "out.csv")
    assert path.parent == tmp_path
    assert re.fullmatch(rf"\.out\.csv\.m3t1r-{os.getpid()}-[0-9a-f]{{12}}\.tmp", path.name)


def test_a_temporary_name_fits_the_folders_name_limit(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    for name in ("é" * 100 + ".csv", "x" * (limit - 4) + ".csv"):  # bytes, not characters, count
        path = temporary_path(tmp_path / name)
        assert len(os.fsencode(path.name)) <= limit and path.name.startswith(".")
        assert path.name[1:].encode()[:20] == name.encode()[:20]  # still recognisable by eye
        path.write_bytes(b"")
        assert pending_temporaries(tmp_path / name) == [path]
        assert pending_temporaries(tmp_path / (name[:-5] + "y.csv")) == []  # same prefix, other name
        path.unlink()


def test_a_claimed_file_is_locked_registered_and_names_its_run(tmp_path):
    temporary, descriptor = claim_temporary(tmp_path / "out.csv")
    try:
        assert temporary in _LIVE_TEMPORARIES and temporaries._holder(temporary) is True
        assert temporaries.live_writer(tmp_path / "out.csv") is None  # this process's own claim
        assert temporary.read_bytes().startswith(f"m3t1r run in progress: pid {os.getpid()} on ".encode())
    finally:
        temporaries.release_temporary(temporary, descriptor, remove=True)
    assert not temporary.exists() and temporary not in _LIVE_TEMPORARIES


def test_a_new_file_gets_the_umask_mode(tmp_path):
    previous = os.umask(0o022)
    try:
        temporary, descriptor = claim_temporary(tmp_path / "new.csv")
    finally:
        os.umask(previous)
    try:
        write_claimed(tmp_path / "new.csv", temporary, descriptor, b"data")
        assert os.stat(temporary).st_mode & 0o777 == 0o644 and temporary.read_bytes() == b"data"
    finally:
        temporaries.release_temporary(temporary, descriptor, remove=True)


def test_an_existing_temporary_name_is_never_reused(tmp_path, monkeypatch):
    taken = tmp_path / ".out.csv.m3t1r-1-00.tmp"
    taken.write_bytes(b"someone else's")
    monkeypatch.setattr(temporaries, "temporary_path", lambda target: taken)
    with pytest.raises(OutputPathError) as caught:
        claim_temporary(tmp_path / "out.csv")
    assert caught.value.path == str(tmp_path / "out.csv")
    assert str(caught.value) == (f"{tmp_path / 'out.csv'}: cannot create a file in {tmp_path}: File exists; "
                                 "nothing was written")
    assert taken.read_bytes() == b"someone else's"


def test_a_failed_write_empties_the_claimed_file(tmp_path, monkeypatch):
    def fsync(descriptor):
        raise OSError(errno.ENOSPC, "No space left on device")

    temporary, descriptor = claim_temporary(tmp_path / "out.csv")
    monkeypatch.setattr(temporaries.os, "fsync", fsync)
    try:
        with pytest.raises(OutputPathError) as caught:
            write_claimed(tmp_path / "out.csv", temporary, descriptor, b"data" * 1000)
        assert str(caught.value) == f"{tmp_path / 'out.csv'}: write failed, file left unchanged: No space left on device"
        assert temporary.stat().st_size == 0 and not (tmp_path / "out.csv").exists()
    finally:
        temporaries.release_temporary(temporary, descriptor, remove=True)


def test_an_interrupted_claim_removes_and_forgets_the_temporary(tmp_path, monkeypatch):
    def write(descriptor, data):
        raise KeyboardInterrupt

    monkeypatch.setattr(temporaries.os, "write", write)
    before = set(_LIVE_TEMPORARIES)
    with pytest.raises(KeyboardInterrupt):
        claim_temporary(tmp_path / "out.csv")
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
