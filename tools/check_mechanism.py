"""Run every verb on a mechanism folder through the `m3t1r` command line and judge the figures.

A mechanism folder holds one URDF and one or more closures files (`robot.closures.yaml`,
`robot.rough.closures.yaml`, ...); each closures file is checked in turn, in a scratch folder, by
the sequence a user would run, and one table per file is printed:

- from a rough home without an assembled one beside it: the home m3t1r assembled closes under
  the independent closure rows (<= 1e-9), and is no farther from the given values (passive joints,
  revolute ones modulo whole turns) than the assembly a least-squares solve from them reaches;
- plan at 20, 40 and 60 poses (each must write its rows);
- fk at the 40-pose plan against an independent solve (Pinocchio placements and a least-squares
  continuation from home along the plan, sharing no code with m3t1r's solver; from a rough home,
  continued from the assembled home of a closures file beside it, else from m3t1r's, checked
  above): <= 1e-9 m;
- ik of those poses' task coordinates back to the plan's actuators: <= 1e-8;
- noise-free calibration of 0.1 mm / 0.1 mrad errors on every origin (`simulate --noise-free`),
  held out by `evaluate` against the truth: max <= 1e-7 m; the nominal's figure against the
  truth's own (fk of both machines at the plan): within 0.5-2x;
- noisy calibration (the truth measured by fk at the plan, 1e-5 m / 2e-5 rad noise added here):
  held-out mean within 0.5-2x of the floor `plan` predicts for those poses and that noise;
- validate on fresh noisy measurements of the truth: mean within 0.67-1.5x of the calibration's
  cross-validation figure;
- compensate (and compensate --report) with the noise-free calibration: the truth driven by the
  commands reaches the targets to <= 1e-7 m;
- view --html writes a page.

Exits 1 if any figure fails (or a command fails, or prints a traceback).

Run: python tools/check_mechanism.py DIR [--closures NAME ...] [--work DIR] [--m3t1r COMMAND]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import re
import shlex
import subprocess
import sys
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
import yaml
from scipy.optimize import least_squares

from m3t1r.errors import M3t1rError
from m3t1r.model.description import Mechanism as Loaded  # for the task the verbs take (declared or derived)

NOISE_POS, NOISE_ROT = 1e-5, 2e-5  # [m], [rad] per axis, the tracker noise of the noisy runs
ERRORS = ("1e-4", "1e-4")  # placement errors of the truth [m], [rad]


@dataclass(frozen=True)
class Figure:
    """One line of the table: what was measured, its value, the rule and whether it holds."""

    check: str
    value: float | None
    rule: str
    passed: bool
    detail: str = ""


class CommandFailed(Exception):
    """An m3t1r command exited non-zero or printed a traceback."""


class Runner:
    """Runs `m3t1r VERB ...` in a scratch folder; keeps what each printed."""

    def __init__(self, command: list[str], work: Path) -> None:
        self.command, self.work, self.log = command, work, []

    def __call__(self, *args: str) -> str:
        done = subprocess.run([*self.command, *args], cwd=self.work, capture_output=True, text=True)
        self.log.append((" ".join(args), done.returncode, done.stdout + done.stderr))
        if done.returncode != 0 or "Traceback" in done.stderr:
            last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
            raise CommandFailed(f"m3t1r {shlex.join(args[:1])} exited {done.returncode}: {last}")
        return done.stdout + done.stderr


# ------------------------------------------------------------------------------------------------
# Tables in and out


def read_table(path: Path) -> tuple[list[str], np.ndarray]:
    rows = [line for line in path.read_text().splitlines() if line and not line.startswith("#")]
    header = next(csv.reader([rows[0]]))
    return header, np.array([[float(v) for v in row.split(",")] for row in rows[1:]]).reshape(-1, len(header))


def write_table(path: Path, header: list[str], values: np.ndarray) -> None:
    lines = [",".join(header)] + [",".join(repr(float(v)) for v in row) for row in np.atleast_2d(values)]
    path.write_text("\n".join(lines) + "\n")


def columns(path: Path, names: list[str]) -> np.ndarray:
    header, values = read_table(path)
    return values[:, [header.index(n) for n in names]]


def task_coordinates(poses: np.ndarray, position: list[str], rotation: str) -> tuple[list[str], np.ndarray]:
    """Task columns (as `ik` reads them) of fk output rows x, y, z, qx, qy, qz, qw."""
    parts = [poses[:, ["xyz".index(a) for a in position]]]
    names = list(position)
    if rotation == "yaw":
        rot = [pin.Quaternion(*row[[6, 3, 4, 5]]).matrix() for row in poses]
        parts.append(np.array([[np.arctan2(r[1, 0], r[0, 0])] for r in rot]))
        names.append("theta")
    elif rotation == "full":
        parts.append(poses[:, 3:7])
        names += ["qx", "qy", "qz", "qw"]
    return names, np.hstack(parts)


# ------------------------------------------------------------------------------------------------
# The independent solve: Pinocchio placements, least squares over the passive joints


class IndependentSolver:
    """Closure rows from the closures file's frames (3D: R_a^T (p_b - p_a); 6D: log6(oMa^-1 oMb)),
    solved by scipy's least squares over every joint but the actuators, continued from home."""

    def __init__(self, urdf: Path, document: dict, assemble: bool = True) -> None:
        self.model = pin.buildModelFromUrdf(str(urdf))
        for name, entry in (document.get("frames") or {}).items():
            parent = self.model.frames[self.model.getFrameId(entry["link"])]
            offset = pin.SE3(pin.rpy.rpyToMatrix(*entry.get("rpy", [0.0, 0.0, 0.0])), np.array(entry["xyz"], float))
            self.model.addFrame(pin.Frame(name, parent.parentJoint, parent.placement * offset, pin.OP_FRAME))
        self.data = self.model.createData()
        self.closures = [
            (self.model.getFrameId(c["frame_a"]), self.model.getFrameId(c["frame_b"]), c["type"], c.get("rows"))
            for c in document["closures"]
        ]
        self.actuated = [self.model.joints[self.model.getJointId(n)] for n in document["actuated_joints"]]
        self.free = [v for v in range(self.model.nv) if v not in [j.idx_v for j in self.actuated]]
        self.passive = [j for j in range(1, self.model.njoints) if self.model.joints[j].idx_v in self.free]
        self.platform = self.model.getFrameId(document["platform_frame"])
        self.q = pin.neutral(self.model)
        for name, value in document["home"].items():
            _set(self.q, self.model.joints[self.model.getJointId(name)], float(value))
        self.given = self.q.copy()
        if assemble:
            self.q = self._solve(self.q)

    def _residual(self, q: np.ndarray) -> np.ndarray:
        pin.framesForwardKinematics(self.model, self.data, q)
        rows = []
        for a, b, kind, chosen in self.closures:
            oma, omb = self.data.oMf[a], self.data.oMf[b]
            full = (
                oma.rotation.T @ (omb.translation - oma.translation)
                if kind == "3D"
                else pin.log6(oma.actInv(omb)).vector
            )
            rows.append(full if chosen is None else full[list(chosen)])
        return np.concatenate(rows)

    def _solve(self, start: np.ndarray) -> np.ndarray:
        def moved(dv: np.ndarray) -> np.ndarray:
            step = np.zeros(self.model.nv)
            step[self.free] = dv
            return pin.integrate(self.model, start, step)

        rows = len(self._residual(start))
        # Levenberg-Marquardt needs as many rows as unknowns; idle spins (a rod's) leave fewer: trust region.
        method = "lm" if rows >= len(self.free) else "trf"
        fit = least_squares(
            lambda dv: self._residual(moved(dv)),
            np.zeros(len(self.free)),
            method=method,
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=20000,
        )
        return moved(fit.x)

    def platform_positions(self, actuators: np.ndarray, substeps: int = 4, stride: float = 0.02) -> np.ndarray:
        """Platform frame positions (N, 3) [m] at actuator rows taken as a path from home, each move in
        at least `substeps` steps of at most `stride` [m or rad] per actuator (longer steps of a leg's
        plan, 0.05 of its 0.3 rad moves, let the least squares jump to another assembly mode)."""
        out, q = [], self.q.copy()
        for row in actuators:
            first = np.array([_get(q, joint) for joint in self.actuated])
            steps = max(substeps, int(np.ceil(np.abs(row - first).max(initial=0.0) / stride)))
            for t in np.linspace(1.0 / steps, 1.0, steps):
                for joint, value in zip(self.actuated, first + t * (row - first)):
                    _set(q, joint, value)
                q = self._solve(q)
            pin.framesForwardKinematics(self.model, self.data, q)
            out.append(self.data.oMf[self.platform].translation.copy())
        return np.array(out)


