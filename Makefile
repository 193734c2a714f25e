# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench models notebooks mutation clean native

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# The compiled Newton loop of FK and IK (src/m3t1r/model/_native_core.hpp and _native_newton.cpp; about a
# minute of g++ the first time, a no-op when up to date). Without it the solvers run their pure-Python loop.
native: $(STAMP)
	$(BIN)/python tools/build_native.py

demo: native
	$(BIN)/m3t1r demo --out demo_out

test: native
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q

bench: native
	$(BIN)/python benchmarks/run_all.py

# Mutation testing of the core modules, one module at a time, in copies under build/mutation/
# (slow: not part of `make test`). MODULES="model.kinematics model.poe" restricts it; see docs/mutation.md.
MODULES ?=
mutation: $(STAMP)
	$(BIN)/python tools/mutation.py $(MODULES)

# Regenerate notebooks/*.ipynb (no outputs) from their jupytext scripts notebooks/*.py, the source of truth.
notebooks: $(STAMP)
	$(BIN)/jupytext --to ipynb $(wildcard notebooks/*.py)

# Regenerate models/m3t1r.urdf and models/m3t1r.closures.yaml from the nominal design.
models: $(STAMP)
	$(BIN)/python models/generate.py

clean:
	rm -rf $(VENV) demo_out src/m3t1r/model/_native_newton*.so
