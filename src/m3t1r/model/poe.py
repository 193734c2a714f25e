"""Local product-of-exponentials (POE) view of a Pinocchio model.

Zhang et al. (Symmetry 2020), section 2, write a serial chain as (eq. 4-6)

    g(q) = T_{B,1}(0) exp(s_1 q_1) T_{1,2}(0) exp(s_2 q_2) ... T_{n-1,n}(0) exp(s_n q_n) T_{n,P}(0)

with every kinematic error lumped into the constant initial poses T(0) (section 3.1). That is
exactly how Pinocchio stores a kinematic tree: `model.jointPlacements[j]` is T_{parent(j),j}(0)
expressed in the parent joint frame, each 1-DoF joint moves by exp6(S_j q_j) with its constant
motion subspace S_j, and a frame placement (relative to its parent joint) is the tool pose T_{n,P}(0).
So this module needs no second kinematic description: a `Placement` names one T(0) of the model,
`perturb` applies the paper's error model T(0) <- T(0) exp6(dt) (eq. 33/34) to a copy, and the error
Jacobian of eq. (17)-(20) is a list of adjoint matrices along the chain.

Batches of configurations are evaluated in numpy, all poses at once: the joint motions exp6(S q) in
closed form (Rodrigues), then one stacked 4 x 4 product per chain link (`placement_poses`). Pinocchio
objects are kept for single poses and for the model itself (`poe_forward`, `perturb`).

Conventions (Pinocchio's): SE3 objects, twists and Jacobian rows in [linear; angular] order, SI units
(m, rad). WORLD means the chain's base frame {B} (Pinocchio's world frame when no base frame is given).
Arrays of poses are homogeneous matrices (..., 4, 4), as `pin.SE3.homogeneous`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from m3t1r.errors import InvalidInputError, UnknownNameError, UnsupportedJointError, require_finite_vector
from m3t1r.model.rotations import jlog3_batch, log3_batch, skew  # re-exported: calibration imports them from here

__all__ = [
    "frames_moved_by_frame_error",
    "Placement",
    "SerialChain",
    "adjoint_matrices",
    "forward_and_error_jacobians",
    "jlog3_batch",
    "log3_batch",
    "perturb",
    "placement_of",
    "placement_poses",
    "poe_forward",
    "skew",
    "tool_poses",
]

_TWIST_COMPONENTS = 6


@dataclass(frozen=True)
class Placement:
    """One constant initial pose T(0) of the model that can carry a kinematic error.

    kind="joint": `model.jointPlacements[model.getJointId(name)]`, the pose of joint `name` in its
    parent joint frame at q = 0 (T_{k-1,k}(0) of eq. 6).
    kind="frame": the placement of frame `name` in its parent joint frame (e.g. the tool T_{n,P}(0)).
    A URDF fixed link gives two frames with the same placement: a FIXED_JOINT frame named after the
    URDF joint and a BODY frame named after the link. Both names denote the same physical placement
    and `perturb` applies the error to the FIXED_JOINT frame (the fixed joint carries the link), then
    carries everything rigidly attached below it. JOINT frames are not placements: use kind="joint".

    Identity is by exact name; ids are resolved against a model only when the placement is used.
    """

    kind: Literal["joint", "frame"]
    name: str

    def __post_init__(self) -> None:
        if self.kind not in ("joint", "frame"):
            raise InvalidInputError(f"Placement kind must be 'joint' or 'frame', got {self.kind!r}")
        if not isinstance(self.name, str) or not self.name:
            raise InvalidInputError(f"Placement name must be a non-empty string, got {self.name!r}")

    @classmethod
    def joint(cls, name: str) -> Placement:
        return cls("joint", name)

    @classmethod
    def frame(cls, name: str) -> Placement:
        return cls("frame", name)

    def parameter_names(self) -> tuple[str, ...]:
        """Names of the six error components dt = [v; w] (m, rad), e.g. 'elbow_joint.dt[5]'."""
        return tuple(f"{self.name}.dt[{k}]" for k in range(_TWIST_COMPONENTS))


# --------------------------------------------------------------------------------------------------
# Name resolution


def _joint_id(model: pin.Model, name: str) -> int:
    if not model.existJointName(name):
        raise UnknownNameError("joint", name)
    joint_id = model.getJointId(name)
    if joint_id == 0:
        raise UnknownNameError("joint", name, "the universe joint has no placement")
    return joint_id


def _frame_id(model: pin.Model, name: str, *, allow_joint_frame: bool) -> int:
    """Frame id by exact name. Pinocchio allows a JOINT frame and a link frame to share a name,
    so every match is examined instead of trusting getFrameId's first hit."""
    if not model.existFrame(name):
        raise UnknownNameError("frame", name)
    matches = [i for i, frame in enumerate(model.frames) if frame.name == name]
    if not allow_joint_frame:
        non_joint = [i for i in matches if model.frames[i].type != pin.FrameType.JOINT]
        if not non_joint:
            raise UnknownNameError(
                "frame", name, "is the JOINT frame of a joint; use Placement.joint(...) to perturb the joint placement"
            )
        matches = non_joint
    if len(matches) > 1:
        kinds = ", ".join(str(model.frames[i].type) for i in matches)
        raise UnknownNameError("frame", name, f"ambiguous: {len(matches)} frames carry this name ({kinds})")
    return matches[0]


