"""`hil run` on the simulated cell with its campaign in the shared PostgreSQL store: the server lost mid-grid
stops the run with what to do (the robot stopped, nothing recorded lost), the same command resumes once the
server is back, every planned point is recorded once, and `hil calibrate` reads the campaign from the store (the
grid is kept coarse for time: calibrate counts its rows and refuses so few, which is its rule)."""

from __future__ import annotations

import subprocess
import sys
import time

import psycopg
import pytest

from hil.data.pg_store import PgCampaignStore
from procedures import grid_sampling
from tests.sim_session import running_cell

pytestmark = [pytest.mark.sim]

GRID = ("--step-mm", "300", "--validation", "3")


def _hil(*args: str) -> list[str]:
    return [sys.executable, "-m", "hil", *args]


def _points(url: str) -> int:
    with PgCampaignStore(url, create=False) as store:
        return len(store.measurement_columns(["point_id"], "grid_sampling"))


@pytest.mark.timeout(300)
def test_a_run_into_the_shared_store_stops_when_the_server_is_lost_and_resumes(pg_server, tmp_path):
    url = pg_server.create_database("runs") + "?campaign=cell7-grid"
    with running_cell(tmp_path, time_scale=50.0, seed=6) as (_cell, config):
        cell_toml = str(tmp_path / "cell.toml")
        done = subprocess.run(
            _hil("run", "registration", "--cell", cell_toml, "--campaign", url),
            capture_output=True, text=True, timeout=120, cwd=tmp_path,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        grid = _hil("run", "grid_sampling", "--cell", cell_toml, "--campaign", url, *GRID)
        run = subprocess.Popen(grid, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
        try:
            deadline = time.monotonic() + 120
            while _points(url) < 5:  # the state to wait for: five grid points committed
                assert run.poll() is None, run.communicate()
                assert time.monotonic() < deadline, "the grid did not start"
                time.sleep(0.05)
            pg_server.lose()
            out, err = run.communicate(timeout=60)
        finally:
            pg_server.start()
        assert run.returncode == 2, err
        assert "Traceback" not in err and "did not answer" in err and "what to do:" in err, err
        assert "run the same command again" in err
        kept = _points(url)
        assert kept >= 5
        resumed = subprocess.run(grid, capture_output=True, text=True, timeout=240, cwd=tmp_path)
        assert resumed.returncode == 0, resumed.stderr
    plan = grid_sampling.PROCEDURE.make_plan(config, step_m=0.3, validation=3)
    with PgCampaignStore(url, create=False) as store:
        rows = store.measurements("grid_sampling")
    with psycopg.connect(pg_server.url("runs")) as conn:  # the campaign's keys, as the drivers read them
        cur = conn.execute(
            "SELECT robot_serial, robot_model, tracker_serial, tracker_software FROM campaign_keys"
        )
        # the simulated CB3 arm has no serial number to give (PolyScope 5.6 and later do): none is made up
        assert cur.fetchall() == [(None, "UR10", "390123", "3.8.712")]
    recorded = list(zip(rows["step"], rows["point_id"], strict=True))
    assert len(recorded) == len(set(recorded)) and set(recorded) == {(p.step, p.point_id) for p in plan.poses}
    calibrated = subprocess.run(
        _hil("calibrate", url, "--robot", "ur10", "-o", "model.json"),
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    # calibrate read the campaign from the store: every recorded row, and a grid this coarse is refused
    assert f"{len(recorded)} rows at {len(recorded)} distinct poses" in calibrated.stderr, calibrated.stderr
    assert calibrated.returncode == 2 and "Traceback" not in calibrated.stderr
