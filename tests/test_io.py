"""Atomic writes, protected inputs, and the numeric CSV reader/writer with its error reporting."""

from __future__ import annotations

import errno
import fcntl
import math
import os
import re
import stat
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import process_holding_flock

from m3t1r.errors import DataFileError, InvalidInputError, OutputPathError
from m3t1r.io import temporaries
from m3t1r.io.outputs import atomic_write_bytes, atomic_write_text
from m3t1r.io.pairing import sha256_bytes, with_closures_sha256
from m3t1r.io.paths import ensure_not_protected
from m3t1r.io.poses import POSE_COLUMNS, pose_rows, poses_from_table
from m3t1r.io.tables import MAX_MAGNITUDE, Table, read_header, read_table, table_text, write_table
from m3t1r.io.temporaries import (
    _LIVE_TEMPORARIES,
    claim_temporary,
    folder_lock,
    pending_temporaries,
    print_notice,
    sweep_locked,
    temporary_path,
    write_claimed,
)

QUATERNION = ("qx", "qy", "qz", "qw")


def write(path: Path, text: str) -> Path:
    path.write_bytes(text.encode("utf-8"))
    return path


def bits(array: np.ndarray) -> np.ndarray:
    """The raw IEEE-754 bits, so that comparisons see -0.0 vs 0.0 and the last ulp."""
    return np.ascontiguousarray(array, dtype=np.float64).view(np.uint64)


# --------------------------------------------------------------------------------------------
# Round trips and format
# --------------------------------------------------------------------------------------------


def test_write_then_read_is_bit_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    awkward = [0.1, 1 / 3, -0.0, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308, -123456789.12345679, np.pi]
    data = np.vstack(
        [
            rng.normal(scale=10.0, size=(50, 4)) * 10.0 ** rng.integers(-12, 12, size=(50, 4)),
            np.reshape(awkward, (2, 4)),
        ]
    )
    path = tmp_path / "table.csv"
    write_table(path, ["a", "b", "c", "d"], data, comments=["units: m", "two\nlines"])

    table = read_table(path, required=["a", "b", "c", "d"], max_magnitude=math.inf)  # any double round-trips

    assert table.columns == ("a", "b", "c", "d")
    np.testing.assert_array_equal(bits(table.data), bits(data))
    # Three comment lines and the header come first.
    np.testing.assert_array_equal(table.line_numbers, np.arange(5, 5 + len(data)))
    assert path.read_text().splitlines()[:4] == ["# units: m", "# two", "# lines", "a,b,c,d"]


def test_values_are_written_in_shortest_exact_form(tmp_path: Path) -> None:
    path = tmp_path / "short.csv"
    write_table(path, ["x"], [[0.1], [3e-05], [-0.0]])
    assert path.read_text().splitlines()[1:] == ["0.1", "3e-05", "-0.0"]


