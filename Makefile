# Quick start:  make demo   |   make test
# Both create their own virtual environment (.venv) and install everything.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: demo test test-fast bench clean system-deps

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# PYTHONWARNINGS: setuptools' notice that an editable install links to this checkout (not a packaging fault)
	PYTHONWARNINGS=ignore $(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

## Run the main job on the embedded default bench (no hardware needed).
demo: $(STAMP)
	$(VENV)/bin/online-id demo

## Debian packages of the vcan tier (QEMU, User-Mode Linux, can-utils ...) and its guest kernel:
## installed when root, else only reported (the vcan tier then skips, saying why in one line).
system-deps:
	scripts/install-system-deps

## Run the whole test suite: the live tier (the service as its own process over kernel sockets, at real time)
## and the vcan tier on a real SocketCAN vcan0 (natively, or inside another kernel when this one has no vcan:
## scripts/vm-run) in the background, beside everything else natively on both cores (pytest-xdist, at a lower
## priority). Lists the slowest tests and each tier's time; fails if any part fails (scripts/test-all,
## docs/testing.md).
test: system-deps $(STAMP)
	scripts/test-all $(PY) $(PYTEST_ARGS)

## Only the fast tier (no slow identification runs).
test-fast: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadscope --no-loadscope-reorder -m "not slow and not vcan and not live" $(PYTEST_ARGS)

## Benchmarks (run by hand; figures go into the README).
bench: $(STAMP)
	$(PY) benchmarks/bench_recursive.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
