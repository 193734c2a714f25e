"""The documentation cites only what a clone has: every repository path named in the README, docs/,
models/README.md, benchmarks/*.md, the CHANGELOG and the docstrings and comments of the code exists,
and no text points outside the repository."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = ("README.md", "CHANGELOG.md", "models/README.md", "docs/*.md", "benchmarks/*.md")
CODE = ("src/**/*.py", "tools/*.py", "benchmarks/*.py", "notebooks/*.py", "hatch_build.py")
TOP_FOLDERS = ("benchmarks", "docs", "models", "notebooks", "src", "tests", "tools")
PACKAGE_FOLDERS = ("m3t1r", "app", "calibration", "io", "model", "paper")  # `app/cli.py`: in src/m3t1r

# A path from the repository root (`docs/design.md`, `src/m3t1r/model/poe.py`, `models/m3t1r.urdf`) or
# inside the package (`m3t1r/app/cli.py`, `app/cli.py`); not preceded by a word, dot or slash, so that URLs, `../x`
# and absolute paths are not read as one.
_FIELD = r"\{[^{}\s]*\}"  # an f-string's replacement field, read as any name
_CITED = re.compile(
    r"(?<![\w./-])((?:%s)/(?:[\w.*/-]|%s)*(?:[\w*]|%s))" % ("|".join(TOP_FOLDERS + PACKAGE_FOLDERS), _FIELD, _FIELD)
)
# A code span that reads as a relative path with a file extension, whatever folder it starts with
# (`.ci/run.sh`, `doc/design.md`, `instruments/vicon.py`); not `../x`, an absolute path or a URL.
_BACKQUOTED = re.compile(r"`(?!\.\./)([\w.-]+(?:/[^`\s/:]+)+\.[A-Za-z]\w*)`")
_LINK = re.compile(r"\]\((?!https?:|mailto:|#)([^)#\s]+)")
_TEST_ID = re.compile(r"(?:tests/)?(test_\w+\.py)::(\w+)|(?<=`)::(\w+)")  # `::name`: in the file cited last
_OUTSIDE = re.compile(r"shared/design|/work/|/tmp/wt/|\.\./\.\./")


def _files(patterns: tuple[str, ...]) -> list[Path]:
    return sorted({path for pattern in patterns for path in ROOT.glob(pattern)})


def _comments_and_strings(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every comment and string literal (docstrings included) of a Python file."""
    tokens = tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline)
    return [(t.start[0], t.string) for t in tokens if t.type in (tokenize.COMMENT, tokenize.STRING)]


def _texts() -> list[tuple[Path, int, str]]:
    texts = [(path, 1, path.read_text(encoding="utf-8")) for path in _files(DOCUMENTS)]
    texts += [(path, line, text) for path in _files(CODE) for line, text in _comments_and_strings(path)]
    return texts


def _exists(cited: str) -> bool:
    """Whether a cited path names something in the checkout; a placeholder (`notebooks/NAME.py`,
    `tests/test_MODULE.py`, `build/<module>.log`), a pattern (`benchmarks/bench_*.py`) or an f-string's field
    (`bench_{name}.py`) stands for the files it matches."""
    path = re.sub(_FIELD, "*", cited)
    first = path.split("/")[0]
    if first in PACKAGE_FOLDERS:
        path = ("src/" if first == "m3t1r" else "src/m3t1r/") + path
    if re.search(r"[A-Z]{3,}|<\w+>", Path(path).stem.replace("README", "")):
        return True  # a placeholder a reader fills in (`NAME`, `<module>`)
    return any(ROOT.glob(path)) if "*" in path else (ROOT / path).exists()


def _line(text: str, start: int, first_line: int) -> int:
    return first_line + text.count("\n", 0, start)


def test_every_cited_repository_path_exists():
    missing = [
        f"{path.relative_to(ROOT)}:{_line(text, m.start(), line)}: {m.group(1)}"
        for path, line, text in _texts()
        for m in _CITED.finditer(text)
        if not _exists(m.group(1))
    ]
    assert not missing, "cited paths that the repository does not have:\n" + "\n".join(missing)


