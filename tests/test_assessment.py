"""Judging fits, naming likely causes, the measurement setup, outliers and model selection."""

from __future__ import annotations

import re

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from m3t1r.calibration.assessment import (
    FitRejected,
    check_fit,
    check_start,
    coverage_notes,
    describe_parameter,
    fit_movement_notes,
    likely_causes,
    metres_as_millimetres_causes,
    quaternion_order_causes,
    register_with_offset,
    residual_causes,
    unexplained_residual_warning,
)
from m3t1r.calibration.identification import forward_selection, outlier_poses, select_base_parameters
from m3t1r.calibration.measurement_setup import (
    MeasurementSetup,
    register_frame,
    register_marker_rotation,
    se3_from_report,
    se3_to_report,
)
from m3t1r.errors import IdentificationError, InvalidInputError

# A toy "machine": two readings move a point on a tilted plane (metres), enough to test the checks.
_AXES = np.array([[0.3, 0.05, 0.02], [0.04, 0.25, 0.1]])


def _predict(readings: np.ndarray) -> np.ndarray:
    return np.array([0.5, 0.5, -0.1]) + readings @ _AXES + 0.2 * np.sin(readings[:, :1]) * np.array([0, 0, 1])


def _readings(n: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 2))


def test_likely_causes_are_silent_on_good_data():
    readings = _readings()
    assert likely_causes(_predict, readings, _predict(readings), ("a", "b"), frame_estimated=False) == []


def test_millimetres_are_named():
    readings = _readings()
    causes = likely_causes(_predict, readings, 1000 * _predict(readings), ("a", "b"), frame_estimated=True)
    assert any("--units mm" in c for c in causes)


def test_another_frame_is_named_only_when_the_frame_is_not_estimated():
    readings = _readings()
    frame = pin.SE3(pin.exp3(np.array([0.3, -1.2, 2.0])), np.array([2.0, -1.0, 0.5]))
    measured = _predict(readings) @ frame.rotation.T + frame.translation
    assert any(
        "--frame estimate" in c for c in likely_causes(_predict, readings, measured, ("a", "b"), frame_estimated=False)
    )
    assert likely_causes(_predict, readings, measured, ("a", "b"), frame_estimated=True) == []


def test_swapped_reading_columns_are_named():
    readings = _readings()
    measured = _predict(readings[:, ::-1])
    causes = likely_causes(_predict, readings, measured, ("a", "b"), frame_estimated=True)
    assert any("'a' and 'b' look swapped" in c for c in causes)


def test_swapped_position_columns_are_named_in_the_base_frame_and_as_a_mirror_otherwise():
    readings = _readings()
    measured = _predict(readings)[:, [0, 2, 1]]
    base = likely_causes(_predict, readings, measured, ("a", "b"), frame_estimated=False)
    assert any("hold x, z, y in that order" in c for c in base)
    estimated = likely_causes(_predict, readings, measured, ("a", "b"), frame_estimated=True)
    assert any("mirror image" in c for c in estimated)


def test_data_of_another_machine_are_named_when_nothing_else_explains_them():
    readings = _readings()
    measured = _predict(np.random.default_rng(5).uniform(-1.0, 1.0, readings.shape))
    causes = likely_causes(_predict, readings, measured, ("a", "b"), frame_estimated=True)
    assert causes and "another machine" in causes[-1]


def test_check_fit_refuses_unconverged_and_unexplained_fits_and_names_the_causes():
    check_fit(True, "cost", 7, 1.2)
    check_fit(True, "cost", 7, 8.99)  # within 3x the noise
    with pytest.raises(FitRejected, match="did not converge") as caught:
        check_fit(False, "max_iterations", 60, 1.0, ["use --frame estimate"])
    assert caught.value.causes == ["use --frame estimate"] and isinstance(caught.value, IdentificationError)
    with pytest.raises(FitRejected, match="3.02 times the stated noise"):
        check_fit(True, "cost", 7, 9.1, ["positions look like millimetres"])
    with pytest.raises(FitRejected, match="nan times"):
        check_fit(True, "cost", 7, float("nan"))


def test_a_residual_beyond_the_noise_that_no_cause_explains_is_accepted_with_a_warning():
    assert check_fit(True, "cost", 7, 8.99) is False
    assert check_fit(True, "cost", 7, 45.0) is True  # unmodelled effects: the caller warns
    warning = unexplained_residual_warning(45.0, "1.34e-03 m", 3.4e-3)
    assert "6.71 times the stated noise (variance factor 45)" in warning
    assert "noise of 1.34e-03 m" in warning and "cross-validated error, 0.0034 m" in warning
    # With the noise estimated from the residual the variance factor is ~1 by construction: a cause refuses.
    assert check_fit(True, "cost", 7, 1.0, [], noise_estimated=True) is False
    with pytest.raises(FitRejected, match="with the noise estimated from the residual") as caught:
        check_fit(True, "cost", 7, 1.0, ["columns 'a' and 'b' look swapped"], noise_estimated=True)
    assert caught.value.causes == ["columns 'a' and 'b' look swapped"]


