"""Loop closures of a tree model: the one definition of their rows and Jacobian (Pinocchio's
constraint models), and what `Mechanism.load` does with them before any solver exists: assemble an
approximate home, and find redundant (gauge) passive joints and dependent closure rows.

Residual of a closure between frames a and b (both placements in the base frame):
- "3D": R_a^T (p_b - p_a) [m] (Pinocchio's PointAnchorConstraint error);
- "6D": log6(oMa^-1 oMb) = [v; w] [m, rad] (FrameAnchorConstraint error).

Everything that depends on a closure's type is in `CLOSURE_TYPES` (rows, Pinocchio models, the exact
Jacobian, the row operator, the smooth rows of load-time assembly): a new type is a new entry there,
and in the compiled loop's `evaluate_closures` (`_native_core.hpp`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Literal, overload

import numpy as np
import pinocchio as pin
import scipy.linalg

from m3t1r.model.rotations import skew

__all__ = [
    "CLOSURE_TYPES",
    "ClosureSpec",
    "ClosureSystem",
    "ClosureType",
    "Redundancy",
    "ROW_COUNT",
    "ASSEMBLY_MAX_CHANGE",
    "without_rows",
    "closure_rank",
    "relative_supports",
    "frame_support",
]

ASSEMBLY_MAX_CHANGE = 0.1  # [rad or m] the most any joint may move when a home is assembled at load
_ASSEMBLY_ITERATIONS = 50

SmoothRows = tuple[list[np.ndarray], list[np.ndarray]]


@dataclass(frozen=True)
class ClosureType:
    """What a closure of one type is, for every part of m3t1r that reads closures.

    rows: residual components; anchor: the Pinocchio constraint model whose position error is the
    residual; contact: its rigid constraint type (`constraint_models`); exact: maps the model's
    velocity-level Jacobian block to the residual's exact derivative (None: it already is);
    operator(oMa, oMb): the residual's derivative (..., rows, 6) along the relative WORLD twist
    xi_b - xi_a, for stacks of closures of the type at once (placements (..., 4, 4));
    smooth(oMa, oMb, J_a, J_b, length): rows without branch cuts with the same zeros, and their
    Jacobian from LOCAL_WORLD_ALIGNED frame Jacobians (load-time assembly from a rough home).
    """

    rows: int
    anchor: Any
    contact: Any
    exact: Callable[[np.ndarray, Any], np.ndarray] | None
    operator: Callable[[np.ndarray, np.ndarray], np.ndarray]
    smooth: Callable[[pin.SE3, pin.SE3, np.ndarray, np.ndarray, float], SmoothRows]


def _point_operator(oMa: np.ndarray, oMb: np.ndarray) -> np.ndarray:
    """d[R_a^T (p_b - p_a)] = R_a^T [I, -[p_b]x] (relative spatial twist of b with respect to a),
    for every pair of placements (..., 4, 4) at once: (..., 3, 6)."""
    rotation_t = np.swapaxes(oMa[..., :3, :3], -1, -2)
    return np.concatenate((rotation_t, -rotation_t @ skew(oMb[..., :3, 3])), axis=-1)


def _frame_operator(oMa: np.ndarray, oMb: np.ndarray) -> np.ndarray:
    """d log6(aMb) = Jlog6(aMb) Ad(oMb^-1) (relative spatial twist), for every pair of placements
    (..., 4, 4): (..., 6, 6)."""
    pairs = zip(oMa.reshape(-1, 4, 4), oMb.reshape(-1, 4, 4))
    blocks = [pin.Jlog6(a.actInv(b)) @ b.inverse().action for a, b in ((pin.SE3(a), pin.SE3(b)) for a, b in pairs)]
    return np.array(blocks).reshape(oMa.shape[:-2] + (6, 6))


def _frame_exact(block: np.ndarray, cdata: Any) -> np.ndarray:
    """The constraint model's 6D Jacobian is the relative twist of b in a's frame (a left perturbation
    of aMb); the exact one is Jlog6(aMb) Ad(aMb^-1) = Jlog6(bMa) times it, since
    log6(exp(x) M) = -log6(M^-1 exp(-x))."""
    return pin.Jlog6(cdata.c1Mc2.inverse()).dot(block)


def _point_smooth(oMa: pin.SE3, oMb: pin.SE3, ja: np.ndarray, jb: np.ndarray, length: float) -> SmoothRows:
    """p_b - p_a in the base frame [m]."""
    return [oMb.translation - oMa.translation], [jb[:3] - ja[:3]]


def _frame_smooth(oMa: pin.SE3, oMb: pin.SE3, ja: np.ndarray, jb: np.ndarray, length: float) -> SmoothRows:
    """p_b - p_a, then length * (R_b - R_a) column by column (a unit of rotation weighs `length` m)."""
    rows, jacobians = _point_smooth(oMa, oMb, ja, jb, length)
    for k in range(3):  # column k of R: d r = w x r = -[r] w
        ra, rb = oMa.rotation[:, k], oMb.rotation[:, k]
        rows.append(length * (rb - ra))
        jacobians.append(length * (-pin.skew(rb) @ jb[3:] + pin.skew(ra) @ ja[3:]))
    return rows, jacobians


CLOSURE_TYPES: dict[str, ClosureType] = {
    "3D": ClosureType(
        3, pin.PointAnchorConstraintModel, pin.ContactType.CONTACT_3D, None, _point_operator, _point_smooth
    ),
    "6D": ClosureType(
        6, pin.FrameAnchorConstraintModel, pin.ContactType.CONTACT_6D, _frame_exact, _frame_operator, _frame_smooth
    ),
}
ROW_COUNT = {name: kind.rows for name, kind in CLOSURE_TYPES.items()}


@dataclass(frozen=True)
class ClosureSpec:
    """One loop closure between two frames of the tree.

    type "3D": the frame origins coincide; residual R_a^T (p_b - p_a), in frame_a's axes [m].
    type "6D": the frames coincide; residual log6(oMa^-1 oMb) = [v; w] in frame_a [m, rad].
    `rows` are the residual components enforced (indices into those 3 or 6 components).
    """

    name: str
    type: Literal["3D", "6D"]
    frame_a: str
    frame_b: str
    rows: tuple[int, ...]
    frame_a_id: int
    frame_b_id: int


@dataclass(frozen=True)
class Redundancy:
    """Passive joints and closure rows that a square closure system must leave out.

    locked: velocity indices of passive joints whose motion the others already span (a gauge, e.g. a
    cut joint modelled as two coaxial hinges); they keep their home value. dropped: indices into the
    enforced rows that depend on the others (e.g. out-of-plane rows of a planar weld).
    """

    locked: tuple[int, ...]
    dropped: tuple[int, ...]
    rank: int


@dataclass(frozen=True, eq=False)
class _ClosuresOfAType:
    """The closures of one type in a `ClosureSystem`: the type's operator, their rows (all of them),
    and their two frames as parent joints and placements in them (a, b), as their constraint models
    place them."""

    operator: Callable[[np.ndarray, np.ndarray], np.ndarray]
    rows: np.ndarray
    joints_a: np.ndarray
    placements_a: np.ndarray
    joints_b: np.ndarray
    placements_b: np.ndarray


class ClosureSystem:
    """Residual and Jacobian of the enforced rows of some closures of `model` (its own `Data`): the one
    definition of a closure's rows that every solve, batch, sensitivity and load-time check reads.

    Pinocchio's constraint models evaluate the rows (one `calc` per closure, one stacked Jacobian):
    measured against a hand-written stacked operator and a numpy batch, they are several times faster
    per pose and within about 1.3x of the numpy batch over 1,000 poses (docs/design.md, "How it works").
    `all_rows=True` enforces every row of every closure (rank analysis, `closure_residual(all_rows)`);
    `data`: a `Data` of `model` to share with another system (default: its own).
    """

    def __init__(
        self, model: pin.Model, closures: tuple[ClosureSpec, ...], all_rows: bool = False, data: pin.Data | None = None
    ) -> None:
        if all_rows:
            closures = tuple(replace(c, rows=tuple(range(ROW_COUNT[c.type]))) for c in closures)
        self.model, self.data = model, model.createData() if data is None else data
        self.constraints, self.constraint_data = pin.StdVec_ConstraintModel(), pin.StdVec_ConstraintData()
        for spec in closures:
            fa, fb = model.frames[spec.frame_a_id], model.frames[spec.frame_b_id]
            anchor = CLOSURE_TYPES[spec.type].anchor
            constraint = anchor(model, fa.parentJoint, fa.placement, fb.parentJoint, fb.placement)
            self.constraints.append(constraint)
            self.constraint_data.append(constraint.createData())
        self.pairs = [(self.constraints[i], self.constraint_data[i]) for i in range(len(self.constraints))]
        inner = [self.constraint_data[i].extract() for i in range(len(self.constraint_data))]
        self.errors = [d.constraint_position_error for d in inner]  # live views, refreshed by `calc`
        slots = np.concatenate(([0], np.cumsum([CLOSURE_TYPES[c.type].rows for c in closures]))).astype(int)
        kinds = [CLOSURE_TYPES[c.type] for c in closures]
        # Where the constraint model's Jacobian is not the residual's exact derivative (6D: by Jlog6).
        self._corrections = [
            (int(slots[i]), int(slots[i + 1]), kind.exact, d)
            for i, (kind, d) in enumerate(zip(kinds, inner))
            if kind.exact
        ]
        # Per type: its row operator, its closures' rows (all of them), and each closure's two frames as
        # (parent joint, placement in it), from which `operators` places them.
        self._by_type: list[_ClosuresOfAType] = []
        for kind in CLOSURE_TYPES.values():
            mine = [i for i in range(len(closures)) if kinds[i] is kind]
            if not mine:
                continue
            a, b = ([model.frames[getattr(closures[i], side)] for i in mine] for side in ("frame_a_id", "frame_b_id"))
            self._by_type.append(
                _ClosuresOfAType(
                    kind.operator,
                    np.concatenate([slots[i] + np.arange(kind.rows) for i in mine]),
                    np.array([f.parentJoint for f in a], dtype=int),
                    np.array([f.placement.homogeneous for f in a]),
                    np.array([f.parentJoint for f in b], dtype=int),
                    np.array([f.placement.homogeneous for f in b]),
                )
            )
        self.enforced = np.concatenate(
            [slots[i] + np.array(c.rows, dtype=int) for i, c in enumerate(closures)] + [np.zeros(0, dtype=int)]
        )
        self.n_rows, self.n_full = len(self.enforced), int(slots[-1])

    @overload
    def evaluate(self, q: np.ndarray, with_jacobian: Literal[True]) -> tuple[np.ndarray, np.ndarray]: ...
    @overload
    def evaluate(self, q: np.ndarray, with_jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]: ...
    def evaluate(self, q: np.ndarray, with_jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Enforced rows at q and, optionally, their exact Jacobian (rows x nv): the constraint models'
        Jacobian, made exact where a type says how (`ClosureType.exact`). Leaves `data` at q (joint
        placements, and the WORLD joint Jacobian `data.J` when with_jacobian)."""
        model, data = self.model, self.data
        if with_jacobian:
            pin.computeJointJacobians(model, data, q)
        else:
            pin.forwardKinematics(model, data, q)
        for constraint, cdata in self.pairs:
            constraint.calc(model, data, cdata)
        # `take` and `dot`, not fancy indexing and `@`: a fraction of their overhead at these sizes.
        residual = np.concatenate(self.errors).take(self.enforced)
        if not with_jacobian:
            return residual, None
        jac = pin.getConstraintsJacobian(model, data, self.constraints, self.constraint_data)
        for start, end, exact, cdata in self._corrections:
            jac[start:end] = exact(jac[start:end], cdata)
        return residual, jac.take(self.enforced, axis=0)

    def sensitivity(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(residual, Jacobian wrt q, row operator (rows x 6)) of the enforced rows at q.

        Row r of closure c changes by operator[r] @ (xi_b - xi_a) for spatial (WORLD) twists xi of its
        two frames, [v; w] at the base origin (`ClosureType.operator`: R_a^T [I, -[p_b]x] for a 3D
        closure, Jlog6(aMb) Ad(oMb^-1) for a 6D one). That is how geometric-parameter sensitivities
        enter (calibration).
        Leaves `data` at q with every frame placed (`data.oMf`) and the WORLD joint Jacobian.
        """
        residual, jac = self.evaluate(q, True)
        pin.updateFramePlacements(self.model, self.data)
        joints = np.array([placement.homogeneous for placement in self.data.oMi.tolist()])
        return residual, jac, self.operators(joints[None])[0]

    def operators(self, joint_placements: np.ndarray) -> np.ndarray:
        """The row operators of `sensitivity` (N, rows, 6) at N configurations at once, from their joint
        placements oMi (N, njoints, 4, 4): each closure frame placed as oMi[parent joint] placement,
        as its constraint model places it."""
        n = len(joint_placements)
        full = np.empty((n, self.n_full, 6))
        for group in self._by_type:
            oMa = joint_placements[:, group.joints_a] @ group.placements_a
            oMb = joint_placements[:, group.joints_b] @ group.placements_b
            full[:, group.rows] = group.operator(oMa, oMb).reshape(n, -1, 6)
        return full[:, self.enforced]

    def assemble(self, q: np.ndarray, free: np.ndarray, tolerance: float) -> tuple[np.ndarray, float]:
        """Least-squares Gauss-Newton on the enforced rows over the columns `free` from q.

        Minimum-norm steps (lstsq) so that a gauge joint does not drift. Returns (q, max |row|); the
        caller judges whether that is closed.
        """
        q = q.copy()
        residual, jac = self.evaluate(q, True)
        for _ in range(_ASSEMBLY_ITERATIONS):
            if not np.all(np.isfinite(residual)) or float(np.abs(residual).max(initial=0.0)) <= tolerance:
                break
            q[free] -= np.linalg.lstsq(jac[:, free], residual, rcond=None)[0]
            residual, jac = self.evaluate(q, True)
        worst = float(np.abs(residual).max(initial=0.0)) if np.all(np.isfinite(residual)) else float("inf")
        return q, worst

    def free_motion(self, q: np.ndarray, passive: np.ndarray, frame_id: int) -> float:
        """Largest speed [m/s or rad/s] of frame `frame_id` along the unit null-space directions of the
        passive closure Jacobian at q (sliders fixed): zero for a gauge (the redundant joints move
        nothing but themselves), not zero when the closures leave the frame free to move."""
        _, jac = self.evaluate(q, True)
        null = _null_space(jac[:, passive])
        frame = pin.getFrameJacobian(self.model, self.data, frame_id, pin.LOCAL_WORLD_ALIGNED)[:, passive]
        return float(np.abs(frame @ null).max(initial=0.0))

    def redundancy(self, q: np.ndarray, passive: np.ndarray) -> tuple[Redundancy, int]:
        """Gauge joints and dependent rows at an assembled q, and the rank of the rows over every column.

        Ranks count singular values above max(shape) * eps * 1e3 times the largest (rounding level of
        an exact closure Jacobian); the choice of which joint to lock and which row to drop follows
        LAPACK's column-pivoted QR (the first independent columns and rows are kept).
        """
        _, jac = self.evaluate(q, True)
        square = jac[:, passive]
        rank = _rank(square)
        locked: tuple[int, ...] = ()
        dropped: tuple[int, ...] = ()
        if rank < square.shape[1]:
            keep = _pivots(square, rank)
            locked = tuple(int(passive[c]) for c in range(square.shape[1]) if c not in keep)
        if rank < square.shape[0]:
            keep = _pivots(square.T, rank)
            dropped = tuple(r for r in range(square.shape[0]) if r not in keep)
        return Redundancy(locked, dropped, rank), _rank(jac)


def frame_support(model: pin.Model, frame_id: int) -> np.ndarray:
    """(nv,) mask of the joints that move frame `frame_id` (1.0) and those that do not (0.0)."""
    mask = np.zeros(model.nv)
    for j in model.supports[model.frames[frame_id].parentJoint][1:]:
        mask[model.idx_vs[j]] = 1.0
    return mask


def relative_supports(model: pin.Model, closures: tuple[ClosureSpec, ...]) -> np.ndarray:
    """(closures, nv) signed column masks support(frame b) - support(frame a): +1 for a joint that moves
    frame b and not frame a, -1 for the reverse, 0 for a joint that moves both or neither."""
    rows = [frame_support(model, c.frame_b_id) - frame_support(model, c.frame_a_id) for c in closures]
    return np.array(rows).reshape(-1, model.nv)


def closure_rank(matrix: np.ndarray) -> int:
    """Rank of a closure Jacobian under the rule every load-time decision uses (`_rank`)."""
    return _rank(matrix)


def closure_null_space(matrix: np.ndarray) -> np.ndarray:
    """Orthonormal basis (columns) of a closure Jacobian's right null space, under the same rule."""
    return _null_space(matrix)


def _rank(matrix: np.ndarray) -> int:
    """Singular values above max(shape) * eps * 1e3 times the largest (one rule for rank and null space)."""
    if matrix.size == 0:
        return 0
    singular = np.linalg.svd(matrix, compute_uv=False)
    return int(np.sum(singular > max(matrix.shape) * np.finfo(float).eps * 1e3 * singular[0]))


def _null_space(matrix: np.ndarray) -> np.ndarray:
    """Orthonormal basis (columns) of the right null space, under `_rank`'s rule."""
    if matrix.shape[0] == 0:
        return np.eye(matrix.shape[1])
    vt = np.linalg.svd(matrix)[2]
    return vt[_rank(matrix) :].T


def _pivots(matrix: np.ndarray, count: int) -> set[int]:
    """Columns chosen first by column-pivoted QR."""
    return set(int(c) for c in scipy.linalg.qr(matrix, pivoting=True, mode="r")[1][:count])


def without_rows(closures: tuple[ClosureSpec, ...], dropped: tuple[int, ...]) -> tuple[ClosureSpec, ...]:
    """The closures with the enforced rows at positions `dropped` (in enforced order) removed."""
    out, position = [], 0
    for spec in closures:
        kept = tuple(r for k, r in enumerate(spec.rows) if position + k not in dropped)
        position += len(spec.rows)
        out.append(replace(spec, rows=kept))
    return tuple(out)
