"""`m3t1r plan` and `m3t1r.calibration.planning`: a D-optimal plan calibrates the machine to the noise level,
beats random poses, stays assemblable and within limits, is ordered for short travel, and its
predicted accuracy is the one a calibration on it reports."""

from __future__ import annotations

import contextlib
import io
import itertools
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from command_lines import run_campaign_verb as run

from m3t1r.app.datasets import read_actuators
from m3t1r.app.demo import DemoSettings
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors, predicted_pose_std
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.identification import select_base_parameters
from m3t1r.calibration.measurements import TrackerNoise, measure
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.planning import (
    order_for_travel,
    path_travel,
    plan_closed_loop,
    plan_serial,
    predicted_accuracy,
    predicted_accuracy_of_rows,
)
from m3t1r.calibration.pose_selection import closed_loop_candidate_blocks, information_log_det
from m3t1r.calibration.serial_robots import load_example_robot
from m3t1r.calibration.simulation import actual_machine, random_placement_errors
from m3t1r.errors import IdentificationError, InvalidInputError, PoorExcitationWarning
from m3t1r.io.tables import read_table
from m3t1r.model.description import Mechanism
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import SerialChain
from m3t1r.model.workspace import workspace_actuators


@pytest.fixture(scope="module")
def plan_file(tmp_path_factory):
    """`m3t1r plan -n 40 -o PLAN.csv` (seed 0, 800 candidates) and its printed summary."""
    path = tmp_path_factory.mktemp("plan") / "plan.csv"
    stream = io.StringIO()
    with contextlib.redirect_stdout(stream):
        status = run(["plan", "-n", "40", "-o", str(path)])
    assert status == 0, stream.getvalue()
    return path, stream.getvalue()


def test_plan_of_40_calibrates_to_the_noise_level(plan_file, mechanism) -> None:
    """Acceptance: simulate a truth machine measured at exactly the planned slider sets, calibrate,
    and judge on 200 other workspace slider sets: at most 10 um mean position error."""
    path, printed = plan_file
    sliders, _ = read_actuators(path, mechanism)  # also checks every slider against its limits
    assert sliders.shape == (40, 4)
    rng = np.random.default_rng(11)
    truth = actual_machine(mechanism, random_placement_errors(ClosedLoopErrorModel(mechanism), rng, 1e-3, 1e-3))
    noise = TrackerNoise(10e-6, 20e-6)
    calibration = calibrate_closed_loop(mechanism, measure(truth, sliders, rng, noise), CalibrationOptions(noise=noise))
    held_out = workspace_actuators(mechanism, 200, np.random.default_rng(12))
    errors = pose_errors(calibration.mechanism, truth, held_out)
    print(
        f"held-out after plan -n 40: {errors.position_mean * 1e6:.2f} um mean, {errors.position_max * 1e6:.2f} um "
        f"max, {errors.rotation_mean * 1e6:.2f} urad mean"
    )
    assert errors.position_mean <= 10e-6
    assert errors.rotation_mean <= 20e-6
    # The printed prediction is what the calibration itself predicts on those poses.
    predicted = float(printed.split("position     mean ")[1].split()[0])
    reported = predicted_pose_std(calibration, held_out)
    assert predicted == pytest.approx(reported.position_mean, rel=0.15)


def test_plan_rows_assemble_on_the_home_branch_within_limits(plan_file, mechanism) -> None:
    path, printed = plan_file
    text = path.read_text()
    assert text.startswith("# written by m3t1r") and "# command: m3t1r" in text
    assert "q11 [m]" in text and "chosen D-optimally among 800 candidates" in printed
    table = read_table(path, required=mechanism.actuated_joints)
    sliders = np.column_stack([table.column(n) for n in mechanism.actuated_joints])
    lower, upper = mechanism.joint_limits()
    assert np.all(sliders >= lower) and np.all(sliders <= upper)
    solver = ClosedLoopSolver(mechanism)
    for row in sliders:
        assert solver.forward(row, q_init=mechanism.home).residual < 1e-9
    assert len({tuple(row) for row in sliders}) == 40


