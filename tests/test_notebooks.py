"""The tutorial notebooks (notebooks/*.ipynb) run top to bottom and are committed without outputs.

Each notebook is executed with nbclient in a kernel that runs this interpreter (sys.executable):
a kernelspec pointing at it is written into a temporary JUPYTER_PATH, so a user-level `python3`
kernelspec for some other Python cannot be picked up. The kernel's working directory is a
temporary folder, so the files a notebook writes (its `_out/`) never land in the repository.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
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


def test_there_are_notebooks():
    names = {path.name for path in NOTEBOOKS}
    assert {"01_model_and_kinematics.ipynb", "02_paper_simulation_study.ipynb",
            "03_closed_loop_calibration_and_compensation.ipynb"} <= names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_notebook_is_stripped(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for index, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name} cell {index} has outputs: strip them (notebooks/build_notebooks.py)"
            assert cell.execution_count is None, f"{path.name} cell {index} has an execution count"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, kernel_name, tmp_path):
    nb = nbformat.read(path, as_version=4)
    # One extra cell, on the executed copy only: which interpreter did the kernel run?
    nb.cells.append(nbformat.v4.new_code_cell("import sys\nprint(sys.prefix)\nprint(sys.executable)"))
    client = nbclient.NotebookClient(nb, kernel_name=kernel_name, timeout=CELL_TIMEOUT, allow_errors=False,
                                     resources={"metadata": {"path": str(tmp_path)}})
    start = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as exc:
        pytest.fail(f"{path.name} failed after {time.perf_counter() - start:.1f} s:\n{exc}", pytrace=False)
    printed = "".join(out.get("text", "") for out in nb.cells[-1].outputs if out.output_type == "stream").split()
    assert printed == [sys.prefix, sys.executable], f"the kernel ran {printed}, not this interpreter"
    for index, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            errors = [out for out in cell.outputs if out.output_type == "error"]
            assert not errors, f"{path.name} cell {index}: {errors[0].ename}: {errors[0].evalue}"
