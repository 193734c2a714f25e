"""Hatchling build hook: a wheel (`pip install .`, `pip wheel .`) carries the compiled Newton loop.

It compiles src/m3t1r/model/_native_newton.cpp (with the _native_core.hpp it includes) by
`tools/build_native.py`'s command into a temporary folder and adds the module to the wheel, which is
then tagged for this interpreter and platform.
Without a C++ compiler (or Pinocchio's headers) the wheel is built without it and says so; the solvers
then run their pure-Python loops. Editable installs (`make`'s `pip install -e`) are left to `make native`,
which builds the module in place.
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

from hatchling.builders.hooks.plugin.interface import BuildHookInterface


class CustomBuildHook(BuildHookInterface):
    """Compiles the Newton loop into a wheel's m3t1r/model/ (hatchling finds the hook by this name)."""

    def initialize(self, version: str, build_data: dict) -> None:
        if self.target_name != "wheel" or version == "editable":
            return
        sys.path.insert(0, str(Path(self.root) / "tools"))
        try:
            import build_native

            self._folder = tempfile.TemporaryDirectory()
            out = Path(self._folder.name) / build_native.target().name
            build_native.compile_module(build_native.SOURCE, out)
        except (ImportError, SystemExit) as exc:  # no pinocchio headers or no compiler: a pure-Python wheel
            warnings.warn(f"m3t1r: building the wheel without the compiled Newton loop ({exc})", stacklevel=1)
            return
        finally:
            sys.path.pop(0)
        build_data["force_include"][str(out)] = f"m3t1r/model/{out.name}"
        build_data["pure_python"] = False
        build_data["infer_tag"] = True

    def finalize(self, version: str, build_data: dict, artifact_path: str) -> None:
        folder = getattr(self, "_folder", None)
        if folder is not None:
            folder.cleanup()
