"""Closed-loop FK and IK throughput: our Newton solver against an SLSQP constrained solve.

Ours: `ClosedLoopSolver.forward` / `.inverse`, Newton with reused LU factors and a first-order
predictor when warm-started (tolerance 1e-12 on the closure rows).

Baseline: the formulation of Gepetto's toolbox-parallel-robots (which does not import with the PyPI
Pinocchio wheel, so it is re-created here): the configuration nearest to a start q0 that closes
the loops, min 1/2 ||x - x0||^2 s.t. closure(q) = 0, by `scipy.optimize.minimize(method="SLSQP")`.
FK: x = passive joints, sliders fixed, 16 equations. IK: x = all 20 joints, 16 closure rows plus
platform position (3) and yaw (1) equal to the target. Both systems are square, so the constraint
set is a set of isolated points and the objective only picks the one nearest the start, like our
branch tracking. To be fair the baseline gets exact (analytic) Jacobians of objective and
constraints, one Pinocchio pass per distinct iterate (residual and Jacobian cached together),
ftol = 1e-10, with which it reaches the same 1e-10 accuracy, and the previous solution as its start
along the path (warm) or home (cold). The toolbox itself passes no Jacobians (SLSQP then takes
forward differences); that variant is timed too, with the same tightened tolerance.

Run: python benchmarks/bench_kinematics.py [--n-path 1000] [--n-slsqp 200] [--repeats 5] [--quick]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_rate, fmt_time, header, median, table  # noqa: E402

from m3t1r._threads import single_blas_thread  # noqa: E402
from m3t1r.model.description import Mechanism  # noqa: E402
from m3t1r.model.design import NOMINAL  # noqa: E402
from m3t1r.model.kinematics import ClosedLoopSolver, yaw_of  # noqa: E402

ACCURACY = 1e-10  # [m, rad] closure residual both methods must reach for the comparison to count
# SLSQP stops when the objective change and the summed constraint violation are below ftol; 1e-10
# is the loosest setting at which every solve still ends below ACCURACY (its last Newton-like step
# lands near 1e-12 anyway), so the baseline does no more work than equal accuracy needs.
SLSQP_FTOL = 1e-10


def workspace_path(n: int, margin: float = 0.9) -> np.ndarray:
    """n targets (x, y, z, theta) [m, m, m, rad] on a closed Lissajous curve through the workspace
    box, `margin` of each half-range: consecutive targets a few mm apart, as a trajectory would be."""
    box = NOMINAL.workspace
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    bounds = np.array([box.x, box.y, box.z, box.theta])
    centre, half = bounds.mean(axis=1), margin * np.diff(bounds, axis=1)[:, 0] / 2
    waves = np.stack(
        [np.sin(2 * np.pi * t), np.sin(4 * np.pi * t + 0.5), np.sin(6 * np.pi * t + 1.0), np.sin(2 * np.pi * t + 2.0)],
        axis=1,
    )
    return centre + half * waves


@dataclass(frozen=True)
class Run:
    """One pass over a list of problems: wall time [s], solved count, worst closure residual,
    worst task error (IK: position [m] or yaw [rad]; FK: nan), and the solutions."""

    seconds: float
    solved: int
    max_residual: float
    max_task_error: float
    solutions: list


class SlsqpKinematics:
    """FK and IK as nearest-point constrained problems for SLSQP.

    analytic=True: exact Jacobians of the objective and of every constraint, residual and Jacobian
    computed together once per iterate. analytic=False: SLSQP's own forward differences, as the
    toolbox calls it (`fmin_slsqp(cost, q0, f_eqcons=residual)`), each difference a residual-only
    Pinocchio pass; only the tolerance is tightened, to reach the same accuracy.
    """

    def __init__(self, mechanism: Mechanism, analytic: bool) -> None:
        self.mechanism = mechanism
        self.analytic = analytic
        self.solver = ClosedLoopSolver(mechanism)  # used for its residual/Jacobian evaluation only
        self.model = mechanism.model
        self.passive, self.actuated = self.solver.passive, self.solver.actuated
        self.platform = mechanism.platform_frame_id
        self._key: bytes | None = None
        self._cache: tuple | None = None

    def _closure(self, q: np.ndarray) -> tuple:
        """(residual, Jacobian wrt q or None, platform pose, platform Jacobian or None) at q; cached
        on q, since SLSQP asks for a constraint's value and its Jacobian at one iterate separately."""
        key = q.tobytes()
        if key != self._key:
            data = self.solver.data
            if self.analytic:
                residual, jacobian, _ = self.solver.closure_sensitivity(q)
                frame_jac = pin.getFrameJacobian(self.model, data, self.platform, pin.LOCAL_WORLD_ALIGNED)
            else:
                residual, jacobian, frame_jac = self.solver.closure_residual(q), None, None
            self._key, self._cache = key, (residual, jacobian, pin.SE3(data.oMf[self.platform]), frame_jac)
        return self._cache

    def _minimize(self, x0: np.ndarray, constraint, constraint_jacobian) -> np.ndarray:
        spec = {"type": "eq", "fun": constraint}
        if self.analytic:
            spec["jac"] = constraint_jacobian
        objective_jac = (lambda x: x - x0) if self.analytic else None
        result = minimize(
            lambda x: 0.5 * float((x - x0) @ (x - x0)),
            x0.copy(),
            jac=objective_jac,
            method="SLSQP",
            constraints=[spec],
            options={"ftol": SLSQP_FTOL, "maxiter": 200},
        )
        return result.x

    def forward(self, sliders: np.ndarray, q_start: np.ndarray) -> np.ndarray:
        q = q_start.copy()
        q[self.actuated] = sliders

        def full(x: np.ndarray) -> np.ndarray:
            q[self.passive] = x
            return q

        x = self._minimize(
            q[self.passive].copy(),
            lambda x: self._closure(full(x))[0],
            lambda x: self._closure(full(x))[1][:, self.passive],
        )
        return full(x).copy()

    def inverse(self, target: np.ndarray, q_start: np.ndarray) -> np.ndarray:
        xyz, theta = target[:3], float(target[3])

        def task(q: np.ndarray) -> np.ndarray:
            residual, _, oMp, _ = self._closure(q)
            yaw_error = math.remainder(yaw_of(oMp.rotation) - theta, 2 * math.pi)
            return np.concatenate((residual, oMp.translation - xyz, [yaw_error]))

        def task_jacobian(q: np.ndarray) -> np.ndarray:
            _, jacobian, oMp, frame_jac = self._closure(q)
            c = oMp.rotation[:, 0]
            horizontal = c[0] ** 2 + c[1] ** 2
            # d atan2(R10, R00) for dR = [omega]x R: the heading's rate from the WORLD angular velocity.
            yaw_row = np.array([-c[0] * c[2], -c[1] * c[2], horizontal]) / horizontal @ frame_jac[3:]
            return np.vstack((jacobian, frame_jac[:3], yaw_row))

        return self._minimize(q_start.copy(), task, task_jacobian).copy()