def test_an_unknown_marker_is_registered_before_naming_another_machine():
    """A point 70 mm off the model's measured frame, in another frame: no mistake once registered."""
    rng = np.random.default_rng(8)
    poses = np.array([pin.SE3(pin.exp3(rng.normal(size=3)), rng.uniform(-0.5, 0.5, 3)).homogeneous for _ in range(30)])
    frame = pin.SE3(pin.exp3(np.array([0.2, -0.4, 2.5])), np.array([1.5, 0.3, -0.2]))
    offset = np.array([0.05, -0.02, 0.045])
    measured = (poses[:, :3, :3] @ offset + poses[:, :3, 3]) @ frame.rotation.T + frame.translation
    found = register_with_offset(poses, measured)
    assert found.rms < 1e-9 and np.allclose(found.offset, offset, atol=1e-9)
    assert np.linalg.norm(pin.log6(found.frame.actInv(frame)).vector) < 1e-9
    readings = np.arange(30)[:, None]
    assert likely_causes(lambda r: poses[r[:, 0]], readings, measured, ("i",), frame_estimated=True) == []
    positions_only = likely_causes(lambda r: poses[r[:, 0], :3, 3], readings, measured, ("i",), frame_estimated=True)
    assert "another machine" in positions_only[-1]
    fixed = register_with_offset(poses, measured, estimate_offset=False)
    assert fixed.rms > 0.03 and not fixed.offset.any()


def test_the_start_check_registers_frame_and_marker_on_the_poses_that_fit_and_names_a_gross_one():
    """A point 70 mm off the predicted frames, in another frame, with one reading 1 km off: the
    registration of frame and offset is robust to it, the typical pose is at the noise-free floor and
    the gross pose alone is returned; registering the frame alone leaves the median pose tens of
    millimetres off (the marker's lever), within any build error but far beyond the data's."""
    rng = np.random.default_rng(8)
    poses = np.array([pin.SE3(pin.exp3(rng.normal(size=3)), rng.uniform(-0.5, 0.5, 3)).homogeneous for _ in range(30)])
    frame = pin.SE3(pin.exp3(np.array([0.2, -0.4, 2.5])), np.array([1.5, 0.3, -0.2]))
    offset = np.array([0.05, -0.02, 0.045])
    measured = (poses[:, :3, :3] @ offset + poses[:, :3, 3]) @ frame.rotation.T + frame.translation
    measured[11] += np.array([0.0, 0.0, 1e3])
    start = check_start(poses, measured, True, lambda: [])
    assert start.gross == (11,) and start.typical < 1e-9 and abs(start.distances[11] - 1e3) < 1e-6
    points_only = check_start(poses[:, :3, 3], measured, True, lambda: [])
    assert points_only.gross == (11,) and 0.02 < points_only.typical < 0.1
    with pytest.raises(FitRejected, match=r"\(median over the poses, after registering the frame and the marker\)"):
        check_start(poses, measured + rng.uniform(-1.0, 1.0, measured.shape), True, lambda: [])


def test_parameters_are_described_by_joint_and_component():
    assert describe_parameter("q22.dt[3]") == "q22 rotation about x"
    assert describe_parameter("marker.dt[2]") == "marker translation along z"
    assert describe_parameter("q22.dt[9]") == "q22.dt[9]" and describe_parameter("q22") == "q22"


def test_movement_notes_flag_implausible_and_negligible_fits():
    far = fit_movement_notes({"q11.dt[0]": 0.03, "q12.dt[4]": 0.05}, 1e-2, 1e-5)
    assert len(far) == 1 and "q11 translation along x +0.03 m" in far[0] and "q12" not in far[0]
    assert fit_movement_notes({"q12.dt[4]": 0.2}, 1e-2, 1e-5)[0].count("rad") == 1
    assert "barely moved" in fit_movement_notes({}, 1e-2, 0.9e-2)[0]
    assert fit_movement_notes({"q11.dt[0]": 0.019, "q12.dt[5]": 0.099}, 1e-2, 1e-5) == []


def test_a_move_within_a_few_of_its_own_std_is_not_called_implausible():
    moved = {"q11.dt[0]": 0.03, "q12.dt[4]": -0.3}
    # 0.03 m with a std of 0.015 m (2 sigma) is what the noise allows; -0.3 rad with a std of 0.05 rad (6 sigma) is not.
    notes = fit_movement_notes(moved, 1e-2, 1e-5, std={"q11.dt[0]": 0.015, "q12.dt[4]": 0.05})
    assert len(notes) == 1 and "q12 rotation about y -0.3 rad" in notes[0] and "q11" not in notes[0]
    assert fit_movement_notes(moved, 1e-2, 1e-5, std={"q11.dt[0]": 0.015, "q12.dt[4]": 0.2}) == []
    assert "q11" in fit_movement_notes(moved, 1e-2, 1e-5, std={"q11.dt[0]": 0.005})[0]  # 6 sigma: implausible


def test_coverage_names_the_poorly_covered_coordinates():
    values = np.column_stack([np.linspace(0, 1, 10), np.linspace(0, 0.1, 10)])
    notes = coverage_notes(values, {"x": (0.0, 1.0), "theta": (-0.5, 0.5)})
    assert len(notes) == 1 and notes[0].startswith("theta spans") and "10 %" in notes[0]


