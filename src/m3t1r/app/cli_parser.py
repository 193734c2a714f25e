"""The argument parser of every `m3t1r` verb: argparse alone, no numeric library.

`m3t1r --help`, `m3t1r --version` and `m3t1r VERB --help` end here, before anything that computes
is imported (`m3t1r.app.cli` imports a verb's module only to run it). Keep this module's imports to
the standard library and the package's light ground (tests/test_startup.py checks what it loads).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from m3t1r._version import __version__
from m3t1r.app.cli_types import (
    count_number,
    finite_number,
    nonnegative_number,
    positive_number,
    seed_number,
    zero_or_count,
)
from m3t1r.io.instruments.names import FORMAT_DESCRIPTIONS
from m3t1r.model.native_status import compiled_newton_status

__all__ = [
    "build_parser",
    "add_campaign_options",
    "add_plan_parser",
    "add_validate_parser",
    "add_convert_parser",
    "AUTO",
    "NOISE_AUTO_HELP",
    "noise_or_auto",
]

AUTO = "auto"
NOISE_AUTO_HELP = (
    "; auto: estimated from the data, as the fit's RMS residual per coordinate scaled by "
    "rows / (rows - fitted parameters) for the degrees of freedom the fit used (refitted with "
    "the estimate and the outlier gate; the report says which noise was used)"
)


class _VersionAction(argparse.Action):
    """`--version`: the version and the compiled loop's status, worked out only when asked."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(f"m3t1r {__version__} (compiled Newton loop: {compiled_newton_status()})", file=sys.stdout)
        parser.exit()


class _DeprecatedAlias(argparse.Action):
    """An old spelling of an option: stores into the new option's destination, with a note on stderr."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        replacement = next(a.option_strings[0] for a in parser._actions if a.dest == self.dest and a is not self)
        print(f"note: {option_string} is deprecated; use {replacement}", file=sys.stderr)
        setattr(namespace, self.dest, values)


class _Parser(argparse.ArgumentParser):
    """argparse's parser, which gives back a file swallowed by a list option (below)."""

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        _give_back_positional(self, namespace)
        return namespace, extras


def _looks_like_file(value: str) -> bool:
    """A path, not a parameter name (`q12.dt[3]`) or NAME=SIGMA: a separator, a table suffix, a file."""
    return "/" in value or "\\" in value or value.lower().endswith((".csv", ".tsv", ".txt")) or Path(value).is_file()


def _give_back_positional(parser: argparse.ArgumentParser, namespace: argparse.Namespace) -> None:
    """`calibrate --fix A B meas.csv`: the list option took the measurement file as one of its values;
    the file goes back to `measurements` (the last value that looks like a file), else the positional
    is missing and argparse's own message says so."""
    if getattr(namespace, "measurements", "") is not None or not hasattr(namespace, "fix"):
        return
    for dest in ("fix", "prior"):
        values = getattr(namespace, dest)
        if values and _looks_like_file(values[-1]):
            namespace.measurements = values.pop()
            return
    parser.error("the following arguments are required: measurements")


def _comma_list(text: str) -> list[str]:
    """`--fix q12,q13.dt[3]`: a comma-separated list, each name stripped."""
    values = [v.strip() for v in text.split(",") if v.strip()]
    if not values:
        raise argparse.ArgumentTypeError(f"expected one or more names, got {text!r}")
    return values


