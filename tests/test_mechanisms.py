"""Three mechanisms of different kinds, through the same code: the M machine (3T1R, sliders), a
planar five-bar (task x, y; revolute motors) and a spherical 3-RRR wrist (task: full orientation).

Forward kinematics against independent solvers, inverse kinematics round trips, noise-free and
noisy closed-loop calibration, and the load-time repairs (approximate home, missing limits,
JOINT-frame closures, a cut joint modelled as two welded hinges).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import closed_form
import numpy as np
import pinocchio as pin
import pytest
import reference_kinematics as reference
import scipy.linalg
import yaml
from model_files import edit_text, edit_yaml, strip_position_limits, welded_double_hinge

from m3t1r.calibration import pipeline
from m3t1r.calibration.closed_loop import calibrate_closed_loop, pose_errors, predicted_pose_std
from m3t1r.calibration.error_model import ClosedLoopErrorModel
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pipeline import CalibrationOptions
from m3t1r.calibration.simulation import PlacementErrorScale, simulate_study
from m3t1r.compensation import joint_limit_violation
from m3t1r.errors import IdentificationError, InvalidInputError, ModelFileError, ModelWarning
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.description import Mechanism, nominal_model_paths
from m3t1r.model.examples import (
    first_time_five_bar_files,
    five_bar_files,
    published_five_bar_files,
    rod_five_bar_files,
    spherical_wrist_files,
)
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import Placement
from m3t1r.model.task import TaskSpec
from m3t1r.model.workspace import declared_workspace, workspace_actuators

KINDS = ("m_machine", "five_bar", "spherical_wrist")


def _files(kind: str, folder: Path) -> tuple[Path, Path]:
    if kind == "m_machine":
        return nominal_model_paths()
    return (five_bar_files if kind == "five_bar" else spherical_wrist_files)(folder)


@pytest.fixture(scope="module", params=KINDS)
def mechanism(request, tmp_path_factory) -> Mechanism:
    return Mechanism.load(*_files(request.param, tmp_path_factory.mktemp(request.param)))


def _kind(mechanism: Mechanism) -> str:
    return {"P_I": "m_machine", "effector": "five_bar", "platform": "spherical_wrist"}[mechanism.platform_frame]


def _reference_forward(kind: str, actuators: np.ndarray) -> np.ndarray:
    """Task coordinates by an independent solver: position (M: x, y, z, yaw), or a rotation matrix."""
    if kind == "m_machine":
        return closed_form.forward(actuators)
    if kind == "five_bar":
        return reference.five_bar_forward(actuators)
    return reference.wrist_forward(actuators)


def test_forward_kinematics_matches_an_independent_solver(mechanism):
    kind = _kind(mechanism)
    solver = ClosedLoopSolver(mechanism)
    actuators = workspace_actuators(mechanism, 25, np.random.default_rng(3))
    batch = solver.forward_batch(actuators)
    assert batch.complete
    for sliders, pose in zip(actuators, batch.poses):
        expected = _reference_forward(kind, sliders)
        if kind == "m_machine":
            got = np.r_[pose[:3, 3], np.arctan2(pose[1, 0], pose[0, 0])]
            np.testing.assert_allclose(got, expected, atol=1e-9)
        elif kind == "five_bar":
            np.testing.assert_allclose(pose[:2, 3], expected, atol=1e-9)
        else:
            assert np.linalg.norm(pin.log3(np.asarray(expected).T @ pose[:3, :3])) < 1e-9


def test_inverse_kinematics_round_trip(mechanism):
    solver = ClosedLoopSolver(mechanism)
    actuators = workspace_actuators(mechanism, 25, np.random.default_rng(4))
    coordinates = mechanism.task.coordinates(solver.forward_batch(actuators).poses)
    batch = solver.inverse_batch(coordinates)
    assert batch.complete
    np.testing.assert_allclose(batch.actuators, actuators, atol=1e-8)
    for target, sliders in zip(coordinates[:8], actuators[:8]):
        np.testing.assert_allclose(solver.inverse(target, q_init=mechanism.home).actuators, sliders, atol=1e-8)
    # A full pose as target: its uncommanded components are ignored.
    full = pin.SE3(solver.forward(actuators[0], q_init=mechanism.home).pose)
    np.testing.assert_allclose(solver.inverse(full, q_init=mechanism.home).actuators, actuators[0], atol=1e-8)


def test_batches_of_no_rows_return_empty_results(mechanism):
    """Zero slider sets or targets (of the right width) are a valid batch: empty arrays of the right
    shapes and no failures, for every task kind (the full-rotation task goes through its own goals)."""
    solver = ClosedLoopSolver(mechanism)
    forward = solver.forward_batch(np.zeros((0, len(mechanism.actuated_joints))))
    assert forward.n == 0 and forward.poses.shape == (0, 4, 4) and forward.q.shape == (0, mechanism.model.nq)
    assert forward.failures == () and forward.indices.shape == (0,)
    inverse = solver.inverse_batch(np.zeros((0, len(mechanism.task.columns))))
    assert inverse.n == 0 and inverse.actuators.shape == (0, len(mechanism.actuated_joints))
    assert inverse.tilt.shape == (0, 2) and inverse.failures == ()
    with pytest.raises(InvalidInputError, match="shape"):
        solver.forward_batch(np.zeros(0))  # no rows and no width: not a batch


def test_task_columns_name_what_is_commanded(mechanism):
    expected = {
        "m_machine": ("x", "y", "z", "theta"),
        "five_bar": ("x", "y"),
        "spherical_wrist": ("qx", "qy", "qz", "qw"),
    }[_kind(mechanism)]
    assert mechanism.task.columns == expected
    assert mechanism.task.dimension == len(mechanism.actuated_joints)
    with pytest.raises(InvalidInputError, match=re.escape(f"expected {len(expected)} values")):
        ClosedLoopSolver(mechanism).inverse(np.zeros(len(expected) + 1))


@pytest.mark.parametrize("noisy", [False, True])
def test_closed_loop_calibration_of_every_origin(mechanism, noisy):
    """0.1 mm / 0.1 mrad errors on every joint and frame origin; 60 poses, judged on 150 held out."""
    noise = TrackerNoise() if noisy else None
    study = simulate_study(
        mechanism,
        n_poses=60,
        n_holdout=150,
        seed=11,
        noise=noise,
        errors=PlacementErrorScale(1e-4, 1e-4),
    )
    calibration = calibrate_closed_loop(
        mechanism, study.measurements, CalibrationOptions(noise=noise or TrackerNoise())
    )
    assert calibration.lm.converged
    held_out = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    if not noisy:
        assert held_out.position_max < 1e-7 and held_out.rotation_max < 1e-6
        return
    # At the covariance floor: the held-out error is what the fit's own covariance predicts.
    predicted = predicted_pose_std(calibration, study.holdout_actuators)
    assert 0.5 < calibration.variance_factor < 1.5
    ratio = held_out.position_rms / predicted.position_rms
    assert 0.4 < ratio < 2.0, ratio


@pytest.mark.parametrize("noisy", [False, True])
def test_a_planar_nominal_does_not_cap_what_a_noise_free_fit_identifies(tmp_path, noisy):
    """The rod five-bar's nominal is planar: out-of-plane errors of the rod's chain move the effector
    only at second order there, so the nominal identifies fewer parameters than a machine with
    1 mm / 1 mrad errors does. Base parameters chosen at the nominal alone leave 1e-6 m held out
    (seed 2); the fit must reach the truth where the data determine it, and keep the nominal's
    parameters on noisy data, where the added directions would fit noise."""
    mechanism = _quiet_load(*rod_five_bar_files(tmp_path))
    noise = TrackerNoise() if noisy else None
    study = simulate_study(
        mechanism,
        n_poses=60,
        n_holdout=150,
        seed=2,
        noise=noise,
        errors=PlacementErrorScale(1e-3, 1e-3),
    )
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise()))
    assert calibration.lm.converged
    held_out = pose_errors(calibration.mechanism, study.truth, study.holdout_actuators)
    if noisy:
        assert len(calibration.fitted) == calibration.base.rank
        assert 0.5 < calibration.variance_factor < 1.5
        assert calibration.iterations == calibration.lm.iterations  # the base fit alone: no refit counted
        return
    assert len(calibration.fitted) > calibration.base.rank
    assert calibration.iterations > calibration.lm.iterations  # the base fit's, then the refit's
    assert held_out.position_max < 1e-7 and held_out.rotation_max < 1e-6
    # A parameter held fixed stays out of the fit past the nominal's rank too.
    added = next(name for name in calibration.fitted if name not in calibration.base.names)
    held = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise(), fixed=[added]))
    assert len(held.fitted) > held.base.rank and added not in held.fitted
    assert abs(held.parameters[added]) < 1e-11  # its start, to the rounding of its placement's other steps


def test_a_refit_past_the_nominal_rank_that_does_not_assemble_is_dropped(tmp_path, monkeypatch):
    """The rod five-bar's noise-free fit, its refit over every column with an effect made to end on a
    machine that does not assemble: the base fit is kept, columns and iterations its own."""
    mechanism = _quiet_load(*rod_five_bar_files(tmp_path))
    study = simulate_study(mechanism, n_poses=60, n_holdout=0, seed=2, errors=PlacementErrorScale(1e-3, 1e-3))
    fit = pipeline.fit

    def refused_refit(problem, state, settings):
        if settings.unit_damping:  # the refit past the nominal's rank alone is damped in units
            raise IdentificationError("calibration ended on a model that does not assemble")
        return fit(problem, state, settings)

    monkeypatch.setattr(pipeline, "fit", refused_refit)
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise()))
    assert calibration.lm.converged and len(calibration.fitted) == calibration.base.rank
    assert calibration.iterations == calibration.lm.iterations


@pytest.mark.parametrize(
    ("actual", "variance_factor"),
    [
        (TrackerNoise(position=1e-4, rotation=2e-4), (50.0, 200.0)),  # 10 times the stated noise: the gate
        (TrackerNoise(position=7e-6, rotation=14e-6), (0.3, 0.7)),  # 0.7 times: not significant
    ],
)
def test_a_noisy_fit_stays_at_the_nominals_parameters(tmp_path, actual, variance_factor):
    """The rod five-bar measured with other noise than the fit is told (10 um, 20 urad). Ten times
    more: the residual is far above the stated noise (a model error, which the weak directions must
    not absorb), so the fit past the nominal's rank is not tried. Less: within the stated noise, the
    directions the estimate adds explain no significant part of it. Either way the fit keeps the
    nominal's base parameters and its iterations are the base fit's alone."""
    mechanism = _quiet_load(*rod_five_bar_files(tmp_path))
    study = simulate_study(
        mechanism, n_poses=60, n_holdout=0, seed=2, noise=actual, errors=PlacementErrorScale(1e-3, 1e-3)
    )
    calibration = calibrate_closed_loop(mechanism, study.measurements, CalibrationOptions(noise=TrackerNoise()))
    low, high = variance_factor
    assert low < calibration.variance_factor < high
    assert len(calibration.fitted) == calibration.base.rank
    assert calibration.iterations == calibration.lm.iterations


# ------------------------------------------------------------------------------------------------
# Load-time repairs
def _load_noting(urdf: Path, closures: Path, pattern: str) -> Mechanism:
    with pytest.warns(ModelWarning, match=pattern):
        return Mechanism.load(urdf, closures)


def test_urdf_without_actuator_limits_takes_the_workspace_box(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    # A <limit> with effort and velocity only (URDF requires the element on a revolute joint): Pinocchio
    # then reads the position limits as [0, 0].
    strip_position_limits(urdf, r"motor_\d")
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    assert [str(w.message) for w in caught] == [
        f"five_bar.closures.yaml: actuator 'motor_{k}' has no usable URDF limits; the workspace box's limits "
        f"[{lo}, {hi}] used instead"
        for k, lo, hi in ((1, 1.93, 2.73), (2, 0.41, 1.21))
    ]
    lower, upper = mechanism.joint_limits()
    np.testing.assert_array_equal(lower, [1.93, 0.41])
    np.testing.assert_array_equal(upper, [2.73, 1.21])
    with pytest.raises(InvalidInputError, match="beyond its joint limit"):
        ClosedLoopSolver(mechanism).forward(np.array([2.8, 0.8]))


def test_home_off_by_1e_5_is_assembled(tmp_path):
    urdf, closures = spherical_wrist_files(tmp_path)
    exact = Mechanism.load(urdf, closures).home
    edit_yaml(
        closures,
        lambda d: d["home"].update(
            {name: value + 1e-5 for name, value in d["home"].items() if not name.startswith("motor")}
        ),
    )
    mechanism = _load_noting(urdf, closures, "home does not close: .* assembled by Newton")
    np.testing.assert_allclose(mechanism.home, exact, atol=1e-10)
    assert ClosedLoopSolver(mechanism).mobility(mechanism.home, all_rows=True) == 3


def test_closure_on_a_joint_frame(tmp_path):
    """D_I is the origin of joint q12_pa (identity placement): a closure may name the joint's frame."""
    source_urdf, source_closures = nominal_model_paths()
    urdf, closures = tmp_path / "m.urdf", tmp_path / "m.closures.yaml"
    urdf.write_bytes(source_urdf.read_bytes())
    closures.write_bytes(source_closures.read_bytes())
    edit_yaml(closures, lambda d: next(c for c in d["closures"] if c["name"] == "five_bar_I").update(frame_b="q12_pa"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to note
        mechanism = Mechanism.load(urdf, closures)
    nominal = Mechanism.load()
    sliders = workspace_actuators(nominal, 5, np.random.default_rng(0))
    np.testing.assert_allclose(
        ClosedLoopSolver(mechanism).forward_batch(sliders).poses,
        ClosedLoopSolver(nominal).forward_batch(sliders).poses,
        atol=1e-12,
    )
    study = simulate_study(mechanism, n_poses=40, n_holdout=50, seed=2, errors=PlacementErrorScale(1e-4, 1e-4))
    calibration = calibrate_closed_loop(mechanism, study.measurements)
    assert "D_I.dt[0]" not in calibration.error_model.names  # the joint's own placement carries it
    assert pose_errors(calibration.mechanism, study.truth, study.holdout_actuators).position_max < 1e-7


def test_welded_double_hinge_locks_the_gauge_joint(tmp_path):
    urdf, closures = welded_double_hinge(tmp_path)
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    notes = [str(w.message) for w in caught]
    assert any("locked at their home value" in n for n in notes), notes
    assert any("3 closure row(s) dropped as dependent on the others: cut[2], cut[3], cut[4]" in n for n in notes), notes
    assert len(mechanism.locked_joints) == 1 and mechanism.locked_joints[0] in ("cut_1", "cut_2")
    assert mechanism.closures[0].rows == (0, 1, 5)
    plain = Mechanism.load(*five_bar_files(tmp_path / "plain"))
    solver, plain_solver = ClosedLoopSolver(mechanism), ClosedLoopSolver(plain)
    sliders = workspace_actuators(plain, 10, np.random.default_rng(5))
    np.testing.assert_allclose(
        solver.forward_batch(sliders).poses[:, :2, 3], plain_solver.forward_batch(sliders).poses[:, :2, 3], atol=1e-12
    )
    targets = plain.task.coordinates(plain_solver.forward_batch(sliders).poses)
    np.testing.assert_allclose(solver.inverse_batch(targets).actuators, sliders, atol=1e-8)
    study = simulate_study(mechanism, n_poses=50, n_holdout=50, seed=3, errors=PlacementErrorScale(1e-4, 1e-4))
    calibration = calibrate_closed_loop(mechanism, study.measurements)
    assert pose_errors(calibration.mechanism, study.truth, study.holdout_actuators).position_max < 1e-7


def _loaded_with_home(urdf: Path, closures: Path, home: dict) -> Mechanism:
    """The pair loaded with `home` (joint name: value) in place of the file's home."""
    edit_yaml(closures, lambda d: d.update(home=home))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        return Mechanism.load(urdf, closures)


def _effector(mechanism: Mechanism) -> np.ndarray:
    data = mechanism.model.createData()
    pin.framesForwardKinematics(mechanism.model, data, mechanism.home)
    return data.oMf[mechanism.platform_frame_id].translation.copy()


def test_rough_homes_assemble_to_the_assembly_mode_nearest_the_guess(tmp_path):
    """The five-bar's two assembly modes at home's motors (the distal links meet on either side of
    the line through the elbows): a home given a quarter-turn off either one assembles back to it,
    the actuators held; given the motors alone (elbows at the URDF zero), to one of the two."""
    urdf, closures = five_bar_files(tmp_path)
    nominal = Mechanism.load(urdf, closures)
    motors = {"motor_1": 2.33, "motor_2": 0.81}
    elbows = {"elbow_1": -1.6508668956787065, "elbow_2": 1.6514519345972394}
    mirrored = _loaded_with_home(urdf, closures, motors | {k: -v for k, v in elbows.items()})
    modes = {"home": nominal, "mirrored": mirrored}
    assert np.linalg.norm(_effector(mirrored) - _effector(nominal)) > 0.05  # two distinct assemblies
    for name, mode in modes.items():
        values = {j: float(mode.home[mode.model.idx_qs[mode.model.getJointId(j)]]) for j in elbows}
        for offset in (0.25, -0.25):
            guess = motors | {"elbow_1": values["elbow_1"] + offset, "elbow_2": values["elbow_2"] - offset}
            loaded = _loaded_with_home(urdf, closures, guess)
            np.testing.assert_allclose(loaded.home, mode.home, atol=1e-9, err_msg=f"{name} {offset}")
            assert {j for j, _ in loaded.home_assembly.moved} == set(elbows)
            assert max(abs(move) for _, move in loaded.home_assembly.moved) == pytest.approx(0.25, abs=1e-6)
            assert loaded.notes[0].startswith("home does not close: closure 'loop' residual ")
    motors_only = _loaded_with_home(urdf, closures, motors)
    assert motors_only.home_assembly.residual < 1e-12
    assert min(np.abs(motors_only.home - mode.home).max() for mode in modes.values()) < 1e-9


def test_a_task_that_is_not_square_is_refused_by_inverse_only(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d["task"].update(position=["x", "y", "z"]))
    mechanism = Mechanism.load(urdf, closures)
    solver = ClosedLoopSolver(mechanism)
    solver.forward(mechanism.home[mechanism.actuated_ids])  # forward kinematics does not need the task
    with pytest.raises(InvalidInputError, match="commands 3 for 2 actuators"):
        solver.inverse(np.zeros(3))


def test_a_frame_error_moves_the_closure_frames_attached_to_it(tmp_path):
    """The wrist's platform link carries the closure frames attach_2 and attach_3: an error on the
    platform frame moves them too (as `perturb` applies it), and the fit's Jacobian must say so.
    Checked against central differences of the residual at the fitted state, column by column."""
    mechanism = Mechanism.load(*spherical_wrist_files(tmp_path))
    default = ClosedLoopErrorModel(mechanism)
    assert "platform.dt[0]" not in default.names  # a link frame on a moving joint: no placement of its own
    error_model = ClosedLoopErrorModel(mechanism, default.placements + (Placement.frame("platform"),))
    study = simulate_study(mechanism, n_poses=30, n_holdout=0, seed=11, errors=PlacementErrorScale(1e-4, 1e-4))
    calibration = calibrate_closed_loop(
        mechanism, study.measurements, CalibrationOptions(outlier_sigma=None), error_model=error_model
    )
    problem, state = calibration.problem, calibration.lm.state
    _, jacobian = problem.residual_and_jacobian(state)
    names = [problem.names[c] for c in problem.columns]
    step = 1e-7
    for k, name in enumerate(names):
        if not name.startswith("platform."):
            continue
        dx = np.zeros(len(names))
        dx[k] = step
        plus = problem.residual_and_jacobian(problem.retract(state, dx))[0]
        minus = problem.residual_and_jacobian(problem.retract(state, -dx))[0]
        difference = (plus - minus) / (2 * step)
        assert np.abs(difference - jacobian[:, k]).max() < 1e-5 * np.abs(jacobian[:, k]).max(), name
    assert any(name.startswith("platform.") for name in names)


def test_kinematics_do_not_need_the_meshes(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    edit_text(
        urdf, lambda text: text.replace('<sphere radius="0.01"/>', '<mesh filename="package://gone/effector.stl"/>', 1)
    )
    assert "gone/effector.stl" in urdf.read_text()
    mechanism = Mechanism.load(urdf, closures)
    ClosedLoopSolver(mechanism).forward(mechanism.home[mechanism.actuated_ids])
    with pytest.raises(ModelFileError, match="cannot load the visual geometry"):
        mechanism.visual_model  # noqa: B018  (the viewer's first access)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.update(schema_version=3), "schema_version 3 is not supported"),
        (lambda d: d["task"].update(rotation="roll"), "task rotation must be one of none, yaw, full, got 'roll'"),
        (lambda d: d["task"].update(position=["x", "w"]), r"task position must be distinct axes among x, y, z"),
        (lambda d: d["task"].update(frame="nowhere"), "task.frame: frame 'nowhere' does not exist"),
        (lambda d: d["task"].update(speed=1), "task: unknown field 'speed'"),
        (lambda d: d["task"].update(position=[], rotation="none"), "task: commands nothing"),
        (
            lambda d: d["workspace"]["actuators"].pop("motor_2"),
            r"workspace.actuators must give an interval \[lo, hi\] "
            "for each of motor_1, motor_2",
        ),
        (
            lambda d: d["workspace"]["actuators"].update(motor_1=[2.0, 1.0]),
            "interval of 'motor_1' must be finite with lo <= hi",
        ),
        (
            lambda d: d["workspace"]["actuators"].update(motor_1=["a", 1.0]),
            r"workspace.actuators.motor_1 must be \[lo, hi\]",
        ),
        (
            lambda d: d.update(workspace={"task": {"x": [0, 1]}, "actuators": {}}),
            "exactly one of 'actuators' or 'task'",
        ),
        (
            lambda d: (
                d.update(workspace={"task": {"x": [-0.1, 0.1], "y": [0.3, 0.5]}}) or d["task"].update(rotation="yaw")
            ),
            "the task commands 3 coordinates for 2 actuators",
        ),
    ],
)
def test_malformed_task_or_workspace_is_named(tmp_path, change, message):
    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, change)
    with pytest.raises(ModelFileError, match=message):
        Mechanism.load(urdf, closures)


