"""What an output path names: `-` for standard output, and whether two paths are the same file
(through symlinks, hard links and bind mounts), so an output never overwrites an input; how much
of an input is read, and why one is refused (`read_input`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeAlias

from m3t1r.errors import OutputPathError

__all__ = [
    "MAX_INPUT_BYTES",
    "STDOUT",
    "StrPath",
    "ensure_not_protected",
    "read_bounded",
    "read_input",
    "size_refusal",
]

StrPath: TypeAlias = "str | os.PathLike[str]"


STDOUT = "-"
"""The output path that means standard output (`-o -`)."""

MAX_INPUT_BYTES = 256 * 2**20
"""Largest input file read [bytes]: a million-row table is about 100 MB. Beyond it a read would
only exhaust the memory (a device such as /dev/zero never ends)."""


def read_bounded(path: StrPath, limit: int = MAX_INPUT_BYTES) -> bytes | None:
    """The bytes of `path`, or None when it holds more than `limit` bytes (read no further).
    OSError as `open` raises it (not found, a directory, no permission)."""
    with open(path, "rb") as stream:
        data = stream.read(limit + 1)
    return None if len(data) > limit else data


def size_refusal(limit: int = MAX_INPUT_BYTES) -> str:
    """The message for an input over `limit` bytes (`read_bounded` gave None)."""
    return f"larger than {limit / 2**20:g} MiB (or a device that never ends): not an input file of m3t1r"


def read_input(path: Path, refusal: Callable[[Path, str], Exception], expected: str = "a file") -> bytes:
    """The bytes of the input file `path` (`read_bounded`), or `refusal(path, why)` raised: file not
    found, a directory (`expected` names what was wanted), cannot read (the system's reason), or
    too large (`size_refusal`). refusal: the typed error of the caller's kind of file, such as
    `DataFileError` or `ModelFileError`."""
    try:
        data = read_bounded(path)
    except FileNotFoundError:
        raise refusal(path, "file not found") from None
    except IsADirectoryError:
        raise refusal(path, f"is a directory, expected {expected}") from None
    except OSError as exc:
        raise refusal(path, f"cannot read: {exc.strerror or exc}") from None
    if data is None:
        raise refusal(path, size_refusal())
    return data


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


def _identity(path: Path) -> tuple[Path, tuple[int, int] | None]:
    try:
        info = os.stat(path)
        inode = (info.st_dev, info.st_ino)
    except OSError:
        inode = None
    return _resolved(path), inode


def _same_identity(a: Path, a_inode, b: Path, b_inode) -> bool:
    return a == b or (a_inode is not None and a_inode == b_inode)


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
