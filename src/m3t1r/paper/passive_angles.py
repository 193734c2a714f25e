"""The paper's passive angles (section 4): the lower crank q_i3 of each chain computed from the
other readings through |A1 A2| = a by the Newton recursion of eq. (22)-(30), to save two sensors,
and two well-posed alternatives (the platform weld, the sliders' closure solve).

The J^-1 of eq. (29)-(30) is 1 x 2: it can only be a pseudo-inverse, and the recursion is then
ill-posed (`estimate_lower_crank_angles`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r._threads import on_one_blas_thread
from m3t1r.errors import InvalidInputError, ModelFileError, NotConvergedError
from m3t1r.model.description import ClosureSpec, Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.paper.chains import PaperChain, _as_configurations, paper_chains

__all__ = ["CrankMethod", "LowerCrankEstimate", "estimate_lower_crank_angles"]

#: How the lower-crank angles q_i3 are obtained (see `estimate_lower_crank_angles`).
CrankMethod = Literal["distance", "platform", "sliders"]


@dataclass(frozen=True)
class LowerCrankEstimate:
    """Estimated lower-crank angles q_i3 of both chains.

    joints: the two lower cranks (q13, q23), by identity from `paper_chains`.
    angles: (N, 2) rad, in `joints` order.
    method: see `estimate_lower_crank_angles`.
    iterations: (N,) Newton iterations per pose.
    residual: (N,) final constraint residual: | a - |A1 A2| | (m) for "distance", the largest
        platform-weld row (m or rad) for "platform", the largest closure row for "sliders".
    """

    joints: tuple[str, str]
    angles: np.ndarray
    method: CrankMethod
    iterations: np.ndarray
    residual: np.ndarray
    idx_q: tuple[int, int] = field(repr=False)

    def apply(self, configurations: np.ndarray) -> np.ndarray:
        """A copy of configurations (N, nq) with the lower cranks replaced by the estimate."""
        out = np.array(configurations, dtype=float)
        out[:, list(self.idx_q)] = self.angles
        return out


def _joint_index(model: pin.Model, name: str) -> tuple[int, int]:
    """(idx_q, idx_v) of a one-DoF joint."""
    j = model.getJointId(name)
    return model.idx_qs[j], model.idx_vs[j]


def _platform_weld(mechanism: Mechanism, chains: Sequence[PaperChain]) -> tuple[ClosureSpec, slice]:
    """The 6D closure between the two chains' tool frames and its slice of the enforced rows."""
    tools = {chain.tool_frame for chain in chains}
    offset = 0
    for spec in mechanism.closures:
        if spec.type == "6D" and {spec.frame_a, spec.frame_b} == tools:
            return spec, slice(offset, offset + len(spec.rows))
        offset += len(spec.rows)
    raise ModelFileError(mechanism.closures_path, f"no 6D closure welds the chains' tool frames {sorted(tools)}")


def _foot_distance_newton(
    model: pin.Model,
    data: pin.Data,
    q: np.ndarray,
    cranks: Sequence[tuple[int, int]],
    feet: Sequence[int],
    distance: float,
    tolerance: float,
    max_iterations: int,
) -> tuple[int, float]:
    """Eq. (25)-(30) on one configuration q (modified in place): q_3 <- q_3 + J^+ dd.

    J (1 x 2) = [-u . dP_1/dq_13, u . dP_2/dq_23] with u the unit vector A1 -> A2 and dP_i/dq_i3
    (eq. 28) the velocity of foot A_i per unit crank rate, i.e. the crank's column of the foot
    frame's LOCAL_WORLD_ALIGNED Jacobian. J^+ = J^T / (J J^T).
    """
    (q1, v1), (q2, v2) = cranks
    error = math.inf
    for iteration in range(max_iterations + 1):
        pin.computeJointJacobians(model, data, q)
        a1, a2 = data.oMi[feet[0]].translation, data.oMi[feet[1]].translation
        gap = a2 - a1
        length = float(np.linalg.norm(gap))
        error = distance - length  # dd of eq. (25)
        if abs(error) <= tolerance:
            return iteration, abs(error)
        if iteration == max_iterations:
            break
        u = gap / length
        dp1 = pin.getJointJacobian(model, data, feet[0], pin.LOCAL_WORLD_ALIGNED)[:3, v1]
        dp2 = pin.getJointJacobian(model, data, feet[1], pin.LOCAL_WORLD_ALIGNED)[:3, v2]
        row = np.array([-(u @ dp1), u @ dp2])
        q[[q1, q2]] += row * (error / (row @ row))
    raise NotConvergedError("the foot-distance recursion of eq. (30) did not converge", abs(error), max_iterations)


def _platform_newton(
    solver: ClosedLoopSolver,
    rows: slice,
    q: np.ndarray,
    cranks: Sequence[tuple[int, int]],
    tolerance: float,
    max_iterations: int,
) -> tuple[int, float]:
    """Gauss-Newton on the platform weld P_I = P_II (its enforced rows) over the two cranks."""
    columns = [v for _, v in cranks]
    indices = [i for i, _ in cranks]
    residual = np.full(1, math.inf)
    for iteration in range(max_iterations + 1):
        full, jacobian, _ = solver.closure_sensitivity(q)
        residual = full[rows]
        step = np.linalg.lstsq(jacobian[rows][:, columns], residual, rcond=None)[0]
        q[indices] -= step
        if float(np.max(np.abs(step))) <= tolerance:
            return iteration + 1, float(np.max(np.abs(solver.closure_residual(q)[rows])))
    raise NotConvergedError(
        "the platform-weld Gauss-Newton did not converge", float(np.max(np.abs(residual))), max_iterations
    )