def test_a_declared_box_the_machine_cannot_reach_is_named(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d.update(workspace={"task": {"x": [-0.1, 0.1], "y": [0.9, 1.0]}}))
    mechanism = Mechanism.load(urdf, closures)
    with pytest.raises(ModelFileError, match=r"draws in the declared task workspace box cannot be assembled from home"):
        workspace_actuators(mechanism, 5, np.random.default_rng(0))


def test_missing_closure_rows_are_not_taken_for_a_gauge(tmp_path):
    """With only the x row of the five-bar's loop, the effector keeps a free motion: an error, not a lock."""
    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d["closures"][0].update(rows=[0]))
    with pytest.raises(
        ModelFileError,
        match="leave 1 degree.* of freedom beyond the actuators: with the actuators "
        "held, frame 'effector' can still move",
    ):
        Mechanism.load(urdf, closures)


def test_a_free_motion_beside_an_idle_spin_is_counted_apart_and_named(tmp_path):
    """A rod with a spherical joint at each end (an idle spin) whose weld leaves out the slide along
    the effector's x (a free motion of the effector): of the 2 degrees of freedom the closures leave,
    the refusal says 1 moves the effector, names the joints that move most along it, and counts the
    other as an idle spin, where a published leg's refusal counted 3 and said nothing of which."""
    urdf, closures = rod_five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d["closures"][0].update(rows=[1, 2, 3, 4, 5]))
    with pytest.raises(ModelFileError) as refusal:
        Mechanism.load(urdf, closures)
    found = re.search(
        r"leave 2 degree\(s\) of freedom beyond the actuators: with the actuators held, frame 'effector' can "
        r"still move along 1 of them \((\S+) per unit joint speed; mostly joints (\S+), (\S+), (\S+)\), and 1 "
        r"move\(s\) only passive joints \(idle spins: load locks those when alone\); rows or closures are missing",
        str(refusal.value),
    )
    assert found is not None, str(refusal.value)
    assert float(found.group(1)) > 1e-3
    assert "elbow_1" in found.group(2, 3, 4)  # chain 1's elbow swings with the effector


