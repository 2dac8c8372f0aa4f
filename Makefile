# Two entry points: `make demo` (main job on the simulated cell) and `make test` (ruff + import layers + mypy + pytest).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: demo test lint bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/hil demo

test: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy
	$(PY) -m pytest -q

bench: $(VENV)/.installed
	$(PY) benchmarks/kinematics.py
	$(PY) benchmarks/compensation.py
	$(PY) benchmarks/calibration.py
	$(PY) benchmarks/tracker.py
	$(PY) benchmarks/ur_fake.py
	$(PY) benchmarks/runner.py
	$(PY) benchmarks/probe.py

clean:
	rm -rf $(VENV)
