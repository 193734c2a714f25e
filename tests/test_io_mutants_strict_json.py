"""io.strict_json tests that kill mutants the behaviour tests let through (docs/mutation.md): the exact
text (two-space indent, final newline) and the conversion of booleans and paths."""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath

import numpy as np

from m3t1r.io.strict_json import json_text


def test_exact_text_with_two_space_indent_and_a_final_newline():
    document = {"a": [1, 2.5], "b": {"c": None}}
    assert json_text(document) == '{\n  "a": [\n    1,\n    2.5\n  ],\n  "b": {\n    "c": null\n  }\n}\n'


def test_booleans_stay_booleans():
    text = json_text({"t": True, "f": False, "np_t": np.True_, "np_f": np.False_, "array": np.array([True, False])})
    assert json.loads(text) == {"t": True, "f": False, "np_t": True, "np_f": False, "array": [True, False]}
    assert '"t": true' in text and '"np_t": true' in text


def test_paths_become_their_string():
    assert json.loads(json_text({"file": Path("/tmp/a.csv"), "pure": PurePosixPath("b/c.urdf")})) == {
        "file": "/tmp/a.csv", "pure": "b/c.urdf"}


def test_non_finite_values_everywhere_become_null():
    document = {"x": float("nan"), 1: [np.float32("inf"), (-np.inf, 2)], "m": np.array([[np.nan, 1.0]])}
    assert json.loads(json_text(document)) == {"x": None, "1": [None, [None, 2]], "m": [[None, 1.0]]}
