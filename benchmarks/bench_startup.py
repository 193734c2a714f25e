"""Start-up: `m3t1r --help`, `--version`, `import m3t1r`, verbs up to their first work, against `import numpy`.

Each command is a fresh interpreter (`python -m m3t1r.app.cli` stands for the console script: the
same imports) importing this tree's `src/` (or `--src`'s: another checkout's, for a before/after).
Wall time is measured around the child, CPU time (user + system) from `getrusage(RUSAGE_CHILDREN)`;
the commands alternate within each round, after one untimed round (bytecode caches), and the table
gives medians with the ratios to `import numpy` of the same run: the machine's speed, not only the
code, sets the absolute times. A whole serial calibration of 37 postures shows what start-up is of
a short command. (This process imports the package to write that campaign; only children are timed.)

Run: python benchmarks/bench_startup.py [--repeats 15] [--src OTHER_CHECKOUT/src]
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
from _common import fmt_time, header, median, table

from m3t1r.calibration import serial_robots, serial_simulation
from m3t1r.io.tables import write_table
from m3t1r.model.poe import SerialChain, tool_poses

SRC = Path(__file__).resolve().parents[1] / "src"
CLI = ["-m", "m3t1r.app.cli"]
MISSING = "no_such_file.csv"
POSTURES = 37  # a serial campaign of the size a user timed: 1 mm / 1 mrad errors, 10 um / 20 urad tracker
# (label, the interpreter's arguments, a regular expression its stdout + stderr must match, exit status).
# The two verbs are given a file that does not exist: they import their stack, load the robot or
# the machine, then stop with status 2 at the file: start-up up to the first real work.
COMMANDS = (
    ("python -c pass (the interpreter alone)", ["-c", "pass"], r"^$", 0),
    ("python -c 'import numpy' (baseline)", ["-c", "import numpy"], r"^$", 0),
    ("python -c 'import m3t1r'", ["-c", "import m3t1r"], r"^$", 0),
    ("m3t1r --version", [*CLI, "--version"], r"^m3t1r \S+( \(compiled Newton loop: (yes|no: .+)\))?\n$", 0),
    ("m3t1r --help", [*CLI, "--help"], r"^usage: m3t1r", 0),
    ("m3t1r calibrate --help", [*CLI, "calibrate", "--help"], r"^usage: m3t1r calibrate", 0),
    (
        "m3t1r fk (missing file: start-up, the M machine loaded)",
        [*CLI, "fk", MISSING, "-o", "out.csv"],
        MISSING + ": file not found",
        2,
    ),
    (
        "m3t1r calibrate --serial ur5 (missing file: start-up, the UR5 loaded)",
        [*CLI, "calibrate", MISSING, "--serial", "ur5", "-o", "ur5.urdf"],
        MISSING + ": file not found",
        2,
    ),
    (
        f"m3t1r calibrate --serial ur5 on {POSTURES} postures (the whole command)",
        [*CLI, "-q", "calibrate", "ur5.csv", "--serial", "ur5", "-o", "ur5.urdf", "--report", "report.json"],
        "wrote report.json",
        0,
    ),
)
BASELINE = "python -c 'import numpy' (baseline)"


def _child_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_once(arguments: list[str], expected: str, status: int, env: dict[str, str], cwd: str) -> tuple[float, float]:
    """(wall [s], CPU [s]) of `python ARGUMENTS`; its output must match `expected`, its exit status `status`."""
    cpu, start = _child_cpu(), time.perf_counter()
    done = subprocess.run([sys.executable, *arguments], capture_output=True, text=True, env=env, cwd=cwd)
    wall = time.perf_counter() - start
    if done.returncode != status or not re.search(expected, done.stdout + done.stderr):
        raise RuntimeError(
            f"python {' '.join(arguments)}: status {done.returncode}, output {(done.stdout + done.stderr)[-300:]!r}"
        )
    return wall, _child_cpu() - cpu


def write_serial_campaign(path: Path, seed: int = 3) -> None:
    """A UR5 campaign: POSTURES tool poses of a 1 mm / 1 mrad robot with tracker noise, in its base frame."""
    model = serial_robots.load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    rng = np.random.default_rng(seed)
    data = serial_simulation.simulate_serial_measurements(model, chain, POSTURES, rng, noise=None)
    exact = tool_poses(chain, data.truth, data.q_true)
    turns = [pin.exp3(rng.normal(0.0, 20e-6, 3)) for _ in range(POSTURES)]
    measured = [pin.SE3(g[:3, :3] @ turn, g[:3, 3] + rng.normal(0.0, 10e-6, 3)) for g, turn in zip(exact, turns)]
    rows = np.hstack([data.q_true, [pin.SE3ToXYZQUAT(g) for g in measured]])
    write_table(
        path,
        list(chain.joint_names) + ["x", "y", "z", "qx", "qy", "qz", "qw"],
        rows,
        [f"{POSTURES} simulated UR5 postures"],
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=15, help="timed rounds (default 15)")
    parser.add_argument(
        "--src",
        type=Path,
        default=SRC,
        help="the package tree to time (default: this checkout's src/; another checkout's "
        "src/ gives the figures of another revision)",
    )
    parser.add_argument("--quick", action="store_true", help="one round, for a smoke test")
    args = parser.parse_args(argv)
    repeats = 1 if args.quick else args.repeats
    # The tree's package, whatever is installed; one BLAS thread, as every benchmark here.
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(args.src), os.environ.get("PYTHONPATH")])),
        "OPENBLAS_NUM_THREADS": "1",
    }
    times: dict[str, list[tuple[float, float]]] = {label: [] for label, *_ in COMMANDS}
    with tempfile.TemporaryDirectory() as folder:  # the verbs' working folder: their data, no MISSING
        write_serial_campaign(Path(folder) / "ur5.csv")
        for round_ in range(repeats + 1):
            for label, arguments, expected, status in COMMANDS:
                measured = run_once(arguments, expected, status, env, folder)
                if round_:  # the first round fills the bytecode caches
                    times[label].append(measured)
    walls = {label: median([w for w, _ in values]) for label, values in times.items()}
    cpus = {label: median([c for _, c in values]) for label, values in times.items()}
    rows = [
        [
            label,
            fmt_time(walls[label]),
            fmt_time(cpus[label]),
            f"{walls[label] / walls[BASELINE]:.2f}",
            f"{cpus[label] / cpus[BASELINE]:.2f}",
        ]
        for label, *_ in COMMANDS
    ]
    print(header("Start-up of the command line and the package", __file__, argv))
    print(
        f"Package: {args.src}. Fresh interpreters, medians of {repeats} interleaved rounds; ratios to "
        "`import numpy` of the same run.\n"
    )
    print(table(["command", "wall", "CPU (user + sys)", "wall / numpy", "CPU / numpy"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
