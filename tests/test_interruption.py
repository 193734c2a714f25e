"""`m3t1r calibrate` killed with SIGKILL at random and at aimed instants (issue 10, item 8).

A worker process imports m3t1r once, then forks one child per run; the child runs the real
`m3t1r.app.cli.main(["calibrate", ...])` and dies by SIGKILL, either after a random delay sent by the
parent or by itself right before or after its k-th `os.replace` (the renames that commit the
outputs). After every kill the parent checks, before anything else touches the folder:

- the inputs (measurements, nominal model) are byte-for-byte untouched;
- the output folder holds a pair that `Mechanism.load(NAME.urdf)` loads, and it is the old pair
  or the new one, never a mix (the URDF's recorded closures sha256 is checked by the loader);
- the report is the old one or the new one, and strict JSON.

The folder then goes back to the old pair (leftover temporary files are left in place), so each
run starts from the same state; the last, uninterrupted, run must sweep every leftover away.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from m3t1r.app.cli import main
from m3t1r.io.signals import Terminated, deliver_signals, signals_deferred, termination_as_exception

WORKER = textwrap.dedent(r"""
    import hashlib, itertools, json, os, random, signal, sys, time
    from pathlib import Path

    from m3t1r.app import cli
    from m3t1r.model.description import Mechanism, nominal_model_paths
    # imported before forking
    import m3t1r.calibration.closed_loop, m3t1r.app.datasets, m3t1r.model.urdf_io, m3t1r.model.kinematics

    config = json.loads(sys.argv[1])
    folder, measurements = Path(config["folder"]), Path(config["measurements"])
    urdf, closures, report = folder / "c.urdf", folder / "c.closures.yaml", folder / "c.json"
    argv = ["calibrate", str(measurements), "-o", str(urdf), "--report", str(report), "--quiet"]
    inputs = [measurements, *nominal_model_paths()]

    def digest(path):
        return hashlib.sha256(path.read_bytes()).hexdigest()

    def run(plan):
        pid = os.fork()
        if pid == 0:
            code = 99
            try:
                if plan.get("rename") is not None:
                    real = os.replace
                    def replace(src, dst, **kw):
                        aimed = Path(dst).name == plan["rename"]
                        if aimed and plan["when"] == "before":
                            os.kill(os.getpid(), signal.SIGKILL)
                        real(src, dst, **kw)
                        if aimed and plan["when"] == "after":
                            os.kill(os.getpid(), signal.SIGKILL)
                    os.replace = replace
                code = cli.main(argv)
            finally:
                os._exit(code)
        if plan.get("delay") is not None:
            time.sleep(plan["delay"])
            os.kill(pid, plan.get("signal", signal.SIGKILL))
        _, status = os.waitpid(pid, 0)
        return status

    input_digests = {str(p): digest(p) for p in inputs}
    old_input, new_input = config["old_input_sha256"], digest(measurements)
    old = {p.name: p.read_bytes() for p in (urdf, closures, report)}

    def restore_old():
        for name, data in old.items():
            staging = folder / ("restore-" + name)
            staging.write_bytes(data)
            os.replace(staging, folder / name)

    # Uninterrupted runs: the new outputs, and how long a run takes once everything is imported
    # (the shorter of two, so that kills aimed inside a run land inside it on a loaded machine too).
    durations = []
    for _ in range(2):
        start = time.monotonic()
        assert run({}) == 0
        durations.append(time.monotonic() - start)
    duration = min(durations)
    new = {p.name: p.read_bytes() for p in (urdf, closures, report)}
    assert new[urdf.name] != old[urdf.name] and new[closures.name] != old[closures.name]
    restore_old()

    rng = random.Random(config["seed"])
    plans = [{"rename": name, "when": when} for name in (urdf.name, closures.name, report.name)
             for when in ("before", "after")]
    plans += [{"delay": rng.uniform(0.2, duration * 0.9), "signal": signal.SIGTERM}]

    def random_plans():
        # Half anywhere in a run, half in its second half, until enough runs were really killed
        # (on a loaded machine a run may still finish before its kill arrives).
        for k in range(config["max_random_runs"]):
            if sum(o["killed"] and "delay" in o["plan"] for o in outcomes) >= config["random_kills"]:
                return
            high = k % 2 == 1
            yield {"delay": duration * rng.uniform(0.5, 0.85) if high else duration * rng.uniform(0.0, 0.85)}

    outcomes = []
    for plan in itertools.chain(plans, random_plans()):
        status = run(plan)
        state = {}
        for path in inputs:
            assert digest(path) == input_digests[str(path)], f"{plan}: input {path} changed"
        machine = Mechanism.load(urdf)  # must load: old pair, new pair, or new URDF + staged closures
        urdf_bytes = urdf.read_bytes()
        version = "new" if urdf_bytes == new[urdf.name] else "old" if urdf_bytes == old[urdf.name] else None
        assert version is not None, f"{plan}: the URDF is neither the old nor the new one"
        closures_used = machine.closures_document
        refuse = lambda token: (_ for _ in ()).throw(ValueError(token))
        document = json.loads(report.read_bytes(), parse_constant=refuse)
        assert document["input"]["sha256"] in (old_input, new_input), f"{plan}: the report is neither old nor new"
        leftovers = sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))
        killed = os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
        outcomes.append({"plan": {k: v for k, v in plan.items()}, "status": status, "version": version,
                         "killed": killed,
                         "leftovers": leftovers,
                         "closures_final": closures.read_bytes() == (new if version == "new" else old)[closures.name]})
        restore_old()

    # A last complete run sweeps what the killed ones left.
    assert run({}) == 0
    final_leftovers = sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))
    print(json.dumps({"duration": duration, "outcomes": outcomes, "final_leftovers": final_leftovers}))
