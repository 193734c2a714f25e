"""The closed-loop error model: placement parameters and the platform pose's sensitivity to them.

Parameters: a right-multiplied 6-vector error dt = [v; w] on every joint placement of the tree
and on every frame a closure or the measurement uses (paper eq. 33: T(0) <- T(0) exp6(dt)). With
the sliders fixed, the passive joints follow the closures, so the sensitivity of the measured
platform pose to the parameters is found by implicit differentiation:

    r_c(q, p) = 0  =>  dq_passive/dp = -J_c,passive^-1 dr_c/dp        (16 x 16 square system)
    d xi_P / dp    = X_P + J_P,passive dq_passive/dp                  (spatial twist, WORLD)

where X_f (6 x P) is the spatial twist of frame f per unit parameter: Pinocchio's WORLD kinematic
regressor for the joint placements (paper eq. 17 columns, Ad(g_{0,k-1} T_{k-1,k}(0))), and
Ad(oMf) for the frame's own placement; a closure's rows see operator @ (X_b - X_a).

"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import Placement, adjoint_matrices, frames_moved_by_frame_error, perturb

__all__ = ["ClosedLoopErrorModel", "PlatformSensitivities", "has_own_placement"]


def has_own_placement(model: pin.Model, frame_id: int) -> bool:
    """Whether a frame has a placement of its own to identify: a frame on a fixed joint (or an
    operational frame), not a JOINT frame nor the frame of a link hanging from a moving joint.

    Those two coincide with their joint's frame by definition (a URDF cannot give a link frame an
    offset from its joint), so an error there is the joint's own placement error, or the
    measurement setup's marker for a measured link.
    """
    frame = model.frames[frame_id]
    if frame.type == pin.FrameType.JOINT:
        return False
    # A BODY frame right under a JOINT frame is a link on a moving joint (under a FIXED_JOINT frame
    # it is a fixed link, whose fixed joint carries the placement).
    return not (frame.type == pin.FrameType.BODY and model.frames[frame.parentFrame].type == pin.FrameType.JOINT)


class ClosedLoopErrorModel:
    """The placement parameters of a mechanism and the platform pose's sensitivity to them.

    placements: every joint of the tree (model order), then every closure frame and the platform
    frame (each once, those with a placement of their own: `has_own_placement`). Parameter k of
    placement i is named f"{name}.dt[{k}]", [v; w] order.
    """

    def __init__(self, mechanism: Mechanism, placements: tuple[Placement, ...] | None = None) -> None:
        model = mechanism.model
        if placements is None:
            joints = tuple(Placement.joint(model.names[j]) for j in range(1, model.njoints))
            frame_ids: list[int] = []
            for spec in mechanism.closures:
                frame_ids += [spec.frame_a_id, spec.frame_b_id]
            frame_ids.append(mechanism.platform_frame_id)
            frames = tuple(
                Placement.frame(model.frames[i].name) for i in dict.fromkeys(frame_ids) if has_own_placement(model, i)
            )
            placements = joints + frames
        self.mechanism = mechanism
        self.placements = placements
        self.names = tuple(n for p in placements for n in p.parameter_names())
        self.n_parameters = len(self.names)
        # Joint parameters: regressor column c (6 per joint, model order) -> parameter column.
        self._joint_columns = np.full(6 * (model.njoints - 1), -1)
        self._frame_block: dict[int, int] = {}
        for i, placement in enumerate(placements):
            if placement.kind == "joint":
                j = model.getJointId(placement.name)
                self._joint_columns[6 * (j - 1) : 6 * j] = np.arange(6 * i, 6 * i + 6)
            else:
                self._frame_block[model.getFrameId(placement.name)] = 6 * i
        self._joint_targets = np.flatnonzero(self._joint_columns >= 0)

        def support(frame_id: int) -> np.ndarray:
            mask = np.zeros(model.njoints - 1)
            mask[np.array(model.supports[model.frames[frame_id].parentJoint][1:], dtype=int) - 1] = 1.0
            return np.repeat(mask, 6)

        # Every frame's regressor is one matrix G (per-joint blocks Ad(oMi[parent] jointPlacement),
        # WORLD) masked by the frame's support; a closure sees the signed mask support(b) - support(a).
        self._closure_frames = [(spec.frame_a_id, spec.frame_b_id, len(spec.rows)) for spec in mechanism.closures]
        self._row_masks = np.vstack(
            [np.tile(support(fb) - support(fa), (count, 1)) for fa, fb, count in self._closure_frames]
        )
        self._platform = mechanism.platform_frame_id
        self._platform_mask = support(self._platform)
        # Rows seeing frame parameters: a frame error moves its anchor and everything rigidly attached
        # to it (`frames_moved_by_frame_error`, as `perturb` applies it) by the spatial twist
        # Ad(oM_anchor) dt: (rows, adjoint slot per row, parameter columns per row, sign) for the
        # frame_b and the frame_a side of every closure whose frame moves.
        self._own_frame_ids = sorted(self._frame_block)
        moved = [frames_moved_by_frame_error(model, f) for f in self._own_frame_ids]
        self._own_terms = []
        for side, sign in ((1, 1.0), (0, -1.0)):
            rows, slots, columns = [], [], []
            row = 0
            for frames_and_count in self._closure_frames:
                frame_id, count = frames_and_count[side], frames_and_count[2]
                for slot, (owner, (_, family)) in enumerate(zip(self._own_frame_ids, moved)):
                    if frame_id in family:
                        block = self._frame_block[owner]
                        for r in range(row, row + count):
                            rows.append(r)
                            slots.append(slot)
                            columns.append(np.arange(block, block + 6))
                row += count
            if rows:
                self._own_terms.append((np.array(rows), np.array(slots), np.array(columns), sign))
        # The platform frame moves with its own parameters and with any frame's it is attached to.
        self._platform_terms = tuple(
            (self._frame_block[owner], slot)
            for slot, (owner, (_, family)) in enumerate(zip(self._own_frame_ids, moved))
            if self._platform in family
        )
        # Batched sensitivities: the parent of each joint (G's blocks are Ad(oMi[parent] jointPlacement)),
        # the platform's support per velocity column, and the frames whose own adjoints are needed.
        self._parents = np.array(model.parents[1:], dtype=int)
        self._platform_v_mask = np.zeros(model.nv)
        for j in model.supports[model.frames[self._platform].parentJoint][1:]:
            self._platform_v_mask[model.idx_vs[j]] = 1.0
        self._adjoint_frames = [anchor for anchor, _ in moved] + [self._platform]
        self._adjoint_joints = np.array([model.frames[f].parentJoint for f in self._adjoint_frames], dtype=int)
        self._plans: dict[bytes, _ColumnPlan] = {}

    def deltas(self, vector: np.ndarray) -> dict[Placement, np.ndarray]:
        """{placement: dt} for a full parameter vector (placements with a zero error omitted)."""
        blocks = np.asarray(vector, dtype=float).reshape(-1, 6)
        return {p: b for p, b in zip(self.placements, blocks) if np.any(b)}

    def perturbed(self, model: pin.Model, vector: np.ndarray) -> pin.Model:
        """A copy of `model` with the parameter vector applied (eq. 33)."""
        return perturb(model, self.deltas(vector))

    def joint_twist_matrices(self, model: pin.Model, joints: np.ndarray) -> np.ndarray:
        """G (N, 6, 6 n_joints): spatial twist (WORLD) per unit joint-placement error (eq. 17), from
        the joint placements oMi (N, njoints, 4, 4): block j = Ad(oMi[parent(j)] jointPlacements[j]),
        the columns of Pinocchio's WORLD kinematic regressor."""
        placements = np.array([placement.homogeneous for placement in model.jointPlacements.tolist()[1:]])
        blocks = adjoint_matrices(joints[:, self._parents] @ placements)  # (N, n_joints, 6, 6)
        return blocks.transpose(0, 2, 1, 3).reshape(len(joints), 6, 6 * len(placements))  # also for no pose

    def platform_sensitivities(
        self, solver: ClosedLoopSolver, configurations, columns: np.ndarray | None = None
    ) -> PlatformSensitivities:
        """Platform poses at N assembled configurations, d xi_P / dp (spatial twists in WORLD) and
        dq_passive / dp at each, for the parameter `columns` (default all).

        Sliders held fixed; the passive joints move with the parameters through the closures.
        Only the Pinocchio passes run per pose; the closures' row operators and the algebra (eq. 17
        blocks Ad(oMi[parent] jointPlacement), closure rows, the implicit passive solve) run on
        stacks, restricted to the requested columns. d xi_P / dp = X_P - (J_P,pas J_c,pas^-1) dr_c/dp:
        the passive solve has 6 right-hand sides, not P. Leaves solver.data at the last configuration.
        """
        model, data = solver.model, solver.data
        n = len(configurations)
        jac_q = np.empty((n, solver.n_rows, model.nv))
        joint_jacobian = np.empty((n, 6, model.nv))
        joints = np.empty((n, model.njoints, 4, 4))
        for i, q in enumerate(configurations):
            jac_q[i] = solver.closure_jacobian(q)  # leaves data.J and data.oMi at q
            joint_jacobian[i] = data.J
            joints[i] = [placement.homogeneous for placement in data.oMi.tolist()]
        operator = solver.closure_operators(joints)  # `closure_sensitivity`'s, for every pose at once
        pin.updateFramePlacements(model, data)  # data left as `closure_sensitivity` leaves it, frames placed
        # oMf = oMi[parent] frame.placement, not data.oMf: Pinocchio never updates oMf[0], the universe
        # frame, which anchors an error of the base frame (it stays at identity when the base moves).
        placements = np.array([model.frames[f].placement.homogeneous for f in self._adjoint_frames])
        frames = joints[:, self._adjoint_joints] @ placements
        plan = self._column_plan(np.arange(self.n_parameters) if columns is None else np.asarray(columns, dtype=int))
        G = self.joint_twist_matrices(model, joints)[:, :, plan.g_columns]
        adjoints = adjoint_matrices(frames)
        dr_dp = np.zeros((n, solver.n_rows, plan.size))
        dr_dp[:, :, plan.joint_slots] = (operator @ G) * plan.row_masks
        # Own placement errors of the closure frames: row r of a closure sees +Ad(oMb) and -Ad(oMa).
        for rows, slots, sign, pick, row_index, slot_index in plan.own_terms:
            values = np.einsum("nrk,nrkj->nrj", operator[:, rows], adjoints[:, slots])[:, pick]
            dr_dp[:, row_index, slot_index] += sign * values
        xi = np.zeros((n, 6, plan.size))
        xi[:, :, plan.joint_slots] = G * plan.platform_mask
        for slots, components, adjoint in plan.platform_terms:
            xi[:, :, slots] += adjoints[:, adjoint][:, :, components]
        square = jac_q[:, :, solver.passive]
        platform_jacobian = (joint_jacobian * self._platform_v_mask)[:, :, solver.passive]  # WORLD frame Jacobian
        through_passive = np.swapaxes(
            np.linalg.solve(np.swapaxes(square, 1, 2), np.swapaxes(platform_jacobian, 1, 2)), 1, 2
        )
        return PlatformSensitivities(frames[:, -1], xi - through_passive @ dr_dp, square, dr_dp)

    def _column_plan(self, columns: np.ndarray) -> _ColumnPlan:
        key = columns.tobytes()
        if key not in self._plans:
            self._plans[key] = _ColumnPlan.build(self, columns)
        return self._plans[key]


