"""Temporary files beside their targets: named so that a later run can recognise them, locked by
their writer while it lives, written and fsynced before any rename, removed at exit, and swept from
a folder only when the run that wrote them is provably gone."""

from __future__ import annotations

import atexit
import datetime as _dt
import errno
import hashlib
import os
import re
import secrets
import socket
import stat
import sys
import time
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from pathlib import Path

from m3t1r.errors import M3t1rError, OutputPathError
from m3t1r.io.pairing import CLOSURES_SUFFIX, closures_match, recorded_closures_sha256
from m3t1r.io.paths import StrPath

try:
    import fcntl
except ImportError:  # Windows: no advisory locks, so no leftover is ever provably abandoned
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "pending_temporaries",
    "print_notice",
    "temporary_path",
    "folder_lock",
    "live_writer",
    "remove_live_temporaries",
    "release_stale_claims",
]

# A temporary file is `.<final name>.m3t1r-<pid>-<random hex>.tmp` in the target's folder: hidden,
# recognisable and on the target's filesystem (so the final rename is atomic). When that name would
# exceed the folder's NAME_MAX, the final name is cut short and a digest of it appended
# (`~<digest>` before `.tmp`), so that every legal output name has a temporary name.
# The pid is informational only: a writer holds an exclusive flock on each of its temporary files
# from creation to rename, and a file is another run's leftover only when that lock can be taken.
# A pid cannot say that: pids repeat, and a run in another container or on another host sharing
# the folder has a pid that means nothing here, while a flock lives exactly as long as its holder.
_TEMPORARY = re.compile(r"^\.(?P<name>.*)\.m3t1r-(?P<pid>\d+)-(?P<token>[0-9a-f]+)(?:~(?P<digest>[0-9a-f]{16}))?\.tmp$")
_DEFAULT_NAME_MAX = 255
_CLAIM_PREFIX = b"m3t1r run in progress: "
_FOLDER_LOCK_NAME = ".m3t1r.lock"  # only where a folder itself cannot be flocked (NFS)
_FOLDER_LOCK_TIMEOUT = 10.0  # [s]; every holder keeps it for milliseconds

# Temporary files of this process not yet renamed; removed at exit if an error skipped that.
_LIVE_TEMPORARIES: set[Path] = set()
# The open (locked) descriptors of the claimed ones among them.
_LIVE_DESCRIPTORS: dict[Path, int] = {}


def print_notice(message: str) -> None:
    """Default `announce` of OutputSet: `m3t1r: <message>` on stderr."""
    print(f"m3t1r: {message}", file=sys.stderr, flush=True)


def temporary_path(target: StrPath) -> Path:
    """A fresh recognisable temporary name for `target`, in the target's folder, within NAME_MAX."""
    target = Path(target)
    tail = f".m3t1r-{os.getpid()}-{secrets.token_hex(6)}"
    name = f".{target.name}{tail}.tmp"
    limit = _name_max(target.parent)
    if len(os.fsencode(name)) <= limit:
        return target.parent / name
    digest = _name_digest(target.name)
    room = max(0, limit - len(os.fsencode(f".{tail}~{digest}.tmp")))
    prefix = os.fsencode(target.name)[:room].decode("utf-8", errors="ignore")
    return target.parent / f".{prefix}{tail}~{digest}.tmp"


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return _DEFAULT_NAME_MAX


def _name_digest(name: str) -> str:
    return hashlib.sha256(os.fsencode(name)).hexdigest()[:16]


def _is_temporary_of(match: re.Match, name: str) -> bool:
    if match["digest"] is None:
        return match["name"] == name
    return match["digest"] == _name_digest(name) and os.fsencode(name).startswith(os.fsencode(match["name"]))


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
        if match and _is_temporary_of(match, target.name):
            try:
                found.append((entry.stat(follow_symlinks=False).st_mtime, target.parent / entry.name))
            except OSError:
                continue
    return [path for _, path in sorted(found)]


# -- locks ------------------------------------------------------------------------------------------
@contextmanager
def folder_lock(folder: StrPath, timeout: float = _FOLDER_LOCK_TIMEOUT) -> Iterator[None]:
    """Hold `folder`'s exclusive lock: whoever sweeps it or claims an output in it holds this.

    The folder itself is flocked; where it cannot be (a directory on NFS), a hidden `.m3t1r.lock`
    file in it is. Raises OutputPathError if another run holds it for `timeout` seconds [s].
    Without advisory locks (Windows) the block runs unlocked.
    """
    folder = Path(folder)
    descriptor = _lockable_descriptor(folder)
    try:
        if descriptor is not None:
            _flock_within(descriptor, folder, timeout)
        yield
    finally:
        if descriptor is not None:
            os.close(descriptor)  # releases the lock


