"""The command line as the tests drive it: the campaign verbs through their own registration, and the
arguments of a serial robot's `calibrate --serial` built in code."""

from __future__ import annotations

import argparse
from pathlib import Path

from m3t1r.app.cli_campaign import add_plan_parser, add_validate_parser
from m3t1r.app.cli_common import RowFailures
from m3t1r.errors import M3t1rError


def run_campaign_verb(argv: list[str]) -> int:
    """`m3t1r plan` or `m3t1r validate` through cli_campaign's own registration (`add_plan_parser`,
    `add_validate_parser`), with `m3t1r.app.cli.main`'s exit statuses: 1 for rows that could not be
    predicted, 2 for an error; the error is printed on stdout."""
    parser = argparse.ArgumentParser(prog="m3t1r")
    verbs = parser.add_subparsers(dest="verb", required=True)
    add_plan_parser(verbs)
    add_validate_parser(verbs)
    args = parser.parse_args(argv)
    try:
        args.run(args)
    except RowFailures as exc:
        print(f"m3t1r: error: {exc}")
        return 1
    except (M3t1rError, OSError) as exc:
        print(f"m3t1r: error: {exc}")
        return 2
    return 0


def serial_calibration_arguments(measurements: Path, report: Path, **overrides: object) -> argparse.Namespace:
    """What `run_serial_calibration` reads of `m3t1r calibrate MEASUREMENTS --serial ur10 --tool tool0
    --report REPORT --frame estimate --folds 4` (no URDF written), priors and joint values already
    parsed; `overrides` replace any of them (marker=[x, y, z] [m], noise_pos=1e-5, ...)."""
    values: dict[str, object] = dict(
        measurements=str(measurements),
        output=None,
        report=str(report),
        serial="ur10",
        base=None,
        tool="tool0",
        noise_pos=1e-5,
        noise_rot=2e-5,
        frame="estimate",
        marker=None,
        units="m",
        force=False,
        max_iterations=None,
        fix=[],
        prior={},
        outlier_sigma=5.0,
        select="loo",
        compliance=False,
        folds=4,
        joint={},
    )
    values.update(overrides)
    return argparse.Namespace(**values)
