"""The package's imports flow one way: ground -> model -> calibration -> compensation -> paper -> app.

Every module's imports are read with `ast`, at module level and inside functions (an import in a
function still makes an arrow), including `if TYPE_CHECKING:` imports. The test asserts:

(a) no cycle among m3t1r modules;
(b) no arrow pointing up the layer order;
(c) no function-level import of an m3t1r module (none is needed now that the graph is acyclic);
(d) no module imports the package facade `m3t1r/__init__.py`, which re-exports the public API, nor
    `m3t1r/paper/__init__.py`, which re-exports the paper's (for notebooks: `from m3t1r import paper`);
    `m3t1r/io/__init__.py` re-exports nothing, so io names come from its modules anyway.

A layer's prefix covers a subpackage's modules: `m3t1r.io` is the ground's io package (paths, pairing,
temporaries, signals, strict_json, outputs, tables, poses, progress), `m3t1r.paper` the paper's
package (chains, error_model, identification, passive_angles, simulation, study, closed_chain).

Allowed exceptions, listed explicitly: the app layer sits above the paper layer (the `paper`
verb runs the paper's study), so app -> paper is a downward arrow, not a sideways one. There is no
other exception.
"""

from __future__ import annotations

import ast
import dataclasses
import graphlib
import importlib
import inspect
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

# Lowest first. A module belongs to the first layer whose prefix matches its dotted name (`m3t1r.io`
# covers m3t1r.io.tables, `m3t1r.paper` covers m3t1r.paper.study, and so on).
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("ground", ("m3t1r.errors", "m3t1r._lazy", "m3t1r._threads", "m3t1r._version", "m3t1r.io", "m3t1r.metrics")),
    ("model", ("m3t1r.model",)),
    ("calibration", ("m3t1r.calibration",)),
    ("compensation", ("m3t1r.compensation",)),
    ("paper", ("m3t1r.paper",)),
    ("app", ("m3t1r.app",)),
    ("facade", ("m3t1r",)),
]
# Function-level imports of m3t1r modules that are allowed (module, imported module): none.
ALLOWED_FUNCTION_LEVEL: set[tuple[str, str]] = set()


def _modules() -> dict[str, tuple[Path, bool]]:
    found = {}
    for path in sorted((SRC / "m3t1r").rglob("*.py")):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        found[".".join(parts)] = (path, is_package)
    return found


MODULES = _modules()


def _layer(module: str) -> int:
    for index, (_, prefixes) in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes if p != "m3t1r"):
            return index
    assert module == "m3t1r", f"{module} belongs to no layer: add it to LAYERS"
    return len(LAYERS) - 1


def _imports(module: str) -> list[tuple[str, int, bool]]:
    """(imported m3t1r module, line, inside a function) for every import statement of `module`."""
    path, is_package = MODULES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    in_function: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            in_function.update(id(child) for child in ast.walk(node) if child is not node)
    found = []
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # `from m3t1r.calibration import serial` imports the module m3t1r.calibration.serial
            targets = [f"{source}.{a.name}" if f"{source}.{a.name}" in MODULES else source for a in node.names]
        for target in targets:
            if target == "m3t1r" or target.startswith("m3t1r."):
                found.append((target, node.lineno, id(node) in in_function))
    return found


GRAPH = {module: _imports(module) for module in MODULES}


def test_every_module_has_a_layer():
    assert len(MODULES) > 30
    for module in MODULES:
        _layer(module)
    for module, imports in GRAPH.items():
        for target, line, _ in imports:
            assert target in MODULES, f"{module}:{line} imports {target}, which is not a module of the package"


def test_no_import_cycles():
    sorter = graphlib.TopologicalSorter({m: {t for t, _, _ in imports if t != m} for m, imports in GRAPH.items()})
    try:
        sorter.prepare()
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")


def test_no_arrow_points_up_the_layers():
    upward = []
    for module, imports in GRAPH.items():
        for target, line, _ in imports:
            if _layer(target) > _layer(module):
                upward.append(
                    f"{module}:{line} ({LAYERS[_layer(module)][0]}) imports {target} ({LAYERS[_layer(target)][0]})"
                )
    assert not upward, "\n".join(upward)


