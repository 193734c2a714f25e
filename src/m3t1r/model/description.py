"""Model files and loading: the URDF tree, its loop closures, and the `Mechanism` that holds them.

The closures file schema is documented in models/README.md. Everything is validated on load, and
each error names the file and the joint, frame or field at fault.
"""

from __future__ import annotations

import copy
import hashlib
import importlib.resources
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Literal

import numpy as np
import pinocchio as pin
import yaml

from m3t1r.errors import ModelFileError
from m3t1r.io.outputs import OutputSet
from m3t1r.io.pairing import paired_closures_path, recorded_closures_sha256, sha256_bytes
from m3t1r.io.temporaries import pending_temporaries
from m3t1r.model.urdf_io import calibrated_urdf_bytes

__all__ = ["ClosureSpec", "Mechanism", "nominal_model_paths", "paired_closures", "HOME_TOLERANCE"]

HOME_TOLERANCE = 1e-9  # max |closure residual| accepted at the declared home pose
_ROW_COUNT = {"3D": 3, "6D": 6}


def nominal_model_paths() -> tuple[Path, Path]:
    """Paths of the packaged nominal URDF and closures file."""
    packaged = importlib.resources.files("m3t1r") / "models"
    candidates = [Path(str(packaged)), Path(__file__).resolve().parents[3] / "models"]
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

    closures_document: dict | None = field(default=None, repr=False, compare=False)
    """The closures file as read (a YAML mapping), so that `save` never re-reads a file that may have changed."""

    @classmethod
    def load(cls, urdf: str | Path | None = None, closures: str | Path | None = None) -> "Mechanism":
        """Load a description: the packaged nominal one by default, or any URDF + closures pair.

        With a URDF and no closures file, the URDF's pair is loaded (`paired_closures`):
        `NAME.urdf` pairs with `NAME.closures.yaml`. A URDF written by `save` records its closures
        file's sha256, and a closures file of another sha256 is refused, naming both files, so a
        URDF never loads with the closures of another machine. A URDF without a pair beside it and
        without a recorded sha256 gets the packaged nominal closures (a plain URDF of this machine).

        Raises ModelFileError (naming the file and the field, joint or frame) when a file is
        missing, Pinocchio rejects the URDF, the two files are not a pair, the closures name
        unknown frames or joints, an actuated joint is not a 1-DoF prismatic/revolute joint, or
        the home pose does not close.
        """
        if urdf is None:
            nominal_urdf, nominal_closures = nominal_model_paths()
            urdf = nominal_urdf
            closures = closures if closures is not None else nominal_closures
        urdf_path = Path(urdf)
        if not urdf_path.is_file():
            raise ModelFileError(urdf_path, "file not found" if not urdf_path.exists() else "not a regular file")
        recorded = _recorded_sha256(urdf_path)
        if closures is None and recorded is None and not _paired_path(urdf_path).is_file():
            closures = nominal_model_paths()[1]
        if closures is None:
            closures_path, data = paired_closures(urdf_path, recorded=recorded)
        else:
            closures_path, data = _closures_of(urdf_path, Path(closures), recorded)
        model, visual = _load_urdf(urdf_path)
        doc = _parse_yaml(closures_path, data)
        try:
            mechanism = _build(model, visual, doc, urdf_path, closures_path)
        except ModelFileError:
            raise
        except (TypeError, ValueError, AttributeError, OverflowError, KeyError) as exc:
            # Safety net for a malformed cell the field checks above did not foresee.
            raise ModelFileError(closures_path, f"malformed closures file: {type(exc).__name__}: {exc}") from None
        mechanism = _with_document(mechanism, doc)
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

    def pair_bytes(self, urdf: str | Path, closures: str | Path | None = None) -> tuple[bytes, bytes]:
        """The (URDF, closures) bytes `save` writes for a pair named `urdf` (closures default: its pair).

        The URDF is this machine's source URDF with every joint `<origin>` rewritten from `model`
        (a calibrated tree keeps its visuals, limits and names) and a comment recording the
        closures bytes' sha256; the closures file is the source's with `home` replaced by this
        machine's assembled home.
        """
        doc = copy.deepcopy(self.closures_document) if self.closures_document is not None else \
            _parse_yaml(self.closures_path, _read_bytes(self.closures_path))
        doc["home"] = {self.model.names[j]: float(self.home[self.model.idx_qs[j]]) for j in range(1, self.model.njoints)}
        closures_path = paired_closures_path(urdf) if closures is None else Path(closures)
        header = (f"# Closures of {Path(urdf).name} (written with it as a pair; its URDF records this file's sha256); "
                  "home re-assembled for its geometry. Schema: models/README.md\n")
        closures_bytes = (header + yaml.safe_dump(doc, sort_keys=False)).encode("utf-8")
        del closures_path
        return calibrated_urdf_bytes(self.urdf_path, self.model, sha256_bytes(closures_bytes)), closures_bytes

    def save(self, urdf: str | Path, closures: str | Path | None = None, protect: tuple = ()) -> None:
        """Write this machine as a URDF + closures pair that `Mechanism.load(urdf)` reads back.

        `closures` defaults to the pair name `NAME.closures.yaml` (`m3t1r.io.pairing.paired_closures_path`).
        The two files are written as a unit (`m3t1r.io.outputs.OutputSet`): checked first (no collision
        with each other, the source files or `protect`, through symlinks and hard links; folder
        writable), then staged and renamed so that an interruption at any instant leaves a
        loadable pair, the old one or the new one.
        """
        outputs = OutputSet(inputs=(self.urdf_path, self.closures_path, *protect))
        machine = outputs.add_machine(urdf, "URDF", closures)
        with outputs:
            outputs.check()
            outputs.stage_machine(machine, self)
            outputs.commit()

    def with_model(self, model: pin.Model) -> "Mechanism":
        """The same closures and actuation on another tree model (a calibrated or perturbed copy)."""
        return Mechanism(model, self.visual_model, self.closures, self.actuated_joints,
                         self.principal_chains, self.platform_frame, self.home.copy(),
                         self.urdf_path, self.closures_path, self.closures_document)


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