def _set(q: np.ndarray, joint, value: float) -> None:
    if joint.nq == 2:  # a continuous joint: (cos, sin)
        q[joint.idx_q : joint.idx_q + 2] = (np.cos(value), np.sin(value))
    else:
        q[joint.idx_q] = value


def _get(q: np.ndarray, joint) -> float:
    return float(np.arctan2(q[joint.idx_q + 1], q[joint.idx_q]) if joint.nq == 2 else q[joint.idx_q])


# ------------------------------------------------------------------------------------------------
# The sequence


def _number(pattern: str, text: str) -> float:
    found = re.search(pattern, text)
    if found is None:
        raise CommandFailed(f"no figure matching {pattern!r} in:\n{text}")
    return float(found.group(1))


def within(check: str, value: float, low: float | None, high: float, unit: str = "") -> Figure:
    """The figure of `value` against its rule: at most `high` (in `unit`), or a ratio in [low, high]; NaN fails."""
    rule = f"<= {high:g}{unit}" if low is None else f"{low:g}-{high:g}x"
    passed = bool(np.isfinite(value) and value <= high and (low is None or value >= low))
    return Figure(check, value, rule, passed)


class Mechanism:
    """One closures file of a folder, with the facts the checks need (task, actuators)."""

    def __init__(self, urdf: Path, closures: Path) -> None:
        self.urdf, self.closures = urdf, closures
        self.document = yaml.safe_load(closures.read_text())
        self.reference_home = _fullest_home(closures, self.document)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = Loaded.load(urdf, closures)
        self.actuators = list(loaded.actuated_joints)
        # Without an assembled home beside it, the reference continues from the home m3t1r assembled
        # (checked to close by `check_home`): an independent solve from a rough guess may reach another
        # assembly mode, and the fk check is about the path, not about which mode load chose.
        self.assembled_home = {
            loaded.model.names[j]: float(loaded.home[loaded.model.idx_qs[j]]) for j in range(1, loaded.model.njoints)
        }
        self.rough = len(self.reference_home) < len(self.assembled_home)
        if self.rough:
            self.reference_home = self.assembled_home
        self.position, self.rotation = list(loaded.task.position), loaded.task.rotation
        self.model_args = ["--model", str(urdf), "--closures", str(closures)]

    def noisy_measurements(self, run: Runner, plan: str, truth: str, out: str, seed: int) -> None:
        """fk of the truth at the plan's actuators, with the tracker noise added: a measurement file."""
        run("fk", plan, "--model", truth, "-o", f"{out}.exact.csv")
        poses = columns(run.work / f"{out}.exact.csv", ["x", "y", "z", "qx", "qy", "qz", "qw"])
        rng = np.random.default_rng(seed)
        noisy = []
        for row in poses:
            rotation = pin.Quaternion(*row[[6, 3, 4, 5]]).matrix() @ pin.exp3(rng.normal(0.0, NOISE_ROT, 3))
            quaternion = pin.Quaternion(rotation).coeffs()
            noisy.append(np.concatenate((row[:3] + rng.normal(0.0, NOISE_POS, 3), quaternion)))
        actuators = columns(run.work / plan, self.actuators)
        write_table(
            run.work / out,
            self.actuators + ["x", "y", "z", "qx", "qy", "qz", "qw"],
            np.hstack((actuators, np.array(noisy))),
        )


