"""The `m3t1r` command line: kinematics, simulation, calibration, compensation, viewing, demo.

Every verb reads validated files, computes, and only then writes its outputs atomically; it never
writes onto an input or the nominal model. Errors print `m3t1r: error: ...` naming the file, line,
column or joint at fault, and exit with status 2 (1 when some rows failed, or a fit was refused as
not supported by the data, and nothing was written).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from m3t1r.app.cli_parser import build_parser as _build_parser
from m3t1r.app.cli_verbs import DEMO, RUNNER, SERIAL_CALIBRATION, VERBS, load

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every verb (`args.verb` names the verb; `cli_verbs.VERBS` what runs it)."""
    return _build_parser(description=__doc__.splitlines()[0])


def cmd_demo(args: argparse.Namespace) -> None:
    """`m3t1r demo`: the end-to-end simulated calibration, through this command line's `main`."""
    load(DEMO)(Path(args.out), main)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)  # --help and --version exit here, before any numeric import
    run = load(SERIAL_CALIBRATION if args.verb == "calibrate" and args.serial else VERBS[args.verb])
    return load(RUNNER)(run, args)


if __name__ == "__main__":
    raise SystemExit(main())