""")


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_calibrate_killed_at_any_instant_leaves_a_loadable_pair(tmp_path, capsys):
    measurements, old_measurements = tmp_path / "m.csv", tmp_path / "m_old.csv"
    folder = tmp_path / "out"
    folder.mkdir()
    assert main(["simulate", "-n", "20", "--seed", "0", "-o", str(measurements)]) == 0
    assert main(["simulate", "-n", "20", "--seed", "1", "-o", str(old_measurements)]) == 0
    # The old outputs: the same command on other data.
    assert (
        main(
            [
                "calibrate",
                str(old_measurements),
                "-o",
                str(folder / "c.urdf"),
                "--report",
                str(folder / "c.json"),
                "--quiet",
            ]
        )
        == 0
    )
    capsys.readouterr()

    config = {
        "folder": str(folder),
        "measurements": str(measurements),
        "seed": 10,
        "random_kills": 14,
        "max_random_runs": 40,
        "old_input_sha256": hashlib.sha256(old_measurements.read_bytes()).hexdigest(),
    }
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    done = subprocess.run(
        [sys.executable, "-c", WORKER, json.dumps(config)], capture_output=True, text=True, env=env, timeout=300
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    outcomes = result["outcomes"]

    assert len(outcomes) >= 21
    aimed = {(o["plan"]["rename"], o["plan"]["when"]): o for o in outcomes if "rename" in o["plan"]}
    # The URDF rename is the pair's commit point.
    assert aimed[("c.urdf", "before")]["version"] == "old" and aimed[("c.urdf", "after")]["version"] == "new"
    # Killed between the URDF and the closures renames: the new URDF loads with the staged closures.
    assert not aimed[("c.urdf", "after")]["closures_final"]
    assert aimed[("c.closures.yaml", "after")]["closures_final"]
    assert aimed[("c.closures.yaml", "after")]["version"] == "new"
    killed = [o for o in outcomes if o["killed"]]
    assert len(killed) >= 20  # 6 aimed at the renames, at least 14 at random instants
    assert {o["version"] for o in outcomes} == {"old", "new"}  # both outcomes were exercised
    # A caught SIGTERM removes the temporary files itself.
    terminated = [o for o in outcomes if o["plan"].get("signal") == 15]
    assert terminated and not terminated[0]["leftovers"]
    print(f"{len(outcomes)} runs, {len(killed)} killed by SIGKILL, a run takes {result['duration']:.2f} s")
    assert result["final_leftovers"] == []


def test_a_signal_during_the_renames_is_reported_with_every_output_written(tmp_path, capsys, monkeypatch):
    """Ctrl-C while the outputs are renamed into place is held back until they all are, then stops the
    command (status 130) saying so, where it said 'not written' of outputs that were all in place."""
    import signal

    sliders = tmp_path / "s.csv"
    sliders.write_text("q11,q11_B2,q21,q21_B4\n0,0,0,0\n")
    rename = os.replace
    calls = []

    def interrupted_rename(source, target):
        # Only the commit's rename of this command's output: any other os.replace in the process (a
        # claim, a sweep, another thread) must neither take the signal nor count.
        if Path(target) == tmp_path / "p.csv":
            if not calls:
                signal.raise_signal(signal.SIGINT)  # arrives during the commit
            calls.append(target)
        rename(source, target)

    monkeypatch.setattr(os, "replace", interrupted_rename)
    # A process started in the background by a non-interactive shell (a CI runner, `cmd &`) inherits
    # SIGINT ignored, and rightly goes on through a Ctrl-C: this test is of one that takes it.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert main(["fk", str(sliders), "-o", str(tmp_path / "p.csv")]) == 130
    finally:
        signal.signal(signal.SIGINT, previous)
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert (
        f"m3t1r: interrupted; it arrived while the outputs were renamed into place, and every one is "
        f"written: {tmp_path / 'p.csv'}"
    ) in err
    assert "x,y,z,qx,qy,qz,qw" in (tmp_path / "p.csv").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.csv", "s.csv"]


def test_fk_on_many_rows_shows_progress_and_stops_soon_after_sigterm(tmp_path):
    """`fk` on 240 000 rows: a progress line while it solves, and SIGTERM stops it within seconds with
    nothing written, where one vectorised solve of every row showed nothing and held the signal
    back until it ended (87 s for a million rows)."""
    import signal
    import time

    import numpy as np

    from m3t1r.model.description import Mechanism
    from m3t1r.model.workspace import workspace_actuators

    mechanism = Mechanism.load()
    sliders = np.tile(workspace_actuators(mechanism, 500, np.random.default_rng(0)), (480, 1))
    source = tmp_path / "s.csv"
    np.savetxt(source, sliders, delimiter=",", header=",".join(mechanism.actuated_joints), comments="", fmt="%.17g")
    child = subprocess.Popen(
        [sys.executable, "-m", "m3t1r.app.cli", "fk", str(source), "-o", str(tmp_path / "p.csv")],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )
    try:
        seen = [child.stderr.readline()]
        while seen[-1] and not seen[-1].startswith("fk: "):
            seen.append(child.stderr.readline())
        assert seen[-1].startswith("fk: ") and "/240000" in seen[-1], seen
        sent = time.monotonic()
        child.send_signal(signal.SIGTERM)
        assert child.wait(timeout=60) == 128 + signal.SIGTERM
        assert time.monotonic() - sent < 5.0
    finally:
        child.kill()
        child.wait()
    assert "terminated by signal SIGTERM; outputs not yet in place were not written" in child.stderr.read()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv"]


# ==================================================================================================
# Signals in process: Terminated, termination_as_exception and held signals
#
# The tests above kill real subprocesses; these run in the test process: `Terminated` carries its signal,
# `termination_as_exception` raises it and restores the previous handlers, and a signal held during a
# block of renames is delivered when the block ends.
# ==================================================================================================


@pytest.mark.parametrize(("signum", "name"), [(signal.SIGTERM, "SIGTERM"), (signal.SIGHUP, "SIGHUP")])
def test_terminated_names_its_signal(signum, name):
    error = Terminated(signum)
    assert error.signum == signum
    assert str(error) == f"terminated by signal {name}"
    assert isinstance(error, BaseException) and not isinstance(error, Exception)


def test_termination_raises_inside_the_block_and_restores_handlers():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGHUP)
    with pytest.raises(Terminated) as caught:
        with termination_as_exception():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs between bytecodes
                pass
    assert caught.value.signum == signal.SIGTERM
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGHUP)) == before


def test_a_signal_held_during_the_renames_arrives_after_them():
    events: list[str] = []
    with pytest.raises(Terminated):
        with termination_as_exception():
            with signals_deferred() as pending:
                signal.pthread_kill(threading.main_thread().ident, signal.SIGHUP)
                for _ in range(1000):
                    pass
                events.append("renamed")
            assert pending == [signal.SIGHUP]
            deliver_signals(pending)
            for _ in range(1000):
                pass
            events.append("not reached")
    assert events == ["renamed"]
