"""A tracker campaign: the cost and the worth of robust estimation, model selection and cross-validation.

Data: a truth machine (1 mm / 1 mrad placement errors) measured by a tracker 1-5 m away at any
heading, through a reflector 50-100 mm off the platform (given to 0.5 mm), noise 10 um / 20 urad,
sliders 1 um, with and without two 3-5 mm gross outliers. Every variant estimates the frame and
the marker. Baseline: the plain least-squares fit (no outlier gate, no selection) on the same data,
timed interleaved in the same process. Reported: time, ratio to the plain fit, and the held-out
prediction error in the tracker frame (200 poses, noise-free truth).

Run: python benchmarks/bench_campaign.py [--poses 60] [--seeds 0 1 2] [--repeats 3] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_time, header, interleaved_times, median, table  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.calibration.closed_loop import calibrate_closed_loop, cross_validate  # noqa: E402
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise, measure
from m3t1r.calibration.pipeline import CalibrationOptions  # noqa: E402
from m3t1r.calibration.simulation import StudyOptions, simulate_study  # noqa: E402
from m3t1r.errors import PoorExcitationWarning  # noqa: E402
from m3t1r.metrics import pose_errors_between  # noqa: E402
from m3t1r.model.description import Mechanism  # noqa: E402

NOISE = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)


def _setup(rng: np.random.Generator) -> MeasurementSetup:
    axis, direction, offset = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    frame = pin.SE3(
        pin.exp3(axis / np.linalg.norm(axis) * rng.uniform(0.5, np.pi)),
        direction / np.linalg.norm(direction) * rng.uniform(1.0, 5.0),
    )
    marker = pin.SE3(pin.exp3(rng.normal(size=3)), offset / np.linalg.norm(offset) * rng.uniform(0.05, 0.1))
    return MeasurementSetup(frame, marker)


def _variants(nominal, study, given):
    base = dict(setup=MeasurementSetup(marker=given), estimate_frame=True, estimate_marker=True)
    return {
        "plain least squares": lambda: calibrate_closed_loop(
            nominal, study.measurements, CalibrationOptions(NOISE, outlier_sigma=None, **base)
        ),
        "outlier gate (5 sigma)": lambda: calibrate_closed_loop(
            nominal, study.measurements, CalibrationOptions(NOISE, **base)
        ),
        "gate + LOO selection": lambda: calibrate_closed_loop(
            nominal, study.measurements, CalibrationOptions(NOISE, select=True, **base)
        ),
    }


def run_case(nominal: Mechanism, seed: int, poses: int, outliers: int, repeats: int) -> list[list[str]]:
    rng = np.random.default_rng(500 + seed)
    setup = _setup(rng)
    study = simulate_study(nominal, poses, 200, seed, noise=NOISE, options=StudyOptions(setup=setup, outliers=outliers))
    given = pin.SE3(np.eye(3), setup.marker.translation + rng.normal(size=3) * 0.5e-3 / np.sqrt(3))
    runs = _variants(nominal, study, given)
    results: dict[str, object] = {}
    times = interleaved_times(runs, repeats, results)
    truth = measure(study.truth, study.holdout_actuators, setup=setup).poses
    plain = median(times["plain least squares"])
    rows = []
    for name, calibration in results.items():
        predicted = measure(calibration.mechanism, study.holdout_actuators, setup=calibration.setup).poses
        errors = pose_errors_between(predicted, truth)
        found = "exact" if calibration.outliers == study.outliers else f"{len(calibration.outliers)} flagged"
        rows.append(
            [
                seed,
                outliers,
                name,
                fmt_time(median(times[name])),
                f"{median(times[name]) / plain:.2f}x",
                f"{errors.position_mean * 1e6:.1f} um",
                f"{errors.rotation_mean * 1e6:.1f} urad",
                found if outliers else f"{len(calibration.outliers)} flagged",
            ]
        )
    cv_times = interleaved_times({"cv": lambda: cross_validate(results["gate + LOO selection"])}, repeats)
    rows.append(
        [
            seed,
            outliers,
            "5-fold cross-validation (after the fit)",
            fmt_time(median(cv_times["cv"])),
            f"{median(cv_times['cv']) / plain:.2f}x",
            "",
            "",
            "",
        ]
    )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.poses, args.seeds, args.repeats = 40, [0], 1
    print(header("Tracker campaign: robust estimation, selection, cross-validation", __file__, argv))
    nominal = Mechanism.load()
    rows = []
    with single_blas_thread(), warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        for seed in args.seeds:
            for outliers in (0, 2):
                rows += run_case(nominal, seed, args.poses, outliers, args.repeats)
    print(
        table(
            [
                "seed",
                "outliers",
                "fit",
                "time",
                "vs plain",
                "held-out position mean",
                "orientation mean",
                "outliers found",
            ],
            rows,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
