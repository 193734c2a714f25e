"""Pairing a URDF with its closures file: the pair's file names and the sha256 of the closures file
that a paired URDF records in a comment (the loader checks it; urdf_io and `OutputSet` write it).

The digest written is `closures_sha256`: of the closures file's content as parsed (a canonical JSON
of the YAML document), so that a comment, a re-indent or CRLF line ends from a Windows checkout
keep the pair, and only a change of meaning breaks it. `closures_match` also accepts the sha256 of
the raw bytes, which URDFs written before recorded."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import yaml

from m3t1r.errors import ModelFileError
from m3t1r.io.paths import StrPath

__all__ = [
    "CLOSURES_SUFFIX",
    "closures_match",
    "closures_sha256",
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


# Versioned, so that a later canonical form can never collide with this one.
_CONTENT_TAG = b"m3t1r closures content v1\n"


def closures_sha256(data: bytes) -> str:
    """The digest a URDF records for closures file bytes `data`: the sha256 of its YAML document as
    parsed (mapping keys sorted, numbers by value: `0.50` is `0.5`), so comments, layout, key order
    and line ends do not change it; the raw bytes' sha256 when `data` is not a YAML document."""
    content = _canonical_content(data)
    return sha256_bytes(data) if content is None else sha256_bytes(_CONTENT_TAG + content)


def closures_match(data: bytes, recorded: str) -> bool:
    """Whether closures file bytes `data` are the ones a URDF recording `recorded` was written with:
    the same content as parsed (`closures_sha256`), or the same bytes (a pair written before the
    digest covered the content)."""
    return recorded in (sha256_bytes(data), closures_sha256(data))


def _canonical_content(data: bytes) -> bytes | None:
    try:
        document = yaml.safe_load(data.decode("utf-8-sig"))
        return json.dumps(document, sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=repr).encode(
            "utf-8"
        )
    except (UnicodeDecodeError, yaml.YAMLError, TypeError, ValueError, RecursionError):
        return None  # not a document the loader would read: only the raw bytes can match


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
    comment = (
        b"<!-- m3t1r pair: closures sha256 "
        + digest.encode("ascii")
        + b" (this URDF loads only with the closures file of that content; models/README.md) -->\n"
    )
    declaration = _DECLARATION.match(stripped)
    at = declaration.end() if declaration else 0
    if declaration and not stripped[:at].endswith(b"\n"):
        comment = b"\n" + comment
    return stripped[:at] + comment + stripped[at:]
