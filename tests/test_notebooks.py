"""The tutorial notebooks: jupytext scripts (notebooks/*.py) and the notebooks generated from them.

The scripts are the source of truth. Each notebooks/NAME.ipynb is generated from notebooks/NAME.py by
`jupytext --to ipynb notebooks/NAME.py` (`make notebooks` does all of them), committed without
outputs, and must hold the same cells as its script.

Each notebook is executed with nbclient in a kernel that runs this interpreter (sys.executable):
a kernelspec pointing at it is written into a temporary JUPYTER_PATH, so a user-level `python3`
kernelspec for some other Python cannot be picked up. The kernel starts in notebooks/, as Jupyter
starts it, with TMPDIR pointing into pytest's temporary folder: a notebook writes its files into
a temporary folder of its own, and running it must leave no new untracked file in the checkout
(`git status`, compared before and after: other untracked files may exist). The notebooks assert
their own results.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import ipykernel  # noqa: F401  (the kernel the notebooks run on)
import jupytext
import nbclient
import nbformat
import pytest

# The notebook tools are dev dependencies (`make test` installs them): a missing one fails here,
# where an import-or-skip would report the notebooks as passed.

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK_DIR = ROOT / "notebooks"
SCRIPTS = sorted(NOTEBOOK_DIR.glob("*.py"))
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
KERNEL_NAME = "m3t1r-test-python"
CELL_TIMEOUT = 300  # [s] per cell; each notebook takes a few seconds in total


@pytest.fixture(scope="module")
def kernel_name(tmp_path_factory) -> str:
    """A kernelspec that launches this very interpreter, on a private JUPYTER_PATH."""
    root = tmp_path_factory.mktemp("jupyter")
    spec_dir = root / "kernels" / KERNEL_NAME
    spec_dir.mkdir(parents=True)
    argv = [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"]
    if sys.version_info >= (3, 11):
        argv.insert(1, "-Xfrozen_modules=off")  # keeps ipykernel's debugger from warning on stderr
    spec = {"argv": argv, "display_name": f"m3t1r tests ({sys.executable})", "language": "python"}
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JUPYTER_PATH", str(root))
        from jupyter_client.kernelspec import KernelSpecManager

        resolved = KernelSpecManager().get_kernel_spec(KERNEL_NAME)
        assert resolved.argv[0] == sys.executable
        yield KERNEL_NAME


def _untracked() -> set[str] | None:
    """The untracked paths of the checkout, one by one (`git status --porcelain --untracked-files=all`),
    or None outside a git checkout. Ignored files (.gitignore) are not listed."""
    if shutil.which("git") is None:
        return None
    done = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=all", "-z"], cwd=ROOT, capture_output=True, check=False
    )
    if done.returncode != 0:
        return None
    return {entry[3:].decode() for entry in done.stdout.split(b"\0") if entry.startswith(b"?? ")}


def test_there_are_notebooks():
    names = {path.stem for path in NOTEBOOKS}
    assert {
        "01_model_and_kinematics",
        "02_paper_simulation_study",
        "03_closed_loop_calibration_and_compensation",
    } <= names
    assert names == {path.stem for path in SCRIPTS}, "every notebook has its jupytext script and vice versa"


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_notebook_matches_its_script(script):
    generated = jupytext.read(script)
    committed = nbformat.read(script.with_suffix(".ipynb"), as_version=4)
    expected = [(cell.cell_type, cell.source) for cell in generated.cells]
    found = [(cell.cell_type, cell.source) for cell in committed.cells]
    assert found == expected, (
        f"{script.with_suffix('.ipynb').name} is out of date: "
        f"run `jupytext --to ipynb notebooks/{script.name}` (or `make notebooks`)"
    )
    assert committed.metadata.get("kernelspec") == generated.metadata.get("kernelspec")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_notebook_is_stripped(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for index, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], (
                f"{path.name} cell {index} has outputs: regenerate it with "
                f"`jupytext --to ipynb notebooks/{path.stem}.py`"
            )
            assert cell.execution_count is None, f"{path.name} cell {index} has an execution count"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs_and_leaves_no_file(path, kernel_name, tmp_path, monkeypatch):
    nb = nbformat.read(path, as_version=4)
    # One extra cell, on the executed copy only: which interpreter did the kernel run?
    nb.cells.append(nbformat.v4.new_code_cell("import sys\nprint(sys.prefix)\nprint(sys.executable)"))
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the kernel's tempfile.mkdtemp() lands here
    client = nbclient.NotebookClient(
        nb,
        kernel_name=kernel_name,
        timeout=CELL_TIMEOUT,
        allow_errors=False,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    before = _untracked()
    start = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as exc:
        pytest.fail(f"{path.name} failed after {time.perf_counter() - start:.1f} s:\n{exc}", pytrace=False)
    after = _untracked()
    printed = "".join(out.get("text", "") for out in nb.cells[-1].outputs if out.output_type == "stream").split()
    assert printed == [sys.prefix, sys.executable], f"the kernel ran {printed}, not this interpreter"
    for index, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            errors = [out for out in cell.outputs if out.output_type == "error"]
            assert not errors, f"{path.name} cell {index}: {errors[0].ename}: {errors[0].evalue}"
    if before is not None and after is not None:
        assert after <= before, f"running {path.name} left files in the checkout: {sorted(after - before)}"