def test_a_row_that_holds_by_itself_is_dropped_with_a_note(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(closures, lambda d: d["closures"][0].update(rows=[0, 1, 2]))  # z: the plane's normal, always 0
    mechanism = _load_noting(urdf, closures, r"1 closure row\(s\) dropped as dependent on the others: loop\[2\]")
    assert mechanism.closures[0].rows == (0, 1) and mechanism.locked_joints == ()


def test_closures_that_hold_the_actuators_are_refused(tmp_path):
    """A second closure pinning the effector to the base: the motors could no longer move."""
    urdf, closures = five_bar_files(tmp_path)
    mechanism = Mechanism.load(urdf, closures)
    data = mechanism.model.createData()
    pin.framesForwardKinematics(mechanism.model, data, mechanism.home)
    x, y, _ = (float(v) for v in data.oMf[mechanism.model.getFrameId("effector")].translation)
    edit_text(
        urdf,
        lambda text: text.replace(
            "</robot>",
            f'<joint name="anchor_fixed" type="fixed"><parent link="base"/>'
            f'<child link="anchor"/><origin xyz="{x!r} {y!r} 0" rpy="0 0 0"/>'
            '</joint><link name="anchor"/></robot>',
        ),
    )
    edit_yaml(
        closures,
        lambda d: d["closures"].append(
            {"name": "pin", "type": "3D", "frame_a": "anchor", "frame_b": "effector", "rows": [0, 1]}
        ),
    )
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == (
        f"{closures}: the closures hold the actuators: the rows have rank 4 over every joint "
        "but 2 over the passive ones (the actuators are not independent inputs)"
    )


def test_a_schema_1_file_samples_between_the_actuator_limits(tmp_path):
    urdf, closures = five_bar_files(tmp_path)
    edit_yaml(
        closures,
        lambda d: (
            [d.pop(key) for key in ("schema_version", "workspace")]
            and d.update(task={"frame": "effector", "position": ["x", "y"], "rotation": "none"})
        ),
    )
    mechanism = Mechanism.load(urdf, closures)
    assert mechanism.workspace is None
    lower, upper = mechanism.joint_limits()
    draws = workspace_actuators(mechanism, 40, np.random.default_rng(1))
    assert np.all(draws >= lower) and np.all(draws <= upper)
    # URDF limits of [0.5, 3.5] rad still assemble everywhere on home's branch (tests/reference_kinematics.py
    # agrees); [0.2, 4.0] reach past the five-bar's singularities, where FK from home changes branch.
    edit_text(urdf, lambda text: text.replace('lower="1.83" upper="2.83"', 'lower="0.5" upper="3.5"'))
    assert len(workspace_actuators(Mechanism.load(urdf, closures), 200, np.random.default_rng(1))) == 200
    edit_text(urdf, lambda text: text.replace('lower="0.5" upper="3.5"', 'lower="0.2" upper="4.0"'))
    with pytest.raises(
        ModelFileError,
        match=r"draws in the actuators' URDF limits \(no workspace declared: add a "
        r"`workspace:` box, models/README.md\) cannot be assembled from home",
    ):
        workspace_actuators(Mechanism.load(urdf, closures), 200, np.random.default_rng(1))


def test_a_first_time_file_gets_the_task_the_actuators_command_and_a_sound_workspace(tmp_path):
    urdf, closures = first_time_five_bar_files(tmp_path)
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(urdf, closures)
    notes = " | ".join(str(w.message) for w in caught)
    assert "no task declared" in notes and "x, y of frame 'effector'" in notes and "declare `task:`" in notes
    assert mechanism.task == TaskSpec("effector", ("x", "y"), "none") and mechanism.workspace is None
    assert np.all(np.isinf(mechanism.joint_limits()[0]))  # no actuator limits to sample between
    with pytest.warns(
        ModelWarning,
        match=r"no workspace declared and no finite actuator limits: sampling in "
        r"motor_1 \[\S+, \S+\] rad, motor_2",
    ):
        box = declared_workspace(mechanism)
    lower, upper = box.bounds(mechanism.actuated_joints)
    home = mechanism.home[mechanism.actuated_ids]
    assert np.all(lower < home) and np.all(home < upper) and np.all(upper - lower > 0.2)
    draws = workspace_actuators(mechanism, 60, np.random.default_rng(3))
    solver = ClosedLoopSolver(mechanism)
    forward = solver.forward_batch(draws)
    # The independent solver (tests/reference_kinematics.py) on home's assembly and working mode everywhere
    expected = np.array([reference.five_bar_forward(a) for a in draws])
    np.testing.assert_allclose(forward.task_poses[:, :2, 3], expected, atol=1e-10)
    inverse = solver.inverse_batch(forward.task_poses[:, :2, 3])
    assert not inverse.failures
    np.testing.assert_allclose(inverse.actuators, draws, atol=1e-8)


def test_a_default_workspace_shrinks_near_a_singularity_and_keeps_every_draw_invertible(tmp_path):
    # Home moved (+0.6, -0.6) rad toward where the five-bar's distal links fold into line: the box
    # shrinks so that every draw stays on home's working mode (IK from home finds the draw again).
    urdf, closures = first_time_five_bar_files(tmp_path)
    mechanism = _quiet_load(urdf, closures)
    wide = np.subtract(*declared_workspace(mechanism).bounds(mechanism.actuated_joints)[::-1])
    sliders = mechanism.home[mechanism.actuated_ids] + np.array([0.6, -0.6])
    shifted = mechanism.with_home(ClosedLoopSolver(mechanism).forward(sliders, q_init=mechanism.home).q)
    with pytest.warns(ModelWarning, match="no workspace declared"):
        lower, upper = declared_workspace(shifted).bounds(mechanism.actuated_joints)
    assert np.all(upper - lower < 0.6 * wide) and np.all(lower < sliders) and np.all(sliders < upper)
    solver = ClosedLoopSolver(shifted)
    draws = workspace_actuators(shifted, 80, np.random.default_rng(4))
    back = solver.inverse_batch(solver.forward_batch(draws).task_poses[:, :2, 3])
    assert not back.failures
    np.testing.assert_allclose(back.actuators, draws, atol=1e-8)


def test_a_schema_1_file_of_four_actuators_keeps_position_and_yaw_without_a_note(tmp_path):
    urdf, closures = nominal_model_paths()
    folder_urdf = tmp_path / "m.urdf"
    folder_urdf.write_bytes(urdf.read_bytes())
    copy = tmp_path / "m.closures.yaml"
    copy.write_bytes(closures.read_bytes())
    edit_yaml(copy, lambda d: [d.pop(key) for key in ("schema_version", "task")])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ModelWarning)
        mechanism = Mechanism.load(folder_urdf, copy)
    assert mechanism.task == TaskSpec("P_I", ("x", "y", "z"), "yaw")
    assert not any("no task declared" in str(w.message) for w in caught)