# ------------------------------------------------------------------------------------------------
# The measurement setup


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-4, 4), min_size=3, max_size=3), st.lists(st.floats(-5, 5), min_size=3, max_size=3))
def test_registration_finds_any_rotation_and_translation(rotation_vector, translation):
    frame = pin.SE3(pin.exp3(np.array(rotation_vector)), np.array(translation))
    poses = np.tile(np.eye(4), (30, 1, 1))
    poses[:, :3, 3] = np.random.default_rng(1).uniform(-0.5, 0.5, (30, 3))
    found = register_frame(poses, (frame.homogeneous @ poses)[:, :3, 3])
    assert np.linalg.norm(pin.log6(found.actInv(frame)).vector) < 1e-9


def test_registration_refuses_collinear_points():
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = np.linspace(0, 1, 10)
    with pytest.raises(IdentificationError, match="collinear"):
        register_frame(poses, poses[:, :3, 3])


def test_marker_rotation_is_found_in_closed_form():
    rng = np.random.default_rng(3)
    frame = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3))
    marker = pin.exp3(rng.normal(size=3))
    platform = np.array(
        [pin.SE3(pin.exp3(np.array([0, 0, t])), rng.normal(size=3)).homogeneous for t in np.linspace(-0.7, 0.7, 12)]
    )
    measured = frame.rotation @ platform[:, :3, :3] @ marker
    assert np.allclose(register_marker_rotation(frame, platform, measured), marker, atol=1e-12)


def test_setup_round_trips_through_the_report_and_refuses_bad_entries():
    setup = MeasurementSetup(
        pin.SE3(pin.exp3(np.array([0.1, 2.0, -0.3])), np.array([3.0, -1.0, 0.5])),
        pin.SE3(pin.exp3(np.array([0.0, 0.5, 0.0])), np.array([0.07, 0.0, 0.02])),
    )
    again = MeasurementSetup.from_report(setup.to_report())
    assert np.allclose(again.frame.homogeneous, setup.frame.homogeneous)
    assert np.allclose(again.marker.homogeneous, setup.marker.homogeneous)
    assert np.allclose(MeasurementSetup.from_report({}).frame.homogeneous, np.eye(4))
    bad = se3_to_report(setup.frame)
    bad["quaternion"] = [0.0, 0.0, 0.0, 2.0]
    with pytest.raises(InvalidInputError, match="norm 2"):
        se3_from_report(bad, "measurement_frame")
    with pytest.raises(InvalidInputError, match="marker"):
        MeasurementSetup.from_report({"marker": {"translation": [1, 2]}})


# ------------------------------------------------------------------------------------------------
# Outliers and selection


def test_outliers_are_flagged_at_the_5_sigma_gate_and_the_gate_widens_with_unmodelled_effects():
    rng = np.random.default_rng(0)
    blocks = rng.normal(size=(200, 6))
    blocks[7] += 8.0
    flagged, scale = outlier_poses(blocks)
    assert list(np.flatnonzero(flagged)) == [7] and scale == pytest.approx(1.0, abs=0.15)
    wide, scale = outlier_poses(4.0 * blocks)  # every residual 4x the stated noise: the gate widens
    assert list(np.flatnonzero(wide)) == [7] and 3.5 < scale < 4.5
    with pytest.raises(InvalidInputError):
        outlier_poses(np.full((3, 3), np.nan))


def test_forward_selection_keeps_the_parameters_that_predict_and_its_press_is_a_true_leave_one_out():
    rng = np.random.default_rng(2)
    n, k, p = 50, 3, 8
    jacobian = rng.normal(size=(n * k, p))
    truth = np.r_[1.0, -2.0, 0.5, np.zeros(p - 3)]
    residual = -(jacobian @ truth) + 0.3 * rng.normal(size=n * k)
    selection = forward_selection(jacobian, residual, k, range(p))
    assert {0, 1, 2} <= set(selection.indices)
    # PRESS of the chosen set equals refitting without each pose in turn.
    columns = list(selection.indices)
    press = 0.0
    for i in range(n):
        keep = np.r_[np.arange(0, i * k), np.arange((i + 1) * k, n * k)]
        x = np.linalg.lstsq(jacobian[keep][:, columns], -residual[keep], rcond=None)[0]
        press += float(np.sum((residual[i * k : (i + 1) * k] + jacobian[i * k : (i + 1) * k, columns] @ x) ** 2))
    assert selection.press == pytest.approx(press, rel=1e-9)
    assert selection.path[len(columns)] == pytest.approx(selection.press) and selection.press <= selection.press_all


def test_forced_columns_are_kept_first_and_the_ones_they_explain_are_dropped():
    rng = np.random.default_rng(4)
    base = rng.normal(size=(60, 4))
    jacobian = np.column_stack([base, base[:, 0] + base[:, 1], base[:, 2]])  # 4 = 0 + 1, 5 = 2
    names = [f"p{i}" for i in range(6)]
    chosen = select_base_parameters(jacobian, names, forced=[4, 5])
    assert chosen.rank == 4 and {4, 5} <= set(chosen.indices) and 2 not in chosen.indices
    dependent = select_base_parameters(jacobian, names, forced=[2, 5])  # 5 duplicates 2: dropped
    assert 2 in dependent.indices and 5 not in dependent.indices and dependent.rank == 4


