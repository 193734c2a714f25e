# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
# STAMP: the package and its runtime dependencies, with cmeel-eigen for `make native` (what `make demo` needs);
# DEV_STAMP: also the test tools, Jupyter and the instrument readers of `m3t1r convert` (`make test`).
STAMP := $(VENV)/.installed
DEV_STAMP := $(VENV)/.installed-dev

.PHONY: demo test bench models notebooks lab mutation clean native

# The editable install compiles the Newton loop in place (hatch_build.py), or fails saying why.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	@echo "installing m3t1r and its dependencies into $(VENV) (compiling the Newton loop when out of date: a few minutes)"
	$(BIN)/python -m pip install --quiet -e '.[native]'
	touch $(STAMP)

$(DEV_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[native,dev,notebooks,formats]'
	touch $(DEV_STAMP)

# The compiled Newton loop of FK and IK (src/m3t1r/model/_native_core.hpp and _native_newton.cpp; about a
# minute of g++ after an edit, a no-op when up to date). Without it the solvers run their pure-Python loop,
# four to six times slower; M3T1R_PURE_PYTHON=1 skips it.
native: $(STAMP)
	$(BIN)/python tools/build_native.py

demo: native
	$(BIN)/m3t1r demo --out demo_out

test: native $(DEV_STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q

bench: native
	$(BIN)/python benchmarks/run_all.py

# Mutation testing of the core modules, one module at a time, in copies under build/mutation/
# (slow: not part of `make test`). MODULES="model.kinematics model.poe" restricts it; see docs/mutation.md.
MODULES ?=
mutation: $(DEV_STAMP)
	$(BIN)/python tools/mutation.py $(MODULES)

# Regenerate notebooks/*.ipynb (no outputs) from their jupytext scripts notebooks/*.py, the source of truth.
notebooks: $(DEV_STAMP)
	$(BIN)/jupytext --to ipynb $(wildcard notebooks/*.py)

# Open the notebooks in JupyterLab (the .ipynb files; jupytext's "Open With" opens the .py sources too).
lab: native $(DEV_STAMP)
	$(BIN)/jupyter lab notebooks/

# Regenerate models/m3t1r.urdf and models/m3t1r.closures.yaml from the nominal design.
models: $(STAMP)
	$(BIN)/python models/generate.py

clean:
	rm -rf $(VENV) demo_out src/m3t1r/model/_native_newton*.so
