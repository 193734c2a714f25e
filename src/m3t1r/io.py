"""Files in and out: atomic writes that cannot clobber an input, and validated numeric CSV tables.

Every output goes through `atomic_write_bytes`, so an interrupted run or a full disk never leaves
a half-written calibration behind, and its `protect` list keeps the nominal model and the
measurement files from being overwritten by a mistyped output path.

CSV format read by `read_table` and written by `write_table`:

- UTF-8 (a byte-order mark is tolerated), comma-separated, SI units (m, rad);
- a line whose first non-blank character is `#` is a comment; blank lines are ignored;
- the first other line is the header of column names, every line after it is a data row;
- every data field is a finite decimal number (`1`, `-0.25`, `3e-05`; no `nan`, `inf`, `1_000`).

Errors in a file are `DataFileError`s carrying the 1-based line number in the file (comments and
blank lines counted, as an editor shows it) and the column name, so a user can go straight to
the bad field.
"""

from __future__ import annotations

import atexit
import csv
import hashlib
import json
import math
import os
import re
import secrets
import signal
import stat
import sys
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeAlias

import numpy as np
import pinocchio as pin

from m3t1r.errors import DataFileError, InvalidInputError, M3t1rError, ModelFileError, OutputPathError

StrPath: TypeAlias = "str | os.PathLike[str]"

POSE_COLUMNS: tuple[str, ...] = ("x", "y", "z", "qx", "qy", "qz", "qw")
"""Columns of a pose: position in m, then the unit quaternion with its scalar part last."""


# --------------------------------------------------------------------------------------------
# Outputs: temporary files, output sets committed as a unit, special files, file pairs
# --------------------------------------------------------------------------------------------

STDOUT = "-"
"""The output path that means standard output (`-o -`)."""

CLOSURES_SUFFIX = ".closures.yaml"

# A temporary file is `.<final name>.m3t1r-<pid>-<random hex>.tmp` in the target's folder: hidden,
# recognisable, on the target's filesystem (so the final rename is atomic), and naming the process
# that wrote it, so that a later run can tell a leftover of a killed run from a live writer's file.
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.m3t1r-(?P<pid>\d+)-(?P<token>[0-9a-f]+)\.tmp$")

# Temporary files of this process not yet renamed; removed at exit if an error skipped that.
_LIVE_TEMPORARIES: set[Path] = set()


def print_notice(message: str) -> None:
    """Default `announce` of OutputSet and `sweep`: `m3t1r: <message>` on stderr."""
    print(f"m3t1r: {message}", file=sys.stderr, flush=True)


def paired_closures_path(urdf: StrPath) -> Path:
    """`NAME.urdf` -> `NAME.closures.yaml` beside it: only the final `.urdf` is replaced.

    `machine.v1.urdf` pairs with `machine.v1.closures.yaml`, never with `machine.closures.yaml`;
    a name without the `.urdf` suffix gets `.closures.yaml` appended.
    """
    path = Path(urdf)
    name = path.name
    stem = name[: -len(".urdf")] if name.lower().endswith(".urdf") and len(name) > len(".urdf") else name
    return path.with_name(stem + CLOSURES_SUFFIX)


def temporary_path(target: StrPath) -> Path:
    """A fresh recognisable temporary name for `target`, in the target's folder."""
    target = Path(target)
    return target.parent / f".{target.name}.m3t1r-{os.getpid()}-{secrets.token_hex(6)}.tmp"