def _fullest_home(closures: Path, document: dict) -> dict:
    """The home to continue the independent solve from: the file's own, or where it gives only some
    joints (a rough home), the fullest home of a closures file beside it with the same closures and
    actuator values: an assembly the file's own rough values must lead m3t1r to."""
    best = document["home"]
    for other in sorted(closures.parent.glob("*.closures.yaml")):
        sibling = yaml.safe_load(other.read_text())
        same = sibling.get("closures") == document.get("closures") and all(
            sibling["home"].get(k) == v for k, v in document["home"].items() if k in document["actuated_joints"]
        )
        if same and len(sibling["home"]) > len(best):
            best = sibling["home"]
    return best


def check_home(m: Mechanism, run: Runner) -> list[Figure]:
    """From a rough home only: the home m3t1r assembled closes under the independent closure rows, and
    is no farther from the given values (passive joints, revolute ones modulo whole turns) than the
    assembly a plain least-squares solve from them reaches."""
    if not m.rough:
        return []
    independent = IndependentSolver(m.urdf, m.document)  # solved from the file's own (rough) home
    ours = IndependentSolver(m.urdf, {**m.document, "home": m.assembled_home}, assemble=False)
    residual = float(np.abs(ours._residual(ours.q)).max())

    def distance(q: np.ndarray) -> float:
        joints = [ours.model.joints[j] for j in ours.passive]
        change = np.array([_get(q, joint) - _get(independent.given, joint) for joint in joints])
        revolute = np.array([joint.shortname().startswith("JointModelR") for joint in joints])
        return float(np.linalg.norm(np.where(revolute, np.remainder(change + np.pi, 2 * np.pi) - np.pi, change)))

    ratio = distance(ours.q) / max(distance(independent.q), 1e-300)
    return [
        within("home by m3t1r: independent residual [m or rad]", residual, None, 1e-9),
        dataclasses.replace(
            within("home: distance to given, m3t1r / least squares", ratio, None, 1.0 + 1e-6),
            detail=f"{distance(ours.q):.3g} / {distance(independent.q):.3g} [rad or m]",
        ),
    ]


