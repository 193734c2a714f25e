"""Measurement plans: which poses to measure for a calibration, in which order, and what to expect.

A plan is N joint-space configurations (slider sets of the M machine, or joint configurations of
a serial robot) chosen among K candidates drawn in the workspace so that the calibration's
information matrix M = sum_i A_i^T A_i has the largest determinant (D-optimality,
`m3t1r.pose_selection.select_poses`), A_i being candidate i's block of the whitened identification
Jacobian at the nominal model. It is then ordered for short travel between consecutive poses, and
its predicted accuracy is the standard deviation of the calibrated model's pose at workspace
poses that follows from M and the noise model alone:

    Cov(x_base) = M^-1 (whitened rows, so the noise variance is inside M),
    std_position(pose) = sqrt(trace(J_p Cov J_p^T)) [m],  std_rotation = sqrt(trace(J_r Cov J_r^T)) [rad],

with J_p (3 rows, m per unit parameter) and J_r (3 rows, rad) the pose sensitivities to the base
parameters; this is what `calibration.predicted_pose_std` reports after a calibration on the same
poses, up to the (second-order) difference between the nominal and the calibrated geometry. The
measurement frame and marker of a tracker add no base parameter: the first joint placements and
the platform (tool) frame already span them.

Travel: the drives move concurrently, so the time of a move is set by its longest joint stroke;
the distance between two configurations is the largest absolute joint difference (the L-infinity
norm, m or rad), and a plan's travel is the sum over its moves, starting from the home
configuration. Ordering is greedy nearest neighbour from home, then 2-opt (segment reversals)
until no reversal shortens the path; beyond `DENSE_ORDERING_MAX` poses, the nearest-neighbour path
alone, found with a k-d tree in O(n) memory instead of an n x n distance matrix.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, cast

import numpy as np
import pinocchio as pin
import scipy.linalg
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from m3t1r._threads import on_one_blas_thread
from m3t1r.calibration.identification import (
    REFERENCE_POSES,
    parameter_columns,
    select_base_parameters,
    unexcited_parameters,
)
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.pose_selection import (
    PoseSelection,
    closed_loop_candidate_blocks,
    reference_base,
    select_poses,
    serial_candidate_blocks,
)
from m3t1r.calibration.serial_simulation import sample_configurations
from m3t1r.errors import InvalidInputError
from m3t1r.metrics import PoseErrors
from m3t1r.model.description import Mechanism
from m3t1r.model.poe import SerialChain
from m3t1r.model.workspace import workspace_actuators

__all__ = [
    "MeasurementPlan",
    "PredictedAccuracy",
    "plan_closed_loop",
    "plan_serial",
    "order_for_travel",
    "path_travel",
    "predicted_accuracy",
    "predicted_accuracy_of_rows",
    "base_information",
    "DEFAULT_CANDIDATES_PER_POSE",
    "DEFAULT_EVALUATION_POSES",
]

#: Candidates drawn per planned pose when the caller does not say (K = 20 N).
DEFAULT_CANDIDATES_PER_POSE = 20
#: Workspace poses at which the predicted accuracy is evaluated.
DEFAULT_EVALUATION_POSES = 200


@dataclass(frozen=True)
class PredictedAccuracy:
    """Predicted standard deviation of the calibrated pose at `n` workspace poses (module docstring).

    std.position [m] and std.rotation [rad] per evaluation pose (rotation NaN for a position-only
    plan, whose data leaves the measured frame's own orientation unidentified).
    """

    std: PoseErrors

    @property
    def n(self) -> int:
        return int(self.std.position.size)


@dataclass(frozen=True)
class MeasurementPlan:
    """A measurement plan (module docstring).

    kind: "closed_loop" or "serial"; columns: joint names of `configurations`' columns (the M
    machine's actuated joints, or the serial chain's joints in order); configurations: (N, n) in
    measuring order [m for sliders and prismatic joints, rad for revolute joints];
    candidate_indices: each row's index among the candidates; n_candidates: K;
    selection: the D-optimal selection (indices sorted ascending, i.e. the selection order);
    log_det: log det of the plan's information matrix over the base columns, whitened rows
    [nepers]; start: the configuration the machine moves from (home); travel: the plan's travel in
    measuring order, travel_selection_order: the same rows in selection order [m or rad, L-inf];
    accuracy: the predicted accuracy over the workspace; noise: (position [m], rotation [rad]);
    column_units: "m" or "rad" per column.
    """

    kind: Literal["closed_loop", "serial"]
    columns: tuple[str, ...]
    configurations: np.ndarray
    candidate_indices: tuple[int, ...]
    n_candidates: int
    selection: PoseSelection = field(repr=False)
    log_det: float
    start: np.ndarray
    travel: float
    travel_selection_order: float
    accuracy: PredictedAccuracy
    position_only: bool
    noise: tuple[float, float]
    column_units: tuple[str, ...] = ()

    @property
    def n_poses(self) -> int:
        return int(self.configurations.shape[0])


# --------------------------------------------------------------------------------------------------
# Travel ordering


#: Up to this many poses the ordering uses a distance matrix (32 MB at 2000) and 2-opt; beyond, a
#: nearest-neighbour scan on a k-d tree, O(n) memory, without the 2-opt (each of its passes is n^2).
DENSE_ORDERING_MAX = 2000


def _distances(points: np.ndarray) -> np.ndarray:
    """(n, n) largest absolute coordinate difference between every two rows [m or rad]."""
    return np.max(np.abs(points[:, None, :] - points[None, :, :]), axis=2)


def path_travel(points: ArrayLike, start: ArrayLike | None = None) -> float:
    """Travel of visiting the rows of `points` (n, d) in order, from `start` (d,) if given: the sum of
    the largest joint stroke of each move [m or rad]."""
    rows = np.atleast_2d(np.asarray(points, dtype=float))
    if start is not None:
        rows = np.vstack((np.asarray(start, dtype=float).reshape(1, -1), rows))
    return float(np.sum(np.max(np.abs(np.diff(rows, axis=0)), axis=1))) if len(rows) > 1 else 0.0


def _nearest_neighbour(distance: np.ndarray) -> list[int]:
    """Greedy path over nodes 1..n-1 of a distance matrix, from node 0."""
    n = distance.shape[0]
    path, left = [0], np.ones(n, dtype=bool)
    left[0] = False
    for _ in range(n - 1):
        row = np.where(left, distance[path[-1]], np.inf)
        nxt = int(np.argmin(row))
        path.append(nxt)
        left[nxt] = False
    return path


def _two_opt(path: list[int], distance: np.ndarray, max_passes: int = 100) -> list[int]:
    """Reverse segments path[i..j] (i >= 1: the start stays first; the path is open) while one
    shortens it by more than 1e-12 relatively; first improvement per i, best j."""
    order = np.array(path)
    n = len(order)
    tolerance = 1e-12 * max(float(distance.max()), 1e-300)
    for _ in range(max_passes):
        improved = False
        for i in range(1, n - 1):
            j = np.arange(i + 1, n)
            before_i, at_i, at_j = order[i - 1], order[i], order[j]
            after_j = np.where(j + 1 < n, order[np.minimum(j + 1, n - 1)], -1)
            tail_old = np.where(after_j >= 0, distance[at_j, np.maximum(after_j, 0)], 0.0)
            tail_new = np.where(after_j >= 0, distance[at_i, np.maximum(after_j, 0)], 0.0)
            gain = distance[before_i, at_i] + tail_old - distance[before_i, at_j] - tail_new
            best = int(np.argmax(gain))
            if gain[best] > tolerance:
                order[i : j[best] + 1] = order[i : j[best] + 1][::-1].copy()
                improved = True
        if not improved:
            break
    return order.tolist()


_NEAR = 8  # neighbours of each row looked up at once by the large-set scan


class _UnvisitedTree:
    """A k-d tree (Chebyshev metric) over the rows of `nodes` not yet `visited`, rebuilt over the
    unvisited ones whenever half of its rows have been visited (so that a query widens little)."""

    def __init__(self, nodes: np.ndarray, visited: np.ndarray) -> None:
        self.nodes, self.visited = nodes, visited
        self._rebuild()

    def _rebuild(self) -> None:
        self.rows = np.flatnonzero(~self.visited)
        self.unvisited = len(self.rows)
        self.tree = cKDTree(self.nodes[self.rows]) if len(self.rows) else None

    def visit(self) -> None:
        """One more row (always one of this tree's: it was unvisited) is visited."""
        self.unvisited -= 1

    def nearest(self, point: np.ndarray) -> int:
        """The unvisited row nearest `point` (at least one must be left)."""
        if self.unvisited < len(self.rows) // 2:
            self._rebuild()
        width = _NEAR
        assert self.tree is not None, "built while rows are left"
        while True:
            _, found = self.tree.query(point, k=min(width, len(self.rows)), p=np.inf)
            rows = self.rows[np.atleast_1d(found)]
            free = rows[~self.visited[rows]]
            if free.size:
                return int(free[0])
            width *= 2  # every row this close is visited: look further


def _nearest_neighbour_scan(nodes: np.ndarray, progress: Callable[[int, int], None] | None = None) -> list[int]:
    """Greedy path over rows 1..n-1 of `nodes` from row 0, as `_nearest_neighbour` on their L-inf
    distances, without the matrix: each row's 8 nearest rows are looked up at once, and when all
    of them are visited the nearest unvisited row comes from a k-d tree of the unvisited rows. A
    query's rows come sorted by distance, so its first unvisited row is the nearest unvisited one.
    O(n) memory; `progress(done, total)` every 1000 rows."""
    n = len(nodes)
    visited = np.zeros(n, dtype=bool)
    _, near = cKDTree(nodes).query(nodes, k=min(_NEAR, n), p=np.inf)
    near = np.asarray(near).reshape(n, -1)
    visited[0] = True
    unvisited = _UnvisitedTree(nodes, visited)
    path, current = [0], 0
    for step in range(1, n):
        row = near[current]
        free = row[~visited[row]]
        current = int(free[0]) if free.size else unvisited.nearest(nodes[current])
        visited[current] = True
        unvisited.visit()
        path.append(current)
        if progress is not None and (step % 1000 == 0 or step == n - 1):
            progress(step, n - 1)
    return path


def order_for_travel(
    points: ArrayLike, start: ArrayLike | None = None, progress: Callable[[int, int], None] | None = None
) -> np.ndarray:
    """A visiting order (indices into the rows of `points` (n, d)) with short travel from `start`
    (d,) (default: from the first row): greedy nearest neighbour, then 2-opt (module docstring);
    beyond `DENSE_ORDERING_MAX` rows the nearest-neighbour path alone, found in O(n) memory.
    `progress(done, total)`: rows placed so far, called by the large-set scan after each."""
    rows = np.atleast_2d(np.asarray(points, dtype=float))
    if rows.shape[0] == 0 or not np.all(np.isfinite(rows)):
        raise InvalidInputError(f"order_for_travel: expected finite points (n >= 1, d), got shape {rows.shape}")
    origin = rows[0] if start is None else np.asarray(start, dtype=float).reshape(-1)
    nodes = np.vstack((origin[None, :], rows))
    if len(nodes) > DENSE_ORDERING_MAX:
        path = _nearest_neighbour_scan(nodes, progress)
    else:
        distance = _distances(nodes)
        path = _two_opt(_nearest_neighbour(distance), distance)
    return np.array(path[1:], dtype=int) - 1


# --------------------------------------------------------------------------------------------------
# Predicted accuracy


def base_information(blocks: np.ndarray, indices: ArrayLike, columns: ArrayLike) -> np.ndarray:
    """M = sum_{i in indices} A_i^T A_i over the given parameter columns (whitened blocks (K, r, P))."""
    chosen = np.asarray(blocks, dtype=float)[np.asarray(indices, dtype=int)][:, :, np.asarray(columns, dtype=int)]
    stacked = chosen.reshape(-1, chosen.shape[2])
    return stacked.T @ stacked


def predicted_accuracy(
    information: np.ndarray, sensitivities: np.ndarray, position_only: bool = False
) -> PredictedAccuracy:
    """Pose std at evaluation poses from an information matrix (m, m) over base parameters and the
    un-whitened pose sensitivities (n, 6, m) to them (position [m], then orientation [rad] rows).

    The covariance M^-1 is formed with M scaled to a unit diagonal (its entries mix m and rad
    units over many decades). Rotation is NaN when `position_only`. Forming M squares the
    condition number of the rows: `predicted_accuracy_of_rows` avoids that where the rows are at hand.
    """
    scale = 1.0 / np.sqrt(np.diag(information))
    try:
        factor = np.linalg.cholesky(information * scale[:, None] * scale[None, :])
    except np.linalg.LinAlgError:
        raise InvalidInputError("the plan does not identify every base parameter: add poses or candidates") from None
    # J Cov J^T = (J S L^-T)(J S L^-T)^T with Cov = S (L L^T)^-1 S.
    return _accuracy(factor, scale, sensitivities, position_only)


def predicted_accuracy_of_rows(
    rows: np.ndarray, sensitivities: np.ndarray, position_only: bool = False
) -> PredictedAccuracy:
    """`predicted_accuracy` of the information M = A^T A of whitened rows A (k, m), from the
    triangular factor of A itself: M = R^T R without forming M, so base parameters that the rows
    identify only weakly (R's diagonal down to 1e-8 of its largest, as the identifiability rule
    allows) do not make a singular M in floating point."""
    norms = np.linalg.norm(rows, axis=0)
    triangular = cast(np.ndarray, np.linalg.qr(rows / np.where(norms > 0.0, norms, 1.0), mode="r"))
    if not (np.all(norms > 0.0) and np.all(np.abs(np.diag(triangular)) > 0.0)):
        raise InvalidInputError("the plan does not identify every base parameter: add poses or candidates")
    scale = 1.0 / norms
    return _accuracy(triangular.T, scale, sensitivities, position_only)


def _accuracy(
    lower: np.ndarray, scale: np.ndarray, sensitivities: np.ndarray, position_only: bool
) -> PredictedAccuracy:
    """Pose std from L (m, m) lower triangular with L L^T = S M S, S = diag(scale)."""
    rows = np.asarray(sensitivities, dtype=float) * scale
    flat = scipy.linalg.solve_triangular(lower, rows.reshape(-1, rows.shape[2]).T, lower=True).T.reshape(rows.shape)
    variance = np.sum(flat**2, axis=2)  # (n, 6) per row
    position = np.sqrt(variance[:, :3].sum(axis=1))
    rotation = np.full(len(position), np.nan) if position_only else np.sqrt(variance[:, 3:].sum(axis=1))
    return PredictedAccuracy(PoseErrors(position, rotation))


def _unwhitened(blocks: np.ndarray, noise: tuple[float, float]) -> np.ndarray:
    """Pose sensitivity rows of full 6-row whitened blocks, back in m and rad."""
    return blocks * np.r_[np.full(3, noise[0]), np.full(3, noise[1])][None, :, None]


# --------------------------------------------------------------------------------------------------
# Plans


@dataclass(frozen=True)
class _Candidates:
    configurations: np.ndarray  # (K, n)
    blocks: np.ndarray  # (K, rows, P) whitened
    evaluation: np.ndarray  # (E, 6, P) un-whitened sensitivities at the evaluation poses
    names: tuple[str, ...]  # the P parameter names


def _plan(
    kind: Literal["closed_loop", "serial"],
    columns: tuple[str, ...],
    candidates: _Candidates,
    n_poses: int,
    start: np.ndarray,
    position_only: bool,
    noise: tuple[float, float],
    units: tuple[str, ...],
    base_columns: tuple[int, ...] | None = None,
) -> MeasurementPlan:
    """Select, order and assess a plan from prepared candidates (over `base_columns`, default the
    candidates' own base parameters)."""
    selection = select_poses(candidates.blocks, n_poses, columns=base_columns)
    if not math.isfinite(selection.log_det):
        raise InvalidInputError(_shortfall(candidates, selection, n_poses, base_columns is not None))
    chosen = np.array(selection.indices, dtype=int)
    order = order_for_travel(candidates.configurations[chosen], start)
    rows = candidates.blocks[chosen][:, :, list(selection.columns)].reshape(-1, len(selection.columns))
    accuracy = predicted_accuracy_of_rows(rows, candidates.evaluation[:, :, list(selection.columns)], position_only)
    # log det M = 2 sum log |R_ii| (A = QR): finite wherever the accuracy is, unlike slogdet of M.
    log_det = 2.0 * float(np.sum(np.log(np.abs(np.diag(cast(np.ndarray, np.linalg.qr(rows, mode="r")))))))
    ordered = candidates.configurations[chosen[order]]
    return MeasurementPlan(
        kind=kind,
        columns=columns,
        configurations=ordered,
        candidate_indices=tuple(int(i) for i in chosen[order]),
        n_candidates=len(candidates.configurations),
        selection=selection,
        log_det=log_det,
        start=np.asarray(start, dtype=float),
        travel=path_travel(ordered, start),
        travel_selection_order=path_travel(candidates.configurations[chosen], start),
        accuracy=accuracy,
        position_only=position_only,
        noise=noise,
        column_units=units,
    )


def _shortfall(candidates: _Candidates, selection: PoseSelection, n_poses: int, reference: bool) -> str:
    """Why the selected poses cannot identify the base parameters (the candidates', or with
    `reference` those of calibrate's reference pose set): which parameters they leave unexcited,
    and how many poses give as many rows as parameters."""
    rows = candidates.blocks.shape[1]
    identifiable = len(selection.columns)
    source = (
        f"the {REFERENCE_POSES} reference poses calibrate judges by"
        if reference
        else f"the {len(candidates.configurations)} candidates"
    )
    head = f"{n_poses} poses cannot identify the {identifiable} parameters that {source} identify"
    chosen = candidates.blocks[list(selection.indices)].reshape(-1, candidates.blocks.shape[2])
    columns = list(selection.columns)
    kept = select_base_parameters(chosen[:, columns], [candidates.names[c] for c in columns], max_condition=math.inf)
    weak = unexcited_parameters(chosen, candidates.names, columns, max(identifiable - kept.rank, 1))
    listed = f"{', '.join(weak[:8])}{' ...' if len(weak) > 8 else ''}"
    if reference and n_poses * rows >= identifiable:
        return (
            f"{head}: they leave {listed} unexcited, parameters barely identifiable on any poses (the "
            "reference poses and the candidates disagree on them), so more poses are unlikely to help: a "
            f"larger workspace box may; or hold them at nominal in the plan and the calibration alike "
            f"(plan --fix {' '.join(weak)}, then calibrate --fix {' '.join(weak)})"
        )
    counts = f"{n_poses} give {n_poses * rows} rows for {identifiable} parameters"
    return f"{head}: they leave {listed} unexcited; plan more poses ({counts})"


def _check_counts(n_poses: int, n_candidates: int | None) -> int:
    if n_poses < 1:
        raise InvalidInputError(f"plan: the number of poses must be >= 1, got {n_poses}")
    k = DEFAULT_CANDIDATES_PER_POSE * n_poses if n_candidates is None else int(n_candidates)
    if k < n_poses:
        raise InvalidInputError(f"plan: {k} candidates cannot give {n_poses} distinct poses")
    return k


@on_one_blas_thread
def plan_closed_loop(
    mechanism: Mechanism,
    n_poses: int,
    rng: np.random.Generator,
    *,
    n_candidates: int | None = None,
    noise: TrackerNoise | None = None,
    position_only: bool = False,
    n_evaluation: int = DEFAULT_EVALUATION_POSES,
    fixed: Sequence[str] = (),
) -> MeasurementPlan:
    """A plan of `n_poses` actuator sets [m or rad] for a closed-loop mechanism (module docstring).

    Candidates (default 20 n_poses) and evaluation poses are drawn uniformly in the design's
    workspace box and mapped to sliders by the nominal IK from home (`workspace_actuators`), so
    every one is within the slider limits and assembles on the home branch. noise: the tracker
    noise the calibration will assume (default `TrackerNoise()`, as `m3t1r calibrate`). fixed:
    parameter (`q12.dt[3]`) or placement (`q12`) names the calibration will hold at nominal
    (`CalibrationOptions.fixed`, `calibrate --fix`): the plan identifies the others, and its
    predicted accuracy takes the held ones as known.
    """
    k = _check_counts(n_poses, n_candidates)
    noise = noise or TrackerNoise()
    sliders = workspace_actuators(mechanism, k, rng)
    blocks, names = closed_loop_candidate_blocks(mechanism, sliders, noise, position_only=position_only)
    held = _held_at_nominal(blocks, names, fixed)
    evaluation, _ = closed_loop_candidate_blocks(mechanism, workspace_actuators(mechanism, n_evaluation, rng), noise)
    scales = (noise.position, noise.rotation)
    candidates = _Candidates(sliders, blocks, _unwhitened(evaluation, scales), names)
    home = mechanism.home[[mechanism.model.idx_qs[mechanism.model.getJointId(n)] for n in mechanism.actuated_joints]]
    units = mechanism.joint_units()
    base = _reference_columns(mechanism, blocks, noise, position_only, held)
    return _plan(
        "closed_loop", mechanism.actuated_joints, candidates, n_poses, home, position_only, scales, units, base
    )


def _held_at_nominal(blocks: np.ndarray, names: Sequence[str], fixed: Sequence[str]) -> list[int]:
    """The columns `fixed` names (as `CalibrationOptions.fixed` does), zeroed in the candidate blocks
    (K, rows, P) in place: no pose is chosen to identify them, and no base parameter includes them."""
    columns = parameter_columns(names, fixed, "fixed parameter")
    blocks[:, :, columns] = 0.0
    return columns


def _reference_columns(
    mechanism: Mechanism, blocks: np.ndarray, noise: TrackerNoise, position_only: bool, fixed: Sequence[int] = ()
) -> tuple[int, ...] | None:
    """The base parameters a plan must identify: those calibrate judges by (`reference_base`, the
    `fixed` columns held) where the candidates identify another number (a direction barely above the
    rank tolerance on one pose set and below it on the other: a leg's rod joints), so that plan and
    calibrate ask the same of the poses; None (the candidates' own choice) otherwise."""
    stacked = blocks.reshape(-1, blocks.shape[2])
    names = [f"p{k}" for k in range(blocks.shape[2])]
    candidates = select_base_parameters(stacked, names, max_condition=math.inf)

    def reference_rows(actuators: np.ndarray) -> np.ndarray:
        rows, _ = closed_loop_candidate_blocks(mechanism, actuators, noise, position_only=position_only)
        return rows.reshape(-1, rows.shape[2])

    reference = reference_base(mechanism, reference_rows, names, fixed=fixed)
    return reference.indices if reference.rank != candidates.rank else None


@on_one_blas_thread
def plan_serial(
    model: pin.Model,
    chain: SerialChain,
    n_poses: int,
    rng: np.random.Generator,
    *,
    n_candidates: int | None = None,
    noise: TrackerNoise | None = None,
    position_only: bool = False,
    n_evaluation: int = DEFAULT_EVALUATION_POSES,
) -> MeasurementPlan:
    """A plan of `n_poses` joint configurations [rad or m] of a serial chain (module docstring).

    Candidates and evaluation configurations are uniform within the joint limits shrunk by 5 % on
    each side (`serial.sample_configurations`); the robot starts from its neutral configuration.
    noise: the tracker noise the calibration will assume (default `TrackerNoise()`: 10 um, 20 urad,
    as `m3t1r calibrate --serial`).
    """
    k = _check_counts(n_poses, n_candidates)
    noise = noise or TrackerNoise()
    configurations = sample_configurations(model, chain, k, rng)
    blocks, names = serial_candidate_blocks(model, chain, configurations, noise, position_only=position_only)
    evaluation, _ = serial_candidate_blocks(model, chain, sample_configurations(model, chain, n_evaluation, rng), noise)
    scales = (noise.position, noise.rotation)
    candidates = _Candidates(configurations, blocks, _unwhitened(evaluation, scales), names)
    start = chain.chain_configuration(pin.neutral(model))
    units = tuple("rad" if np.any(twist[3:]) else "m" for twist in chain.twists)
    return _plan("serial", chain.joint_names, candidates, n_poses, start, position_only, scales, units)
