"""Peak memory and time of `m3t1r calibrate` by pose count (issue 12, item 3).

For each size N: `m3t1r simulate -n N` writes noisy measurements of a simulated machine, then
`m3t1r calibrate` runs on them with the command's defaults (outliers gated, model selection,
5-fold cross-validation) in a fresh child process, which reports its own peak resident set size
(`getrusage`, the whole process: Python, numpy and Pinocchio) and wall time. The baseline, measured
in the same run, is a child that only imports the package and loads the model: what the command
needs before any data. Reported per size: peak, peak above the baseline, that per pose, and time
per pose (constant when time is linear in the pose count).

Goals (issue 12): at most 1 GiB at 20,000 poses and 1.5 GiB at 100,000.

Run: python benchmarks/bench_memory.py [--sizes 5000 20000 100000] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_time, header, table  # noqa: E402

GIB = 1024**3


def _child(argv: list[str]) -> None:
    """In the child: run the CLI (or only load the model) and print peak RSS [bytes] and wall time."""
    from m3t1r.app.cli import main
    from m3t1r.model.description import Mechanism

    start = time.perf_counter()
    if argv:
        status = main(argv)
        if status != 0:
            raise SystemExit(f"m3t1r {' '.join(argv)} exited with {status}")
    else:
        Mechanism.load()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kB on Linux
    print(json.dumps({"peak": peak, "seconds": time.perf_counter() - start}))


def _measure(argv: list[str]) -> dict:
    completed = subprocess.run(
        [sys.executable, __file__, "--child", *argv],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    return json.loads(completed.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 100000])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    parser.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        _child(args.child)
        return 0
    sizes = [60] if args.quick else args.sizes
    print(header("Calibration memory by pose count (whole `m3t1r calibrate` command)", __file__, argv))
    baseline = _measure([])
    rows = [["imports and model only", f"{baseline['peak'] / GIB:.3f} GiB", "-", "-", "-", "-"]]
    with tempfile.TemporaryDirectory() as folder:
        for n in sizes:
            data, machine = Path(folder) / f"m{n}.csv", Path(folder) / f"c{n}.urdf"
            _measure(["simulate", "-n", str(n), "-o", str(data), "-q"])
            result = _measure(["calibrate", str(data), "-o", str(machine), "-q"])
            above = result["peak"] - baseline["peak"]
            rows.append(
                [
                    f"{n:,} poses",
                    f"{result['peak'] / GIB:.3f} GiB",
                    f"{above / GIB:.3f} GiB",
                    f"{above / n / 1024:.1f} kB",
                    fmt_time(result["seconds"]),
                    f"{1e3 * result['seconds'] / n:.2f} ms",
                ]
            )
    print(table(["run", "peak RSS", "above the baseline", "per pose", "wall time", "time per pose"], rows))
    print()
    print("Goals: peak at most 1 GiB at 20,000 poses and 1.5 GiB at 100,000 (issue 12).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
