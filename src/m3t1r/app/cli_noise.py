"""`--noise-pos auto` / `--noise-rot auto` of `m3t1r calibrate`: the tracker noise from the data.

A stated noise is used as given. An `auto` one is estimated from the fit's own residual
(`assessment.noise_from_residual`: the mean square per coordinate, scaled for the degrees of
freedom the fit used): a first fit with a provisional noise and no outlier gate gives the
residual; the fit is repeated with the estimate and the gate, and again (up to four times) while the
inliers' residual moves the estimate by over 10 %. The report and the printout say which noise was stated and which
estimated, and its value.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TypeVar

from m3t1r.app.cli_parser import AUTO, NOISE_AUTO_HELP, noise_or_auto
from m3t1r.calibration.assessment import FitRejected, check_fit, noise_from_residual
from m3t1r.calibration.measurements import TrackerNoise

__all__ = ["judge_fit", "AUTO", "NOISE_AUTO_HELP", "NoiseChoice", "ResidualSummary", "fit_with_noise", "noise_or_auto"]

#: The provisional noise of the first fit when a noise is estimated [m], [rad]: only the ratio of
#: the two matters to that fit, and 1 mm per mrad weighs a metre-sized lever's errors alike.
PROVISIONAL_POSITION, PROVISIONAL_ROTATION = 1e-3, 1e-3
#: A refit when the inliers' residual moves the estimate by more than this fraction, at most
#: MAX_REFITS times (gross readings that the first, ungated fit spread into the estimate are
#: gated out one refit after another as the estimate shrinks).
REFIT_CHANGE, MAX_REFITS = 0.1, 4

Fit = TypeVar("Fit")


@dataclass(frozen=True)
class ResidualSummary:
    """What a fit left: RMS over inlier poses of the position error norm [m] and of the rotation
    angle [rad] (nan without orientations), the inlier poses, residual rows per pose (3 or 6) and
    the parameters fitted."""

    position_rms: float
    rotation_rms: float
    poses: int
    rows_per_pose: int
    fitted: int


@dataclass(frozen=True)
class NoiseChoice:
    """The noise a calibration used: `noise` (the final fit's) and which of its position and
    rotation parts were estimated from the data rather than stated."""

    noise: TrackerNoise
    position_estimated: bool = False
    rotation_estimated: bool = False

    @property
    def estimated(self) -> bool:
        """Whether any part was estimated (the residual test then says nothing)."""
        return self.position_estimated or self.rotation_estimated

    def describe(self, position_only: bool) -> str:
        """'tracker noise 1.1e-03 m (estimated from the residual), 2e-05 rad (stated)'."""
        parts = [
            f"{self.noise.position:.3g} m ({'estimated from the residual' if self.position_estimated else 'stated'})"
        ]
        if not position_only:
            parts.append(
                f"{self.noise.rotation:.3g} rad "
                f"({'estimated from the residual' if self.rotation_estimated else 'stated'})"
            )
        return "tracker noise " + ", ".join(parts)

    def report(self) -> dict[str, object]:
        """The report's `noise_source` field (the values are in `noise_model`)."""
        return {
            "position": "estimated" if self.position_estimated else "stated",
            "rotation": "estimated" if self.rotation_estimated else "stated",
            "method": "fit residual per coordinate, scaled by rows / (rows - fitted)" if self.estimated else None,
        }


def fit_with_noise(
    position: float | str,
    rotation: float | str,
    base: TrackerNoise,
    fit: Callable[[TrackerNoise, bool], Fit],
    summary: Callable[[Fit], ResidualSummary],
) -> tuple[Fit, NoiseChoice]:
    """The calibration `fit(noise, outlier_gate)` with the noise stated or estimated (module
    docstring). position, rotation: the options' values (a number or AUTO); base: the other
    noise figures (the actuators')."""
    choice = NoiseChoice(
        replace(
            base,
            position=PROVISIONAL_POSITION if position == AUTO else float(position),
            rotation=PROVISIONAL_ROTATION if rotation == AUTO else float(rotation),
        ),
        position == AUTO,
        rotation == AUTO,
    )
    if not choice.estimated:
        return fit(choice.noise, True), choice
    result = fit(choice.noise, False)
    choice = replace(choice, noise=_estimate(choice, summary(result)))
    result = fit(choice.noise, True)
    for _ in range(MAX_REFITS):
        again = _estimate(choice, summary(result))
        if (
            max(abs(again.position / choice.noise.position - 1.0), abs(again.rotation / choice.noise.rotation - 1.0))
            <= REFIT_CHANGE
        ):
            break
        choice = replace(choice, noise=again)
        result = fit(choice.noise, True)
    return result, choice


def _estimate(choice: NoiseChoice, left: ResidualSummary) -> TrackerNoise:
    """The noise with its estimated parts taken from the residual (floored at 1e-12: exact data)."""
    position, rotation = noise_from_residual(
        left.position_rms, left.rotation_rms, left.poses, left.rows_per_pose, left.fitted
    )
    noise = choice.noise
    return replace(
        noise,
        position=max(position, 1e-12) if choice.position_estimated else noise.position,
        rotation=max(rotation, 1e-12) if choice.rotation_estimated and math.isfinite(rotation) else noise.rotation,
    )


def judge_fit(
    converged: bool,
    termination: str,
    iterations: int,
    variance_factor: float,
    choice: NoiseChoice,
    causes: Callable[[], list[str]],
    force: bool,
) -> bool:
    """`check_fit` for a closed-loop or serial fit, with the likely causes computed only when they can
    matter (a fit that did not converge or left more than 3 times the noise, or an estimated noise);
    `force` downgrades a refusal to a warning on stderr. Returns whether the residual is beyond the
    noise for no nameable cause (the caller writes the result with a warning)."""
    suspicious = not converged or not variance_factor <= 9.0 or choice.estimated
    try:
        return check_fit(
            converged,
            termination,
            iterations,
            variance_factor,
            causes() if suspicious else (),
            noise_estimated=choice.estimated,
        )
    except FitRejected as exc:
        if not force:
            raise
        print(f"m3t1r: warning: writing anyway (--force): {exc.reason}", file=sys.stderr)
        return False
