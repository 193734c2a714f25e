"""Hatchling build hook: every install carries the compiled Newton loop, or fails saying why.

A wheel (`pip install .`, `pip wheel .`) gets src/m3t1r/model/_native_newton.cpp (with the
_native_core.hpp it includes) compiled by `tools/build_native.py`'s command into a temporary folder,
and is then tagged for this interpreter and platform. An editable install (`pip install -e .`, as
`make` does) compiles the module in place, next to its source, unless it is already up to date.
Pinocchio's, Eigen's and Boost's headers come from the build environment (the build requirements
`pin` and `cmeel-eigen`). When the module cannot be compiled (no C++ compiler, headers missing, a
compiler error) the build fails with the reason; M3T1R_PURE_PYTHON=1 asks for a package without it,
whose solvers run their pure-Python loops (the same results, four to six times slower).
"""

from __future__ import annotations

import importlib.util
import tempfile
from pathlib import Path
from types import ModuleType

from hatchling.builders.hooks.plugin.interface import BuildHookInterface


class CustomBuildHook(BuildHookInterface):
    """Compiles the Newton loop into a wheel's m3t1r/model/ (hatchling finds the hook by this name)."""

    def initialize(self, version: str, build_data: dict) -> None:
        if self.target_name != "wheel":
            return
        build_native = _load_build_native(Path(self.root))
        if build_native.pure_python_requested():
            self.app.display_warning(
                f"m3t1r: {build_native.PURE_PYTHON} is set: building without the compiled "
                "Newton loop (the solvers run their pure-Python loop)"
            )
            return
        try:
            if version == "editable":
                self._compile_in_place(build_native)
            else:
                self._compile_into_wheel(build_native, build_data)
        except SystemExit as failure:  # build_native's way of naming the cause
            raise SystemExit(
                f"m3t1r: cannot build the compiled Newton loop.\n{failure}\nm3t1r: {build_native.WITHOUT_IT}"
            ) from None

    def _compile_in_place(self, build_native: ModuleType) -> None:
        out = build_native.target()
        if build_native.up_to_date(out):
            self.app.display_info(f"m3t1r: {out.name} is up to date")
            return
        build_native.compile_module(build_native.SOURCE, out)

    def _compile_into_wheel(self, build_native: ModuleType, build_data: dict) -> None:
        self._folder = tempfile.TemporaryDirectory()
        out = Path(self._folder.name) / build_native.target().name
        build_native.compile_module(build_native.SOURCE, out)
        build_data["force_include"][str(out)] = f"m3t1r/model/{out.name}"
        build_data["pure_python"] = False
        build_data["infer_tag"] = True

    def finalize(self, version: str, build_data: dict, artifact_path: str) -> None:
        folder = getattr(self, "_folder", None)
        if folder is not None:
            folder.cleanup()


def _load_build_native(root: Path) -> ModuleType:
    """tools/build_native.py of the tree being built, by path (the tools folder is not a package)."""
    spec = importlib.util.spec_from_file_location("_m3t1r_build_native", root / "tools" / "build_native.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
