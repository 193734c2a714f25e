"""io.outputs tests that kill mutants the behaviour tests let through (docs/mutation.md): the exact
error of every refusal (path and message), each special-file kind, what `OutputSet` records
(kind, temporaries, notes, committed), lookups by path, staging through a file name, and the
failures of a write-through and of a rename. Root writes anywhere, so a folder without write or
search permission is simulated through `os.access`."""

from __future__ import annotations

import errno
import io
import os
import socket
import stat
from pathlib import Path

import pytest

from m3t1r.errors import OutputPathError
from m3t1r.io import outputs as outputs_module
from m3t1r.io.outputs import Output, OutputSet, atomic_write_bytes
from m3t1r.io.temporaries import _LIVE_TEMPORARIES

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
    assert (output.kind, output.temporary, output.data, output.closures, output.pair_of) == ("file", None, None, None, None)
    assert output.path == tmp_path / "a.csv" and output.label == "--out"
    stdout = Output("-", "--report")
    assert (stdout.kind, stdout.path, stdout.temporary, stdout.data, stdout.name) == (
        "stdout", None, None, None, "standard output")


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
    assert str(caught.value) == ("-: --machine: a machine is a URDF and its closures file; "
                                 "it cannot be written to standard output")


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
    assert str(error) == (f"{tmp_path / 'a.csv'}: --report is the same file as -o ({tmp_path / 'a.csv'}): "
                          "every output must be a different file")


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
        str(plain / "r.json"), f"{plain / 'r.json'}: --report: folder {plain} is not a folder")


@pytest.mark.parametrize("denied", [os.W_OK, os.X_OK])
def test_a_folder_without_write_or_search_permission_is_refused(tmp_path, monkeypatch, denied):
    real_access = os.access
    monkeypatch.setattr(outputs_module.os, "access",
                        lambda path, mode: False if mode & denied else real_access(path, mode))
    outputs = OutputSet()
    outputs.add(tmp_path / "r.json", "--report")
    error = _refusal(outputs)
    assert (error.path, str(error)) == (
        str(tmp_path / "r.json"), f"{tmp_path / 'r.json'}: --report: folder {tmp_path} is not writable")


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
    assert str(_refusal(outputs)) == (f"{closures_fifo}: closures file of -o is a named pipe; "
                                      "a machine is a pair of regular files")


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
        "/dev/full", "/dev/full: --report: write failed: No space left on device")


class _FailingStdout:
    def __init__(self, error: BaseException) -> None:
        self.buffer = self
        self.error = error

    def write(self, data):
        raise self.error

    def flush(self):
        pass


@pytest.mark.parametrize(("error", "message"), [
    (BrokenPipeError(errno.EPIPE, "Broken pipe"), "--report: the reader closed the pipe"),
    (OSError(errno.EIO, "Input/output error"), "--report: write failed: Input/output error"),
])
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


def test_staging_path_is_a_registered_temporary_beside_the_target(tmp_path):
    outputs = OutputSet()
    target = tmp_path / "plot.png"
    outputs.add(target, "--plot")
    outputs.check()
    first = outputs.staging_path(str(target))
    assert first.parent == tmp_path and first.name.startswith(".plot.png.m3t1r-") and first.suffix == ".tmp"
    assert first in _LIVE_TEMPORARIES and outputs.output(target).temporary == first
    first.write_bytes(b"one")
    second = outputs.staging_path(target)  # the same claimed (locked) file, emptied for the next writer
    assert second == first and second.read_bytes() == b"" and second in _LIVE_TEMPORARIES
    second.write_bytes(b"png")  # in place: the file's lock stays
    outputs.commit()
    assert target.read_bytes() == b"png" and second not in _LIVE_TEMPORARIES


def test_staging_path_refuses_streams():
    outputs = OutputSet()
    outputs.add("-", "--plot")
    with pytest.raises(OutputPathError) as caught:
        outputs.staging_path("-")
    assert (caught.value.path, str(caught.value)) == (
        "standard output",
        "standard output: --plot: a writer needing a file name cannot write to a pipe, device or standard output")


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
    with pytest.raises(ValueError, match=(f"^outputs declared but never staged: {tmp_path / 'a.csv'}, "
                                          f"{tmp_path / 'b.csv'}, standard output$")):
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
