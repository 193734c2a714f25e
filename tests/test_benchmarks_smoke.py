"""Smoke run of every benchmark at tiny sizes: each prints its tables and the run succeeds.

No timing is asserted here: timings belong to the benchmarks themselves (benchmarks/README.md).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TITLES = (
    "## Closed-loop kinematics",
    "## Kinematics in units of one Pinocchio pass",
    "## Kinematics against the evaluation floor",
    "## Serial identification",
    "## Scaling",
    "## Calibration memory by pose count",
    "## Pose selection",
    "## Uncertainty",
    "## Tracker campaign",
    "## Start-up of the command line and the package",
)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess, Path]:
    out_dir = tmp_path_factory.mktemp("bench")
    completed = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick", "--out-dir", str(out_dir)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    return completed, out_dir


def test_every_benchmark_runs_and_prints_its_tables(quick_run) -> None:
    completed, _ = quick_run
    assert completed.returncode == 0, completed.stdout[-3000:] + completed.stderr[-3000:]
    output = completed.stdout
    for title in TITLES:
        assert title in output, f"missing section {title!r}"
    sections = output.split("<!-- benchmarks/bench_")[1:]
    assert len(sections) == len(TITLES)
    for section in sections:
        assert "| " in section and "|---" in section, "a benchmark printed no table"
        assert "- machine:" in section and "- command:" in section and "- date:" in section
    assert "FAILED" not in output


def test_uncertainty_map_is_written(quick_run) -> None:
    _, out_dir = quick_run
    image = out_dir / "uncertainty_map.png"
    assert image.is_file() and image.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_against_an_earlier_revision_runs_in_one_process() -> None:
    """`bench_against.py REV` imports the revision's package beside the tree's and times both; against
    HEAD itself the results agree to rounding."""
    completed = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_against.py"), "HEAD", "--quick"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert completed.returncode == 0, completed.stdout[-3000:] + completed.stderr[-3000:]
    rows = [line for line in completed.stdout.splitlines() if line.startswith("| ") and "operation" not in line]
    assert [row.split("|")[1].strip() for row in rows] == [
        "FK warm (path)",
        "IK warm (path)",
        "compensation (path)",
        "forward_batch",
    ]
    for row in rows:
        assert float(row.split("|")[-2]) <= 1e-12  # the same code on both sides
