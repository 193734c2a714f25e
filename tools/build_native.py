"""Compile m3t1r's Newton loop (src/m3t1r/model/_native_newton.cpp, _native_core.hpp) in place, for this Python.

Header-only use of Pinocchio's C++ API (the `pin` wheel's `libpinocchio` ships its headers), with
Eigen's headers from `cmeel-eigen` (the Eigen that eigenpy is built against) and Boost's from
`cmeel-boost`: the module builds its own `pinocchio::Model` from arrays and links no Pinocchio
library, so it does not depend on the wheel's binary interface. `make` runs this after installing
(`make native`), and hatch_build.py runs `compile_module` for wheels and editable installs. Without
the module the solvers run their pure-Python Newton (same results, four to six times slower;
`m3t1r.model.native.status()` says which runs). A build that cannot compile fails with the reason,
unless M3T1R_PURE_PYTHON=1 asks for the pure-Python package.

Run: python tools/build_native.py [--force]   (about a minute of g++; skipped when up to date)
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import os
import shlex
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[1] / "src" / "m3t1r" / "model" / "_native_newton.cpp"
# Pinocchio's CMake targets set these (its joint variant needs more than Boost.MPL's default 20 types).
DEFINES = [
    "BOOST_MPL_LIMIT_LIST_SIZE=30",
    "BOOST_MPL_LIMIT_VECTOR_SIZE=30",
    "BOOST_MPL_CFG_NO_PREPROCESSED_HEADERS",
    "BOOST_FUSION_INVOKE_MAX_ARITY=12",
    "NDEBUG",
]
# The environment variable that asks for a package without the compiled loop (hatch_build.py, `make native`).
PURE_PYTHON = "M3T1R_PURE_PYTHON"
WITHOUT_IT = (
    f"fix the cause, or set {PURE_PYTHON}=1 to go without the compiled loop (the solvers then run "
    "their pure-Python loop, four to six times slower)"
)
# Each header tree: the distributions that may ship it (first found wins) and one file of it, below
# the include directory to pass to the compiler.
HEADER_TREES = {
    "Eigen": (("cmeel-eigen",), "include/eigen3", "Eigen/Core"),
    "Pinocchio": (("libpinocchio", "pin"), "include", "pinocchio/multibody.hpp"),  # pin < 4 shipped them itself
    "Boost": (("cmeel-boost",), "include", "boost/version.hpp"),
}


def pure_python_requested() -> bool:
    """Whether M3T1R_PURE_PYTHON is set to a true value (1, yes, true, on)."""
    return os.environ.get(PURE_PYTHON, "").strip().lower() in ("1", "yes", "true", "on")


def target() -> Path:
    return SOURCE.with_name("_native_newton" + sysconfig.get_config_var("EXT_SUFFIX"))


def include_dirs() -> list[Path]:
    """The compiler's -I directories, found in the installed files of the distributions that ship them.

    Not through `import pinocchio`: in pip's isolated build environment the target environment's
    cmeel prefix stays on sys.path (its .pth file ran at start-up), so `pinocchio` resolves to the
    target's copy, which has no Eigen headers (cmeel-eigen is a build requirement only). The
    distributions' metadata are looked up in this interpreter's site-packages, the build
    environment's. SystemExit names what is missing."""
    found = [_header_tree(what, names, include, probe) for what, (names, include, probe) in HEADER_TREES.items()]
    python = Path(sysconfig.get_paths()["include"])
    if not (python / "Python.h").exists():
        raise SystemExit(f"build_native: Python's headers not found at {python} (install the python3-dev package)")
    return list(dict.fromkeys([*found, python]))  # one prefix usually holds all three


