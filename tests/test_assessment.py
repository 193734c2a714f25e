"""Judging fits, naming likely causes, the measurement setup, outliers and model selection."""

from __future__ import annotations

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
    assert any("--frame estimate" in c for c in likely_causes(_predict, readings, measured, ("a", "b"),
                                                              frame_estimated=False))
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
    platform = np.array([pin.SE3(pin.exp3(np.array([0, 0, t])), rng.normal(size=3)).homogeneous
                         for t in np.linspace(-0.7, 0.7, 12)])
    measured = frame.rotation @ platform[:, :3, :3] @ marker
    assert np.allclose(register_marker_rotation(frame, platform, measured), marker, atol=1e-12)


def test_setup_round_trips_through_the_report_and_refuses_bad_entries():
    setup = MeasurementSetup(pin.SE3(pin.exp3(np.array([0.1, 2.0, -0.3])), np.array([3.0, -1.0, 0.5])),
                             pin.SE3(pin.exp3(np.array([0.0, 0.5, 0.0])), np.array([0.07, 0.0, 0.02])))
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
        press += float(np.sum((residual[i * k:(i + 1) * k] + jacobian[i * k:(i + 1) * k, columns] @ x) ** 2))
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
    causes = metres_as_millimetres_causes(_predict, readings / 1000, _predict(readings) / 1000, np.array([True, True]),
                                          frame_estimated=False)
    assert len(causes) == 1 and "drop --units mm" in causes[0]
    assert metres_as_millimetres_causes(_predict, readings, _predict(readings), np.array([True, True]),
                                        frame_estimated=False) == []


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
    frame = pin.SE3(pin.exp3(np.array([0.1, -0.4, 2.0])), np.array([3.0, -1.0, 0.5])) if frame_estimated \
        else pin.SE3.Identity()
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