def test_a_wrong_unit_is_named_alone_not_followed_by_frame_advice():
    """--units mm on metre data was also told to use --frame estimate."""
    readings = _readings()
    causes = likely_causes(_predict, readings, _predict(readings) / 1000, ("a", "b"), frame_estimated=False)
    assert causes == [causes[0]] and "drop --units mm" in causes[0]


def test_metres_read_as_millimetres_are_named_when_the_readings_were_scaled_too():
    readings = _readings()
    causes = metres_as_millimetres_causes(
        _predict, readings / 1000, _predict(readings) / 1000, np.array([True, True]), frame_estimated=False
    )
    assert len(causes) == 1 and "drop --units mm" in causes[0]
    assert (
        metres_as_millimetres_causes(
            _predict, readings, _predict(readings), np.array([True, True]), frame_estimated=False
        )
        == []
    )


def test_a_small_residual_names_no_mistake_and_a_large_one_names_the_marker():
    """A noise stated ten times too small was answered with 'give --marker': a sub-millimetre
    residual is the noise (or unmodelled effects), written with a warning, not a setup mistake."""
    small = dict(marker_given=False, position_only=False)
    assert residual_causes(1.5e-5, 3e-5, beyond_noise=True, **small) == []
    large = residual_causes(4e-3, 0.05, beyond_noise=True, **small)
    assert len(large) == 1 and "--marker X Y Z" in large[0]
    assert residual_causes(4e-3, 0.05, beyond_noise=True, marker_given=True, position_only=False) == []
    assert residual_causes(4e-3, float("nan"), beyond_noise=True, marker_given=False, position_only=True) == []
    # Within the noise (as when it is estimated from the residual), only a rotation no tracker leaves.
    assert residual_causes(4e-3, 2e-3, beyond_noise=False, **small) == []
    assert len(residual_causes(4e-3, 0.05, beyond_noise=False, **small)) == 1
    warning = unexplained_residual_warning(100.0, "1e-05 m and 2e-05 rad", 1.4e-5)
    assert "a noisier tracker than stated" in warning and "--noise-pos auto" in warning and "--marker" not in warning


def _yawing_poses(n: int = 20) -> np.ndarray:
    rng = np.random.default_rng(2)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for pose in poses:
        pose[:3, :3] = pin.exp3(np.r_[rng.normal(0, 0.02, 2), rng.uniform(-0.8, 0.8)])
        pose[:3, 3] = rng.uniform(-0.3, 0.3, 3)
    return poses


@pytest.mark.parametrize("frame_estimated", [False, True])
def test_quaternions_scalar_first_under_scalar_last_names_are_named(frame_estimated):
    poses = _yawing_poses()
    frame = (
        pin.SE3(pin.exp3(np.array([0.1, -0.4, 2.0])), np.array([3.0, -1.0, 0.5]))
        if frame_estimated
        else pin.SE3.Identity()
    )
    marker = pin.exp3(np.array([0.3, 0.0, -0.2]))
    measured = frame.homogeneous @ poses
    rotations = measured[:, :3, :3] @ marker
    assert quaternion_order_causes(poses, measured[:, :3, 3], rotations, frame_estimated=frame_estimated) == []
    # The file holds w, x, y, z under qx, qy, qz, qw: the reader builds the quaternion (x=w, y=x, z=y, w=z).
    wxyz = [pin.Quaternion(r) for r in rotations]
    misread = np.array([pin.Quaternion(q.z, q.w, q.x, q.y).normalized().matrix() for q in wxyz])
    causes = quaternion_order_causes(poses, measured[:, :3, 3], misread, frame_estimated=frame_estimated)
    assert len(causes) == 1 and "look like w, x, y, z (scalar first)" in causes[0]


def test_a_refusal_before_the_fit_does_not_offer_force():
    """'--force writes it anyway' was printed where --force has nothing to write, even when it was given."""
    with pytest.raises(FitRejected) as caught:
        check_start(np.zeros((5, 3)), np.ones((5, 3)), False, lambda: [])
    assert str(caught.value).endswith("nothing was written") and not caught.value.forceable
    with pytest.raises(FitRejected) as caught:
        check_fit(True, "cost", 7, 100.0, ["positions look like millimetres"])  # a fit that ran, judged
    assert str(caught.value).endswith("nothing was written (--force writes it anyway)") and caught.value.forceable


