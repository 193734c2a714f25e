"""m3t1r.model.closures: the closure system's Jacobian, the rank rule, row bookkeeping, assembly."""

from __future__ import annotations

import warnings

import numpy as np
import pinocchio as pin
import pytest
import yaml

from m3t1r.errors import ModelFileError, ModelWarning
from m3t1r.model.closures import (
    CLOSURE_TYPES,
    ROW_COUNT,
    ClosureSpec,
    ClosureSystem,
    _null_space,
    _rank,
    frame_support,
    relative_supports,
    without_rows,
)
from m3t1r.model.description import Mechanism, nominal_model_paths
from m3t1r.model.examples import rod_five_bar_files, spherical_wrist_files


@pytest.fixture(scope="module")
def wrist(tmp_path_factory):
    return Mechanism.load(*spherical_wrist_files(tmp_path_factory.mktemp("wrist")))


def test_jacobian_matches_differences_far_from_assembly(wrist):
    """Away from an assembly the 6D rows' relative placement is far from identity, where the
    Jlog6(aMb) Ad(aMb^-1) = Jlog6(bMa) factor on Pinocchio's velocity-level Jacobian matters."""
    system = ClosureSystem(wrist.model, wrist.closures)
    q = wrist.home + np.random.default_rng(0).normal(0.0, 0.4, wrist.model.nq)
    residual, jacobian = system.evaluate(q, True)
    assert np.abs(residual).max() > 0.1
    step = 1e-7
    for k in range(wrist.model.nv):
        dq = np.zeros(wrist.model.nv)
        dq[k] = step
        difference = (system.evaluate(q + dq, False)[0] - system.evaluate(q - dq, False)[0]) / (2 * step)
        np.testing.assert_allclose(jacobian[:, k], difference, atol=1e-7)


def _rod_five_bar(folder):
    """The rod five-bar, whose load notes (open limits, the rod's idle spin locked) are not what is
    tested here."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelWarning)
        return Mechanism.load(*rod_five_bar_files(folder))


@pytest.mark.parametrize("machine", ["m_machine", "wrist", "rod_five_bar"])
def test_row_operator_maps_the_relative_twist_to_the_jacobian(machine, wrist, tmp_path):
    """`sensitivity`'s operator, row by row, times the relative WORLD twist (J_b - J_a) of a closure's
    two frames is that closure's Jacobian, away from an assembly too: 3D closures (M machine), 6D
    welds held in some rows (wrist) and in all six (rod five-bar); every row of every closure with
    all_rows, in the closures' order."""
    mechanism = {
        "m_machine": lambda: Mechanism.load(),
        "wrist": lambda: wrist,
        "rod_five_bar": lambda: _rod_five_bar(tmp_path),
    }[machine]()
    q = mechanism.home + np.random.default_rng(4).normal(0.0, 0.2, mechanism.model.nq)
    for all_rows in (False, True):
        system = ClosureSystem(mechanism.model, mechanism.closures, all_rows=all_rows)
        residual, jacobian, operator = system.sensitivity(q)
        np.testing.assert_array_equal(residual, system.evaluate(q, False)[0])
        assert operator.shape == (system.n_rows, 6) == (len(residual), 6)
        start = 0
        for closure in mechanism.closures:
            frame_b, frame_a = (
                pin.getFrameJacobian(system.model, system.data, f, pin.WORLD)
                for f in (closure.frame_b_id, closure.frame_a_id)
            )
            count = ROW_COUNT[closure.type] if all_rows else len(closure.rows)
            rows = slice(start, start + count)
            np.testing.assert_allclose(operator[rows] @ (frame_b - frame_a), jacobian[rows], atol=1e-12)
            start = rows.stop
        assert start == system.n_rows


def test_every_closure_type_has_its_rows_models_and_operator():
    """The one table of closure types: 3D holds 3 rows (a point anchor), 6D six (a frame anchor);
    the operator of identical frames at the origin is [I, 0] for a point and the identity for a weld."""
    assert ROW_COUNT == {"3D": 3, "6D": 6}
    assert CLOSURE_TYPES["3D"].anchor is pin.PointAnchorConstraintModel
    assert CLOSURE_TYPES["6D"].contact == pin.ContactType.CONTACT_6D
    identity = np.eye(4)[None]
    np.testing.assert_allclose(CLOSURE_TYPES["3D"].operator(identity, identity)[0], np.eye(3, 6), atol=0)
    np.testing.assert_allclose(CLOSURE_TYPES["6D"].operator(identity, identity)[0], np.eye(6), atol=1e-15)


@pytest.mark.parametrize("machine", ["m_machine", "wrist", "rod_five_bar"])
def test_row_operators_of_many_configurations_at_once_are_each_one_s_operator(machine, wrist, tmp_path):
    """`operators` from the joint placements of N configurations (stacked as (N, njoints, 4, 4)) gives
    each configuration's `sensitivity` operator, 3D closures (M machine) and 6D welds (wrist, rod
    five-bar), away from an assembly; enforced rows and every row."""
    mechanism = {
        "m_machine": lambda: Mechanism.load(),
        "wrist": lambda: wrist,
        "rod_five_bar": lambda: _rod_five_bar(tmp_path),
    }[machine]()
    rng = np.random.default_rng(5)
    configurations = mechanism.home + rng.normal(0.0, 0.3, (3, mechanism.model.nq))
    for all_rows in (False, True):
        system = ClosureSystem(mechanism.model, mechanism.closures, all_rows=all_rows)
        expected, placements = [], []
        for q in configurations:
            expected.append(system.sensitivity(q)[2])
            placements.append([p.homogeneous for p in system.data.oMi.tolist()])
        batch = system.operators(np.array(placements))
        assert batch.shape == (3, system.n_rows, 6)
        np.testing.assert_allclose(batch, np.array(expected), rtol=0, atol=1e-12)


