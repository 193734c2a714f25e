"""Install m3t1r the four ways a user does, each into a fresh virtual environment, and check that every
one runs the compiled Newton loop.

1. `pip install .`;
2. `pip install --force-reinstall .` over it (Pinocchio then already installed, without Eigen's headers);
3. `pip wheel .` by that environment's pip, the wheel installed into a new environment;
4. `pip install -e .` and `python tools/build_native.py` (what `make` does).

Each build compiles the module (a few minutes of g++ each; run it on a quiet machine) and needs PyPI
or a pip cache. The tree is copied first (without .venv, .git or a compiled module), so the checkout
is never built in. Exits 1 if an install lacks the module or a wheel is tagged for any platform.

Run: python tools/check_installs.py [--python python3.11] [--work DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIPPED = (".git", ".venv", "build", "dist", "mutants", "demo_out", "__pycache__", "*.so", "*.partial", "*.egg-info")
# Run in the new environment from outside the tree, so that it imports the installed package.
CHECK = "from m3t1r.model import native; print(native.status()); raise SystemExit(0 if native.AVAILABLE else 1)"


def run(command: list[str | Path], cwd: Path) -> None:
    print("  $", " ".join(str(part) for part in command), flush=True)
    subprocess.run([str(part) for part in command], cwd=cwd, env=_environment(), check=True)


def _environment() -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "M3T1R_PURE_PYTHON")}
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    return env


def new_venv(python: str, folder: Path) -> Path:
    subprocess.run([python, "-m", "venv", str(folder)], check=True)
    return folder / "bin"


def uses_the_compiled_loop(bin_dir: Path) -> bool:
    found = subprocess.run(
        [str(bin_dir / "python"), "-c", CHECK], cwd="/", env=_environment(), capture_output=True, text=True
    )
    print("  status:", (found.stdout + found.stderr).strip().splitlines()[-1:] or ["(nothing)"])
    return found.returncode == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--python", default=sys.executable, help="interpreter of the new environments")
    parser.add_argument("--work", type=Path, help="folder for the environments and the copy (default: a temporary one)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        work = args.work or Path(scratch)
        tree = work / "tree"
        shutil.rmtree(tree, ignore_errors=True)
        shutil.copytree(ROOT, tree, ignore=shutil.ignore_patterns(*SKIPPED))
        results = check_all(args.python, work, tree)
    print("\ninstall path                              compiled loop   seconds")
    for name, (ok, seconds) in results.items():
        print(f"{name:42s}{'yes' if ok else 'NO':16s}{seconds:7.0f}")
    return 0 if all(ok for ok, _ in results.values()) else 1


def check_all(python: str, work: Path, tree: Path) -> dict[str, tuple[bool, float]]:
    results: dict[str, tuple[bool, float]] = {}
    first = new_venv(python, work / "venv-install")
    results["pip install ."] = _timed(
        lambda: run([first / "pip", "install", "."], tree) or uses_the_compiled_loop(first)
    )
    results["pip install --force-reinstall ."] = _timed(
        lambda: run([first / "pip", "install", "--force-reinstall", "."], tree) or uses_the_compiled_loop(first)
    )
    wheels = work / "wheels"
    shutil.rmtree(wheels, ignore_errors=True)

    def wheel_then_install() -> bool:
        run([first / "pip", "wheel", "--no-deps", "-w", wheels, "."], tree)
        (wheel,) = wheels.glob("m3t1r-*.whl")
        print("  wheel:", wheel.name)
        fresh = new_venv(python, work / "venv-wheel")
        run([fresh / "pip", "install", wheel], work)
        return not wheel.name.endswith("-none-any.whl") and uses_the_compiled_loop(fresh)

    results["pip wheel ., wheel into a new venv"] = _timed(wheel_then_install)

    def editable() -> bool:
        bin_dir = new_venv(python, work / "venv-editable")
        run([bin_dir / "pip", "install", "-e", ".[native]"], tree)
        run([bin_dir / "python", "tools/build_native.py"], tree)  # `make native`: up to date after the install
        return uses_the_compiled_loop(bin_dir)

    results["pip install -e .[native], make native"] = _timed(editable)
    return results


def _timed(step) -> tuple[bool, float]:
    start = time.perf_counter()
    try:
        ok = bool(step())
    except subprocess.CalledProcessError as failure:
        print(f"  failed: {failure}")
        ok = False
    return ok, time.perf_counter() - start


if __name__ == "__main__":
    sys.exit(main())