def _frame_anchor(model: pin.Model, frame_id: int) -> int:
    """The frame that physically carries `frame_id`'s placement.

    Pinocchio's URDF parser turns a fixed joint into a FIXED_JOINT frame and the child link into a
    BODY frame whose parentFrame is that FIXED_JOINT frame, with the same placement. The fixed joint
    is what an assembly error displaces, so it is the anchor; any other frame anchors itself.
    """
    frame = model.frames[frame_id]
    if frame.type == pin.FrameType.BODY and frame.parentFrame != frame_id:
        parent = model.frames[frame.parentFrame]
        if (
            parent.type == pin.FrameType.FIXED_JOINT
            and parent.parentJoint == frame.parentJoint
            and parent.placement.isApprox(frame.placement)
        ):
            return frame.parentFrame
    return frame_id


def _rigidly_attached(model: pin.Model, anchor_id: int) -> tuple[list[int], list[int]]:
    """Frames and joints whose placements are rigidly tied to frame `anchor_id`.

    Frames: every frame reached from the anchor through parentFrame links that stay on the anchor's
    parent joint. Joints: those whose JOINT frame hangs from one of these frames; their placements
    are expressed in the common parent joint frame, so a displaced fixed link must move them too.
    """
    parent_joint = model.frames[anchor_id].parentJoint
    children: dict[int, list[int]] = {}
    for i, frame in enumerate(model.frames):
        if i != frame.parentFrame:
            children.setdefault(frame.parentFrame, []).append(i)
    frames: list[int] = []
    joints: list[int] = []
    stack = list(children.get(anchor_id, ()))
    while stack:
        i = stack.pop()
        frame = model.frames[i]
        if frame.type == pin.FrameType.JOINT:
            if frame.parentJoint != parent_joint and model.parents[frame.parentJoint] == parent_joint:
                joints.append(frame.parentJoint)
            continue
        if frame.parentJoint != parent_joint:
            continue
        frames.append(i)
        stack.extend(children.get(i, ()))
    return frames, joints


def frames_moved_by_frame_error(model: pin.Model, frame_id: int) -> tuple[int, set[int]]:
    """(anchor, frames) of a frame placement error as `perturb` applies it: the anchor frame that
    carries it, and every frame that moves rigidly with the anchor (its attached frames, and all
    frames of the subtrees of joints hanging from them), the named frame included. All of them
    move by the same spatial twist Ad(oM_anchor) dt."""
    anchor = _frame_anchor(model, frame_id)
    attached, joints = _rigidly_attached(model, anchor)
    moved = {anchor, frame_id, *attached}
    subtree = {j for j in range(1, model.njoints) if any(k in model.supports[j].tolist() for k in joints)}
    moved |= {i for i, frame in enumerate(model.frames) if frame.parentJoint in subtree}
    return anchor, moved