def test_a_derived_task_is_recorded_in_the_written_pair(tmp_path):
    mechanism = _quiet_load(*first_time_five_bar_files(tmp_path / "model"))
    mechanism.save(tmp_path / "copy.urdf")
    written = yaml.safe_load((tmp_path / "copy.closures.yaml").read_text())
    assert written["task"] == {"frame": "effector", "position": ["x", "y"], "rotation": "none"}
    assert _quiet_load(tmp_path / "copy.urdf").task == mechanism.task


# ------------------------------------------------------------------------------------------------
# Published traits: the forms URDFs take as people publish them (generated fixtures with each trait)

PUBLISHED = {"published_five_bar": published_five_bar_files, "rod_five_bar": rod_five_bar_files}


@pytest.fixture(scope="module", params=sorted(PUBLISHED))
def published(request, tmp_path_factory) -> tuple[Path, Path]:
    return PUBLISHED[request.param](tmp_path_factory.mktemp(request.param))


def _quiet_load(*paths) -> Mechanism:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        return Mechanism.load(*paths)


def test_published_traits_load_with_notes_and_solve_as_the_plain_five_bar(published, tmp_path):
    with pytest.warns(ModelWarning) as caught:
        mechanism = Mechanism.load(*published)
    notes = " | ".join(str(w.message) for w in caught)
    assert "without usable URDF limits" in notes and "taken as unbounded" in notes, notes
    lower, upper = mechanism.joint_limits(
        tuple(
            mechanism.model.names[j]
            for j in range(1, mechanism.model.njoints)
            if mechanism.model.names[j] not in mechanism.actuated_joints
        )
    )
    assert np.all(lower == -np.inf) and np.all(upper == np.inf)  # an empty <limit/> is "not given", not [0, 0]
    assert mechanism.model.nq == mechanism.model.nv and len(mechanism.locked_joints) == 1
    plain = Mechanism.load(*five_bar_files(tmp_path / "plain"))
    sliders = workspace_actuators(plain, 12, np.random.default_rng(2))
    expected = ClosedLoopSolver(plain).forward_batch(sliders).task_poses[:, :2, 3]
    solver = ClosedLoopSolver(mechanism)
    np.testing.assert_allclose(solver.forward_batch(sliders).task_poses[:, :2, 3], expected, atol=1e-10)
    inverse = solver.inverse_batch(expected)
    assert not inverse.failures
    np.testing.assert_allclose(inverse.actuators, sliders, atol=1e-8)
    for q in inverse.q:  # passive values far outside [0, 0] are within their (absent) limits
        assert joint_limit_violation(mechanism.model, q) is None