def test_comments_blank_lines_and_line_endings(tmp_path: Path) -> None:
    path = tmp_path / "commented.csv"
    text = (
        "\ufeff# produced by a test\r\n\r\n   # indented comment\r\n x , y \r\n1,2\r\n\r\n"
        "# between rows\r\n 3 , 4e0 \r\n\n"
    )
    write(path, text)

    table = read_table(path, required=["x", "y"])

    assert table.columns == ("x", "y")
    np.testing.assert_array_equal(table.data, [[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(table.line_numbers, [5, 8])
    np.testing.assert_array_equal(table.column("y"), [2.0, 4.0])


def test_optional_columns_and_groups(tmp_path: Path) -> None:
    with_all = write(tmp_path / "all.csv", "t,x,y,z,qx,qy,qz,qw\n0,1,2,3,0,0,0,1\n")
    without = write(tmp_path / "without.csv", "x,y,z\n1,2,3\n")
    schema = dict(required=["x", "y", "z"], optional=["t"], optional_groups=[QUATERNION])

    assert read_table(with_all, **schema).has_column("qw")
    table = read_table(without, **schema)
    assert not table.has_column("qw") and not table.has_column("t")
    with pytest.raises(KeyError, match="has no column 'qw'"):
        table.column("qw")


def test_table_is_immutable(tmp_path: Path) -> None:
    table = read_table(write(tmp_path / "t.csv", "x\n1\n2\n"), required=["x"])
    with pytest.raises(ValueError):
        table.data[0, 0] = 5.0
    with pytest.raises(ValueError):
        table.column("x")[0] = 5.0
    error = table.error(1, "outside the joint limits", column="x")
    assert (error.row, error.column) == (3, "x")


def test_schema_naming_a_column_twice_is_a_caller_bug(tmp_path: Path) -> None:
    path = write(tmp_path / "t.csv", "x\n1\n")
    with pytest.raises(ValueError, match="more than once"):
        read_table(path, required=["x"], optional=["x"])


# --------------------------------------------------------------------------------------------
# Malformed files: every error names the file, the line and the column
# --------------------------------------------------------------------------------------------

REQUIRED = ("x", "y", "z")

MALFORMED = {
    # case: (file text, expected line, expected column, message fragment)
    "empty": ("", None, None, "no header line"),
    "comments only": ("# nothing\n\n  # here\n", None, None, "no header line"),
    "header only": ("# c\nx,y,z\n\n", 2, None, "no data rows"),
    "duplicate header name": ("x,y,z,y\n1,2,3,4\n", 1, "y", "appears twice"),
    "empty header name": ("x,,y,z\n1,2,3,4\n", 1, None, "header field 2 is empty"),
    "missing required": ("# c\nx,z\n1,2\n", 2, "y", "missing required columns: y"),
    "missing and unknown": ("a1,a2,x\n1,2,3\n", 1, "y", "missing required columns: y, z; unknown columns: a1, a2"),
    "unknown only": ("x,y,z,q11\n1,2,3,4\n", 1, "q11", "unknown columns: q11"),
    "partial group": ("x,y,z,qx,qy,qz\n1,2,3,0,0,0\n", 1, "qw", "qx, qy, qz, qw go together: qw missing"),
    "semicolons": ("x;y;z\n1;2;3\n", 1, "x", "separated by commas"),
    "too few fields": ("x,y,z\n1,2,3\n4,5\n", 3, "z", "2 fields, but the header has 3"),
    "too many fields": ("x,y,z\n1,2,3,4\n", 2, None, "4 fields, but the header has 3"),
    "trailing comma": ("x,y,z\n1,2,3,\n", 2, None, "4 fields"),
    "not a number": ("x,y,z\n1,2,3\n\n4,abc,6\n", 4, "y", "'abc' is not a number"),
    "underscore digits": ("x,y,z\n1_000,2,3\n", 2, "x", "'1_000' is not a number"),
    "empty field": ("x,y,z\n1,,3\n", 2, "y", "empty field"),
    "nan": ("x,y,z\n1,2,nan\n", 2, "z", "'nan' is not finite"),
    "inf": ("x,y,z\n-Infinity,2,3\n", 2, "x", "'-Infinity' is not finite"),
    "overflow": ("x,y,z\n1,1e999,3\n", 2, "y", "too large for a double"),
    "bad quoting": ('x,y,z\n1,2,3\n1,"2,3\n4,5,6\n', 3, None, "malformed CSV"),
    "exponent without digits": ("x,y,z\n1,2,3\n4,1e,6\n", 3, "y", "'1e' is not a number"),
    "two decimal points": ("x,y,z\n1.2.3,2,3\n", 2, "x", "'1.2.3' is not a number"),
    "a sign alone": ("x,y,z\n1,2,-\n", 2, "z", "'-' is not a number"),
    # The first fault in file order, whatever the kinds of the later ones.
    "a bad number before too few fields": ("x,y,z\n1,abc,3\n4,5\n", 2, "y", "'abc' is not a number"),
    "a bad number before bad quoting": ('x,y,z\n1,2,x\n1,"2,3\n', 2, "z", "'x' is not a number"),
    "an overflow before a bad number": ("x,y,z\n1,2,3\n1e999,2,3\n4,abc,6\n", 3, "x", "too large for a double"),
}


@pytest.mark.parametrize("case", MALFORMED, ids=list(MALFORMED))
def test_malformed_file_names_line_and_column(tmp_path: Path, case: str) -> None:
    text, line, column, fragment = MALFORMED[case]
    path = write(tmp_path / "bad.csv", text)

    with pytest.raises(DataFileError) as caught:
        read_table(path, required=REQUIRED, optional_groups=[QUATERNION])

    error = caught.value
    assert (error.row, error.column) == (line, column)
    assert fragment in str(error)
    assert str(error).startswith(str(path))
    if line is not None:
        assert f"line {line}" in str(error)
    if column is not None:
        assert f"column '{column}'" in str(error)


def test_every_decimal_form_reads_as_python_reads_it(tmp_path: Path) -> None:
    """Signs, a bare point on either side, leading zeros, exponents of either case: each field is the
    double float() gives it (a table of plain decimals is converted in one pass)."""
    fields = [["+1.", "-.5", "3e-2"], ["00012", "1E5", "0.1"], ["-0.30000000000000004", "2.5e-310", "7"]]
    path = write(tmp_path / "forms.csv", "x,y,z\n" + "".join(",".join(row) + "\n" for row in fields))
    table = read_table(path, required=REQUIRED)
    assert table.data.tolist() == [[float(field) for field in row] for row in fields]
    assert table.line_numbers.tolist() == [2, 3, 4]


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DataFileError, match="file not found") as caught:
        read_table(tmp_path / "absent.csv", required=REQUIRED)
    assert caught.value.path == str(tmp_path / "absent.csv")


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(DataFileError, match="is a directory"):
        read_table(tmp_path, required=REQUIRED)


def test_non_utf8_byte_names_its_line(tmp_path: Path) -> None:
    path = tmp_path / "latin1.csv"
    path.write_bytes(b"x,y,z\n1,2,3\n# r\xe9sum\xe9\n")
    with pytest.raises(DataFileError, match="not UTF-8") as caught:
        read_table(path, required=REQUIRED)
    assert caught.value.row == 3


def test_duplicate_rows_rejected_on_request_naming_both_lines(tmp_path: Path) -> None:
    path = write(tmp_path / "dup.csv", "x,y,z\n1,2,3\n4,5,6\n# again\n1.0,2e0,3\n")

    assert read_table(path, required=REQUIRED).n_rows == 3
    with pytest.raises(DataFileError, match="repeats line 2") as caught:
        read_table(path, required=REQUIRED, reject_duplicate_rows=True)
    assert caught.value.row == 5


# --------------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------------


def test_atomic_write_replaces_content_and_keeps_permissions(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    target.chmod(0o640)

    atomic_write_text(target, "new ✓")

    assert target.read_text(encoding="utf-8") == "new ✓"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    assert os.listdir(tmp_path) == ["out.txt"]


@pytest.mark.parametrize("failing", ["replace", "fsync"])
def test_failed_write_leaves_target_untouched_and_no_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing: str
) -> None:
    target = tmp_path / "out.csv"
    target.write_bytes(b"precious")

    def fail(*args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, failing, fail)
    with pytest.raises(OutputPathError, match="No space left on device") as caught:
        write_table(target, ["x"], [[1.0]])
    monkeypatch.undo()

    assert caught.value.path == str(target)
    assert target.read_bytes() == b"precious"
    assert os.listdir(tmp_path) == ["out.csv"]


def test_interrupted_write_removes_temporary_and_propagates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    class Interrupted(BaseException):
        pass

    def interrupt(*args: object) -> None:
        raise Interrupted

    target = tmp_path / "out.bin"
    target.write_bytes(b"precious")
    monkeypatch.setattr(os, "replace", interrupt)
    with pytest.raises(Interrupted):
        atomic_write_bytes(target, b"new")
    monkeypatch.undo()

    assert target.read_bytes() == b"precious"
    assert os.listdir(tmp_path) == ["out.bin"]


def test_unwritable_data_is_refused_before_touching_the_file(tmp_path: Path) -> None:
    target = tmp_path / "out.csv"
    target.write_bytes(b"precious")

    with pytest.raises(InvalidInputError, match="row 1, column 'y' is nan"):
        write_table(target, ["x", "y"], [[1.0, 2.0], [3.0, np.nan]])
    with pytest.raises(InvalidInputError, match="not numeric"):
        write_table(target, ["x"], [["one"]])
    with pytest.raises(InvalidInputError, match="shape"):
        write_table(target, ["x", "y"], [[1.0, 2.0, 3.0]])
    with pytest.raises(InvalidInputError, match="read as a comment"):
        write_table(target, ["#x"], [[1.0]])
    with pytest.raises(InvalidInputError, match="more than once"):
        write_table(target, ["x", "x"], [[1.0, 2.0]])

    assert target.read_bytes() == b"precious"
    assert os.listdir(tmp_path) == ["out.csv"]


def test_output_into_missing_directory_or_onto_directory(tmp_path: Path) -> None:
    with pytest.raises(OutputPathError, match="does not exist"):
        atomic_write_text(tmp_path / "no" / "such" / "file.txt", "x")
    with pytest.raises(OutputPathError, match="is a directory"):
        atomic_write_text(tmp_path, "x")


def test_protected_inputs_are_never_overwritten(tmp_path: Path) -> None:
    nominal = tmp_path / "models" / "robot.urdf"
    nominal.parent.mkdir()
    nominal.write_bytes(b"<robot/>")
    symlink = tmp_path / "link.urdf"
    symlink.symlink_to(nominal)
    hardlink = tmp_path / "hard.urdf"
    os.link(nominal, hardlink)
    spellings = [nominal, str(nominal), tmp_path / "models" / ".." / "models" / "robot.urdf", symlink, hardlink]

    for spelling in spellings:
        with pytest.raises(OutputPathError, match="refusing to overwrite the input file"):
            atomic_write_text(spelling, "clobbered", protect=[nominal])
        with pytest.raises(OutputPathError):
            write_table(spelling, ["x"], [[1.0]], protect=[str(nominal)])

    assert nominal.read_bytes() == b"<robot/>"
    ensure_not_protected(tmp_path / "calibrated.urdf", protect=[nominal, tmp_path / "absent.csv"])
    atomic_write_text(tmp_path / "calibrated.urdf", "ok", protect=[nominal])


# --------------------------------------------------------------------------------------------
# Poses
# --------------------------------------------------------------------------------------------


def test_pose_round_trip_through_a_file(tmp_path: Path) -> None:
    pin.seed(3)
    poses = [pin.SE3.Random() for _ in range(20)]
    path = tmp_path / "poses.csv"
    write_table(path, POSE_COLUMNS, pose_rows(poses))

    read = poses_from_table(read_table(path, required=POSE_COLUMNS))

    assert len(read) == len(poses)
    for original, loaded in zip(poses, read):
        assert np.allclose(original.homogeneous, loaded.homogeneous, rtol=0.0, atol=1e-15)


def test_pose_rows_fix_the_quaternion_sign() -> None:
    quaternions = [
        pin.Quaternion(-0.5, 0.5, -0.5, 0.5),  # (w, x, y, z): negative scalar part
        pin.Quaternion(0.0, -1.0, 0.0, 0.0),  # half turn about -x, the same rotation as about +x
        pin.Quaternion(0.0, 0.0, -0.6, 0.8),
    ]
    poses = [pin.SE3(q.matrix(), np.array([0.1, -0.0, 0.3])) for q in quaternions]

    rows = pose_rows(poses)

    assert rows.shape == (3, 7)
    np.testing.assert_allclose(rows[0, 3:], [-0.5, 0.5, -0.5, 0.5], atol=1e-15)
    np.testing.assert_allclose(rows[1, 3:], [1.0, 0.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rows[2, 3:], [0.0, 0.6, -0.8, 0.0], atol=1e-15)
    assert not np.signbit(rows[:, 1]).any()  # no "-0.0" in files
    assert pose_rows([]).shape == (0, 7)


def test_quaternion_norm_checked_with_its_line(tmp_path: Path) -> None:
    path = write(
        tmp_path / "poses.csv",
        "x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n# second pose\n1,2,3,0,0,0.6,0.8000001\n4,5,6,0,0,0,0.98\n",
    )
    table = read_table(path, required=POSE_COLUMNS)

    with pytest.raises(
        DataFileError, match=r"quaternion \(qx, qy, qz, qw\) norm 0.98 is not 1 \(tolerance 1e-06\)"
    ) as caught:
        poses_from_table(table)
    assert caught.value.row == 5

    loose = poses_from_table(table, quat_tol=0.05)
    rotation = loose[1].rotation
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(loose[2].translation, [4.0, 5.0, 6.0])


def test_poses_need_all_pose_columns(tmp_path: Path) -> None:
    table = Table(path=tmp_path / "t.csv", columns=("x", "y", "z"), data=np.zeros((1, 3)), line_numbers=[2])
    with pytest.raises(DataFileError, match="missing pose columns: qx, qy, qz, qw"):
        poses_from_table(table)


def test_orientation_columns_in_another_form_name_the_conversion(tmp_path):
    """A measurement table with Euler angles was refused as 'unknown columns ... another model?'."""
    path = tmp_path / "m.csv"
    path.write_text("j1,x,y,z,roll,pitch,yaw\n0.1,1,2,3,0,0,0\n")
    with pytest.raises(DataFileError) as caught:
        read_table(path, required=("j1", "x", "y", "z"), optional_groups=(("qx", "qy", "qz", "qw"),))
    message = str(caught.value)
    assert "roll, pitch, yaw look like an orientation as Euler angles" in message
    assert f"`m3t1r convert {path} --euler SEQ [--degrees] -o measurements.csv`" in message
    assert "another model" not in message
    with pytest.raises(DataFileError, match=r"another model\?\); expected columns: j1, x, y, z$"):
        read_table(path, required=("j1", "x", "y", "z"))  # a table without orientation: no such hint


def test_a_blank_allowed_column_reads_and_writes_an_unseen_point_as_nan(tmp_path: Path) -> None:
    """Columns of points a tracker may not see: an empty field is NaN there and an error elsewhere,
    and `table_text` writes NaN back as an empty field in those columns only."""
    path = tmp_path / "points.csv"
    path.write_text("q,x1,y1,z1\n0.5,,,\n0.25,1,2,3\n")
    table = read_table(path, required=("q", "x1", "y1", "z1"), blank_allowed=("x1", "y1", "z1"))
    assert np.isnan(table.data[0, 1:]).all() and table.data[1].tolist() == [0.25, 1.0, 2.0, 3.0]
    assert read_header(path) == ("q", "x1", "y1", "z1")
    with pytest.raises(DataFileError, match="line 2.*column 'x1'.*empty field"):
        read_table(path, required=("q", "x1", "y1", "z1"))
    text = table_text(table.columns, table.data, blank_allowed=("x1", "y1", "z1"))
    assert text.splitlines()[1:] == ["0.5,,,", "0.25,1.0,2.0,3.0"]
    with pytest.raises(InvalidInputError, match="column 'x1' is nan"):
        table_text(table.columns, table.data, blank_allowed=("y1",))


# ==================================================================================================
# Pose tables: the quaternion norm tolerance from both sides
# ==================================================================================================


def _table(tmp_path: Path, norm_error: float) -> Table:
    quaternion = np.array([0.0, 0.0, 0.6, 0.8]) * (1.0 + norm_error)
    data = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0, *quaternion]])
    return Table(path=tmp_path / "poses.csv", columns=POSE_COLUMNS, data=data, line_numbers=[2, 7])


