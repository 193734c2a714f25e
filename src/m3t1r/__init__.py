"""m3t1r: the M-shaped 3T1R parallel manipulator on Pinocchio.

Data flows one way, and the imports agree (tests/test_layering.py checks it):

    ground        errors, _threads, _version, io, metrics      typed errors, atomic files and CSV tables, pose errors
    model/        design, description, kinematics, batch_kinematics, urdf_io, workspace, poe
    calibration/  measurements, error model, identification, closed-loop and serial calibration,
                  pose selection, planning, simulation, assessment, validation
    compensation  commands corrected with the calibrated model
    paper/, app/  the paper's two-chain method; the command line, demo, reports, plots, views

The names below are the public API; everything else is reached through its module.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from m3t1r._version import __version__

if TYPE_CHECKING:  # the names as type checkers and editors see them; at run time `__getattr__` loads them
    from m3t1r.calibration.closed_loop import (
        ClosedLoopCalibration,
        CrossValidation,
        calibrate_closed_loop,
        cross_validate,
        pose_errors,
        predicted_measurement_std,
        predicted_pose_std,
    )
    from m3t1r.calibration.error_model import ClosedLoopErrorModel
    from m3t1r.calibration.measurement_setup import MeasurementSetup
    from m3t1r.calibration.measurements import PoseMeasurements, TrackerNoise, measure
    from m3t1r.calibration.pipeline import CalibrationOptions
    from m3t1r.calibration.planning import MeasurementPlan, plan_closed_loop, plan_serial
    from m3t1r.calibration.pose_selection import PoseSelection, select_poses
    from m3t1r.calibration.serial import SerialCalibration, calibrate_serial
    from m3t1r.calibration.serial_evaluation import SerialCrossValidation, cross_validate_serial
    from m3t1r.calibration.serial_robots import load_example_robot
    from m3t1r.calibration.simulation import (
        PlacementErrorScale,
        SimulatedStudy,
        StudyOptions,
        actual_machine,
        simulate_study,
    )
    from m3t1r.calibration.validation import Validation, validate
    from m3t1r.compensation import Compensation, CompensationAccuracy, Compensator, compensate, compensation_accuracy
    from m3t1r.errors import (
        BranchChangeError,
        DataFileError,
        IdentificationError,
        InvalidInputError,
        KinematicsError,
        M3t1rError,
        ModelFileError,
        ModelWarning,
        NotConvergedError,
        OutOfWorkspaceError,
        OutputPathError,
        PoorExcitationWarning,
        SingularConfigurationError,
    )
    from m3t1r.metrics import PoseErrors
    from m3t1r.model.constraint_models import rigid_constraint_datas, rigid_constraint_models
    from m3t1r.model.description import ClosureSpec, Mechanism
    from m3t1r.model.design import NOMINAL
    from m3t1r.model.examples import five_bar_files, spherical_wrist_files
    from m3t1r.model.kinematics import ClosedLoopSolver, ForwardResult, InverseResult
    from m3t1r.model.poe import SerialChain
    from m3t1r.model.task import TaskSpec, WorkspaceSpec
    from m3t1r.model.urdf_io import write_calibrated_urdf
    from m3t1r.model.workspace import declared_workspace, workspace_actuators

# Where each public name is defined. `import m3t1r` imports none of these modules, for start-up time:
# the command line (`m3t1r --version`, `--help`) and a script that needs one name do not pay for
# SciPy, Pinocchio and the whole calibration stack (over a second); `m3t1r.X` imports X's module on
# first use. tests/test_startup.py checks this table against the TYPE_CHECKING imports above.
_MODULE_EXPORTS: dict[str, tuple[str, ...]] = {
    "m3t1r.calibration.closed_loop": (
        "ClosedLoopCalibration",
        "CrossValidation",
        "calibrate_closed_loop",
        "cross_validate",
        "pose_errors",
        "predicted_measurement_std",
        "predicted_pose_std",
    ),
    "m3t1r.calibration.error_model": ("ClosedLoopErrorModel",),
    "m3t1r.calibration.measurement_setup": ("MeasurementSetup",),
    "m3t1r.calibration.measurements": ("PoseMeasurements", "TrackerNoise", "measure"),
    "m3t1r.calibration.pipeline": ("CalibrationOptions",),
    "m3t1r.calibration.planning": ("MeasurementPlan", "plan_closed_loop", "plan_serial"),
    "m3t1r.calibration.pose_selection": ("PoseSelection", "select_poses"),
    "m3t1r.calibration.serial": ("SerialCalibration", "calibrate_serial"),
    "m3t1r.calibration.serial_evaluation": ("SerialCrossValidation", "cross_validate_serial"),
    "m3t1r.calibration.serial_robots": ("load_example_robot",),
    "m3t1r.calibration.simulation": (
        "PlacementErrorScale",
        "SimulatedStudy",
        "StudyOptions",
        "actual_machine",
        "simulate_study",
    ),
    "m3t1r.calibration.validation": ("Validation", "validate"),
    "m3t1r.compensation": (
        "Compensation",
        "CompensationAccuracy",
        "Compensator",
        "compensate",
        "compensation_accuracy",
    ),
    "m3t1r.errors": (
        "BranchChangeError",
        "DataFileError",
        "IdentificationError",
        "InvalidInputError",
        "KinematicsError",
        "M3t1rError",
        "ModelFileError",
        "ModelWarning",
        "NotConvergedError",
        "OutOfWorkspaceError",
        "OutputPathError",
        "PoorExcitationWarning",
        "SingularConfigurationError",
    ),
    "m3t1r.metrics": ("PoseErrors",),
    "m3t1r.model.constraint_models": ("rigid_constraint_datas", "rigid_constraint_models"),
    "m3t1r.model.description": ("ClosureSpec", "Mechanism"),
    "m3t1r.model.design": ("NOMINAL",),
    "m3t1r.model.examples": ("five_bar_files", "spherical_wrist_files"),
    "m3t1r.model.kinematics": ("ClosedLoopSolver", "ForwardResult", "InverseResult"),
    "m3t1r.model.poe": ("SerialChain",),
    "m3t1r.model.task": ("TaskSpec", "WorkspaceSpec"),
    "m3t1r.model.urdf_io": ("write_calibrated_urdf",),
    "m3t1r.model.workspace": ("declared_workspace", "workspace_actuators"),
}
_EXPORTS = {name: module for module, names in _MODULE_EXPORTS.items() for name in names}


def __getattr__(name: str) -> object:
    """The public name `name`, imported from its module on first access (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'm3t1r' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later accesses find it without calling here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


__all__ = [
    "__version__",
    # errors
    "M3t1rError",
    "InvalidInputError",
    "ModelFileError",
    "DataFileError",
    "OutputPathError",
    "KinematicsError",
    "OutOfWorkspaceError",
    "BranchChangeError",
    "SingularConfigurationError",
    "NotConvergedError",
    "IdentificationError",
    "PoorExcitationWarning",
    "ModelWarning",
    # model
    "NOMINAL",
    "Mechanism",
    "ClosureSpec",
    "ClosedLoopSolver",
    "ForwardResult",
    "InverseResult",
    "SerialChain",
    "write_calibrated_urdf",
    "workspace_actuators",
    "declared_workspace",
    "TaskSpec",
    "WorkspaceSpec",
    "five_bar_files",
    "spherical_wrist_files",
    "rigid_constraint_models",
    "rigid_constraint_datas",
    # calibration
    "PoseErrors",
    "TrackerNoise",
    "PoseMeasurements",
    "MeasurementSetup",
    "measure",
    "ClosedLoopErrorModel",
    "CalibrationOptions",
    "ClosedLoopCalibration",
    "calibrate_closed_loop",
    "pose_errors",
    "predicted_pose_std",
    "predicted_measurement_std",
    "CrossValidation",
    "cross_validate",
    "SerialCalibration",
    "SerialCrossValidation",
    "calibrate_serial",
    "cross_validate_serial",
    "load_example_robot",
    "SimulatedStudy",
    "simulate_study",
    "PlacementErrorScale",
    "StudyOptions",
    "actual_machine",
    "PoseSelection",
    "select_poses",
    "MeasurementPlan",
    "plan_closed_loop",
    "plan_serial",
    "Validation",
    "validate",
    # compensation
    "Compensator",
    "Compensation",
    "CompensationAccuracy",
    "compensate",
    "compensation_accuracy",
]