def test_a_reflector_the_measured_frame_absorbed_is_not_told_to_check_the_units() -> None:
    """Without --marker the tool frame took up a 7 cm reflector: 'check the units' named a fault the
    data do not show; the note names the measured frame instead, and other far moves keep the check."""
    notes = fit_movement_notes({"tool.dt[2]": 0.07, "tool.dt[4]": 0.2, "q2.dt[0]": 1e-4}, 1e-2, 1e-5, "tool")
    assert "check the units" not in notes[0] and "only the measured frame tool moved" in notes[0]
    assert "reflector" in notes[1] and "--marker X Y Z" in notes[1]
    # TIAGo without --marker: the fit shared the 7 cm between the tool frame and the last joint's
    # translation along its own axis, which moves the tool frame alike.
    shared = fit_movement_notes({"tool.dt[2]": 0.0735, "q7.dt[2]": 0.0567}, 1e-2, 1e-5, "tool", ("q7.dt[2]",))
    assert "check the units" not in shared[0] and "translations along the last joint's axis" in shared[0]
    mixed = fit_movement_notes({"tool.dt[2]": 0.07, "q2.dt[0]": 0.05}, 1e-2, 1e-5, "tool")
    assert "check the units" in mixed[0] and "the moves of tool itself are the reflector below" in mixed[0]


# ==================================================================================================
# Messages, thresholds and the start check, exactly
#
# Every message word for word (with its numbers), every threshold of likely_causes, check_start,
# fit_movement_notes and coverage_notes from both sides, and the validity guard of the swapped-columns check.
# ==================================================================================================


NAMES = ("a", "b")


def kabsch_rms(points: np.ndarray, measured: np.ndarray) -> float:
    """RMS [m] left by the best rigid motion of `points` onto `measured` (independent of the module)."""
    p, m = points - points.mean(0), measured - measured.mean(0)
    u, _, vt = np.linalg.svd(m.T @ p)
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return float(np.sqrt(np.mean(np.sum((p @ rotation.T - m) ** 2, axis=1))))


def times_better(cause: str) -> float:
    return float(re.search(r"(\d+) times better", cause).group(1))


# --------------------------------------------------------------------------------------------------
# FitRejected, check_fit, check_start


def test_fit_rejected_lists_the_causes_and_what_was_not_written() -> None:
    error = FitRejected("the reason", ["one", "two"])
    assert error.reason == "the reason" and error.causes == ["one", "two"]
    assert str(error) == (
        "the reason\n  likely cause: one\n  likely cause: two\n  nothing was written (--force writes it anyway)"
    )


def test_check_fit_messages_and_the_accepted_boundary() -> None:
    check_fit(True, "cost", 7, 9.0)  # exactly 3 times the noise: accepted
    with pytest.raises(FitRejected) as info:
        check_fit(False, "max_iterations", 60, 1.0, ["c"])
    assert info.value.reason == (
        "the fit did not converge (max_iterations after 60 iterations; --max-iterations raises the cap)"
    )
    assert info.value.causes == ["c"]
    assert check_fit(True, "cost", 7, 16.0) is True  # beyond the noise, no cause: accepted, to be warned of
    with pytest.raises(FitRejected) as info:
        check_fit(True, "cost", 7, 16.0, ["given"])
    assert (
        info.value.reason
        == "the residual is 4 times the stated noise (accepted up to 3): the model does not explain the data"
    )
    assert info.value.causes == ["given"]
    with pytest.raises(FitRejected) as info:
        check_fit(True, "cost", 7, float("inf"))
    assert info.value.reason.startswith("the residual is nan times the stated noise")
    assert info.value.causes == ["a reading or measurement the model cannot evaluate"]


def _cloud(n: int = 10) -> np.ndarray:
    return np.random.default_rng(3).uniform(-0.5, 0.5, (n, 3)) + np.array([1.0, 2.0, 0.5])


def test_check_start_measures_the_median_distance_to_the_nominal_points() -> None:
    points = _cloud()
    offsets = np.zeros_like(points)
    offsets[:, 0] = 0.2 * np.where(np.arange(len(points)) % 2, 1.0, -1.0)  # every pose 0.2 m off
    with pytest.raises(FitRejected) as info:
        check_start(points, points + offsets, False, lambda: ["cause"], what="robot")
    assert info.value.reason == (
        "the nominal robot is 0.2 m from the measurements (median over the poses), beyond any "
        "build error (0.1 m): the fit was not attempted"
    )
    assert info.value.causes == ["cause"] and not info.value.forceable
    exact = np.zeros_like(points)  # exactly HOPELESS_RESIDUAL (0.1 m) as computed: not beyond
    exact[:, 0] = [0.1] * 7 + [np.nextafter(0.1, 0.0)] * 3
    assert check_start(np.zeros_like(points), exact, False, lambda: []).gross == ()
    check_start(points, points + 0.05, False, lambda: [])  # 0.087 m, large coordinates
    three = exact.copy()
    three[:3, 0] = 0.5  # 3 of 10 beyond: more than MAX_GROSS_SHARE, the data as a whole
    with pytest.raises(FitRejected, match="3 of 10 poses are beyond it"):
        check_start(np.zeros_like(points), three, False, lambda: [])
    three[2, 0] = 0.0
    assert check_start(np.zeros_like(points), three, False, lambda: []).gross == (0, 1)