@pytest.mark.parametrize("norm_error", [1e-4, 1e-5, 2e-6, -2e-6])
def test_default_quaternion_tolerance_refuses_just_beyond_1e_6(tmp_path, norm_error):
    with pytest.raises(DataFileError, match=r"norm .* is not 1 \(tolerance 1e-06\)") as caught:
        poses_from_table(_table(tmp_path, norm_error))
    assert caught.value.row == 7


@pytest.mark.parametrize("norm_error", [5e-7, -5e-7, 0.0])
def test_default_quaternion_tolerance_accepts_within_1e_6_and_normalizes(tmp_path, norm_error):
    poses = poses_from_table(_table(tmp_path, norm_error))
    rotation = poses[1].rotation
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(rotation[:2, :2], [[1 - 2 * 0.36, -2 * 0.48], [2 * 0.48, 1 - 2 * 0.36]], atol=1e-12)
    np.testing.assert_array_equal(poses[1].translation, [1.0, 2.0, 3.0])


def test_explicit_quaternion_tolerance_is_used_at_its_boundary(tmp_path):
    table = _table(tmp_path, 2e-3)
    assert len(poses_from_table(table, quat_tol=3e-3)) == 2
    with pytest.raises(DataFileError, match=r"tolerance 0.001\)"):
        poses_from_table(table, quat_tol=1e-3)


