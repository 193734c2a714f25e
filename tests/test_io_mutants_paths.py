"""io.paths tests that kill mutants the behaviour tests let through (docs/mutation.md): `-` is standard
output on both sides (never the file named `-`), a protected path is refused even before it exists,
hard links are the same file, and the refusal names the output and the input."""

from __future__ import annotations

import os

import pytest

from m3t1r.errors import OutputPathError
from m3t1r.io.paths import ensure_not_protected


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
