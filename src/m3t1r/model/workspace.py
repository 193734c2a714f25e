"""Workspace sampling: actuator sets drawn in the mechanism's declared workspace (closures file), or in a
box derived around home when the file declares none and the actuators have no finite limits."""

from __future__ import annotations

import itertools
import math
import warnings
import weakref

import numpy as np
import pinocchio as pin

from m3t1r._threads import on_one_blas_thread
from m3t1r.errors import InvalidInputError, ModelFileError, ModelWarning
from m3t1r.model.closures import ClosureSystem
from m3t1r.model.defaults import actuator_task_jacobian
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.task import WorkspaceSpec

__all__ = [
    "workspace_actuators",
    "declared_workspace",
    "default_workspace",
    "default_workspace_notes",
    "DEFAULT_CONDITIONING",
]


def declared_workspace(mechanism: Mechanism) -> WorkspaceSpec:
    """The mechanism's workspace; without one (schema 1 files), the actuators' URDF limits as a box, or
    where they are not all finite, the box around home that `default_workspace` derives (said in a
    ModelWarning note, once per mechanism).

    Raises InvalidInputError when there is neither a workspace nor finite actuator limits, and no
    box around home keeps its assembly mode and conditioning (home itself singular).
    """
    if mechanism.workspace is not None:
        return mechanism.workspace
    lower, upper = mechanism.joint_limits()
    if np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower < upper):
        return WorkspaceSpec(
            actuators=tuple(
                (name, float(lo), float(hi)) for name, lo, hi in zip(mechanism.actuated_joints, lower, upper)
            )
        )
    if mechanism not in _DERIVED:
        _DERIVED[mechanism] = default_workspace(mechanism)
        note = f"{mechanism.closures_path.name}: {_derived_note(mechanism, _DERIVED[mechanism])}"
        if _noted(mechanism, note):  # copies of one machine (rehomed, calibrated) derive the same box: said once
            warnings.warn(note, ModelWarning, stacklevel=2)
    return _DERIVED[mechanism]


def default_workspace_notes(mechanism: Mechanism) -> list[str]:
    """The note on the workspace box derived for a mechanism that declares none and has no finite
    actuator limits (`declared_workspace`), or [] (declared, limits, or none derivable: the verbs
    that sample say why)."""
    lower, upper = mechanism.joint_limits()
    if mechanism.workspace is not None or (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
        return []
    if mechanism not in _DERIVED:
        try:
            _DERIVED[mechanism] = default_workspace(mechanism)
        except InvalidInputError:
            return []
    note = _derived_note(mechanism, _DERIVED[mechanism])
    _noted(mechanism, f"{mechanism.closures_path.name}: {note}")  # the caller says it: no warning later
    return [note]


def _noted(mechanism: Mechanism, note: str) -> bool:
    """Record a derived-box note; True the first time this process sees it for this closures file.
    Keyed by the file's full path, so that another file of the same name (another folder) is told too."""
    key = (str(mechanism.closures_path.resolve()), note)
    first = key not in _NOTED
    _NOTED.add(key)
    return first


def _derived_note(mechanism: Mechanism, workspace: WorkspaceSpec) -> str:
    units = mechanism.joint_units()
    box = ", ".join(f"{name} [{lo:.4g}, {hi:.4g}] {unit}" for (name, lo, hi), unit in zip(workspace.actuators, units))
    return (
        f"no workspace declared and no finite actuator limits: sampling in {box}, the box around home that "
        f"assembles from home on its mode with the task Jacobian at least {DEFAULT_CONDITIONING:g} as well "
        "conditioned as at home; declare `workspace:` to choose another (models/README.md)"
    )


_DERIVED: "weakref.WeakKeyDictionary[Mechanism, WorkspaceSpec]" = weakref.WeakKeyDictionary()
_NOTED: set[tuple[str, str]] = set()  # (closures file, note) pairs said in this process
DEFAULT_CONDITIONING = 0.25  # a default box keeps this fraction of home's actuator-to-task conditioning
_REACH_RAD = 0.5  # the largest half-width tried for a revolute actuator [rad]
_REACH_LENGTH = 0.25  # ... for a prismatic one, as a fraction of the task frame's distance from the base origin
_SHRINK = 1.0 / math.sqrt(2.0)
_TRIALS = 12  # half-widths tried, each 1/sqrt(2) of the last: down to 1/45 of the largest


@on_one_blas_thread
def default_workspace(mechanism: Mechanism) -> WorkspaceSpec:
    """The largest box around home's actuators, within any limits given, in which every point of a
    test pattern (a grid for up to three actuators, else corners, axes and 64 draws) assembles from
    home on home's assembly mode, keeps the sign of the actuator-to-task Jacobian's determinant
    (home's working mode), and keeps its conditioning (smallest over largest singular value, for
    the passive closure block and the task) at least DEFAULT_CONDITIONING of home's.

    Half-widths start at 0.5 rad for revolute actuators and 1/4 of the task frame's distance from
    the base origin for prismatic ones, and shrink by 1/sqrt(2) until the pattern passes.
    Raises InvalidInputError naming the closures file when even the smallest box fails.
    """
    solver, system = ClosedLoopSolver(mechanism), ClosureSystem(mechanism.model, mechanism.closures)
    home = mechanism.home[mechanism.actuated_ids]
    reference = _conditioning(mechanism, system, mechanism.home)
    if reference is None:
        raise InvalidInputError(
            f"{mechanism.closures_path}: no workspace declared, no finite actuator limits, and "
            "home is singular (no box around it keeps one assembly and working mode); add a "
            "`workspace:` box (models/README.md)"
        )
    lower, upper = mechanism.joint_limits()
    reach = _largest_reach(mechanism)
    pattern = _test_pattern(len(home))
    for trial in range(_TRIALS):
        half = reach * _SHRINK**trial
        lo, hi = np.maximum(home - half, lower), np.minimum(home + half, upper)
        points = np.clip(home + pattern * half, lo, hi)
        batch = solver.forward_batch(points)
        if batch.failures:
            continue
        measures = [_conditioning(mechanism, system, q) for q in batch.q]
        if all(
            m is not None
            and m[2] == reference[2]
            and m[0] >= DEFAULT_CONDITIONING * reference[0]
            and m[1] >= DEFAULT_CONDITIONING * reference[1]
            for m in measures
        ):
            return WorkspaceSpec(
                actuators=tuple((name, float(a), float(b)) for name, a, b in zip(mechanism.actuated_joints, lo, hi))
            )
    raise InvalidInputError(
        f"{mechanism.closures_path}: no workspace declared, no finite actuator limits, and no "
        f"box around home down to {reach.min() * _SHRINK ** (_TRIALS - 1):.3g} keeps home's "
        "assembly mode and conditioning; add a `workspace:` box (models/README.md)"
    )


def _largest_reach(mechanism: Mechanism) -> np.ndarray:
    """The largest half-width tried per actuator [rad or m]."""
    data = mechanism.model.createData()
    pin.framesForwardKinematics(mechanism.model, data, mechanism.home)
    frame = mechanism.model.getFrameId(mechanism.task.frame)
    length = max(float(np.linalg.norm(data.oMf[frame].translation)), 1e-3)
    return np.array([_REACH_RAD if unit == "rad" else _REACH_LENGTH * length for unit in mechanism.joint_units()])


def _test_pattern(count: int) -> np.ndarray:
    """Points in [-1, 1]^count: the 5^count grid for up to 3 actuators, else the corners, the points at
    +-1/2 and +-1 on each axis, and 64 uniform draws (fixed seed)."""
    if count <= 3:
        return np.array(list(itertools.product((-1.0, -0.5, 0.0, 0.5, 1.0), repeat=count)))
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=count)))
    axes = np.vstack([scale * np.eye(count) for scale in (-1.0, -0.5, 0.5, 1.0)])
    return np.vstack((corners, axes, np.random.default_rng(0).uniform(-1.0, 1.0, (64, count))))


