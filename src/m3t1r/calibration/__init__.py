"""Calibration: measurements and their setup, the error model, identification, closed-loop and serial
calibration, pose selection and planning, simulation, and the assessment and validation of a fit."""
