"""D-optimal pose selection: optimality on small problems, invariances, robot block builders."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from m3t1r.calibration.pose_selection import (
    closed_loop_candidate_blocks,
    information_log_det,
    observability_index,
    select_poses,
    serial_candidate_blocks,
)
from m3t1r.errors import IdentificationError, InvalidInputError


def synthetic_blocks(n_candidates: int, rows: int, n_parameters: int, seed: int) -> np.ndarray:
    """Candidates of uneven information (some poses excite some parameters much more)."""
    rng = np.random.default_rng(seed)
    strength = rng.uniform(0.2, 3.0, (n_candidates, 1, n_parameters))
    return rng.normal(size=(n_candidates, rows, n_parameters)) * strength * rng.uniform(1e-3, 1e3, n_parameters)


def brute_force_best(blocks: np.ndarray, n_poses: int) -> tuple[tuple[int, ...], float]:
    best, best_value = (), -math.inf
    for subset in itertools.combinations(range(len(blocks)), n_poses):
        value = information_log_det(blocks, subset)
        if value > best_value:
            best, best_value = subset, value
    return best, best_value


@pytest.mark.parametrize("seed, rows, n_parameters, n_poses", [(0, 2, 4, 3), (1, 1, 3, 4), (2, 3, 5, 2), (3, 2, 5, 4)])
def test_greedy_plus_exchange_reaches_the_brute_force_optimum(seed, rows, n_parameters, n_poses) -> None:
    blocks = synthetic_blocks(13, rows, n_parameters, seed)
    best, best_value = brute_force_best(blocks, n_poses)
    selection = select_poses(blocks, n_poses)
    assert selection.indices == best
    # The reported value is on unit-RMS columns: a constant offset from the raw log det.
    offset = 2.0 * np.sum(np.log(selection.column_scale))
    assert selection.log_det == pytest.approx(best_value + offset, abs=1e-8)


def test_selected_set_beats_random_sets() -> None:
    blocks = synthetic_blocks(300, 6, 20, seed=4)
    selection = select_poses(blocks, 10)
    rng = np.random.default_rng(5)
    random_values = [information_log_det(blocks, rng.choice(300, 10, replace=False)) for _ in range(200)]
    assert information_log_det(blocks, selection.indices) > max(random_values)
    assert len(selection.indices) == len(set(selection.indices)) == 10


def test_exchange_improves_a_poor_start_and_history_never_decreases() -> None:
    blocks = synthetic_blocks(80, 3, 8, seed=6)
    start = list(range(6))
    started = select_poses(blocks, 6, initial=start)
    assert started.log_det > information_log_det(blocks, start) + 2 * np.sum(np.log(started.column_scale))
    assert started.n_exchanges > 0
    assert np.all(np.diff(started.history) > 0)
    greedy = select_poses(blocks, 6)
    assert np.all(np.diff(greedy.history[6:]) > 0)  # the exchange phase only accepts improvements


def test_choice_does_not_depend_on_parameter_units() -> None:
    blocks = synthetic_blocks(60, 2, 6, seed=7)
    rescaled = blocks * np.array([1e3, 1.0, 1e-3, 1.0, 7.0, 1.0])  # e.g. m -> mm on some columns
    a, b = select_poses(blocks, 8), select_poses(rescaled, 8)
    assert a.indices == b.indices
    assert a.log_det == pytest.approx(b.log_det, rel=1e-10)
    assert a.observability_index == pytest.approx(b.observability_index, rel=1e-10)


def test_observability_index_and_log_det_agree_with_their_definitions() -> None:
    blocks = synthetic_blocks(40, 3, 5, seed=8)
    selection = select_poses(blocks, 7)
    stacked = (blocks[list(selection.indices)][:, :, list(selection.columns)] * selection.column_scale).reshape(-1, 5)
    singular = np.linalg.svd(stacked, compute_uv=False)
    assert selection.observability_index == pytest.approx(np.prod(singular) ** (1 / 5) / math.sqrt(7), rel=1e-10)
    assert observability_index(stacked, 7) == pytest.approx(selection.observability_index, rel=1e-12)
    assert selection.log_det == pytest.approx(np.linalg.slogdet(stacked.T @ stacked)[1], rel=1e-10)
    assert selection.condition_number == pytest.approx(singular[0] / singular[-1], rel=1e-10)


def test_redundant_parameters_are_judged_on_the_base_columns() -> None:
    blocks = synthetic_blocks(50, 2, 4, seed=9)
    redundant = np.concatenate([blocks, blocks[:, :, [0]] - blocks[:, :, [2]], np.zeros((50, 2, 1))], axis=2)
    selection = select_poses(redundant, 5)
    assert len(selection.columns) == 4 and np.isfinite(selection.log_det)
    assert selection.indices == select_poses(blocks, 5).indices


def test_too_few_rows_report_a_rank_deficient_set() -> None:
    blocks = synthetic_blocks(20, 1, 6, seed=10)
    selection = select_poses(blocks, 3)  # 3 rows for 6 parameters
    assert selection.log_det == -math.inf and selection.observability_index == 0.0
    assert len(selection.indices) == 3


def test_invalid_inputs() -> None:
    blocks = synthetic_blocks(10, 2, 3, seed=11)
    with pytest.raises(InvalidInputError):
        select_poses(blocks, 0)
    with pytest.raises(InvalidInputError):
        select_poses(blocks, 11)
    with pytest.raises(InvalidInputError):
        select_poses(blocks, 3, initial=[0, 0, 1])
    with pytest.raises(InvalidInputError):
        select_poses(blocks, 3, columns=[0, 5])
    bad = blocks.copy()
    bad[4, 0, 0] = np.nan
    with pytest.raises(InvalidInputError, match="candidate 4"):
        select_poses(bad, 3)
    with pytest.raises(IdentificationError):
        select_poses(np.zeros((3, 2)), 1)  # nothing is identifiable


def test_serial_blocks_selection_beats_random() -> None:
    from m3t1r.calibration.serial_robots import example_tool_frame, load_example_robot
    from m3t1r.calibration.serial_simulation import sample_configurations
    from m3t1r.model.poe import SerialChain

    model = load_example_robot("ur5")
    chain = SerialChain.from_model(model, example_tool_frame("ur5"))
    q = sample_configurations(model, chain, 200, np.random.default_rng(12))
    blocks, names = serial_candidate_blocks(model, chain, q)
    assert blocks.shape == (200, 6, chain.n_parameters) and len(names) == chain.n_parameters
    selection = select_poses(blocks, 8)
    rng = np.random.default_rng(13)
    random_values = [
        information_log_det(blocks[:, :, list(selection.columns)], rng.choice(200, 8, replace=False)) for _ in range(50)
    ]
    assert information_log_det(blocks[:, :, list(selection.columns)], selection.indices) > max(random_values)


def test_closed_loop_blocks_match_the_calibration_jacobian(mechanism) -> None:
    from m3t1r.calibration.closed_loop import ClosedLoopProblem
    from m3t1r.calibration.error_model import ClosedLoopErrorModel
    from m3t1r.calibration.measurements import TrackerNoise, measure
    from m3t1r.calibration.pipeline import CalibrationOptions
    from m3t1r.model.workspace import workspace_actuators

    actuators = workspace_actuators(mechanism, 40, np.random.default_rng(14))
    noise = TrackerNoise()
    error_model = ClosedLoopErrorModel(mechanism)
    blocks, names = closed_loop_candidate_blocks(mechanism, actuators, noise, error_model=error_model)
    assert blocks.shape == (40, 6, error_model.n_parameters) and names == error_model.names
    # At exact measurements on the nominal machine these are the calibration's whitened rows.
    measurements = measure(mechanism, actuators)
    problem = ClosedLoopProblem(
        error_model, measurements, np.arange(error_model.n_parameters), CalibrationOptions(noise)
    )
    state = problem.assemble(mechanism.model, None)
    _, jacobian = problem.evaluate(state, problem.columns)
    np.testing.assert_allclose(blocks.reshape(-1, error_model.n_parameters), jacobian, atol=1e-6 * np.abs(blocks).max())
    # 56 base parameters at the nominal geometry (docs/design.md); 20 poses identify them.
    selection = select_poses(blocks, 20)
    assert np.isfinite(selection.log_det) and len(selection.columns) == 56
    rng = np.random.default_rng(15)
    kept = blocks[:, :, list(selection.columns)]
    assert information_log_det(kept, selection.indices) > max(
        information_log_det(kept, rng.choice(40, 20, replace=False)) for _ in range(20)
    )