def test_a_weld_of_coaxial_hinges_on_declared_frames_keeps_its_in_plane_rows(tmp_path):
    mechanism = _quiet_load(*published_five_bar_files(tmp_path))
    assert mechanism.closures[0].rows == (0, 1, 5)
    assert mechanism.locked_joints[0] in ("cut_1", "cut_2")
    weld = mechanism.model.frames[mechanism.model.getFrameId("weld_1")]
    assert weld.type == pin.FrameType.OP_FRAME
    np.testing.assert_allclose(weld.placement.translation, [0.0, 0.0, 0.02], atol=1e-15)  # on stub_1's joint


def test_the_rods_idle_spin_is_locked(tmp_path):
    mechanism = _quiet_load(*rod_five_bar_files(tmp_path))
    assert len(mechanism.locked_joints) == 1 and mechanism.locked_joints[0] in ("x", "y", "z", "s2_x", "s2_y", "s2_z")
    assert mechanism.closures[0].rows == (0, 1, 2, 3, 4, 5)


def test_a_rough_home_is_assembled_with_the_rods_idle_spin_nearest_the_guess(tmp_path):
    """The rod's spin about its own axis moves no link but the rod: every spin closes, and load must take
    the one nearest the given values. From x = 2 and s2_z = 1 rad off, the damped solve alone left the
    spin 0.9 rad (tangentially) away from the nearest, 2.70 instead of 2.55 rad from the guess."""
    urdf, closures = rod_five_bar_files(tmp_path)
    document = yaml.safe_load(closures.read_text())
    document["home"].update(x=2.0, s2_z=1.0)
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    mechanism = _quiet_load(urdf, closures)
    model = mechanism.model
    guess = mechanism.home.copy()
    for name, value in document["home"].items():
        guess[model.idx_qs[model.getJointId(name)]] = value
    passive = [model.idx_vs[j] for j in range(1, model.njoints) if model.names[j] not in mechanism.actuated_joints]
    residual, jacobian = ClosureSystem(model, mechanism.closures, all_rows=True).evaluate(mechanism.home, True)
    assert np.abs(residual).max() < 1e-9
    spin = scipy.linalg.null_space(jacobian[:, passive])
    assert spin.shape[1] == 1  # the idle spin, the only motion left with the motors held
    offset = mechanism.home[passive] - guess[passive]
    assert abs(float(spin[:, 0] @ offset)) < 1e-6  # nearest along the spin: the offset is normal to it
    assert np.linalg.norm(offset) < 2.6