def pending_temporaries(target: StrPath) -> list[Path]:
    """Temporary files for `target` present in its folder (of any process), oldest first."""
    target = Path(target)
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return []
    found = []
    for entry in entries:
        match = _TEMPORARY.match(entry.name)
        if match and match["name"] == target.name:
            try:
                found.append((entry.stat(follow_symlinks=False).st_mtime, target.parent / entry.name))
            except OSError:
                continue
    return [path for _, path in sorted(found)]


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of `data`."""
    return hashlib.sha256(data).hexdigest()


def ensure_not_protected(path: StrPath, protect: Iterable[StrPath]) -> None:
    """Raise OutputPathError if `path` is the same file as any path in `protect`.

    Two paths are the same file if they resolve to the same absolute path (symlinks followed) or
    name the same existing inode (hard links, bind mounts). Call it before a long computation to
    fail early; the atomic writers call it again anyway.
    """
    if str(path) == STDOUT:
        return
    target = Path(path)
    for protected in protect:
        if str(protected) != STDOUT and _same_file(target, Path(protected)):
            raise OutputPathError(target, f"refusing to overwrite the input file {protected}")


def atomic_write_bytes(path: StrPath, data: bytes, protect: Iterable[StrPath] = ()) -> None:
    """Replace the file at `path` with `data` in one step, or leave it untouched.

    The bytes go to a temporary file in the target's directory (same filesystem, so the final
    `os.replace` is an atomic rename), are flushed and fsynced, then renamed over `path`: a
    reader sees the old content or the new, never a prefix. On any failure the temporary file
    is removed and an existing target is left as it was. A replaced file keeps its permission
    bits; a new one gets the process umask's. A symlink at `path` is replaced, not followed.

    `-` writes to standard output, and an existing named pipe or character device (a terminal,
    /dev/null) is written through, never replaced: nothing atomic is pretended there.

    Raises OutputPathError if `path` is one of `protect`, is a directory or another special
    file, its directory does not exist or is not writable, or the write fails.
    """
    outputs = OutputSet(inputs=protect, announce=None)
    outputs.add(path)
    with outputs:
        outputs.check()
        outputs.stage(path, data)
        outputs.commit()


def atomic_write_text(path: StrPath, text: str, protect: Iterable[StrPath] = ()) -> None:
    """`atomic_write_bytes` of `text` encoded as UTF-8, line endings written as given."""
    atomic_write_bytes(path, text.encode("utf-8"), protect=protect)


def json_text(document: object) -> str:
    """Strict JSON of `document`: NaN and infinities become `null`, numpy scalars and arrays plain.

    The result always parses with a strict parser (no `NaN`, `Infinity`); keys keep their order.
    """
    return json.dumps(_strict(document), indent=2, allow_nan=False) + "\n"


def _strict(value: object) -> object:
    if isinstance(value, dict):
        return {str(key): _strict(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(item) for item in value]
    if isinstance(value, np.ndarray):
        return [_strict(item) for item in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


class Output:
    """One declared output of an `OutputSet`. `path` is as given; `label` names it in messages."""

    def __init__(self, path: StrPath, label: str, pair_of: "Output | None" = None) -> None:
        self.path = Path(path) if str(path) != STDOUT else None
        self.label = label
        self.pair_of = pair_of  # for a closures file: the URDF output it belongs with
        self.closures: Output | None = None  # for a machine URDF: its closures output
        self.kind = "stdout" if self.path is None else "file"  # "file", "stdout" or "special"
        self.temporary: Path | None = None
        self.data: bytes | None = None  # for stdout and special files, written at commit

    @property
    def name(self) -> str:
        return "standard output" if self.path is None else str(self.path)

    def __repr__(self) -> str:
        return f"Output({self.name!r}, {self.label!r}, kind={self.kind!r})"


class OutputSet:
    """All the outputs of one command, checked before any work and written as a unit.

    Usage::

        outputs = OutputSet(inputs=[measurements, nominal.urdf_path, nominal.closures_path])
        machine = outputs.add_machine(args.output, "-o")     # NAME.urdf and NAME.closures.yaml
        report = outputs.add(args.report, "--report")        # None when args.report is None
        outputs.check()                                       # OutputPathError now, nothing written
        ...compute...
        outputs.stage_machine(machine, calibrated); outputs.stage_json(report, document)
        outputs.commit()                                      # every output lands, or none changes

    `check` refuses (with `OutputPathError`, exit status 2 in the CLI): two outputs that are the
    same file, or an output that is an input, compared through symlinks and hard links; an output
    folder that does not exist or is not writable; an output that is a directory, a socket or a
    block device; a machine URDF given as `-` or as a pipe or device (a machine is two files).
    It also sweeps each output folder for temporary files left by killed runs (see `sweep`).

    `stage*` writes each output's bytes to a temporary file beside its target at once (a full
    disk shows then, before anything is replaced). `commit` then renames them over their targets
    with catchable signals held back, auxiliary outputs first and each machine URDF last but one:
    the URDF rename is a pair's commit point, and its closures file is renamed right after. A
    URDF records its closures file's sha256 and the loader also accepts the staged closures file
    of that hash, so a kill at any instant leaves a loadable pair, old or new (models/README.md).
    `-` (stdout) and existing pipes and character devices are written through at commit.

    Used as a context manager, an exception or caught signal inside the block removes every
    temporary file; `discard()` does the same explicitly.
    """

    def __init__(self, inputs: Iterable[StrPath] = (), *, announce=print_notice) -> None:
        self.inputs: list[Path] = [Path(p) for p in inputs if p is not None and str(p) != STDOUT]
        self.outputs: list[Output] = []
        self.announce = announce
        self.notes: list[str] = []
        self.committed = False

    # -- declaring --------------------------------------------------------------------------
    def add_input(self, path: StrPath | None) -> None:
        """Declare one more input file that no output may be."""
        if path is not None and str(path) != STDOUT:
            self.inputs.append(Path(path))

    def add(self, path: StrPath | None, label: str = "output") -> Output | None:
        """Declare an output file (`-` is stdout); None gives None, for optional outputs."""
        if path is None:
            return None
        output = Output(path, label)
        self.outputs.append(output)
        return output

    def add_machine(self, urdf: StrPath | None, label: str = "-o", closures: StrPath | None = None) -> Output | None:
        """Declare a machine: URDF `NAME.urdf` and its closures file (default `NAME.closures.yaml`).

        Returns the URDF's Output; its `.closures` is the closures file's. None gives None.
        """
        if urdf is None:
            return None
        if str(urdf) == STDOUT:
            raise OutputPathError(STDOUT, f"{label}: a machine is a URDF and its closures file; "
                                          "it cannot be written to standard output")
        machine = Output(urdf, label)
        machine.closures = Output(paired_closures_path(urdf) if closures is None else closures,
                                  f"closures file of {label}", pair_of=machine)
        self.outputs += [machine, machine.closures]
        return machine

    def output(self, path: StrPath) -> Output:
        """The declared Output for `path` (as given)."""
        for output in self.outputs:
            if (output.path is None and str(path) == STDOUT) or (output.path is not None and output.path == Path(path)):
                return output
        raise KeyError(f"{path} is not a declared output")

    # -- checking ---------------------------------------------------------------------------
    def check(self) -> None:
        """Refuse collisions, missing or read-only folders and unusable special files; sweep leftovers.

        Raises OutputPathError naming the output, by its label, and what it collides with.
        """
        seen: list[tuple[Output, Path, tuple[int, int] | None]] = []
        folders: list[Path] = []
        stdout_user: Output | None = None
        for output in self.outputs:
            if output.path is None:
                if stdout_user is not None:
                    raise OutputPathError(STDOUT, f"{output.label} and {stdout_user.label} both write to standard output")
                stdout_user = output
                continue
            self._classify(output)
            resolved, inode = _identity(output.path)
            for protected in self.inputs:
                if _same_identity(resolved, inode, *_identity(protected)):
                    raise OutputPathError(output.path, f"{output.label}: refusing to overwrite the input file {protected}")
            for other, other_resolved, other_inode in seen:
                if _same_identity(resolved, inode, other_resolved, other_inode):
                    raise OutputPathError(
                        output.path, f"{output.label} is the same file as {other.label} ({other.path}): "
                                     "every output must be a different file")
            seen.append((output, resolved, inode))
            if output.kind == "file":
                folder = output.path.parent
                if folder not in folders:
                    _check_folder(output, folder)
                    folders.append(folder)
        for folder in folders:
            self.notes += sweep(folder, announce=self.announce)

    def _classify(self, output: Output) -> None:
        path = output.path
        try:
            info = path.stat()  # follows a symlink: a link to a pipe is written through too
        except FileNotFoundError:
            output.kind = "file"
            return
        except OSError as exc:
            if path.is_symlink():  # a dangling or looping symlink is replaced like a file
                output.kind = "file"
                return
            raise OutputPathError(path, f"{output.label}: cannot inspect: {exc.strerror or exc}") from None
        mode = info.st_mode
        if stat.S_ISREG(mode):
            output.kind = "file"
        elif stat.S_ISDIR(mode):
            raise OutputPathError(path, f"{output.label} is a directory, expected a file path")
        elif stat.S_ISFIFO(mode) or stat.S_ISCHR(mode):
            if output.closures is not None or output.pair_of is not None:
                raise OutputPathError(path, f"{output.label} is a {'named pipe' if stat.S_ISFIFO(mode) else 'device'}; "
                                            "a machine is a pair of regular files")
            output.kind = "special"
        else:
            what = "block device" if stat.S_ISBLK(mode) else "socket" if stat.S_ISSOCK(mode) else "special file"
            raise OutputPathError(path, f"{output.label} is a {what}; refusing to write to it")

    # -- staging ----------------------------------------------------------------------------
    def stage(self, output: Output | StrPath, data: bytes | str) -> None:
        """Give `output` its content: written now to its temporary file (or kept for a stream)."""
        output = self._resolve(output)
        payload = data.encode("utf-8") if isinstance(data, str) else bytes(data)
        if output.kind != "file":
            output.data = payload
            return
        self._forget_temporary(output)
        output.temporary = _write_temporary(output.path, payload)

    def stage_json(self, output: Output | StrPath | None, document: object) -> None:
        """Stage strict JSON (`json_text`); None output: nothing to do."""
        if output is not None:
            self.stage(output, json_text(document))

    def stage_machine(self, output: Output | StrPath, mechanism: object) -> None:
        """Stage a machine pair from `mechanism.pair_bytes(urdf_name)` (a `Mechanism`)."""
        output = self._resolve(output)
        if output.closures is None:
            raise ValueError(f"{output.name} was not declared with add_machine")
        urdf_bytes, closures_bytes = mechanism.pair_bytes(output.path, output.closures.path)
        self.stage(output.closures, closures_bytes)
        self.stage(output, urdf_bytes)

    def staging_path(self, output: Output | StrPath) -> Path:
        """A temporary path to hand to a writer that needs a file name (a plot, say); renamed at commit.

        Only for regular-file outputs. The name ends in `.tmp`: give the writer the format explicitly.
        """
        output = self._resolve(output)
        if output.kind != "file":
            raise OutputPathError(output.name, f"{output.label}: a writer needing a file name cannot write to a "
                                               "pipe, device or standard output")
        self._forget_temporary(output)
        output.temporary = temporary_path(output.path)
        _LIVE_TEMPORARIES.add(output.temporary)
        return output.temporary

    # -- committing -------------------------------------------------------------------------
    def commit(self) -> list[str]:
        """Move every staged output into place (order in the class docstring); return their names.

        Raises ValueError if an output was never staged (a caller bug), OutputPathError if a
        rename fails; temporary files are removed on failure.
        """
        missing = [o.name for o in self.outputs if o.kind == "file" and (o.temporary is None or not o.temporary.exists())]
        missing += [o.name for o in self.outputs if o.kind != "file" and o.data is None]
        if missing:
            self.discard()
            raise ValueError(f"outputs declared but never staged: {', '.join(missing)}")
        plain = [o for o in self.outputs if o.kind == "file" and o.closures is None and o.pair_of is None]
        machines = [o for o in self.outputs if o.closures is not None]
        streams = [o for o in self.outputs if o.kind != "file"]
        folders: list[Path] = []
        try:
            with _signals_held():
                for output in plain:
                    self._rename(output)
                for machine in machines:
                    self._rename(machine)  # the commit point of the pair
                    self._rename(machine.closures)
                for output in (*plain, *machines, *(m.closures for m in machines)):
                    if output.path.parent not in folders:
                        folders.append(output.path.parent)
        except BaseException:
            self.discard()
            raise
        for folder in folders:
            _fsync_directory(folder)
        for output in streams:
            _write_through(output)
        self.committed = True
        return [o.name for o in self.outputs]

    def discard(self) -> None:
        """Remove every temporary file not yet renamed."""
        for output in self.outputs:
            self._forget_temporary(output)

    def __enter__(self) -> "OutputSet":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is not None:
            self.discard()

    # -- helpers ----------------------------------------------------------------------------
    def _resolve(self, output: Output | StrPath) -> Output:
        return output if isinstance(output, Output) else self.output(output)

    def _rename(self, output: Output) -> None:
        try:
            os.replace(output.temporary, output.path)
        except OSError as exc:
            raise OutputPathError(output.path, f"{output.label}: could not move the new file into place: "
                                               f"{exc.strerror or exc}") from None
        _LIVE_TEMPORARIES.discard(output.temporary)
        output.temporary = None

    @staticmethod
    def _forget_temporary(output: Output) -> None:
        if output.temporary is not None:
            _remove_quietly(output.temporary)
            _LIVE_TEMPORARIES.discard(output.temporary)
            output.temporary = None


def sweep(folder: StrPath, announce=print_notice) -> list[str]:
    """Deal with temporary files left in `folder` by killed m3t1r runs; return what was done.

    A leftover is a recognisable temporary file whose writing process no longer exists. A
    staged closures file whose URDF (`NAME.urdf` beside it) records its sha256 while
    `NAME.closures.yaml` does not match is the second half of an interrupted pair commit: it is
    renamed into place, completing that commit. Every other leftover is removed. Files of
    running processes are left alone.
    """
    folder = Path(folder)
    notes: list[str] = []
    try:
        names = sorted(entry.name for entry in os.scandir(folder))
    except OSError:
        return notes
    for name in names:
        match = _TEMPORARY.match(name)
        if not match or _process_alive(int(match["pid"])):
            continue
        leftover, target = folder / name, folder / match["name"]
        try:
            if target.name.endswith(CLOSURES_SUFFIX) and _completes_pair(leftover, target):
                os.replace(leftover, target)
                notes.append(f"completed the interrupted write of {target} (its URDF already named it)")
            else:
                os.unlink(leftover)
                notes.append(f"removed {leftover}, a temporary file left by an interrupted run")
        except OSError as exc:
            notes.append(f"could not clean up {leftover}: {exc.strerror or exc}")
    if announce is not None:
        for note in notes:
            announce(note)
    return notes


def _completes_pair(leftover: Path, closures: Path) -> bool:
    urdf = closures.with_name(closures.name[: -len(CLOSURES_SUFFIX)] + ".urdf")
    try:
        recorded = recorded_closures_sha256(urdf.read_bytes())
    except (OSError, M3t1rError):
        return False
    if recorded is None or sha256_bytes(leftover.read_bytes()) != recorded:
        return False
    try:
        return sha256_bytes(closures.read_bytes()) != recorded
    except OSError:
        return True


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists, owned by someone else (or cannot tell: keep it)
    return True


def _check_folder(output: Output, folder: Path) -> None:
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise OutputPathError(output.path, f"{output.label}: folder {folder} {what}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(output.path, f"{output.label}: folder {folder} is not writable")


def _identity(path: Path) -> tuple[Path, tuple[int, int] | None]:
    try:
        info = os.stat(path)
        inode = (info.st_dev, info.st_ino)
    except OSError:
        inode = None
    return _resolved(path), inode


def _same_identity(a: Path, a_inode, b: Path, b_inode) -> bool:
    return a == b or (a_inode is not None and a_inode == b_inode)


def _write_temporary(target: Path, data: bytes) -> Path:
    try:
        mode: int | None = stat.S_IMODE(target.stat().st_mode)
    except OSError:
        mode = None
    temporary = temporary_path(target)
    try:
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    except OSError as exc:
        raise OutputPathError(target, f"cannot create a temporary file in {target.parent}: {exc.strerror}") from None
    _LIVE_TEMPORARIES.add(temporary)
    try:
        with os.fdopen(descriptor, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        if mode is not None:
            os.chmod(temporary, mode)
    except OSError as exc:
        _remove_quietly(temporary)
        _LIVE_TEMPORARIES.discard(temporary)
        raise OutputPathError(target, f"write failed, file left unchanged: {exc.strerror or exc}") from None
    except BaseException:
        _remove_quietly(temporary)
        _LIVE_TEMPORARIES.discard(temporary)
        raise
    return temporary


def _write_through(output: Output) -> None:
    try:
        if output.path is None:
            stream = sys.stdout.buffer
            stream.write(output.data)
            stream.flush()
            return
        with open(output.path, "wb") as stream:  # a pipe or device: opened for writing, never replaced
            stream.write(output.data)
    except BrokenPipeError:
        raise OutputPathError(output.name, f"{output.label}: the reader closed the pipe") from None
    except OSError as exc:
        raise OutputPathError(output.name, f"{output.label}: write failed: {exc.strerror or exc}") from None


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT, SIGTERM, SIGHUP back while renaming; they are delivered when the block ends."""
    held = {signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", signal.SIGTERM)}
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class Terminated(BaseException):
    """A SIGTERM or SIGHUP arrived; raised so that cleanup runs as for Ctrl-C."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"terminated by signal {signal.Signals(signum).name}")


@contextmanager
def termination_as_exception() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise `Terminated` (SIGINT already raises
    KeyboardInterrupt), so `with OutputSet` blocks and `finally` clauses remove temporary files."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated(signum)

    previous = {}
    for signum in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if signum is not None:
            previous[signum] = signal.signal(signum, handler)
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


@atexit.register
def _remove_live_temporaries() -> None:
    for path in list(_LIVE_TEMPORARIES):
        _remove_quietly(path)
    _LIVE_TEMPORARIES.clear()


def _same_file(a: Path, b: Path) -> bool:
    if _resolved(a) == _resolved(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist, so they cannot be the same file
        return False


def _resolved(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # symlink loop: compare the unresolved absolute path instead
        return path.absolute()


def _remove_quietly(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _fsync_directory(directory: Path) -> None:
    # The rename is durable only once the directory entry reaches the disk. Best effort: some
    # platforms and network filesystems cannot open or fsync a directory, and the new file is
    # already in place, so raising here would misreport the outcome.
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


# --------------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------------

_QUIET = False


def set_quiet(quiet: bool) -> None:
    """Silence (True) or allow (False) every `Progress` of this process (the CLI's `--quiet`)."""
    global _QUIET
    _QUIET = bool(quiet)


class Progress:
    """Progress of a long loop on stderr: a bar on a terminal, a plain line every few seconds otherwise.

    Shows nothing during the first `delay` seconds (default 2 s), so quick commands stay silent,
    and nothing at all after `set_quiet(True)`. Usage::

        with Progress("calibrating", total=n_iterations) as progress:
            for k in range(n_iterations):
                ...
                progress.update(k + 1, note=f"cost {cost:.3g}")   # or progress.advance()

    `total=None` shows a count without a bar. Cheap to call every step: output is rate-limited.
    """

    def __init__(self, label: str, total: int | None = None, *, stream=None, delay: float = 2.0,
                 interval: float | None = None) -> None:
        self.label = label
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.delay = delay
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = interval if interval is not None else (0.1 if self.tty else 5.0)
        self.done = 0
        self.note = ""
        self.start = time.monotonic()
        self._last = -math.inf
        self._shown = False

    def advance(self, steps: int = 1, note: str | None = None) -> None:
        self.update(self.done + steps, note)

    def update(self, done: int, note: str | None = None) -> None:
        self.done = int(done)
        if note is not None:
            self.note = note
        now = time.monotonic()
        if _QUIET or now - self.start < self.delay or now - self._last < self.interval:
            return
        self._last = now
        self._emit(now, final=False)

    def close(self) -> None:
        if self._shown and not _QUIET:
            self._emit(time.monotonic(), final=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _emit(self, now: float, final: bool) -> None:
        elapsed = now - self.start
        if self.total:
            fraction = min(1.0, self.done / self.total)
            count = f"{self.done}/{self.total}"
            eta = f", about {elapsed / fraction - elapsed:.0f} s left" if 0 < fraction < 1 else ""
        else:
            fraction, count, eta = None, f"{self.done}", ""
        note = f" {self.note}" if self.note else ""
        try:
            if self.tty:
                bar = "" if fraction is None else "[" + "#" * int(24 * fraction) + "-" * (24 - int(24 * fraction)) + "] "
                line = f"\r{self.label}: {bar}{count} ({elapsed:.0f} s{eta}){note}"
                self.stream.write(line[:200].ljust(80) + ("\n" if final else ""))
            else:
                self.stream.write(f"{self.label}: {count} ({elapsed:.0f} s{eta}){note}\n")
            self.stream.flush()
        except (OSError, ValueError):
            return
        self._shown = True


# --------------------------------------------------------------------------------------------
# Numeric CSV tables
# --------------------------------------------------------------------------------------------

MAX_MAGNITUDE = 1e6
"""Largest magnitude accepted in a CSV field by default [m or rad]: 1000 km, far beyond any
machine, far below the 1e154 whose square overflows a double."""


@dataclass(frozen=True, eq=False)
class Table:
    """A validated numeric CSV table. Its arrays are read-only copies, so a frozen table stays frozen.

    Attributes:
        path: the file the table was read from.
        columns: column names, in file order.
        data: (n_rows, n_columns) float64 values, SI units (m, rad).
        line_numbers: (n_rows,) int64, the 1-based line of each data row in `path`, so that code
            rejecting a row later (say, a joint value outside its limits) can name the line.
    """

    path: Path
    columns: tuple[str, ...]
    data: np.ndarray
    line_numbers: np.ndarray

    def __post_init__(self) -> None:
        data = np.array(self.data, dtype=float)
        lines = np.array(self.line_numbers, dtype=np.int64)
        if data.ndim != 2 or data.shape[1] != len(self.columns):
            raise ValueError(f"data of shape {data.shape} does not match {len(self.columns)} columns")
        if lines.shape != (data.shape[0],):
            raise ValueError(f"line_numbers of shape {lines.shape} does not match {data.shape[0]} rows")
        data.setflags(write=False)
        lines.setflags(write=False)
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "columns", tuple(self.columns))
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "line_numbers", lines)

    @property
    def n_rows(self) -> int:
        """Number of data rows."""
        return int(self.data.shape[0])

    def has_column(self, name: str) -> bool:
        """Whether the file has column `name` (an optional column may be absent)."""
        return name in self.columns

    def column(self, name: str) -> np.ndarray:
        """The (n_rows,) values of column `name`, as a read-only view."""
        try:
            index = self.columns.index(name)
        except ValueError:
            raise KeyError(f"{self.path} has no column '{name}'; it has {', '.join(self.columns)}") from None
        return self.data[:, index]

    def error(self, row_index: int, message: str, column: str | None = None) -> DataFileError:
        """A DataFileError about data row `row_index` (0-based), located at its line in the file."""
        return DataFileError(self.path, message, row=int(self.line_numbers[row_index]), column=column)


def read_table(
    path: StrPath,
    required: Sequence[str],
    optional: Sequence[str] = (),
    optional_groups: Sequence[Sequence[str]] = (),
    *,
    reject_duplicate_rows: bool = False,
    max_magnitude: float = MAX_MAGNITUDE,
) -> Table:
    """Read and validate a numeric CSV table (format in the module docstring).

    Args:
        path: the CSV file.
        required: columns the file must have.
        optional: columns the file may have, each on its own.
        optional_groups: columns that come all together or not at all, e.g. a quaternion
            `("qx", "qy", "qz", "qw")`.
        reject_duplicate_rows: also refuse two rows with identical values (a measurement
            recorded twice would weigh double in a fit).
        max_magnitude: refuse a value whose magnitude exceeds this (default `MAX_MAGNITUDE`):
            such a value is a unit or column mix-up, and would overflow later computations
            (1e300 squared is inf) far from the row that caused it.

    Any other column in the file is an error: a file written for another model or another
    command must not load with some of its columns silently ignored.

    Raises:
        DataFileError: missing or unreadable file, no header, no data rows, empty or duplicate
            column name, missing required columns, unknown columns, a group present only in
            part, a row with the wrong number of fields, a field that is not a finite number,
            a duplicate row. It names the line and, where there is one, the column.
        ValueError: the schema itself is inconsistent (a name given twice): a caller bug.
    """
    source = Path(path)
    _check_schema(required, optional, optional_groups)
    records = _records(source, _read_text(source))
    try:
        header_line, header = next(records)
    except StopIteration:
        raise DataFileError(source, "no header line: the file is empty or holds only comments") from None
    columns = _check_header(source, header_line, header, required, optional, optional_groups)

    rows: list[list[float]] = []
    lines: list[int] = []
    for line, fields in records:
        if len(fields) != len(columns):
            # Too few fields: name the first column without a value; too many: no column to name.
            missing = columns[len(fields)] if len(fields) < len(columns) else None
            raise DataFileError(
                source, f"{len(fields)} fields, but the header has {len(columns)} columns", row=line, column=missing
            )
        rows.append([_parse_number(source, line, name, field, max_magnitude) for name, field in zip(columns, fields)])
        lines.append(line)
    if not rows:
        raise DataFileError(source, "no data rows after the header", row=header_line)

    table = Table(path=source, columns=columns, data=np.array(rows, dtype=float), line_numbers=np.array(lines))
    if reject_duplicate_rows:
        _reject_duplicate_rows(table)
    return table


def write_table(
    path: StrPath,
    columns: Sequence[str],
    data: object,
    comments: Sequence[str] = (),
    protect: Iterable[StrPath] = (),
) -> None:
    """Write a numeric table that `read_table` reads back bit-for-bit, atomically.

    Args:
        path: the output CSV file.
        columns: column names, unique, without commas, quotes or line breaks.
        data: (n_rows, len(columns)) finite numbers, SI units; at least one row.
        comments: lines written first as `# ...`, e.g. provenance and units; a comment with
            line breaks becomes several comment lines.
        protect: input files that `path` must not be (see `atomic_write_bytes`).

    Each value is written as the shortest decimal that parses back to the same double
    (`repr`), which is as exact as 17 significant digits and keeps `0.1` readable as `0.1`.

    Raises:
        InvalidInputError: bad column names, wrong shape, non-numeric or non-finite data; no
            file is touched.
        OutputPathError: see `atomic_write_bytes`.
    """
    atomic_write_text(path, table_text(columns, data, comments, what=f"table data for {path}"), protect=protect)


def table_text(columns: Sequence[str], data: object, comments: Sequence[str] = (), what: str = "table data") -> str:
    """The text `write_table` writes (same arguments and InvalidInputError), for an `OutputSet.stage`."""
    names = tuple(columns)
    _check_column_names(names)
    try:
        array = np.asarray(data, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{what}: not numeric ({exc})") from None
    if array.ndim != 2 or array.shape[1] != len(names) or array.shape[0] == 0:
        raise InvalidInputError(
            f"{what}: shape {array.shape}, expected (n_rows >= 1, {len(names)} columns)"
        )
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        row, col = (int(i) for i in bad[0])
        raise InvalidInputError(
            f"{what}: row {row}, column '{names[col]}' is {array[row, col]}, not a finite number"
        )

    lines = [_comment_line(part) for comment in comments for part in (comment.splitlines() or [""])]
    lines.append(",".join(names))
    lines.extend(",".join(format_float(value) for value in row) for row in array.tolist())
    return "\n".join(lines) + "\n"


def format_float(value: float) -> str:
    """The shortest decimal string that parses back to exactly the same double."""
    return repr(float(value))


# Strict decimal syntax: Python's float() would also take "1_000", "infinity" and " nan ".
_DECIMAL = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
# Universal newlines, but only those: str.splitlines() also splits on form feeds and U+2028,
# which would make our line numbers disagree with the user's editor.
_LINE_BREAK = re.compile(r"\r\n|\r|\n")


def _read_text(source: Path) -> str:
    try:
        raw = source.read_bytes()
    except FileNotFoundError:
        raise DataFileError(source, "file not found") from None
    except IsADirectoryError:
        raise DataFileError(source, "is a directory, expected a CSV file") from None
    except OSError as exc:
        raise DataFileError(source, f"cannot read: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DataFileError(source, f"not UTF-8 text (byte 0x{raw[exc.start]:02x})", row=line) from None


def _records(source: Path, text: str) -> Iterator[tuple[int, list[str]]]:
    """(line number, stripped fields) of each non-comment, non-blank line."""
    for line_number, line in enumerate(_LINE_BREAK.split(text), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        # One line at a time, so that a stray quote cannot swallow the following lines and
        # shift every line number after it.
        try:
            fields = next(csv.reader([line], strict=True))
        except csv.Error as exc:
            raise DataFileError(source, f"malformed CSV: {exc}", row=line_number) from None
        yield line_number, [field.strip() for field in fields]


def _check_schema(required: Sequence[str], optional: Sequence[str], groups: Sequence[Sequence[str]]) -> None:
    if isinstance(required, str) or isinstance(optional, str) or any(isinstance(g, str) for g in groups):
        raise ValueError("column lists must be sequences of names, not strings")
    names = [*required, *optional, *(name for group in groups for name in group)]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"table schema names {', '.join(repeated)} more than once")


def _check_header(
    source: Path,
    line: int,
    header: list[str],
    required: Sequence[str],
    optional: Sequence[str],
    groups: Sequence[Sequence[str]],
) -> tuple[str, ...]:
    for position, name in enumerate(header, start=1):
        if not name:
            raise DataFileError(source, f"header field {position} is empty", row=line)
    present: set[str] = set()
    for name in header:
        if name in present:
            raise DataFileError(source, "column name appears twice in the header", row=line, column=name)
        present.add(name)

    known = {*required, *optional, *(name for group in groups for name in group)}
    unknown = [name for name in header if name not in known]
    missing = [name for name in required if name not in present]
    # A single header field holding ';' or a tab is a file with another separator.
    hint = " (fields must be separated by commas)" if len(header) == 1 and re.search(r"[;\t]", header[0]) else ""
    if missing:
        message = f"missing required columns: {', '.join(missing)}"
        if unknown:
            message += f"; unknown columns: {', '.join(unknown)} (is this file for another model?)"
        raise DataFileError(source, message + hint, row=line, column=missing[0])
    if unknown:
        expected = ", ".join([*required, *optional, *(name for group in groups for name in group)])
        raise DataFileError(
            source,
            f"unknown columns: {', '.join(unknown)} (is this file for another model?); expected columns: {expected}"
            + hint,
            row=line,
            column=unknown[0],
        )
    for group in groups:
        given = [name for name in group if name in present]
        absent = [name for name in group if name not in present]
        if given and absent:
            raise DataFileError(
                source,
                f"columns {', '.join(group)} go together: {', '.join(absent)} missing",
                row=line,
                column=absent[0],
            )
    return tuple(header)


def _parse_number(source: Path, line: int, column: str, field: str, max_magnitude: float = math.inf) -> float:
    if _DECIMAL.fullmatch(field):
        value = float(field)
        if not math.isfinite(value):
            raise DataFileError(source, f"value {field} is too large for a double", row=line, column=column)
        if abs(value) > max_magnitude:
            raise DataFileError(source, f"value {field} is implausibly large: |value| > {max_magnitude:g} "
                                        "(SI units: m, rad); it would overflow the computation", row=line, column=column)
        return value
    if not field:
        message = "empty field"
    elif _NON_FINITE.fullmatch(field):
        message = f"value '{field}' is not finite"
    else:
        message = f"'{field}' is not a number"
    raise DataFileError(source, message, row=line, column=column)


def _reject_duplicate_rows(table: Table) -> None:
    # Keyed on values, not text: "1.0" and "1" are the same measurement.
    first_line: dict[tuple[float, ...], int] = {}
    for values, line in zip(table.data.tolist(), table.line_numbers.tolist()):
        earlier = first_line.setdefault(tuple(values), line)
        if earlier != line:
            raise DataFileError(table.path, f"row repeats line {earlier}", row=line)


def _check_column_names(names: tuple[str, ...]) -> None:
    for name in names:
        if not isinstance(name, str) or not name or name != name.strip() or re.search(r"[,\"\r\n]", name):
            raise InvalidInputError(f"column name {name!r}: must be non-empty, unpadded, without , \" or line breaks")
        if name.startswith("#"):
            raise InvalidInputError(f"column name {name!r}: a header starting with '#' would read as a comment")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise InvalidInputError(f"column names given more than once: {', '.join(repeated)}")


def _comment_line(text: str) -> str:
    return f"# {text}" if text else "#"


# --------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------


def poses_from_table(table: Table, quat_tol: float = 1e-6) -> list[pin.SE3]:
    """The pose of each row of a table with the `POSE_COLUMNS`, as placements.

    Each quaternion must have unit norm within `quat_tol` (dimensionless) and is then
    normalized: a looser quaternion is a corrupted or mislabelled column, not rounding.

    Raises:
        DataFileError: a pose column is missing, or a quaternion's norm is off by more than
            `quat_tol`, naming its line.
    """
    if not (math.isfinite(quat_tol) and quat_tol > 0):
        raise ValueError(f"quat_tol must be a positive finite number, got {quat_tol}")
    missing = [name for name in POSE_COLUMNS if not table.has_column(name)]
    if missing:
        raise DataFileError(table.path, f"missing pose columns: {', '.join(missing)}", column=missing[0])
    xyzquat = np.column_stack([table.column(name) for name in POSE_COLUMNS])
    norms = np.linalg.norm(xyzquat[:, 3:], axis=1)
    off = np.flatnonzero(np.abs(norms - 1.0) > quat_tol)
    if off.size:
        row = int(off[0])
        raise table.error(row, f"quaternion (qx, qy, qz, qw) norm {norms[row]:.6g} is not 1 (tolerance {quat_tol:g})")
    xyzquat[:, 3:] /= norms[:, np.newaxis]
    return [pin.XYZQUATToSE3(row) for row in xyzquat]


def pose_rows(poses: Iterable[pin.SE3]) -> np.ndarray:
    """(n, 7) rows `x, y, z, qx, qy, qz, qw` (m, unit quaternion) of `poses`, in `POSE_COLUMNS` order.

    q and -q are the same rotation; the sign is fixed to qw > 0 (and, when qw = 0, to a
    positive first non-zero vector component) so that equal poses give equal rows, and files
    can be compared and checked for duplicates.
    """
    rows = np.array([pin.SE3ToXYZQUAT(pose) for pose in poses], dtype=float).reshape(-1, 7)
    quaternions = rows[:, 3:]
    vector = quaternions[:, :3]
    leading = vector[np.arange(len(rows)), np.argmax(vector != 0.0, axis=1)] if len(rows) else np.empty(0)
    flip = (quaternions[:, 3] < 0.0) | ((quaternions[:, 3] == 0.0) & (leading < 0.0))
    quaternions[flip] *= -1.0
    rows += 0.0  # turns -0.0 into 0.0, so files never show "-0.0"
    return rows


# --------------------------------------------------------------------------------------------
# Pairing a URDF with its closures file (the loader checks it; urdf_io writes it)
# --------------------------------------------------------------------------------------------

# One comment line before the root element. The digest is what the loader checks; the words
# are for a person opening the file.
_PAIRING = re.compile(rb"<!-- m3t1r pair: closures sha256 ([0-9a-f]{64})\b[^>]*-->[ \t]*(?:\r?\n)?")


_DECLARATION = re.compile(rb"\A(?:\xef\xbb\xbf)?\s*<\?xml[^>]*\?>[ \t]*(?:\r?\n)?")


def recorded_closures_sha256(urdf: bytes) -> str | None:
    """The closures sha256 a paired URDF records, or None for a URDF that records none.

    Raises ModelFileError (path unknown here: "URDF") if it records two different ones.
    """
    digests = {match[1].decode("ascii") for match in _PAIRING.finditer(urdf)}
    if len(digests) > 1:
        raise ModelFileError("URDF", "records two different closures sha256 digests")
    return digests.pop() if digests else None


def with_closures_sha256(urdf: bytes, digest: str | None) -> bytes:
    """`urdf` with its pairing comment set to `digest` (removed when None), placed after the XML declaration."""
    stripped = _PAIRING.sub(b"", urdf)
    if digest is None:
        return stripped
    if not re.fullmatch(r"[0-9a-f]{64}", digest):
        raise ValueError(f"not a sha256 hex digest: {digest!r}")
    comment = (b"<!-- m3t1r pair: closures sha256 " + digest.encode("ascii")
               + b" (this URDF loads only with the closures file of that sha256; models/README.md) -->\n")
    declaration = _DECLARATION.match(stripped)
    at = declaration.end() if declaration else 0
    if declaration and not stripped[:at].endswith(b"\n"):
        comment = b"\n" + comment
    return stripped[:at] + comment + stripped[at:]
