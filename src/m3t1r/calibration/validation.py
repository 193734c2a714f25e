"""Validation of a calibrated model on a measurement campaign: predict every measured row, compare.

Each row of a measurement file (the format `m3t1r calibrate` reads: joint readings named by joint,
x, y, z and optionally qx, qy, qz, qw, all lengths in the file's unit) is predicted as

    T_predicted = measurement_frame . FK(readings) . marker

with the model kind, the measured frame, the measurement frame and the marker taken from the
calibration report (`m3t1r calibrate --report`): for the M machine, FK is the closed-loop forward
kinematics of the calibrated URDF and its closures file, each slider set assembled from home (the
branch the calibration used); for a serial robot, the POE forward kinematics of the report's chain
(base frame to tool frame) on the calibrated URDF, at the readings moved by the joint compliance
under gravity the report holds (`calibrate --serial --compliance`: q + c tau(q), tau from the
calibrated URDF's inertias), and with the report's constant joints (`--joint NAME=VALUE`) where
the file has no column for them.

Per row: position error |p_predicted - p_measured| [m], and when orientation was measured the
rotation angle |log3(R_measured^T R_predicted)| [rad] and, for a task commanding a yaw, the heading (yaw)
error of the platform implied by the measurement, yaw(R_f^T R_measured R_m^T) - yaw(R_platform)
[rad, wrapped to (-pi, pi]].

Flags (5-sigma-equivalent chi-square gate, as `m3t1r.identification.outlier_poses` applies it in
calibration): a row's statistic is d^2 = |dp|^2 / sigma_p^2 (+ |dr|^2 / sigma_r^2 with
orientation), dr = log3(R_measured^T R_predicted), sigma_p and sigma_r from the report's noise
model. Under that noise d^2 is chi^2 with k = 3 (position only) or 6 degrees of freedom; the row is
flagged when d^2 / s^2 exceeds the chi^2_k quantile whose upper tail has the two-sided normal tail
probability of 5 sigma (5.7e-7): d^2 > 31.8 s^2 for k = 3 and 39.5 s^2 for k = 6 (a position-only
row is flagged beyond 5.64 s sigma_p of 3-D distance; the naive gate "distance over sigma_p sqrt(3)
above 5", i.e. beyond 8.66 sigma_p, would be an 8.1-sigma gate, tail probability 4e-16).
s^2 = max(1, v) with v the report's `variance_factor` (chi^2 per degree of freedom of the
calibration's own residual; 1 when the report has none): unmodelled effects the calibration
already saw widen the gate instead of flagging every row. Unlike `outlier_poses`, the factor is
not re-estimated from the rows being validated: it is fixed before they are seen, so a model (or
a measurement setup) that predicts the whole file badly gets every row flagged rather than a gate
widened to fit it. The sigma-equivalent of a row is z with P(|N(0,1)| > z) = P(chi^2_k > d^2 / s^2).
The prediction itself is taken as exact: its uncertainty after a calibration on N >> p poses is
small against the noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pinocchio as pin
import scipy.special

from m3t1r.calibration.identification import OUTLIER_SIGMA, outlier_gate
from m3t1r.calibration.measurement_setup import LENGTH_UNITS, MeasurementSetup
from m3t1r.calibration.serial import compliant_readings
from m3t1r.calibration.serial_robots import load_serial_urdf, serial_chain_of
from m3t1r.errors import InvalidInputError, M3t1rError, ModelFileError
from m3t1r.io.instruments.records import CONVERTED_COLUMNS
from m3t1r.io.paths import read_bounded, size_refusal
from m3t1r.io.poses import measurement_column, poses_from_table
from m3t1r.io.strict_json import parse_strict_json
from m3t1r.io.tables import read_table
from m3t1r.metrics import PoseErrors, pose_errors_between
from m3t1r.model.description import Mechanism
from m3t1r.model.kinematics import ClosedLoopSolver
from m3t1r.model.poe import log3_batch, tool_poses

__all__ = [
    "CalibrationReport",
    "Campaign",
    "Validation",
    "read_report",
    "read_campaign",
    "validate",
    "sigma_equivalent",
]

_QUATERNION = ("qx", "qy", "qz", "qw")


@dataclass(frozen=True)
class CalibrationReport:
    """What validation needs from a calibration report (`read_report`).

    kind: "closed_loop" or "serial"; setup: measurement frame and marker (m); noise: tracker
    (position [m], rotation [rad]) standard deviations; units: the calibration input's length unit
    ("m" or "mm"; None when the report does not say); measured_frame: the frame measured (the
    platform frame P_I, or the serial tool frame; None when absent); tool, base, chain: the serial
    chain (None / () for the M machine); variance_factor: the calibration's chi^2 per degree of
    freedom (None when the report has none); compliance: {joint: c} [rad/Nm, m/N] fitted by
    `calibrate --serial --compliance` (readings q -> q + c tau(q)); constant_joints: {joint: value}
    [rad, m] of chain joints the calibration's file did not log (`--joint NAME=VALUE`); robot: the
    nominal robot the serial calibration started from (a URDF path or an example robot's name, as
    given); position_only: whether the calibration's tracker measured positions only.
    """

    path: Path
    kind: Literal["closed_loop", "serial"]
    setup: MeasurementSetup
    noise: tuple[float, float]
    units: str | None
    measured_frame: str | None
    tool: str | None = None
    base: str | None = None
    chain: tuple[str, ...] = ()
    variance_factor: float | None = None
    compliance: Mapping[str, float] = field(default_factory=dict)
    constant_joints: Mapping[str, float] = field(default_factory=dict)
    robot: str | None = None
    position_only: bool = False


def _field(document: Mapping, dotted: str, path: Path) -> object:
    """document["a"]["b"] for "a.b", or InvalidInputError naming the file and the field."""
    value: object = document
    for key in dotted.split("."):
        if not isinstance(value, Mapping) or key not in value:
            raise InvalidInputError(f"{path}: report field '{dotted}' is missing")
        value = value[key]
    return value


def _positive(document: Mapping, dotted: str, path: Path) -> float:
    value = _field(document, dotted, path)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise InvalidInputError(f"{path}: report field '{dotted}' must be a positive number, got {value!r}")
    return float(value)


def _load_json(path: Path) -> Mapping:
    try:
        data = read_bounded(path)
        if data is None:
            raise InvalidInputError(f"{path}: {size_refusal()}")
        text = data.decode("utf-8")
    except FileNotFoundError:
        raise InvalidInputError(f"{path}: calibration report not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidInputError(f"{path}: cannot read the calibration report: {exc}") from None
    try:
        document = parse_strict_json(text)
    except ValueError as exc:  # json.JSONDecodeError included
        raise InvalidInputError(f"{path}: not a JSON report ({exc})") from None
    if not isinstance(document, Mapping):
        raise InvalidInputError(f"{path}: a calibration report is a JSON object")
    return document


def read_report(path: str | Path) -> CalibrationReport:
    """Read the fields validation needs from a calibration report (JSON of `m3t1r calibrate`).

    Required: kind, noise_model.position_m, noise_model.rotation_rad, measurement_frame, marker,
    and for kind "serial" nominal_model.tool and nominal_model.chain. Raises InvalidInputError
    naming the file and the field for a missing or malformed one or another kind.
    """
    source = Path(path)
    document = _load_json(source)
    kind = _field(document, "kind", source)
    if kind not in ("closed_loop", "serial"):
        raise InvalidInputError(
            f"{source}: report field 'kind' is {kind!r}; validation reads 'closed_loop' or 'serial'"
        )
    for key in ("measurement_frame", "marker"):
        _field(document, key, source)
    try:
        setup = MeasurementSetup.from_report(document)
    except InvalidInputError as exc:
        raise InvalidInputError(f"{source}: {exc}") from None
    noise = (
        _positive(document, "noise_model.position_m", source),
        _positive(document, "noise_model.rotation_rad", source),
    )
    units = document.get("input", {}).get("units") if isinstance(document.get("input"), Mapping) else None
    if units is not None and units not in LENGTH_UNITS:
        raise InvalidInputError(
            f"{source}: report field 'input.units' is {units!r}; expected one of {sorted(LENGTH_UNITS)}"
        )
    measured = document.get("measured_frame")
    factor = _variance_factor(document, source)
    if kind == "closed_loop":
        return CalibrationReport(source, "closed_loop", setup, noise, units, measured, variance_factor=factor)
    tool, chain = _field(document, "nominal_model.tool", source), _field(document, "nominal_model.chain", source)
    base = document["nominal_model"].get("base")
    if not isinstance(tool, str) or not (base is None or isinstance(base, str)):
        raise InvalidInputError(
            f"{source}: report fields 'nominal_model.tool' / 'nominal_model.base' must be frame names"
        )
    if not isinstance(chain, list) or not chain or not all(isinstance(n, str) for n in chain):
        raise InvalidInputError(f"{source}: report field 'nominal_model.chain' must be a list of joint names")
    position_only = isinstance(document.get("input"), Mapping) and document["input"].get("position_only") is True
    return CalibrationReport(
        source,
        "serial",
        setup,
        noise,
        units,
        measured,
        tool,
        base,
        tuple(chain),
        factor,
        _joint_numbers(document, "compliance", source, chain),
        _joint_numbers(document, "constant_joints", source, chain),
        robot if isinstance(robot := document["nominal_model"].get("robot"), str) else None,
        position_only,
    )


def _joint_numbers(document: Mapping, key: str, path: Path, chain: list[str]) -> dict[str, float]:
    """The report's optional {joint: number} field `key`, every joint one of the chain's."""
    value = document.get(key) or {}
    if not isinstance(value, Mapping) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value.values()
    ):
        raise InvalidInputError(f"{path}: report field '{key}' must map joint names to numbers, got {value!r}")
    unknown = sorted(set(value) - set(chain))
    if unknown:
        raise InvalidInputError(
            f"{path}: report field '{key}' names {', '.join(unknown)}, not in 'nominal_model.chain'"
        )
    return {str(k): float(v) for k, v in value.items()}


def _variance_factor(document: Mapping, path: Path) -> float | None:
    """The report's optional `variance_factor` (a non-negative number or null)."""
    value = document.get("variance_factor")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
        raise InvalidInputError(
            f"{path}: report field 'variance_factor' must be a non-negative number or null, got {value!r}"
        )
    return float(value)