@dataclass(frozen=True, eq=False)
class PlatformSensitivities:
    """Platform sensitivities at N assembled configurations, over P parameter columns.

    poses: platform frames (N, 4, 4) in the base frame; twist_jacobians: d xi_P / dp (N, 6, P),
    spatial twists in WORLD; passive_jacobians: J_c,passive (N, n_pas, n_pas); closure_jacobians:
    dr_c / dp (N, n_pas, P) at fixed joints (so that dq_passive / dp = -J_c,passive^-1 dr_c/dp, the
    module docstring's implicit differentiation).
    """

    poses: np.ndarray
    twist_jacobians: np.ndarray
    passive_jacobians: np.ndarray
    closure_jacobians: np.ndarray


@dataclass(frozen=True, eq=False)
class _ColumnPlan:
    """Where each requested parameter column comes from in `platform_sensitivities`."""

    size: int
    joint_slots: np.ndarray  # output columns that are joint-placement parameters
    g_columns: np.ndarray  # their columns in G
    row_masks: np.ndarray  # (n_rows, len(joint_slots)) signed closure supports
    platform_mask: np.ndarray  # (len(joint_slots),) platform support
    own_terms: tuple  # (rows, slots, sign, pick (R, 6) mask, row index, output slot) per closure side
    platform_terms: tuple  # (output columns, twist components, adjoint slot) per frame parameter moving the platform

    @staticmethod
    def build(model: ClosedLoopErrorModel, columns: np.ndarray) -> _ColumnPlan:
        slot_of = np.full(model.n_parameters, -1)
        slot_of[columns] = np.arange(len(columns))
        g_column_of = np.full(model.n_parameters, -1)
        g_column_of[model._joint_columns[model._joint_targets]] = model._joint_targets
        joint_slots = np.flatnonzero(g_column_of[columns] >= 0)
        g_columns = g_column_of[columns[joint_slots]]
        own_terms = []
        for rows, slots, blocks, sign in model._own_terms:
            pick = slot_of[blocks] >= 0  # (R, 6)
            if pick.any():
                row_index = np.broadcast_to(rows[:, None], blocks.shape)[pick]
                own_terms.append((rows, slots, sign, pick, row_index, slot_of[blocks][pick]))
        platform_terms = []
        for block, adjoint in model._platform_terms:
            wanted = slot_of[block : block + 6] >= 0
            if wanted.any():
                platform_terms.append((slot_of[block : block + 6][wanted], np.flatnonzero(wanted), adjoint))
        return _ColumnPlan(
            len(columns),
            joint_slots,
            g_columns,
            model._row_masks[:, g_columns],
            model._platform_mask[g_columns],
            tuple(own_terms),
            tuple(platform_terms),
        )
