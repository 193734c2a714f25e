"""The `m3t1r` command line: kinematics, simulation, calibration, compensation, viewing, demo.

Every verb reads validated files, computes, and only then writes its outputs atomically; it never
writes onto an input or the nominal model. Errors print `m3t1r: error: ...` naming the file, line,
column or joint at fault, and exit with status 2 (1 when some rows failed, or a fit was refused as
not supported by the data, and nothing was written).
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable, Sequence
from pathlib import Path

from m3t1r.app.cli_parser import build_parser as _build_parser

__all__ = ["main", "build_parser", "VERBS", "load"]

# The module and function that run each verb. This table is the one place the command line imports
# by name, for start-up time: `m3t1r --help`, `--version` and `VERB --help` need argparse alone, and a
# verb imports its own stack only (SciPy, Pinocchio, matplotlib, meshcat cost seconds together), so
# this module imports no verb module at its top. tests/test_startup.py checks that every verb of the
# parser is here and resolves.
VERBS: dict[str, str] = {
    "fk": "m3t1r.app.cli_kinematics:cmd_fk",
    "ik": "m3t1r.app.cli_kinematics:cmd_ik",
    "simulate": "m3t1r.app.cli_studies:cmd_simulate",
    "calibrate": "m3t1r.app.cli_calibrate:cmd_calibrate",
    "compensate": "m3t1r.app.cli_kinematics:cmd_compensate",
    "view": "m3t1r.app.cli_view:cmd_view",
    "demo": "m3t1r.app.cli:cmd_demo",
    "paper": "m3t1r.app.cli_studies:cmd_paper",
    "evaluate": "m3t1r.app.cli_kinematics:cmd_evaluate",
    "plan": "m3t1r.app.cli_campaign:cmd_plan",
    "validate": "m3t1r.app.cli_campaign:cmd_validate",
}
# `calibrate --serial` runs without the closed-loop stack and its plots.
SERIAL_CALIBRATION = "m3t1r.app.cli_serial:cmd_calibrate_serial"
_RUNNER = "m3t1r.app.cli_run:run_verb"  # exit statuses and signals: needs the errors, hence numpy
_DEMO = "m3t1r.app.demo:run_demo"


def load(reference: str) -> Callable:
    """The function named by "package.module:function", its module imported now."""
    module, _, name = reference.partition(":")
    return getattr(importlib.import_module(module), name)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every verb (`args.verb` names the verb; `VERBS` says what runs it)."""
    return _build_parser(description=__doc__.splitlines()[0])


def cmd_demo(args: argparse.Namespace) -> None:
    """`m3t1r demo`: the end-to-end simulated calibration, through this command line's `main`."""
    load(_DEMO)(Path(args.out), main)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)  # --help and --version exit here, before any numeric import
    run = load(SERIAL_CALIBRATION if args.verb == "calibrate" and args.serial else VERBS[args.verb])
    return load(_RUNNER)(run, args)


if __name__ == "__main__":
    raise SystemExit(main())