def _closure_error(solver: ClosedLoopSolver, q: np.ndarray) -> float:
    return float(np.max(np.abs(solver.closure_residual(q))))


def _task_error(solver: ClosedLoopSolver, q: np.ndarray, target: np.ndarray) -> float:
    solver.closure_residual(q)  # leaves the frame placements at q
    oMp = solver.data.oMf[solver.mechanism.platform_frame_id]
    return max(
        float(np.max(np.abs(oMp.translation - target[:3]))),
        abs(math.remainder(yaw_of(oMp.rotation) - target[3], 2 * math.pi)),
    )


def run_ours_fk(solver: ClosedLoopSolver, sliders: np.ndarray, warm: bool) -> Run:
    home = solver.mechanism.home
    solver.reset()
    solutions = []
    start = time.perf_counter()
    for values in sliders:
        solutions.append(solver.forward(values, q_init=None if warm else home).q)
    seconds = time.perf_counter() - start
    check = ClosedLoopSolver(solver.mechanism)
    return Run(seconds, len(solutions), max(_closure_error(check, q) for q in solutions), math.nan, solutions)


def run_ours_ik(solver: ClosedLoopSolver, targets: np.ndarray, warm: bool) -> Run:
    home = solver.mechanism.home
    solver.reset()
    solutions = []
    start = time.perf_counter()
    for target in targets:
        solutions.append(solver.inverse(target, q_init=None if warm else home).q)
    seconds = time.perf_counter() - start
    check = ClosedLoopSolver(solver.mechanism)
    return Run(
        seconds,
        len(solutions),
        max(_closure_error(check, q) for q in solutions),
        max(_task_error(check, q, t) for q, t in zip(solutions, targets)),
        solutions,
    )


def run_slsqp(baseline: SlsqpKinematics, problems: np.ndarray, kind: str, warm: bool) -> Run:
    home = baseline.mechanism.home
    q = home.copy()
    solutions = []
    start = time.perf_counter()
    for problem in problems:
        start_q = q if warm else home
        q = baseline.forward(problem, start_q) if kind == "fk" else baseline.inverse(problem, start_q)
        solutions.append(q)
    seconds = time.perf_counter() - start
    check = ClosedLoopSolver(baseline.mechanism)
    residuals = [_closure_error(check, s) for s in solutions]
    tasks = [_task_error(check, s, t) for s, t in zip(solutions, problems)] if kind == "ik" else [math.nan]
    solved = sum(
        r <= ACCURACY and (kind == "fk" or e <= ACCURACY)
        for r, e in zip(residuals, tasks if kind == "ik" else [0.0] * len(residuals))
    )
    return Run(seconds, solved, max(residuals), max(tasks), solutions)


def _difference(mechanism: Mechanism, ours: list, theirs: list, kind: str) -> float:
    """Largest platform position difference [m] (FK) or slider difference [m] (IK) between solutions."""
    if kind == "ik":
        actuated = mechanism.actuated_ids
        return max(float(np.max(np.abs(a[actuated] - b[actuated]))) for a, b in zip(ours, theirs))
    model, data = mechanism.model, mechanism.model.createData()
    worst = 0.0
    for a, b in zip(ours, theirs):
        pin.framesForwardKinematics(model, data, a)
        pa = data.oMf[mechanism.platform_frame_id].translation.copy()
        pin.framesForwardKinematics(model, data, b)
        worst = max(worst, float(np.linalg.norm(pa - data.oMf[mechanism.platform_frame_id].translation)))
    return worst