def test_no_function_level_imports_of_package_modules():
    hidden = [
        f"{module}:{line} imports {target} inside a function"
        for module, imports in GRAPH.items()
        for target, line, inside in imports
        if inside and (module, target) not in ALLOWED_FUNCTION_LEVEL
    ]
    assert not hidden, "\n".join(hidden)


# Packages whose __init__ re-exports their modules' names, for users outside the package.
FACADES = ("m3t1r", "m3t1r.paper")


def test_nothing_inside_imports_the_facade():
    assert [m for m, imports in GRAPH.items() if m != "m3t1r" and any(t == "m3t1r" for t, _, _ in imports)] == []


def test_nothing_inside_imports_a_subpackage_facade():
    found = [
        f"{module}:{line} imports {target}"
        for module, imports in GRAPH.items()
        if module not in FACADES
        for target, line, _ in imports
        if target in FACADES
    ]
    assert found == []


def test_the_io_package_exports_nothing():
    body = ast.parse((SRC / "m3t1r" / "io" / "__init__.py").read_text(encoding="utf-8")).body
    assert len(body) == 1 and isinstance(body[0], ast.Expr)  # its docstring only


def test_the_facade_exports_what_it_names():
    import m3t1r

    assert len(set(m3t1r.__all__)) == len(m3t1r.__all__)
    missing = [name for name in m3t1r.__all__ if not hasattr(m3t1r, name)]
    assert missing == []
    assert (SRC / "m3t1r" / "py.typed").is_file()


# ------------------------------------------------------------------------------------------------
# A public signature stays short: at most MAX_PARAMETERS parameters (self/cls and *args/**kwargs
# aside); settings that travel together belong in a small frozen dataclass (CalibrationOptions,
# StudyOptions, TwoChainOptions, PlotFile, ...).
MAX_PARAMETERS = 8
# Justified exceptions, "module.qualname": none. Dataclass and NamedTuple constructors are exempt
# (checked below): their fields are the record itself, one parameter per field by construction.
ALLOWED_LONG_SIGNATURES: set[str] = set()


def _is_record(cls: type) -> bool:
    return dataclasses.is_dataclass(cls) or (issubclass(cls, tuple) and hasattr(cls, "_fields"))


def _counted_parameters(function: object, is_method: bool) -> int:
    parameters = list(inspect.signature(function).parameters.values())  # type: ignore[arg-type]
    if is_method and parameters and parameters[0].name in ("self", "cls"):
        parameters = parameters[1:]
    return sum(p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD) for p in parameters)


def _public_callables() -> list[tuple[str, object, bool]]:
    """(name, function, is_method) for every function in a module's __all__ and every public method
    (and __init__) defined by a public class there."""
    found: list[tuple[str, object, bool]] = []
    for module_name in sorted(MODULES):
        module = importlib.import_module(module_name)
        for name in getattr(module, "__all__", ()):
            value = getattr(module, name)
            if getattr(value, "__module__", None) != module_name:
                continue  # a re-export: checked where it is defined
            if inspect.isfunction(value):
                found.append((f"{module_name}.{name}", value, False))
            elif inspect.isclass(value):
                for attribute, member in vars(value).items():
                    if attribute.startswith("_") and attribute != "__init__":
                        continue
                    if attribute == "__init__" and _is_record(value):
                        continue
                    is_static = isinstance(member, staticmethod)
                    function = member.__func__ if isinstance(member, (staticmethod, classmethod)) else member
                    if inspect.isfunction(function):
                        found.append((f"{module_name}.{name}.{attribute}", function, not is_static))
    return found


def test_public_functions_take_at_most_eight_parameters():
    callables = _public_callables()
    assert len(callables) > 100  # the walk sees the public API, not an empty list
    long = {
        name: count
        for name, function, is_method in callables
        if (count := _counted_parameters(function, is_method)) > MAX_PARAMETERS
    }
    assert {name: count for name, count in long.items() if name not in ALLOWED_LONG_SIGNATURES} == {}
    assert ALLOWED_LONG_SIGNATURES <= set(long), "an allowed exception that is no longer long"