def paired_closures(urdf: str | Path, *, recorded: str | None | bool = False) -> tuple[Path, bytes]:
    """The closures file that pairs with `urdf`, and its bytes, as read once.

    `NAME.urdf` pairs with `NAME.closures.yaml` (only the final `.urdf` replaced). If the URDF
    records a closures sha256 (every URDF written by `Mechanism.save` does), the closures file must
    have it; when `NAME.closures.yaml` does not, a staged closures file of an interrupted pair
    write (`.NAME.closures.yaml.m3t1r-*.tmp`) that has it is used instead: the URDF was renamed,
    its closures file not yet (models/README.md, "A machine is a pair of files").

    Raises ModelFileError: no closures file, or none with the recorded sha256.
    """
    urdf_path = Path(urdf)
    if recorded is False:
        recorded = _recorded_sha256(urdf_path)
    return _closures_of(urdf_path, _paired_path(urdf_path), recorded)


def _paired_path(urdf: Path) -> Path:
    return paired_closures_path(urdf)


def _recorded_sha256(urdf: Path) -> str | None:
    try:
        return recorded_closures_sha256(_read_bytes(urdf))
    except ModelFileError as exc:
        raise ModelFileError(urdf, str(exc).split(": ", 1)[-1]) from None


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ModelFileError(path, "file not found") from None
    except IsADirectoryError:
        raise ModelFileError(path, "is a directory, expected a file") from None
    except OSError as exc:
        raise ModelFileError(path, f"cannot read: {exc.strerror or exc}") from None


def _closures_of(urdf: Path, closures: Path, recorded: str | None) -> tuple[Path, bytes]:
    data = None if not closures.exists() and recorded is not None else _read_bytes(closures)
    if recorded is None:
        return closures, data
    if data is not None and hashlib.sha256(data).hexdigest() == recorded:
        return closures, data
    for pending in reversed(pending_temporaries(closures)):
        try:
            staged = pending.read_bytes()
        except OSError:
            continue
        if hashlib.sha256(staged).hexdigest() == recorded:
            return closures, staged
    if data is None:
        raise ModelFileError(closures, f"file not found: {urdf.name} records closures sha256 {recorded[:16]}..., "
                                       "and no closures file with it is there")
    actual = hashlib.sha256(data).hexdigest()
    raise ModelFileError(
        closures, f"not the closures file of {urdf}: the URDF records closures sha256 {recorded[:16]}..., "
                  f"this file has {actual[:16]}... The two files were not written together (one was rewritten "
                  "by another run, or copied from another machine); load the URDF with the closures file "
                  "written with it")


def _parse_yaml(path: Path, data: bytes) -> dict:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ModelFileError(path, f"line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ModelFileError(path, f"{where}not valid YAML: {problem}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # e.g. a date 2001-13-01
        raise ModelFileError(path, f"cannot read closures YAML: {type(exc).__name__}: {exc}") from None
    if not isinstance(doc, dict):
        raise ModelFileError(path, "closures file must be a YAML mapping")
    for key in ("actuated_joints", "closures", "platform_frame", "home"):
        if key not in doc:
            raise ModelFileError(path, f"missing field '{key}'")
    return doc


def _with_document(mechanism: Mechanism, doc: dict) -> Mechanism:
    return Mechanism(mechanism.model, mechanism.visual_model, mechanism.closures, mechanism.actuated_joints,
                     mechanism.principal_chains, mechanism.platform_frame, mechanism.home,
                     mechanism.urdf_path, mechanism.closures_path, copy.deepcopy(doc))


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
    for spec, residual in closure_residual_by_closure(mechanism, mechanism.home):
        # Only the enforced rows: on a machine with errors the others cannot all hold (mechanism.md).
        worst = float(np.max(np.abs(residual[list(spec.rows)])))
        if not worst <= HOME_TOLERANCE:  # a NaN residual (home values too large) fails too
            raise ModelFileError(mechanism.closures_path,
                                 f"home does not close: closure '{spec.name}' residual {worst:.3e} > {HOME_TOLERANCE:g}")


def closure_residual_by_closure(mechanism: Mechanism, q: np.ndarray) -> Iterator[tuple[ClosureSpec, np.ndarray]]:
    """Yield (closure, full residual of its type) at q; a slow, obvious reference for checks."""
    model = mechanism.model
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    for spec in mechanism.closures:
        oMa, oMb = data.oMf[spec.frame_a_id], data.oMf[spec.frame_b_id]
        if spec.type == "3D":
            yield spec, oMa.rotation.T @ (oMb.translation - oMa.translation)
        else:
            yield spec, pin.log6(oMa.actInv(oMb)).vector
