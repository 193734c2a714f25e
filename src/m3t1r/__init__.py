"""m3t1r: the M-shaped 3T1R parallel manipulator on Pinocchio.

Data flows one way: description (model files) -> kinematics (closed-loop FK/IK) -> poe and
calibration (local POE error model, identification) -> compensation; io, datasets, viz, plots and
the CLI sit on top.
"""

__version__ = "0.1.0"