BASELINES = (("SLSQP, exact Jacobians", True), ("SLSQP, finite differences (toolbox call)", False))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n-path", type=int, default=1000, help="targets along the path (ours)")
    parser.add_argument("--n-slsqp", type=int, default=200, help="first targets of the path solved by SLSQP too")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    args = parser.parse_args(argv)
    if args.quick:
        args.n_path, args.n_slsqp, args.repeats = 60, 6, 1
    args.n_slsqp = min(args.n_slsqp, args.n_path)
    print(header("Closed-loop kinematics: Newton (ours) vs SLSQP nearest-point solve", __file__, argv))
    mechanism = Mechanism.load()
    targets = workspace_path(args.n_path)
    cases = [("FK", "fk", True), ("IK", "ik", True), ("FK", "fk", False), ("IK", "ik", False)]
    with single_blas_thread():
        solver = ClosedLoopSolver(mechanism)
        sliders = np.array([solver.inverse(t).actuators for t in targets])  # warm, along the path
        baselines = {name: SlsqpKinematics(mechanism, analytic) for name, analytic in BASELINES}
        ours_runs: dict[tuple, list[Run]] = {c: [] for c in cases}
        ours_sub: dict[tuple, list[Run]] = {c: [] for c in cases}
        their_runs: dict[tuple, list[Run]] = {(c, name): [] for c in cases for name in baselines}
        for _ in range(args.repeats):
            for case in cases:  # interleaved: ours on the whole path, then ours and SLSQP on its first part
                _, kind, warm = case
                run_ours = run_ours_fk if kind == "fk" else run_ours_ik
                problems = sliders if kind == "fk" else targets
                ours_runs[case].append(run_ours(solver, problems, warm))
                ours_sub[case].append(run_ours(solver, problems[: args.n_slsqp], warm))
                for name, baseline in baselines.items():
                    their_runs[case, name].append(run_slsqp(baseline, problems[: args.n_slsqp], kind, warm))

    rows_ours, rows_cmp = [], []
    for case in cases:
        name, kind, warm = case
        label = f"{name} {'warm (path)' if warm else 'cold (home)'}"
        runs = ours_runs[case]
        per = median([r.seconds for r in runs]) / args.n_path
        rows_ours.append(
            [
                label,
                args.n_path,
                f"{min(r.solved for r in runs)}/{args.n_path}",
                fmt_time(per),
                fmt_rate(1.0 / per),
                f"{max(r.max_residual for r in runs):.1e}",
                "-" if kind == "fk" else f"{max(r.max_task_error for r in runs):.1e}",
            ]
        )
        ours_per = median([r.seconds for r in ours_sub[case]]) / args.n_slsqp
        for baseline in baselines:
            runs = their_runs[case, baseline]
            theirs_per = median([r.seconds for r in runs]) / args.n_slsqp
            last = runs[-1]
            rows_cmp.append(
                [
                    label,
                    baseline,
                    fmt_time(ours_per),
                    fmt_time(theirs_per),
                    f"{theirs_per / ours_per:.1f}x",
                    f"{last.solved}/{args.n_slsqp}",
                    f"{last.max_residual:.1e}",
                    "-" if kind == "fk" else f"{last.max_task_error:.1e}",
                    f"{_difference(mechanism, ours_sub[case][-1].solutions, last.solutions, kind):.1e}",
                ]
            )
    step = np.median(np.linalg.norm(np.diff(targets[:, :3], axis=0), axis=1))
    print(
        f"Path: closed Lissajous curve through 90 % of the workspace box, {args.n_path} targets "
        f"({step * 1e3:.1f} mm apart); warm = each solve starts from the previous solution, cold = from "
        f"home. Median of {args.repeats} repeat(s).\n"
    )
    print("### Ours\n")
    print(
        table(["case", "solves", "converged", "time/solve", "solves/s", "max closure res.", "max task err."], rows_ours)
    )
    print(f"\n### Ours vs SLSQP on the first {args.n_slsqp} targets (same starts, interleaved)\n")
    print(
        table(
            [
                "case",
                "baseline",
                "ours/solve",
                "SLSQP/solve",
                "speed-up",
                f"SLSQP at <= {ACCURACY:g}",
                "SLSQP max closure res.",
                "SLSQP max task err.",
                "max diff vs ours",
            ],
            rows_cmp,
        )
    )
    print(
        f"\nOurs stops at 1e-12 on the closure rows, SLSQP at ftol {SLSQP_FTOL:g}; both must end below "
        f"{ACCURACY:g} for the times to compare. 'max diff vs ours': platform position [m] (FK) or slider "
        "[m] (IK) difference between the two solutions (both found the same assembly). Goals: warm FK and IK "
        ">= 5,000 solves/s each on one core; >= 20x faster than SLSQP at equal accuracy."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