# ==================================================================================================
# Tables: exact errors naming file, line and column
#
# Both sides of every check, the magnitude bound at its value, and what `Table` stores (types, dtypes,
# read-only arrays).
# ==================================================================================================


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


@pytest.mark.parametrize(
    "schema",
    [
        {"required": "xy"},
        {"required": ["x"], "optional": "yz"},
        {"required": ["x"], "optional_groups": ["yz"]},
    ],
)
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
        "(is this file for another model?) (fields must be separated by commas)"
    )
    # One field without a separator, and two fields one of which holds a ';': no hint.
    single = _csv(tmp_path, "x\n1\n", "single.csv")
    assert str(_read_error(single, ["x", "y"])) == f"{single}, line 1, column 'y': missing required columns: y"
    two = _csv(tmp_path, "x,a;b\n1,2\n", "two.csv")
    assert str(_read_error(two, ["x"])) == (
        f"{two}, line 1, column 'a;b': unknown columns: a;b (is this file for another model?); expected columns: x"
    )


def test_unknown_columns_list_them_and_the_expected_ones(tmp_path):
    path = _csv(tmp_path, "x,u,v\n1,2,3\n")
    error = _read_error(path, ["x"], ["y"], [("qa", "qb")])
    assert error.column == "u"
    assert str(error) == (
        f"{path}, line 1, column 'u': unknown columns: u, v (is this file for another model?); "
        "expected columns: x, y, qa, qb"
    )


