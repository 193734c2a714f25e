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

import csv
import math
import os
import re
import secrets
import stat
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeAlias

import numpy as np
import pinocchio as pin

from m3t1r.errors import DataFileError, InvalidInputError, OutputPathError

StrPath: TypeAlias = "str | os.PathLike[str]"

POSE_COLUMNS: tuple[str, ...] = ("x", "y", "z", "qx", "qy", "qz", "qw")
"""Columns of a pose: position in m, then the unit quaternion with its scalar part last."""


# --------------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------------


def ensure_not_protected(path: StrPath, protect: Iterable[StrPath]) -> None:
    """Raise OutputPathError if `path` is the same file as any path in `protect`.

    Two paths are the same file if they resolve to the same absolute path (symlinks followed) or
    name the same existing inode (hard links, bind mounts). Call it before a long computation to
    fail early; the atomic writers call it again anyway.
    """
    target = Path(path)
    for protected in protect:
        if _same_file(target, Path(protected)):
            raise OutputPathError(target, f"refusing to overwrite the input file {protected}")


def atomic_write_bytes(path: StrPath, data: bytes, protect: Iterable[StrPath] = ()) -> None:
    """Replace the file at `path` with `data` in one step, or leave it untouched.

    The bytes go to a temporary file in the target's directory (same filesystem, so the final
    `os.replace` is an atomic rename), are flushed and fsynced, then renamed over `path`: a
    reader sees the old content or the new, never a prefix. On any failure the temporary file
    is removed and an existing target is left as it was. A replaced file keeps its permission
    bits; a new one gets the process umask's. A symlink at `path` is replaced, not followed.

    Raises OutputPathError if `path` is one of `protect`, is a directory, its directory does
    not exist, or the write fails.
    """
    target = Path(path)
    ensure_not_protected(target, protect)
    if target.is_dir():
        raise OutputPathError(target, "is a directory, expected a file path")
    directory = target.parent
    if not directory.is_dir():
        raise OutputPathError(target, f"directory {directory} does not exist")
    try:
        mode: int | None = stat.S_IMODE(target.stat().st_mode)
    except OSError:
        mode = None
    # A hidden name next to the target keeps the rename on one filesystem; the random part
    # keeps concurrent writers of the same target from sharing a temporary file.
    temporary = directory / f".{target.name}.{secrets.token_hex(6)}.tmp"
    try:
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    except OSError as exc:
        raise OutputPathError(target, f"cannot create a temporary file in {directory}: {exc.strerror}") from exc
    try:
        with os.fdopen(descriptor, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        if mode is not None:
            os.chmod(temporary, mode)
        os.replace(temporary, target)
    except OSError as exc:
        _remove_quietly(temporary)
        raise OutputPathError(target, f"write failed, file left unchanged: {exc}") from exc
    except BaseException:
        _remove_quietly(temporary)
        raise
    _fsync_directory(directory)


def atomic_write_text(path: StrPath, text: str, protect: Iterable[StrPath] = ()) -> None:
    """`atomic_write_bytes` of `text` encoded as UTF-8, line endings written as given."""
    atomic_write_bytes(path, text.encode("utf-8"), protect=protect)


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
# Numeric CSV tables
# --------------------------------------------------------------------------------------------


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
        rows.append([_parse_number(source, line, name, field) for name, field in zip(columns, fields)])
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
    names = tuple(columns)
    _check_column_names(names)
    try:
        array = np.asarray(data, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"table data for {path}: not numeric ({exc})") from None
    if array.ndim != 2 or array.shape[1] != len(names) or array.shape[0] == 0:
        raise InvalidInputError(
            f"table data for {path}: shape {array.shape}, expected (n_rows >= 1, {len(names)} columns)"
        )
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        row, col = (int(i) for i in bad[0])
        raise InvalidInputError(
            f"table data for {path}: row {row}, column '{names[col]}' is {array[row, col]}, not a finite number"
        )

    lines = [_comment_line(part) for comment in comments for part in (comment.splitlines() or [""])]
    lines.append(",".join(names))
    lines.extend(",".join(format_float(value) for value in row) for row in array.tolist())
    atomic_write_text(path, "\n".join(lines) + "\n", protect=protect)


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


def _parse_number(source: Path, line: int, column: str, field: str) -> float:
    if _DECIMAL.fullmatch(field):
        value = float(field)
        if math.isfinite(value):
            return value
        raise DataFileError(source, f"value {field} is too large for a double", row=line, column=column)
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
