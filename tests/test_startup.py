"""Start-up: what `import m3t1r`, `m3t1r --help`, `m3t1r --version` and each verb's module import.

Each check runs in a fresh interpreter and reads its `sys.modules`: which modules load does not
depend on the machine (how long they take does; `benchmarks/bench_startup.py` measures that).
"""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import m3t1r
from m3t1r.app.cli import build_parser, main
from m3t1r.app.cli_verbs import (
    CALIBRATION_PLOTS,
    DECLARE_VALIDATION_PLOTS,
    DEMO,
    RUNNER,
    SERIAL_CALIBRATION,
    VALIDATION_PLOTS,
    VERBS,
    load,
)
from m3t1r.model import native

SRC = Path(__file__).resolve().parents[1] / "src"
# Libraries a command that only answers from argparse must not import (seconds of start-up together).
NUMERIC = ("numpy", "scipy", "pinocchio", "matplotlib", "meshcat", "yaml", "lxml")


def _loaded_after(code: str, modules: tuple[str, ...]) -> tuple[list[str], str]:
    """(the `modules` loaded after running `code` in a fresh interpreter, its stdout)."""
    probe = f"import json, sys\n{code}\nprint(json.dumps([m for m in {list(modules)!r} if m in sys.modules]))"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=300, check=True
    )
    *output, last = done.stdout.strip().splitlines()
    return json.loads(last), "\n".join(output)


def _command_line(argv: list[str]) -> str:
    """Python that runs `m3t1r ARGV` as the console script does, past its SystemExit."""
    return f"from m3t1r.app.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass"


def test_import_m3t1r_loads_no_numeric_library() -> None:
    loaded, _ = _loaded_after("import m3t1r", NUMERIC + ("scipy.stats",))
    assert loaded == []


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["calibrate", "--help"], ["plan", "--help"]])
def test_help_and_version_load_no_numeric_library(argv: list[str]) -> None:
    loaded, output = _loaded_after(_command_line(argv), NUMERIC + ("scipy.stats",))
    assert loaded == []
    assert "usage: m3t1r" in output or output.startswith("m3t1r ")


def test_version_names_the_compiled_loop_as_the_solver_sees_it() -> None:
    _, output = _loaded_after(_command_line(["--version"]), ())
    match = re.fullmatch(r"m3t1r (\S+) \(compiled Newton loop: (yes|no: .+)\)", output)
    assert match is not None, output
    assert match[1] == m3t1r.__version__
    assert (match[2] == "yes") == native.AVAILABLE  # the same verdict as the module the solvers use


# What no verb module may import, and what only some need (matplotlib comes with `calibrate --plots`
# alone, through cli_verbs.CALIBRATION_PLOTS; the viewer and the demo draw with meshcat).
NEVER = ("scipy.stats",)
NOT_FOR = {
    "m3t1r.app.cli_kinematics": ("matplotlib", "meshcat", "pinocchio.visualize", "m3t1r.calibration.closed_loop"),
    "m3t1r.app.cli_serial": ("matplotlib", "meshcat", "pinocchio.visualize", "m3t1r.calibration.closed_loop"),
    "m3t1r.app.cli_campaign": ("matplotlib", "meshcat", "pinocchio.visualize"),
    "m3t1r.app.cli_studies": ("matplotlib", "meshcat", "pinocchio.visualize"),
    "m3t1r.app.cli_calibrate": ("matplotlib", "meshcat", "pinocchio.visualize"),
    "m3t1r.app.cli_view": ("matplotlib",),
    # convert reads files: no fit, and the optional readers only for their formats
    "m3t1r.app.cli_convert": (
        "matplotlib",
        "meshcat",
        "pinocchio.visualize",
        "m3t1r.calibration.closed_loop",
        "m3t1r.calibration.serial",
        "ezc3d",
        "rosbags",
    ),
    "m3t1r.app.cli": ("numpy",),  # the demo's own module is imported when it runs
}


def test_every_verb_has_a_run_function_and_nothing_else_does() -> None:
    verbs = re.findall(r"^    ([a-z]+)\b", build_parser().format_help(), re.MULTILINE)  # the help lists each verb
    assert set(verbs) == set(VERBS)
    for reference in [
        *VERBS.values(),
        SERIAL_CALIBRATION,
        CALIBRATION_PLOTS,
        VALIDATION_PLOTS,
        DECLARE_VALIDATION_PLOTS,
        RUNNER,
        DEMO,
    ]:
        assert callable(load(reference)), reference
    for reference in [*VERBS.values(), SERIAL_CALIBRATION]:
        assert reference.partition(":")[0] in NOT_FOR, f"{reference}: say what its module may not import"


@pytest.mark.parametrize("module", sorted(NOT_FOR))
def test_a_verb_imports_only_its_own_stack(module: str) -> None:
    loaded, _ = _loaded_after(f"import {module}", NEVER + NOT_FOR[module])
    assert loaded == []


def test_calibrate_serial_runs_without_the_closed_loop_calibration(tmp_path, capsys) -> None:
    """`calibrate --serial` goes to its own run function, which reads the robot before the data."""
    argv = ["calibrate", str(tmp_path / "missing.csv"), "--serial", "ur5", "-o", str(tmp_path / "ur5.urdf")]
    loaded, _ = _loaded_after(
        _command_line(argv), ("m3t1r.app.cli_calibrate", "m3t1r.calibration.closed_loop", "matplotlib")
    )
    assert loaded == []
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert "ur5 is an example-robot-data robot" in captured.out and "missing.csv: file not found" in captured.err
    assert not (tmp_path / "ur5.urdf").exists()


def test_the_facade_loads_a_name_on_first_use_and_lists_every_name() -> None:
    tree = ast.parse((SRC / "m3t1r" / "__init__.py").read_text(encoding="utf-8"))
    guarded = next(node for node in tree.body if isinstance(node, ast.If))  # `if TYPE_CHECKING:`
    typed = {alias.name: node.module for node in guarded.body for alias in node.names}
    public = set(m3t1r.__all__) - {"__version__"}
    assert set(typed) == public  # what type checkers see is what `__all__` promises
    for name, module in typed.items():
        assert getattr(m3t1r, name) is getattr(sys.modules[module], name), name
    assert public <= set(dir(m3t1r))
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        m3t1r.no_such_name
    loaded, output = _loaded_after(
        "from m3t1r import TrackerNoise\nprint(TrackerNoise().position)",
        ("matplotlib", "meshcat", "scipy.stats", "m3t1r.calibration.closed_loop"),
    )
    assert loaded == [] and float(output) > 0
