"""Serial-robot identification: analytic POE Jacobian + our LM vs finite-difference LM.

Ours: `m3t1r.calibration.serial.calibrate_serial` (error Jacobian from adjoints along the chain, Levenberg-
Marquardt with multiplicative updates T(0) <- T(0) exp6(dx) over the base parameters).

Baseline: the approach of the FIGAROH toolbox, a residual function evaluated with Pinocchio's
forward kinematics and `scipy.optimize.least_squares(method="lm")` given NO Jacobian, so MINPACK
forms it by forward differences. Made fair: the same parameters (our final base set, each a
right-multiplied error twist on its placement, applied to the nominal model as T(0) exp6(x);
FIGAROH itself uses additive offsets on xyz/rpy, which differ only by a change of chart), the same
whitened residual (position in the base frame / sigma_p, log3(R_meas^T R) in the tool frame /
sigma_R), the same data and the same start (nominal); tolerances 1e-10. It is handed the base
set for free (no rank analysis timed).

Accuracy: tool position and orientation RMS error against the truth at held-out configurations.

Run: python benchmarks/bench_identification.py [--robots ur10 ur5] [--datasets 3] [--repeats 3] [--quick]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_time, header, interleaved_times, median, table  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.serial import calibrate_serial  # noqa: E402
from m3t1r.calibration.serial_evaluation import pose_errors
from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
from m3t1r.calibration.serial_simulation import sample_configurations, simulate_serial_measurements
from m3t1r.calibration.simulation import PlacementErrorScale
from m3t1r.model.poe import SerialChain, perturb  # noqa: E402

N_POSES = 50
N_HELD_OUT = 200
NOISE = TrackerNoise(position=10e-6, rotation=20e-6)  # tracker 10 um / 20 urad; exact joint readings


class FiniteDifferenceCalibration:
    """Whitened pose residual over the base parameters for MINPACK's LM with difference quotients."""

    def __init__(
        self,
        model: pin.Model,
        chain: SerialChain,
        q_chain: np.ndarray,
        measured: tuple[pin.SE3, ...],
        base_indices: tuple[int, ...],
        noise: TrackerNoise,
    ) -> None:
        self.model, self.chain = model, chain
        self.configurations = [chain.model_configuration(model, q) for q in q_chain]
        self.positions = np.array([g.translation for g in measured])
        self.rotations_t = [g.rotation.T for g in measured]
        self.base = np.array(base_indices)
        self.placements = chain.placements()
        self.weights = np.r_[np.full(3, 1.0 / noise.position), np.full(3, 1.0 / noise.rotation)]

    def model_at(self, x: np.ndarray) -> pin.Model:
        full = np.zeros(self.chain.n_parameters)
        full[self.base] = x
        return perturb(self.model, {p: full[6 * k : 6 * k + 6] for k, p in enumerate(self.placements)})

    def residual(self, x: np.ndarray) -> np.ndarray:
        model = self.model_at(x)
        data = model.createData()
        tool = self.chain.tool_frame_id
        out = np.empty((len(self.configurations), 6))
        for i, q in enumerate(self.configurations):
            pin.forwardKinematics(model, data, q)
            g = pin.updateFramePlacement(model, data, tool)
            out[i, :3] = g.translation - self.positions[i]
            out[i, 3:] = pin.log3(self.rotations_t[i] @ g.rotation)
        return (out * self.weights).ravel()

    def solve(self) -> tuple[pin.Model, int]:
        """The calibrated model and the number of residual evaluations, difference quotients included
        (counted here: scipy's `nfev` for method "lm" leaves them out)."""
        calls = [0]

        def counted(x: np.ndarray) -> np.ndarray:
            calls[0] += 1
            return self.residual(x)

        result = least_squares(counted, np.zeros(len(self.base)), method="lm", ftol=1e-10, xtol=1e-10, gtol=1e-10)
        return self.model_at(result.x), calls[0]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", nargs="+", default=["ur10", "ur5"])
    parser.add_argument("--datasets", type=int, default=3, help="independent truth robots / datasets per robot")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats per dataset")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.robots, args.datasets, args.repeats = ["ur5"], 1, 1
    print(header("Serial identification: analytic Jacobian + LM (ours) vs finite-difference LM", __file__, argv))
    rows, detail = [], []
    with single_blas_thread():
        for robot in args.robots:
            model = load_example_robot(robot)
            chain = SerialChain.from_model(model, example_tool_frame(robot))
            ours_t, fd_t, ours_err, fd_err, nfevs = [], [], [], [], []
            for seed in range(args.datasets):
                rng = np.random.default_rng(100 + seed)
                data = simulate_serial_measurements(
                    model,
                    chain,
                    N_POSES,
                    rng,
                    errors=PlacementErrorScale(1e-3, 1e-3),
                    joint_offset=1e-3,
                    noise=NOISE,
                )
                held_out = sample_configurations(model, chain, N_HELD_OUT, rng)
                ours = calibrate_serial(
                    model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=NOISE)
                )
                baseline = FiniteDifferenceCalibration(
                    model, chain, data.q_readings, data.measured_poses, ours.base.indices, NOISE
                )
                fd_model, nfev = baseline.solve()
                times = interleaved_times(
                    {
                        "ours": lambda: calibrate_serial(
                            model, chain, data.q_readings, data.measured_poses, CalibrationOptions(noise=NOISE)
                        ),
                        "fd": baseline.solve,
                    },
                    args.repeats,
                )
                ours_t.append(median(times["ours"]))
                fd_t.append(median(times["fd"]))
                e_ours = pose_errors(ours.model, data.truth, chain, held_out)
                e_fd = pose_errors(fd_model, data.truth, chain, held_out)
                before = pose_errors(model, data.truth, chain, held_out)
                ours_err.append((e_ours.position_rms, e_ours.rotation_rms))
                fd_err.append((e_fd.position_rms, e_fd.rotation_rms))
                nfevs.append(nfev)
                detail.append(
                    [
                        robot,
                        seed,
                        ours.base.rank,
                        f"{before.position_rms * 1e3:.2f} mm",
                        f"{e_ours.position_rms * 1e6:.2f} / {e_fd.position_rms * 1e6:.2f}",
                        f"{e_ours.rotation_rms * 1e6:.2f} / {e_fd.rotation_rms * 1e6:.2f}",
                        f"{ours.iterations} / {nfev}",
                        fmt_time(ours_t[-1]),
                        fmt_time(fd_t[-1]),
                    ]
                )
            ratio = median(fd_t) / median(ours_t)
            o, f = np.mean(ours_err, axis=0), np.mean(fd_err, axis=0)
            rows.append(
                [
                    robot,
                    args.datasets,
                    fmt_time(median(ours_t)),
                    fmt_time(median(fd_t)),
                    f"{ratio:.1f}x",
                    f"{o[0] * 1e6:.2f} / {f[0] * 1e6:.2f}",
                    f"{o[1] * 1e6:.2f} / {f[1] * 1e6:.2f}",
                    f"{np.mean(nfevs):.0f}",
                ]
            )
    print(
        f"{N_POSES} poses per dataset, truth errors 1 mm / 1 mrad per placement and 1 mrad joint offsets, tracker "
        f"noise {NOISE.position * 1e6:g} um / {NOISE.rotation * 1e6:g} urad, held-out RMS over {N_HELD_OUT} "
        f"configurations. Times: median over datasets of the per-dataset median of {args.repeats} interleaved "
        "repeat(s).\n"
    )
    print(
        table(
            [
                "robot",
                "datasets",
                "ours",
                "FD-LM",
                "speed-up",
                "held-out pos. RMS um (ours / FD)",
                "held-out rot. RMS urad (ours / FD)",
                "FD residual evals",
            ],
            rows,
        )
    )
    print("\nPer dataset:\n")
    print(
        table(
            [
                "robot",
                "seed",
                "base params",
                "error before",
                "pos. RMS um (ours / FD)",
                "rot. RMS urad (ours / FD)",
                "LM iterations / FD evals",
                "ours",
                "FD-LM",
            ],
            detail,
        )
    )
    print("\nGoal: >= 20x faster than finite-difference LM with the same or better held-out accuracy.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