@dataclass(frozen=True)
class Campaign:
    """Rows of a measurement file in SI units: readings (N, n) [m or rad] in `columns` order,
    measured poses (N, 4, 4) [m] (identity rotation when position-only), each row's file line, and
    its `source` (N,) (where `m3t1r convert` found the pose in the instrument's file; None without
    that column)."""

    path: Path
    columns: tuple[str, ...]
    readings: np.ndarray
    measured: np.ndarray
    position_only: bool
    lines: np.ndarray
    units: str
    sources: np.ndarray | None = None


def read_campaign(
    path: str | Path,
    columns: Sequence[str],
    prismatic: Sequence[bool],
    units: str = "m",
    optional: Sequence[str] = (),
    constants: Mapping[str, float] | None = None,
) -> Campaign:
    """Read a measurement CSV: the joint `columns`, optional columns (read and ignored, e.g. passive
    joint encoders, and `m3t1r convert`'s source and position_std), x, y, z and optionally qx, qy,
    qz, qw. Lengths (x, y, z and the columns whose `prismatic` flag is set) are in `units` and
    converted to m. `constants` {column: value [SI]}: a column the file may lack, then read as that
    value on every row. Raises DataFileError naming the
    file, line and column (missing file, unknown columns, non-numbers, non-unit quaternions)."""
    if units not in LENGTH_UNITS:
        raise InvalidInputError(f"units must be one of {sorted(LENGTH_UNITS)}, got {units!r}")
    scale = LENGTH_UNITS[units]
    constants = constants or {}
    required = tuple(c for c in columns if c not in constants) + ("x", "y", "z")
    table = read_table(
        path, required=required, optional=(*optional, *constants, *CONVERTED_COLUMNS), optional_groups=(_QUATERNION,)
    )
    readings = np.column_stack(
        [
            table.column(n) * (scale if p else 1.0) if table.has_column(n) else np.full(table.n_rows, constants[n])
            for n, p in zip(columns, prismatic)
        ]
    )
    position_only = not table.has_column("qw")
    measured = np.tile(np.eye(4), (table.n_rows, 1, 1))
    if not position_only:
        measured[:] = [pose.homogeneous for pose in poses_from_table(table)]
    measured[:, :3, 3] = np.column_stack([table.column(n) for n in ("x", "y", "z")]) * scale
    sources = table.column("source") if table.has_column("source") else None
    return Campaign(table.path, tuple(columns), readings, measured, position_only, table.line_numbers, units, sources)


