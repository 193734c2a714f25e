"""Atomic writes, protected inputs, and the numeric CSV reader/writer with its error reporting."""

from __future__ import annotations

import math
import os
import stat
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from m3t1r.errors import DataFileError, InvalidInputError, OutputPathError
from m3t1r.io.outputs import atomic_write_bytes, atomic_write_text
from m3t1r.io.paths import ensure_not_protected
from m3t1r.io.poses import POSE_COLUMNS, pose_rows, poses_from_table
from m3t1r.io.tables import Table, read_header, read_table, table_text, write_table

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
    data = np.vstack([rng.normal(scale=10.0, size=(50, 4)) * 10.0 ** rng.integers(-12, 12, size=(50, 4)),
                      np.reshape(awkward, (2, 4))])
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
    text = ("\ufeff# produced by a test\r\n\r\n   # indented comment\r\n x , y \r\n1,2\r\n\r\n"
            "# between rows\r\n 3 , 4e0 \r\n\n")
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

    with pytest.raises(DataFileError, match=r"quaternion \(qx, qy, qz, qw\) norm 0.98 is not 1 \(tolerance 1e-06\)") as caught:
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