def test_plan_is_d_better_than_random_slider_sets(plan_file, mechanism) -> None:
    path, _ = plan_file
    planned, _ = read_actuators(path, mechanism)
    rng = np.random.default_rng(5)
    random_sets = [workspace_actuators(mechanism, 40, rng) for _ in range(3)]
    blocks, names = closed_loop_candidate_blocks(mechanism, np.vstack([planned, *random_sets]))
    columns = list(select_base_parameters(blocks.reshape(-1, len(names)), names, 1e-9, max_condition=np.inf).indices)
    planned_value = information_log_det(blocks[:, :, columns], range(40))
    random_values = [information_log_det(blocks[:, :, columns], range(40 * k, 40 * k + 40)) for k in (1, 2, 3)]
    print(f"log det: plan {planned_value:.1f}, random {', '.join(f'{v:.1f}' for v in random_values)}")
    assert all(planned_value > v + 10.0 for v in random_values)  # e^10: a much smaller confidence volume


def test_ordering_shortens_travel_and_keeps_every_pose() -> None:
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (40, 4))
    start = np.zeros(4)
    order = order_for_travel(points, start)
    assert sorted(order.tolist()) == list(range(40))
    ordered = path_travel(points[order], start)
    assert ordered < 0.5 * path_travel(points, start)
    assert path_travel(points[:1], start) == pytest.approx(np.max(np.abs(points[0])))


def test_two_opt_is_optimal_on_a_small_set() -> None:
    points = np.random.default_rng(3).uniform(-1, 1, (7, 2))
    start = np.zeros(2)
    best = min(path_travel(points[list(p)], start) for p in itertools.permutations(range(7)))
    assert path_travel(points[order_for_travel(points, start)], start) <= best * 1.1  # 2-opt: near optimal


def test_library_plan_travel_and_accuracy(mechanism) -> None:
    plan = plan_closed_loop(mechanism, 15, np.random.default_rng(1), n_candidates=150, n_evaluation=30)
    assert plan.n_poses == 15 and plan.travel < plan.travel_selection_order
    assert sorted(plan.candidate_indices) == list(plan.selection.indices)
    assert plan.accuracy.n == 30 and np.all(plan.accuracy.std.position > 0)
    home = mechanism.home[[mechanism.model.idx_qs[mechanism.model.getJointId(n)] for n in mechanism.actuated_joints]]
    np.testing.assert_allclose(plan.start, home)
    position_only = plan_closed_loop(
        mechanism, 25, np.random.default_rng(1), n_candidates=150, n_evaluation=30, position_only=True
    )
    assert np.all(np.isnan(position_only.accuracy.std.rotation)) and position_only.accuracy.std.position_mean > 0


def test_serial_plan(tmp_path, capsys) -> None:
    assert run(["plan", "-n", "20", "--serial", "ur5", "--candidates", "200", "-o", str(tmp_path / "ur5.csv")]) == 0
    out = capsys.readouterr().out
    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, "tool0")
    table = read_table(tmp_path / "ur5.csv", required=chain.joint_names)
    q = np.column_stack([table.column(n) for n in chain.joint_names])
    lower, upper = chain.position_limits(model)
    assert q.shape == (20, 6) and np.all(q >= lower) and np.all(q <= upper)
    assert "20 joint configurations" in out and "rad in this order" in out
    plan = plan_serial(model, chain, 20, np.random.default_rng(0), n_candidates=200, n_evaluation=20)
    assert plan.travel < plan.travel_selection_order and plan.column_units == ("rad",) * 6


_PLAN_FIGURES = re.compile(
    r"chosen D-optimally among (\d+) candidates \(seed (\d+)\): log det ([-0-9.]+), "
    r"condition number ([0-9.e+-]+), (\d+) identifiable parameters"
)


