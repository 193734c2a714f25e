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

from m3t1r._version import __version__
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
from m3t1r.calibration.planning import MeasurementPlan, plan_closed_loop, plan_serial
from m3t1r.calibration.pose_selection import PoseSelection, select_poses
from m3t1r.calibration.serial import SerialCalibration, calibrate_serial
from m3t1r.calibration.serial_evaluation import SerialCrossValidation, cross_validate_serial
from m3t1r.calibration.serial_robots import load_example_robot
from m3t1r.calibration.simulation import SimulatedStudy, actual_machine, simulate_study
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
from m3t1r.model.description import ClosureSpec, Mechanism
from m3t1r.model.design import NOMINAL
from m3t1r.model.examples import five_bar_files, spherical_wrist_files
from m3t1r.model.kinematics import ClosedLoopSolver, ForwardResult, InverseResult
from m3t1r.model.poe import SerialChain
from m3t1r.model.task import TaskSpec, WorkspaceSpec
from m3t1r.model.urdf_io import write_calibrated_urdf
from m3t1r.model.workspace import declared_workspace, workspace_actuators

__all__ = [
    "__version__",
    # errors
    "M3t1rError", "InvalidInputError", "ModelFileError", "DataFileError", "OutputPathError", "KinematicsError",
    "OutOfWorkspaceError", "BranchChangeError", "SingularConfigurationError", "NotConvergedError",
    "IdentificationError", "PoorExcitationWarning", "ModelWarning",
    # model
    "NOMINAL", "Mechanism", "ClosureSpec", "ClosedLoopSolver", "ForwardResult", "InverseResult", "SerialChain",
    "write_calibrated_urdf", "workspace_actuators", "declared_workspace", "TaskSpec", "WorkspaceSpec",
    "five_bar_files", "spherical_wrist_files",
    # calibration
    "PoseErrors", "TrackerNoise", "PoseMeasurements", "MeasurementSetup", "measure", "ClosedLoopErrorModel",
    "ClosedLoopCalibration", "calibrate_closed_loop", "pose_errors", "predicted_pose_std", "predicted_measurement_std",
    "CrossValidation",
    "cross_validate", "SerialCalibration", "SerialCrossValidation", "calibrate_serial",
    "cross_validate_serial", "load_example_robot", "SimulatedStudy", "simulate_study", "actual_machine",
    "PoseSelection", "select_poses", "MeasurementPlan", "plan_closed_loop", "plan_serial", "Validation", "validate",
    # compensation
    "Compensator", "Compensation", "CompensationAccuracy", "compensate", "compensation_accuracy",
]