def test_check_start_registers_the_frame_when_it_is_estimated() -> None:
    points = _cloud()
    frame = pin.SE3(pin.exp3(np.array([0.4, -1.0, 2.0])), np.array([3.0, -2.0, 1.0]))
    moved = points @ frame.rotation.T + frame.translation
    check_start(points, moved, True, lambda: [])  # metres away, but a rigid motion explains it
    mirrored = moved * np.array([1.0, 1.0, -1.0])
    rms = kabsch_rms(points, mirrored)
    assert rms > 0.1
    with pytest.raises(FitRejected) as info:
        check_start(points, mirrored, True, lambda: [])
    assert info.value.reason.startswith("the nominal machine is ") and info.value.reason.endswith(
        " m from the measurements (median over the poses, after registering the frame), beyond any build error "
        "(0.1 m): the fit was not attempted"
    )
    gross = moved.copy()
    gross[4] += np.array([0.0, 1e4, 0.0])  # 10 km off: moves a least-squares frame by 1 km
    start = check_start(points, gross, True, lambda: [])
    assert start.gross == (4,) and start.typical < 1e-9 and abs(start.distances[4] - 1e4) < 1e-6


# --------------------------------------------------------------------------------------------------
# describe_parameter, coverage_notes


@pytest.mark.parametrize(
    ("name", "described"),
    [
        ("q.dt[5]", "q rotation about z"),
        ("q.dt[05]", "q rotation about z"),
        ("a.dt[3].dt[0]", "a.dt[3] translation along x"),
        ("q.dt[6]", "q.dt[6]"),
        ("q.dt[12]", "q.dt[12]"),
        ("q.dt[3a]", "q.dt[3a]"),
        ("q.dt[34", "q.dt[34"),
        (".dt[3]", ".dt[3]"),
    ],
)
def test_describe_parameter_reads_only_well_formed_names(name: str, described: str) -> None:
    assert describe_parameter(name) == described


def test_coverage_notes_scale_with_the_workspace() -> None:
    values = np.column_stack([np.linspace(0.0, 0.5, 11), np.linspace(0.0, 0.5, 11)])
    notes = coverage_notes(values, {"x": (-1.0, 1.0), "y": (0.0, 1.0)})
    # x: 0.5 of a 2 m workspace (25 %) is poor; y: exactly half of 1 m is not below half.
    assert notes == ["x spans 0 .. 0.5 (25 % of the workspace's -1 .. 1)"]


# --------------------------------------------------------------------------------------------------
# fit_movement_notes


def test_the_three_farthest_moves_are_listed_by_their_ratio_to_the_limit() -> None:
    moved = {"q1.dt[1]": 0.05, "q2.dt[4]": 0.3, "q3.dt[2]": -0.03, "q4.dt[3]": 0.11, "q5.dt[0]": 0.02}
    notes = fit_movement_notes(moved, 1e-2, 1e-5)
    assert notes == [
        "the fit moved implausibly far for a machine built to drawing (q2 rotation about y +0.3 rad, "
        "q1 translation along y +0.05 m, q3 translation along z -0.03 m): check the units, the measurement frame, "
        "the reading columns and that the model is this machine's"
    ]


def test_the_last_dt_index_of_a_name_decides_translation_or_rotation() -> None:
    assert len(fit_movement_notes({"a.dt[3].dt[0]": 0.05}, 1e-2, 1e-5)) == 1
    assert fit_movement_notes({"a.dt[0].dt[3]": 0.05}, 1e-2, 1e-5) == []


def test_the_measured_frame_moving_far_names_a_reflector() -> None:
    note = (
        "the measured frame tool itself moved: the measured point is probably a reflector off it, now baked into "
        "the machine; give its position with --marker X Y Z"
    )
    assert fit_movement_notes({"tool.dt[1]": 0.05}, 1e-2, 1e-5, "tool")[1] == note
    # Another parameter far, the frame's own translation at the limit or its rotation: no reflector note.
    for moved in ({"q1.dt[0]": 0.05, "tool.dt[1]": 0.02}, {"q1.dt[0]": 0.05, "tool.dt[4]": 0.5}, {"q1.dt[0]": 0.05}):
        assert len(fit_movement_notes(moved, 1e-2, 1e-5, "tool")) == 1


def test_barely_moved_boundaries() -> None:
    note = (
        "the fit barely moved (residual RMS 1 -> 0.9 m): the nominal model already explains the data, or the "
        "poses do not excite the errors"
    )
    assert fit_movement_notes({}, 1.0, 0.9) == [note]
    assert fit_movement_notes({}, 1.0, 0.8) == []  # exactly 80 %: it moved enough
    assert fit_movement_notes({}, 0.0, 1e-3) == []  # no residual before: nothing to compare


# --------------------------------------------------------------------------------------------------
# likely_causes


def test_too_few_assembling_readings_are_named_exactly() -> None:
    readings = _readings()

    def predict(r: np.ndarray) -> np.ndarray:
        points = _predict(r)
        points[4:] = np.nan  # only the first 4 rows assemble
        return points

    measured = _predict(readings)
    assert likely_causes(predict, readings, measured, NAMES, frame_estimated=False) == []  # 4 are enough
    points = predict(readings)
    points[3] = np.nan
    assert likely_causes(lambda r: points, readings, measured, NAMES, frame_estimated=False) == [
        "the readings do not assemble on this machine: columns in another order or unit, or another machine"
    ]


