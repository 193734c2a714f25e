"""Whether the compiled Newton loop (`_native_newton`) is usable, told without importing Pinocchio or numpy.

The one place that loads the compiled module and checks its build stamp against its sources:
`m3t1r.model.native` runs its solvers with what `load_compiled` returns, and `m3t1r --version`
reports `compiled_newton_status()`. The module loads in a few milliseconds on its own (it links
Pinocchio's C++ library, not its Python package); a module built from other sources is refused, since
its calls may not match the Python side's.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
from pathlib import Path
from types import ModuleType

__all__ = ["compiled_newton_status", "load_compiled", "NOT_BUILT", "STALE", "SOURCES"]

_MODULE = "m3t1r.model._native_newton"
# What the module is compiled from, in the order tools/build_native.py hashes them into its stamp.
SOURCES = tuple(Path(__file__).with_name(name) for name in ("_native_newton.cpp", "_native_core.hpp"))
NOT_BUILT, STALE = "not built", "older than its source"
_REBUILD = "make native, or python tools/build_native.py"


def load_compiled() -> tuple[ModuleType | None, str]:
    """The compiled module and "", or None and why not: NOT_BUILT, STALE (built from other sources),
    or "it does not load (...)". An install without the sources trusts its build."""
    if importlib.util.find_spec(_MODULE) is None:
        return None, NOT_BUILT
    try:
        module = importlib.import_module(_MODULE)
    except ImportError as exc:
        return None, f"it does not load ({exc})"
    if all(source.exists() for source in SOURCES):
        expected = hashlib.sha256(b"".join(source.read_bytes() for source in SOURCES)).hexdigest()
        if getattr(module, "source_sha256", "") != expected:
            return None, STALE
    return module, ""


def compiled_newton_status() -> str:
    """ "yes" when the compiled Newton loop is built, loads and matches its sources, else "no: <why>"."""
    module, why = load_compiled()
    if module is not None:
        return "yes"
    return f"no: {why}" + ("" if why.startswith("it does not load") else f" ({_REBUILD})")
