"""Reading instruments' text exports: lines with their numbers, delimiters, numbers with a
decimal comma, empty cells for what was not seen."""

from __future__ import annotations

import math
import re
from pathlib import Path

from m3t1r.errors import DataFileError

__all__ = ["numbered_lines", "detect_delimiter", "split_fields", "parse_number", "is_number"]

_NUMBER = re.compile(r"^[+-]?(\d+([.,]\d*)?|[.,]\d+)([eE][+-]?\d+)?$")


def numbered_lines(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, text without its line break) of every line; DataFileError when the
    file is missing or not text (naming the encodings tried)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataFileError(path, f"cannot read: {exc.strerror or exc}") from None
    if b"\x00" in raw[:4096]:
        raise DataFileError(
            path, "a binary file, not a text export (C3D files and ROS 2 bags are read with --format c3d / rosbag)"
        )
    for encoding in ("utf-8-sig", "cp1252"):
        try:
            text = raw.decode(encoding)
            break
        except UnicodeDecodeError:
            continue
    else:  # pragma: no cover - cp1252 fails only on five undefined bytes
        raise DataFileError(path, "not UTF-8 or Windows-1252 text")
    return list(enumerate(text.splitlines(), start=1))


def detect_delimiter(header: str) -> str:
    """The header's field separator: tab, ';' (then commas are decimal commas) or ','."""
    for candidate in ("\t", ";"):
        if candidate in header:
            return candidate
    return ","


def split_fields(text: str, delimiter: str) -> list[str]:
    """The fields of one line, stripped of blanks and of one pair of surrounding quotes."""
    fields = [f.strip() for f in text.split(delimiter)]
    return [f[1:-1].strip() if len(f) >= 2 and f[0] == f[-1] == '"' else f for f in fields]


def is_number(text: str) -> bool:
    """Whether `text` is a decimal number (a decimal comma allowed)."""
    return bool(_NUMBER.match(text.strip()))


def parse_number(path: Path, line: int, column: str, text: str, decimal_comma: bool = False) -> float:
    """A field as a float; an empty field is NaN (a sample not seen). DataFileError naming the
    line and column for anything else that is not a finite number."""
    field = text.strip()
    if not field:
        return math.nan
    if decimal_comma:
        field = field.replace(",", ".")
    if not _NUMBER.match(field):
        raise DataFileError(path, f"'{text}' is not a number", row=line, column=column)
    return float(field)
