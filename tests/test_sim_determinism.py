"""The simulated cell is deterministic: the same seed and the same commands give the same campaign, bit for bit,
however loaded the machine (the second run has a CPU hog beside it)."""

from __future__ import annotations

import subprocess
import sys
from contextlib import contextmanager

import numpy as np
import pandas as pd
import pytest

from fakes.cell import SimCellConfig, SimulatedCell
from hil.data.store import P_COLUMNS, Q_COLUMNS, CampaignStore, campaign_dataset
from hil.runner.registry import load
from tests.sim_session import running_cell, session_on

pytestmark = [pytest.mark.sim, pytest.mark.timeout(600)]

COMPARED = [*(f"q{i}_rad" for i in range(1, 7)), "x_mm", "y_mm", "z_mm", "temperature_c", "t_s"]


@contextmanager
def _cpu_hog(on: bool):
    """A busy loop in another process while the block runs (a loaded CI machine)."""
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if on else None
    try:
        yield
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()


def _measure(folder, loaded: bool) -> dict[str, pd.DataFrame]:
    """Registration and a small grid with validation poses on a fresh cell of seed 4; the exported campaign."""
    folder.mkdir()
    campaign = folder / "campaign.sqlite"
    registration, grid_sampling = load("registration"), load("grid_sampling")
    with (
        _cpu_hog(loaded),
        running_cell(folder, seed=4, time_scale=50.0) as (_, config),
        session_on(config, campaign) as session,
    ):
        registration(session)
        grid_sampling(session, step_m=0.3, validation=8, seed=4)
    with CampaignStore(campaign, create=False) as store:
        reg = store.measurements("registration")
        first = store.started_s
        exported = {
            "registration": pd.DataFrame(
                {
                    **{c: reg[c] for c in (*Q_COLUMNS, *P_COLUMNS)},
                    "temperature_c": reg["temperature_c"],
                    "t_s": reg["timestamp_s"] - first,
                }
            ),
            "grid": campaign_dataset(store, "grid_sampling", step="grid")[COMPARED],
            "validation": campaign_dataset(store, "grid_sampling", step="validation")[COMPARED],
        }
    return exported


@pytest.mark.parametrize("hog", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_the_same_seed_gives_the_same_campaign_bit_for_bit_under_load(tmp_path, hog):
    """By default the suite's own parallel workers load the machine differently during the two runs; `make soak`
    adds a CPU hog beside the second (on a 2-core machine it takes a core from every other test for its run)."""
    quiet = _measure(tmp_path / "quiet", loaded=False)
    loaded = _measure(tmp_path / "loaded", loaded=hog)
    for name, frame in quiet.items():
        assert len(frame) > 5, name
        assert frame["t_s"].iloc[-1] > 0, name  # the cell's clock moved on with the work
        pd.testing.assert_frame_equal(frame, loaded[name], check_exact=True, obj=name)


def test_standing_still_draws_no_noise_and_does_not_warm_the_arm():
    cell = SimulatedCell(SimCellConfig(seed=2, thermal=True))
    q = cell.commanded_q
    q[0] += 0.1
    cell.set_commanded_joints(q)
    encoders = cell.encoder_joints()
    cell.advance_timer(3600.0)  # an idle hour on the timer clock
    for _ in range(100):
        assert not cell.set_commanded_joints(q)  # the controller's idle ticks
    np.testing.assert_array_equal(cell.encoder_joints(), encoders)
    assert cell.physics_time_s == 0.0 and cell.structure_temperature_c() == 20.0
    twin = SimulatedCell(SimCellConfig(seed=2, thermal=True))
    twin.set_commanded_joints(q)
    np.testing.assert_array_equal(twin.measure_smr(1), cell.measure_smr(1))  # the first reading of each
    cell.advance_time(600.0)  # an explicit wait warms the arm
    assert cell.structure_temperature_c() > 20.0


def test_a_cell_started_again_continues_the_campaigns_clock(tmp_path):
    """A later stage's (or a resume's) fresh cell restarts its own clock at zero: the session's timestamps continue
    from the campaign's latest measurement by the cell's elapsed time, never from the host's clock."""
    from hil.station.instruments import continuing_clock
    from tests.test_store import make_record as record

    cell_s = [1000.0]  # the new cell's clock (UNIX seconds of its own start plus simulated activity)
    with CampaignStore(tmp_path / "c.sqlite") as store:
        assert (
            continuing_clock(lambda: cell_s[0], store)() > 1e9
        )  # a new campaign: its start is the host's now
        store.record_measurement(record(0, t0=5000.0))
        store.record_measurement(record(1, t0=5000.0))  # latest at 5002 s
        clock = continuing_clock(lambda: cell_s[0], store)
        cell_s[0] += 7.5
        assert clock() == 5002.0 + 7.5