@pytest.mark.parametrize(
    ("scale", "cause"),
    [
        (1000.0, "positions look like millimetres (spread 1000 times the model's): use --units mm"),
        (300.5, "positions look like millimetres (spread 300 times the model's): use --units mm"),
        (2999.0, "positions look like millimetres (spread 2999 times the model's): use --units mm"),
        (3000.5, None),
        (299.0, None),
        (1e-3, "positions look like metres (spread 1/1000 of the model's): drop --units mm"),
        (1 / 2000.0, "positions look like metres (spread 1/2000 of the model's): drop --units mm"),
        (1 / 300.5, "positions look like metres (spread 1/300 of the model's): drop --units mm"),
        (1 / 3000.5, None),
        (1 / 200.0, None),
    ],
)
def test_unit_mistakes_are_named_within_their_spread_ratios(scale: float, cause: str | None) -> None:
    readings = _readings()
    causes = likely_causes(_predict, readings, scale * _predict(readings), NAMES, frame_estimated=True)
    units = [c for c in causes if "--units" in c]
    assert units == ([cause] if cause else [])


def test_another_frame_is_named_from_a_2_cm_rms_offset_and_5_times_the_registered_residual() -> None:
    readings = _readings()
    points = _predict(readings)
    causes = likely_causes(_predict, readings, points + np.array([0.5, 0.0, 0.0]), NAMES, frame_estimated=False)
    frame = [c for c in causes if "--frame estimate" in c]
    assert len(frame) == 1
    assert frame[0].startswith(
        "the data look like they are in another frame (a rigid registration moves them 0.5 m and "
    )
    assert frame[0].endswith(" m RMS): use --frame estimate")
    assert likely_causes(_predict, readings, points + np.array([0.01, 0.0, 0.0]), NAMES, frame_estimated=False) == []
    # Registered residual r, offset such that the direct RMS is 5.5 r: named (the rule is 5 r).
    noise = np.random.default_rng(4).normal(0.0, 0.01, points.shape)
    noise -= noise.mean(0)
    registered = kabsch_rms(points, points + noise)
    shift = np.sqrt((5.5 * registered) ** 2 - np.mean(np.sum(noise**2, axis=1)))
    causes = likely_causes(
        _predict, readings, points + noise + np.array([0.0, shift, 0.0]), NAMES, frame_estimated=False
    )
    assert any("--frame estimate" in c for c in causes)


def test_another_machine_is_named_with_its_registered_residual() -> None:
    readings = _readings()
    measured = _predict(np.random.default_rng(5).uniform(-1.0, 1.0, readings.shape))
    causes = likely_causes(_predict, readings, measured, NAMES, frame_estimated=True)
    rms = kabsch_rms(_predict(readings), measured)
    assert causes == [
        f"the data do not fit this machine even after a rigid registration ({rms:.3g} m RMS): data from "
        "another machine, or the wrong model files"
    ]


def test_swapped_position_columns_report_how_much_better_they_fit() -> None:
    readings = _readings()
    points = _predict(readings)
    noise = np.random.default_rng(6).normal(0.0, 1e-4, points.shape)
    measured = points[:, [1, 0, 2]] + noise
    base = likely_causes(_predict, readings, measured, NAMES, frame_estimated=False)
    swapped = [c for c in base if "position columns" in c]
    assert len(swapped) == 1 and swapped[0].startswith("the position columns look like they hold y, x, z in that order")
    direct = np.sqrt(np.mean(np.sum((points - measured) ** 2, axis=1)))
    best = np.sqrt(np.mean(np.sum((points - measured[:, [1, 0, 2]]) ** 2, axis=1)))
    assert times_better(swapped[0]) == pytest.approx(direct / best, abs=0.5)
    mirror = [c for c in likely_causes(_predict, readings, measured, NAMES, frame_estimated=True) if "mirror" in c]
    assert len(mirror) == 1
    expected = kabsch_rms(points, measured) / kabsch_rms(points, measured[:, [1, 0, 2]])
    assert times_better(mirror[0]) == pytest.approx(expected, abs=0.5)


def test_only_the_best_column_order_is_reported() -> None:
    """x and z nearly equal: two orders explain y, x, z data; the better one alone is named."""
    readings = _readings()

    def predict(r: np.ndarray) -> np.ndarray:
        points = _predict(r)
        points[:, 2] = points[:, 0] + 0.01 * np.sin(3.0 * r[:, 1])
        return points

    measured = predict(readings)[:, [1, 0, 2]]
    base = [
        c for c in likely_causes(predict, readings, measured, NAMES, frame_estimated=False) if "position columns" in c
    ]
    assert len(base) == 1 and "hold y, x, z" in base[0]


def test_no_column_order_is_named_for_data_that_fit_or_fit_no_order() -> None:
    readings = _readings()

    def predict(r: np.ndarray) -> np.ndarray:  # x and y equal: the identity and the x/y swap both fit exactly
        points = _predict(r)
        points[:, 1] = points[:, 0]
        return points

    assert likely_causes(predict, readings, predict(readings), NAMES, frame_estimated=False) == []
    other = _predict(np.random.default_rng(5).uniform(-1.0, 1.0, readings.shape))
    assert not [
        c for c in likely_causes(_predict, readings, other, NAMES, frame_estimated=False) if "position columns" in c
    ]


