"""Model files and loading: the URDF tree, its loop closures, and the `Mechanism` that holds them.

The closures file schema is documented in models/README.md. Everything is validated on load, and
each error names the file and the joint, frame or field at fault.
"""

from __future__ import annotations

import importlib.resources
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pinocchio as pin
import yaml

from .errors import ModelFileError

__all__ = ["ClosureSpec", "Mechanism", "nominal_model_paths", "HOME_TOLERANCE"]

HOME_TOLERANCE = 1e-9  # max |closure residual| accepted at the declared home pose
_ROW_COUNT = {"3D": 3, "6D": 6}


def nominal_model_paths() -> tuple[Path, Path]:
    """Paths of the packaged nominal URDF and closures file."""
    packaged = importlib.resources.files("m3t1r") / "models"
    candidates = [Path(str(packaged)), Path(__file__).resolve().parents[2] / "models"]
    for folder in candidates:  # installed wheel first, then a source checkout (editable install)
        urdf, closures = folder / "m3t1r.urdf", folder / "m3t1r.closures.yaml"
        if urdf.is_file() and closures.is_file():
            return urdf, closures
    raise ModelFileError(candidates[-1], "the packaged nominal model files are missing")


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


@dataclass(frozen=True, eq=False)
class Mechanism:
    """A closed-chain machine: Pinocchio tree model, visual geometry, closures and actuation.

    `model` is the open tree (four chains from `base`); the closures make it a mechanism.
    Joint values are Pinocchio configuration vectors (nq == nv, revolute/prismatic only).
    """

    model: pin.Model
    visual_model: pin.GeometryModel
    closures: tuple[ClosureSpec, ...]
    actuated_joints: tuple[str, ...]
    principal_chains: dict[str, tuple[str, ...]]
    platform_frame: str
    home: np.ndarray
    urdf_path: Path
    closures_path: Path

    @classmethod
    def load(cls, urdf: str | Path | None = None, closures: str | Path | None = None) -> "Mechanism":
        """Load a description: the packaged nominal one by default, or any URDF + closures pair.

        Raises ModelFileError (naming the file and the field, joint or frame) when a file is
        missing, Pinocchio rejects the URDF, the closures name unknown frames or joints, an
        actuated joint is not a 1-DoF prismatic/revolute joint, or the home pose does not close.
        """
        if (urdf is None) != (closures is None):
            nominal_urdf, nominal_closures = nominal_model_paths()
            urdf = urdf if urdf is not None else nominal_urdf
            closures = closures if closures is not None else nominal_closures
        elif urdf is None:
            urdf, closures = nominal_model_paths()
        urdf_path, closures_path = Path(urdf), Path(closures)
        for path in (urdf_path, closures_path):
            if not path.is_file():
                raise ModelFileError(path, "file not found")
        model, visual = _load_urdf(urdf_path)
        doc = _read_yaml(closures_path)
        mechanism = _build(model, visual, doc, urdf_path, closures_path)
        _check_home_closes(mechanism)
        return mechanism

    # Convenience views, all derived from the model (no duplicated state).
    @property
    def actuated_ids(self) -> np.ndarray:
        """Velocity indices of the actuated joints, in `actuated_joints` order."""
        return np.array([self.model.idx_vs[self.model.getJointId(n)] for n in self.actuated_joints])

    @property
    def passive_ids(self) -> np.ndarray:
        """Velocity indices of every joint that is not actuated, ascending."""
        mask = np.ones(self.model.nv, dtype=bool)
        mask[self.actuated_ids] = False
        return np.flatnonzero(mask)

    @property
    def platform_frame_id(self) -> int:
        return self.model.getFrameId(self.platform_frame)

    @property
    def n_constraints(self) -> int:
        """Number of enforced closure rows."""
        return sum(len(c.rows) for c in self.closures)

    def joint_limits(self, names: tuple[str, ...] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper position limits [m or rad] of the named joints (default: actuated)."""
        names = self.actuated_joints if names is None else names
        idx = [self.model.idx_qs[self.model.getJointId(n)] for n in names]
        return self.model.lowerPositionLimit[idx].copy(), self.model.upperPositionLimit[idx].copy()

    def configuration(self, values: dict[str, float]) -> np.ndarray:
        """Full configuration from {joint name: value}; unnamed joints take their home value."""
        q = self.home.copy()
        for name, value in values.items():
            if not self.model.existJointName(name):
                raise KeyError(f"no joint named '{name}' in {self.urdf_path}")
            q[self.model.idx_qs[self.model.getJointId(name)]] = value
        return q

    def save(self, urdf: str | Path, closures: str | Path, protect: tuple = ()) -> None:
        """Write this machine as a URDF + closures pair that `Mechanism.load` reads back.

        The URDF is this machine's source URDF with every joint `<origin>` rewritten from `model`
        (a calibrated tree keeps its visuals, limits and names); the closures file is the source's
        with `home` replaced by this machine's assembled home. Both writes are atomic and never
        touch the source files or `protect`.
        """
        from .io import atomic_write_text
        from .urdf_io import write_calibrated_urdf

        sources = (self.urdf_path, self.closures_path, *protect)
        doc = yaml.safe_load(self.closures_path.read_text())
        doc["home"] = {self.model.names[j]: float(self.home[self.model.idx_qs[j]]) for j in range(1, self.model.njoints)}
        header = f"# Closures of {Path(urdf).name}; home re-assembled for its geometry. Schema: models/README.md\n"
        from .io import ensure_not_protected

        ensure_not_protected(closures, sources)
        write_calibrated_urdf(self.urdf_path, self.model, Path(urdf), protect=sources)
        atomic_write_text(closures, header + yaml.safe_dump(doc, sort_keys=False), protect=sources)

    def with_model(self, model: pin.Model) -> "Mechanism":
        """The same closures and actuation on another tree model (a calibrated or perturbed copy)."""
        return Mechanism(model, self.visual_model, self.closures, self.actuated_joints,
                         self.principal_chains, self.platform_frame, self.home.copy(),
                         self.urdf_path, self.closures_path)


def _load_urdf(path: Path) -> tuple[pin.Model, pin.GeometryModel]:
    try:
        model = pin.buildModelFromUrdf(str(path))
        visual = pin.buildGeomFromUrdf(model, str(path), pin.GeometryType.VISUAL, package_dirs=[str(path.parent)])
    except Exception as exc:  # Pinocchio raises bare RuntimeError/ValueError for bad XML
        raise ModelFileError(path, f"Pinocchio rejected the URDF: {exc}") from None
    for j in range(1, model.njoints):
        if model.nqs[j] != 1 or model.nvs[j] != 1:
            raise ModelFileError(path, f"joint '{model.names[j]}' is not a 1-DoF revolute/prismatic joint "
                                       f"(nq={model.nqs[j]}); continuous and multi-DoF joints are not supported")
    return model, visual


def _read_yaml(path: Path) -> dict:
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ModelFileError(path, f"cannot read closures YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise ModelFileError(path, "closures file must be a YAML mapping")
    for key in ("actuated_joints", "closures", "platform_frame", "home"):
        if key not in doc:
            raise ModelFileError(path, f"missing field '{key}'")
    return doc


def _frame_id(model: pin.Model, name: object, path: Path, where: str) -> int:
    if not isinstance(name, str) or not model.existFrame(name):
        raise ModelFileError(path, f"{where}: frame '{name}' does not exist in the URDF")
    return model.getFrameId(name)


def _build(model: pin.Model, visual: pin.GeometryModel, doc: dict, urdf_path: Path, path: Path) -> Mechanism:
    actuated = doc["actuated_joints"]
    if not isinstance(actuated, list) or not actuated:
        raise ModelFileError(path, "actuated_joints must be a non-empty list of joint names")
    for name in actuated:
        if isinstance(name, str) and model.existFrame(name, pin.FrameType.FIXED_JOINT):
            raise ModelFileError(path, f"actuated_joints: '{name}' is a fixed joint, not prismatic or revolute")
        if not isinstance(name, str) or not model.existJointName(name):
            raise ModelFileError(path, f"actuated_joints: joint '{name}' does not exist in {urdf_path.name}")
        shortname = model.joints[model.getJointId(name)].shortname()
        if not any(shortname.startswith(k) for k in ("JointModelP", "JointModelR")) or "Unbounded" in shortname:
            raise ModelFileError(path, f"actuated_joints: joint '{name}' is {shortname}, not prismatic or revolute")
    if len(set(actuated)) != len(actuated):
        raise ModelFileError(path, "actuated_joints: a joint is listed twice")

    closures = []
    seen = set()
    for k, entry in enumerate(doc["closures"] or []):
        where = f"closures[{k}]"
        if not isinstance(entry, dict):
            raise ModelFileError(path, f"{where}: expected a mapping")
        name = entry.get("name", where)
        where = f"closure '{name}'"
        if name in seen:
            raise ModelFileError(path, f"{where}: duplicate closure name")
        seen.add(name)
        kind = entry.get("type")
        if kind not in _ROW_COUNT:
            raise ModelFileError(path, f"{where}: type must be 3D or 6D, got {kind!r}")
        ia = _frame_id(model, entry.get("frame_a"), path, where)
        ib = _frame_id(model, entry.get("frame_b"), path, where)
        rows = entry.get("rows", list(range(_ROW_COUNT[kind])))
        if (not isinstance(rows, list) or not rows or len(set(rows)) != len(rows)
                or not all(isinstance(r, int) and 0 <= r < _ROW_COUNT[kind] for r in rows)):
            raise ModelFileError(path, f"{where}: rows must be distinct indices in 0..{_ROW_COUNT[kind] - 1}, got {rows!r}")
        closures.append(ClosureSpec(name, kind, entry["frame_a"], entry["frame_b"], tuple(sorted(rows)), ia, ib))
    if not closures:
        raise ModelFileError(path, "closures: at least one closure is required")

    platform = doc["platform_frame"]
    _frame_id(model, platform, path, "platform_frame")

    chains = {}
    for chain_name, items in (doc.get("principal_chains") or {}).items():
        if not isinstance(items, list) or len(items) < 2:
            raise ModelFileError(path, f"principal_chains.{chain_name}: expected joint names then a frame name")
        for joint in items[:-1]:
            if not model.existJointName(joint):
                raise ModelFileError(path, f"principal_chains.{chain_name}: joint '{joint}' does not exist")
        _frame_id(model, items[-1], path, f"principal_chains.{chain_name}")
        chains[chain_name] = tuple(items)

    home_doc = doc["home"]
    if not isinstance(home_doc, dict):
        raise ModelFileError(path, "home must map joint names to values")
    home = pin.neutral(model)
    for name, value in home_doc.items():
        if not model.existJointName(name):
            raise ModelFileError(path, f"home: joint '{name}' does not exist")
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ModelFileError(path, f"home: joint '{name}' has non-numeric value {value!r}") from None
        if not np.isfinite(value):
            raise ModelFileError(path, f"home: joint '{name}' has non-finite value {value}")
        home[model.idx_qs[model.getJointId(name)]] = value
    return Mechanism(model, visual, tuple(closures), tuple(actuated), chains, platform, home, urdf_path, path)


def _check_home_closes(mechanism: Mechanism) -> None:
    # Imported here: kinematics depends on this module, not the other way round.
    from .kinematics import closure_residual_by_closure

    for spec, residual in closure_residual_by_closure(mechanism, mechanism.home):
        # Only the enforced rows: on a machine with errors the others cannot all hold (mechanism.md).
        worst = float(np.max(np.abs(residual[list(spec.rows)])))
        if worst > HOME_TOLERANCE:
            raise ModelFileError(mechanism.closures_path,
                                 f"home does not close: closure '{spec.name}' residual {worst:.3e} > {HOME_TOLERANCE:g}")
