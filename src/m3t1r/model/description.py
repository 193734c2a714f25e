"""Model files and loading: the URDF tree, its loop closures, and the `Mechanism` that holds them.

The closures file schema is documented in models/README.md. Everything is validated on load, and
each error names the file and the joint, frame or field at fault.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.resources
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, cast

import numpy as np
import pinocchio as pin
import yaml

from m3t1r.errors import ModelFileError, ModelWarning
from m3t1r.io.outputs import OutputSet
from m3t1r.io.pairing import closures_match, closures_sha256, paired_closures_path, recorded_closures_sha256
from m3t1r.io.paths import read_input
from m3t1r.io.temporaries import pending_temporaries
from m3t1r.model.assembly import HomeAssembly, assemble_home, limits_violated
from m3t1r.model.closures import ClosureSpec, ClosureSystem, closure_rank, without_rows
from m3t1r.model.defaults import default_task, task_entry, task_words
from m3t1r.model.mjcf_io import is_mjcf, mjcf_sidecar_path, read_mjcf
from m3t1r.model.schema import SCHEMA_VERSIONS, declared_frame_entries, load_closures_yaml, read_description
from m3t1r.model.task import TaskSpec, WorkspaceSpec
from m3t1r.model.urdf_io import calibrated_urdf_bytes, refuse_mimic_joints, revolute_urdf_text, tree_urdf_bytes

__all__ = ["ClosureSpec", "Mechanism", "nominal_model_paths", "paired_closures", "HOME_TOLERANCE", "SCHEMA_VERSIONS"]

HOME_TOLERANCE = 1e-9  # max |closure residual| accepted at the home pose (after assembly)


def nominal_model_paths() -> tuple[Path, Path]:
    """Paths of the packaged nominal URDF and closures file."""
    packaged = importlib.resources.files("m3t1r") / "models"
    candidates = [Path(str(packaged)), Path(__file__).resolve().parents[3] / "models"]
    for folder in candidates:  # installed wheel first, then a source checkout (editable install)
        urdf, closures = folder / "m3t1r.urdf", folder / "m3t1r.closures.yaml"
        if urdf.is_file() and closures.is_file():
            return urdf, closures
    raise ModelFileError(candidates[-1], "the packaged nominal model files are missing")


@dataclass(frozen=True, eq=False)
class Mechanism:
    """A closed-chain machine: Pinocchio tree model, closures, actuation, task and workspace.

    `model` is the open tree (one chain per actuator from `base`); the closures make it a mechanism.
    Joint values are Pinocchio configuration vectors (nq == nv: revolute and prismatic joints, a
    URDF's continuous joints built as revolute ones without limits).
    `task`: what inverse kinematics commands (schema v1 files: position and yaw of `platform_frame`);
    `workspace`: where simulations and plans sample (None: not declared, schema v1);
    `locked_joints`: passive joints held at their home value: declared by the closures file
    (`locked_joints`, as `save` writes it), then those found redundant at load (a gauge);
    `notes`: what `load` changed or assumed (assembled home, locked joints, missing limits);
    `home_assembly`: how the home was assembled when the file's did not close (None: it did).
    The visual geometry loads on first use of `visual_model` (kinematics never needs the meshes).
    """

    model: pin.Model
    closures: tuple[ClosureSpec, ...]
    actuated_joints: tuple[str, ...]
    principal_chains: dict[str, tuple[str, ...]]
    platform_frame: str
    home: np.ndarray
    urdf_path: Path
    closures_path: Path

    closures_document: dict | None = field(default=None, repr=False, compare=False)
    """The closures file as read (a YAML mapping), so that `save` never re-reads a file that may have changed."""
    task: TaskSpec = cast(TaskSpec, None)  # None: the platform frame's task, which __post_init__ sets
    workspace: WorkspaceSpec | None = None
    locked_joints: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    home_assembly: HomeAssembly | None = None
    source: str = "urdf"
    """What `urdf_path` is: "urdf", or "mjcf" (tree and closures read from an MJCF file; `save` writes a URDF pair)."""
    visual_cache: dict = field(default_factory=dict, repr=False, compare=False)
    """Holds the visual geometry once loaded; shared by the copies `with_model`/`with_home` make (same tree)."""

    def __post_init__(self) -> None:
        if self.task is None:
            object.__setattr__(self, "task", TaskSpec(self.platform_frame))

    @property
    def visual_model(self) -> pin.GeometryModel:
        """Visual geometry of the URDF (meshes resolved next to it), loaded on first use.

        Raises ModelFileError naming the URDF when a mesh cannot be found or read.
        """
        if "geometry" not in self.visual_cache:
            self.visual_cache["geometry"] = _load_visual(self.urdf_path, self.model)
        return self.visual_cache["geometry"]

    @classmethod
    def load(cls, urdf: str | Path | None = None, closures: str | Path | None = None) -> "Mechanism":
        """Load a description: the packaged nominal one by default, or any URDF + closures pair.

        With a URDF and no closures file, the URDF's pair is loaded (`paired_closures`):
        `NAME.urdf` pairs with `NAME.closures.yaml`. A URDF written by `save` records its closures
        file's sha256, and a closures file of another sha256 is refused, naming both files, so a
        URDF never loads with the closures of another machine. A URDF without a pair beside it and
        without a recorded sha256 gets the packaged nominal closures (a plain URDF of this machine).
        An MJCF file (root `<mujoco>`) holds its own closures and actuators (`m3t1r.model.mjcf_io`);
        `closures` then names its optional sidecar (default `NAME.closures.yaml` beside `NAME.xml`).

        Raises ModelFileError (naming the file and the field, joint or frame) when a file is
        missing, Pinocchio rejects the URDF, the two files are not a pair, the closures name
        unknown frames or joints, a joint is not a 1-DoF prismatic, revolute or continuous joint,
        or the home pose does not close.
        """
        if urdf is None:
            nominal_urdf, nominal_closures = nominal_model_paths()
            urdf = nominal_urdf
            closures = closures if closures is not None else nominal_closures
        urdf_path = Path(urdf)
        if not urdf_path.is_file():
            raise ModelFileError(urdf_path, "file not found" if not urdf_path.exists() else "not a regular file")
        if is_mjcf(_read_bytes(urdf_path)):
            return _load_mjcf(urdf_path, None if closures is None else Path(closures))
        recorded = _recorded_sha256(urdf_path)
        if closures is None and recorded is None and not _paired_path(urdf_path).is_file():
            closures = nominal_model_paths()[1]
        if closures is None:
            closures_path, data = paired_closures(urdf_path, recorded=recorded)
        else:
            closures_path, data = _closures_of(urdf_path, Path(closures), recorded)
        return _finish(_load_urdf(urdf_path), _parse_yaml(closures_path, data), urdf_path, closures_path)

    # Convenience views, all derived from the model (no duplicated state).
    @property
    def actuated_ids(self) -> np.ndarray:
        """Velocity indices of the actuated joints, in `actuated_joints` order."""
        return np.array([self.model.idx_vs[self.model.getJointId(n)] for n in self.actuated_joints])

    @property
    def passive_ids(self) -> np.ndarray:
        """Velocity indices of the joints the closures solve for (neither actuated nor locked), ascending."""
        mask = np.ones(self.model.nv, dtype=bool)
        mask[self.actuated_ids] = False
        mask[self.locked_ids] = False
        return np.flatnonzero(mask)

    @property
    def locked_ids(self) -> np.ndarray:
        """Velocity indices of the locked (gauge) joints, in `locked_joints` order."""
        return np.array([self.model.idx_vs[self.model.getJointId(n)] for n in self.locked_joints], dtype=int)

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

    def joint_units(self, names: tuple[str, ...] | None = None) -> tuple[str, ...]:
        """ "m" (prismatic) or "rad" (revolute) per named joint (default: actuated): the unit of its value."""
        names = self.actuated_joints if names is None else names
        return tuple(
            "m" if self.model.joints[self.model.getJointId(n)].shortname().startswith("JointModelP") else "rad"
            for n in names
        )

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
        machine's assembled home and what load derived recorded (`_record_derived`).
        """
        doc = (
            copy.deepcopy(self.closures_document)
            if self.closures_document is not None
            else _parse_yaml(self.closures_path, _read_bytes(self.closures_path))
        )
        doc["home"] = {
            self.model.names[j]: float(self.home[self.model.idx_qs[j]]) for j in range(1, self.model.njoints)
        }
        _record_derived(doc, self)
        closures_path = paired_closures_path(urdf) if closures is None else Path(closures)
        header = (
            f"# Closures of {Path(urdf).name} (written with it as a pair; its URDF records this file's sha256); "
            "home re-assembled for its geometry; rows and locked joints as load derived them. "
            "Schema: models/README.md\n"
        )
        closures_bytes = (header + yaml.safe_dump(doc, sort_keys=False)).encode("utf-8")
        del closures_path
        if self.source == "mjcf":  # no URDF to rewrite: the tree itself, its declared frames left to the closures
            urdf_bytes = tree_urdf_bytes(
                self.model,
                self.model.name or Path(urdf).stem,
                closures_sha256(closures_bytes),
                skip_frames=tuple(doc.get("frames") or ()),
            )
            return urdf_bytes, closures_bytes
        return calibrated_urdf_bytes(self.urdf_path, self.model, closures_sha256(closures_bytes)), closures_bytes

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
        return dataclasses.replace(self, model=model, home=self.home.copy())

    def with_home(self, home: np.ndarray) -> "Mechanism":
        """The same machine with another home configuration (nq) [m, rad]."""
        return dataclasses.replace(self, home=np.array(home, dtype=float))


def _finish(
    model: pin.Model, doc: dict, urdf_path: Path, closures_path: Path, source: str = "urdf", notes: tuple[str, ...] = ()
) -> Mechanism:
    """The Mechanism of a tree and its closures document, settled (`_settled`), its notes warned."""
    try:
        mechanism = _build(model, doc, urdf_path, closures_path)
    except ModelFileError:
        raise
    except (TypeError, ValueError, AttributeError, OverflowError, KeyError) as exc:
        # Safety net for a malformed cell the field checks did not foresee.
        raise ModelFileError(closures_path, f"malformed closures file: {type(exc).__name__}: {exc}") from None
    mechanism = _settled(dataclasses.replace(mechanism, closures_document=copy.deepcopy(doc), source=source))
    mechanism = dataclasses.replace(mechanism, notes=notes + mechanism.notes)
    for note in mechanism.notes:
        warnings.warn(f"{mechanism.closures_path.name}: {note}", ModelWarning, stacklevel=3)
    return mechanism


def _load_mjcf(path: Path, closures: Path | None) -> Mechanism:
    """An MJCF mechanism (`m3t1r.model.mjcf_io`), with its sidecar closures file when given or beside it."""
    sidecar_path = closures if closures is not None else mjcf_sidecar_path(path)
    sidecar = None
    if closures is not None or sidecar_path.is_file():
        sidecar = _parse_yaml(sidecar_path, _read_bytes(sidecar_path), required=())
    tree = read_mjcf(path, _read_bytes(path), sidecar, sidecar_path)
    return _finish(tree.model, tree.document, path, sidecar_path if sidecar is not None else path, "mjcf", tree.notes)


def _record_derived(doc: dict, mechanism: Mechanism) -> None:
    """Write into a closures document what load derived, so that the pair reloads as this machine:
    each closure's enforced rows (dependent rows dropped), the locked gauge joints, and the declared
    frames' placements (calibration identifies them; the URDF cannot hold them). On another
    geometry (a calibrated or perturbed copy) the dropped rows no longer hold by themselves and
    the gauges are no longer exact, so re-deriving them there would describe another machine."""
    entries = doc.get("closures")
    if isinstance(entries, list) and len(entries) == len(mechanism.closures):
        for entry, spec in zip(entries, mechanism.closures):
            if isinstance(entry, dict):
                entry["rows"] = list(spec.rows)
        # A closure all of whose rows depended on the others constrains nothing: a file cannot say rows: [].
        doc["closures"] = [entry for entry, spec in zip(entries, mechanism.closures) if spec.rows]
    if mechanism.locked_joints:
        doc["locked_joints"] = list(mechanism.locked_joints)
    if "task" not in doc and mechanism.task is not None:  # derived at load: another geometry must not re-derive it
        doc["task"] = task_entry(mechanism.task)
    if doc.get("frames"):
        doc["frames"] = declared_frame_entries(mechanism.model, doc)


def _load_urdf(path: Path) -> pin.Model:
    """The URDF's tree, with its continuous joints built as revolute ones (`urdf_io.revolute_urdf_text`)."""
    text = revolute_urdf_text(path, _read_bytes(path))
    try:
        model = pin.buildModelFromUrdf(str(path)) if text is None else pin.buildModelFromXML(text)
    except Exception as exc:  # Pinocchio raises bare RuntimeError/ValueError for bad XML
        raise ModelFileError(path, f"Pinocchio rejected the URDF: {exc}") from None
    for j in range(1, model.njoints):
        if model.nqs[j] != 1 or model.nvs[j] != 1:
            raise ModelFileError(
                path,
                f"joint '{model.names[j]}' is not a 1-DoF revolute/prismatic/continuous "
                f"joint (nq={model.nqs[j]}); multi-DoF joints are not supported",
            )
    refuse_mimic_joints(path, _read_bytes(path), list(model.names)[1:])
    return model


def _load_visual(path: Path, model: pin.Model) -> pin.GeometryModel:
    try:
        if is_mjcf(_read_bytes(path)):
            raise ModelFileError(path, "the visual geometry of an MJCF model is not loaded")
        return pin.buildGeomFromUrdf(model, str(path), pin.GeometryType.VISUAL, package_dirs=[str(path.parent)])
    except ModelFileError:
        raise
    except Exception as exc:  # a mesh not found or unreadable
        raise ModelFileError(path, f"cannot load the visual geometry: {exc}") from None


def paired_closures(urdf: str | Path, *, recorded: str | None | Literal[False] = False) -> tuple[Path, bytes]:
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
    data = _read_bytes(urdf)  # its errors name `urdf` already
    try:
        return recorded_closures_sha256(data)
    except ModelFileError as exc:  # names the file "URDF": name it by its path (which may hold ": ")
        raise ModelFileError(urdf, str(exc).removeprefix(f"{exc.path}: ")) from None


def _read_bytes(path: Path) -> bytes:
    return read_input(path, ModelFileError)


def _closures_of(urdf: Path, closures: Path, recorded: str | None) -> tuple[Path, bytes]:
    if recorded is None:
        return closures, _read_bytes(closures)
    data = None if not closures.exists() else _read_bytes(closures)
    if data is not None and closures_match(data, recorded):
        return closures, data
    for pending in reversed(pending_temporaries(closures)):
        try:
            staged = pending.read_bytes()
        except OSError:
            continue
        if closures_match(staged, recorded):
            return closures, staged
    if data is None:
        raise ModelFileError(
            closures,
            f"file not found: {urdf.name} records closures sha256 {recorded[:16]}..., "
            "and no closures file with it is there",
        )
    raise ModelFileError(
        closures,
        f"not the closures file of {urdf}: the URDF records closures sha256 {recorded[:16]}..., "
        f"this file's content has {closures_sha256(data)[:16]}... The two files were not written "
        "together (one was rewritten by another run, or copied from another machine, or its content "
        "edited: comments, layout and line ends do not count); load the URDF with the closures file "
        "written with it; to pair these two deliberately, delete the line `<!-- m3t1r pair: ... -->` "
        "from the URDF (it then loads with any closures file; saving records a new pair)",
    )


def _parse_yaml(
    path: Path, data: bytes, required: tuple[str, ...] = ("actuated_joints", "closures", "platform_frame", "home")
) -> dict:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ModelFileError(path, f"line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x})") from None
    try:
        doc = load_closures_yaml(text, path)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ModelFileError(path, f"{where}not valid YAML: {problem}") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # e.g. a date 2001-13-01
        raise ModelFileError(path, f"cannot read closures YAML: {type(exc).__name__}: {exc}") from None
    if not isinstance(doc, dict):
        raise ModelFileError(path, "closures file must be a YAML mapping")
    for key in required:
        if key not in doc:
            raise ModelFileError(path, f"missing field '{key}'")
    return doc


def _build(model: pin.Model, doc: dict, urdf_path: Path, path: Path) -> Mechanism:
    described = read_description(model, doc, urdf_path, path)
    return Mechanism(
        model,
        described.closures,
        described.actuated_joints,
        described.principal_chains,
        described.platform_frame,
        described.home,
        urdf_path,
        path,
        task=described.task,
        workspace=described.workspace,
        locked_joints=described.locked_joints,
    )


def _settled(mechanism: Mechanism) -> Mechanism:
    """The mechanism with its actuator limits, home and closure system made usable, and notes on what
    that changed: missing limits replaced, an approximate home assembled, gauge joints locked."""
    notes = list(_replace_missing_limits(mechanism)) + _unbounded_passive_joints(mechanism)
    system = ClosureSystem(mechanism.model, mechanism.closures)
    passive = mechanism.passive_ids
    home, assembly = mechanism.home, None
    if not np.abs(system.evaluate(home, False)[0]).max(initial=0.0) <= HOME_TOLERANCE:  # NaN fails too
        home, assembly = _assembled_home(mechanism, system, passive)
        notes.append(assembly.note(HOME_TOLERANCE))
    _refuse_home_beyond_limits(mechanism, home)
    redundancy, full_rank = system.redundancy(home, passive)
    if full_rank > redundancy.rank:
        raise ModelFileError(
            mechanism.closures_path,
            f"the closures hold the actuators: the rows have rank {full_rank} over every joint but "
            f"{redundancy.rank} over the passive ones (the actuators are not independent inputs)",
        )
    if redundancy.locked:
        for frame in dict.fromkeys((mechanism.platform_frame_id, mechanism.model.getFrameId(mechanism.task.frame))):
            speed = system.free_motion(home, passive, frame)
            if speed > 1e-9:
                raise ModelFileError(
                    mechanism.closures_path,
                    _free_motion_refusal(mechanism, system, home, frame, len(redundancy.locked), speed),
                )
    locked = tuple(_joint_name(mechanism.model, v) for v in redundancy.locked)
    closures = mechanism.closures
    if locked:  # joints the file declares locked are not noted again
        notes.append(
            f"passive joint(s) {', '.join(locked)} locked at their home value: their motion is "
            "already spanned by the other passive joints (a gauge, e.g. a cut joint modelled twice)"
        )
    if redundancy.dropped:
        closures = without_rows(closures, redundancy.dropped)
        notes.append(
            f"{len(redundancy.dropped)} closure row(s) dropped as dependent on the others: "
            + ", ".join(_row_names(mechanism.closures, redundancy.dropped))
        )
    settled = dataclasses.replace(
        mechanism, closures=closures, home=home, locked_joints=mechanism.locked_joints + locked, home_assembly=assembly
    )
    return dataclasses.replace(settled, task=_task_of(settled, notes), notes=tuple(notes))


def _free_motion_refusal(
    mechanism: Mechanism, system: ClosureSystem, home: np.ndarray, frame: int, free: int, speed: float
) -> str:
    """Why the closures leave `free` degrees of freedom with the actuators held, where `frame` moves
    along some of them (`speed` [m or rad per unit joint speed] at most): how many move it, the
    joints that move most along the one that moves it fastest, and how many move nothing but
    passive joints (idle spins, which alone would be locked)."""
    passive = mechanism.passive_ids
    _, jacobian = system.evaluate(home, True)
    rows = jacobian[:, passive]
    null = np.linalg.svd(rows)[2][closure_rank(rows) :].T if rows.shape[0] else np.eye(len(passive))
    frame_jacobian = pin.getFrameJacobian(mechanism.model, system.data, frame, pin.LOCAL_WORLD_ALIGNED)
    _, motion, directions = np.linalg.svd(frame_jacobian[:, passive] @ null)
    moving = int(np.count_nonzero(motion > 1e-9))
    fastest = null @ directions[0]
    names = [_joint_name(mechanism.model, int(passive[k])) for k in np.argsort(-np.abs(fastest))[:3]]
    idle = free - moving
    return (
        f"the closures leave {free} degree(s) of freedom beyond the actuators: with the actuators held, "
        f"frame '{mechanism.model.frames[frame].name}' can still move along {moving} of them ({speed:.2g} per "
        f"unit joint speed; mostly joints {', '.join(names)})"
        + (f", and {idle} move(s) only passive joints (idle spins: load locks those when alone)" if idle else "")
        + "; rows or closures are missing"
    )


def _task_of(mechanism: Mechanism, notes: list[str]) -> TaskSpec:
    """The declared task, or without one the task the actuators command at home (`model.defaults`),
    with a note when that is not schema 1's position-and-yaw task."""
    if mechanism.closures_document is None or "task" in mechanism.closures_document:
        return mechanism.task
    derived = default_task(
        ClosureSystem(mechanism.model, mechanism.closures),
        mechanism.home,
        mechanism.actuated_ids,
        mechanism.passive_ids,
        mechanism.platform_frame,
    )
    if derived is None or derived == mechanism.task:
        return mechanism.task
    notes.append(
        f"no task declared: inverse kinematics, plans and reports take the {task_words(derived)} "
        "(the coordinates the actuators command at home); declare `task:` to choose others "
        "(models/README.md)"
    )
    return derived


def _joint_name(model: pin.Model, velocity_index: int) -> str:
    return next(model.names[j] for j in range(1, model.njoints) if model.idx_vs[j] == velocity_index)


def _row_names(closures: tuple[ClosureSpec, ...], dropped: tuple[int, ...]) -> list[str]:
    names = [f"{spec.name}[{r}]" for spec in closures for r in spec.rows]
    return [names[k] for k in dropped]


def _assembled_home(
    mechanism: Mechanism, system: ClosureSystem, passive: np.ndarray
) -> tuple[np.ndarray, HomeAssembly]:
    """The assembly nearest the given home (`model.assembly`), or ModelFileError when there is none
    near it or it leaves a joint's limits."""
    home, assembly = assemble_home(mechanism.model, mechanism.closures, system, mechanism.home, passive)
    given = (
        f"home does not close: closure '{assembly.worst}' residual {assembly.given_residual:.3e} > {HOME_TOLERANCE:g}"
    )
    if not assembly.residual <= HOME_TOLERANCE:
        raise ModelFileError(
            mechanism.closures_path,
            f"{given}, and Newton from the given values reached only {assembly.residual:.1e}; "
            + _with_actuators_free(mechanism, system),
        )
    for name, value, lower, upper in limits_violated(mechanism.model, home, passive)[:1]:
        raise ModelFileError(
            mechanism.closures_path,
            f"{given}; the assembly nearest the given values puts joint '{name}' at {value:.6g}, "
            f"beyond its URDF limits [{lower:.6g}, {upper:.6g}] (give home values of the passive "
            "joints near the assembly mode wanted)",
        )
    return home, assembly


def _refuse_home_beyond_limits(mechanism: Mechanism, home: np.ndarray) -> None:
    """ModelFileError (the closures file, where home is given) when home, as given or assembled,
    leaves a joint's usable URDF limits: an actuator there is a slider value every solve refuses."""
    model = mechanism.model
    for name, value, lower, upper in limits_violated(model, home, np.arange(model.nv))[:1]:
        raise ModelFileError(
            mechanism.closures_path,
            f"home puts joint '{name}' at {value:.6g}, beyond its URDF limits [{lower:.6g}, {upper:.6g}]: "
            "give a home inside them, or limits that hold it",
        )


def _with_actuators_free(mechanism: Mechanism, system: ClosureSystem) -> str:
    """Advice for a home that does not assemble with the actuators held: the same solve with every
    joint free either closes within the joint limits (then the actuator values it needed are given)
    or does not (then the closures may not hold on this tree at all)."""
    model = mechanism.model
    every = np.arange(model.nv)
    home, assembly = assemble_home(model, mechanism.closures, system, mechanism.home, every)
    beyond = limits_violated(model, home, every)[:1]
    if assembly.residual <= HOME_TOLERANCE and not beyond:
        values = ", ".join(
            f"{name}: {home[model.idx_qs[model.getJointId(name)]] + 0.0:.4g}" for name in mechanism.actuated_joints
        )
        return (
            f"with the actuators free too, it closes with them at {{{values}}}: give actuator home values "
            "near those, a little inside the actuators' reach (the nearest values that close are often at "
            "its edge, where the loops are singular)"
        )
    found = (
        f"with every joint free it closes only with joint '{beyond[0][0]}' at {beyond[0][1]:.4g}, beyond its "
        f"URDF limits [{beyond[0][2]:.4g}, {beyond[0][3]:.4g}]"
        if assembly.residual <= HOME_TOLERANCE
        else f"even with every joint free it reaches only {assembly.residual:.1e} from the given values"
    )
    return (
        f"{found}: the closures may not all hold on this model (check each closure's type, 3D or 6D, its rows "
        "and frames, and that the model's joints are the mechanism's: a ball joint given as one revolute, say), "
        "or the given values are far from any assembly"
    )


def _replace_missing_limits(mechanism: Mechanism) -> list[str]:
    """Actuators without usable URDF limits (lower >= upper, as Pinocchio gives for a missing
    <limit>) take the workspace's actuator interval, else none (unbounded); one note per joint."""
    model, notes = mechanism.model, []
    box = mechanism.workspace.actuators if mechanism.workspace is not None else ()
    intervals = {name: (lo, hi) for name, lo, hi in box}
    for name in mechanism.actuated_joints:
        k = model.idx_qs[model.getJointId(name)]
        if model.lowerPositionLimit[k] < model.upperPositionLimit[k]:
            continue
        lo, hi = intervals.get(name, (-np.inf, np.inf))
        lower, upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
        lower[k], upper[k] = lo, hi
        model.lowerPositionLimit, model.upperPositionLimit = lower, upper
        source = "the workspace box's" if name in intervals else "no"
        notes.append(f"actuator '{name}' has no usable URDF limits; {source} limits [{lo:g}, {hi:g}] used instead")
    return notes


def _unbounded_passive_joints(mechanism: Mechanism) -> list[str]:
    """Passive joints without usable URDF limits (an empty or absent `<limit>`, which Pinocchio reads
    as [0, 0], or a continuous joint) made unbounded: published URDFs mean "not given", not "locked"."""
    model = mechanism.model
    actuated = set(mechanism.actuated_joints)
    lower, upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
    unbounded = []
    for j in range(1, model.njoints):
        k = model.idx_qs[j]
        if model.names[j] not in actuated and not lower[k] < upper[k]:
            lower[k], upper[k] = -np.inf, np.inf
            unbounded.append(model.names[j])
    if not unbounded:
        return []
    model.lowerPositionLimit, model.upperPositionLimit = lower, upper
    shown = ", ".join(unbounded[:6]) + (f" and {len(unbounded) - 6} more" if len(unbounded) > 6 else "")
    return [
        f"{len(unbounded)} passive joint(s) without usable URDF limits ({shown}): taken as unbounded "
        "(an empty <limit/> or a continuous joint gives no range)"
    ]