def placement_of(model: pin.Model, placement: Placement) -> pin.SE3:
    """A copy of the initial pose T(0) named by `placement`, in its parent joint frame (m, rad)."""
    if placement.kind == "joint":
        return model.jointPlacements[_joint_id(model, placement.name)].copy()
    return model.frames[_frame_id(model, placement.name, allow_joint_frame=False)].placement.copy()


def perturb(model: pin.Model, deltas: Mapping[Placement, ArrayLike]) -> pin.Model:
    """A copy of `model` with T(0) <- T(0) exp6(dt) for every (placement, dt) (paper eq. 33/34).

    dt = [v; w] (m, rad) is a right-multiplied error, i.e. a twist expressed in the frame of the
    placement itself (the paper's "error relative to its local coordinate system", eq. 15).

    A frame error is applied to the frame's anchor (the FIXED_JOINT frame when a URDF BODY frame is
    named, see `Placement`) and carried rigidly by everything attached below it on the same parent
    joint: new_G = new_A (old_A^-1 old_G) for frames and for the placements of joints hanging from
    them. The caller's model is never modified. Naming the same physical placement twice (e.g. a
    link and its fixed joint) is rejected rather than silently composed.
    """
    out = pin.Model(model)
    seen: dict[tuple[str, int], Placement] = {}
    for placement, value in deltas.items():
        if not isinstance(placement, Placement):
            raise InvalidInputError(f"perturb: keys must be Placement objects, got {placement!r}")
        dt = require_finite_vector(value, _TWIST_COMPONENTS, f"error twist of {placement.kind} '{placement.name}'")
        if placement.kind == "joint":
            key = ("joint", _joint_id(model, placement.name))
        else:
            key = ("frame", _frame_anchor(model, _frame_id(model, placement.name, allow_joint_frame=False)))
        if key in seen:
            raise InvalidInputError(
                f"perturb: {placement.kind} '{placement.name}' and {seen[key].kind} '{seen[key].name}' "
                "name the same physical placement"
            )
        seen[key] = placement
        error = pin.exp6(dt)
        if key[0] == "joint":
            out.jointPlacements[key[1]] = out.jointPlacements[key[1]] * error
            continue
        anchor = key[1]
        old = out.frames[anchor].placement.copy()
        new = old * error
        # Compose with the current (possibly already perturbed) placements so that errors on nested
        # frames commute: the parent's error acts on the left, the child's own on the right.
        to_new = new * old.inverse()
        frames, joints = _rigidly_attached(out, anchor)
        out.frames[anchor].placement = new
        for i in frames:
            out.frames[i].placement = to_new * out.frames[i].placement
        for j in joints:
            out.jointPlacements[j] = to_new * out.jointPlacements[j]
    return out


# --------------------------------------------------------------------------------------------------
# Serial chain