def test_the_demo_s_plan_prints_the_readme_s_figures(tmp_path, capsys) -> None:
    """The README's demo output is what a fresh clone prints: `make demo`'s plan step, the same
    command, gives its log det, condition number and identifiable count on any processor.

    Tolerances: rounding moves log det by under 1e-9 nepers and the condition number by under 1e-9
    relatively, while a selection that keeps one column of an interchangeable pair instead of the
    other moved log det by 1.1 (1218.65 against 1217.55) and a different pose set moves it by
    0.1 or more. Printing rounds to 0.01 nepers and 3 digits, so a value at a rounding boundary may
    print one digit off: 0.02 and 1 % allow that and sit far below those changes."""
    settings = DemoSettings()
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    command = f"$ m3t1r plan -n {settings.n_poses} --seed {settings.seed} -o plan.csv"
    assert command in readme, "the README's demo output no longer shows the demo's plan command"
    documented = _PLAN_FIGURES.search(readme, readme.index(command))
    assert documented is not None
    assert (
        run(["plan", "-n", str(settings.n_poses), "--seed", str(settings.seed), "-o", str(tmp_path / "plan.csv")]) == 0
    )
    printed = _PLAN_FIGURES.search(capsys.readouterr().out)
    assert printed is not None
    assert printed.group(1, 2, 5) == documented.group(1, 2, 5)  # candidates, seed, identifiable count
    assert float(printed.group(3)) == pytest.approx(float(documented.group(3)), abs=0.02)
    assert float(printed.group(4)) == pytest.approx(float(documented.group(4)), rel=0.01)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["-n", "10", "--candidates", "5"], "5 candidates"),
        (["-n", "5"], "cannot identify"),
        (["-n", "10", "--serial", "ur5", "--model", "x.urdf"], "--model/--closures"),
        (["-n", "10", "--tool", "tool0"], "--serial only"),
        (["-n", "10", "--serial", "nowhere.urdf"], "nowhere.urdf: file not found"),
        (["-n", "10", "--serial", "ur5", "--tool", "no_frame"], "no_frame"),
    ],
)
def test_plan_errors(tmp_path, capsys, argv, message) -> None:
    assert run(["plan", *argv, "-o", str(tmp_path / "plan.csv")]) == 2
    assert message in capsys.readouterr().out
    assert not (tmp_path / "plan.csv").exists()


@pytest.mark.parametrize("files", [five_bar_files, spherical_wrist_files])
def test_too_few_planned_poses_name_what_they_leave_unexcited(files, tmp_path) -> None:
    """Three poses of a five-bar or the wrist cannot identify what the candidates identify: the
    refusal names the parameters left unexcited and asks for more poses (the candidates identify
    them, so more poses do help)."""
    machine = Mechanism.load(*files(tmp_path))
    with pytest.raises(InvalidInputError) as refusal:
        plan_closed_loop(machine, 3, np.random.default_rng(0), n_evaluation=5)
    message = str(refusal.value)
    names = ClosedLoopErrorModel(machine).names
    found = re.fullmatch(
        r"3 poses cannot identify the (\d+) parameters that the 60 candidates identify: they leave "
        r"(.+) unexcited; plan more poses \(3 give 18 rows for \1 parameters\)",
        message,
    )
    assert found is not None, message
    assert set(found.group(2).removesuffix(" ...").split(", ")) <= set(names)
    assert plan_closed_loop(machine, 12, np.random.default_rng(0), n_evaluation=5).n_poses == 12


def test_predicted_accuracy_holds_for_parameters_the_rule_keeps_however_weak() -> None:
    """A base parameter identified only just above the rank tolerance (R's diagonal 3e-8 of its
    largest, as a leg's rod joints give: cassie-like legs planned at 40 and 60 poses were refused)
    squares to a condition number near 1e16 in A^T A; the accuracy from the rows' own factor is
    the covariance's, checked against an SVD of the rows, and agrees with the information-matrix
    route where that one is well conditioned."""
    rng = np.random.default_rng(5)
    rows = rng.normal(size=(240, 4)) * [1.0, 1e3, 1e-2, 1.0]  # mixed units, as m and rad columns
    rows[:, 3] = rows[:, 0] + 3e-8 * rng.normal(size=240)  # barely independent of column 0
    assert select_base_parameters(rows, list("abcd"), max_condition=np.inf).rank == 4
    sensitivities = rng.normal(size=(7, 6, 4))
    accuracy = predicted_accuracy_of_rows(rows, sensitivities)
    _, singular, vt = np.linalg.svd(rows, full_matrices=False)
    covariance = vt.T @ np.diag(singular**-2.0) @ vt
    variance = np.einsum("nrp,pq,nrq->nr", sensitivities, covariance, sensitivities)
    np.testing.assert_allclose(accuracy.std.position, np.sqrt(variance[:, :3].sum(axis=1)), rtol=1e-4)
    np.testing.assert_allclose(accuracy.std.rotation, np.sqrt(variance[:, 3:].sum(axis=1)), rtol=1e-4)
    sound = rows[:, :3]
    np.testing.assert_allclose(
        predicted_accuracy_of_rows(sound, sensitivities[:, :, :3]).std.position,
        predicted_accuracy(sound.T @ sound, sensitivities[:, :, :3]).std.position,
        rtol=1e-9,
    )
    with pytest.raises(InvalidInputError, match="does not identify every base parameter"):
        predicted_accuracy_of_rows(np.zeros((12, 2)), sensitivities[:, :, :2])


