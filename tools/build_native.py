"""Compile m3t1r's Newton loop (src/m3t1r/model/_native_newton.cpp, _native_core.hpp) in place, for this Python.

Header-only use of Pinocchio's C++ API (the `pin` wheel ships its headers), with Eigen's headers from
`cmeel-eigen` (the Eigen that eigenpy is built against) and Boost's from `cmeel-boost`: the module
builds its own `pinocchio::Model` from arrays and links no Pinocchio library, so it does not depend on
the wheel's binary interface. `make` runs this after installing; without the module the solvers run
their pure-Python Newton (same results, slower; `m3t1r.model.native.AVAILABLE` says which).

Run: python tools/build_native.py [--force]   (about a minute of g++; skipped when up to date)
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pinocchio

SOURCE = Path(__file__).resolve().parents[1] / "src" / "m3t1r" / "model" / "_native_newton.cpp"
# Pinocchio's CMake targets set these (its joint variant needs more than Boost.MPL's default 20 types).
DEFINES = ["BOOST_MPL_LIMIT_LIST_SIZE=30", "BOOST_MPL_LIMIT_VECTOR_SIZE=30", "BOOST_MPL_CFG_NO_PREPROCESSED_HEADERS",
           "BOOST_FUSION_INVOKE_MAX_ARITY=12", "NDEBUG"]


def target() -> Path:
    return SOURCE.with_name("_native_newton" + sysconfig.get_config_var("EXT_SUFFIX"))


def include_dirs() -> list[Path]:
    prefix = Path(pinocchio.__file__).resolve().parents[4]  # .../cmeel.prefix/lib/pythonX.Y/site-packages/pinocchio
    eigen = prefix / "include" / "eigen3"
    if not (eigen / "Eigen" / "Core").exists():
        raise SystemExit(f"build_native: Eigen headers not found at {eigen} (pip install cmeel-eigen)")
    return [prefix / "include", eigen, Path(sysconfig.get_paths()["include"])]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when the module is newer than its source")
    args = parser.parse_args(argv)
    out = target()
    if not args.force and out.exists() and out.stat().st_mtime >= max(p.stat().st_mtime for p in sources(SOURCE)):
        print(f"build_native: {out.name} is up to date")
        return 0
    compile_module(SOURCE, out)
    return 0


def sources(source: Path) -> list[Path]:
    """What the module is compiled from: `source` and the core header it includes (a revision from
    before the header has the file alone). m3t1r.model.native hashes the same files, in this order."""
    return [part for part in (source, source.with_name("_native_core.hpp")) if part.exists()]


def compile_module(source: Path, out: Path) -> None:
    """Compile `source` into the extension module `out` (SystemExit when the compiler fails or is missing)."""
    compiler = os.environ.get("CXX", "g++")
    if shutil.which(compiler) is None:
        raise SystemExit(f"build_native: no C++ compiler ({compiler}); the pure-Python solver will run")
    partial = out.with_suffix(".partial")
    # m3t1r.model.native refuses a module of other source: the stamp covers every file it is built from.
    digest = hashlib.sha256(b"".join(part.read_bytes() for part in sources(source))).hexdigest()
    # -O3: it vectorises the dense LU's row operations (no fast-math: the same rounding as -O2);
    # forward_batch about 10 % faster than with -O2 (benchmarks/README.md).
    command = [compiler, "-O3", "-std=c++17", "-shared", "-fPIC", "-pthread", "-fvisibility=hidden", "-w",
               *(f"-D{d}" for d in DEFINES), f'-DM3T1R_SOURCE_SHA256="{digest}"',
               *(f"-I{d}" for d in include_dirs()), str(source), "-o", str(partial)]
    print("build_native: compiling", source, "(about a minute)", flush=True)
    if subprocess.run(command).returncode != 0:
        partial.unlink(missing_ok=True)
        raise SystemExit("build_native: the compiler failed (above); the pure-Python solver will run")
    partial.replace(out)  # atomic: an interrupted build leaves no half-written module behind
    print(f"build_native: wrote {out}")


if __name__ == "__main__":
    sys.exit(main())