@dataclass(frozen=True)
class _JointMotionTerms:
    """Constants of exp6(S q) for the chain's twists S_k = [v_k; w_k], to evaluate it in closed form.

    With u = w / |w| and angle a = |w| q (rad), Rodrigues gives the rotation
        R = I + sin(a) [u] + (1 - cos(a)) [u]^2
    and the translation V(a) v q of the SE(3) exponential is
        p = q v + (1 - cos(a)) [u] v / |w| + (a - sin(a)) [u]^2 v / |w|,
    which has no 1/a singularity at q = 0. A prismatic joint (w = 0) gets zero [u] terms: R = I, p = q v.

    Both are linear in the five scalars c = (1, sin a, 1 - cos a, q, a - sin a), so the flattened 4 x 4
    matrix of joint k is c @ basis[k], with basis (n, 5, 16) holding the matching constant parts.
    """

    rate: np.ndarray  # (n,) |w_k| (rad per unit of joint coordinate; 0 for prismatic joints)
    basis: np.ndarray  # (n, 5, 16)

    @classmethod
    def from_twists(cls, twists: np.ndarray) -> _JointMotionTerms:
        twists = np.asarray(twists, dtype=float).reshape(-1, 6)
        linear, angular = twists[:, :3], twists[:, 3:]
        rate = np.linalg.norm(angular, axis=1)
        inverse_rate = np.divide(1.0, rate, out=np.zeros_like(rate), where=rate > 0.0)
        axis_skew = skew(angular * inverse_rate[:, None])
        axis_skew2 = axis_skew @ axis_skew
        basis = np.zeros((len(twists), 5, 4, 4))
        basis[:, 0, :3, :3] = np.eye(3)
        basis[:, 0, 3, 3] = 1.0
        basis[:, 1, :3, :3] = axis_skew
        basis[:, 2, :3, :3] = axis_skew2
        basis[:, 2, :3, 3] = (axis_skew @ linear[:, :, None])[:, :, 0] * inverse_rate[:, None]
        basis[:, 3, :3, 3] = linear
        basis[:, 4, :3, 3] = (axis_skew2 @ linear[:, :, None])[:, :, 0] * inverse_rate[:, None]
        return cls(rate, basis.reshape(len(twists), 5, 16))