def test_plan_and_calibrate_count_the_same_identifiable_parameters(tmp_path) -> None:
    """One identifiability decision: the count `plan` prints is the one `calibrate` reports on the
    planned poses (the packaged five-bar and wrist, exact measurements)."""
    for files in (five_bar_files, spherical_wrist_files):
        machine = Mechanism.load(*files(tmp_path))
        plan = plan_closed_loop(machine, 20, np.random.default_rng(3), n_evaluation=5)
        calibration = calibrate_closed_loop(
            machine, measure(machine, plan.configurations), CalibrationOptions(outlier_sigma=None)
        )
        assert len(plan.selection.columns) == calibration.base.rank


def _boxed_five_bar(tmp_path: Path, half: float) -> tuple[Path, Path]:
    """The packaged five-bar's files with a workspace box of +-half [rad] about home on each slider."""
    urdf, closures = five_bar_files(tmp_path)
    document = yaml.safe_load(closures.read_text())
    home = document["home"]
    document["workspace"] = {"actuators": {a: [home[a] - half, home[a] + half] for a in document["actuated_joints"]}}
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    return urdf, closures


def test_a_direction_at_the_rank_tolerance_is_decided_as_calibrate_decides(tmp_path):
    """The five-bar in a box of +-0.35 mrad about home: its two weakest parameters sit at the rank
    tolerance (|R_ii| / |R_00| ~ 1e-8, from the box's curvature), identifiable on calibrate's 40
    reference poses (1.03e-8) and not on the plan's 400 candidates (0.97e-8). The plan asks of its
    poses what calibrate will: the reference's 18, and refuses as calibrate refuses, naming the same
    two and not advising more poses; at +-1 mrad both count 18 and the plan is calibrated."""

    def boxed(half: float) -> Mechanism:
        return Mechanism.load(*_boxed_five_bar(tmp_path, half))

    narrow = boxed(3.5e-4)
    with pytest.raises(InvalidInputError) as refusal:
        plan_closed_loop(narrow, 20, np.random.default_rng(0), n_evaluation=5)
    planned = re.search(
        r"cannot identify the (\d+) parameters that the 40 reference poses calibrate judges by "
        r"identify: they leave (.+) unexcited, .* more poses are unlikely to help",
        str(refusal.value),
    )
    assert planned is not None, str(refusal.value)
    poses = workspace_actuators(narrow, 20, np.random.default_rng(4))
    with pytest.raises(IdentificationError) as calibrated:
        calibrate_closed_loop(narrow, measure(narrow, poses), CalibrationOptions(outlier_sigma=None))
    named = re.search(
        r"for (\d+) identifiable parameters and identify only \d+: (.+) are barely", str(calibrated.value)
    )
    assert named is not None, str(calibrated.value)
    assert planned.group(1) == named.group(1) == "18" and planned.group(2) == named.group(2)
    wide = boxed(1e-3)
    plan = plan_closed_loop(wide, 20, np.random.default_rng(0), n_evaluation=5)
    calibration = calibrate_closed_loop(
        wide, measure(wide, plan.configurations), CalibrationOptions(outlier_sigma=None)
    )
    assert len(plan.selection.columns) == calibration.base.rank == 18


