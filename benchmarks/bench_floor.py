"""Kinematics against the evaluation floor: the three ratios of issue 26's goals, in one run.

Unit: one `computeJointJacobians` + `updateFramePlacements` on the M model, timed interleaved with
the operations below, so that each ratio is taken under the same machine load. Operations, with
their goals (per pose or per target, in units):

- `forward_batch` over n random workspace poses from home, on one thread (goal <= 4) and on every
  core (goal <= 2.5), with the mean Newton steps per row;
- warm IK along the 1,000-target Lissajous path of `bench_kinematics.py` (goal <= 8), and warm FK
  along it (no goal; for comparison);
- compensation along the same path (`Compensator.compensate`: calibrated IK + nominal FK) with a
  1 mm / 1 mrad perturbed machine as the calibrated model (goal <= 15).

The floor under each is Pinocchio's own work: the Jacobian evaluations Newton takes (counted in the
Python loop, which takes the compiled loop's steps) times one unit, plus residual-only passes.

Run: python benchmarks/bench_floor.py [--n-path 1000 --n-batch 10000 --repeats 7] [--quick]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_time, header, interleaved_times, median, table  # noqa: E402
from bench_batch import evaluations_per_solve, perturbed, residual_cost, unit_runner  # noqa: E402
from bench_kinematics import workspace_path  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.compensation import Compensator  # noqa: E402
from m3t1r.model.description import Mechanism  # noqa: E402
from m3t1r.model.design import NOMINAL  # noqa: E402
from m3t1r.model.kinematics import ClosedLoopSolver  # noqa: E402
from m3t1r.model.native import available_cores  # noqa: E402

GOALS = {
    "forward_batch, 1 thread": 4.0,
    "forward_batch, every core": 2.5,
    "IK warm (path)": 8.0,
    "compensation (path)": 15.0,
}
_UNITS = 2000  # unit passes per timed round


def runners(mechanism: Mechanism, targets: np.ndarray, sliders: np.ndarray, cloud_sliders: np.ndarray) -> dict:
    """The timed operations (callables), the unit and a residual-only pass first."""
    solver = ClosedLoopSolver(mechanism)
    compensator = Compensator(mechanism, perturbed(mechanism))

    def fk() -> None:
        solver.reset()
        for values in sliders:
            solver.forward(values)

    def ik() -> None:
        solver.reset()
        for target in targets:
            solver.inverse(target)

    def compensation():
        compensator.reset()
        return compensator.compensate(targets)

    return {
        "unit": unit_runner(mechanism, _UNITS),
        "residual pass (forwardKinematics)": residual_cost(mechanism, _UNITS),
        "forward_batch, 1 thread": lambda: solver.forward_batch(cloud_sliders, threads=1),
        "forward_batch, every core": lambda: solver.forward_batch(cloud_sliders),
        "FK warm (path)": fk,
        "IK warm (path)": ik,
        "compensation (path)": compensation,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n-path", type=int, default=1000)
    parser.add_argument("--n-batch", type=int, default=10000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    args = parser.parse_args(argv)
    if args.quick:
        args.n_path, args.n_batch, args.repeats = 40, 60, 1
    print(header("Kinematics against the evaluation floor (issue 26's goals)", __file__, argv))
    mechanism = Mechanism.load()
    with single_blas_thread():
        solver = ClosedLoopSolver(mechanism)
        targets = workspace_path(args.n_path)
        sliders = np.array([solver.inverse(t).actuators for t in targets])
        cloud = NOMINAL.workspace.sample(np.random.default_rng(0), args.n_batch)
        cloud_sliders = solver.inverse_batch(cloud).actuators
        runs = runners(mechanism, targets, sliders, cloud_sliders)
        results: dict = {}
        times = interleaved_times(runs, args.repeats, results)
        evaluations = evaluations_per_solve(mechanism, targets, sliders)
    counts = {
        "unit": _UNITS,
        "residual pass (forwardKinematics)": _UNITS,
        "FK warm (path)": args.n_path,
        "IK warm (path)": args.n_path,
        "compensation (path)": args.n_path,
    }
    counts.update({name: len(cloud_sliders) for name in runs if name.startswith("forward_batch")})
    unit = median(times["unit"]) / _UNITS
    per = {name: median(t) / counts[name] for name, t in times.items()}
    spread = {name: (min(t) / counts[name] / unit, max(t) / counts[name] / unit) for name, t in times.items()}
    batch = results["forward_batch, 1 thread"]
    res_unit = per["residual pass (forwardKinematics)"] / unit
    floors = {"FK warm (path)": evaluations["FK"], "IK warm (path)": evaluations["IK"]}
    rows = []
    for name in runs:
        if name == "unit":
            continue
        goal = GOALS.get(name)
        floor = floors.get(name)
        rows.append(
            [
                name,
                fmt_time(per[name]),
                f"{per[name] / unit:.2f}",
                f"{spread[name][0]:.2f}-{spread[name][1]:.2f}",
                "-" if goal is None else f"<= {goal:g}",
                "-" if goal is None else ("met" if per[name] / unit <= goal else "not met"),
                "-"
                if floor is None
                else f"{floor[0]:.2f} + {floor[1]:.2f} x {res_unit:.2f} = {floor[0] + floor[1] * res_unit:.2f}",
            ]
        )
    print(
        f"Unit (computeJointJacobians + updateFramePlacements): {fmt_time(unit)}; median of {args.repeats} "
        f"interleaved rounds; {available_cores()} cores for 'every core'.\n"
    )
    print(
        table(
            [
                "operation",
                "time per pose / solve / target",
                "units (median)",
                "units (min-max)",
                "goal",
                "",
                "floor [units]: Jacobian + residual evaluations x their cost",
            ],
            rows,
        )
    )
    print(
        f"\nforward_batch: {len(batch.indices)}/{len(cloud_sliders)} rows converged, mean "
        f"{batch.iterations.mean():.2f} Newton steps per row from home (the predicted start counts as one), "
        f"max closure residual {batch.residuals.max():.1e}."
    )
    comp = results["compensation (path)"]
    print(f"compensation: {len(comp.indices)}/{args.n_path} targets, mean {comp.iterations.mean():.2f} IK steps.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
