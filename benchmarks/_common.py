"""Shared plumbing of the benchmark scripts: machine description, timing and plain-text tables.

Timings on a shared machine are noisy, so every script measures our method and its baseline in
the same process, interleaved, several times, on one BLAS thread, and reports medians and ratios.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence

__all__ = ["header", "table", "interleaved_times", "median", "fmt_time", "fmt_rate", "cpu_model"]


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else platform.processor()."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def header(title: str, script: str | None = None, argv: Sequence[str] | None = None) -> str:
    """Title, date, command and machine lines to print above a benchmark's tables.

    script: the benchmark file (its `__file__`); argv: the arguments its `main` received (None:
    the command line's). The command shown is the one that reproduces this benchmark alone.
    """
    import numpy
    import pinocchio
    import scipy

    try:
        load = "%.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        load = "n/a"
    if script is not None:
        arguments = list(sys.argv[1:] if argv is None else argv)
        command = "`" + " ".join(["python", f"benchmarks/{os.path.basename(script)}"] + arguments) + "`"
        if sys.argv and os.path.basename(sys.argv[0]) == "run_all.py":
            command += " (run by `" + " ".join(["python", "benchmarks/run_all.py"] + sys.argv[1:]) + "`)"
    else:
        command = "`" + " ".join(["python"] + sys.argv) + "`"
    lines = [
        f"## {title}",
        "",
        f"- date: {_dt.datetime.now().astimezone().isoformat(timespec='seconds')}",
        f"- command: {command}",
        f"- machine: {platform.platform()}; CPU: {cpu_model()}; {os.cpu_count()} logical cores; "
        f"load average (1/5/15 min): {load}",
        f"- python {platform.python_version()}, numpy {numpy.__version__}, scipy {scipy.__version__}, "
        f"pinocchio {pinocchio.__version__}; BLAS limited to 1 thread",
        "",
    ]
    return "\n".join(lines)


def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A markdown (pipe) table with columns padded for reading as plain text too."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(r[k]) for r in cells) for k in range(len(headers))]
    lines = [
        "| " + " | ".join(c.ljust(w) for c, w in zip(cells[0], widths)) + " |",
        "|" + "|".join("-" * (w + 2) for w in widths) + "|",
    ]
    lines += ["| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |" for r in cells[1:]]
    return "\n".join(lines)


def interleaved_times(
    runs: dict[str, Callable[[], object]], repeats: int, results: dict[str, object] | None = None
) -> dict[str, list[float]]:
    """Wall times [s] of each callable, `repeats` rounds, the callables alternating within a round
    so that a burst of load from other processes hits all of them rather than one. When `results`
    is given, it receives each callable's last return value (so the timed runs double as the
    runs whose output is checked)."""
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            start = time.perf_counter()
            value = run()
            times[name].append(time.perf_counter() - start)
            if results is not None:
                results[name] = value
    return times


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def fmt_time(seconds: float) -> str:
    """Seconds with a unit suited to their size."""
    if seconds < 1e-3:
        return f"{seconds * 1e6:.1f} us"
    if seconds < 1.0:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def fmt_rate(per_second: float) -> str:
    return f"{per_second:,.0f}/s"
