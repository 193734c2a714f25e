"""Outputs as a unit: atomic writes that cannot clobber an input, and `OutputSet`, every output of
one command checked before any work and committed together.

Every output goes through an `OutputSet` (`atomic_write_bytes` is a set of one), so an
interrupted run or a full disk never leaves a half-written calibration behind, and its inputs
keep the nominal model and the measurement files from being overwritten by a mistyped output path.
"""

from __future__ import annotations

import os
import stat
import sys
from collections.abc import Iterable
from contextlib import ExitStack
from pathlib import Path
from typing import Protocol, overload

from m3t1r.errors import OutputPathError
from m3t1r.io.pairing import paired_closures_path
from m3t1r.io.paths import STDOUT, StrPath, _identity, _same_identity
from m3t1r.io.signals import deliver_signals, signals_deferred
from m3t1r.io.strict_json import json_text
from m3t1r.io.temporaries import (
    _LIVE_TEMPORARIES,
    _fsync_directory,
    _remove_quietly,
    claim_temporary,
    folder_lock,
    live_writer,
    print_notice,
    release_stale_claims,
    release_temporary,
    sweep_locked,
    temporary_path,
    write_claimed,
)

__all__ = ["Output", "OutputSet", "atomic_write_bytes", "atomic_write_text", "interrupted_outputs"]


class _MachinePair(Protocol):
    """What `stage_machine` writes: a `Mechanism` (named by its role, so io does not import model)."""

    def pair_bytes(self, urdf: Path, closures: Path) -> tuple[bytes, bytes]: ...


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


def interrupted_outputs(exc: BaseException) -> str:
    """What an interruption (Ctrl-C, SIGTERM) left written, in words: every output of a commit the
    signal arrived during (`OutputSet.commit` names them on the exception), or none."""
    written = getattr(exc, "outputs_written", None)
    if written:
        return f"it arrived while the outputs were renamed into place, and every one is written: {', '.join(written)}"
    return "outputs not yet in place were not written"


