# Quick start:  make demo   |   make test
# Both create their own virtual environment (.venv) and install everything.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: demo test test-fast bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

## Run the main job on the embedded default bench (no hardware needed).
demo: $(STAMP)
	$(VENV)/bin/online-id demo

## Run the whole test suite.
test: $(STAMP)
	$(PY) -m pytest $(PYTEST_ARGS)

## Only the fast tier (no slow identification runs).
test-fast: $(STAMP)
	$(PY) -m pytest -m "not slow and not vcan" $(PYTEST_ARGS)

## Benchmarks (run by hand; figures go into the README).
bench: $(STAMP)
	$(PY) benchmarks/bench_recursive.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