def test_row_operators_keep_the_stack_shape_of_the_placements():
    """Each type's operator on placements stacked (2, 3, 4, 4) is (2, 3, rows, 6), each block the
    operator of its one pair."""
    rng = np.random.default_rng(6)
    oMa, oMb = (
        np.array([pin.exp6(twist).homogeneous for twist in rng.normal(0, 1, (6, 6))]).reshape(2, 3, 4, 4)
        for _ in range(2)
    )
    for kind in CLOSURE_TYPES.values():
        stacked = kind.operator(oMa, oMb)
        assert stacked.shape == (2, 3, kind.rows, 6)
        for i in range(2):
            for k in range(3):
                np.testing.assert_allclose(
                    stacked[i, k], kind.operator(oMa[i, k][None], oMb[i, k][None])[0], rtol=0, atol=1e-12
                )


def test_relative_supports_are_one_signed_row_per_closure(wrist):
    """(closures, nv), each row support(frame b) - support(frame a); no closures: (0, nv)."""
    supports = relative_supports(wrist.model, wrist.closures)
    assert supports.shape == (len(wrist.closures), wrist.model.nv)
    for row, closure in zip(supports, wrist.closures):
        np.testing.assert_array_equal(
            row, frame_support(wrist.model, closure.frame_b_id) - frame_support(wrist.model, closure.frame_a_id)
        )
    assert set(np.unique(supports)) <= {-1.0, 0.0, 1.0} and np.abs(supports).sum() > 0
    assert relative_supports(wrist.model, ()).shape == (0, wrist.model.nv)


def test_a_system_given_a_data_evaluates_in_it(wrist):
    """`data=`: the system computes in the caller's Data (the solver shares its own), not a new one."""
    data = wrist.model.createData()
    system = ClosureSystem(wrist.model, wrist.closures, data=data)
    assert system.data is data
    q = wrist.home + 0.1
    system.evaluate(q, True)
    pin.forwardKinematics(wrist.model, reference := wrist.model.createData(), q)
    np.testing.assert_allclose(data.oMi[-1].homogeneous, reference.oMi[-1].homogeneous, atol=1e-12)


def test_assembly_from_a_configuration_that_is_not_finite_reports_an_infinite_residual(wrist):
    """A NaN joint value gives NaN rows: no step is taken and the worst row is reported as inf, never NaN."""
    system = ClosureSystem(wrist.model, wrist.closures)
    q = wrist.home.copy()
    q[0] = np.nan
    out, worst = system.assemble(q, np.arange(wrist.model.nv), 1e-9)
    assert worst == np.inf
    np.testing.assert_array_equal(out, q)


def test_rank_rule():
    assert _rank(np.zeros((0, 3))) == 0
    assert _rank(np.array([[2.0]])) == 1
    assert _rank(np.diag([1.0, 1e-11])) == 2  # well above 2 * eps * 1e3
    assert _rank(np.diag([1.0, 1e-14])) == 1  # below 2 * eps * 1e3 = 4.4e-13
    assert _rank(np.diag([1e-9, 1e-23])) == 1  # relative to the largest, not absolute
    assert _rank(np.diag([1e9, 1.0])) == 2
    null = _null_space(np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    assert null.shape == (3, 1)
    np.testing.assert_allclose(np.abs(null[:, 0]), [2**-0.5, 2**-0.5, 0.0], atol=1e-15)
    np.testing.assert_array_equal(_null_space(np.zeros((0, 2))), np.eye(2))
    np.testing.assert_allclose(np.abs(_null_space(np.array([[1.0, 0.0]]))), [[0.0], [1.0]], atol=1e-15)


def test_without_rows_counts_positions_across_closures():
    def spec(name: str, rows: tuple[int, ...]) -> ClosureSpec:
        return ClosureSpec(name, "6D", "a", "b", rows, 1, 2)

    closures = (spec("one", (0, 1, 5)), spec("two", (0, 1, 2)), spec("three", (3, 4)))
    kept = without_rows(closures, (1, 3, 7))  # one[1], two[0], three[4]
    assert [c.rows for c in kept] == [(0, 5), (1, 2), (3,)]
    assert [c.name for c in kept] == ["one", "two", "three"]


def test_a_home_that_overflows_is_refused_by_name(tmp_path):
    """Two sliders of one loop at +-1.7e308: the residual overflows to inf, and Newton cannot help."""
    source_urdf, source_closures = nominal_model_paths()
    urdf, closures = tmp_path / "m.urdf", tmp_path / "m.closures.yaml"
    urdf.write_bytes(source_urdf.read_bytes())
    document = yaml.safe_load(source_closures.read_text())
    document["home"].update(q11=1.7e308, q11_B2=-1.7e308)
    closures.write_text(yaml.safe_dump(document, sort_keys=False))
    with pytest.raises(ModelFileError) as caught:
        Mechanism.load(urdf, closures)
    assert str(caught.value) == (
        f"{closures}: home does not close: closure 'five_bar_I' residual inf > 1e-09, and "
        "Newton from the given values reached only inf; even with every joint free it reaches only inf from "
        "the given values: the closures may not all hold on this model (check each closure's type, 3D or 6D, its "
        "rows and frames, and that the model's joints are the mechanism's: a ball joint given as one revolute, "
        "say), or the given values are far from any assembly"
    )