@dataclass(frozen=True, eq=False)
class Validation:
    """Outcome of `validate` (module docstring), SI units (m, rad) throughout.

    lines: file line of every input row (N,); predictions: predicted measurements (N, 4, 4) in the
    measurement frame [m], NaN for a failed row; measured: the measured poses (N, 4, 4) [m];
    rows: indices of the rows that were predicted (M,), in file order; errors: their position and
    rotation errors (M,) (rotation NaN when position-only); heading: their heading (yaw) errors
    (M,) [rad] for a yaw task (the M machine) with orientation, else None; statistic: d^2 per predicted row (M,);
    sigmas: its sigma-equivalent z (M,); flagged: file lines of the rows beyond the gate;
    failures: (file line, reason) of the rows that could not be predicted; scale: the factor s
    (from the report's variance factor); gate: the chi^2_k quantile d^2 / s^2 is compared with;
    units: the file's length unit.
    residuals: the predicted rows' residuals normalised by the report's noise model (M, 3 or 6),
    [dp / sigma_p, dr / sigma_r] (N(0, 1) under that model); noise: that model (sigma_p [m],
    sigma_r [rad]); sources: every input row's `source` (N,), or None when the file has no such column.
    """

    path: Path
    kind: Literal["closed_loop", "serial"]
    lines: np.ndarray
    predictions: np.ndarray
    measured: np.ndarray
    rows: np.ndarray
    errors: PoseErrors
    heading: np.ndarray | None
    statistic: np.ndarray
    sigmas: np.ndarray
    flagged: tuple[int, ...]
    failures: tuple[tuple[int, str], ...]
    scale: float
    gate: float
    position_only: bool
    units: str
    residuals: np.ndarray | None = None
    noise: tuple[float, float] | None = None
    sources: np.ndarray | None = None