def _partial_predict(limit: float):
    def predict(r: np.ndarray) -> np.ndarray:
        points = _predict(r)
        points[r[:, 0] > limit] = np.nan
        return points

    return predict


@pytest.mark.parametrize(("n_invalid", "named"), [(4, True), (5, False)])
def test_a_column_swap_is_judged_only_when_90_percent_of_its_readings_assemble(n_invalid: int, named: bool) -> None:
    rng = np.random.default_rng(8)
    readings = np.column_stack([rng.uniform(-1.0, 0.8, 40), rng.uniform(-1.0, 0.8, 40)])
    readings[:n_invalid, 1] = 0.9  # these rows do not assemble once a and b are exchanged
    measured = _predict(readings[:, ::-1])
    causes = likely_causes(_partial_predict(0.85), readings, measured, NAMES, frame_estimated=True)
    assert any("'a' and 'b' look swapped" in c for c in causes) == named


def test_a_swap_of_four_readings_is_judged() -> None:
    readings = _readings(4, seed=2)
    causes = likely_causes(_predict, readings, _predict(readings[:, ::-1]), NAMES, frame_estimated=True)
    assert any("'a' and 'b' look swapped" in c for c in causes)


def test_an_unassembled_swap_does_not_stop_the_search_and_the_ratio_is_reported() -> None:
    readings = np.column_stack([_readings(40, seed=9), np.random.default_rng(10).uniform(-1.0, 1.0, 40)])
    readings[:, 0] = np.random.default_rng(11).uniform(1.5, 2.0, 40)  # a beyond b's range: a/b swapped fails

    def predict(r: np.ndarray) -> np.ndarray:
        points = _predict(r[:, 1:]) + 0.01 * r[:, :1] * np.array([1.0, -1.0, 0.5])
        points[r[:, 1] > 1.2] = np.nan
        return points

    swapped = readings[:, [0, 2, 1]]
    measured = predict(swapped) + np.random.default_rng(12).normal(0.0, 1e-4, (40, 3))
    names = ("a", "b", "c")
    causes = likely_causes(predict, readings, measured, names, frame_estimated=True)
    found = [c for c in causes if "'b' and 'c' look swapped" in c]
    assert len(found) == 1
    expected = kabsch_rms(predict(readings), measured) / kabsch_rms(predict(swapped), measured)
    assert times_better(found[0]) == pytest.approx(expected, rel=0.01)


def _noise_scale_for_ratio(ratio_of_scale, target: float = 5.5) -> float:
    """The noise scale s at which ratio_of_scale(s) (decreasing in s) equals `target`, by bisection."""
    low, high = 1e-8, 1.0
    for _ in range(80):
        middle = np.sqrt(low * high)
        low, high = (middle, high) if ratio_of_scale(middle) > target else (low, middle)
    return float(np.sqrt(low * high))


def test_each_swap_rule_is_5_times_better_not_6() -> None:
    """Data that a swap explains 5.5 times better than the nominal reading: every rule names it."""
    readings = _readings()
    points = _predict(readings)
    noise = np.random.default_rng(13).normal(size=points.shape)

    swapped_points = _predict(readings[:, ::-1])
    scale = _noise_scale_for_ratio(
        lambda s: (
            kabsch_rms(points, swapped_points + s * noise) / kabsch_rms(swapped_points, swapped_points + s * noise)
        )
    )
    causes = likely_causes(_predict, readings, swapped_points + scale * noise, NAMES, frame_estimated=True)
    assert any("'a' and 'b' look swapped" in c for c in causes)

    def direct(measured: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((points - measured) ** 2, axis=1))))

    permuted = points[:, [1, 0, 2]]
    scale = _noise_scale_for_ratio(
        lambda s: direct(permuted + s * noise) / direct((permuted + s * noise)[:, [1, 0, 2]])
    )
    causes = likely_causes(_predict, readings, permuted + scale * noise, NAMES, frame_estimated=False)
    assert any("hold y, x, z in that order" in c for c in causes)

    scale = _noise_scale_for_ratio(
        lambda s: kabsch_rms(points, permuted + s * noise) / kabsch_rms(points, (permuted + s * noise)[:, [1, 0, 2]])
    )
    causes = likely_causes(_predict, readings, permuted + scale * noise, NAMES, frame_estimated=True)
    assert any("mirror image" in c for c in causes)


def test_movement_limits_and_coverage_percentages_exactly() -> None:
    assert fit_movement_notes({"q.dt[0]": 0.02, "r.dt[3]": -0.1}, 1e-2, 1e-5) == []  # at the limits: not beyond
    values = np.linspace(0.0, 0.453, 5)[:, None]
    assert coverage_notes(values, {"x": (0.0, 1.0)}) == ["x spans 0 .. 0.453 (45 % of the workspace's 0 .. 1)"]
