"""Closing a home that does not close (`m3t1r.model.assembly`): the assembly nearest the given values,
whole turns wrapped into the limits, the report and its note, the joints beyond their limits."""

import warnings

import numpy as np
import pinocchio as pin
import pytest
from mjcf_mechanisms import spatial_loop_mjcf, straight_four_bar_mjcf

from m3t1r.errors import ModelWarning
from m3t1r.model.assembly import HomeAssembly, assemble_home, limits_violated
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.description import Mechanism

# ---------------------------------------------------------------------------------------------------
# The assembly nearest the given values, and its report


def _index(mechanism, joint):
    return mechanism.model.idx_qs[mechanism.model.getJointId(joint)]


def _assembled(mechanism, guess):
    system = ClosureSystem(mechanism.model, mechanism.closures)
    return assemble_home(mechanism.model, mechanism.closures, system, guess, mechanism.passive_ids)


def test_a_passive_joint_given_off_is_brought_back_and_reported(mechanism):
    """q13 given at 0.7 rad: the nearest assembly is the nominal home; q13 moved by home - 0.7 (0.347)."""
    guess = mechanism.home.copy()
    guess[_index(mechanism, "q13")] = 0.7
    home, report = _assembled(mechanism, guess)
    assert np.abs(home - mechanism.home).max() < 1e-9 and guess[_index(mechanism, "q13")] == 0.7  # not in place
    assert report.worst == "platform" and report.given_residual == pytest.approx(0.2105, abs=1e-4)
    assert report.residual < 1e-12 and report.wrapped == () and report.iterations >= 1
    assert [name for name, _ in report.moved] == ["q13"]
    assert report.moved[0][1] == pytest.approx(mechanism.home[_index(mechanism, "q13")] - 0.7, abs=1e-9)


def test_a_home_that_closes_is_kept_and_a_whole_turn_is_wrapped_not_moved(mechanism):
    home, report = _assembled(mechanism, mechanism.home.copy())
    assert np.abs(home - mechanism.home).max() < 1e-12 and report.moved == () and report.iterations == 0
    assert report.given_residual < 1e-12 and report.worst == "platform"  # the largest row, however small
    turned = mechanism.home.copy()
    turned[_index(mechanism, "q13")] += 2 * np.pi  # beyond q13's limits [-30, 150] deg
    home, report = _assembled(mechanism, turned)
    assert np.abs(home - mechanism.home).max() < 1e-12
    assert report.wrapped == ("q13",) and report.moved == () and report.iterations == 0


# ---------------------------------------------------------------------------------------------------
# The note for the user


def test_the_note_names_the_closure_the_moves_largest_first_and_the_wraps():
    report = HomeAssembly("platform", 0.21048, 1e-16, (("q13", 0.347198), ("q12", -0.01)), ("q22",), 6)
    assert report.note(1e-9) == (
        "home does not close: closure 'platform' residual 2.105e-01 > 1e-09; assembled by Newton (damped, "
        "actuators held) at the assembly nearest the given values: passive joints moved by q13 +0.347, "
        "q12 -0.01 [rad or m]; q22 wrapped by whole turns. To choose another assembly mode, give "
        "approximate values of its passive joints in `home`"
    )


def test_the_note_shows_six_moves_and_counts_the_others():
    moved = tuple((f"j{k}", 0.1 * (9 - k)) for k in range(9))
    note = HomeAssembly("loop", 1.0, 0.0, moved, ("a", "b"), 3).note(1e-6)
    assert "moved by j0 +0.9, j1 +0.8, j2 +0.7, j3 +0.6, j4 +0.5, j5 +0.4 and 3 more [rad or m]; a, b wrapped" in note
    assert "> 1e-06;" in note
    assert "moved by nothing [rad or m]. To choose" in HomeAssembly("loop", 1.0, 0.0, (), (), 0).note(1e-9)
    six = HomeAssembly("loop", 1.0, 0.0, moved[:6], (), 0).note(1e-9)
    assert "j5 +0.4 [rad or m]. To choose" in six
    seven = HomeAssembly("loop", 1.0, 0.0, moved[:7], (), 0).note(1e-9)
    assert "j5 +0.4 and 1 more [rad or m]. To choose" in seven