@dataclass(frozen=True)
class SerialChain:
    """The joints from a base frame {B} to a tool frame {P}, seen as the local POE of eq. (6).

    joint_ids: the tool's parent-joint support after the base frame's parent joint, root first.
    Every joint must have one DoF and move as exp6(S q) with a constant motion subspace S
    (revolute, prismatic, helical, any axis). Unbounded revolute joints (nq = 2: cos, sin) are
    accepted; their chain coordinate is the angle atan2(sin, cos) in rad.
    Chain configurations `q_chain` are vectors of these joint coordinates in chain order (rad or m).

    The chain stores ids, names and the (n, 6) read-only joint twists S_k = [v; w] (each in its own
    joint frame), not poses: every function takes the model whose placements to use, so one chain
    serves a nominal model and all its `perturb`-ed copies (which never change joint types).
    Build it with `from_model`.
    """

    joint_ids: tuple[int, ...]
    joint_names: tuple[str, ...]
    tool_frame_id: int
    tool_frame: str
    base_frame_id: int | None
    base_frame: str | None
    idx_q: tuple[int, ...]
    nq_per_joint: tuple[int, ...]
    twists: np.ndarray = field(repr=False, compare=False)

    @classmethod
    def from_model(cls, model: pin.Model, tool_frame: str, base_frame: str | None = None) -> SerialChain:
        """Build the chain {B} -> {P}.

        tool_frame: any non-JOINT frame (its placement is the tool pose T_{n,P}(0)).
        base_frame: a frame on a joint of the tool's support (or on the universe); None means
        Pinocchio's world frame. Raises UnknownNameError / UnsupportedJointError naming the culprit.
        """
        tool_id = _frame_id(model, tool_frame, allow_joint_frame=False)
        tool_joint = model.frames[tool_id].parentJoint
        support = list(model.supports[tool_joint])  # [0, ..., tool_joint]
        base_id: int | None = None
        start = 0
        if base_frame is not None:
            base_id = _frame_id(model, base_frame, allow_joint_frame=True)
            base_joint = model.frames[base_id].parentJoint
            if base_joint not in support:
                raise UnknownNameError(
                    "frame",
                    base_frame,
                    f"is on joint '{model.names[base_joint]}', which does not support tool frame '{tool_frame}'",
                )
            start = support.index(base_joint)
        joint_ids = tuple(int(j) for j in support[start + 1 :])
        if not joint_ids:
            raise InvalidInputError(f"no joint moves tool frame '{tool_frame}' relative to the base")
        idx_q: list[int] = []
        nq_per_joint: list[int] = []
        for j in joint_ids:
            joint = model.joints[j]
            if joint.nv != 1 or joint.nq not in (1, 2):
                raise UnsupportedJointError(
                    model.names[j],
                    f"{joint.shortname()} has nq={joint.nq}, nv={joint.nv}; a serial POE chain needs 1-DoF joints",
                )
            idx_q.append(joint.idx_q)
            nq_per_joint.append(joint.nq)
        chain = cls(
            joint_ids=joint_ids,
            joint_names=tuple(model.names[j] for j in joint_ids),
            tool_frame_id=tool_id,
            tool_frame=tool_frame,
            base_frame_id=base_id,
            base_frame=base_frame,
            idx_q=tuple(idx_q),
            nq_per_joint=tuple(nq_per_joint),
            twists=np.empty((0, 6)),
        )
        twists = chain.joint_twists(model)
        twists.flags.writeable = False
        object.__setattr__(chain, "twists", twists)  # frozen: set once, before anyone sees the chain
        chain._check_exponential_joints(model)
        return chain

    @property
    def n_joints(self) -> int:
        return len(self.joint_ids)

    @property
    def n_parameters(self) -> int:
        """6 (n + 1): one error twist per joint placement plus the tool placement."""
        return _TWIST_COMPONENTS * (self.n_joints + 1)

    def placements(self) -> tuple[Placement, ...]:
        """The chain's error-carrying placements in Jacobian column order: each joint, then the tool."""
        return tuple(Placement.joint(name) for name in self.joint_names) + (Placement.frame(self.tool_frame),)

    def parameter_names(self) -> tuple[str, ...]:
        """Column names of the error Jacobian (`forward_and_error_jacobians`), 6 per placement."""
        return tuple(name for p in self.placements() for name in p.parameter_names())

    def rank_bound(self, position_only: bool = False) -> int:
        """An upper bound on the rank of the error Jacobian that holds at every model and configuration.

        An error twist c on placement k that commutes with the joint twist S_k (ad_{S_k} c = 0) passes
        through the joint motion, Ad(exp6(S_k q)) c = c, so it equals the error Ad(T_{k,k+1}(0)^-1) c on the
        next placement, exactly: one linear dependency among the columns per dimension of the
        centraliser of S_k. That is 2 for a screw (revolute or helical joint: the twist itself and the
        pure rotation about, or translation along, its axis) and 4 for a pure translation (prismatic
        joint: every translation and the rotation about its axis), the paper's 4 r + 2 p + 6 (section
        3.2). Position rows also never see the tool's own rotation (3 zero columns). The dependencies are
        independent (each involves its own placement's block), hence the bound; base-parameter selection
        never counts them, its pivots being at rounding level there.
        """
        prismatic = int(np.count_nonzero(~np.any(self.twists[:, 3:], axis=1)))
        dependencies = 2 * self.n_joints + 2 * prismatic + (3 if position_only else 0)
        return self.n_parameters - dependencies

    def check_model(self, model: pin.Model) -> None:
        """Raise InvalidInputError if `model` does not have this chain's joints and frames at the same ids."""
        ok = model.njoints > max(self.joint_ids) and model.nframes > self.tool_frame_id
        ok = ok and all(model.names[j] == name for j, name in zip(self.joint_ids, self.joint_names))
        ok = ok and model.frames[self.tool_frame_id].name == self.tool_frame
        if ok and self.base_frame_id is not None:
            ok = model.nframes > self.base_frame_id and model.frames[self.base_frame_id].name == self.base_frame
        if not ok:
            raise InvalidInputError(
                f"model '{model.name}' does not match the serial chain to '{self.tool_frame}' "
                "(build the chain from this model or from the model it was perturbed from)"
            )

    def initial_poses(self, model: pin.Model) -> list[pin.SE3]:
        """[T_{B,1}(0), T_{1,2}(0), ..., T_{n-1,n}(0), T_{n,P}(0)] of eq. (6), copies.

        T_{B,1}(0) includes the inverse base-frame placement when a base frame is set.
        """
        self.check_model(model)
        poses = [model.jointPlacements[j].copy() for j in self.joint_ids]
        if self.base_frame_id is not None:
            poses[0] = model.frames[self.base_frame_id].placement.inverse() * poses[0]
        poses.append(model.frames[self.tool_frame_id].placement.copy())
        return poses

    def initial_transforms(self, model: pin.Model) -> np.ndarray:
        """`initial_poses` as one (n + 1, 4, 4) array of homogeneous matrices (m), a fresh copy.

        This is the state `placement_poses` consumes: a calibration can update these n + 1 matrices
        (T(0) <- T(0) exp6(dt), eq. 33) without copying a Pinocchio model at every step.
        """
        return np.array([pose.homogeneous for pose in self.initial_poses(model)])

    @cached_property
    def _motion_terms(self) -> _JointMotionTerms:
        # cached_property writes the instance __dict__ directly, which a frozen dataclass allows.
        return _JointMotionTerms.from_twists(self.twists)

    def joint_motions(self, q_chain: ArrayLike) -> np.ndarray:
        """exp6(S_k q_k) for every joint k and configuration, (n, N, 4, 4) homogeneous matrices.

        q_chain: (N, n) chain coordinates (rad or m).
        Closed form for all N configurations at once (see `_JointMotionTerms`), instead of N n
        calls to pin.exp6; joint-major so that each joint's (N, 4, 4) stack is contiguous.
        """
        terms = self._motion_terms
        q = _checked_configurations(self, q_chain).T  # (n, N)
        angle = q * terms.rate[:, None]
        sine = np.sin(angle)
        coefficients = np.stack([np.ones_like(q), sine, 1.0 - np.cos(angle), q, angle - sine], axis=-1)
        return (coefficients @ terms.basis).reshape(q.shape + (4, 4))

    def joint_twists(self, model: pin.Model) -> np.ndarray:
        """(n, 6) joint twists S_k = [v; w] (dimensionless; per rad or per m), each in its own joint
        frame, read from Pinocchio's motion subspace (e.g. revolute about z -> [0, 0, 0, 0, 0, 1])."""
        q = pin.neutral(model)
        twists = np.empty((len(self.joint_ids), 6))
        for k, j in enumerate(self.joint_ids):
            joint = model.joints[j]
            joint_data = joint.createData()
            joint.calc(joint_data, q)
            twists[k] = np.asarray(joint_data.S).reshape(6)
        return twists

    def position_limits(self, model: pin.Model) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) chain coordinate limits (rad or m); unbounded revolute joints get [-pi, pi]."""
        lower = np.empty(self.n_joints)
        upper = np.empty(self.n_joints)
        for k, (i, nq) in enumerate(zip(self.idx_q, self.nq_per_joint)):
            if nq == 2:
                lower[k], upper[k] = -np.pi, np.pi
            else:
                lower[k], upper[k] = model.lowerPositionLimit[i], model.upperPositionLimit[i]
        return lower, upper

    def chain_configuration(self, q: ArrayLike) -> np.ndarray:
        """Chain coordinates (n,) extracted from a full model configuration q (nq,)."""
        q = np.asarray(q, dtype=float)
        needed = max(i + nq for i, nq in zip(self.idx_q, self.nq_per_joint))
        if q.ndim != 1 or q.size < needed:
            raise InvalidInputError(f"configuration: expected a vector of >= {needed} values, got shape {q.shape}")
        out = np.empty(self.n_joints)
        for k, (i, nq) in enumerate(zip(self.idx_q, self.nq_per_joint)):
            out[k] = np.arctan2(q[i + 1], q[i]) if nq == 2 else q[i]
        return out

    def model_configuration(
        self, model: pin.Model, q_chain: ArrayLike, reference: ArrayLike | None = None
    ) -> np.ndarray:
        """A full configuration (nq,) equal to `reference` (default: neutral) except on the chain."""
        q_chain = require_finite_vector(q_chain, self.n_joints, "chain configuration")
        q = pin.neutral(model) if reference is None else require_finite_vector(reference, model.nq, "reference").copy()
        for k, (i, nq) in enumerate(zip(self.idx_q, self.nq_per_joint)):
            if nq == 2:
                q[i], q[i + 1] = np.cos(q_chain[k]), np.sin(q_chain[k])
            else:
                q[i] = q_chain[k]
        return q

    def _check_exponential_joints(self, model: pin.Model) -> None:
        """The POE needs each joint to move as exp6(S q); verify it once rather than trust joint types."""
        angle = 0.7
        for k, j in enumerate(self.joint_ids):
            joint = model.joints[j]
            joint_data = joint.createData()
            q = np.zeros(self.n_joints)
            q[k] = angle
            joint.calc(joint_data, self.model_configuration(model, q))
            if not joint_data.M.isApprox(pin.exp6(self.twists[k] * angle), 1e-12):
                raise UnsupportedJointError(
                    model.names[j], f"{joint.shortname()} does not move as exp6(S q); it cannot be a POE factor"
                )


# --------------------------------------------------------------------------------------------------
# Forward kinematics and error Jacobian


def _base_inverse(chain: SerialChain, model: pin.Model) -> pin.SE3:
    if chain.base_frame_id is None:
        return pin.SE3.Identity()
    return model.frames[chain.base_frame_id].placement.inverse()


def poe_forward(chain: SerialChain, model: pin.Model, q_chain: ArrayLike) -> pin.SE3:
    """Tool pose g_{B,P}(q) = prod_k T_{k-1,k}(0) exp6(S_k q_k) . T_{n,P}(0) (eq. 4/6), in {B}.

    Equals Pinocchio's `data.oMf[tool]` (or oMf[base]^-1 oMf[tool] with a base frame).
    q_chain: (n,) chain coordinates (rad or m), see `SerialChain.chain_configuration`.
    """
    chain.check_model(model)
    q_chain = require_finite_vector(q_chain, chain.n_joints, "chain configuration")
    g = _base_inverse(chain, model)
    for k, j in enumerate(chain.joint_ids):
        g = g * model.jointPlacements[j] * pin.exp6(chain.twists[k] * q_chain[k])
    return g * model.frames[chain.tool_frame_id].placement


def placement_poses(chain: SerialChain, transforms: ArrayLike, q_chain: ArrayLike) -> np.ndarray:
    """Poses in {B} of the chain's n + 1 placement frames, at a batch of configurations.

    transforms: (n + 1, 4, 4) initial poses T(0) as from `SerialChain.initial_transforms` (m).
    q_chain: (N, n) chain coordinates (rad or m).
    Returns F (N, n + 1, 4, 4) with F_k = g_{B,k-1}(q) T_{k-1,k}(0): the frame in which the error dt_k
    of placement k acts (eq. 17: its Jacobian block is Ad(F_k)), and F_n = g_{B,P}(q), the tool pose
    of eq. (6). Batched over poses: 2 n stacked 4 x 4 products instead of a Python loop per pose.
    """
    n = chain.n_joints
    transforms = np.asarray(transforms, dtype=float)
    if transforms.shape != (n + 1, 4, 4):
        raise InvalidInputError(f"initial transforms: expected shape ({n + 1}, 4, 4), got {transforms.shape}")
    motions = chain.joint_motions(q_chain)  # (n, N, 4, 4)
    n_poses = motions.shape[1]
    frames = np.empty((n + 1, n_poses, 4, 4))
    frames[0] = transforms[0]
    moved = np.empty((n_poses, 4, 4))
    for k in range(n):
        np.matmul(frames[k], motions[k], out=moved)  # g_{B,k} = F_k exp6(S_k q_k)
        # F_{k+1} = g_{B,k} T_{k,k+1}(0): one constant right factor, so a single (4N x 4) @ (4 x 4)
        # product, several times faster than a broadcast stacked matmul.
        np.matmul(moved.reshape(-1, 4), transforms[k + 1], out=frames[k + 1].reshape(-1, 4))
    return np.swapaxes(frames, 0, 1)


def tool_poses(chain: SerialChain, model: pin.Model, q_chain: ArrayLike) -> np.ndarray:
    """Tool poses g_{B,P} (N, 4, 4) (m) of `model` at chain configurations (N, n): `poe_forward` for a
    batch, as homogeneous matrices."""
    chain.check_model(model)
    return placement_poses(chain, chain.initial_transforms(model), q_chain)[:, -1]


def adjoint_matrices(poses: np.ndarray) -> np.ndarray:
    """Ad(g) = [[R, [p] R], [0, R]] (..., 6, 6) of homogeneous poses (..., 4, 4), [linear; angular] order
    like `pin.SE3.action`: it maps a twist in the frame of g to the same twist in the reference frame."""
    rotation, position = poses[..., :3, :3], poses[..., :3, 3]
    out = np.zeros(poses.shape[:-2] + (6, 6))
    out[..., :3, :3] = rotation
    out[..., 3:, 3:] = rotation
    out[..., :3, 3:] = skew(position) @ rotation
    return out


def _checked_configurations(chain: SerialChain, q_chain: ArrayLike) -> np.ndarray:
    q_chain = np.atleast_2d(np.asarray(q_chain, dtype=float))
    if q_chain.ndim != 2 or q_chain.shape[1] != chain.n_joints:
        raise InvalidInputError(f"chain configurations: expected shape (N, {chain.n_joints}), got {q_chain.shape}")
    if not np.all(np.isfinite(q_chain)):
        row = int(np.flatnonzero(~np.all(np.isfinite(q_chain), axis=1))[0])
        raise InvalidInputError(f"chain configurations: non-finite value in row {row}")
    return q_chain


def forward_and_error_jacobians(
    chain: SerialChain, model: pin.Model, q_chain: ArrayLike
) -> tuple[list[pin.SE3], np.ndarray]:
    """Tool poses and WORLD error Jacobians at a batch of chain configurations.

    q_chain: (N, n). Returns ([g_1 .. g_N], J of shape (N, 6, 6(n+1))), J the error Jacobian of
    eq. (17)-(20) in the WORLD (spatial) convention at each configuration:
    J = [Ad(T_{B,1}(0)), Ad(g_{B,1} T_{1,2}(0)), ..., Ad(g_{B,n-1} T_{n-1,n}(0)), Ad(g_{B,n} T_{n,P}(0))]
    with g_{B,k} the pose of joint k after its motion. Columns follow `chain.parameter_names()`:
    the stacked right-multiplied placement errors x = [dt_1; ...; dt_n; dt_P] ([v; w], m and rad,
    each in its own placement frame, as in `perturb`). Rows are the end-effector error twist
    y = log6(g_actual g^-1) = [v; w] expressed in {B} (eq. 18), to first order y = J x.
    Without a base frame, the joint blocks equal those of
    `pin.computeFrameKinematicRegressor(model, data, tool, pin.WORLD)` and the tool block is Ad(oMf).
    Both come from one batched pass along the chain (`placement_poses`); use that function
    directly to stay in arrays.
    """
    chain.check_model(model)
    frames = placement_poses(chain, chain.initial_transforms(model), q_chain)
    n_poses, n_blocks = frames.shape[:2]
    # (N, n+1, 6, 6) -> (N, 6, n+1, 6): block k holds the 6 columns of placement k.
    jacobians = np.swapaxes(adjoint_matrices(frames), 1, 2).reshape(n_poses, 6, 6 * n_blocks)
    return [pin.SE3(g) for g in frames[:, -1]], jacobians
