"""D-optimal calibration poses vs random ones: held-out error after a noisy closed-loop calibration.

Candidates: slider sets of platform poses drawn uniformly in the workspace box. Ours:
`m3t1r.calibration.pose_selection.select_poses` on the whitened identification blocks of the NOMINAL model
(the truth is unknown when poses are planned): greedy + exchange maximisation of log det of the
information matrix over the 56 base parameters. Baseline: the same number of poses drawn at random
from the same candidates, several draws. Both sets are then measured on the same truth machines
(1 mm / 1 mrad placement errors, tracker noise 10 um / 20 urad, slider noise 1 um), calibrated with
`calibrate_closed_loop`, and judged on the same held-out poses.

Run: python benchmarks/bench_pose_selection.py [--candidates 500] [--poses 20] [--truths 3] [--draws 5] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_time, header, table  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors  # noqa: E402
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurements import TrackerNoise, measure
from m3t1r.calibration.pipeline import CalibrationOptions  # noqa: E402
from m3t1r.calibration.pose_selection import (
    closed_loop_candidate_blocks,
    information_log_det,
    observability_index,
    select_poses,
)
from m3t1r.calibration.simulation import actual_machine, random_placement_errors
from m3t1r.errors import IdentificationError  # noqa: E402
from m3t1r.model.description import Mechanism  # noqa: E402
from m3t1r.model.workspace import workspace_actuators  # noqa: E402

NOISE = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)


def held_out_error(
    nominal: Mechanism, truth: Mechanism, actuators: np.ndarray, holdout: np.ndarray, rng: np.random.Generator
) -> tuple[float, float] | None:
    """Mean held-out position [m] and orientation [rad] error after calibrating on `actuators`;
    None when the set cannot identify the base parameters."""
    measurements = measure(truth, actuators, rng, NOISE)
    try:
        calibration = calibrate_closed_loop(nominal, measurements, CalibrationOptions(noise=NOISE))
    except IdentificationError:
        return None
    errors = pose_errors(calibration.mechanism, truth, holdout)
    return errors.position_mean, errors.rotation_mean


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--candidates", type=int, default=500)
    parser.add_argument("--poses", type=int, default=20)
    parser.add_argument("--truths", type=int, default=3, help="truth machines (independent seeds)")
    parser.add_argument("--draws", type=int, default=5, help="random pose sets per truth machine")
    parser.add_argument("--holdout", type=int, default=200)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.candidates, args.truths, args.draws, args.holdout = 60, 1, 1, 30
    print(header("Pose selection: D-optimal vs random calibration poses (closed loop)", __file__, argv))
    nominal = Mechanism.load()
    error_model = ClosedLoopErrorModel(nominal)
    rng = np.random.default_rng(2024)
    with single_blas_thread():
        candidates = workspace_actuators(nominal, args.candidates, rng)
        start = time.perf_counter()
        blocks, _ = closed_loop_candidate_blocks(nominal, candidates, NOISE, error_model=error_model)
        block_time = time.perf_counter() - start
        start = time.perf_counter()
        selection = select_poses(blocks, args.poses)
        select_time = time.perf_counter() - start
        kept = blocks[:, :, list(selection.columns)] * selection.column_scale
        random_sets = [
            [rng.choice(args.candidates, args.poses, replace=False) for _ in range(args.draws)]
            for _ in range(args.truths)
        ]
        rows, summary = [], {"selected": [], "random": []}
        for t in range(args.truths):
            truth_rng = np.random.default_rng(500 + t)
            truth = actual_machine(nominal, random_placement_errors(error_model, truth_rng, 1e-3, 1e-3), error_model)
            holdout = workspace_actuators(nominal, args.holdout, truth_rng)
            chosen = held_out_error(nominal, truth, candidates[list(selection.indices)], holdout, truth_rng)
            drawn = [held_out_error(nominal, truth, candidates[s], holdout, truth_rng) for s in random_sets[t]]
            ok = [d for d in drawn if d is not None]
            random_mean = np.mean(ok, axis=0) if ok else (np.nan, np.nan)
            summary["selected"].append(chosen if chosen is not None else (np.nan, np.nan))
            summary["random"].append(random_mean)
            rows.append(
                [
                    t,
                    f"{chosen[0] * 1e6:.1f}" if chosen else "failed",
                    f"{random_mean[0] * 1e6:.1f}"
                    + (f" ({len(drawn) - len(ok)} failed)" if len(ok) < len(drawn) else ""),
                    f"{random_mean[0] / chosen[0]:.2f}x" if chosen else "-",
                    f"{chosen[1] * 1e6:.1f}" if chosen else "failed",
                    f"{random_mean[1] * 1e6:.1f}",
                    f"{random_mean[1] / chosen[1]:.2f}x" if chosen else "-",
                ]
            )
    random_log_dets = [information_log_det(kept, s) for sets in random_sets for s in sets]
    finite = [v for v in random_log_dets if np.isfinite(v)]
    random_o1 = [
        observability_index(kept[s].reshape(-1, kept.shape[2]), args.poses) for sets in random_sets for s in sets
    ]
    selected_mean, random_mean = np.nanmean(summary["selected"], axis=0), np.nanmean(summary["random"], axis=0)
    print(
        f"{args.candidates} candidates in the workspace box; {args.poses} poses chosen; {args.truths} truth machine(s) "
        f"x {args.draws} random draw(s); held-out mean error over {args.holdout} poses. Blocks for all "
        f"candidates: {fmt_time(block_time)}; selection: {fmt_time(select_time)} ({selection.n_exchanges} exchanges, "
        f"{selection.passes} passes).\n"
    )
    print(
        table(
            ["set", "log det (normalised)", "observability O1", "condition number"],
            [
                [
                    "D-optimal",
                    f"{selection.log_det:.1f}",
                    f"{selection.observability_index:.3g}",
                    f"{selection.condition_number:.3g}",
                ],
                [
                    "random (mean of draws)",
                    f"{np.mean(finite):.1f}" if finite else "-inf",
                    f"{np.mean(random_o1):.3g}",
                    f"{len(random_log_dets) - len(finite)} of {len(random_log_dets)} rank deficient",
                ],
            ],
        )
    )
    print()
    print(
        table(
            [
                "truth",
                "pos. um D-opt",
                "pos. um random",
                "random / D-opt",
                "rot. urad D-opt",
                "rot. urad random",
                "random / D-opt",
            ],
            rows
            + [
                [
                    "mean",
                    f"{selected_mean[0] * 1e6:.1f}",
                    f"{random_mean[0] * 1e6:.1f}",
                    f"{random_mean[0] / selected_mean[0]:.2f}x",
                    f"{selected_mean[1] * 1e6:.1f}",
                    f"{random_mean[1] * 1e6:.1f}",
                    f"{random_mean[1] / selected_mean[1]:.2f}x",
                ]
            ],
        )
    )
    print("\nGoal: the selected poses beat random ones (ratio random / D-opt > 1).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