# ---------------------------------------------------------------------------------------------------
# Joints beyond their limits


def test_joints_beyond_their_limits_are_listed_with_the_limits(mechanism):
    """q13's limits are [-pi/6, 5 pi/6]: 1e-6 past either is beyond, 1e-13 past is not; an absent
    limit (lower >= upper) is never crossed."""
    model, q = mechanism.model.copy(), mechanism.home.copy()
    v = _index(mechanism, "q13")
    lower, upper = model.lowerPositionLimit[v], model.upperPositionLimit[v]
    joints = mechanism.passive_ids
    assert limits_violated(model, q, joints) == []
    for value in (lower - 1e-6, upper + 1e-6):
        q[v] = value
        assert limits_violated(model, q, joints) == [("q13", value, lower, upper)]
    for value in (lower - 1e-13, upper + 1e-13, lower, upper):
        q[v] = value
        assert limits_violated(model, q, joints) == []
    q[v] = upper + 1.0
    assert limits_violated(model, q, np.array([v])) == [("q13", upper + 1.0, lower, upper)]
    assert limits_violated(model, q, np.array([v + 1])) == []  # not among the joints asked about
    limits = model.upperPositionLimit.copy()
    limits[v] = lower
    model.upperPositionLimit = limits
    assert limits_violated(model, q, joints) == []


# ---------------------------------------------------------------------------------------------------
# Whole turns into the limits


def _with_limits(mechanism, joint, lower, upper):
    model = mechanism.model.copy()
    v = _index(mechanism, joint)
    low, high = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
    low[v], high[v] = lower, upper
    model.lowerPositionLimit, model.upperPositionLimit = low, high
    return model


@pytest.mark.parametrize(("lower", "upper", "turns"), [(6.0, 7.5, 1), (-5.5, -5.0, -1), (13.0, 14.0, 2)])
def test_a_revolute_joint_is_turned_into_limits_beyond_a_half_turn(mechanism, lower, upper, turns):
    """q13 at home (60 deg) with limits that hold it only whole turns away: turned there, reported
    wrapped, not moved. Every joint passed (the sliders too, which are never turned)."""
    model = _with_limits(mechanism, "q13", lower, upper)
    system = ClosureSystem(model, mechanism.closures)
    every = np.arange(model.nv)
    home, report = assemble_home(model, mechanism.closures, system, mechanism.home.copy(), every)
    v = _index(mechanism, "q13")
    assert home[v] == pytest.approx(mechanism.home[v] + 2 * np.pi * turns, abs=1e-12)
    assert report.wrapped == ("q13",) and report.moved == ()
    others = np.arange(model.nq) != v
    np.testing.assert_allclose(home[others], mechanism.home[others], rtol=0, atol=1e-12)


def test_limits_no_whole_turn_fits_leave_the_principal_angle(mechanism):
    """Limits [3, 4] rad: 60 deg is outside, and a turn more (420 deg) too: q13 stays at 60 deg,
    which `limits_violated` then reports."""
    model = _with_limits(mechanism, "q13", 3.0, 4.0)
    system = ClosureSystem(model, mechanism.closures)
    turned = mechanism.home.copy()
    v = _index(mechanism, "q13")
    turned[v] += 4 * np.pi
    home, report = assemble_home(model, mechanism.closures, system, turned, mechanism.passive_ids)
    assert home[v] == pytest.approx(mechanism.home[v], abs=1e-12) and report.wrapped == ("q13",)
    assert limits_violated(model, home, np.array([v])) == [("q13", home[v], 3.0, 4.0)]


def test_limits_that_state_nothing_take_the_principal_angle(mechanism):
    """lower >= upper (an absent limit): into (-pi, pi]."""
    model = _with_limits(mechanism, "q13", 0.0, 0.0)
    system = ClosureSystem(model, mechanism.closures)
    turned = mechanism.home.copy()
    v = _index(mechanism, "q13")
    turned[v] -= 2 * np.pi
    home, report = assemble_home(model, mechanism.closures, system, turned, mechanism.passive_ids)
    assert home[v] == pytest.approx(mechanism.home[v], abs=1e-12) and report.wrapped == ("q13",)


