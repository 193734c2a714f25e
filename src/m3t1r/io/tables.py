"""Validated numeric CSV tables: `read_table` and `Table`, `write_table` and `table_text`.

CSV format read by `read_table` and written by `write_table`:

- UTF-8 (a byte-order mark is tolerated), comma-separated, SI units (m, rad);
- a line whose first non-blank character is `#` is a comment; blank lines are ignored;
- the first other line is the header of column names, every line after it is a data row;
- every data field is a finite decimal number (`1`, `-0.25`, `3e-05`; no `nan`, `inf`, `1_000`), or empty
  in a column the reader allows blank (a point the tracker did not see), read as NaN.

Errors in a file are `DataFileError`s carrying the 1-based line number in the file (comments and
blank lines counted, as an editor shows it) and the column name, so a user can go straight to
the bad field.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m3t1r.errors import DataFileError, InvalidInputError
from m3t1r.io.outputs import atomic_write_text
from m3t1r.io.paths import StrPath, read_input

__all__ = ["MAX_MAGNITUDE", "Table", "format_float", "read_header", "read_table", "table_text", "write_table"]

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
    blank_allowed: Sequence[str] = (),
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
        blank_allowed: columns whose empty field is read as NaN (a point the tracker did not see);
            anywhere else an empty field is an error.

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

    rows: list[list[str]] = []
    lines: list[int] = []
    convert = _Converter(source, columns, blank_allowed, max_magnitude)
    try:
        for line, fields in records:
            if len(fields) != len(columns):
                # Too few fields: name the first column without a value; too many: no column to name.
                missing = columns[len(fields)] if len(fields) < len(columns) else None
                raise DataFileError(
                    source, f"{len(fields)} fields, but the header has {len(columns)} columns", row=line, column=missing
                )
            rows.append(fields)
            lines.append(line)
    except DataFileError:
        convert.field_by_field(rows, lines)  # a bad field on an earlier line is the first fault
        raise
    if not rows:
        raise DataFileError(source, "no data rows after the header", row=header_line)

    table = Table(path=source, columns=columns, data=convert(rows, lines), line_numbers=np.array(lines))
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


def table_text(
    columns: Sequence[str],
    data: object,
    comments: Sequence[str] = (),
    what: str = "table data",
    blank_allowed: Sequence[str] = (),
) -> str:
    """The text `write_table` writes (same arguments and InvalidInputError), for an `OutputSet.stage`;
    NaN in a `blank_allowed` column is written as an empty field (`read_table` reads it back as NaN)."""
    names = tuple(columns)
    _check_column_names(names)
    try:
        array = np.asarray(data, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{what}: not numeric ({exc})") from None
    if array.ndim != 2 or array.shape[1] != len(names) or array.shape[0] == 0:
        raise InvalidInputError(f"{what}: shape {array.shape}, expected (n_rows >= 1, {len(names)} columns)")
    blank = np.isnan(array) & np.isin(np.array(names), list(blank_allowed))[None, :]
    bad = np.argwhere(~np.isfinite(array) & ~blank)
    if bad.size:
        row, col = (int(i) for i in bad[0])
        raise InvalidInputError(f"{what}: row {row}, column '{names[col]}' is {array[row, col]}, not a finite number")

    lines = [_comment_line(part) for comment in comments for part in (comment.splitlines() or [""])]
    lines.append(",".join(names))
    lines.extend(
        ",".join("" if value != value else format_float(value) for value in row)  # NaN: blank_allowed
        for row in array.tolist()
    )
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


def read_header(path: StrPath) -> tuple[str, ...]:
    """The column names of a CSV table (its first non-comment line), to choose the schema that
    `read_table` then checks; DataFileError for a missing, unreadable or empty file."""
    source = Path(path)
    try:
        return tuple(next(_records(source, _read_text(source)))[1])
    except StopIteration:
        raise DataFileError(source, "no header line: the file is empty or holds only comments") from None


def _read_text(source: Path) -> str:
    raw = read_input(source, DataFileError, "a CSV file")
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


#: Orientation columns in another form than the quaternion a measurement table holds: the names
#: (lowercase), what they are, and the `m3t1r convert` options that read them.
_OTHER_ORIENTATIONS = (
    (("roll", "pitch", "yaw"), "Euler angles", "--euler SEQ [--degrees]"),
    (("rx", "ry", "rz"), "Euler angles or a rotation vector", "--euler SEQ (or --rotation-vector) [--degrees]"),
    (("rvx", "rvy", "rvz"), "a rotation vector", "[--degrees]"),
    (tuple(f"r{i}{j}" for i in "123" for j in "123"), "a rotation matrix", ""),
)
_QUATERNION = ("qx", "qy", "qz", "qw")


def _orientation_hint(source: Path, unknown: Sequence[str], groups: Sequence[Sequence[str]]) -> str:
    """For a table that takes a quaternion group: the sentence naming unknown columns that hold an
    orientation in another form, and how to convert them (empty when there are none)."""
    if not any(tuple(group) == _QUATERNION for group in groups):
        return ""
    lower = {name.lower() for name in unknown}
    for names, what, options in _OTHER_ORIENTATIONS:
        if set(names) <= lower:
            listed = ", ".join(names) if len(names) < 9 else f"{names[0]} ... {names[-1]}"
            return (
                f"; {listed} look like an orientation as {what}: this file takes a unit quaternion qx, qy, qz, "
                f"qw, and `m3t1r convert {source} {options + ' ' if options else ''}-o measurements.csv` "
                "converts the file (it keeps the joint columns)"
            )
    return ""


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
    orientation = _orientation_hint(source, unknown, groups)
    hint += orientation
    question = "" if orientation else " (is this file for another model?)"
    if missing:
        message = f"missing required columns: {', '.join(missing)}"
        if unknown:
            message += f"; unknown columns: {', '.join(unknown)}{question}"
        raise DataFileError(source, message + hint, row=line, column=missing[0])
    if unknown:
        expected = ", ".join([*required, *optional, *(name for group in groups for name in group)])
        raise DataFileError(
            source,
            f"unknown columns: {', '.join(unknown)}{question}; expected columns: {expected}" + hint,
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


# Characters of plain decimals and the line breaks joining them: on fields of these alone, float()
# accepts exactly what `_DECIMAL` does (no underscores, letters or spaces; one character class, so
# that matching a whole table keeps no state per field).
_DECIMAL_CHARACTERS = re.compile(r"[0-9eE+\-.\n]*")


@dataclass(frozen=True)
class _Converter:
    """The fields of a table's data rows to doubles: every field a plain decimal (`_DECIMAL`), finite
    and within max_magnitude, converted in one pass (float() of each, into one array); any other
    table field by field, which refuses the first bad field in file order, as `_parse_number` words it."""

    source: Path
    columns: tuple[str, ...]
    blank_allowed: Sequence[str]
    max_magnitude: float

    def __call__(self, rows: list[list[str]], lines: list[int]) -> np.ndarray:
        fields = [field for row in rows for field in row]
        if _DECIMAL_CHARACTERS.fullmatch("\n".join(fields)):
            try:
                values = np.fromiter(map(float, fields), dtype=float, count=len(fields))
            except ValueError:  # a field such as "1e" or "": the field-by-field pass names it
                pass
            else:
                if np.all(np.isfinite(values)) and np.all(np.abs(values) <= self.max_magnitude):
                    return values.reshape(len(rows), len(self.columns))
        return self.field_by_field(rows, lines)

    def field_by_field(self, rows: list[list[str]], lines: list[int]) -> np.ndarray:
        values = [
            [
                math.nan
                if not field and name in self.blank_allowed
                else _parse_number(self.source, line, name, field, self.max_magnitude)
                for name, field in zip(self.columns, fields)
            ]
            for line, fields in zip(lines, rows)
        ]
        return np.array(values, dtype=float).reshape(len(rows), len(self.columns))


def _parse_number(source: Path, line: int, column: str, field: str, max_magnitude: float = math.inf) -> float:
    if _DECIMAL.fullmatch(field):
        value = float(field)
        if not math.isfinite(value):
            raise DataFileError(source, f"value {field} is too large for a double", row=line, column=column)
        if abs(value) > max_magnitude:
            raise DataFileError(
                source,
                f"value {field} is implausibly large: |value| > {max_magnitude:g} "
                "(SI units: m, rad); it would overflow the computation",
                row=line,
                column=column,
            )
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
            raise InvalidInputError(f'column name {name!r}: must be non-empty, unpadded, without , " or line breaks')
        if name.startswith("#"):
            raise InvalidInputError(f"column name {name!r}: a header starting with '#' would read as a comment")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise InvalidInputError(f"column names given more than once: {', '.join(repeated)}")


def _comment_line(text: str) -> str:
    return f"# {text}" if text else "#"
