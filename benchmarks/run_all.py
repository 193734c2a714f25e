"""Run every benchmark in turn and print their tables (markdown) to stdout.

Run: python benchmarks/run_all.py [--quick] [--only kinematics scaling ...] [--out-dir DIR]

--quick uses tiny sizes (a smoke run of every code path in well under a minute; its timings mean
nothing). Each benchmark runs in this process, one after the other, so that interpreter start-up
and imports are paid once; each one limits BLAS to one thread itself.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

BENCHMARKS = (
    "kinematics",
    "batch",
    "floor",
    "identification",
    "scaling",
    "memory",
    "pose_selection",
    "uncertainty",
    "campaign",
    "startup",
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    parser.add_argument("--only", nargs="+", choices=BENCHMARKS, default=list(BENCHMARKS))
    parser.add_argument(
        "--out-dir",
        type=Path,
        default=Path(tempfile.gettempdir()),
        help="where figures (the uncertainty map) are written",
    )
    args = parser.parse_args(argv)
    failures = []
    for name in args.only:
        module = importlib.import_module(f"bench_{name}")
        extra = ["--out", str(args.out_dir / "uncertainty_map.png")] if name == "uncertainty" else []
        start = time.perf_counter()
        print(f"\n<!-- benchmarks/bench_{name}.py -->\n", flush=True)
        try:
            status = module.main((["--quick"] if args.quick else []) + extra)
        except Exception as exc:  # report and go on: one broken benchmark should not hide the others
            print(f"\nbench_{name} FAILED: {type(exc).__name__}: {exc}")
            status = 1
        if status:
            failures.append(name)
        print(f"\n(bench_{name}: {time.perf_counter() - start:.1f} s wall)", flush=True)
    if failures:
        print(f"\nFailed: {', '.join(failures)}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
