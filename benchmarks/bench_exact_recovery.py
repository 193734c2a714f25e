"""Noise-free recovery of a 1 mm / 1 mrad machine: the default fit vs the opt-in refinement.

The stretch goal of issue 3 is exact recovery (1e-9 m). This prints how close each stage gets on
held-out poses and what it costs, against the reference implementation's 0.17 um (docs/results.md).
Run: python benchmarks/bench_exact_recovery.py [--seeds 0 1]
"""

from __future__ import annotations

import argparse
import time

from m3t1r._threads import single_blas_thread
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.simulation import simulate_study
from m3t1r.model.description import Mechanism


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--iterations", type=int, default=400)
    args = parser.parse_args()
    nominal = Mechanism.load()
    print(f"{'seed':>4} {'stage':<28}{'base':>5}{'fitted':>7}{'held-out mean [m]':>19}{'max [m]':>11}{'time [s]':>10}")
    with single_blas_thread():
        for seed in args.seeds:
            study = simulate_study(nominal, 50, 200, seed)
            for label, refine in (("default fit", False), ("refined at the estimate", True)):
                start = time.perf_counter()
                calibration = calibrate_closed_loop(
                    nominal, study.measurements, CalibrationOptions(refine=refine, refine_iterations=args.iterations)
                )
                seconds = time.perf_counter() - start
                errors = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
                print(
                    f"{seed:>4} {label:<28}{calibration.base.rank:>5}{len(calibration.fitted):>7}"
                    f"{errors.position_mean:>19.2e}{errors.position.max():>11.2e}{seconds:>10.1f}"
                )
    print("reference implementation (docs/results.md): 1.7e-07 mean, 1.3e-06 max")


if __name__ == "__main__":
    main()
