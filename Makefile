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

## Debian packages of the vcan tier (User-Mode Linux, can-utils): installed
## when root, else only reported (the vcan tests then skip, saying why).
system-deps:
	scripts/install-system-deps

## Run the whole test suite: everything but the live and vcan tiers natively on both cores (pytest-xdist),
## then the live tier (the service as its own process over kernel sockets, at real time: run alone,
## so the suite's own load does not compete with it), then the vcan tier on a real SocketCAN vcan0
## (natively, or inside User-Mode Linux when this kernel has no vcan). Fails if any part fails.
test: system-deps $(STAMP)
	@native=0; live=0; vcan=0; \
	echo '$(PY) -m pytest -n 2 -m "not vcan and not live" $(PYTEST_ARGS)'; \
	$(PY) -m pytest -n 2 -m "not vcan and not live" $(PYTEST_ARGS) || native=$$?; \
	echo '$(PY) -m pytest -m live tests/live $(PYTEST_ARGS)'; \
	$(PY) -m pytest -m live tests/live $(PYTEST_ARGS) || live=$$?; \
	echo 'scripts/test-vcan $(PY) $(PYTEST_ARGS)'; \
	scripts/test-vcan $(PY) $(PYTEST_ARGS) || vcan=$$?; \
	if [ $$native -ne 0 ] || [ $$live -ne 0 ] || [ $$vcan -ne 0 ]; then \
	    echo "make test: FAILED (pytest exit: $$native native, $$live live tier, $$vcan vcan tier)" >&2; \
	    exit 1; \
	fi

## Only the fast tier (no slow identification runs).
test-fast: $(STAMP)
	$(PY) -m pytest -n 2 -m "not slow and not vcan and not live" $(PYTEST_ARGS)

## Benchmarks (run by hand; figures go into the README).
bench: $(STAMP)
	$(PY) benchmarks/bench_recursive.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