def sigma_equivalent(d2: np.ndarray, dof: int) -> np.ndarray:
    """z with P(|N(0, 1)| > z) = P(chi^2_dof > d2), per entry: a chi-square statistic in normal sigmas.

    From the log tail, so that z stays finite far beyond 8 sigma; where even the log tail
    underflows (d2 in the thousands), sqrt(d2) stands in (the two agree within a few percent there).
    """
    d2 = np.asarray(d2, dtype=float)
    z = -scipy.special.ndtri_exp(_chi2_log_tail(d2, dof) - math.log(2.0))
    return np.where(np.isfinite(z), z, np.sqrt(d2))


def _chi2_log_tail(d2: np.ndarray, dof: int) -> np.ndarray:
    """log P(chi^2_dof > d2), as scipy.stats' chi2.logsf computes it (without importing scipy.stats):
    the log of the upper tail above the median, log1p of minus the lower tail below it (where the
    upper tail is near 1 and its log would lose digits)."""
    median = 2.0 * scipy.special.gammaincinv(dof / 2.0, 0.5)
    with np.errstate(divide="ignore"):  # a tail that underflows to 0 gives -inf: sigma_equivalent's sqrt(d2)
        return np.where(d2 > median, np.log(scipy.special.chdtrc(dof, d2)), np.log1p(-scipy.special.chdtr(dof, d2)))


