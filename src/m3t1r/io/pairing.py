"""Pairing a URDF with its closures file: the pair's file names and the sha256 of the closures file
that a paired URDF records in a comment (the loader checks it; urdf_io and `OutputSet` write it)."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from m3t1r.errors import ModelFileError
from m3t1r.io.paths import StrPath

__all__ = [
    "CLOSURES_SUFFIX",
    "paired_closures_path",
    "recorded_closures_sha256",
    "sha256_bytes",
    "with_closures_sha256",
]

CLOSURES_SUFFIX = ".closures.yaml"


def paired_closures_path(urdf: StrPath) -> Path:
    """`NAME.urdf` -> `NAME.closures.yaml` beside it: only the final `.urdf` is replaced.

    `machine.v1.urdf` pairs with `machine.v1.closures.yaml`, never with `machine.closures.yaml`;
    a name without the `.urdf` suffix gets `.closures.yaml` appended.
    """
    path = Path(urdf)
    name = path.name
    stem = name[: -len(".urdf")] if name.lower().endswith(".urdf") and len(name) > len(".urdf") else name
    return path.with_name(stem + CLOSURES_SUFFIX)


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of `data`."""
    return hashlib.sha256(data).hexdigest()


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