def test_a_written_truth_and_calibrated_pair_reloads_as_the_machine_it_came_from(published, tmp_path):
    nominal = _quiet_load(*published)
    study = simulate_study(nominal, n_poses=30, n_holdout=20, seed=5, errors=PlacementErrorScale(1e-4, 1e-4))
    calibrated = calibrate_closed_loop(nominal, study.measurements).mechanism
    for name, machine in (("truth", study.truth), ("calibrated", calibrated)):
        machine.save(tmp_path / f"{name}.urdf")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ModelWarning)
            reloaded = Mechanism.load(tmp_path / f"{name}.urdf")
        # Nothing re-derived (the file says which rows and joints): only the limits the URDF keeps as published.
        assert all("usable URDF limits" in str(w.message) for w in caught), [str(w.message) for w in caught]
        assert reloaded.locked_joints == machine.locked_joints
        assert [c.rows for c in reloaded.closures] == [c.rows for c in machine.closures]
        errors = pose_errors(reloaded, machine, study.holdout_actuators)
        assert errors.position_max < 1e-9 and errors.rotation_max < 1e-9, (name, errors.position_max)


def test_a_continuous_joint_stays_continuous_in_the_written_urdf(tmp_path):
    mechanism = _quiet_load(*published_five_bar_files(tmp_path))
    mechanism.save(tmp_path / "copy.urdf")
    assert 'name="motor_1" type="continuous"' in (tmp_path / "copy.urdf").read_text()


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["frames"].update(weld_1={"link": "stub_1", "xyz": [0, 0]}), "frames.weld_1.xyz must be three"),
        (lambda d: d["frames"].update(distal_1={"link": "stub_1"}), "frames.distal_1: a frame of that name already"),
        (
            lambda d: d["frames"].update(weld_1={"link": "nowhere"}),
            "frames.weld_1.link: frame 'nowhere' does not exist",
        ),
        (lambda d: d.update(locked_joints=["motor_1"]), "locked_joints: 'motor_1' is an actuated joint"),
        (lambda d: d.update(locked_joints=["cut_9"]), "locked_joints: joint 'cut_9' does not exist"),
    ],
)
def test_malformed_declared_frames_or_locked_joints_are_named(tmp_path, change, message):
    urdf, closures = published_five_bar_files(tmp_path)
    edit_yaml(closures, change)
    with pytest.raises(ModelFileError, match=re.escape(message)):
        _quiet_load(urdf, closures)