def check_plans_and_kinematics(m: Mechanism, run: Runner) -> list[Figure]:
    figures = []
    for n in (20, 40, 60):  # a refused size fails its line; fk and ik still run on the 40-pose plan
        try:
            run("plan", *m.model_args, "-n", str(n), "-o", f"plan{n}.csv")
        except CommandFailed as exc:
            figures.append(Figure(f"plan -n {n}: rows written", None, f"== {n}", False, str(exc).splitlines()[0]))
            continue
        rows = len(read_table(run.work / f"plan{n}.csv")[1])
        figures.append(Figure(f"plan -n {n}: rows written", rows, f"== {n}", rows == n))
    actuators = columns(run.work / "plan40.csv", m.actuators)
    run("fk", "plan40.csv", *m.model_args, "-o", "poses.csv")
    poses = columns(run.work / "poses.csv", ["x", "y", "z", "qx", "qy", "qz", "qw"])
    reference = IndependentSolver(m.urdf, {**m.document, "home": m.reference_home}).platform_positions(actuators)
    figures.append(
        within("fk vs independent solve, max [m]", float(np.abs(poses[:, :3] - reference).max()), None, 1e-9)
    )
    names, targets = task_coordinates(poses, m.position, m.rotation)
    write_table(run.work / "targets.csv", names, targets)
    run("ik", "targets.csv", *m.model_args, "-o", "back.csv")
    back = columns(run.work / "back.csv", m.actuators)
    figures.append(within("ik round trip, max [m or rad]", float(np.abs(back - actuators).max()), None, 1e-8))
    return figures


