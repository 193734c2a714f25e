"""io.tables tests that kill mutants the behaviour tests let through (docs/mutation.md): exact error
messages naming file, line and column, both sides of every check, the magnitude bound at its value,
and what `Table` stores (types, dtypes, read-only arrays)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from m3t1r.errors import DataFileError, InvalidInputError
from m3t1r.io.tables import MAX_MAGNITUDE, Table, read_table, table_text, write_table


def _csv(tmp_path: Path, text: str, name: str = "t.csv") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    return path


def _read_error(path: Path, *args, **kwargs) -> DataFileError:
    with pytest.raises(DataFileError) as caught:
        read_table(path, *args, **kwargs)
    return caught.value


# -- Table ------------------------------------------------------------------------------------


def test_table_normalizes_its_fields(tmp_path):
    table = Table(path=str(tmp_path / "a.csv"), columns=["x", "y"], data=[[1, 2], [3, 4]], line_numbers=[2.0, 5.0])
    assert isinstance(table.path, Path) and table.path == tmp_path / "a.csv"
    assert isinstance(table.columns, tuple) and table.columns == ("x", "y")
    assert isinstance(table.data, np.ndarray) and table.data.dtype == np.float64
    assert isinstance(table.line_numbers, np.ndarray) and table.line_numbers.dtype == np.int64
    assert not table.data.flags.writeable and not table.line_numbers.flags.writeable
    np.testing.assert_array_equal(table.line_numbers, [2, 5])


def test_table_refuses_data_not_matching_its_columns_or_lines(tmp_path):
    with pytest.raises(ValueError, match=re.escape("data of shape (3,) does not match 3 columns")):
        Table(path=tmp_path / "a.csv", columns=("x", "y", "z"), data=[1.0, 2.0, 3.0], line_numbers=[2])
    with pytest.raises(ValueError, match=re.escape("data of shape (1, 2) does not match 3 columns")):
        Table(path=tmp_path / "a.csv", columns=("x", "y", "z"), data=[[1.0, 2.0]], line_numbers=[2])
    with pytest.raises(ValueError, match=re.escape("line_numbers of shape (2,) does not match 1 rows")):
        Table(path=tmp_path / "a.csv", columns=("x", "y", "z"), data=[[1.0, 2.0, 3.0]], line_numbers=[2, 3])


def test_table_column_and_error_name_the_file(tmp_path):
    table = Table(path=tmp_path / "a.csv", columns=("x", "y", "z"), data=[[1.0, 2.0, 3.0]], line_numbers=[4])
    with pytest.raises(KeyError, match=re.escape(f"{tmp_path / 'a.csv'} has no column 'w'; it has x, y, z")):
        table.column("w")
    error = table.error(0, "bad", column="y")
    assert (error.path, error.row, error.column) == (str(tmp_path / "a.csv"), 4, "y")
    assert str(error) == f"{tmp_path / 'a.csv'}, line 4, column 'y': bad"


# -- read_table: file level ---------------------------------------------------------------------


def test_missing_directory_unreadable_and_empty_files_are_named(tmp_path):
    missing = tmp_path / "missing.csv"
    assert str(_read_error(missing, ["x"])) == f"{missing}: file not found"
    folder = tmp_path / "folder.csv"
    folder.mkdir()
    error = _read_error(folder, ["x"])
    assert (error.path, str(error)) == (str(folder), f"{folder}: is a directory, expected a CSV file")
    under_a_file = _csv(tmp_path, "x\n1\n") / "inner.csv"  # a path through a file: NotADirectoryError
    error = _read_error(under_a_file, ["x"])
    assert (error.path, str(error)) == (str(under_a_file), f"{under_a_file}: cannot read: Not a directory")
    empty = _csv(tmp_path, "# only a comment\n\n", "empty.csv")
    assert str(_read_error(empty, ["x"])) == f"{empty}: no header line: the file is empty or holds only comments"
    header_only = _csv(tmp_path, "# c\nx\n", "header.csv")
    assert str(_read_error(header_only, ["x"])) == f"{header_only}, line 2: no data rows after the header"


def test_non_utf8_names_the_file_and_line(tmp_path):
    path = tmp_path / "latin.csv"
    path.write_bytes(b"x\n1\n\xe9\n")
    error = _read_error(path, ["x"])
    assert (error.path, error.row) == (str(path), 3)
    assert str(error) == f"{path}, line 3: not UTF-8 text (byte 0xe9)"


# -- read_table: schema and header --------------------------------------------------------------


@pytest.mark.parametrize("schema", [
    {"required": "xy"},
    {"required": ["x"], "optional": "yz"},
    {"required": ["x"], "optional_groups": ["yz"]},
])
def test_a_column_list_given_as_a_string_is_refused(tmp_path, schema):
    path = _csv(tmp_path, "x\n1\n")
    with pytest.raises(ValueError, match=r"^column lists must be sequences of names, not strings$"):
        read_table(path, **schema)


def test_a_schema_naming_columns_twice_lists_them(tmp_path):
    path = _csv(tmp_path, "x\n1\n")
    with pytest.raises(ValueError, match=r"^table schema names x, y more than once$"):
        read_table(path, ["x", "y"], ["y"], [("x", "z")])


def test_duplicate_header_name(tmp_path):
    path = _csv(tmp_path, "x,y,x\n1,2,3\n")
    error = _read_error(path, ["x", "y"])
    assert str(error) == f"{path}, line 1, column 'x': column name appears twice in the header"


def test_separator_hint_only_for_a_single_field_with_a_semicolon_or_tab(tmp_path):
    semicolons = _csv(tmp_path, "x;y\n1;2\n", "semi.csv")
    assert str(_read_error(semicolons, ["x", "y"])) == (
        f"{semicolons}, line 1, column 'x': missing required columns: x, y; unknown columns: x;y "
        "(is this file for another model?) (fields must be separated by commas)")
    # One field without a separator, and two fields one of which holds a ';': no hint.
    single = _csv(tmp_path, "x\n1\n", "single.csv")
    assert str(_read_error(single, ["x", "y"])) == f"{single}, line 1, column 'y': missing required columns: y"
    two = _csv(tmp_path, "x,a;b\n1,2\n", "two.csv")
    assert str(_read_error(two, ["x"])) == (
        f"{two}, line 1, column 'a;b': unknown columns: a;b (is this file for another model?); expected columns: x")


def test_unknown_columns_list_them_and_the_expected_ones(tmp_path):
    path = _csv(tmp_path, "x,u,v\n1,2,3\n")
    error = _read_error(path, ["x"], ["y"], [("qa", "qb")])
    assert error.column == "u"
    assert str(error) == (f"{path}, line 1, column 'u': unknown columns: u, v (is this file for another model?); "
                          "expected columns: x, y, qa, qb")


def test_a_partial_group_lists_the_absent_columns(tmp_path):
    path = _csv(tmp_path, "x,qa\n1,2\n")
    error = _read_error(path, ["x"], (), [("qa", "qb", "qc")])
    assert str(error) == f"{path}, line 1, column 'qb': columns qa, qb, qc go together: qb, qc missing"


# -- read_table: fields ---------------------------------------------------------------------------


def test_too_few_and_too_many_fields(tmp_path):
    few = _csv(tmp_path, "x,y,z\n1\n", "few.csv")
    error = _read_error(few, ["x", "y", "z"])
    assert (error.row, error.column) == (2, "y")
    many = _csv(tmp_path, "x,y\n1,2,3\n", "many.csv")
    error = _read_error(many, ["x", "y"])
    assert (error.row, error.column) == (2, None)
    assert str(error) == f"{many}, line 2: 3 fields, but the header has 2 columns"


def test_empty_field_message(tmp_path):
    path = _csv(tmp_path, "x,y\n1,\n")
    assert str(_read_error(path, ["x", "y"])) == f"{path}, line 2, column 'y': empty field"


def test_default_magnitude_bound_is_inclusive_at_1e6(tmp_path):
    assert MAX_MAGNITUDE == 1e6
    at_bound = _csv(tmp_path, "x,y\n1000000,-1e6\n", "at.csv")
    np.testing.assert_array_equal(read_table(at_bound, ["x", "y"]).data, [[1e6, -1e6]])
    beyond = _csv(tmp_path, "# units: m\nx,y\n0,1000000.0000001\n", "beyond.csv")
    error = _read_error(beyond, ["x", "y"])
    assert (error.path, error.row, error.column) == (str(beyond), 3, "y")
    assert str(error) == (f"{beyond}, line 3, column 'y': value 1000000.0000001 is implausibly large: |value| > 1e+06 "
                          "(SI units: m, rad); it would overflow the computation")


def test_explicit_magnitude_bound(tmp_path):
    path = _csv(tmp_path, "x\n2.5\n")
    assert read_table(path, ["x"], max_magnitude=2.5).data[0, 0] == 2.5
    with pytest.raises(DataFileError, match=r"\|value\| > 2.4 "):
        read_table(path, ["x"], max_magnitude=2.4)


def test_duplicate_rows_name_the_file_and_both_lines(tmp_path):
    path = _csv(tmp_path, "x,y\n1,2\n# again\n1.0,2\n")
    error = _read_error(path, ["x", "y"], reject_duplicate_rows=True)
    assert (error.path, error.row) == (str(path), 4)
    assert str(error) == f"{path}, line 4: row repeats line 2"


# -- table_text / write_table ---------------------------------------------------------------------


@pytest.mark.parametrize("name", ["a,b", 'a"b', "a\nb", "", " a", "a "])
def test_bad_column_names_are_refused_with_the_rule(name):
    with pytest.raises(InvalidInputError, match=re.escape(
            f"column name {name!r}: must be non-empty, unpadded, without , \" or line breaks")):
        table_text(["x", name], [[1.0, 2.0]])


def test_a_non_string_column_name_is_an_invalid_input():
    with pytest.raises(InvalidInputError, match=r"^column name 5: must be non-empty"):
        table_text(["x", 5], [[1.0, 2.0]])


def test_repeated_column_names_are_listed():
    with pytest.raises(InvalidInputError, match=r"^column names given more than once: a, b$"):
        table_text(["a", "b", "a", "b"], [[1.0, 2.0, 3.0, 4.0]])


def test_table_text_refuses_zero_rows_and_names_the_default_what():
    with pytest.raises(InvalidInputError, match=re.escape("table data: shape (0, 2), expected (n_rows >= 1, 2 columns)")):
        table_text(["a", "b"], np.empty((0, 2)))
    with pytest.raises(InvalidInputError, match=r"^table data: row 0, column 'b' is nan, not a finite number$"):
        table_text(["a", "b"], [[1.0, np.nan]])


def test_write_table_names_its_path_in_data_errors(tmp_path):
    path = tmp_path / "out.csv"
    with pytest.raises(InvalidInputError, match=re.escape(f"table data for {path}: row 1, column 'a' is inf")):
        write_table(path, ["a"], [[1.0], [np.inf]])
    assert not path.exists()


def test_an_empty_comment_is_a_bare_hash():
    assert table_text(["a"], [[1.0]], comments=["", "two\nlines"]) == "#\n# two\n# lines\na\n1.0\n"