class _ExtendLists(argparse.Action):
    """A repeatable list option: each occurrence takes one or more values, each a comma list."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        items = list(getattr(namespace, self.dest) or [])
        setattr(namespace, self.dest, items + [v for group in values for v in group])


def _add_deprecated_alias(parser: argparse.ArgumentParser, option: str, dest: str) -> None:
    parser.add_argument(option, dest=dest, action=_DeprecatedAlias, metavar="PATH", help=argparse.SUPPRESS)


def _add_model_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", metavar="URDF", help="machine URDF or MJCF (default: the packaged nominal model)")
    parser.add_argument("--closures", metavar="YAML", help="its closures file (default: URDF stem + .closures.yaml)")


def _add_noise_options(parser: argparse.ArgumentParser, estimable: bool = False) -> None:
    number, auto = (noise_or_auto, NOISE_AUTO_HELP) if estimable else (positive_number, "")
    parser.add_argument(
        "--noise-pos", type=number, default=10e-6, metavar="M", help="tracker position noise [m]" + auto
    )
    parser.add_argument(
        "--noise-rot", type=number, default=20e-6, metavar="RAD", help="tracker rotation noise [rad]" + auto
    )
    parser.add_argument(
        "--noise-act", type=nonnegative_number, default=1e-6, metavar="M", help="slider reading noise [m]"
    )


def build_parser(description: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of every verb; the verb's name is `args.verb`."""
    parser = _Parser(prog="m3t1r", description=description)
    parser.add_argument(
        "--version",
        action=_VersionAction,
        nargs=0,
        help="show the version and whether the compiled Newton loop is in use, and exit",
    )
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB")

    p = verbs.add_parser("fk", help="forward kinematics: slider sets -> platform poses")
    p.add_argument("actuators", help="CSV with one column per actuated joint [m]")
    p.add_argument("-o", "--output", required=True, help="poses CSV (x,y,z,qx,qy,qz,qw)")
    _add_model_options(p)

    p = verbs.add_parser("ik", help="inverse kinematics: task-frame poses -> actuator sets (the closures file's task)")
    p.add_argument("poses", help="CSV with the task's columns (M machine: x,y,z,theta) or x,y,z,qx,qy,qz,qw")
    p.add_argument("-o", "--output", required=True, help="slider CSV (columns named by actuated joint)")
    _add_model_options(p)

    p = verbs.add_parser("simulate", help="simulate an actual machine and its calibration measurements")
    p.add_argument("-n", type=count_number, default=20, help="number of poses (default 20)")
    p.add_argument("--seed", type=seed_number, default=0)
    p.add_argument(
        "--sigma-pos", type=nonnegative_number, default=1e-3, metavar="M", help="placement error std, translation [m]"
    )
    p.add_argument(
        "--sigma-rot", type=nonnegative_number, default=1e-3, metavar="RAD", help="placement error std, rotation [rad]"
    )
    _add_noise_options(p)
    p.add_argument("--noise-free", action="store_true", help="exact measurements")
    p.add_argument("--position-only", action="store_true", help="a tracker without orientation")
    p.add_argument(
        "--tracker-frame",
        nargs=6,
        type=finite_number,
        metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
        help="the robot base in the tracker's frame [m, rad] (default: measured in the base frame)",
    )
    p.add_argument(
        "--marker",
        nargs=3,
        type=finite_number,
        metavar=("X", "Y", "Z"),
        help="the reflector in the platform frame [m] (default: the platform frame's origin)",
    )
    p.add_argument("--units", choices=("m", "mm"), default="m", help="length unit of the written file")
    p.add_argument(
        "--outliers", type=zero_or_count, default=0, metavar="K", help="spoil K measurements with 3-5 mm gross errors"
    )
    p.add_argument(
        "--with-passive",
        action="store_true",
        help="also record encoders on the idle chains' hinges (q12_B2, q22_B4) for cross-validation "
        "(another mechanism: on every passive joint the closures solve)",
    )
    p.add_argument("-o", "--output", required=True, help="measurement CSV")
    p.add_argument("--truth-urdf", metavar="URDF", help="also write the actual machine (and its closures file)")
    _add_model_options(p)

    p = verbs.add_parser("calibrate", help="identify the geometry from measurements; write a calibrated URDF")
    p.add_argument("measurements", nargs="?", help="measurement CSV (sliders by joint name, x,y,z[,qx,qy,qz,qw])")
    p.add_argument("-o", "--output", required=True, help="calibrated URDF (a .closures.yaml is written beside it)")
    p.add_argument("--report", metavar="JSON", help="identified parameters, std, rank, RMS, input sha256")
    p.add_argument("--plots", metavar="DIR", help="write error plots (PNG) into DIR")
    p.add_argument(
        "--serial", metavar="ROBOT_OR_URDF", help="calibrate a serial chain instead (ur5, ur10, panda or a URDF)"
    )
    p.add_argument("--base", metavar="FRAME", help="with --serial: base frame (default the model root)")
    p.add_argument("--tool", metavar="FRAME", help="with --serial: the measured tool frame")
    p.add_argument(
        "--compliance",
        action="store_true",
        help="with --serial: joint compliance under gravity as candidate parameters (needs the URDF's "
        "inertias; kept in --report, which validate and compensate read)",
    )
    p.add_argument(
        "--joint",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="with --serial: a chain joint the file does not log, at this constant value [rad or m] "
        "(a tool changer; repeatable; kept in the report)",
    )
    add_campaign_options(p)
    _add_noise_options(p, estimable=True)
    _add_model_options(p)

    p = verbs.add_parser("compensate", help="corrected commands for targets, from a calibrated model (paper sec. 7)")
    p.add_argument(
        "targets",
        help="CSV with the task's columns (M machine: x,y,z,theta) or x,y,z,qx,qy,qz,qw; "
        "with a serial report, a joint program (columns by joint name)",
    )
    p.add_argument("--calibrated", required=True, metavar="URDF", help="calibrated URDF")
    p.add_argument("--calibrated-closures", metavar="YAML", help="its closures (default: beside the URDF)")
    p.add_argument(
        "--report",
        metavar="JSON",
        help="targets are poses of the measured frame (the marker) in this "
        "calibration's measurement frame (the tracker's), not the base's; "
        "a serial calibration's report: its chain and compliance, the "
        "targets a joint program",
    )
    p.add_argument(
        "--output-kind",
        choices=("pose", "actuators"),
        default="pose",
        help="pose: T_cp for a controller with the nominal model; actuators: slider commands",
    )
    p.add_argument(
        "--unordered",
        action="store_true",
        help="the targets are not a path (a grid, a map, unrelated poses): solve each from home, "
        "all at once, instead of warm-starting from the previous target",
    )
    p.add_argument("-o", "--output", required=True, help="commands CSV")
    _add_model_options(p)

    p = verbs.add_parser("view", help="meshcat scene of the nominal and calibrated machines")
    _add_model_options(p)
    _add_deprecated_alias(p, "--nominal", "model")
    p.add_argument("--calibrated", metavar="URDF")
    p.add_argument("--calibrated-closures", metavar="YAML")
    p.add_argument(
        "--pose",
        nargs="+",
        type=finite_number,
        metavar="VALUE",
        help="command both machines to these task coordinates (the task's columns; M machine: "
        "x y z theta [m, m, m, rad]; default: home)",
    )
    p.add_argument("--measurements", metavar="CSV", help="show measured platform positions as markers")
    p.add_argument("--html", metavar="PATH", help="write a self-contained static page instead of serving")
    p.add_argument(
        "--magnify",
        type=_magnification,
        default=None,
        metavar="K",
        help="draw the calibrated machine's deviation from the nominal K times, stated on the page "
        "(1: true scale; default auto: the largest offset drawn as a tenth of the machine's size, "
        "1 mm as 0.1 m on a metre-sized machine)",
    )

    p = verbs.add_parser(
        "demo", help="the main job: a simulated tracker campaign, plan to compensation (no input needed)"
    )
    p.add_argument("--out", default="demo_out", help="artifact folder (default demo_out)")

    p = verbs.add_parser("paper", help="the paper's two-chain method: its simulation study, or on the closed chain")
    p.add_argument("--seed", type=seed_number, default=3)
    p.add_argument("--noise", action="store_true", help="tracker, encoder and slider noise")
    p.add_argument(
        "--passive-from",
        choices=("sensor", "distance", "platform", "sliders"),
        default=None,
        help="lower cranks q13, q23: read (default), the paper's recursion (eq. 30), or a closure solve; "
        "not with --closed",
    )
    p.add_argument("--closed", action="store_true", help="run the method on the full closed-chain machine instead")

    p = verbs.add_parser("evaluate", help="compare nominal and calibrated machines against a (simulated) truth")
    p.add_argument("--truth", required=True, metavar="URDF")
    p.add_argument("--calibrated", required=True, metavar="URDF")
    _add_model_options(p)
    _add_deprecated_alias(p, "--nominal", "model")
    _add_deprecated_alias(p, "--nominal-closures", "closures")
    p.add_argument("-n", type=count_number, default=200)
    p.add_argument("--seed", type=seed_number, default=1)

    add_plan_parser(verbs)
    add_convert_parser(verbs)
    add_validate_parser(verbs)
    # --quiet before or after the verb; the verb's copy must not reset the global one.
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress display on stderr")
    for sub in verbs.choices.values():
        sub.add_argument(
            "-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress display on stderr"
        )
    return parser