def check_noise_free(m: Mechanism, run: Runner) -> list[Figure]:
    run(
        "simulate",
        *m.model_args,
        "-n",
        "40",
        "--sigma-pos",
        ERRORS[0],
        "--sigma-rot",
        ERRORS[1],
        "--noise-free",
        "--seed",
        "1",
        "-o",
        "exact.csv",
        "--truth-urdf",
        "truth.urdf",
    )
    run("calibrate", "exact.csv", *m.model_args, "-o", "cal.urdf", "--report", "cal.json")
    text = run("evaluate", *m.model_args, "--truth", "truth.urdf", "--calibrated", "cal.urdf")
    calibrated = _number(r"calibrated\s+\S+ m\s+(\S+) m", text)
    calibrated_mean = _number(r"calibrated\s+(\S+) m", text)
    nominal = _number(r"nominal\s+(\S+) m", text)
    run("fk", "plan40.csv", "--model", "truth.urdf", "-o", "truth_poses.csv")
    truth = columns(run.work / "truth_poses.csv", ["x", "y", "z"])
    ours = columns(run.work / "poses.csv", ["x", "y", "z"])
    own = float(np.linalg.norm(truth - ours, axis=1).mean())
    held_out = within("noise-free calibration, held-out max [m]", calibrated, None, 1e-7)
    return [
        dataclasses.replace(held_out, detail=f"mean {calibrated_mean:.3g}"),
        within("evaluate nominal mean / truth's own at the plan", nominal / own, 0.5, 2.0),
    ]


def check_noisy(m: Mechanism, run: Runner) -> list[Figure]:
    noise = ["--noise-pos", repr(NOISE_POS), "--noise-rot", repr(NOISE_ROT)]
    text = run("plan", *m.model_args, "-n", "40", *noise, "-o", "plan_noisy.csv")
    floor = _number(r"position\s+mean (\S+) m", text)
    m.noisy_measurements(run, "plan_noisy.csv", "truth.urdf", "noisy.csv", seed=3)
    run("calibrate", "noisy.csv", *m.model_args, *noise, "-o", "caln.urdf", "--report", "caln.json")
    held_out = _number(
        r"calibrated\s+(\S+) m", run("evaluate", *m.model_args, "--truth", "truth.urdf", "--calibrated", "caln.urdf")
    )
    run("plan", *m.model_args, "-n", "40", "--seed", "7", "-o", "fresh_plan.csv")
    m.noisy_measurements(run, "fresh_plan.csv", "truth.urdf", "fresh.csv", seed=4)
    validated = _number(
        r"position \[m\]\s+([-+.0-9eE]+)\s",
        run("validate", "fresh.csv", "--calibrated", "caln.urdf", "--report", "caln.json"),
    )
    cross = json.loads((run.work / "caln.json").read_text())["cross_validation"]["position_mean_m"]
    return [
        Figure(
            "noisy: held-out mean [m] / plan's predicted floor",
            held_out / floor,
            "0.5-2x",
            0.5 <= held_out / floor <= 2.0,
            f"{held_out:.3g} / {floor:.3g}",
        ),
        Figure(
            "validate mean / cross-validation mean",
            validated / cross,
            "0.67-1.5x",
            0.67 <= validated / cross <= 1.5,
            f"{validated:.3g} / {cross:.3g}",
        ),
    ]