@on_one_blas_thread
def estimate_lower_crank_angles(
    mechanism: Mechanism,
    readings: ArrayLike | Mapping[str, ArrayLike],
    *,
    method: CrankMethod = "distance",
    model: pin.Model | None = None,
    initial: ArrayLike | None = None,
    foot_distance: float | None = None,
    tolerance: float = 1e-13,
    max_iterations: int = 50,
) -> LowerCrankEstimate:
    """Compute the lower-crank angles q_13, q_23 (the paper's q_i3) instead of reading them.

    method:
    - "distance", the paper's section 4: the feet A_1, A_2 (eq. 22-24, from every other reading
      and the chain model) must be `foot_distance` = a apart (eq. 25-26); Newton's recursion
      q <- q + J^-1 dd (eq. 29-30) from `initial`. This is one equation in two unknowns, so J is
      1 x 2 and its "inverse" can only be the pseudo-inverse J^T / (J J^T), the minimum-norm
      update. The recursion then converges to *a* point of the solution curve {|A1 A2| = a},
      to first order the one nearest to the initial guess, not to the true angles: the component
      of the initial error along the curve survives. On this machine the curve's tangent is both
      cranks turning the same way: the feet shift sideways together and one rises as the other
      drops, which leaves |A1 A2| unchanged to first order. So that part of the platform's x and
      z comes from the initial guess, not from the readings. The missing information is in the
      other rows of the platform closure: the feet must stay at the same height.
    - "platform", well posed from the same readings: Gauss-Newton on the platform weld
      P_I(q_13) = P_II(q_23) over its enforced rows (x, y, z, yaw; four equations in two
      unknowns). Exact on a machine that matches `model`.
    - "sliders", the full closure solve: the closed-loop forward kinematics of `mechanism` at
      the slider readings gives every passive joint (`model` is not used). Needs no passive
      reading at all, but only as good as the mechanism model's closures: on a real machine
      described by its nominal model it inherits the nominal geometry's errors.

    In this machine's chains the lower crank's coupling joint q_i3_pa is read too, and the
    parallelogram makes q_i3 = beta - q_i3_pa on the nominal machine; the paper's chain has no
    such joint, and "distance" does not use it (A_i lies on its axis).

    readings: (N, nq) configurations (or {joint: (N,)}); the lower-crank entries are ignored.
    model: chain model for "distance" and "platform" (default: the mechanism's).
    initial: (2,) or (N, 2) starting angles (rad) for "distance" and "platform"; default: the
        lower cranks of `mechanism.home`.
    foot_distance: a (m); default |A_1 A_2| of the mechanism model at its home.
    tolerance: "distance" stops when |dd| <= tolerance (m), "platform" when the step is
        <= tolerance (rad): its four rows need not vanish on a machine that differs from `model`.
    Raises NotConvergedError (or, for "sliders", the closed-loop solver's KinematicsError).
    """
    if method not in ("distance", "platform", "sliders"):
        raise InvalidInputError(f"method must be 'distance', 'platform' or 'sliders', got {method!r}")
    chains = paper_chains(mechanism)
    model = mechanism.model if model is None else model
    q_all = _as_configurations(mechanism, readings)
    n_poses = q_all.shape[0]
    joints = (chains[0].lower_crank, chains[1].lower_crank)
    cranks = [_joint_index(model, name) for name in joints]
    idx_q = (cranks[0][0], cranks[1][0])
    start = mechanism.home[list(idx_q)] if initial is None else np.asarray(initial, dtype=float)
    if start.shape not in ((2,), (1, 2), (n_poses, 2)) or not np.all(np.isfinite(start)):
        raise InvalidInputError(f"initial: expected 2 or ({n_poses}, 2) finite angles")
    start = np.broadcast_to(start, (n_poses, 2))
    angles = np.empty((n_poses, 2))
    iterations = np.zeros(n_poses, dtype=int)
    residual = np.empty(n_poses)
    if method == "distance":
        data = model.createData()
        feet = [model.getJointId(chain.lower_coupling) for chain in chains]
        if foot_distance is None:
            pin.forwardKinematics(model, data, mechanism.home)
            foot_distance = float(np.linalg.norm(data.oMi[feet[1]].translation - data.oMi[feet[0]].translation))
        for k in range(n_poses):
            q = q_all[k].copy()
            q[list(idx_q)] = start[k]
            iterations[k], residual[k] = _foot_distance_newton(
                model, data, q, cranks, feet, foot_distance, tolerance, max_iterations
            )
            angles[k] = q[list(idx_q)]
    elif method == "platform":
        _, rows = _platform_weld(mechanism, chains)
        solver = ClosedLoopSolver(mechanism.with_model(model))
        for k in range(n_poses):
            q = q_all[k].copy()
            q[list(idx_q)] = start[k]
            iterations[k], residual[k] = _platform_newton(solver, rows, q, cranks, tolerance, max_iterations)
            angles[k] = q[list(idx_q)]
    else:
        solver = ClosedLoopSolver(mechanism)
        for k in range(n_poses):
            result = solver.forward(q_all[k, mechanism.actuated_ids], q_init=mechanism.home)
            angles[k] = result.q[list(idx_q)]
            iterations[k], residual[k] = result.iterations, result.residual
    return LowerCrankEstimate(joints, angles, method, iterations, residual, idx_q)
