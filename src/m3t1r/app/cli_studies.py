"""The simulation verbs: `m3t1r simulate` (an actual machine and measurements of it) and `m3t1r paper`
(the paper's two-chain study, or its method on the closed chain).

`m3t1r.app.cli` imports this module only to run one of them.
"""

from __future__ import annotations

import argparse

from m3t1r.app.cli_common import load_mechanism, provenance, say
from m3t1r.app.datasets import measurement_table
from m3t1r.calibration.measurement_setup import MeasurementSetup
from m3t1r.calibration.measurements import TrackerNoise
from m3t1r.calibration.simulation import PlacementErrorScale, StudyOptions, simulate_study
from m3t1r.errors import InvalidInputError
from m3t1r.io.outputs import OutputSet
from m3t1r.io.progress import Heartbeat
from m3t1r.io.tables import table_text
from m3t1r.model.design import IDLE_CHAIN_JOINTS
from m3t1r.paper.closed_chain import closed_chain_study
from m3t1r.paper.study import PassiveSource, paper_study

__all__ = ["cmd_simulate", "cmd_paper"]


def cmd_simulate(args: argparse.Namespace) -> None:
    """`m3t1r simulate`: a perturbed machine and noisy measurements of it."""
    nominal = load_mechanism(args.model, args.closures)
    outputs = OutputSet(inputs=(nominal.urdf_path, nominal.closures_path))
    measurement_output = outputs.add(args.output, "-o")
    truth_output = outputs.add_machine(args.truth_urdf, "--truth-urdf")
    outputs.check()
    noise = None if args.noise_free else TrackerNoise(args.noise_pos, args.noise_rot, args.noise_act)
    passive = _recorded_passive_joints(nominal) if args.with_passive else ()
    setup = MeasurementSetup.from_numbers(args.tracker_frame, args.marker)
    with Heartbeat("simulating", f"{args.n} poses"):  # one batch: no count to show
        study = simulate_study(
            nominal,
            args.n,
            0,
            args.seed,
            errors=PlacementErrorScale(args.sigma_pos, args.sigma_rot),
            noise=noise,
            options=StudyOptions(
                setup=setup, position_only=args.position_only, passive_joints=passive, outliers=args.outliers
            ),
        )
    comments = provenance(args) + [
        f"truth: {args.sigma_pos:g} m / {args.sigma_rot:g} rad errors on every joint placement and "
        f"closure/platform frame, seed {args.seed}",
        "noise: none"
        if noise is None
        else f"noise: tracker {noise.position:g} m / {noise.rotation:g} rad, sliders {noise.actuator:g} m",
        f"lengths in {args.units}; measured: tracker frame . platform . marker",
    ]
    if study.outliers:
        comments.append(f"gross outliers (3-5 mm) on data rows {', '.join(str(i + 1) for i in study.outliers)}")
    columns, rows = measurement_table(nominal, study.measurements, passive, study.passive_readings, args.units)
    with outputs:
        outputs.stage(measurement_output, table_text(columns, rows, comments))
        if truth_output is not None:
            outputs.stage_machine(truth_output, study.truth)
        outputs.commit()
    say(
        outputs,
        f"wrote {args.n} {'position-only ' if args.position_only else ''}measurements to {measurement_output.name}",
    )
    if truth_output is not None:
        say(outputs, f"wrote the truth machine to {truth_output.name} and {truth_output.closures.name}")


def cmd_paper(args: argparse.Namespace) -> None:
    """`m3t1r paper`: the paper's simulation study, or its method on the closed chain."""
    if args.closed and args.passive_from is not None:
        raise InvalidInputError(
            "--closed runs every variant (passive joints read, sliders alone, closed loop); "
            "--passive-from applies to the two-chain study only"
        )
    passive_from: PassiveSource = args.passive_from or "sensor"  # argparse's choices are PassiveSource's
    noise = TrackerNoise() if args.noise else None
    label = "with noise (tracker 10 um / 20 urad, encoders 10 urad)" if args.noise else "noise-free"

    def row(name, errors) -> str:
        return (
            f"{name:<46}{errors.position_mean:>14.3e}{errors.position.max():>14.3e}"
            f"{errors.rotation_mean:>16.3e}{errors.rotation.max():>15.3e}"
        )

    header = f"{'':<46}{'pos mean [m]':>14}{'pos max [m]':>14}{'rot mean [rad]':>16}{'rot max [rad]':>15}"
    if args.closed:
        print(f"the paper's two-chain method on the closed-chain machine, seed {args.seed}, {label}:", flush=True)
        result = closed_chain_study(args.seed, noise=noise)
        print(header)
        print(row("nominal model", result.nominal))
        print(row("chain B1, every passive joint read: before", result.sensors_before))
        print(row("chain B1, every passive joint read: after", result.sensors_after))
        print(row("chain B3 fitted to P_I: after", result.second_chain_after))
        print(row("chain B1 from the sliders alone", result.sliders_only))
        if result.closed_loop is not None:
            print(row("closed-loop calibration (m3t1r.calibration)", result.closed_loop))
        return
    print(
        f"the paper's simulation study (two serial chains, Table-1-like dt, ds, dq), seed {args.seed}, "
        f"lower cranks from {passive_from}, {label}:",
        flush=True,
    )
    study = paper_study(args.seed, noise=noise, passive_from=passive_from)
    ident = study.identifiability
    print(
        f"identifiable: {ident.rank_per_chain} per chain, {ident.rank_stacked} stacked "
        f"(the paper's bound for the whole machine: {ident.paper_bound})"
    )
    if study.failure:
        print(f"identification failed: {study.failure}")
    print(header)
    for chain, errors in study.holdout_poses.items():
        print(row(f"held-out poses, chain {chain}: before", errors.before))
        if errors.after is not None:
            print(row(f"held-out poses, chain {chain}: after", errors.after))


def _recorded_passive_joints(mechanism) -> tuple[str, ...]:
    """`simulate --with-passive`: the idle chains' hinges on the M machine, else every joint the closures solve."""
    model, solved = mechanism.model, set(mechanism.passive_ids.tolist())
    if all(model.existJointName(name) for name in IDLE_CHAIN_JOINTS):
        return IDLE_CHAIN_JOINTS
    return tuple(model.names[j] for j in range(1, model.njoints) if model.idx_vs[j] in solved)