def test_plan_fix_plans_for_the_parameters_calibrate_fix_fits(tmp_path, capsys):
    """The narrow five-bar's refusal names the two parameters to hold and the commands that hold them;
    `plan --fix` with those names writes a plan of the 16 others, which `calibrate` holding the same two
    identifies in full (without them held, calibrate refuses those poses)."""
    urdf, closures = _boxed_five_bar(tmp_path, 3.5e-4)
    plan_csv = tmp_path / "plan.csv"
    argv = ["plan", "-n", "20", "--model", str(urdf), "--closures", str(closures), "-o", str(plan_csv)]
    assert run(argv) == 2
    refusal = capsys.readouterr().out
    advice = re.search(r"\(plan --fix (.+), then calibrate --fix (.+)\)", refusal)
    assert advice is not None and advice.group(1) == advice.group(2), refusal
    held = advice.group(1).split()
    assert len(held) == 2 and not plan_csv.exists()
    assert run([*argv, "--fix", *held]) == 0
    assert "16 identifiable parameters" in capsys.readouterr().out
    narrow = Mechanism.load(urdf, closures)
    sliders, _ = read_actuators(plan_csv, narrow)
    measured = measure(narrow, sliders)
    calibration = calibrate_closed_loop(narrow, measured, CalibrationOptions(outlier_sigma=None, fixed=held))
    assert calibration.base.rank == 16 and not set(held) & set(calibration.fitted)
    with pytest.raises(IdentificationError, match="identify only 17"), pytest.warns(PoorExcitationWarning):
        calibrate_closed_loop(narrow, measured, CalibrationOptions(outlier_sigma=None))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--fix", "q99"], "fixed parameter: 'q99' is neither a parameter"),
        (["--serial", "ur5", "--fix", "shoulder_pan_joint"], "--fix plans a closed-loop machine"),
    ],
)
def test_plan_fix_refuses_what_it_cannot_hold(tmp_path, capsys, argv, message):
    assert run(["plan", "-n", "10", *argv, "-o", str(tmp_path / "plan.csv")]) == 2
    assert message in capsys.readouterr().out
    assert not (tmp_path / "plan.csv").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["-n", "0"], "argument -n: expected at least 1, got 0"),
        (["-n", "5", "--seed", "-1"], "a seed is a whole number of at least 0"),
    ],
)
def test_plan_counts_and_seeds_are_refused_as_they_are_parsed(tmp_path, capsys, argv, message) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run(["plan", *argv, "-o", str(tmp_path / "plan.csv")])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "plan.csv").exists()


def test_bad_counts_in_the_library(mechanism) -> None:
    with pytest.raises(InvalidInputError):
        plan_closed_loop(mechanism, 3, np.random.default_rng(0), n_candidates=2)


def _greedy_reference(points: np.ndarray, start: np.ndarray) -> list[int]:
    """Nearest neighbour by L-inf distance from `start`, one row at a time (O(n^2) time, O(n) memory)."""
    left, current, order = np.ones(len(points), dtype=bool), start, []
    for _ in range(len(points)):
        distance = np.where(left, np.max(np.abs(points - current), axis=1), np.inf)
        nearest = int(np.argmin(distance))
        order.append(nearest)
        left[nearest], current = False, points[nearest]
    return order


def test_a_large_pose_set_is_ordered_by_nearest_neighbour_without_a_distance_matrix():
    """Beyond 2000 poses the order is the greedy nearest-neighbour path (the same as a plain scan
    gives), found in a few MB: an n x n matrix of 20 000 poses needs 3.2 GB (12.8 GB for the
    broadcast that built it), which made `plan -n 200000` fail and a SIGTERM wait minutes."""
    import tracemalloc

    from m3t1r.calibration.planning import order_for_travel, path_travel

    rng = np.random.default_rng(3)
    points, start = rng.uniform(-0.2, 0.2, (2500, 4)), np.zeros(4)
    order = order_for_travel(points, start)
    assert order.tolist() == _greedy_reference(points, start)
    assert path_travel(points[order], start) < 0.2 * path_travel(points, start)
    many = rng.uniform(-0.2, 0.2, (20000, 4))
    tracemalloc.start()
    try:
        order = order_for_travel(many, start)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sorted(order.tolist()) == list(range(20000)) and peak < 50e6