def _conditioning(mechanism: Mechanism, system: ClosureSystem, q: np.ndarray) -> tuple[float, float, bool] | None:
    """(passive block's, task Jacobian's singular value ratio, sign of the task Jacobian's determinant)
    at an assembled q; None where either is singular."""
    jacobian = actuator_task_jacobian(system, q, mechanism.actuated_ids, mechanism.passive_ids, mechanism.task)
    if jacobian is None or jacobian.shape[0] != jacobian.shape[1] or not np.all(np.isfinite(jacobian)):
        return None
    passive = system.evaluate(q, True)[1][:, mechanism.passive_ids]
    ratios = []
    for matrix in (passive, jacobian):
        singular = np.linalg.svd(matrix, compute_uv=False) if matrix.size else np.ones(1)
        ratios.append(float(singular[-1] / singular[0]) if singular[0] > 0.0 else 0.0)
    if min(ratios) <= 0.0:
        return None
    return ratios[0], ratios[1], bool(np.linalg.det(jacobian) > 0.0)


@on_one_blas_thread
def workspace_actuators(nominal: Mechanism, n: int, rng: np.random.Generator) -> np.ndarray:
    """n actuator sets (n x k) [m or rad] drawn uniformly in the declared workspace, each assembled
    from home (so every one is on the home branch).

    A task box is drawn in task coordinates and mapped by inverse kinematics; an actuator box is
    drawn directly and checked by forward kinematics. Raises ModelFileError (naming the closures
    file and a draw) when the machine cannot reach a draw: the declared box is wrong for it.
    """
    workspace = declared_workspace(nominal)
    if n == 0:
        return np.zeros((0, len(nominal.actuated_joints)))
    solver = ClosedLoopSolver(nominal)
    if workspace.kind == "task":
        batch = solver.inverse_batch(workspace.task_poses(nominal.task, rng, n))
        actuators = batch.actuators
    else:
        lo, hi = workspace.bounds(nominal.actuated_joints)
        actuators = lo + (hi - lo) * rng.random((n, len(lo)))
        batch = solver.forward_batch(actuators)
    if batch.failures:
        first = batch.failures[0]
        where = (
            f"declared {workspace.kind} workspace box"
            if nominal.workspace is not None
            else "default box around home (no workspace declared: add a `workspace:` box, models/README.md)"
            if _DERIVED.get(nominal) is workspace
            else "actuators' URDF limits (no workspace declared: add a `workspace:` box, models/README.md)"
        )
        raise ModelFileError(
            nominal.closures_path,
            f"{len(batch.failures)} of {n} draws in the {where} cannot be "
            f"assembled from home; first, draw {first.index}: {first.reason}",
        )
    return np.array(actuators).reshape(n, len(nominal.actuated_joints))