def test_a_partial_group_lists_the_absent_columns(tmp_path):
    path = _csv(tmp_path, "x,qa\n1,2\n")
    error = _read_error(path, ["x"], (), [("qa", "qb", "qc")])
    assert str(error) == f"{path}, line 1, column 'qb': columns qa, qb, qc go together: qb, qc missing"


_POSE_SCHEMA = {"required": ("j1", "x", "y", "z"), "optional_groups": (QUATERNION,)}
_CONVERTS = "converts the file (it keeps the joint columns)"


def test_a_rotation_matrix_is_named_by_its_first_and_last_columns_and_converted_without_options(tmp_path):
    matrix = [f"r{i}{j}" for i in "123" for j in "123"]
    path = _csv(tmp_path, ",".join(["j1", "x", "y", "z", *matrix]) + "\n" + ",".join(["0"] * 13) + "\n")
    assert str(_read_error(path, **_POSE_SCHEMA)) == (
        f"{path}, line 1, column 'r11': unknown columns: {', '.join(matrix)}; expected columns: j1, x, y, z, qx, qy, "
        "qz, qw; r11 ... r33 look like an orientation as a rotation matrix: this file takes a unit quaternion qx, "
        f"qy, qz, qw, and `m3t1r convert {path} -o measurements.csv` {_CONVERTS}"
    )


def test_an_orientation_hint_beside_a_missing_column_asks_no_question(tmp_path):
    path = _csv(tmp_path, "j1,x,y,roll,pitch,yaw\n0,1,2,0,0,0\n")
    assert str(_read_error(path, **_POSE_SCHEMA)) == (
        f"{path}, line 1, column 'z': missing required columns: z; unknown columns: roll, pitch, yaw; roll, pitch, "
        "yaw look like an orientation as Euler angles: this file takes a unit quaternion qx, qy, qz, qw, and "
        f"`m3t1r convert {path} --euler SEQ [--degrees] -o measurements.csv` {_CONVERTS}"
    )


def test_unknown_columns_of_a_pose_table_that_are_no_orientation_get_no_hint(tmp_path):
    path = _csv(tmp_path, "j1,x,y,z,roll,pitch\n0,1,2,3,0,0\n")  # two of the three angles: not Euler angles
    assert str(_read_error(path, **_POSE_SCHEMA)) == (
        f"{path}, line 1, column 'roll': unknown columns: roll, pitch (is this file for another model?); "
        "expected columns: j1, x, y, z, qx, qy, qz, qw"
    )


def test_read_header_names_the_file_that_has_no_header_or_a_malformed_one(tmp_path):
    empty = _csv(tmp_path, "# only a comment\n\n", "empty.csv")
    with pytest.raises(DataFileError) as caught:
        read_header(empty)
    assert (caught.value.path, str(caught.value)) == (
        str(empty),
        f"{empty}: no header line: the file is empty or holds only comments",
    )
    quoted = _csv(tmp_path, '# c\nx,"y\n1,2\n', "quoted.csv")
    with pytest.raises(DataFileError) as caught:
        read_header(quoted)
    assert (caught.value.path, caught.value.row) == (str(quoted), 2)
    assert str(caught.value).startswith(f"{quoted}, line 2: malformed CSV: ")


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
    assert str(error) == (
        f"{beyond}, line 3, column 'y': value 1000000.0000001 is implausibly large: |value| > 1e+06 "
        "(SI units: m, rad); it would overflow the computation"
    )


def test_the_magnitude_bound_is_inclusive_in_a_table_with_blank_fields_too(tmp_path):
    """A blank field (allowed in its column) sends the whole table through the field-by-field reading:
    the same bound, inclusive at its value."""
    path = _csv(tmp_path, "x,y\n1000000,\n-1e6,2\n")
    data = read_table(path, ["x", "y"], blank_allowed=("y",)).data
    assert data[:, 0].tolist() == [1e6, -1e6] and np.isnan(data[0, 1]) and data[1, 1] == 2.0
    beyond = _csv(tmp_path, "x,y\n1000000.0000001,\n", "beyond.csv")
    assert str(_read_error(beyond, ["x", "y"], blank_allowed=("y",))).startswith(
        f"{beyond}, line 2, column 'x': value 1000000.0000001 is implausibly large: |value| > 1e+06 "
    )


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
    with pytest.raises(
        InvalidInputError,
        match=re.escape(f'column name {name!r}: must be non-empty, unpadded, without , " or line breaks'),
    ):
        table_text(["x", name], [[1.0, 2.0]])


def test_a_non_string_column_name_is_an_invalid_input():
    with pytest.raises(InvalidInputError, match=r"^column name 5: must be non-empty"):
        table_text(["x", 5], [[1.0, 2.0]])


def test_repeated_column_names_are_listed():
    with pytest.raises(InvalidInputError, match=r"^column names given more than once: a, b$"):
        table_text(["a", "b", "a", "b"], [[1.0, 2.0, 3.0, 4.0]])


def test_table_text_refuses_zero_rows_and_names_the_default_what():
    with pytest.raises(
        InvalidInputError, match=re.escape("table data: shape (0, 2), expected (n_rows >= 1, 2 columns)")
    ):
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


# ==================================================================================================
# Poses: quat_tol, normalization and the canonical quaternion sign
#
# The quat_tol argument check on both sides, the tolerance at its exact value, normalization of every
# quaternion component, the missing-column error, and the canonical sign of half-turn quaternions (qw = 0).
# ==================================================================================================


