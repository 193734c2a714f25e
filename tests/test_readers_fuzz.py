"""Property-based tests: the CSV and YAML readers given random bytes and random cells (issue 10, item 8).

Whatever the content, a reader returns a validated result or raises a typed m3t1r error that
names the file; never a traceback from the standard library, numpy, yaml or Pinocchio.
"""

from __future__ import annotations

import copy
import tempfile
import warnings
from pathlib import Path

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from m3t1r.app.datasets import read_actuators, read_measurements, read_targets
from m3t1r.errors import DataFileError, M3t1rError, ModelFileError, ModelWarning
from m3t1r.io.tables import read_table
from m3t1r.model.description import Mechanism, nominal_model_paths

NOMINAL = Mechanism.load()
NOMINAL_URDF, NOMINAL_CLOSURES = nominal_model_paths()
NOMINAL_DOC = yaml.safe_load(NOMINAL_CLOSURES.read_text())
FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SLOW = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

COLUMNS = [*NOMINAL.actuated_joints, "x", "y", "z", "qx", "qy", "qz", "qw", "theta", "q12", "bogus", ""]
# Cells that are numbers, almost numbers, and things that break naive parsers.
CELL = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(min_value=-0.5, max_value=0.5).map(repr),
    st.integers(min_value=-(10**400), max_value=10**400).map(str),
    st.sampled_from(
        [
            "",
            " ",
            "nan",
            "-inf",
            "Infinity",
            "1e300",
            "-1e309",
            "1_000",
            "0x10",
            "1,5",
            '"1"',
            '"',
            "1e",
            ".",
            "-",
            "+.5",
            "\u00a01",
            "１",
            "1\r2",
            "# 1",
            "\ufeff0.1",
            "0.1\t",
        ]
    ),
    st.text(max_size=6),
)


def _write(folder: str, name: str, data: bytes) -> Path:
    path = Path(folder) / name
    path.write_bytes(data)
    return path


def _csv(header: list[str], rows: list[list[str]], newline: str) -> bytes:
    lines = [",".join(header), *(",".join(row) for row in rows)]
    return newline.join(lines).encode("utf-8", "surrogatepass")


@FAST
@given(st.binary(max_size=400))
def test_csv_reader_on_random_bytes(data):
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "t.csv", data)
        for read in (
            lambda: read_table(path, required=["a"], optional=["b"]),
            lambda: read_actuators(path, NOMINAL),
            lambda: read_targets(path),
            lambda: read_measurements(path, NOMINAL),
        ):
            try:
                read()
            except DataFileError as exc:
                assert str(path) in str(exc)


@FAST
@given(
    header=st.lists(st.sampled_from(COLUMNS), min_size=1, max_size=12),
    rows=st.lists(st.lists(CELL, min_size=0, max_size=12), min_size=0, max_size=4),
    newline=st.sampled_from(["\n", "\r\n", "\r"]),
    valid_prefix=st.booleans(),
)
def test_csv_readers_on_random_cells(header, rows, newline, valid_prefix):
    if valid_prefix:  # a plausible measurement file with random cells in it
        header = [*NOMINAL.actuated_joints, "x", "y", "z", "qx", "qy", "qz", "qw"]
        rows = [(row + ["0.1"] * len(header))[: len(header)] for row in rows] or [["0"] * len(header)]
    try:
        data = _csv(header, rows, newline)
    except UnicodeEncodeError:
        return
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "m.csv", data)
        for read in (
            lambda: read_measurements(path, NOMINAL),
            lambda: read_targets(path),
            lambda: read_actuators(path, NOMINAL),
        ):
            try:
                result = read()
            except DataFileError as exc:
                assert str(path) in str(exc)
            else:
                values = result[0] if isinstance(result, tuple) else result.measurements.actuators
                if isinstance(values, np.ndarray):
                    assert np.isfinite(values).all()


@SLOW
@given(st.binary(max_size=300))
def test_closures_reader_on_random_bytes(data):
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "m.closures.yaml", data)
        try:
            Mechanism.load(NOMINAL_URDF, path)
        except ModelFileError as exc:
            assert str(path) in str(exc)


YAML_VALUE = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats()
    | st.text(max_size=8)
    | st.sampled_from(["P_I", "q11", "3D", "6D", "base", "platform"]),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=5), children, max_size=3),
    max_leaves=8,
)


@SLOW
@given(data=st.data())
def test_closures_reader_on_random_cells(data):
    doc = copy.deepcopy(NOMINAL_DOC)
    # Replace one field, or one item inside a closure, or one home value, by a random value.
    where = data.draw(st.sampled_from(["top", "closure", "home", "chain", "delete"]))
    if where == "top":
        doc[data.draw(st.sampled_from(sorted(doc)))] = data.draw(YAML_VALUE)
    elif where == "closure":
        closure = doc["closures"][data.draw(st.integers(0, len(doc["closures"]) - 1))]
        closure[data.draw(st.sampled_from(["name", "type", "frame_a", "frame_b", "rows"]))] = data.draw(YAML_VALUE)
    elif where == "home":
        doc["home"][data.draw(st.sampled_from(sorted(doc["home"])))] = data.draw(YAML_VALUE)
    elif where == "chain":
        doc["principal_chains"] = data.draw(YAML_VALUE)
    else:
        del doc[data.draw(st.sampled_from(sorted(doc)))]
    with tempfile.TemporaryDirectory() as folder:
        path = _write(folder, "m.closures.yaml", yaml.safe_dump(doc, allow_unicode=True).encode("utf-8"))
        try:
            with warnings.catch_warnings():
                # A home value a little off is repaired by Newton with a ModelWarning (its own tests
                # are in test_mechanisms); here only refusals and crashes matter.
                warnings.simplefilter("ignore", ModelWarning)
                Mechanism.load(NOMINAL_URDF, path)
        except M3t1rError as exc:
            assert str(path) in str(exc)