# ---------------------------------------------------------------------------------------------------
# The damped steps


@pytest.mark.parametrize(
    ("given", "steps"),
    [({"q13": 0.7}, 6), ({"q13": 2.0}, 10), ({"q12_pa": 0.5}, 7), ({"q12": 0.3, "q13": 0.2, "q22": 1.5}, 23)],
)
def test_the_damped_phase_takes_as_many_steps_as_nielsen_s_update_gives(mechanism, given, steps):
    """Levenberg-Marquardt from mu = 1e-3 max diag(J^T J), Nielsen's update (mu x max(1/3, 1 - (2 gain - 1)^3)
    on a step that lowers the cost, mu x nu and nu x 2 otherwise): the step counts of four starts, each
    ending on a closed home (the last, far from the nominal, on another assembly of the five-bars)."""
    guess = mechanism.home.copy()
    for joint, value in given.items():
        guess[_index(mechanism, joint)] = value
    home, report = _assembled(mechanism, guess)
    assert report.iterations == steps and report.residual < 1e-12
    closes = ClosureSystem(mechanism.model, mechanism.closures).evaluate(home, False)[0]
    assert np.abs(closes).max() < 1e-12


# ---------------------------------------------------------------------------------------------------
# A guess the solve stalls at: restarts from fixed offsets


def test_a_linkage_given_stretched_straight_is_assembled_from_the_restarts(tmp_path):
    """The four-bar with every link on one line (the cut sites 8 cm apart along it): the damped solve
    from there stalls (a stationary point of the residual); the 8 restarts from fixed offsets close on
    one of the two mirror assemblies, equally far from the line. The steps count every attempt."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        mechanism = Mechanism.load(straight_four_bar_mjcf(tmp_path))
    model = mechanism.model
    system = ClosureSystem(model, mechanism.closures)
    home, report = assemble_home(model, mechanism.closures, system, pin.neutral(model), mechanism.passive_ids)
    assert np.abs(system.evaluate(home, False)[0]).max() < 1e-12 and report.residual < 1e-12
    assert report.worst == "loop" and report.given_residual == pytest.approx(0.08, abs=1e-12)
    assert report.iterations == 130 and report.wrapped == ()
    assert [name for name, _ in report.moved] == ["rocker", "knee"]
    sizes = [abs(move) for _, move in report.moved]
    assert sizes == pytest.approx([1.2164911578, 0.9625507479], abs=1e-9)
    assert report.moved[0][1] * report.moved[1][1] < 0  # the knee bends against the rocker


def test_a_closure_enforced_whole_is_assembled_with_its_smooth_rows(tmp_path):
    """The spatial loop's one 6D weld, all rows enforced: its smooth residual (rotations weighed by
    the tree's mean joint offset) brings every passive joint given 0.2 rad off back in 6 damped steps."""
    (tmp_path / "spatial_loop.closures.yaml").write_text(
        "platform_frame: platform\ntask: {position: [x]}\nworkspace: {actuators: {j1: [-0.3, 0.3]}}\n"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        mechanism = Mechanism.load(spatial_loop_mjcf(tmp_path))
    assert [len(c.rows) for c in mechanism.closures] == [6]
    guess = mechanism.home.copy()
    guess[mechanism.passive_ids] += 0.2
    home, report = _assembled(mechanism, guess)
    assert report.iterations == 6 and report.residual < 1e-12
    np.testing.assert_allclose(home, mechanism.home, rtol=0, atol=1e-12)
    assert sorted(name for name, _ in report.moved) == ["j2", "j3", "j4", "j5", "j6", "j7"]
    assert [move for _, move in report.moved] == pytest.approx([-0.2] * 6, abs=1e-12)


def test_a_slider_beyond_its_stroke_is_named(mechanism):
    """Velocity index 0 is the first slider, q11 (the universe joint has none)."""
    q = mechanism.home.copy()
    q[0] = 0.65
    assert limits_violated(mechanism.model, q, np.array([0])) == [("q11", 0.65, -0.6, 0.6)]