def _add_fix_option(parser: argparse.ArgumentParser) -> None:
    """`--fix`, the parameters held at nominal: in `calibrate`, and in `plan`, which plans for the others."""
    parser.add_argument(
        "--fix",
        nargs="+",
        type=_comma_list,
        action=_ExtendLists,
        default=[],
        metavar="NAME",
        help="hold parameters (q12.dt[3]) or whole placements (q12) at nominal (repeatable, or a "
        "comma list: --fix q12 --fix q13,q14)",
    )


def add_campaign_options(parser: argparse.ArgumentParser) -> None:
    """The measurement-setup, robustness and judgement options of `calibrate` (closed loop and serial)."""
    parser.add_argument(
        "--frame",
        choices=("base", "estimate"),
        default="base",
        help="base: data are in the robot base frame; estimate: in a tracker's own frame, "
        "estimated with the machine (default base)",
    )
    parser.add_argument(
        "--marker",
        nargs=3,
        type=finite_number,
        metavar=("X", "Y", "Z"),
        help="nominal position of the measured point in the platform (serial: tool) frame [m]; "
        "estimated with the machine",
    )
    parser.add_argument(
        "--units",
        choices=("m", "mm"),
        default="m",
        help="length unit of the file's length columns (x, y, z and prismatic joints)",
    )
    parser.add_argument(
        "--outlier-sigma",
        type=_outlier_sigma,
        default=5.0,
        metavar="S",
        help="flag poses beyond S noise sigmas and leave them out (0: keep every pose; default 5)",
    )
    parser.add_argument(
        "--select",
        choices=("loo", "none"),
        default="loo",
        help="model selection: keep the parameters that predict left-out poses (default loo)",
    )
    _add_fix_option(parser)
    parser.add_argument(
        "--prior",
        nargs="+",
        type=_comma_list,
        action=_ExtendLists,
        default=[],
        metavar="NAME=SIGMA",
        help="a prior toward nominal with this standard deviation [m or rad] (repeatable, or a comma list)",
    )
    parser.add_argument(
        "--folds",
        type=_folds,
        default=5,
        help="cross-validation folds, at least 2 (default 5); "
        "repeats of a pose (same source or joint readings) are held out together",
    )
    parser.add_argument(
        "--validate",
        metavar="FILE",
        help="a held-out measurement file (same columns and units) scored by the calibration in the same run",
    )
    parser.add_argument(
        "--max-iterations", type=count_number, default=None, metavar="N", help="Levenberg-Marquardt cap"
    )
    parser.add_argument("--force", action="store_true", help="write a fit that is judged unsupported, with a warning")


