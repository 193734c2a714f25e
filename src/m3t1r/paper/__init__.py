"""The calibration method of Zhang et al. (Symmetry 2020), reproduced faithfully as a baseline.

The paper calibrates the machine as two serial chains, B1 -> P and B3 -> P (its chains i = 1, 2),
each read by sensors on every joint, and measures the platform pose with a tracker:

- error model (section 3): per chain the local POE of eq. (6), every error lumped into the initial
  poses T(0) (eq. 11), y_i = log6(g_meas g_i(q)^-1) (eq. 18) = J_i x_i (eq. 19-20), WORLD rows;
- identification (section 5): the m-pose stack (eq. 31) solved by least squares (eq. 32), batch or
  recursively one pose at a time, iterated with T(0) <- T(0) exp6(X) (eq. 33) until ||X|| < tol;
- passive angles (section 4): the lower crank q_i3 of each chain computed from the other readings
  through |A1 A2| = a by the Newton recursion of eq. (30), to save two sensors;
- simulation (section 6): an "actual" chain with errors on T(0), twists and joint variables
  (eq. 34-37), 20 poses from the mechanism's numerical forward kinematics.

On this repository's machine (`docs/design.md`, "The mechanism") the paper's "equivalent" revolute
joints q_i2, q_i3 are parallelograms: chain B1 is (q11, q12, q12_pa, q13, q13_pa, q14, P_I), the
coupling joints q_i2_pa, q_i3_pa being read like every other joint of the chain. Chain B3 ends
at P_II, the second copy of the platform frame, welded to P_I by the platform closure.

Choices this module makes where the paper is silent or inconsistent (each argued where it is made):

1. Eq. (21) is implemented in the stacked form [y1; y2] = blockdiag(J1, J2) [x1; x2], not as
   written (A = [J1, J2], Y = y1 = y2), which adds both chains' predictions of one error
   (`two_chain_error_model`).
2. The J^-1 of eq. (29)-(30) is 1 x 2: it can only be a pseudo-inverse, and the recursion is
   then ill-posed (`estimate_lower_crank_angles`).
3. Rows are weighted at the tool point, where the tracker's position and orientation noise are
   isotropic (`calibrate_two_chains`).

What the simulations show (seeds and numbers in tests/test_paper.py):
- The paper's own study (`paper_study`), every joint read, no noise: the calibrated chains
  reproduce the actual chains to 1e-15 m and rad, twist and offset errors included. With a
  10 um / 20 urad tracker and 10 urad encoders, errors fall from millimetres to about 10 um
  and 20 urad, a 100-700x reduction (the paper claims at least 10x).
- The lower cranks from the paper's recursion are off by about 0.1 rad; the calibration then
  leaves millimetres and tens of milliradians. The platform weld recovers them exactly.
- On the closed-chain machine (`closed_chain_study`) the chain ending at the measured frame
  fits exactly, but only while every passive joint is read: predicting from the sliders needs
  the passive angles, and with the nominal model's the result is no better than the
  uncalibrated machine. The other chain cannot follow the measured frame at all.

Conventions: Pinocchio's, [linear; angular] twists, SI units (m, rad); WORLD is the base frame {B}.
Readings are full Pinocchio configurations (N, nq) of the mechanism's tree (or {joint: values});
only the entries of the joints that are read matter.

The package follows the paper's sections, one module each:

- `chains`: the two chains on the mechanism's tree (`PaperChain`, `paper_chains`);
- `error_model`: section 3, eq. (17)-(21) and (31), and the rank analysis (`two_chain_identifiability`);
- `identification`: section 5, eq. (32)-(33), batch or recursive least squares (`calibrate_two_chains`);
- `passive_angles`: section 4, eq. (22)-(30) (`estimate_lower_crank_angles`);
- `simulation`: section 6's actual chains and sensors, eq. (34)-(37) and Table 1 (`preset_errors`);
- `study`: section 6's study (`paper_study`);
- `closed_chain`: the comparison on the closed-chain machine (`closed_chain_study`).

This package's `__init__` re-exports their public names, so `from m3t1r import paper` then
`paper.calibrate_two_chains(...)` reads as the paper does; code inside the package imports from
the modules.
"""

from __future__ import annotations

from m3t1r.paper.chains import PaperChain, paper_chains
from m3t1r.paper.closed_chain import ClosedChainStudyResult, closed_chain_study
from m3t1r.paper.error_model import (
    PAPER_IDENTIFIABLE_BOUND,
    Identifiability,
    TwoChainErrorModel,
    two_chain_error_model,
    two_chain_identifiability,
)
from m3t1r.paper.identification import (
    EXACT_DATA_REL_TOL,
    NOISY_READINGS_REL_TOL,
    PaperCalibration,
    TwoChainOptions,
    calibrate_two_chains,
)
from m3t1r.paper.passive_angles import CrankMethod, LowerCrankEstimate, estimate_lower_crank_angles
from m3t1r.paper.simulation import (
    PASSIVE_ENCODER_NOISE,
    PresetErrors,
    PresetErrorScale,
    TwoChainStudyOptions,
    actual_chain_poses,
    preset_errors,
)
from m3t1r.paper.study import ChainErrors, PaperStudyResult, PassiveSource, paper_study

__all__ = [
    "EXACT_DATA_REL_TOL",
    "NOISY_READINGS_REL_TOL",
    "PAPER_IDENTIFIABLE_BOUND",
    "PASSIVE_ENCODER_NOISE",
    "ChainErrors",
    "ClosedChainStudyResult",
    "CrankMethod",
    "Identifiability",
    "LowerCrankEstimate",
    "PaperCalibration",
    "PaperChain",
    "PaperStudyResult",
    "PassiveSource",
    "PresetErrorScale",
    "PresetErrors",
    "TwoChainErrorModel",
    "TwoChainOptions",
    "TwoChainStudyOptions",
    "actual_chain_poses",
    "calibrate_two_chains",
    "closed_chain_study",
    "estimate_lower_crank_angles",
    "paper_chains",
    "paper_study",
    "preset_errors",
    "two_chain_error_model",
    "two_chain_identifiability",
]
