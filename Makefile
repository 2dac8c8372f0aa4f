# Entry points: `make demo` (main job on the simulated cell), `make test` (ruff + import layers + the strict docs
# build + mypy + pytest, the check of every change), `make docs` (the documentation site in site/) and
# `make soak` (the long soaks marked `slow`, for a nightly run).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# pytest-xdist: six workers, each test module on one worker (its module-scoped fixtures, a simulated cell or
# a campaign, are built once), a module with sim tests and one without in turn (tests/conftest.py). Six on two cores: the
# sim tests spend much of their time waiting for the simulated cell, and more workers than cores overlap those
# waits; but every connected cell and driver also costs CPU for as long as it waits, so eight cost more than
# they overlap. Measured on a 2-core machine, the whole suite of 1304 tests, one run each, caches warm:
# four workers 250 s (388 CPU-s), six 230 s (421 CPU-s), eight 259 s (485 CPU-s).
# PYTEST_PARALLEL= runs the suite in one process.
PYTEST_PARALLEL ?= -n 6 --dist loadfile --no-loadscope-reorder
# One BLAS thread per test process: six workers (and their cells and commands) already share two cores, and
# OpenBLAS's own pool on the suite's small matrices only added work (the diagnosis tests: 28.3 -> 23.9 CPU-s).
ONE_BLAS_THREAD := OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1

.PHONY: demo test lint docs typecheck prime unit soak bench clean

# uv installs the project and its dev tools (pip brings it in from PyPI, so plain Python 3.11 is all a machine
# needs): 9 s on a fresh clone against pip's 23 s. The venv is made without pip and the machine's own pip puts uv
# in it (pip 22.3 and later: --python), 2.0 s where ensurepip's copy of pip and then uv took 5.3 s at the head
# of every fresh check; a Python without a pip of its own falls back to ensurepip. uv adds pip to the venv for
# whoever wants .venv/bin/pip. Not byte-compiled here: compiling all 10 400 modules of the dependencies took
# 14 s of a 2-core machine (24 CPU-s) for the fraction any process imports; `prime` compiles what the tests
# import, once.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv --without-pip $(VENV)
	$(PYTHON) -m pip --python $(PY) install --quiet uv 2>/dev/null || \
		{ $(PY) -m ensurepip --default-pip >/dev/null && $(PY) -m pip install --quiet uv; }
	$(VENV)/bin/uv pip install --quiet --python $(PY) -e '.[dev]' pip
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/hil demo

# Every part of the check starts as soon as what it needs is there: the system programs' install
# (tools/system-deps: apt, on a fresh machine headless Chromium and 18 libraries, 7.1 s of a 2-core machine with
# the packages already downloaded) beside the venv's, not after it; then ruff and the import layers, the docs
# build, mypy and the tests' bytecode side by side; pytest once the bytecode and the system programs are
# there. A failing ruff or layer check (0.6 s) stops make before pytest starts.
test:
	$(MAKE) --no-print-directory -j6 lint docs typecheck unit

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/lint-imports

# The documentation site (docs/, mkdocs.yml) into site/. Strict: a broken link or anchor, or a page missing from
# the nav, fails the build. The CLI reference and the procedures' parameter tables are generated from the code
# at build time (tools/docs_reference.py). A few seconds. Not --quiet: it hides the warnings that strict counts.
docs: $(VENV)/.installed
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

# mypy beside pytest, at a lower priority: a cold mypy (a fresh clone has no .mypy_cache) takes 21-23 CPU-s,
# and the pytest workers leave part of a core idle while the simulated cells run in scaled wall-clock time
# (65-120 s into a fresh run on a 2-core machine, 19 core-s in all); niced, mypy runs in those gaps instead of
# holding back the tests' start.
typecheck: $(VENV)/.installed
	nice -n 10 $(VENV)/bin/mypy

# The server and the browser some tests drive for real (PostgreSQL, Chromium), installed from the distribution's
# packages where missing (tools/system-deps): part of the set-up, never assumed by a test.
$(VENV)/.system-deps: tools/system-deps
	tools/system-deps
	mkdir -p $(VENV)
	touch $@

# Bytecode first, once: the project's modules compiled, and one collection that imports what the tests import
# (numpy, scipy, pandas, ...) and caches the tests' assertion-rewritten modules, so the pytest workers read them
# instead of each compiling the same files at the same moment. The suite itself also writes bytecode: a module
# first imported by a test, a `python -m hil` or a simulated cell is compiled once, not by every process
# (PYTHONDONTWRITEBYTECODE, set on some machines, would stop every process from writing). Measured on a 2-core
# machine: a collection takes 7.3-7.7 CPU-s with nothing cached and 2.9-3.0 s with the cache.
prime: $(VENV)/.installed
	PYTHONDONTWRITEBYTECODE= $(PY) -m compileall -q -j 2 hil fakes drivers procedures tests benchmarks docs/examples
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -q --collect-only -p no:cacheprovider > /dev/null

unit: prime $(VENV)/.system-deps
	PYTHONDONTWRITEBYTECODE= $(ONE_BLAS_THREAD) $(PY) -m pytest -q --durations=15 $(PYTEST_PARALLEL)

# The long soaks (20 SIGKILLs of a campaign, a whole demo resumed): minutes; the default suite runs a short
# version of each.
soak: $(VENV)/.installed
	$(PY) -m pytest -q -m slow $(PYTEST_PARALLEL)

bench: $(VENV)/.installed
	$(PY) benchmarks/kinematics.py
	$(PY) benchmarks/compensation.py
	$(PY) benchmarks/calibration.py
	$(PY) benchmarks/tracker.py
	$(PY) benchmarks/ur_fake.py
	$(PY) benchmarks/runner.py
	$(PY) benchmarks/probe.py

clean:
	rm -rf $(VENV) site
