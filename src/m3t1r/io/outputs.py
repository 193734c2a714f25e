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
from pathlib import Path

from m3t1r.errors import OutputPathError
from m3t1r.io.pairing import paired_closures_path
from m3t1r.io.paths import STDOUT, StrPath, _identity, _same_identity
from m3t1r.io.signals import _signals_held
from m3t1r.io.strict_json import json_text
from m3t1r.io.temporaries import (
    _LIVE_TEMPORARIES,
    _fsync_directory,
    _remove_quietly,
    _write_temporary,
    print_notice,
    sweep,
    temporary_path,
)

__all__ = ["Output", "OutputSet", "atomic_write_bytes", "atomic_write_text"]

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


def _check_folder(output: Output, folder: Path) -> None:
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise OutputPathError(output.path, f"{output.label}: folder {folder} {what}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(output.path, f"{output.label}: folder {folder} is not writable")


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