def _folds(text: str) -> int:
    value = int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"at least 2 folds, got {value}")
    return value


def _outlier_sigma(text: str) -> float:
    value = float(text)
    if not (value == 0 or 1.0 <= value < 1e3):
        raise argparse.ArgumentTypeError(f"0 (keep every pose) or a gate of 1 to 1000 sigmas, got {text}")
    return value


def add_plan_parser(verbs: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `plan` verb to argparse's subparsers object `verbs`."""
    p = verbs.add_parser("plan", help="choose calibration poses D-optimally, ordered for short travel")
    p.add_argument("-n", type=count_number, required=True, help="number of poses to measure")
    p.add_argument("-o", "--output", required=True, help="plan CSV (sliders, or joints with --serial, by joint name)")
    p.add_argument("--seed", type=seed_number, default=0, help="seed of the candidate draw (default 0)")
    p.add_argument(
        "--candidates", type=count_number, metavar="K", help="candidates drawn in the workspace (default 20 n)"
    )
    p.add_argument("--position-only", action="store_true", help="a tracker without orientation")
    _add_fix_option(p)  # the parameters calibrate will hold: the plan identifies the others
    p.add_argument("--noise-pos", type=positive_number, default=10e-6, metavar="M", help="tracker position noise [m]")
    p.add_argument(
        "--noise-rot", type=positive_number, default=20e-6, metavar="RAD", help="tracker rotation noise [rad]"
    )
    p.add_argument("--model", metavar="URDF", help="machine URDF or MJCF (default: the packaged nominal model)")
    p.add_argument("--closures", metavar="YAML", help="its closures file (default: URDF stem + .closures.yaml)")
    p.add_argument(
        "--serial", metavar="ROBOT_OR_URDF", help="plan for a serial robot (ur3, ur5, ur10, panda or a URDF)"
    )
    p.add_argument("--base", metavar="FRAME", help="with --serial: base frame (default the model root)")
    p.add_argument(
        "--tool", metavar="FRAME", help="with --serial: the measured tool frame (default for example robots)"
    )
    return p


def add_validate_parser(verbs: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `validate` verb to argparse's subparsers object `verbs`."""
    p = verbs.add_parser("validate", help="predict a measurement file with a calibrated model; per-row errors")
    p.add_argument("measurements", help="measurement CSV (joints by name, x,y,z[,qx,qy,qz,qw])")
    p.add_argument(
        "--calibrated",
        required=True,
        metavar="URDF",
        help="calibrated URDF (M machine: its NAME.closures.yaml beside it)",
    )
    p.add_argument("--report", required=True, metavar="JSON", help="the calibration report (model kind, setup, noise)")
    p.add_argument("--units", choices=("m", "mm"), help="length unit of the file (default: the calibration input's)")
    p.add_argument("--predictions", metavar="CSV", help="write the predicted measurements, one row per input row")
    p.add_argument(
        "--plots",
        metavar="DIR",
        help="write plots (PNG) into DIR: error histograms and a QQ plot against "
        "the noise model, errors over the workspace, flagged rows named",
    )
    return p


def noise_or_auto(text: str) -> float | str:
    """argparse type of --noise-pos / --noise-rot in `calibrate`: a number above 0 (`positive_number`),
    or `auto`."""
    if text.strip().lower() == AUTO:
        return AUTO
    try:
        return positive_number(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (a noise [m or rad] or '{AUTO}')") from None


def add_convert_parser(verbs: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `convert` verb to argparse's subparsers object `verbs`."""
    p = verbs.add_parser(
        "convert",
        help="a tracker's export (and the robot's log) -> measurement CSV",
        description="Formats: " + "; ".join(f"{name}: {text}" for name, text in FORMAT_DESCRIPTIONS.items()),
    )
    p.add_argument("tracker", metavar="TRACKER_FILE", help="the instrument's file (a bag: its folder or .db3/.mcap)")
    p.add_argument(
        "--robot",
        metavar="ROBOT_LOG",
        help="the robot's joint log: CSV (time or t_start,t_end, joints by name) or a ROS 2 bag with JointState",
    )
    p.add_argument("-o", "--output", required=True, metavar="MEASUREMENTS.csv", help="measurement CSV to write")
    p.add_argument(
        "--format", choices=tuple(FORMAT_DESCRIPTIONS), help="the tracker file's format (default: from its content)"
    )
    p.add_argument(
        "--body",
        metavar="NAME",
        help="the rigid body, marker, label, group or topic to read "
        "(a marker number K for x1..xK columns; all: every marker, as "
        "points of the tool; rigid: those markers as one rigid body)",
    )
    p.add_argument(
        "--units",
        choices=("m", "mm", "cm", "in"),
        help="position unit when the file does not state it (default m for tables)",
    )
    p.add_argument(
        "--euler", metavar="SEQ", help="Euler convention of rotation columns (scipy's: xyz extrinsic, XYZ intrinsic)"
    )
    p.add_argument("--degrees", action="store_true", help="Euler angles (or a rotation vector) in degrees")
    p.add_argument(
        "--rotation-vector",
        action="store_true",
        help="rx, ry, rz are a rotation vector (axis times angle, as a UR controller logs), not Euler "
        "angles (rvx, rvy, rvz always are; r11 ... r33 are read as a rotation matrix)",
    )
    p.add_argument(
        "--joints",
        nargs="+",
        metavar="NAME",
        help="the joint columns (default: every other numeric column but times and counters)",
    )
    p.add_argument(
        "--joint-degrees", nargs="+", default=[], metavar="NAME", help="joint columns in degrees ('all': every joint)"
    )
    p.add_argument(
        "--still-speed",
        type=_positive,
        default=5e-3,
        metavar="M_PER_S",
        help="a tracker stream is still below this speed (default 5e-3 m/s)",
    )
    p.add_argument(
        "--robot-still-speed",
        type=_positive,
        default=2e-3,
        metavar="RAD_PER_S",
        help="the robot log is still below this joint speed (default 2e-3 rad/s or m/s)",
    )
    p.add_argument(
        "--min-dwell",
        type=_positive,
        default=0.5,
        metavar="S",
        help="shortest still stretch kept as a pose (default 0.5 s)",
    )
    p.add_argument(
        "--pair",
        choices=("auto", "order", "time"),
        default="auto",
        help="pair poses with the robot's stops by clock (auto, when both have times) or by order",
    )
    return p


def _magnification(text: str) -> float | None:
    if text.strip().lower() == AUTO:
        return None
    value = finite_number(text)
    if value < 1.0:
        raise argparse.ArgumentTypeError(f"a factor of at least 1 (1: true scale), got {text}")
    return value


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"a positive number, got {text}")
    return value
