"""Mutation testing of the core modules, one module at a time (`make mutation`).

For each module named on the command line (default: every key of [tool.m3t1r-mutation.tests] in
pyproject.toml) this copies the working tree into build/mutation/<module>/, points mutmut's
`only_mutate` and test selection at that module and its own tests (the fastest relevant subset),
runs `nice -n 10 mutmut run` there (mutmut 3 mutates and runs tests in a `mutants/` folder inside
that copy, never in the checkout), and prints the score:

    score = killed / (mutants - equivalent)

where "killed" counts mutants whose tests failed or timed out, every other status (survived, no
test covers it, suspicious, skipped) counts against the score, and "equivalent" are the mutants
that docs/mutation.md lists as changes no test can observe. A row there names a change, not
mutmut's generated name (which is numbered within the function and shifts with every edit): the
function, its line as written and the line as the mutant writes it. Every mutant of that function
making that change to a line of that text matches the row; a row that matches no mutant is
reported as stale, and a survivor is written in the same row format, ready to be reviewed.

With --functions NAME ... (`name` or `Class.name`, as a row writes them) only those functions' mutants
run and count: the score of what an edit touched, in minutes where the module takes an hour.

Usage: python tools/mutation.py [MODULE ...] [--max-children N] [--workdir DIR] [--functions NAME ...]
"""

from __future__ import annotations

import argparse
import ast
import difflib
import re
import shutil
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import tomllib
from mutmut.mutation.file_mutation import mutate_file_contents
from mutmut.utils.format_utils import orig_function_and_class_names_from_key

ROOT = Path(__file__).resolve().parents[1]
KILLED = {"killed", "timeout", "caught by type check"}
LINE_BREAK = " ⏎ "  # joins the lines of a change that spans several


@dataclass(frozen=True)
class MutantChange:
    """What a mutant changes: the function (`name` or `Class.name`) and its changed lines, stripped."""

    module: str
    function: str
    original: str
    mutated: str

    def row(self, why: str = "") -> str:
        """The change as a row of docs/mutation.md's table of its module."""
        return f"| {code_cell(self.function)} | {code_cell(self.original)} | {code_cell(self.mutated)} | {why} |"


def code_cell(text: str) -> str:
    """`text` as a code span in a Markdown table cell: `|` escaped, doubled backticks around a backtick."""
    text = text.replace("|", "\\|")
    return f"`` {text} ``" if "`" in text else f"`{text}`"


def cell_text(cell: str) -> str:
    """The inverse of `code_cell`."""
    cell = cell.strip()
    if cell.startswith("`` ") and cell.endswith(" ``"):
        cell = cell[3:-3]
    elif cell.startswith("`") and cell.endswith("`"):
        cell = cell[1:-1]
    return cell.replace("\\|", "|")


def equivalent_changes(text: str | None = None) -> dict[MutantChange, str]:
    """docs/mutation.md's equivalent mutants, each with its reason: the rows of the tables under a
    `### <module>` heading of its "Equivalent mutants" section."""
    if text is None:
        text = (ROOT / "docs" / "mutation.md").read_text(encoding="utf-8")
    changes: dict[MutantChange, str] = {}
    module = None
    for line in text.splitlines():
        if line.startswith("## "):
            module = None
        elif line.startswith("### "):
            module = line[4:].strip().strip("`")
        elif module and line.startswith("| `"):
            cells = re.split(r"(?<!\\)\|", line.strip())[1:-1]
            function, original, mutated, why = (cells + [""] * 4)[:4]
            changes[MutantChange(module, cell_text(function), cell_text(original), cell_text(mutated))] = why.strip()
    return changes


def mutant_changes(module: str, root: Path = ROOT) -> dict[str, MutantChange]:
    """Every mutant mutmut generates for `module` of the tree at `root` (by its generated name) and
    what it changes.

    Generated with mutmut's own mutator, the same as `mutmut run`'s; the mutated file is parsed once
    and each mutant diffed against the function's original copy."""
    path = module_path(module)
    mutated = mutate_file_contents(path, (root / path).read_text(encoding="utf-8"))
    functions = generated_functions(mutated.code)
    changes = {}
    for generated in mutated.mutant_names:
        name = f"m3t1r.{module}.{generated}"
        function, class_name = orig_function_and_class_names_from_key(name)
        original = functions[generated.partition("__mutmut_")[0] + "__mutmut_orig"]
        diff = list(difflib.unified_diff(original.splitlines(), functions[generated].splitlines(), lineterm="", n=0))
        removed = [line[1:].strip() for line in diff[2:] if line.startswith("-")]
        added = [line[1:].strip() for line in diff[2:] if line.startswith("+")]
        qualified = f"{class_name}.{function}" if class_name else function
        changes[name] = MutantChange(module, qualified, LINE_BREAK.join(removed), LINE_BREAK.join(added))
    return changes


