"""Peak memory and time of `m3t1r calibrate` by pose count (issues 12 and 26).

For each size N: `m3t1r simulate -n N` writes noisy measurements of a simulated machine, then
`m3t1r calibrate` runs on them with the command's defaults (outliers gated, model selection,
5-fold cross-validation) in a fresh child process, which reports its own peak resident set size
(`getrusage`, the whole process: Python, numpy and Pinocchio) and wall time. The baseline, measured
in the same run, is a child that only imports the package and loads the model: what the command
needs before any data. Reported per size: peak, peak above the baseline, that per pose, and time
per pose (constant when time is linear in the pose count).

Then the check that bounding the memory changed no result: on `--compare` simulated poses (5,000)
the fit with Levenberg-Marquardt's least squares accumulated pose block by pose block (the default,
`CalibrationOptions.stream_jacobian`) against the fit holding the whole Jacobian, same options as
the command's (outlier gate, model selection): the largest platform pose difference of the two
calibrated machines at 200 held-out slider sets.

With `--against SRC` (another checkout's `src` folder, e.g. a `git worktree` of the tree before a
change): the whole command on one `--compare`-pose file, run by this tree and by that one in fresh
children, timed: every number of the two calibrated URDFs and closures files (the largest
difference [m, rad]; the text around the numbers must be the same), and the two reports (outliers,
fitted parameters, cross-validation figures), which must be the same text.

Goals (issue 26): at most 1 GiB and 5 minutes at 100,000 poses on one process; the same calibrated
model as the in-memory fit to 1e-9 m on 5,000 poses.

Run: python benchmarks/bench_memory.py [--sizes 5000 20000 100000] [--compare 5000] [--against SRC] [--quick]
(`--sizes` with no size runs only the comparisons.)
"""

from __future__ import annotations

import argparse
import json
import os
import re
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


def _measure(argv: list[str], src: Path | None = None, cwd: Path | None = None) -> dict:
    """Run a child (`_child`) and return its peak and seconds, and "report": what the command printed.
    src: import m3t1r from that folder instead; cwd: the child's working folder."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    if src is not None:
        env["PYTHONPATH"] = str(src)
    completed = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child", *argv],
        capture_output=True,
        text=True,
        check=True,
        env=env,
        cwd=cwd,
    )
    lines = completed.stdout.strip().splitlines()
    return {**json.loads(lines[-1]), "report": lines[:-1]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[5000, 20000, 100000])
    parser.add_argument("--compare", type=int, default=5000, help="poses of the streamed / in-memory check (0: none)")
    parser.add_argument("--against", type=Path, help="another checkout's src: compare its outputs")
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
    compare = 60 if args.quick else args.compare
    if compare:
        print(_streamed_against_in_memory(compare))
        print()
    if compare and args.against is not None:
        print(_against_other_tree(args.against, compare))
        print()
    print("Goals (issue 26): at most 1 GiB and 5 min at 100,000 poses; streamed = in-memory to 1e-9 m at 5,000.")
    return 0


def _streamed_against_in_memory(n: int) -> str:
    """The largest pose difference [m, rad] of the streamed and the in-memory fit of n simulated poses."""
    import dataclasses

    from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors
    from m3t1r.calibration.measurements import TrackerNoise
    from m3t1r.calibration.pipeline import CalibrationOptions
    from m3t1r.calibration.simulation import StudyOptions, simulate_study
    from m3t1r.model.description import Mechanism

    nominal = Mechanism.load()
    study = simulate_study(
        nominal, n_poses=n, n_holdout=200, seed=26, noise=TrackerNoise(), options=StudyOptions(outliers=3)
    )
    options = CalibrationOptions(noise=TrackerNoise(), select=True)
    timed = {}
    for stream in (True, False):
        start = time.perf_counter()
        fit = calibrate_closed_loop(nominal, study.measurements, dataclasses.replace(options, stream_jacobian=stream))
        timed[stream] = (fit, time.perf_counter() - start)
    (streamed, t_streamed), (in_memory, t_in_memory) = timed[True], timed[False]
    between = pose_errors(streamed.mechanism, in_memory.mechanism, study.holdout_actuators)
    same = streamed.fitted == in_memory.fitted and streamed.outliers == in_memory.outliers
    return (
        f"{n:,} poses, streamed ({fmt_time(t_streamed)}) against in-memory ({fmt_time(t_in_memory)}) fit: "
        f"calibrated machines within {between.position_max:.1e} m, {between.rotation_max:.1e} rad; "
        f"{'the same' if same else 'DIFFERENT'} fitted parameters ({len(streamed.fitted)}) and outliers "
        f"{streamed.outliers}"
    )


_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _numbers_and_text(text: str) -> tuple[list[float], str]:
    """Every number of a written model file and the text around them; the URDF's line naming its
    closures file's sha256 is left out (it changes with any digit of that file)."""
    kept = "\n".join(line for line in text.splitlines() if "sha256" not in line)
    return [float(x) for x in _NUMBER.findall(kept)], _NUMBER.sub("#", kept)


def _against_other_tree(src: Path, n: int) -> str:
    """`m3t1r calibrate` on one file of n simulated poses by this tree and by the tree at `src`: the
    largest difference of any number in the written files, and whether the reports are the same."""
    with tempfile.TemporaryDirectory() as folder:
        data = Path(folder) / f"m{n}.csv"
        _measure(["simulate", "-n", str(n), "-o", str(data), "-q"])
        runs = {}
        for name, tree in (("this tree", None), ("the other tree", src.resolve())):
            out = Path(folder) / name.replace(" ", "_")
            out.mkdir()
            result = _measure(["calibrate", str(data), "-o", "c.urdf", "-q"], src=tree, cwd=out)
            files = [_numbers_and_text((out / f).read_text()) for f in ("c.urdf", "c.closures.yaml")]
            runs[name] = (result, files)
    (ours, our_files), (theirs, their_files) = runs["this tree"], runs["the other tree"]
    largest, same_text = 0.0, True
    for (a, text_a), (b, text_b) in zip(our_files, their_files):
        same_text &= text_a == text_b and len(a) == len(b)
        largest = max([largest, *(abs(x - y) for x, y in zip(a, b))])
    differing = [f"  this: {x}\n  other: {y}" for x, y in zip(ours["report"], theirs["report"]) if x != y]
    same_report = not differing and len(ours["report"]) == len(theirs["report"])
    return "\n".join(
        [
            f"{n:,} poses, `m3t1r calibrate` by this tree ({fmt_time(ours['seconds'])}, "
            f"{ours['peak'] / GIB:.3f} GiB) and by {src} ({fmt_time(theirs['seconds'])}, "
            f"{theirs['peak'] / GIB:.3f} GiB): every number of the URDF and closures files within "
            f"{largest:.1e}{'' if same_text else ' (the TEXT AROUND THEM DIFFERS)'}; "
            + ("the same report:" if same_report else "DIFFERENT reports:"),
            *("  " + line for line in ours["report"]),
            *differing,
        ]
    )


if __name__ == "__main__":
    sys.exit(main())
