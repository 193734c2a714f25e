"""Scaling with the number of poses: closed-loop and serial calibration, RLS updates, compensation.

1. Closed-loop calibration (`calibrate_closed_loop`, 204 placement parameters, 56 base) on noisy
   simulated data (1 mm / 1 mrad truth errors, tracker 10 um / 20 urad): wall time, LM iterations,
   peak Python/numpy memory (tracemalloc, in a separate run because tracing slows Python down;
   Pinocchio's C++ allocations are not traced) and held-out error. Baselines: the reference
   implementation's published 2.8 s at 50 poses (docs/results.md; not runnable here) and, measured
   in the same run at the smallest sizes, finite-difference LM (`least_squares(method="lm")`, no
   Jacobian) on the same whitened residual over the same base parameters, each residual a fresh
   assembly of every pose on the trial model.
2. Recursive least squares: cost of absorbing one pose (6 rows, 56 parameters) into
   `RecursiveLeastSquares`, against re-solving the batch problem from scratch at each new pose.
3. Serial calibration (UR10, `calibrate_serial`) at growing sizes, with finite-difference LM at the
   smaller ones.
4. Compensation throughput (`m3t1r.compensation.Compensator`, calibrated IK + nominal FK per
   target) along a 1,000-target path, warm-started, against the same solves started from home.

Run: python benchmarks/bench_scaling.py [--sizes 20 50 100 1000] [--fd-sizes 20 50] [--quick]
     (add 10000 to --sizes to measure it rather than extrapolate; about a minute and 1.4 GB here)
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_rate, fmt_time, header, interleaved_times, median, table  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors  # noqa: E402
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.identification import RecursiveLeastSquares, batch_least_squares  # noqa: E402
from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions  # noqa: E402
from m3t1r.calibration.simulation import simulate_study  # noqa: E402
from m3t1r.errors import KinematicsError  # noqa: E402
from m3t1r.model.description import Mechanism  # noqa: E402
from m3t1r.model.kinematics import ClosedLoopSolver  # noqa: E402

NOISE = TrackerNoise(position=10e-6, rotation=20e-6, actuator=1e-6)
REFERENCE_50_POSES = 2.8  # [s] an independent reference implementation (plain Python), 50 poses: docs/results.md
GOALS = {50: 0.5, 1000: 5.0}  # [s] issue goals on one core


def peak_memory(run) -> float:
    """Peak traced allocation [bytes] while `run()` executes (numpy buffers and Python objects)."""
    tracemalloc.start()
    try:
        run()
        return float(tracemalloc.get_traced_memory()[1])
    finally:
        tracemalloc.stop()


class FiniteDifferenceClosedLoop:
    """Whitened closed-loop pose residual over given base columns, for MINPACK's LM without Jacobian.

    Same residual rows as `calibrate_closed_loop`: [p_model - p_meas; log3(R_meas^T R_model)] divided
    by the tracker noise; same parameters (right-multiplied placement errors, here applied from the
    nominal model in one step). Each residual assembles every pose on the trial model, warm-started
    from the configurations of the previous evaluation.
    """

    def __init__(self, nominal: Mechanism, measurements: PoseMeasurements, columns: np.ndarray) -> None:
        import pinocchio as pin

        self.pin = pin
        self.nominal = nominal
        self.error_model = ClosedLoopErrorModel(nominal)
        self.measurements = measurements
        self.columns = columns
        self.weights = np.r_[np.full(3, 1 / NOISE.position), np.full(3, 1 / NOISE.rotation)]
        solver = ClosedLoopSolver(nominal)
        self.configurations = [solver.forward(a, q_init=nominal.home).q for a in measurements.actuators]
        self.start = list(self.configurations)

    def residual(self, x: np.ndarray) -> np.ndarray:
        pin = self.pin
        vector = np.zeros(self.error_model.n_parameters)
        vector[self.columns] = x
        solver = ClosedLoopSolver(self.nominal.with_model(self.error_model.perturbed(self.nominal.model, vector)))
        out = np.empty((len(self.measurements), 6))
        configurations = []
        try:
            for i, (sliders, measured) in enumerate(zip(self.measurements.actuators, self.measurements.poses)):
                result = solver.forward(sliders, q_init=self.configurations[i])
                configurations.append(result.q)
                out[i, :3] = result.pose.translation - measured.translation
                out[i, 3:] = pin.log3(measured.rotation.T @ result.pose.rotation)
        except KinematicsError:
            return np.full(out.size, 1e10)  # a trial model that does not assemble: a huge cost
        self.configurations = configurations
        return (out * self.weights).ravel()

    def solve(self) -> tuple[object, int]:
        self.configurations = list(self.start)
        calls = [0]

        def counted(x: np.ndarray) -> np.ndarray:
            calls[0] += 1
            return self.residual(x)

        result = least_squares(counted, np.zeros(len(self.columns)), method="lm", ftol=1e-10, xtol=1e-10, gtol=1e-10)
        vector = np.zeros(self.error_model.n_parameters)
        vector[self.columns] = result.x
        model = self.error_model.perturbed(self.nominal.model, vector)
        from m3t1r.model.kinematics import rehomed

        return rehomed(self.nominal.with_model(model)), calls[0]


def closed_loop_section(
    nominal: Mechanism, sizes: list[int], fd_sizes: list[int], repeats: int, memory: bool
) -> tuple[str, dict]:
    rows, fd_rows, timings = [], [], {}
    for n in sizes:
        study = simulate_study(nominal, n_poses=n, n_holdout=100, seed=7 + n, noise=NOISE)
        run = lambda: calibrate_closed_loop(nominal, study.measurements, CalibrationOptions(noise=NOISE))  # noqa: E731
        runs: dict = {"ours": run}
        if n in fd_sizes:
            # The baseline estimates our base set: the rank analysis is given to it for free.
            columns = np.array(run().base.indices)
            fd = FiniteDifferenceClosedLoop(nominal, study.measurements, columns)
            runs["fd"] = fd.solve
        results: dict = {}
        # Finite differences take tens of seconds per run: one round with them, then ours alone.
        times = interleaved_times(runs, 1, results)
        if n <= 100 and repeats > 1:
            times["ours"] += interleaved_times({"ours": run}, repeats - 1)["ours"]
        calibration = results["ours"]
        seconds = median(times["ours"])
        timings[n] = seconds
        peak = peak_memory(run) if memory else float("nan")
        errors = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
        goal = GOALS.get(n)
        verdict = (
            "-"
            if goal is None
            else (f"met ({goal:g} s)" if seconds < goal else f"MISSED by {seconds / goal:.1f}x ({goal:g} s)")
        )
        rows.append(
            [
                n,
                fmt_time(seconds),
                f"{seconds / n * 1e3:.1f} ms",
                calibration.lm.iterations,
                calibration.lm.termination,
                f"{peak / 2**20:.1f} MiB" if memory else "-",
                f"{errors.position_mean * 1e6:.1f}",
                f"{errors.rotation_mean * 1e6:.1f}",
                verdict,
            ]
        )
        if "fd" in results:
            fd_model, fd_calls = results["fd"]
            fd_seconds = median(times["fd"])
            fd_errors = pose_errors(fd_model, study.truth, study.holdout_actuators)
            fd_rows.append(
                [
                    n,
                    fmt_time(seconds),
                    fmt_time(fd_seconds),
                    f"{fd_seconds / seconds:.1f}x",
                    fd_calls,
                    f"{errors.position_mean * 1e6:.1f} / {fd_errors.position_mean * 1e6:.1f}",
                ]
            )
    text = [
        table(
            [
                "poses",
                "time",
                "per pose",
                "LM iter.",
                "stop",
                "peak mem.",
                "held-out pos. mean um",
                "held-out rot. mean urad",
                "goal",
            ],
            rows,
        )
    ]
    largest = max(sizes)
    if 10000 not in sizes and largest >= 1000:
        text.append(
            f"\n10,000 poses not run: extrapolated linearly from {largest} poses, "
            f"~{timings[largest] / largest * 10000:.0f} s (the per-pose FK and sensitivity work and "
            "the LM QR are all linear in the pose count; the iteration count is assumed unchanged)."
        )
    if 50 in timings:
        text.append(
            f"\nReference implementation at 50 poses: {REFERENCE_50_POSES} s; ours "
            f"{timings[50]:.2f} s ({REFERENCE_50_POSES / timings[50]:.1f}x faster, different machine)."
        )
    if fd_rows:
        text.append(
            "\nFinite-difference LM on the same data and base parameters (one run, alternating with ours' first):\n"
        )
        text.append(
            table(
                ["poses", "ours", "FD-LM", "speed-up", "FD residual evals", "held-out pos. mean um (ours / FD)"],
                fd_rows,
            )
        )
    return "\n".join(text), timings


def rls_section(nominal: Mechanism, n_poses: int) -> str:
    """Per-pose RLS update against a batch re-solve, on whitened closed-loop rows at the nominal model."""
    from m3t1r.calibration.pose_selection import closed_loop_candidate_blocks
    from m3t1r.model.workspace import workspace_actuators

    rng = np.random.default_rng(11)
    blocks, _ = closed_loop_candidate_blocks(nominal, workspace_actuators(nominal, n_poses, rng), NOISE)
    from m3t1r.calibration.identification import select_base_parameters

    base = select_base_parameters(blocks.reshape(-1, blocks.shape[2]), [str(k) for k in range(blocks.shape[2])])
    A = blocks[:, :, list(base.indices)]
    truth = rng.normal(0.0, 1e-3, A.shape[2])
    y = A @ truth + rng.normal(0.0, 1.0, A.shape[:2])  # whitened rows: unit noise
    rls = RecursiveLeastSquares(A.shape[2])
    update_times, batch_times = [], []
    for k in range(n_poses):
        start = time.perf_counter()
        rls.update(A[k], y[k])
        update_times.append(time.perf_counter() - start)
        if k + 1 >= 10 and (k + 1) % max(1, n_poses // 20) == 0:  # the batch baseline at a few sizes
            start = time.perf_counter()
            batch_least_squares(A[: k + 1].reshape(-1, A.shape[2]), y[: k + 1].ravel())
            batch_times.append((k + 1, time.perf_counter() - start))
    final = batch_least_squares(A.reshape(-1, A.shape[2]), y.ravel())
    agreement = float(np.max(np.abs(rls.estimate - final.x)) / np.max(np.abs(final.x)))
    update = median(update_times)
    rows = [["RLS update (any pose count)", fmt_time(update), fmt_rate(1 / update)]]
    shown = sorted(set(range(0, len(batch_times), max(1, len(batch_times) // 4))) | {len(batch_times) - 1})
    for count, seconds in (batch_times[i] for i in shown):
        rows.append([f"batch re-solve at {count} poses", fmt_time(seconds), f"{seconds / update:.0f}x the update"])
    return (
        table(["operation (6 rows, %d base parameters)" % A.shape[2], "time", "rate / ratio"], rows)
        + f"\n\nRLS estimate after {n_poses} poses vs batch solution: max relative difference {agreement:.1e}."
    )


def serial_section(sizes: list[int], fd_sizes: list[int], repeats: int, memory: bool) -> str:
    from bench_identification import NOISE as SERIAL_NOISE
    from bench_identification import FiniteDifferenceCalibration

    from m3t1r.calibration.serial import calibrate_serial
    from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
    from m3t1r.calibration.serial_simulation import simulate_serial_measurements
    from m3t1r.model.poe import SerialChain

    model = load_example_robot("ur10")
    chain = SerialChain.from_model(model, example_tool_frame("ur10"))
    rows = []
    for n in sizes:
        data = simulate_serial_measurements(model, chain, n, np.random.default_rng(n), noise=SERIAL_NOISE)
        run = lambda: calibrate_serial(
            model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=SERIAL_NOISE)
        )  # noqa: E731
        runs = {"ours": run}
        if n in fd_sizes:
            runs["fd"] = FiniteDifferenceCalibration(
                model, chain, data.q_readings, data.measured_poses, run().base.indices, SERIAL_NOISE
            ).solve
        results: dict = {}
        times = interleaved_times(runs, repeats if n <= 1000 else 1, results)
        result = results["ours"]
        seconds = median(times["ours"])
        peak = peak_memory(run) if memory else float("nan")
        fd = f"{fmt_time(median(times['fd']))} ({median(times['fd']) / seconds:.1f}x)" if "fd" in times else "-"
        rows.append(
            [
                n,
                fmt_time(seconds),
                f"{seconds / n * 1e6:.0f} us",
                result.iterations,
                f"{peak / 2**20:.1f} MiB" if memory else "-",
                fd,
            ]
        )
    return table(["poses", "ours", "per pose", "LM iter.", "peak mem.", "FD-LM (ratio)"], rows)


def compensation_section(nominal: Mechanism, n_targets: int, repeats: int) -> str:
    from bench_kinematics import workspace_path

    from m3t1r.calibration.simulation import actual_machine, random_placement_errors

    try:
        from m3t1r.compensation import Compensator
    except ImportError:
        return "m3t1r.compensation not available: not measured."
    error_model = ClosedLoopErrorModel(nominal)
    calibrated = actual_machine(
        nominal, random_placement_errors(error_model, np.random.default_rng(5), 1e-3, 1e-3), error_model
    )  # any perturbed machine: the speed does not depend on which
    targets = workspace_path(n_targets)
    compensator = Compensator(nominal, calibrated)

    def warm() -> None:
        compensator.reset()
        result = compensator.compensate(targets)
        assert result.complete, result.failures[:1]

    def cold() -> None:
        for target in targets:
            compensator.reset()
            compensator.command(target)

    times = interleaved_times({"warm": warm, "cold": cold}, repeats)
    w, c = median(times["warm"]) / n_targets, median(times["cold"]) / n_targets
    return table(
        ["compensation (calibrated IK + nominal FK)", "time/target", "targets/s"],
        [
            [f"warm-started along the path ({n_targets} targets)", fmt_time(w), fmt_rate(1 / w)],
            ["each target from home (baseline)", fmt_time(c), fmt_rate(1 / c)],
            ["speed-up of warm starts", f"{c / w:.1f}x", "-"],
        ],
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 50, 100, 1000])
    parser.add_argument(
        "--fd-sizes",
        type=int,
        nargs="*",
        default=[20, 50],
        help="closed-loop sizes at which finite-difference LM also runs (slow)",
    )
    parser.add_argument("--serial-sizes", type=int, nargs="+", default=[20, 50, 100, 1000, 10000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-memory", action="store_true", help="skip the tracemalloc runs")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.fd_sizes, args.serial_sizes, args.repeats = [20], [], [20, 100], 1
        args.no_memory = True
    n_targets = 60 if args.quick else 1000
    print(header("Scaling: calibration time and memory, RLS updates, compensation throughput", __file__, argv))
    nominal = Mechanism.load()
    with single_blas_thread():
        print(
            f"### Closed-loop calibration (noisy: {NOISE.position * 1e6:g} um / {NOISE.rotation * 1e6:g} urad; "
            f"median of {args.repeats} run(s) up to 100 poses, 1 above)\n"
        )
        text, _ = closed_loop_section(nominal, sorted(args.sizes), args.fd_sizes, args.repeats, not args.no_memory)
        print(text)
        print("\n### Recursive least squares, per pose\n")
        print(rls_section(nominal, 60 if args.quick else 1000))
        print("\n### Serial calibration, UR10 (50 % of the rows are orientation)\n")
        print(
            serial_section(
                sorted(args.serial_sizes), [n for n in args.serial_sizes if n <= 100], args.repeats, not args.no_memory
            )
        )
        print("\n### Compensation throughput\n")
        print(compensation_section(nominal, n_targets, args.repeats))
    print(
        "\nGoals: 50-pose closed-loop calibration < 0.5 s and 1,000 poses < 5 s on one core. Peak memory is "
        "what tracemalloc sees (numpy and Python objects), not Pinocchio's C++ heap."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
