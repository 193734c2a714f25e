"""Kinematics of this tree against an earlier revision, both imported into one process.

Two processes of the same code on this VM differ by up to 40 % in the unit (memory placement), so
before/after comparisons made in separate runs can show a change that is not there. Here the
revision's package is extracted with `git archive`, renamed (`m3t1r` -> `m3t1r_at_<rev>`, its own
imports rewritten; its compiled Newton loop, if it has one, built with `tools/build_native.py`'s
command, about a minute) and imported beside the working tree's; each operation of both is then timed in
interleaved rounds, so both see the same machine. Operations: the unit (one `computeJointJacobians`
+ `updateFramePlacements`), warm FK / IK and compensation along the 1,000-target path of
`bench_kinematics.py` (a 1 mm / 1 mrad perturbed machine as the calibrated one), and
`forward_batch` over 2,000 workspace slider sets. Each round builds new solvers on both sides
(where their buffers land moves a solve's time by up to 40 %). Reported: the median over rounds
of each, the ratio of revision to tree, and the largest difference between their results.

Run: python benchmarks/bench_against.py REV [--rounds 15] [--quick]
"""

from __future__ import annotations

import argparse
import importlib
import io
import re
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import build_native  # noqa: E402
from _common import fmt_time, header, median, table  # noqa: E402
from bench_batch import perturbed, unit_runner  # noqa: E402
from bench_kinematics import workspace_path  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.model.description import Mechanism  # noqa: E402
from m3t1r.model.kinematics import ClosedLoopSolver  # noqa: E402
from m3t1r.model.workspace import workspace_actuators  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def extract_revision(revision: str, folder: Path) -> tuple[str, Path]:
    """The package of `revision` under `folder` as an importable, renamed package; returns its name
    and the revision's models folder."""
    found = subprocess.run(
        ["git", "rev-parse", "--short", "--verify", "--quiet", f"{revision}^{{commit}}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    if found.returncode != 0:
        raise SystemExit(f"bench_against: {revision!r} is not a revision of {ROOT}")
    short = found.stdout.strip()
    name = f"m3t1r_at_{short}"
    archive = subprocess.run(
        ["git", "archive", revision, "src/m3t1r", "models"], cwd=ROOT, check=True, capture_output=True
    ).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    package = folder / name
    (folder / "src" / "m3t1r").rename(package)
    pattern = re.compile(r"\bm3t1r(?=[.\s]|$)")  # m3t1r.x, `from m3t1r import`, `import m3t1r`
    for source in package.rglob("*.py"):
        source.write_text(pattern.sub(name, source.read_text()))
    compiled = package / "model" / "_native_newton.cpp"
    if compiled.exists():  # a revision with the compiled Newton loop: built, so that compiled meets compiled
        build_native.compile_module(compiled, compiled.with_name(build_native.target().name))
    return name, folder / "models"


def runners(package: str, models: Path, targets: np.ndarray, sliders: np.ndarray, cloud: np.ndarray):
    """A factory of callables for one package (the tree's `m3t1r` or a renamed revision), each
    returning its results. Every call of the factory builds new solvers: where Pinocchio's `Data` and
    numpy's buffers land in memory moves a solve's time by up to 40 % (the same code, two solver
    objects, one process), so each round gets new ones and the median over rounds is reported."""
    description = importlib.import_module(f"{package}.model.description")
    kinematics = importlib.import_module(f"{package}.model.kinematics")
    compensation = importlib.import_module(f"{package}.compensation")
    nominal = description.Mechanism.load(models / "m3t1r.urdf", models / "m3t1r.closures.yaml")
    calibrated = kinematics.rehomed(nominal.with_model(perturbed(nominal).model))

    def build() -> dict:
        solver = kinematics.ClosedLoopSolver(nominal)
        compensator = compensation.Compensator(nominal, calibrated)

        def fk():
            return np.array([solver.forward(values).pose.homogeneous for values in sliders])

        def ik():
            return np.array([solver.inverse(target).actuators for target in targets])

        def compensate():
            return np.asarray(compensator.compensate(targets).actuators)

        return {
            "FK warm (path)": fk,
            "IK warm (path)": ik,
            "compensation (path)": compensate,
            "forward_batch": lambda: solver.forward_batch(cloud).poses,
        }

    return build


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("revision", help="git revision to compare with, e.g. HEAD~3")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    args = parser.parse_args(argv)
    n_path, n_batch, rounds = (20, 20, 1) if args.quick else (1000, 2000, args.rounds)
    print(header(f"Kinematics of this tree against {args.revision}, in one process", __file__, argv))

    with tempfile.TemporaryDirectory() as folder, single_blas_thread():
        name, models = extract_revision(args.revision, Path(folder))
        sys.path.insert(0, folder)
        mechanism = Mechanism.load()
        targets = workspace_path(n_path)
        sliders = np.array([ClosedLoopSolver(mechanism).inverse(t).actuators for t in targets])
        cloud = workspace_actuators(mechanism, n_batch, np.random.default_rng(0))
        factories = {
            "tree": runners("m3t1r", ROOT / "models", targets, sliders, cloud),
            "revision": runners(name, models, targets, sliders, cloud),
        }
        times: dict[tuple[str, str], list[float]] = {}
        results: dict[tuple[str, str], object] = {}
        base = unit_runner(mechanism, 2000)
        for _ in range(rounds):
            start = time.perf_counter()
            base()
            times.setdefault(("unit", ""), []).append((time.perf_counter() - start) / 2000)
            sides = {side: factory() for side, factory in factories.items()}  # new solvers every round
            for operation in sides["tree"]:
                for side in ("revision", "tree"):
                    start = time.perf_counter()
                    results[operation, side] = sides[side][operation]()
                    times.setdefault((operation, side), []).append(time.perf_counter() - start)
    counts = {
        "FK warm (path)": n_path,
        "IK warm (path)": n_path,
        "compensation (path)": n_path,
        "forward_batch": n_batch,
    }
    unit_time = median(times["unit", ""])
    rows = []
    for operation, count in counts.items():
        theirs, ours = median(times[operation, "revision"]) / count, median(times[operation, "tree"]) / count
        agree = float(
            np.max(np.abs(np.asarray(results[operation, "revision"]) - np.asarray(results[operation, "tree"])))
        )
        rows.append(
            [
                operation,
                fmt_time(theirs),
                f"{theirs / unit_time:.1f}",
                fmt_time(ours),
                f"{ours / unit_time:.1f}",
                f"{theirs / ours:.2f}x",
                f"{agree:.1e}",
            ]
        )
    print(
        f"Unit (computeJointJacobians + updateFramePlacements): {fmt_time(unit_time)}; medians of {rounds} "
        "interleaved rounds, new solvers each round; per solve / target / pose.\n"
    )
    print(
        table(
            ["operation", f"{args.revision}: time", "units", "tree: time", "units", "speed-up", "largest difference"],
            rows,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