def test_every_backquoted_path_exists():
    """A path in a code span that starts with a folder the check above does not read (a typo such as
    `doc/`, a hidden folder, a package sub-folder cited without its parents) names a file too."""
    known = TOP_FOLDERS + PACKAGE_FOLDERS
    missing = [
        f"{path.relative_to(ROOT)}:{_line(text, m.start(), line)}: {m.group(1)}"
        for path, line, text in _texts()
        for m in _BACKQUOTED.finditer(text)
        if m.group(1).split("/")[0] not in known and not _exists(m.group(1))
    ]
    assert not missing, "paths in code spans that the repository does not have:\n" + "\n".join(missing)


@pytest.mark.parametrize("document", _files(DOCUMENTS), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_of_a_document_resolves_inside_the_repository(document: Path):
    text = document.read_text(encoding="utf-8")
    broken = []
    for m in _LINK.finditer(text):
        target = (document.parent / m.group(1)).resolve()
        if not target.is_relative_to(ROOT) or not target.exists():
            broken.append(f"{document.relative_to(ROOT)}:{_line(text, m.start(), 1)}: {m.group(1)}")
    assert not broken, "links to nothing in the repository:\n" + "\n".join(broken)


def _test_functions(file_name: str) -> set[str]:
    path = ROOT / "tests" / file_name
    if not path.is_file():
        return set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)}


def test_every_cited_test_exists():
    """A document citing a test by its id (`test_io.py::test_x`, or `::test_y` after it) names a test
    function of that file: a renamed or removed test leaves no dangling reference."""
    missing = []
    for path, line, text in _texts():
        cited_file = None
        for m in _TEST_ID.finditer(text):
            cited_file = m.group(1) or cited_file
            name = m.group(2) or m.group(3)
            if cited_file is None or name not in _test_functions(cited_file):
                missing.append(f"{path.relative_to(ROOT)}:{_line(text, m.start(), line)}: {cited_file}::{name}")
    assert not missing, "cited tests that do not exist:\n" + "\n".join(missing)


def test_no_text_points_outside_the_repository():
    outside = [
        f"{path.relative_to(ROOT)}:{_line(text, m.start(), line)}: {m.group(0)}"
        for path, line, text in _texts()
        for m in _OUTSIDE.finditer(text)
    ]
    assert not outside, "texts citing files a clone does not have:\n" + "\n".join(outside)


def test_the_scan_reads_what_it_claims_to():
    """The checks above look at the documents and the code they say they do, and tell a cited path
    that exists from one that does not."""
    names = {str(path.relative_to(ROOT)) for path, _, _ in _texts()}
    assert {"README.md", "CHANGELOG.md", "models/README.md", "docs/design.md", "src/m3t1r/model/poe.py"} <= names
    text = "see `docs/design.md`, m3t1r/model/poe.py, app/cli.py, f'tools/{name}.py' and docs/none.md."
    cited = [m.group(1) for m in _CITED.finditer(text)]
    assert cited == ["docs/design.md", "m3t1r/model/poe.py", "app/cli.py", "tools/{name}.py", "docs/none.md"]
    assert [_exists(c) for c in cited] == [True, True, True, True, False]
    assert _exists("notebooks/NAME.py") and _exists("benchmarks/bench_*.py") and not _exists("tools/bench_*.py")
    assert not _CITED.findall("https://example.org/docs/x.md ../docs/x.md /usr/src/x.py")
    spans = "`.ci/run.sh`, `doc/design.md`, `https://example.org/x.md`, `../docs/x.md`, `/usr/x.py`, `a b/c.md`"
    assert _BACKQUOTED.findall(spans) == [".ci/run.sh", "doc/design.md"]
    assert not _exists("doc/design.md") and _exists("build/mutation/<module>.survivors.txt")
    ids = [(m.group(1), m.group(2) or m.group(3)) for m in _TEST_ID.finditer("`test_docs.py::test_x`, `::test_y`")]
    assert ids == [("test_docs.py", "test_x"), (None, "test_y")]
    assert "test_every_cited_test_exists" in _test_functions("test_docs.py") and not _test_functions("test_none.py")


def test_the_readme_is_a_front_page_of_at_most_300_lines():
    """Issue 25: the README is what a newcomer reads first; history and long tables live in docs/."""
    lines = (ROOT / "README.md").read_text(encoding="utf-8").count("\n")
    assert lines <= 300, f"README.md has {lines} lines"
