"""Which function runs each `m3t1r` verb, as "package.module:function", imported only when it runs.

This table is the one place the command line imports by name, for start-up time: `m3t1r --help`,
`--version` and `VERB --help` need argparse alone, and a verb imports its own stack only (SciPy,
Pinocchio, matplotlib and meshcat cost seconds together), so no module here is imported at the top
of the command line. tests/test_startup.py checks that every verb of the parser is here, resolves,
and leaves out what it does not need.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

__all__ = [
    "VERBS",
    "SERIAL_CALIBRATION",
    "CALIBRATION_PLOTS",
    "DECLARE_PLOTS",
    "VALIDATION_PLOTS",
    "DECLARE_VALIDATION_PLOTS",
    "RUNNER",
    "DEMO",
    "load",
]

VERBS: dict[str, str] = {
    "fk": "m3t1r.app.cli_kinematics:cmd_fk",
    "ik": "m3t1r.app.cli_kinematics:cmd_ik",
    "simulate": "m3t1r.app.cli_studies:cmd_simulate",
    "calibrate": "m3t1r.app.cli_calibrate:cmd_calibrate",
    "compensate": "m3t1r.app.cli_kinematics:cmd_compensate",
    "view": "m3t1r.app.cli_view:cmd_view",
    "demo": "m3t1r.app.cli:cmd_demo",
    "paper": "m3t1r.app.cli_studies:cmd_paper",
    "evaluate": "m3t1r.app.cli_kinematics:cmd_evaluate",
    "plan": "m3t1r.app.cli_campaign:cmd_plan",
    "validate": "m3t1r.app.cli_campaign:cmd_validate",
    "convert": "m3t1r.app.cli_convert:cmd_convert",
}
SERIAL_CALIBRATION = "m3t1r.app.cli_serial:cmd_calibrate_serial"  # calibrate --serial: no closed-loop stack
CALIBRATION_PLOTS = "m3t1r.app.reporting:write_calibration_plots"  # matplotlib, for calibrate --plots only
DECLARE_PLOTS = "m3t1r.app.reporting:declare_plot_outputs"  # the same module: --plots is checked before the fit
VALIDATION_PLOTS = "m3t1r.app.reporting:write_validation_plots"  # matplotlib, for validate --plots only
DECLARE_VALIDATION_PLOTS = "m3t1r.app.reporting:declare_validation_plot_outputs"
RUNNER = "m3t1r.app.cli_run:run_verb"  # exit statuses and signals: the errors, hence numpy
DEMO = "m3t1r.app.demo:run_demo"


def load(reference: str) -> Callable:
    """The function named by "package.module:function", its module imported now."""
    module, _, name = reference.partition(":")
    return getattr(importlib.import_module(module), name)