def _pose_table(tmp_path: Path, quaternion, columns=POSE_COLUMNS) -> Table:
    row = [1.0, 2.0, 3.0, *quaternion][: len(columns)]
    return Table(path=tmp_path / "poses.csv", columns=columns, data=[row], line_numbers=[3])


@pytest.mark.parametrize("quat_tol", [0.0, -1e-6, math.inf, -math.inf, math.nan])
def test_quat_tol_must_be_positive_and_finite(tmp_path, quat_tol):
    with pytest.raises(ValueError, match=rf"^quat_tol must be a positive finite number, got {quat_tol}$"):
        poses_from_table(_pose_table(tmp_path, (0.0, 0.0, 0.0, 1.0)), quat_tol=quat_tol)


def test_norm_off_by_exactly_the_tolerance_is_accepted(tmp_path):
    table = _pose_table(tmp_path, (0.0, 0.0, 0.0, 1.5))  # norm 1.5: off by exactly 0.5
    np.testing.assert_array_equal(poses_from_table(table, quat_tol=0.5)[0].rotation, np.eye(3))
    with pytest.raises(DataFileError, match=r"norm 1.5 is not 1 \(tolerance 0.4999"):
        poses_from_table(table, quat_tol=0.49999)


def test_every_quaternion_component_is_normalized(tmp_path):
    scaled = np.array([0.5, 0.5, 0.5, 0.5]) * 1.001
    pose = poses_from_table(_pose_table(tmp_path, scaled), quat_tol=0.01)[0]
    # q = (1, 1, 1, 1) / 2 is the rotation by 120 degrees about (1, 1, 1): x -> y -> z -> x.
    np.testing.assert_allclose(pose.rotation, [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_array_equal(pose.translation, [1.0, 2.0, 3.0])


def test_missing_pose_column_names_the_file_and_the_first_missing(tmp_path):
    columns = ("x", "y", "z", "qx", "qy", "qz")
    with pytest.raises(DataFileError) as caught:
        poses_from_table(_pose_table(tmp_path, (0.0, 0.0, 0.0), columns=columns))
    error = caught.value
    assert (error.path, error.row, error.column) == (str(tmp_path / "poses.csv"), None, "qw")
    assert str(error) == f"{tmp_path / 'poses.csv'}, column 'qw': missing pose columns: qw"
    with pytest.raises(DataFileError) as caught:
        poses_from_table(_pose_table(tmp_path, (0.0,), columns=("x", "y", "z", "qx")))
    assert caught.value.column == "qy"
    assert str(caught.value).endswith("missing pose columns: qy, qz, qw")


@pytest.mark.parametrize(
    ("quaternion", "canonical"),
    [
        ((0.6, 0.8, 0.0, 0.0), (0.6, 0.8, 0.0, 0.0)),
        ((-0.6, 0.8, 0.0, 0.0), (0.6, -0.8, 0.0, 0.0)),
        ((0.0, -0.6, 0.8, 0.0), (0.0, 0.6, -0.8, 0.0)),
        ((0.0, 0.0, 0.6, 0.0), (0.0, 0.0, 1.0, 0.0)),
    ],
)
def test_half_turn_sign_is_fixed_by_the_first_non_zero_component(quaternion, canonical):
    x, y, z, w = quaternion
    rotation = pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()
    rows = pose_rows([pin.SE3(rotation, np.array([0.1, -0.2, 0.3]))])
    assert rows.shape == (1, 7)
    np.testing.assert_allclose(rows[0, 3:], canonical, atol=1e-15)
    assert rows[0, 6] == 0.0


# ==================================================================================================
# Paths: standard output, protected inputs and hard links
#
# `-` is standard output on both sides (never the file named `-`), a protected path is refused even before
# it exists, hard links are the same file, and the refusal names the output and the input.
# ==================================================================================================


def test_refusal_names_the_output_and_the_input(tmp_path):
    data = tmp_path / "in.csv"
    data.write_text("x\n1\n")
    with pytest.raises(OutputPathError) as caught:
        ensure_not_protected(str(tmp_path / "." / "in.csv"), [tmp_path / "other.csv", data])
    assert caught.value.path == str(tmp_path / "in.csv")
    assert str(caught.value) == f"{tmp_path / 'in.csv'}: refusing to overwrite the input file {data}"


def test_a_protected_path_not_yet_existing_is_refused_by_name(tmp_path):
    with pytest.raises(OutputPathError, match="refusing to overwrite"):
        ensure_not_protected(tmp_path / "future.csv", [tmp_path / "future.csv"])


def test_hard_links_are_the_same_file_and_other_files_are_not(tmp_path):
    data = tmp_path / "in.csv"
    data.write_text("x\n1\n")
    os.link(data, tmp_path / "hard.csv")
    with pytest.raises(OutputPathError, match="refusing to overwrite the input file"):
        ensure_not_protected(tmp_path / "hard.csv", [data])
    (tmp_path / "other.csv").write_text("y\n")
    ensure_not_protected(tmp_path / "other.csv", [data])
    ensure_not_protected(tmp_path / "new.csv", [data])


def test_dash_is_standard_output_never_the_file_named_dash(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "-").write_text("a file named dash")
    ensure_not_protected("-", [tmp_path / "-"])  # the output is stdout, not that file
    ensure_not_protected(tmp_path / "-", ["-"])  # an input "-" is stdin, not that file
    with pytest.raises(OutputPathError):
        ensure_not_protected(tmp_path / "-", [tmp_path / "-"])


# ==================================================================================================
# Temporaries: leftovers of interrupted commits, names, modes and failures
#
# Which leftover completes an interrupted pair commit and which is removed, live writers' files kept
# (including another user's, simulated), the temporary name, the new file's mode, failures while creating
# or writing a temporary, `pending_temporaries` with symlinks and vanishing entries, and `print_notice`.
# ==================================================================================================


DEAD_PID = 2**22 + 1  # above any pid_max: never a live process


def _leftover(folder: Path, name: str, data: bytes = b"staged", pid: int = DEAD_PID) -> Path:
    path = folder / f".{name}.m3t1r-{pid}-0a.tmp"
    path.write_bytes(data)
    return path


def _urdf_recording(folder: Path, data: bytes, name: str = "m.urdf") -> Path:
    path = folder / name
    path.write_bytes(with_closures_sha256(b"<robot/>", sha256_bytes(data)))
    return path


# -- sweep and pair completion ------------------------------------------------------------------------


def _swept(folder: Path) -> list[str]:
    """The notes of a sweep of `folder` under its lock, as `OutputSet.check` runs it."""
    with folder_lock(folder):
        return sweep_locked(folder)


def test_a_staged_closures_file_named_by_its_urdf_completes_the_commit(tmp_path):
    _urdf_recording(tmp_path, b"new")
    (tmp_path / "m.closures.yaml").write_bytes(b"old")
    leftover = _leftover(tmp_path, "m.closures.yaml", b"new")
    notes = _swept(tmp_path)
    assert (tmp_path / "m.closures.yaml").read_bytes() == b"new" and not leftover.exists()
    assert notes == [f"completed the interrupted write of {tmp_path / 'm.closures.yaml'} (its URDF already named it)"]


def test_a_staged_closures_file_completes_a_pair_whose_closures_file_is_missing(tmp_path):
    _urdf_recording(tmp_path, b"new")
    _leftover(tmp_path, "m.closures.yaml", b"new")
    _swept(tmp_path)
    assert (tmp_path / "m.closures.yaml").read_bytes() == b"new"


@pytest.mark.parametrize("case", ["other digest", "no digest", "no urdf", "already in place"])
def test_other_closures_leftovers_are_removed(tmp_path, case):
    if case == "other digest":
        _urdf_recording(tmp_path, b"something else")
    elif case == "no digest":
        (tmp_path / "m.urdf").write_bytes(b"<robot/>")
    elif case == "already in place":
        _urdf_recording(tmp_path, b"new")
    (tmp_path / "m.closures.yaml").write_bytes(b"new" if case == "already in place" else b"old")
    leftover = _leftover(tmp_path, "m.closures.yaml", b"new")
    notes = _swept(tmp_path)
    assert not leftover.exists()
    assert (tmp_path / "m.closures.yaml").read_bytes() == (b"new" if case == "already in place" else b"old")
    assert notes == [f"removed {leftover}, a temporary file left by an interrupted run"]


def test_only_closures_files_are_ever_completed(tmp_path):
    # "r.json" minus the closures suffix is "", whose URDF would be ".urdf": even if that names
    # the leftover, a report's leftover is removed.
    _urdf_recording(tmp_path, b"new", name=".urdf")
    leftover = _leftover(tmp_path, "r.json", b"new")
    _swept(tmp_path)
    assert not leftover.exists() and not (tmp_path / "r.json").exists()


def test_a_leftover_that_cannot_be_removed_is_noted(tmp_path):
    stuck = tmp_path / f".r.json.m3t1r-{DEAD_PID}-0b.tmp"
    stuck.mkdir()  # unlink of a directory fails
    assert _swept(tmp_path) == [f"could not clean up {stuck}: Is a directory"] and stuck.is_dir()


def test_files_whose_lock_is_held_are_kept_whatever_pid_they_name(tmp_path):
    """Liveness is the writer's flock, not its pid: a file naming a pid that does not exist here (a
    writer in another container or on another host) is kept while its lock is held, and one naming
    this very process is removed when nobody holds it (a reused pid)."""
    elsewhere = _leftover(tmp_path, "r.json", pid=DEAD_PID)
    reused = _leftover(tmp_path, "s.json", pid=os.getpid())
    child = process_holding_flock(elsewhere)
    try:
        assert _swept(tmp_path) == [f"removed {reused}, a temporary file left by an interrupted run"]
        assert elsewhere.exists() and not reused.exists()
    finally:
        child.kill()
        child.wait()
    _swept(tmp_path)  # its writer gone, the lock with it
    assert not elsewhere.exists()


@pytest.mark.parametrize("error", [OSError(errno.ENOLCK, "No locks available"), OSError(errno.EINVAL, "x")])
def test_a_file_whose_lock_cannot_be_probed_is_kept(tmp_path, monkeypatch, error):
    def flock(descriptor, operation):
        raise error

    leftover = _leftover(tmp_path, "r.json")
    with folder_lock(tmp_path):  # the folder's own lock first, then every probe fails
        monkeypatch.setattr(temporaries.fcntl, "flock", flock)
        assert sweep_locked(tmp_path) == [] and leftover.exists()


# -- temporary names and writes ---------------------------------------------------------------------


def test_temporary_name_is_hidden_and_names_the_process(tmp_path):
    path = temporary_path(tmp_path / "out.csv")
    assert path.parent == tmp_path
    assert re.fullmatch(rf"\.out\.csv\.m3t1r-{os.getpid()}-[0-9a-f]{{12}}\.tmp", path.name)


def test_a_temporary_name_fits_the_folders_name_limit(tmp_path):
    limit = os.pathconf(tmp_path, "PC_NAME_MAX")
    for name in ("é" * 100 + ".csv", "x" * (limit - 4) + ".csv"):  # bytes, not characters, count
        path = temporary_path(tmp_path / name)
        assert len(os.fsencode(path.name)) <= limit and path.name.startswith(".")
        assert path.name[1:].encode()[:20] == name.encode()[:20]  # still recognisable by eye
        path.write_bytes(b"")
        assert pending_temporaries(tmp_path / name) == [path]
        assert pending_temporaries(tmp_path / (name[:-5] + "y.csv")) == []  # same prefix, other name
        path.unlink()


def _flock_is_held(path: Path) -> bool:
    """Whether another open file holds `path`'s exclusive flock (what a second writer would see)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(descriptor)


def test_a_claimed_file_is_locked_registered_and_names_its_run(tmp_path):
    temporary, descriptor = claim_temporary(tmp_path / "out.csv")
    try:
        assert temporary in _LIVE_TEMPORARIES and _flock_is_held(temporary)
        assert temporaries.live_writer(tmp_path / "out.csv") is None  # this process's own claim
        assert temporary.read_bytes().startswith(f"m3t1r run in progress: pid {os.getpid()} on ".encode())
    finally:
        temporaries.release_temporary(temporary, descriptor, remove=True)
    assert not temporary.exists() and temporary not in _LIVE_TEMPORARIES


def test_a_new_file_gets_the_umask_mode(tmp_path):
    previous = os.umask(0o022)
    try:
        temporary, descriptor = claim_temporary(tmp_path / "new.csv")
    finally:
        os.umask(previous)
    try:
        write_claimed(tmp_path / "new.csv", temporary, descriptor, b"data")
        assert os.stat(temporary).st_mode & 0o777 == 0o644 and temporary.read_bytes() == b"data"
    finally:
        temporaries.release_temporary(temporary, descriptor, remove=True)


def test_an_existing_temporary_name_is_never_reused(tmp_path, monkeypatch):
    taken = tmp_path / ".out.csv.m3t1r-1-00.tmp"
    taken.write_bytes(b"someone else's")
    monkeypatch.setattr(temporaries, "temporary_path", lambda target: taken)
    with pytest.raises(OutputPathError) as caught:
        claim_temporary(tmp_path / "out.csv")
    assert caught.value.path == str(tmp_path / "out.csv")
    assert str(caught.value) == (
        f"{tmp_path / 'out.csv'}: cannot create a file in {tmp_path}: File exists; nothing was written"
    )
    assert taken.read_bytes() == b"someone else's"


def test_a_failed_write_empties_the_claimed_file(tmp_path, monkeypatch):
    def fsync(descriptor):
        raise OSError(errno.ENOSPC, "No space left on device")

    temporary, descriptor = claim_temporary(tmp_path / "out.csv")
    monkeypatch.setattr(temporaries.os, "fsync", fsync)
    try:
        with pytest.raises(OutputPathError) as caught:
            write_claimed(tmp_path / "out.csv", temporary, descriptor, b"data" * 1000)
        assert (
            str(caught.value) == f"{tmp_path / 'out.csv'}: write failed, file left unchanged: No space left on device"
        )
        assert temporary.stat().st_size == 0 and not (tmp_path / "out.csv").exists()
    finally:
        temporaries.release_temporary(temporary, descriptor, remove=True)


def test_an_interrupted_claim_removes_and_forgets_the_temporary(tmp_path, monkeypatch):
    def write(descriptor, data):
        raise KeyboardInterrupt

    monkeypatch.setattr(temporaries.os, "write", write)
    before = set(_LIVE_TEMPORARIES)
    with pytest.raises(KeyboardInterrupt):
        claim_temporary(tmp_path / "out.csv")
    assert list(tmp_path.iterdir()) == [] and set(_LIVE_TEMPORARIES) == before


# -- pending_temporaries ----------------------------------------------------------------------------


def test_pending_temporaries_include_a_dangling_symlink(tmp_path):
    link = tmp_path / f".out.csv.m3t1r-{DEAD_PID}-0c.tmp"
    link.symlink_to(tmp_path / "nowhere")
    assert pending_temporaries(tmp_path / "out.csv") == [link]


def test_pending_temporaries_skip_an_entry_that_vanished(tmp_path, monkeypatch):
    class Entry:
        def __init__(self, name: str, mtime: float | None) -> None:
            self.name, self.mtime = name, mtime

        def stat(self, follow_symlinks=True):
            if self.mtime is None:
                raise FileNotFoundError(errno.ENOENT, "gone")
            return os.stat_result((0, 0, 0, 0, 0, 0, 0, 0, self.mtime, 0))

    entries = [
        Entry(".out.csv.m3t1r-1-0a.tmp", 2.0),
        Entry(".out.csv.m3t1r-2-0b.tmp", None),
        Entry(".out.csv.m3t1r-3-0c.tmp", 1.0),
        Entry("out.csv", 0.0),
    ]
    monkeypatch.setattr(temporaries.os, "scandir", lambda folder: iter(entries))
    assert pending_temporaries(tmp_path / "out.csv") == [
        tmp_path / ".out.csv.m3t1r-3-0c.tmp",
        tmp_path / ".out.csv.m3t1r-1-0a.tmp",
    ]


# -- print_notice --------------------------------------------------------------------------------------


def test_print_notice_writes_a_flushed_line_on_stderr(monkeypatch):
    class Stream:
        def __init__(self) -> None:
            self.events: list[str] = []

        def write(self, text):
            self.events.append(text)

        def flush(self):
            self.events.append("<flush>")

    stream = Stream()
    monkeypatch.setattr(sys, "stderr", stream)
    print_notice("removed x")
    assert "".join(stream.events[:-1]) == "m3t1r: removed x\n" and stream.events[-1] == "<flush>"
