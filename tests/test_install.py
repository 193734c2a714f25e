"""Installs keep the compiled Newton loop or fail saying why (hatch_build.py, tools/build_native.py).

Each test builds a copy of the source tree through hatchling's PEP 517 hooks with `CXX` naming a
compiler that does not exist, so nothing compiles and each build takes about a second: the build
fails naming the missing compiler and the variable that would let it through, and M3T1R_PURE_PYTHON=1
gives a pure-Python package. A real compile takes minutes: tools/check_installs.py runs the four
install paths (pip install, --force-reinstall, pip wheel, editable) in fresh virtual environments.
"""

import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODULE_GLOB = "_native_newton*.so"


def _tree(tmp_path: Path, with_module: bool = False) -> Path:
    """What a build reads, copied (mtimes kept); the compiled module only if `with_module`."""
    tree = tmp_path / "tree"
    (tree / "tools").mkdir(parents=True)
    for name in ("pyproject.toml", "hatch_build.py", "README.md", "LICENSE", ".gitignore"):
        shutil.copy2(ROOT / name, tree / name)
    shutil.copy2(ROOT / "tools" / "build_native.py", tree / "tools")
    shutil.copytree(ROOT / "models", tree / "models", ignore=shutil.ignore_patterns("__pycache__"))
    skipped = ("__pycache__", "*.partial") + (() if with_module else (MODULE_GLOB,))
    shutil.copytree(ROOT / "src", tree / "src", ignore=shutil.ignore_patterns(*skipped))
    return tree


def _build(tree: Path, kind: str, pure_python: bool) -> tuple[subprocess.CompletedProcess, Path]:
    """hatchling's build_wheel or build_editable in `tree`, with no C++ compiler; (process, output folder)."""
    import hatchling  # noqa: F401  (the build backend, a dev dependency: missing, these tests fail, not skip)

    out = tree.parent / "dist"
    out.mkdir(exist_ok=True)
    env = {**os.environ, "CXX": "no-such-compiler"}
    env.pop("M3T1R_PURE_PYTHON", None)
    if pure_python:
        env["M3T1R_PURE_PYTHON"] = "1"
    code = f"import sys, hatchling.build as backend; print(backend.build_{kind}(sys.argv[1]))"
    process = subprocess.run(
        [sys.executable, "-c", code, str(out)], cwd=tree, env=env, capture_output=True, text=True, timeout=120
    )
    return process, out


def test_a_wheel_build_without_a_compiler_fails_naming_the_compiler_and_the_way_out(tmp_path):
    process, out = _build(_tree(tmp_path), "wheel", pure_python=False)
    assert process.returncode != 0
    assert "cannot build the compiled Newton loop" in process.stderr
    assert "no C++ compiler: 'no-such-compiler'" in process.stderr
    assert "M3T1R_PURE_PYTHON=1" in process.stderr
    assert "Traceback" not in process.stderr
    assert not list(out.glob("*.whl"))


def test_the_pure_python_variable_builds_a_wheel_for_any_platform_without_the_module(tmp_path):
    process, out = _build(_tree(tmp_path), "wheel", pure_python=True)
    assert process.returncode == 0, process.stderr
    (wheel,) = out.glob("*.whl")
    assert wheel.name == "m3t1r-0.1.0-py3-none-any.whl"
    names = zipfile.ZipFile(wheel).namelist()
    assert "m3t1r/model/native.py" in names
    assert not [name for name in names if name.endswith(".so")]
    assert [name for name in names if name.startswith("m3t1r-0.1.0.dist-info/") and name.endswith("/LICENSE")]


def test_an_editable_build_without_a_compiler_fails_and_leaves_no_module_behind(tmp_path):
    tree = _tree(tmp_path)
    process, out = _build(tree, "editable", pure_python=False)
    assert process.returncode != 0
    assert "no C++ compiler: 'no-such-compiler'" in process.stderr
    assert "M3T1R_PURE_PYTHON=1" in process.stderr
    model = tree / "src" / "m3t1r" / "model"
    assert not list(model.glob(MODULE_GLOB)) and not list(model.glob("*.partial"))
    process, out = _build(tree, "editable", pure_python=True)
    assert process.returncode == 0, process.stderr
    assert len(list(out.glob("*.whl"))) == 1 and not list(model.glob(MODULE_GLOB))


def test_an_editable_build_keeps_an_up_to_date_module_without_compiling(tmp_path):
    if not list((ROOT / "src" / "m3t1r" / "model").glob(MODULE_GLOB)):
        pytest.fail("no compiled module in the tree: run `make native` (python tools/build_native.py)")
    tree = _tree(tmp_path, with_module=True)
    (module,) = (tree / "src" / "m3t1r" / "model").glob(MODULE_GLOB)
    before = module.stat().st_mtime_ns
    process, out = _build(tree, "editable", pure_python=False)
    assert process.returncode == 0, process.stderr
    assert module.stat().st_mtime_ns == before


def _build_native():
    import importlib.util

    spec = importlib.util.spec_from_file_location("build_native_under_test", ROOT / "tools" / "build_native.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_header_trees_are_found_in_the_installed_distributions_files():
    """Through the metadata of cmeel-eigen, libpinocchio (or pin) and cmeel-boost, not `import pinocchio`."""
    folders = _build_native().include_dirs()
    for probe in ("Eigen/Core", "pinocchio/multibody.hpp", "boost/version.hpp", "Python.h"):
        assert any((folder / probe).is_file() for folder in folders), probe


def test_a_missing_header_tree_is_named_with_the_distribution_to_install(monkeypatch):
    build_native = _build_native()
    monkeypatch.setitem(build_native.HEADER_TREES, "Eigen", (("no-such-eigen",), "include/eigen3", "Eigen/Core"))
    with pytest.raises(
        SystemExit,
        match=r"Eigen's headers not found: no installed no-such-eigen distribution "
        r"ships include/eigen3/Eigen/Core \(pip install no-such-eigen\)",
    ):
        build_native.include_dirs()


def test_a_module_is_up_to_date_by_its_sources_stamp_not_by_file_times(tmp_path):
    """A module copied into a checkout (or sources checked out after a build) has any file time: the
    build trusts the stamp the module carries, the hash m3t1r checks at import."""
    tree = _tree(tmp_path, with_module=True)
    spec = importlib.util.spec_from_file_location("build_native_in_tree", tree / "tools" / "build_native.py")
    build_native = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build_native)
    (module,) = (tree / "src" / "m3t1r" / "model").glob(MODULE_GLOB)
    assert build_native.up_to_date(module)
    os.utime(module, (0, 0))  # older than its sources: still the module they build
    assert build_native.up_to_date(module)
    header = tree / "src" / "m3t1r" / "model" / "_native_core.hpp"
    header.write_text(header.read_text() + "\n// an edit\n")
    os.utime(module, None)  # newer than the edited header, and stale all the same
    assert not build_native.up_to_date(module)