def _predict_closed_loop(
    calibrated: Path, report: CalibrationReport, units: str, measurements: Path, progress: Callable[[int], None] | None
) -> tuple[Campaign, np.ndarray, list[tuple[int, str]], bool]:
    """Platform poses (N, 4, 4) of the calibrated machine at each row's actuators (NaN where it fails),
    the rows that failed, and whether its task commands a yaw (then the heading error means something)."""
    mechanism = Mechanism.load(calibrated)
    if report.measured_frame not in (None, mechanism.platform_frame):
        raise InvalidInputError(
            f"{report.path}: report field 'measured_frame' is {report.measured_frame!r}, "
            f"but {calibrated} measures its platform frame '{mechanism.platform_frame}'"
        )
    model = mechanism.model
    names = mechanism.actuated_joints
    passive = tuple(model.names[j] for j in range(1, model.njoints) if model.names[j] not in names)
    campaign = read_campaign(
        measurements,
        tuple(map(measurement_column, names)),
        [_is_prismatic(model, n) for n in names],
        units,
        tuple(map(measurement_column, passive)),
    )
    poses = np.full((len(campaign.lines), 4, 4), np.nan)
    failures: list[tuple[int, str]] = []
    if len(campaign.readings):
        solved = ClosedLoopSolver(mechanism).forward_batch(campaign.readings)  # every row from home
        poses[solved.indices] = solved.poses
        failures = [(int(campaign.lines[f.index]), f"{calibrated.name}: {f.reason}") for f in solved.failures]
    if progress is not None:
        progress(len(campaign.readings))
    return campaign, poses, failures, mechanism.task.rotation == "yaw"


def _is_prismatic(model: pin.Model, joint: str) -> bool:
    """Whether a 1-DoF joint translates (its motion subspace has no angular part)."""
    j = model.getJointId(joint)
    data = model.joints[j].createData()
    model.joints[j].calc(data, pin.neutral(model))
    return not np.any(np.asarray(data.S)[3:])


def _predict_serial(
    calibrated: Path, report: CalibrationReport, units: str, measurements: Path
) -> tuple[Campaign, np.ndarray]:
    """Tool poses (N, 4, 4) in the chain's base frame of the calibrated serial robot at each row."""
    model, urdf = load_serial_urdf(calibrated)
    assert report.tool is not None, "read_report refuses a serial report without its tool"
    try:
        chain = serial_chain_of(model, urdf, calibrated, report.tool, report.base)
    except M3t1rError as exc:
        raise ModelFileError(
            calibrated, f"chain of report {report.path.name} (base {report.base}, tool {report.tool}): {exc}"
        ) from None
    if report.measured_frame not in (None, report.tool):
        raise InvalidInputError(
            f"{report.path}: report field 'measured_frame' is {report.measured_frame!r}, but "
            f"'nominal_model.tool' is {report.tool!r}"
        )
    if chain.joint_names != report.chain:
        raise InvalidInputError(
            f"{report.path}: report field 'nominal_model.chain' lists {list(report.chain)}, but "
            f"{calibrated} has {list(chain.joint_names)} from {report.base} to {report.tool}"
        )
    campaign = read_campaign(
        measurements,
        chain.joint_names,
        [not np.any(s[3:]) for s in chain.twists],
        units,
        constants=report.constant_joints,
    )
    try:
        q = compliant_readings(model, chain, campaign.readings, report.compliance)
    except InvalidInputError as exc:
        raise ModelFileError(calibrated, f"the compliance of report {report.path.name}: {exc}") from None
    return campaign, tool_poses(chain, model, q)