def _lockable_descriptor(folder: Path) -> int | None:
    if fcntl is None:
        return None
    try:
        descriptor: int | None = os.open(folder, os.O_RDONLY)
    except OSError:
        descriptor = None  # a folder we may write but not read: its lock file instead
    if descriptor is not None:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
            fcntl.flock(descriptor, fcntl.LOCK_UN)
            return descriptor
        except BlockingIOError:
            return descriptor  # held by another run right now: lockable, _flock_within waits
        except OSError:
            os.close(descriptor)
    try:
        return os.open(folder / _FOLDER_LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        return None  # neither lockable: run unlocked rather than refuse every write there


def _flock_within(descriptor: int, folder: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise OutputPathError(
                    folder, f"another m3t1r run has held this folder's lock for over {timeout:g} s; nothing was written"
                ) from None
            time.sleep(0.01)
        except OSError:
            return  # the filesystem refuses locks after all: unlocked, as on Windows


def _holder(path: Path) -> bool | None:
    """Whether a live process holds `path`'s flock: True, False (provably nobody), None (cannot tell)."""
    if fcntl is None:
        return None
    descriptor = None
    for flags in (os.O_RDWR, os.O_RDONLY):
        try:
            descriptor = os.open(path, flags | os.O_NOFOLLOW | getattr(os, "O_NONBLOCK", 0))
            break
        except OSError as exc:
            if exc.errno in (errno.ENOENT, errno.ELOOP, errno.EISDIR):
                return False  # gone already, a symlink or a directory: nobody writes through it
    if descriptor is None:
        return None
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return False
    except BlockingIOError:
        return True
    except OSError:
        return None
    finally:
        os.close(descriptor)  # releases the probe's lock, if taken


def live_writer(target: StrPath) -> str | None:
    """Who is writing `target` now, if another live process is: its own description, or None.

    Call with `target`'s folder lock held (`folder_lock`), so that nobody claims it meanwhile.
    """
    for path in pending_temporaries(target):
        if path in _LIVE_TEMPORARIES or _holder(path) is not True:
            continue
        try:
            with open(path, "rb") as stream:
                head = stream.read(400)
        except OSError:
            head = b""
        if head.startswith(_CLAIM_PREFIX):
            return head[len(_CLAIM_PREFIX) :].split(b"\n", 1)[0].decode("utf-8", errors="replace")
        match = _TEMPORARY.match(path.name)
        return f"pid {match['pid'] if match else '?'}, now renaming its outputs into place"
    return None


def release_stale_claims(target: StrPath, own: Collection[Path]) -> None:
    """Remove this process's claims on `target` other than `own`: left by an earlier command of the
    same process that failed between its check and its commit (an API caller, a notebook). Within
    one process the latest claim wins; two threads must not write the same file."""
    for path in pending_temporaries(target):
        if path in _LIVE_TEMPORARIES and path not in own:
            release_temporary(path, _LIVE_DESCRIPTORS.get(path), remove=True)


def claim_description() -> str:
    """This run, as another run's refusal names it: pid, host, start time and command."""
    command = " ".join(["m3t1r", *sys.argv[1:]]) if sys.argv[1:] else "the m3t1r API"
    started = _dt.datetime.fromtimestamp(_STARTED).isoformat(timespec="seconds")
    return f"pid {os.getpid()} on {socket.gethostname()}, started {started}: {command}"[:300]


_STARTED = time.time()


# -- sweeping ---------------------------------------------------------------------------------------
def sweep_locked(folder: Path) -> list[str]:
    """Deal with temporary files left in `folder` by killed m3t1r runs; return what was done.

    Call with `folder_lock(folder)` held (`OutputSet.check` does, and announces the notes). A
    leftover is a recognisable temporary file whose writer's lock can be taken: no live process,
    in this container or another, on this host or another sharing the folder, holds it. A
    staged closures file whose URDF (`NAME.urdf` beside it) records its sha256 while
    `NAME.closures.yaml` does not match is the second half of an interrupted pair commit: it is
    renamed into place, completing that commit. Every other leftover is removed. Files of
    running processes, and files whose lock cannot be probed, are left alone.
    """
    notes: list[str] = []
    try:
        names = sorted(entry.name for entry in os.scandir(folder))
    except OSError:
        return notes
    for name in names:
        match = _TEMPORARY.match(name)
        leftover = folder / name
        if not match or leftover in _LIVE_TEMPORARIES or _holder(leftover) is not False:
            continue
        target = _target_of(match, folder, names)
        try:
            if target is not None and target.name.endswith(CLOSURES_SUFFIX) and _completes_pair(leftover, target):
                os.replace(leftover, target)
                notes.append(f"completed the interrupted write of {target} (its URDF already named it)")
            else:
                os.unlink(leftover)
                notes.append(f"removed {leftover}, a temporary file left by an interrupted run")
        except OSError as exc:
            notes.append(f"could not clean up {leftover}: {exc.strerror or exc}")
    return notes


def _target_of(match: re.Match, folder: Path, names: list[str]) -> Path | None:
    """The final path a temporary file was for; for a shortened name, the folder entry (or the
    closures file of a URDF there) whose name it was cut from, None when none is."""
    if match["digest"] is None:
        return folder / match["name"]
    candidates = [*names, *(n[: -len(".urdf")] + CLOSURES_SUFFIX for n in names if n.endswith(".urdf"))]
    return next((folder / n for n in candidates if _is_temporary_of(match, n)), None)


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


# -- claiming and writing ---------------------------------------------------------------------------
def claim_temporary(target: Path) -> tuple[Path, int]:
    """Create a fresh temporary file for `target`, lock it and name this run in it: (path, descriptor).

    Call with the folder's lock held (`folder_lock`), so that no sweep sees the file between its
    creation and its lock. The lock lasts until the descriptor is closed (`release_temporary`);
    the file is registered for removal at exit.
    """
    temporary = temporary_path(target)
    try:
        descriptor = os.open(temporary, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    except OSError as exc:
        raise OutputPathError(
            target, f"cannot create a file in {target.parent}: {exc.strerror or exc}; nothing was written"
        ) from None
    _LIVE_TEMPORARIES.add(temporary)
    _LIVE_DESCRIPTORS[temporary] = descriptor
    try:
        if fcntl is not None:
            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                pass  # no locks on this filesystem: other runs cannot tell, so they keep the file
        _write_all(descriptor, _CLAIM_PREFIX + claim_description().encode("utf-8", errors="replace") + b"\n")
    except BaseException as exc:
        release_temporary(temporary, descriptor, remove=True)
        if isinstance(exc, OSError):
            raise OutputPathError(
                target, f"cannot write in {target.parent}: {exc.strerror or exc}; nothing was written"
            ) from None
        raise
    return temporary, descriptor


def write_claimed(target: Path, temporary: Path, descriptor: int, data: bytes) -> None:
    """Replace the content of a claimed temporary file with `data`, flushed to disk; give it the
    permission bits of an existing `target` (a new target keeps the umask's). On failure the file
    is emptied again (a full disk gets its space back) and OutputPathError names `target`."""
    try:
        mode: int | None = stat.S_IMODE(target.stat().st_mode)
    except OSError:
        mode = None
    try:
        os.ftruncate(descriptor, 0)
        os.lseek(descriptor, 0, os.SEEK_SET)
        _write_all(descriptor, data)
        os.fsync(descriptor)
        if mode is not None:
            os.chmod(temporary, mode)
    except OSError as exc:
        try:
            os.ftruncate(descriptor, 0)
        except OSError:
            pass
        raise OutputPathError(target, f"write failed, file left unchanged: {exc.strerror or exc}") from None


def release_temporary(temporary: Path, descriptor: int | None, *, remove: bool) -> None:
    """Close a claimed file's descriptor (its lock goes with it) and, if `remove`, delete the file."""
    if remove:
        _remove_quietly(temporary)
    _LIVE_TEMPORARIES.discard(temporary)
    _LIVE_DESCRIPTORS.pop(temporary, None)
    if descriptor is not None:
        try:
            os.close(descriptor)
        except OSError:
            pass


def _write_all(descriptor: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(descriptor, view) :]


@atexit.register
def remove_live_temporaries() -> None:
    """Remove every temporary file of this process not yet renamed and release its lock (at exit,
    and at the end of each command-line run, so that nothing outlives a failed command)."""
    for path in list(_LIVE_TEMPORARIES):
        release_temporary(path, _LIVE_DESCRIPTORS.get(path), remove=True)
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
