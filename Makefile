# Developer entry points: `make test` bootstraps .venv from PyPI (requirements.txt) on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# test files run on this many worker processes (pytest-xdist): the cores, at most 4
TEST_JOBS ?= $(shell $(PYTHON) -c 'import os; print(max(1, min(4, len(os.sched_getaffinity(0)))))' 2>/dev/null || echo 1)

# DDS stays on loopback for everything started from here (DESIGN.md section 4).
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp
export PYTHONHASHSEED := 0

.PHONY: venv warm test lint demo bench clean check-python

venv: $(VENV)/.stamp $(VENV)/.warm

check-python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: '$(PYTHON)' not found on PATH (need Python >= 3.10)" >&2; exit 1; }
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "error: Python >= 3.10 is needed, $(PYTHON) is " + sys.version.split()[0])'

$(VENV)/.stamp: requirements.txt setup.py setup.cfg package.xml
	@$(MAKE) --no-print-directory check-python
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.txt
	$(BIN)/python -m pip install --quiet -e . --no-deps
	@touch $(VENV)/COLCON_IGNORE $@

# numba's kernels compiled into its cache once per install and per change of the sources (the
# cache folder is keyed by them), so no tool's first run compiles (transplanter_ident/cli/warm.py).
PACKAGE_SOURCES := $(shell find transplanter_ident -name '*.py' 2>/dev/null)

warm: $(VENV)/.warm

$(VENV)/.warm: $(VENV)/.stamp $(PACKAGE_SOURCES)
	$(BIN)/python -m transplanter_ident.cli.warm
	@touch $@

test: venv
	$(BIN)/ruff check transplanter_ident test
	@$(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadfile test; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "error: pytest collected no tests (exit code 5); treating that as a failure" >&2; exit 1; fi; \
	exit $$rc

lint: $(VENV)/.stamp
	$(BIN)/ruff check .

demo: venv
	$(BIN)/python -m transplanter_ident.cli.demo

bench: venv
	$(BIN)/python bench/run.py

clean:
	rm -rf $(VENV) build install log .pytest_cache .ruff_cache *.egg-info
	find . -name __pycache__ -type d -prune -exec rm -rf {} +

# Regenerate the committed sample bags (bags/README.md lists the same commands).
.PHONY: bags
bags: venv
	$(BIN)/python -m transplanter_ident.cli.simulate -o bags/step20-ccw --scenario step20-ccw --seed 1 --compress --force
	$(BIN)/python -m transplanter_ident.cli.simulate -o bags/step30-cw --scenario step30-cw --seed 2 --compress --force
	$(BIN)/python -m transplanter_ident.cli.simulate -o bags/sine --scenario sine --seed 3 --compress --force
	$(BIN)/python -m transplanter_ident.cli.simulate -o bags/surface-change --scenario surface-change --seed 4 --compress --force