def _heading_errors(setup: MeasurementSetup, measured: np.ndarray, platform: np.ndarray) -> np.ndarray:
    """Heading errors [rad] of the platform implied by each measurement against the predicted one."""
    implied = setup.frame.rotation.T @ measured[:, :3, :3] @ setup.marker.rotation.T
    yaw = lambda r: np.arctan2(r[:, 1, 0], r[:, 0, 0])  # noqa: E731  (kinematics.yaw_of, batched)
    return np.angle(np.exp(1j * (yaw(implied) - yaw(platform[:, :3, :3]))))


def _whitened(
    predicted: np.ndarray, measured: np.ndarray, noise: tuple[float, float], position_only: bool
) -> np.ndarray:
    """Per-row residual [dp / sigma_p, dr / sigma_r] (M, 3 or 6), dr = log3(R_measured^T R_predicted)."""
    position = (predicted[:, :3, 3] - measured[:, :3, 3]) / noise[0]
    if position_only:
        return position
    logs, _ = log3_batch(np.swapaxes(measured[:, :3, :3], 1, 2) @ predicted[:, :3, :3])
    return np.hstack((position, logs / noise[1]))


def validate(
    measurements: str | Path,
    calibrated: str | Path,
    report: str | Path,
    units: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> Validation:
    """Predict every row of a measurement file with a calibrated model and compare (module docstring).

    units: the file's length unit, "m" or "mm" (default: the unit of the calibration's input, as
    the report records it, else m). progress: called with the number of rows done (M machine).
    Rows that cannot be predicted (a slider set that does not assemble or is beyond its limit) are
    listed in `failures` and the rest are assessed. Raises InvalidInputError when no row could be
    predicted, and the errors of `read_report`, `read_campaign` and the model loaders.
    """
    info = read_report(report)
    units = units or info.units or "m"
    calibrated = Path(calibrated)
    failures: list[tuple[int, str]] = []
    yaw_task = False
    if info.kind == "closed_loop":
        campaign, platform, failures, yaw_task = _predict_closed_loop(
            calibrated, info, units, Path(measurements), progress
        )
    elif info.setup.points:
        raise InvalidInputError(
            f"{info.path}: the calibration fitted {len(info.setup.points)} points per pose; "
            "validate reads one measured frame per row: score a file of several points with "
            "`m3t1r calibrate ... --validate FILE`"
        )
    else:
        campaign, platform = _predict_serial(calibrated, info, units, Path(measurements))
    ok = np.flatnonzero(np.all(np.isfinite(platform), axis=(1, 2)))
    if ok.size == 0:
        raise InvalidInputError(
            f"{campaign.path}: no row could be predicted; first failure, line {failures[0][0]}: {failures[0][1]}"
        )
    predictions = np.full_like(platform, np.nan)
    predictions[ok] = info.setup.measured_poses(platform[ok])
    measured = campaign.measured[ok]
    errors = pose_errors_between(predictions[ok], measured)
    if campaign.position_only:
        errors = PoseErrors(errors.position, np.full(ok.size, np.nan))
    whitened = _whitened(predictions[ok], measured, info.noise, campaign.position_only)
    dof = whitened.shape[1]
    statistic = np.sum(whitened**2, axis=1)
    scale = math.sqrt(max(1.0, info.variance_factor or 1.0))
    gate = outlier_gate(OUTLIER_SIGMA, dof)
    mask = statistic / scale**2 > gate
    heading = None if (not yaw_task or campaign.position_only) else _heading_errors(info.setup, measured, platform[ok])
    return Validation(
        path=campaign.path,
        kind=info.kind,
        lines=campaign.lines,
        predictions=predictions,
        measured=campaign.measured,
        rows=ok,
        errors=errors,
        heading=heading,
        statistic=statistic,
        sigmas=sigma_equivalent(statistic / scale**2, dof),
        flagged=tuple(int(campaign.lines[i]) for i in ok[mask]),
        failures=tuple(failures),
        scale=scale,
        gate=gate,
        position_only=campaign.position_only,
        units=units,
        residuals=whitened,
        noise=info.noise,
        sources=campaign.sources,
    )
