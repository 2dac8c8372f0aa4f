"""Suite-wide setup: subprocesses started by tests (`python -m hil ...`) import this checkout; hypothesis
profiles (`ci` when the CI variable is set, as CI sets it to `true`; `dev` otherwise; HYPOTHESIS_PROFILE
overrides)."""

import gc
import os
from pathlib import Path

import pytest
from hypothesis import settings

REPO_ROOT = str(Path(__file__).resolve().parents[1])
os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (REPO_ROOT, os.environ.get("PYTHONPATH")) if p)

# Tests that talk to a fake server over sockets set their own example counts and no deadline (a busy CI
# machine is slow). `ci`: the same examples on every run (a red build is reproducible from its log) and no
# example database on a fresh clone; `dev`: fresh examples each run, failures remembered in .hypothesis/.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True, deadline=None)
settings.register_profile("dev", deadline=None)
_ci = os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if _ci else "dev"))


@pytest.fixture(scope="session")
def gravity_cell_diagnosis():
    """The simulated UR10 cell's default campaign (seed 2: geometric errors plus gravity compliance) and its
    diagnosis against the validation set, built once per test process. Shared: read it, do not change it
    (copy the frames first)."""
    from calib_data import cell_datasets

    from hil.analysis.diagnosis.pipeline import run_diagnosis

    cell, train, val = cell_datasets(seed=2)
    return cell, train, val, run_diagnosis(train, "ur10", df_validate=val)


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (`make test`: --dist loadfile --no-loadscope-reorder) the modules are handed out in
    this order: a module with `sim` tests (the long wall-clock ones: a demo, campaigns on the simulated cell),
    then one without, in turn. The sim modules start early, so none of them starts last while the other
    workers idle, and the cores their cells leave idle while the workers wait on them run the other modules:
    all sim modules first kept every worker waiting on a cell for the first minute (1.1-1.8 of 2 cores busy;
    on a 2-core machine, the suite took 160.0 and 161.4 s that way, 147.2 and 147.7 s in turn). A module's
    tests stay together and in file order; a run in one process keeps the file order."""
    if not hasattr(config, "workerinput"):
        return
    sim_modules = {item.path for item in items if item.get_closest_marker("sim")}
    modules = list(dict.fromkeys(item.path for item in items))
    sim = [m for m in modules if m in sim_modules]
    other = [m for m in modules if m not in sim_modules]
    order: list = []
    while sim or other:
        order += sim[:1] + other[:1]
        sim, other = sim[1:], other[1:]
    rank = {m: k for k, m in enumerate(order)}
    items.sort(key=lambda item: rank[item.path])  # stable: a module's tests in file order


def pytest_collection_finish(session):
    """The collected process's objects (the imported numpy, scipy, pandas, the test modules) live to the end:
    frozen, the collector stops walking them in every full collection, and it runs a young-generation pass
    a tenth as often (what the tests leave is still collected, in bigger batches). The collector's time in
    the six workers of the non-sim tests, timed with gc.callbacks: 6.8 CPU-s before, 4.9 so."""
    gc.collect()
    gc.freeze()
    young, middle, old = gc.get_threshold()
    gc.set_threshold(10 * young, middle, old)


@pytest.fixture(scope="session")
def pg_server():
    """A real PostgreSQL server (tests/pg_server.py), started once per test process by the first test that asks
    for it and stopped at the end; its password is in PGPASSWORD, as a cell's environment would give it."""
    from pg_server import PASSWORD, PgServer

    server = PgServer()
    try:
        server.start()
        os.environ["PGPASSWORD"] = PASSWORD
        yield server
    finally:
        os.environ.pop("PGPASSWORD", None)
        server.remove()