class Output:
    """One declared output of an `OutputSet`. `path` is as given; `label` names it in messages."""

    def __init__(self, path: StrPath, label: str, pair_of: "Output | None" = None) -> None:
        self.path = Path(path) if str(path) != STDOUT else None
        self.label = label
        self.pair_of = pair_of  # for a closures file: the URDF output it belongs with
        self.closures: Output | None = None  # for a machine URDF: its closures output
        self.kind = "stdout" if self.path is None else "file"  # "file", "stdout" or "special"
        self.temporary: Path | None = None  # claimed at check: this run's locked file beside the target
        self.descriptor: int | None = None  # the temporary's open descriptor, which holds its lock
        self.staged = False
        self.create_folder = False  # a missing folder is created (a plots folder), removed again if unused
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
        with outputs:
            outputs.check()                                   # OutputPathError now, nothing written
            ...compute...
            outputs.stage_machine(machine, calibrated); outputs.stage_json(report, document)
            outputs.commit()                                  # every output lands, or none changes

    `check` refuses (with `OutputPathError`, exit status 2 in the CLI): two outputs that are the
    same file, or an output that is an input, compared through symlinks and hard links; an output
    folder that does not exist or is not writable; an output that is a directory, a socket or a
    block device, or an existing file that cannot be replaced (immutable); a machine URDF given as
    `-` or as a pipe or device (a machine is two files); and an output that another live m3t1r run
    is writing (naming that run). It sweeps each output folder for temporary files left by killed
    runs (see `temporaries.sweep_locked`) and then claims every output: a temporary file beside each target, created
    and exclusively locked under the folder's lock, so that a second writer of the same file is
    refused at its own `check` and no sweep mistakes this run's files for leftovers. (Within one
    process the latest claim wins: a command that failed before its commit leaves no obstacle.)

    `stage*` writes each output's bytes to its temporary file at once (a full disk shows then,
    before anything is replaced). `commit` then renames them over their targets with catchable
    signals held back, auxiliary outputs first and each machine URDF last but one: the URDF rename
    is a pair's commit point, and its closures file is renamed right after. A URDF records its
    closures file's sha256 and the loader also accepts the staged closures file of that hash, so a
    kill at any instant leaves a loadable pair, old or new (models/README.md). A rename that fails
    puts back every output already renamed (each old file is kept as a hard link until the end).
    `-` (stdout) and existing pipes and character devices are written through at commit.

    Used as a context manager, an exception or caught signal inside the block removes every
    temporary file (and a folder `check` created); `discard()` does the same explicitly.
    """

    def __init__(self, inputs: Iterable[StrPath | None] = (), *, announce=print_notice) -> None:
        self.inputs: list[Path] = [Path(p) for p in inputs if p is not None and str(p) != STDOUT]
        self.outputs: list[Output] = []
        self.announce = announce
        self.notes: list[str] = []
        self.committed = False
        self.created_folders: list[Path] = []  # by check, deepest last; removed by discard when empty

    # -- declaring --------------------------------------------------------------------------
    def add_input(self, path: StrPath | None) -> None:
        """Declare one more input file that no output may be."""
        if path is not None and str(path) != STDOUT:
            self.inputs.append(Path(path))

    @overload
    def add(self, path: StrPath, label: str = ..., *, create_folder: bool = ...) -> Output: ...
    @overload
    def add(self, path: None, label: str = ..., *, create_folder: bool = ...) -> None: ...
    def add(self, path: StrPath | None, label: str = "output", *, create_folder: bool = False) -> Output | None:
        """Declare an output file (`-` is stdout); None gives None, for optional outputs.

        `create_folder`: a missing folder (and its missing parents) is created by `check`, once
        every other check passed, and removed by `discard` if nothing landed in it.
        """
        if path is None:
            return None
        output = Output(path, label)
        output.create_folder = create_folder
        self.outputs.append(output)
        return output

    @overload
    def add_machine(self, urdf: StrPath, label: str = ..., closures: StrPath | None = ...) -> Output: ...
    @overload
    def add_machine(self, urdf: None, label: str = ..., closures: StrPath | None = ...) -> None: ...
    def add_machine(self, urdf: StrPath | None, label: str = "-o", closures: StrPath | None = None) -> Output | None:
        """Declare a machine: URDF `NAME.urdf` and its closures file (default `NAME.closures.yaml`).

        Returns the URDF's Output; its `.closures` is the closures file's. None gives None.
        """
        if urdf is None:
            return None
        if str(urdf) == STDOUT:
            raise OutputPathError(
                STDOUT, f"{label}: a machine is a URDF and its closures file; it cannot be written to standard output"
            )
        machine = Output(urdf, label)
        machine.closures = Output(
            paired_closures_path(urdf) if closures is None else closures, f"closures file of {label}", pair_of=machine
        )
        self.outputs += [machine, machine.closures]
        return machine

    def drop(self, output: Output | StrPath) -> None:
        """Withdraw a declared plain output that will not be written after all (its claim released)."""
        output = self._resolve(output)
        if output.closures is not None or output.pair_of is not None:
            raise ValueError(f"{output.name} is half of a machine pair; a pair is written whole")
        self._forget_temporary(output)
        self.outputs.remove(output)

    def output(self, path: StrPath) -> Output:
        """The declared Output for `path` (as given)."""
        for output in self.outputs:
            if (output.path is None and str(path) == STDOUT) or (output.path is not None and output.path == Path(path)):
                return output
        raise KeyError(f"{path} is not a declared output")

    # -- checking ---------------------------------------------------------------------------
    def check(self) -> None:
        """Refuse collisions, missing or read-only folders, unusable special files and outputs
        another live run is writing; sweep leftovers; claim every output (class docstring).

        Raises OutputPathError naming the output, by its label, and what it collides with.
        Calling it again (after `add_input`, say) checks again and claims only new outputs.
        """
        seen: list[tuple[Output, Path, tuple[int, int] | None]] = []
        folders: list[Path] = []
        stdout_user: Output | None = None
        for output in self.outputs:
            if output.path is None:
                if stdout_user is not None:
                    raise OutputPathError(
                        STDOUT, f"{output.label} and {stdout_user.label} both write to standard output"
                    )
                stdout_user = output
                continue
            self._classify(output)
            resolved, inode = _identity(output.path)
            for protected in self.inputs:
                if _same_identity(resolved, inode, *_identity(protected)):
                    raise OutputPathError(
                        output.path, f"{output.label}: refusing to overwrite the input file {protected}"
                    )
            for other, other_resolved, other_inode in seen:
                if _same_identity(resolved, inode, other_resolved, other_inode):
                    raise OutputPathError(
                        output.path,
                        f"{output.label} is the same file as {other.label} ({other.path}): "
                        "every output must be a different file",
                    )
            seen.append((output, resolved, inode))
            if output.kind == "file":
                _check_replaceable(output)
                folder = output.path.parent
                if folder not in folders:
                    _check_folder(output, folder)
                    folders.append(folder)
        try:
            self._claim(folders)
        except BaseException:
            self.discard()
            raise

    def _claim(self, folders: list[Path]) -> None:
        """Create missing folders, then under every output folder's lock: sweep, refuse outputs a
        live run is writing, and claim each unclaimed output."""
        for output in self.outputs:
            if output.create_folder and output.kind == "file" and not _target(output).parent.is_dir():
                self._create_folder(output)
        unclaimed = [o for o in self.outputs if o.kind == "file" and o.descriptor is None]
        notes: list[str] = []
        with ExitStack() as locks:
            for _, folder in sorted({_identity(f)[0]: f for f in folders}.items()):
                locks.enter_context(folder_lock(folder))  # in one global order: no two runs deadlock
            for folder in folders:
                notes += sweep_locked(folder)
            own = {o.temporary for o in self.outputs if o.temporary is not None}
            for output in unclaimed:
                target = _target(output)
                release_stale_claims(target, own)
                writer = live_writer(target)
                if writer is not None:
                    raise OutputPathError(
                        target,
                        f"{output.label}: another m3t1r run is writing this file in "
                        f"{target.parent} ({writer}); nothing was written: "
                        "wait for it to finish, or write elsewhere",
                    )
            for output in unclaimed:
                output.temporary, output.descriptor = claim_temporary(_target(output))
        self.notes += notes
        if self.announce is not None:
            for note in notes:
                self.announce(note)

    def _create_folder(self, output: Output) -> None:
        missing = []
        folder = _target(output).parent
        while not folder.exists() and folder != folder.parent:
            missing.append(folder)
            folder = folder.parent
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:
                continue
            except OSError as exc:
                raise OutputPathError(
                    output.path,
                    f"{output.label}: cannot create folder {folder}: {exc.strerror or exc}; nothing was written",
                ) from None
            self.created_folders.append(folder)

    def _classify(self, output: Output) -> None:
        path = _target(output)
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
                raise OutputPathError(
                    path,
                    f"{output.label} is a {'named pipe' if stat.S_ISFIFO(mode) else 'device'}; "
                    "a machine is a pair of regular files",
                )
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
        self._ensure_claimed(output)
        assert output.temporary is not None and output.descriptor is not None, "claimed above"
        write_claimed(_target(output), output.temporary, output.descriptor, payload)
        output.staged = True

    def stage_json(self, output: Output | StrPath | None, document: object) -> None:
        """Stage strict JSON (`json_text`); None output: nothing to do."""
        if output is not None:
            self.stage(output, json_text(document))

    def stage_machine(self, output: Output | StrPath, mechanism: _MachinePair) -> None:
        """Stage a machine pair from `mechanism.pair_bytes(urdf_name)` (a `Mechanism`)."""
        output = self._resolve(output)
        if output.closures is None:
            raise ValueError(f"{output.name} was not declared with add_machine")
        urdf_bytes, closures_bytes = mechanism.pair_bytes(_target(output), _target(output.closures))
        self.stage(output.closures, closures_bytes)
        self.stage(output, urdf_bytes)

    def _ensure_claimed(self, output: Output) -> None:
        if output.descriptor is None:  # staged without check: claim it now, under the folder lock
            with folder_lock(_target(output).parent):
                output.temporary, output.descriptor = claim_temporary(_target(output))

    # -- committing -------------------------------------------------------------------------
    def commit(self) -> list[str]:
        """Move every staged output into place (order in the class docstring); return their names.

        Raises ValueError if an output was never staged (a caller bug), OutputPathError if a
        rename fails, after putting back every output it had already renamed; temporary files are
        removed on failure. A SIGINT, SIGTERM or SIGHUP that arrives during the renames is raised
        once every file is in place, with `outputs_written` (the names) set on the exception.
        """
        missing = [
            o.name
            for o in self.outputs
            if o.kind == "file" and (not o.staged or o.temporary is None or not o.temporary.exists())
        ]
        missing += [o.name for o in self.outputs if o.kind != "file" and o.data is None]
        if missing:
            self.discard()
            raise ValueError(f"outputs declared but never staged: {', '.join(missing)}")
        plain = [o for o in self.outputs if o.kind == "file" and o.closures is None and o.pair_of is None]
        pairs = [(o, o.closures) for o in self.outputs if o.closures is not None]
        order = [*plain, *(o for pair in pairs for o in pair)]  # a URDF, then its closures file
        folders = list(dict.fromkeys(_target(o).parent for o in order))
        with signals_deferred() as pending:
            try:
                with ExitStack() as locks:
                    for _, folder in sorted({_identity(f)[0]: f for f in folders}.items()):
                        locks.enter_context(folder_lock(folder))
                    self._rename_all(order)
            except BaseException:
                self.discard()
                raise
            self.committed = True
            for folder in folders:
                _fsync_directory(folder)
        written = [o.name for o in order]
        try:
            deliver_signals(pending)
        except BaseException as exc:  # every file is in place: say so, whatever stops the streams
            exc.outputs_written = written  # type: ignore[attr-defined]
            raise
        for output in self.outputs:
            if output.kind != "file":
                _write_through(output)
        return [o.name for o in self.outputs]

    def _rename_all(self, order: list[Output]) -> None:
        """Rename every temporary over its target; on a failure, put the renamed ones back and raise."""
        renamed: list[tuple[Output, Path | None | bool]] = []
        backups: list[Path] = []
        try:
            for output in order:
                backup = _keep_old(_target(output))
                if isinstance(backup, Path):
                    backups.append(backup)
                self._rename(output)
                renamed.append((output, backup))
        except OutputPathError as exc:
            if not renamed:
                raise
            lost = _put_back(renamed)
            restored = (
                f"the {len(renamed)} output(s) renamed before it were put back as they were"
                if not lost
                else f"could not put back the old {', '.join(lost)}"
            )
            raise OutputPathError(exc.path, f"{str(exc).removeprefix(f'{exc.path}: ')}; {restored}") from None
        finally:
            for backup in backups:
                _remove_quietly(backup)
                _LIVE_TEMPORARIES.discard(backup)

    def discard(self) -> None:
        """Remove every temporary file not yet renamed, and every folder `check` created that is empty."""
        for output in self.outputs:
            self._forget_temporary(output)
        for folder in reversed(self.created_folders):
            try:
                folder.rmdir()
            except OSError:
                pass  # not empty (something else landed there) or already gone: leave it
        self.created_folders = []

    def __enter__(self) -> "OutputSet":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is not None:
            self.discard()

    # -- helpers ----------------------------------------------------------------------------
    def _resolve(self, output: Output | StrPath) -> Output:
        return output if isinstance(output, Output) else self.output(output)

    def _rename(self, output: Output) -> None:
        assert output.temporary is not None, "committed outputs are staged"
        try:
            os.replace(output.temporary, _target(output))
        except OSError as exc:
            raise OutputPathError(
                output.path, f"{output.label}: could not move the new file into place: {exc.strerror or exc}"
            ) from None
        release_temporary(output.temporary, output.descriptor, remove=False)
        output.temporary, output.descriptor = None, None
        output.staged = False

    @staticmethod
    def _forget_temporary(output: Output) -> None:
        if output.temporary is not None:
            release_temporary(output.temporary, output.descriptor, remove=True)
            output.temporary, output.descriptor = None, None
            output.staged = False


def _target(output: Output) -> Path:
    """The path of a file, pipe or device output: every output but standard output, which these steps skip."""
    assert output.path is not None, f"{output.label} is standard output"
    return output.path


def _keep_old(target: Path) -> Path | None | bool:
    """A hard link to the file at `target` under a temporary name, to put it back if a later rename
    fails: its path; None when there is no old file; False when it cannot be kept (no hard links)."""
    if not os.path.lexists(target):
        return None
    backup = temporary_path(target)
    try:
        os.link(target, backup, follow_symlinks=False)
    except OSError:
        return False
    _LIVE_TEMPORARIES.add(backup)  # removed at exit even if this process dies in the commit
    return backup


def _put_back(renamed: list[tuple[Output, Path | None | bool]]) -> list[str]:
    """Undo renames, last first: the old file back from its link, a new one removed; what could not be."""
    lost = []
    for output, backup in reversed(renamed):
        try:
            if isinstance(backup, Path):
                os.replace(backup, _target(output))
            elif backup is None:
                os.unlink(_target(output))
            else:
                lost.append(output.name)
        except OSError:
            lost.append(output.name)
    return lost


def _check_replaceable(output: Output) -> None:
    """Refuse an existing regular file that no rename may replace: an immutable or append-only
    file, or one on a read-only file system. Judged without opening it: write access denied
    although the permission bits grant it (a read-only mode alone does not stop a rename)."""
    path = _target(output)
    try:
        info = os.lstat(path)
        if not stat.S_ISREG(info.st_mode) or os.access(path, os.W_OK, follow_symlinks=False):
            return
    except (OSError, NotImplementedError):
        return
    euid = os.geteuid() if hasattr(os, "geteuid") else -1
    if euid == 0 or (info.st_uid == euid and info.st_mode & stat.S_IWUSR):
        raise OutputPathError(
            path,
            f"{output.label}: cannot be replaced: write access denied by the file system "
            "(an immutable or append-only file, or a read-only mount)",
        )


def _check_folder(output: Output, folder: Path) -> None:
    if output.create_folder and not folder.exists():
        folder = next(p for p in folder.parents if p.exists() or p == p.parent)
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise OutputPathError(output.path, f"{output.label}: folder {folder} {what}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(output.path, f"{output.label}: folder {folder} is not writable")


def _write_through(output: Output) -> None:
    assert output.data is not None, "commit checked every stream has its data"
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