def check_compensation_and_view(m: Mechanism, run: Runner) -> list[Figure]:
    poses = columns(run.work / "truth_poses.csv", ["x", "y", "z", "qx", "qy", "qz", "qw"])
    names, targets = task_coordinates(poses, m.position, m.rotation)
    write_table(run.work / "comp_targets.csv", names, targets)
    # With --report the targets are the measured point's poses in the tracker's frame: here the base's,
    # and the platform frame's origin (simulate's defaults), whatever the task.
    write_table(run.work / "comp_poses.csv", ["x", "y", "z", "qx", "qy", "qz", "qw"], poses)
    figures = []
    for label, extra in (("compensate", []), ("compensate --report", ["--report", "cal.json"])):
        out = f"commands{len(extra)}.csv"
        run(
            "compensate",
            "comp_poses.csv" if extra else "comp_targets.csv",
            *m.model_args,
            "--calibrated",
            "cal.urdf",
            "--output-kind",
            "actuators",
            *extra,
            "-o",
            out,
        )
        run("fk", out, "--model", "truth.urdf", "-o", f"reached{len(extra)}.csv")
        reached = columns(run.work / f"reached{len(extra)}.csv", ["x", "y", "z"])
        positions = [k for k, n in enumerate(names) if n in ("x", "y", "z")]
        error = np.abs(reached[:, ["xyz".index(names[k]) for k in positions]] - targets[:, positions]).max()
        figures.append(within(f"{label}: truth reaches targets, max [m]", float(error), None, 1e-7))
    run("view", *m.model_args, "--calibrated", "cal.urdf", "--html", "view.html")
    size = (run.work / "view.html").stat().st_size
    figures.append(Figure("view --html: page written [bytes]", size, "> 0", size > 0))
    return figures


CHECKS = (check_home, check_plans_and_kinematics, check_noise_free, check_noisy, check_compensation_and_view)


def check(urdf: Path, closures: Path, runner: Runner) -> list[Figure]:
    """Every check on one closures file; a failed command fails its group, the next groups still run."""
    try:
        mechanism = Mechanism(urdf, closures)
    except M3t1rError as exc:  # what every verb would print first
        return [Figure("load", None, "runs", False, str(exc).splitlines()[0])]
    figures: list[Figure] = []
    for group in CHECKS:
        try:
            figures += group(mechanism, runner)
        except (CommandFailed, ValueError, KeyError, FileNotFoundError, IndexError) as exc:
            figures.append(
                Figure(
                    group.__name__.removeprefix("check_").replace("_", " "),
                    None,
                    "runs",
                    False,
                    str(exc).splitlines()[0],
                )
            )
    return figures


def table(title: str, figures: list[Figure]) -> str:
    lines = [title, f"{'check':<52} {'value':>11}  {'rule':<10} result"]
    for f in figures:
        value = "-" if f.value is None else f"{f.value:.3g}"
        lines.append(
            f"{f.check:<52} {value:>11}  {f.rule:<10} {'pass' if f.passed else 'FAIL'}"
            + (f"  ({f.detail})" if f.detail else "")
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a folder with one URDF and its closures file(s)")
    parser.add_argument("--closures", nargs="+", help="closures files to check (default: every *.closures.yaml)")
    parser.add_argument("--work", type=Path, help="scratch folder kept afterwards (default: a temporary one)")
    parser.add_argument(
        "--m3t1r",
        default=f"{shlex.quote(sys.executable)} -m m3t1r.app.cli",
        help="the command line to run (default: this Python's m3t1r)",
    )
    args = parser.parse_args(argv)
    urdfs = sorted(args.folder.glob("*.urdf"))
    if len(urdfs) != 1:
        parser.error(f"{args.folder}: expected one URDF, found {len(urdfs)}")
    names = args.closures or sorted(p.name for p in args.folder.glob("*.closures.yaml"))
    failed = False
    for name in names:
        with tempfile.TemporaryDirectory(prefix="check_mechanism_") as scratch:
            work = (args.work / Path(name).stem) if args.work else Path(scratch)
            work.mkdir(parents=True, exist_ok=True)
            figures = check(urdfs[0].resolve(), (args.folder / name).resolve(), Runner(shlex.split(args.m3t1r), work))
        print(table(f"{args.folder.name}/{name}", figures) + "\n", flush=True)
        failed |= not all(f.passed for f in figures)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
