"""Whether the compiled Newton loop (`_native_newton`) would be used, told without importing Pinocchio or numpy.

`m3t1r --version` reports it. The compiled module loads in a few milliseconds on its own (it links
Pinocchio's C++ library, not its Python package), so this imports it and compares its build stamp
with its sources as `m3t1r.model.native` does when it loads: a module built from other sources is
refused there, and is reported as not in use here.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
from pathlib import Path

__all__ = ["compiled_newton_status"]

_MODULE = "m3t1r.model._native_newton"
# What the module is compiled from, in the order tools/build_native.py hashes them into its stamp.
_SOURCE_NAMES = ("_native_newton.cpp", "_native_core.hpp")


def compiled_newton_status() -> str:
    """"yes" when the compiled Newton loop is built, loads and matches its sources, else "no: <why>"."""
    if importlib.util.find_spec(_MODULE) is None:
        return "no: not built (make native, or python tools/build_native.py)"
    try:
        module = importlib.import_module(_MODULE)
    except ImportError as exc:
        return f"no: it does not load ({exc})"
    sources = [Path(__file__).with_name(name) for name in _SOURCE_NAMES]
    if all(source.exists() for source in sources):  # an install without the sources trusts its build
        expected = hashlib.sha256(b"".join(source.read_bytes() for source in sources)).hexdigest()
        if getattr(module, "source_sha256", "") != expected:
            return "no: it is older than its source (make native, or python tools/build_native.py)"
    return "yes"