def _header_tree(what: str, names: tuple[str, ...], include: str, probe: str) -> Path:
    for name in names:
        for dist in importlib.metadata.distributions(name=name):
            for file in dist.files or ():
                path = file.as_posix()
                if path.endswith(f"{include}/{probe}") and Path(dist.locate_file(file)).exists():
                    return Path(dist.locate_file(path[: -len(probe) - 1])).resolve()
    raise SystemExit(
        f"build_native: {what}'s headers not found: no installed {' or '.join(names)} "
        f"distribution ships {include}/{probe} (pip install {names[0]})"
    )


def up_to_date(out: Path) -> bool:
    """Whether the module `out` exists and was compiled from today's sources: the stamp it carries
    (`source_sha256`) is the hash of the files it is compiled from, as m3t1r checks at import. File
    times decide nothing: a module copied in, or sources checked out after the build, have any."""
    if not out.exists():
        return False
    expected = hashlib.sha256(b"".join(p.read_bytes() for p in sources(SOURCE))).hexdigest()
    # Read in a child process: this one may overwrite the file next, which must not be mapped here.
    probe = (
        "import importlib.util, sys; spec = importlib.util.spec_from_file_location('m3t1r.model._native_newton', "
        "sys.argv[1]); module = importlib.util.module_from_spec(spec); spec.loader.exec_module(module); "
        "print(getattr(module, 'source_sha256', ''))"
    )
    found = subprocess.run([sys.executable, "-c", probe, str(out)], capture_output=True, text=True, check=False)
    return found.returncode == 0 and found.stdout.strip() == expected


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when the module carries its sources' stamp")
    args = parser.parse_args(argv)
    out = target()
    if pure_python_requested():
        print(f"build_native: {PURE_PYTHON} is set: not compiling; the solvers run their pure-Python loop")
        return 0
    if not args.force and up_to_date(out):
        print(f"build_native: {out.name} is up to date")
        return 0
    try:
        compile_module(SOURCE, out)
    except SystemExit as failure:
        raise SystemExit(f"{failure}\nbuild_native: {WITHOUT_IT}") from None
    return 0


def sources(source: Path) -> list[Path]:
    """What the module is compiled from: `source` and the core header it includes (a revision from
    before the header has the file alone). m3t1r.model.native_status hashes the same files, in this order."""
    return [part for part in (source, source.with_name("_native_core.hpp")) if part.exists()]


def compile_module(source: Path, out: Path) -> None:
    """Compile `source` into the extension module `out` (SystemExit naming the cause when a header tree
    or the compiler is missing, or the compiler fails). $CXX names the compiler (default g++)."""
    compiler = shlex.split(os.environ.get("CXX", "g++")) or ["g++"]
    if shutil.which(compiler[0]) is None:
        raise SystemExit(f"build_native: no C++ compiler: {compiler[0]!r} (from $CXX, default g++) is not on PATH")
    includes = include_dirs()
    partial = out.with_suffix(".partial")
    # m3t1r.model.native refuses a module of other source: the stamp covers every file it is built from.
    digest = hashlib.sha256(b"".join(part.read_bytes() for part in sources(source))).hexdigest()
    # -O3: it vectorises the dense LU's row operations (no fast-math: the same rounding as -O2);
    # forward_batch about 10 % faster than with -O2 (benchmarks/README.md).
    command = [
        *compiler,
        "-O3",
        "-std=c++17",
        "-shared",
        "-fPIC",
        "-pthread",
        "-fvisibility=hidden",
        "-w",
        *(f"-D{d}" for d in DEFINES),
        f'-DM3T1R_SOURCE_SHA256="{digest}"',
        *(f"-I{d}" for d in includes),
        str(source),
        "-o",
        str(partial),
    ]
    print("build_native: compiling", source, "(about a minute)", flush=True)
    if subprocess.run(command).returncode != 0:
        partial.unlink(missing_ok=True)
        raise SystemExit(f"build_native: the compiler failed (above): {shlex.join(command)}")
    partial.replace(out)  # atomic: an interrupted build leaves no half-written module behind
    print(f"build_native: wrote {out}")


if __name__ == "__main__":
    sys.exit(main())
