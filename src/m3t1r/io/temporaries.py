"""Temporary files beside their targets: named so that a later run can recognise them, written and
fsynced before any rename, removed at exit, and swept from a folder when a killed run left them."""

from __future__ import annotations

import atexit
import os
import re
import secrets
import stat
import sys
from pathlib import Path

from m3t1r.errors import M3t1rError, OutputPathError
from m3t1r.io.pairing import CLOSURES_SUFFIX, closures_match, recorded_closures_sha256
from m3t1r.io.paths import StrPath

__all__ = ["pending_temporaries", "print_notice", "sweep", "temporary_path"]

# A temporary file is `.<final name>.m3t1r-<pid>-<random hex>.tmp` in the target's folder: hidden,
# recognisable, on the target's filesystem (so the final rename is atomic), and naming the process
# that wrote it, so that a later run can tell a leftover of a killed run from a live writer's file.
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.m3t1r-(?P<pid>\d+)-(?P<token>[0-9a-f]+)\.tmp$")


# Temporary files of this process not yet renamed; removed at exit if an error skipped that.
_LIVE_TEMPORARIES: set[Path] = set()


def print_notice(message: str) -> None:
    """Default `announce` of OutputSet and `sweep`: `m3t1r: <message>` on stderr."""
    print(f"m3t1r: {message}", file=sys.stderr, flush=True)


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
    if recorded is None or not closures_match(leftover.read_bytes(), recorded):
        return False
    try:
        return not closures_match(closures.read_bytes(), recorded)
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


@atexit.register
def _remove_live_temporaries() -> None:
    for path in list(_LIVE_TEMPORARIES):
        _remove_quietly(path)
    _LIVE_TEMPORARIES.clear()


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
