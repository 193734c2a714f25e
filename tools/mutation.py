"""Mutation testing of the core modules, one module at a time (`make mutation`).

For each module named on the command line (default: every key of [tool.m3t1r-mutation.tests] in
pyproject.toml) this copies the working tree into build/mutation/<module>/, points mutmut's
`only_mutate` and test selection at that module and its own tests (the fastest relevant subset),
runs `nice -n 10 mutmut run` there (mutmut 3 mutates and runs tests in a `mutants/` folder inside
that copy, never in the checkout), and prints the score:

    score = killed / (mutants - equivalent)

where "killed" counts mutants whose tests failed or timed out, every other status (survived, no
test covers it, suspicious, skipped) counts against the score, and "equivalent" are the mutants
listed in docs/mutation.md (a row starting with the mutant's name in backticks), which no test
can kill. Mutant names are numbered within each function: after an edit of a module, re-review
its equivalent list.

Usage: python tools/mutation.py [MODULE ...] [--max-children N] [--keep]
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
KILLED = {"killed", "timeout", "caught by type check"}


def equivalent_mutants() -> set[str]:
    text = (ROOT / "docs" / "mutation.md").read_text(encoding="utf-8")
    return set(re.findall(r"^\|\s*`(m3t1r\.[^`]+)`", text, flags=re.MULTILINE))


def copy_tree(destination: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "src", "tests", "models", "pyproject.toml"],
                           cwd=ROOT, check=True, capture_output=True, text=True).stdout.split()
    # The compiled Newton loop is built, not tracked: the copy's tests run the same solver as the checkout's.
    files += [str(p.relative_to(ROOT)) for p in (ROOT / "src" / "m3t1r" / "model").glob("_native_newton*.so")]
    if destination.exists():
        shutil.rmtree(destination)
    for name in files:
        source = ROOT / name
        if source.is_file():
            target = destination / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)


def module_path(module: str) -> str:
    """`model.kinematics` -> `src/m3t1r/model/kinematics.py`: a module's key in [tool.m3t1r-mutation.tests]."""
    return "src/m3t1r/" + module.replace(".", "/") + ".py"


def configure(copy: Path, module: str, tests: list[str]) -> None:
    path = copy / "pyproject.toml"
    text = path.read_text(encoding="utf-8")
    as_toml = lambda items: "[" + ", ".join(f'"{item}"' for item in items) + "]"  # noqa: E731
    text = re.sub(r"^only_mutate = .*$", f"only_mutate = {as_toml([module_path(module)])}", text, flags=re.MULTILINE)
    text = re.sub(r"^pytest_add_cli_args_test_selection = .*$",
                  f"pytest_add_cli_args_test_selection = {as_toml(tests)}", text, flags=re.MULTILINE)
    path.write_text(text, encoding="utf-8")


def results(copy: Path) -> dict[str, str]:
    output = subprocess.run([sys.executable, "-m", "mutmut", "results", "--all", "true"], cwd=copy, check=True,
                            capture_output=True, text=True).stdout
    return dict(line.strip().rsplit(": ", 1) for line in output.splitlines() if ": " in line)


def run_module(module: str, tests: list[str], max_children: int, workdir: Path) -> tuple[int, int, int, Counter]:
    copy = workdir / module
    copy_tree(copy)
    configure(copy, module, tests)
    log = workdir / f"{module}.log"  # mutmut's output: why a run failed (e.g. its clean test run)
    with log.open("w") as output:
        subprocess.run(["nice", "-n", "10", sys.executable, "-m", "mutmut", "run", "--max-children", str(max_children)],
                       cwd=copy, check=True, stdout=output, stderr=subprocess.STDOUT)
    statuses = results(copy)
    equivalent = equivalent_mutants()
    counted = {name: status for name, status in statuses.items() if name not in equivalent}
    counts = Counter(counted.values())
    killed = sum(n for status, n in counts.items() if status in KILLED)
    survivors = sorted(name for name, status in counted.items() if status not in KILLED)
    (workdir / f"{module}.survivors.txt").write_text("".join(f"{n}: {counted[n]}\n" for n in survivors))
    return killed, len(counted), len(statuses) - len(counted), counts


def main() -> int:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["m3t1r-mutation"]["tests"]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", default=list(config), help=f"among {', '.join(config)}")
    parser.add_argument("--max-children", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=ROOT / "build" / "mutation")
    args = parser.parse_args()
    unknown = [m for m in args.modules if m not in config]
    if unknown:
        parser.error(f"no test selection for {unknown} in [tool.m3t1r-mutation.tests]")
    args.workdir.mkdir(parents=True, exist_ok=True)
    total_killed = total = 0
    print(f"{'module':<16} {'killed':>7} {'counted':>8} {'equivalent':>11} {'score':>7}  other statuses")
    for module in args.modules:
        killed, counted, equivalent, counts = run_module(module, config[module], args.max_children, args.workdir)
        total_killed, total = total_killed + killed, total + counted
        other = ", ".join(f"{s} {n}" for s, n in sorted(counts.items()) if s not in KILLED)
        print(f"{module:<16} {killed:>7} {counted:>8} {equivalent:>11} {100 * killed / max(counted, 1):>6.1f}%  {other}",
              flush=True)
    print(f"{'total':<16} {total_killed:>7} {total:>8} {'':>11} {100 * total_killed / max(total, 1):>6.1f}%")
    print(f"survivors listed in {args.workdir}/<module>.survivors.txt")
    return 0


if __name__ == "__main__":
    sys.exit(main())