def generated_functions(code: str) -> dict[str, str]:
    """The text of every function and method of mutmut's mutated file by generated name, the name
    itself left out of its `def` line (a mutant can change a default argument's value)."""
    lines = code.splitlines(keepends=True)
    bodies = {}
    for node in ast.parse(code).body:
        for function in node.body if isinstance(node, ast.ClassDef) else [node]:
            if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
                text = "".join(lines[function.lineno - 1 : function.end_lineno])
                bodies[function.name] = text.replace(f"def {function.name}(", "def (", 1)
    return bodies


def copy_tree(destination: Path) -> None:
    files = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard", "src", "tests", "models", "pyproject.toml"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
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
    text = re.sub(
        r"^pytest_add_cli_args_test_selection = .*$",
        f"pytest_add_cli_args_test_selection = {as_toml(tests)}",
        text,
        flags=re.MULTILINE,
    )
    path.write_text(text, encoding="utf-8")


def results(copy: Path) -> dict[str, str]:
    output = subprocess.run(
        [sys.executable, "-m", "mutmut", "results", "--all", "true"],
        cwd=copy,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return dict(line.strip().rsplit(": ", 1) for line in output.splitlines() if ": " in line)


def mutant_pattern(module: str, function: str) -> str:
    """mutmut's name pattern of the mutants of `function` (`name` or `Class.name`) in `module`."""
    class_name, _, name = function.rpartition(".")
    return f"m3t1r.{module}." + (f"x\u01c1{class_name}\u01c1{name}" if class_name else f"x_{name}") + "__mutmut_*"


def run_module(
    module: str, tests: list[str], max_children: int, workdir: Path, functions: list[str] | None = None
) -> tuple[int, int, int, Counter]:
    copy = workdir / module
    copy_tree(copy)
    configure(copy, module, tests)
    log = workdir / f"{module}.log"  # mutmut's output: why a run failed (e.g. its clean test run)
    names = [mutant_pattern(module, f) for f in functions or ()]
    with log.open("w") as output:
        subprocess.run(
            ["nice", "-n", "10", sys.executable, "-m", "mutmut", "run", "--max-children", str(max_children), *names],
            cwd=copy,
            check=True,
            stdout=output,
            stderr=subprocess.STDOUT,
        )
    changes = mutant_changes(module, copy)  # the copy's source: the checkout may change during the run
    statuses = {
        name: status for name, status in results(copy).items() if not functions or changes[name].function in functions
    }
    equivalent = {change for change in equivalent_changes() if change.module == module}
    counted = {name: status for name, status in statuses.items() if changes[name] not in equivalent}
    counts = Counter(counted.values())
    killed = sum(n for status, n in counts.items() if status in KILLED)
    survivors = sorted(name for name, status in counted.items() if status not in KILLED)
    stale = {change for change in equivalent if not functions or change.function in functions} - {
        changes[name] for name in statuses
    }
    (workdir / f"{module}.survivors.txt").write_text(
        "".join(f"{changes[n].row(counted[n])}\n" for n in survivors)
        + "".join(f"stale row, no such mutant: {change.row()}\n" for change in sorted(stale, key=str))
    )
    return killed, len(counted), len(statuses) - len(counted), counts


def main() -> int:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["m3t1r-mutation"]["tests"]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", default=list(config), help=f"among {', '.join(config)}")
    parser.add_argument("--max-children", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=ROOT / "build" / "mutation")
    parser.add_argument("--functions", nargs="+", help="only these functions' mutants (name or Class.name)")
    args = parser.parse_args()
    unknown = [m for m in args.modules if m not in config]
    if unknown:
        parser.error(f"no test selection for {unknown} in [tool.m3t1r-mutation.tests]")
    args.workdir.mkdir(parents=True, exist_ok=True)
    total_killed = total = 0
    print(f"{'module':<16} {'killed':>7} {'counted':>8} {'equivalent':>11} {'score':>7}  other statuses")
    for module in args.modules:
        killed, counted, equivalent, counts = run_module(
            module, config[module], args.max_children, args.workdir, args.functions
        )
        total_killed, total = total_killed + killed, total + counted
        other = ", ".join(f"{s} {n}" for s, n in sorted(counts.items()) if s not in KILLED)
        print(
            f"{module:<16} {killed:>7} {counted:>8} {equivalent:>11} {100 * killed / max(counted, 1):>6.1f}%  {other}",
            flush=True,
        )
    print(f"{'total':<16} {total_killed:>7} {total:>8} {'':>11} {100 * total_killed / max(total, 1):>6.1f}%")
    print(f"survivors (and stale rows of docs/mutation.md) listed in {args.workdir}/<module>.survivors.txt")
    return 0


if __name__ == "__main__":
    sys.exit(main())
