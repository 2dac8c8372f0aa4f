"""The shared campaign store on a real PostgreSQL server (tests/pg_server.py): the campaign file's contract and
guarantees, a clear refusal of a wrong password, and the crash tests: two cells writing at once, kill -9 in the
middle of recording, the server lost mid-run, resume. No mock of the database."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import psycopg
import pytest
from pg_server import PASSWORD
from pg_writer import record

from hil.data.campaigns import open_campaign
from hil.data.pg_errors import CampaignLoginRefused
from hil.data.pg_schema import HEAD_REVISION, head_revision
from hil.data.pg_store import PgCampaignStore
from hil.data.pg_url import CampaignURLError
from hil.data.store import (
    CampaignError,
    CampaignStore,
    DuplicateMeasurementError,
    OutcomeRecord,
    ResultRecord,
    Verdict,
)
from tests.cli_in_process import run_hil

WRITER = [sys.executable, str(Path(__file__).with_name("pg_writer.py"))]


@pytest.fixture(scope="module")
def database(pg_server) -> str:
    """A fresh database of the test server for this module (no schema yet: the first store migrates it)."""
    return pg_server.create_database("store_tests")


def _fill(store) -> None:
    """The same records, in the same order, whatever the back-end."""
    store.add_snapshot(
        {"cell": {"robot": {"model": "ur10"}}, "station": {"robot_controller_version": "5.11"}}
    )
    for i in range(4):
        store.record_measurement(record("grid", i))
    store.record_measurement(record("validation", 0))
    store.record_event("beam_break", "no target at p2", procedure="grid_sampling", step="grid", point_id="p2")
    store.record_event("resumed", "resumed", data={"skipped": 3})
    store.finish_step("grid_sampling", "grid", {"points": 4})
    store.finish_step("grid_sampling", "grid", {"points": 5})
    store.record_outcome(OutcomeRecord("iso9283", "AP_p", 1e-4, "m", 2e-4, "max", Verdict.PASS, "5 poses"))
    store.record_outcome(OutcomeRecord("iso9283", "RP_l", None, "m", None, "max", Verdict.NOT_JUDGED))
    store.record_result(
        ResultRecord("calibration", {"rms_after_mm": 0.08}, {"robot": "ur10", "params": [1.5]})
    )
    store.record_result(ResultRecord("diagnosis", {"effects_found": []}, None))
    store.log("INFO", "first line")
    store.log("WARNING", "second line")


def _without(df: pd.DataFrame, *columns: str) -> pd.DataFrame:
    return df.drop(columns=[c for c in columns if c in df.columns]).reset_index(drop=True)


def test_a_campaign_in_the_database_reads_back_as_the_file_does(database, tmp_path):
    with CampaignStore(tmp_path / "c.sqlite") as file, PgCampaignStore(database + "?campaign=contract") as pg:
        _fill(file)
        _fill(pg)
        clock = ("id", "recorded_s", "first_recorded_s", "last_recorded_s")
        a, b = file.measurements(), pg.measurements()
        assert list(a.columns) == list(b.columns)
        pd.testing.assert_frame_equal(
            _without(a, *clock).drop(columns=["q_target_rad", "q_rad", "T_base_flange", "p_tracker_m"]),
            _without(b, *clock).drop(columns=["q_target_rad", "q_rad", "T_base_flange", "p_tracker_m"]),
        )
        assert [r.point_id for r in file.records("grid_sampling", "grid")] == ["p0", "p1", "p2", "p3"]
        assert [r.point_id for r in pg.records("grid_sampling", "grid")] == ["p0", "p1", "p2", "p3"]
        np.testing.assert_array_equal(pg.records()[3].p_tracker_m, file.records()[3].p_tracker_m)
        pd.testing.assert_frame_equal(
            _without(file.measurement_columns(["x_m"], step=["validation"]), "id"),
            _without(pg.measurement_columns(["x_m"], step=["validation"]), "id"),
        )
        pd.testing.assert_frame_equal(
            _without(file.point_counts(), *clock), _without(pg.point_counts(), *clock), check_dtype=False
        )
        pd.testing.assert_frame_equal(_without(file.events(), *clock), _without(pg.events(), *clock))
        pd.testing.assert_frame_equal(_without(file.steps(), *clock), _without(pg.steps(), *clock))
        pd.testing.assert_frame_equal(_without(file.log_lines(1), *clock), _without(pg.log_lines(1), *clock))
        assert (
            pg.step_result("grid_sampling", "grid")
            == {"points": 5}
            == file.step_result("grid_sampling", "grid")
        )
        assert pg.step_result("grid_sampling", "validation") is None
        assert pg.outcomes() == file.outcomes()
        assert [replace(r, recorded_s=0.0) for r in pg.results()] == [
            replace(r, recorded_s=0.0) for r in file.results()
        ]
        assert pg.results()[0].model == {"robot": "ur10", "params": [1.5]} and pg.results()[1].model is None
        assert pg.snapshots() == file.snapshots()
        assert pg.started_s == file.started_s and pg.last_timestamp_s == file.last_timestamp_s
        assert pg.last_temperature_c() == file.last_temperature_c() == 20.0
        assert pg.integrity_ok()


def test_a_point_is_recorded_once_and_a_recorded_row_never_changes(database):
    with open_campaign(database + "?campaign=once") as store:
        store.record_measurement(record("grid", 0))
        with pytest.raises(DuplicateMeasurementError, match="already recorded"):
            store.record_measurement(record("grid", 0))
        assert len(store.measurements()) == 1
    with psycopg.connect(database, autocommit=True) as conn:
        for sql in ("UPDATE measurements SET x_m = 0", "DELETE FROM measurements", "DELETE FROM campaigns"):
            with pytest.raises(psycopg.errors.RaiseException, match="append-only"):
                conn.execute(sql)


def test_the_schema_is_alembics_head_and_a_newer_one_is_refused(pg_server, database):
    with PgCampaignStore(database + "?campaign=schema"):
        pass
    with psycopg.connect(database) as conn:
        assert conn.execute("SELECT version_num FROM hil_schema_version").fetchone()[0] == head_revision()
    assert head_revision() == HEAD_REVISION  # the store's quick check knows the newest migration
    newer = pg_server.create_database("newer_schema")
    with PgCampaignStore(newer + "?campaign=a"):
        pass
    with psycopg.connect(newer, autocommit=True) as conn:
        conn.execute("UPDATE hil_schema_version SET version_num = 'from_a_newer_hil'")
    with pytest.raises(CampaignError, match="upgrade hil"):
        PgCampaignStore(newer + "?campaign=a")


def test_a_campaign_is_opened_by_its_label_or_its_uuid_and_never_made_up(database):
    with PgCampaignStore(database + "?campaign=by-label") as store:
        made = store.uuid
    with PgCampaignStore(database + f"?campaign={made}", create=False) as store:
        assert store.label == "by-label"
    with pytest.raises(CampaignError, match="no campaign 'missing'"):
        PgCampaignStore(database + "?campaign=missing", create=False)
    with pytest.raises(CampaignURLError, match="name the campaign"):
        PgCampaignStore(database)


def test_a_wrong_password_is_a_clear_refusal_and_no_password_is_ever_shown(
    pg_server, database, monkeypatch, tmp_path, capsys
):
    monkeypatch.setenv("PGPASSWORD", "not-the-password")
    with pytest.raises(CampaignLoginRefused, match="refused the login") as refused:
        PgCampaignStore(database + "?campaign=contract")
    assert "not-the-password" not in str(refused.value)
    with pytest.raises(CampaignURLError, match="password in a campaign URL is refused") as in_url:
        PgCampaignStore(database.replace("hil@", f"hil:{PASSWORD}@") + "?campaign=contract")
    assert PASSWORD not in str(in_url.value)
    done = run_hil(  # PGPASSWORD is still the wrong one
        "calibrate", database + "?campaign=contract", "--robot", "ur10", "-o", "m.json", cwd=tmp_path, capsys=capsys
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "refused the login" in done.stderr and "PGPASSWORD" in done.stderr
    assert "not-the-password" not in done.stderr


def test_a_password_file_named_by_the_cell_config_logs_in(database, tmp_path, monkeypatch):
    with PgCampaignStore(database + "?campaign=by-password-file") as store:
        store.record_measurement(record("grid", 0))
    monkeypatch.delenv("PGPASSWORD")
    secret = tmp_path / "db.password"
    secret.write_text(PASSWORD + "\n")
    with open_campaign(database + "?campaign=by-password-file", password_file=secret) as store:
        assert len(store.measurements()) == 1
    with pytest.raises(CampaignLoginRefused):
        PgCampaignStore(database + "?campaign=by-password-file")  # neither PGPASSWORD nor a file: refused


def _writer(url: str, step: str, n: int, *options: str) -> subprocess.Popen:
    return subprocess.Popen(
        [*WRITER, url, step, str(n), *options],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _wait_for_points(writer: subprocess.Popen, count: int) -> None:
    """Read the writer's progress until it has committed `count` points (each line: one committed point)."""
    assert writer.stdout is not None
    for _ in range(count):
        line = writer.stdout.readline()
        assert line, (
            f"the writer stopped early: {writer.wait()} {writer.stderr.read() if writer.stderr else ''}"
        )


def _assert_complete(url: str, step: str, n: int) -> pd.DataFrame:
    """Every point once, each row holding its own values."""
    with PgCampaignStore(url, create=False) as store:
        m = store.measurements("grid_sampling", step)
    assert len(m) == n
    assert sorted(m["point_id"]) == sorted(f"p{i}" for i in range(n))
    index = m["point_id"].str.removeprefix("p").astype(int).to_numpy()
    np.testing.assert_array_equal(m["x_m"].to_numpy(), index)
    assert set(m["y_m"]) == {sum(map(ord, step))}
    return m


def test_two_cells_write_at_once_without_blocking_or_mixing(pg_server):
    fresh = pg_server.create_database("two_cells")  # both writers migrate a fresh database at once
    n = 400
    writers = {c: _writer(f"{fresh}?campaign={c}", f"grid-{c}", n, "--on-go") for c in ("cell-a", "cell-b")}
    for w in writers.values():
        assert w.stdout is not None and w.stdout.readline() == "ready\n", w.stderr.read() if w.stderr else ""
    for w in writers.values():  # both opened (and migrated) the database: now both record at once
        assert w.stdin is not None
        w.stdin.write("go\n")
        w.stdin.flush()
    outputs = {cell: w.communicate(timeout=90) for cell, w in writers.items()}
    for cell, w in writers.items():
        assert w.returncode == 0, outputs[cell][1]
    frames = {cell: _assert_complete(f"{fresh}?campaign={cell}", f"grid-{cell}", n) for cell in writers}
    a, b = (frames[c]["recorded_s"] for c in ("cell-a", "cell-b"))
    assert max(a.min(), b.min()) < min(a.max(), b.max())  # they did write at the same time
    slowest = [float(outputs[c][0].split()[-1]) for c in writers]
    assert max(slowest) < 2.0, slowest  # no insert waited on the other cell


def test_kill_9_while_recording_loses_and_duplicates_nothing(database):
    url, n = database + "?campaign=killed", 300
    for kill_after in (40, 60):
        writer = _writer(url, "grid", n)
        _wait_for_points(writer, kill_after)
        writer.send_signal(signal.SIGKILL)  # mid-loop: most likely between sending a point and its commit
        writer.wait()
    with PgCampaignStore(url, create=False) as store:
        assert len(store.measurements()) >= 40 + 60
    done = _writer(url, "grid", n)
    out, err = done.communicate(timeout=60)
    assert done.returncode == 0, err
    _assert_complete(url, "grid", n)


def test_a_server_lost_mid_run_stops_the_writer_and_the_run_resumes_when_it_is_back(pg_server, database):
    url, n = database + "?campaign=lost-server", 300
    writer = _writer(url, "grid", n)
    _wait_for_points(writer, 50)
    try:
        pg_server.lose()
        out, err = writer.communicate(timeout=60)
        assert writer.returncode == 3, err
        assert "did not answer" in err and "everything recorded before is kept" in err
        committed = 50 + len(out.split())  # the points it said were committed
    finally:
        pg_server.start()
    with PgCampaignStore(url, create=False) as store:
        assert len(store.measurements()) >= committed  # none lost
    resumed = _writer(url, "grid", n)
    out, err = resumed.communicate(timeout=60)
    assert resumed.returncode == 0, err
    assert len(out.split()) - 2 <= n - committed  # only what was missing was measured again
    _assert_complete(url, "grid", n)


def test_a_campaign_is_keyed_by_its_robot_controller_tracker_cell_operator_dates_and_temperatures(database):
    station = {
        "robot_controller_version": "5.11.1.0", "robot_serial_number": "20235500123", "robot_model_reported": "UR10",
        "tracker": {"name": "AT901", "serial_number": 390123, "software_version": "3.8.712"},
        "cell_name": "cell-7", "operator_name": "A. Engineer",
    }  # fmt: skip
    with PgCampaignStore(database + "?campaign=keyed") as store:
        store.add_snapshot(
            {"robot_definition": {"model": "ur10"}, "station": {"robot_controller_version": "5.9"}}
        )
        store.add_snapshot(
            {"robot_definition": {"model": "ur10"}, "station": station}
        )  # the latest one counts
        for i in range(3):
            store.record_measurement(replace(record("grid", i), temperature_c=20.0 + i))
    with psycopg.connect(database) as conn:
        cur = conn.execute("SELECT * FROM campaign_keys WHERE label = 'keyed'")
        keys = dict(zip([d.name for d in cur.description or ()], cur.fetchone() or (), strict=True))
    assert keys["robot_model"] == "UR10" and keys["robot_serial"] == "20235500123"
    assert keys["controller_version"] == "5.11.1.0"
    assert (keys["tracker_name"], keys["tracker_serial"], keys["tracker_software"]) == (
        "AT901",
        "390123",
        "3.8.712",
    )
    assert (keys["cell_name"], keys["operator_name"]) == ("cell-7", "A. Engineer")
    assert keys["points"] == 3 and (keys["first_s"], keys["last_s"]) == (1.7e9, 1.7e9 + 2)
    assert (keys["temperature_min_c"], keys["temperature_max_c"]) == (20.0, 22.0)


def _push(capsys, *args: str) -> SimpleNamespace:
    """`hil campaign push ARGS` in this process (what it prints and its exit code, as the command line gives
    them)."""
    return run_hil("campaign", "push", *args, cwd=".", capsys=capsys)


def test_push_copies_a_file_campaign_by_its_uuid_and_pushing_again_adds_nothing(database, tmp_path, capsys):
    path = tmp_path / "cell9-offline.sqlite"
    with CampaignStore(path) as file:
        _fill(file)
        identity = file.uuid
    first = _push(capsys, str(path), database)
    assert first.returncode == 0, first.stderr
    assert f"campaign {identity}" in first.stdout and "added 1 snapshots, 5 measurements" in first.stdout
    again = _push(capsys, str(path), database)
    assert again.returncode == 0 and "nothing new to add" in again.stdout, again.stdout + again.stderr
    with CampaignStore(path) as file, PgCampaignStore(database + f"?campaign={identity}", create=False) as pg:
        assert pg.label == "cell9-offline" and pg.created_s == file.created_s
        clock = ("id", "recorded_s")
        pd.testing.assert_frame_equal(
            _without(file.measurements(), *clock), _without(pg.measurements(), *clock)
        )
        assert [len(t()) for t in (pg.events, pg.steps, pg.log_lines)] == [2, 2, 2]
        assert pg.outcomes() == file.outcomes() and pg.results() == file.results()
        file.record_measurement(record("grid", 7))  # the cell measured on after its first push
        file.record_event("resumed", "one more point")
    grown = _push(capsys, str(path), database)
    assert grown.returncode == 0 and "added 1 measurements, 1 events" in grown.stdout, (
        grown.stdout + grown.stderr
    )
    with PgCampaignStore(database + f"?campaign={identity}", create=False) as pg:
        assert len(pg.measurements()) == 6 and len(pg.events()) == 3


def test_push_refuses_a_label_another_campaign_holds(database, tmp_path, capsys):
    with PgCampaignStore(database + "?campaign=taken-label"):
        pass
    path = tmp_path / "other.sqlite"
    with CampaignStore(path) as file:
        file.add_snapshot({"cell": {}})
    taken = _push(capsys, str(path), database + "?campaign=taken-label")
    assert taken.returncode == 2 and "is taken by another campaign" in taken.stderr, taken.stderr
    assert "Traceback" not in taken.stderr


def test_cells_opening_a_fresh_database_at_once_migrate_it_once(pg_server):
    fresh = pg_server.create_database("migrated_at_once")
    with ThreadPoolExecutor(4) as pool:  # each opening runs the upgrade in its own transaction, lock first
        labels = list(pool.map(lambda i: PgCampaignStore(f"{fresh}?campaign=c{i}").label, range(4)))
    assert labels == ["c0", "c1", "c2", "c3"]
    with psycopg.connect(fresh) as conn:
        assert conn.execute("SELECT version_num FROM hil_schema_version").fetchall() == [(HEAD_REVISION,)]


HOLD_LOCK = """
import sys
from hil.data.campaign_lock import Holder
from hil.data.pg_campaign_lock import PgCampaignLock
lock = PgCampaignLock(sys.argv[1], Holder.this_process("hil run grid_sampling"))
lock.acquire()
print("held", flush=True)
sys.stdin.read()
"""


def test_one_driver_per_shared_campaign_named_when_refused_and_freed_when_its_process_dies(database):
    """A shared campaign has one driver, as a campaign file has: a second is refused with who holds it (its
    connection's name, from the server's own view of its locks), and a holder killed with SIGKILL leaves no
    stale lock (the server drops its connection). Another campaign in the same database is not held."""
    from hil.data.campaign_lock import CampaignBusyError, Holder
    from hil.data.pg_campaign_lock import PgCampaignLock

    url = database + "?campaign=one-driver"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, url], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(
            CampaignBusyError, match=rf"driven by hil run grid_sampling, process {holder.pid} on"
        ):
            PgCampaignLock(url, Holder.this_process("hil serve")).acquire()
        with PgCampaignLock(database + "?campaign=another", Holder.this_process("hil serve")):
            pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    deadline = time.monotonic() + 30  # the server sees the connection close; wait on that, not a fixed time
    while True:
        try:
            with PgCampaignLock(url, Holder.this_process("hil serve")):
                break
        except CampaignBusyError:
            assert time.monotonic() < deadline, "the killed holder's lock was never released"
            time.sleep(0.05)


def test_a_loop_without_a_model_plans_from_a_shared_campaigns_registration(database):
    """A procedure that reads its campaign while planning (the pseudo-target loop without --model) reads a
    shared one as it reads a file: the registration and tool fit the campaign holds place the nominal model."""
    import tomllib

    from hil.geometry.se3 import make_transform
    from hil.runner.cell_config import parse_cell_config
    from procedures.pseudo_target import _campaign_model
    from tests.cell_fixtures import sim_cell_toml

    config = parse_cell_config(tomllib.loads(sim_cell_toml()))
    url = database + "?campaign=planned-from-registration"
    T_tracker_base = make_transform(np.eye(3), [2.0, 0.5, -0.3])
    with PgCampaignStore(url) as store:
        store.finish_step("registration", "fit", {"T_tracker_base": T_tracker_base.tolist()})
        store.finish_step("tool_fit", "fit", {"nests_flange_mm": {"1": [10.0, 20.0, 110.0]}})
    model = _campaign_model(config, url)
    np.testing.assert_allclose(model.T_tracker_base, T_tracker_base)
    with pytest.raises(ValueError, match="give --campaign with a registration"):
        _campaign_model(config, database + "?campaign=nothing-recorded-here")


def test_compensate_reads_the_targets_of_a_shared_campaign_as_of_a_file(database, tmp_path):
    """`hil compensate MODEL URL --step validation`: the validation targets of a campaign in the shared store
    (its robot, registration and tool fit recorded there), each reached by the model."""
    from calib_data import cell_datasets, record_validated_campaign, true_effect_model

    from hil.cli import main

    _, train, val = cell_datasets(step_m=0.2, n_val=4, seed=0)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    model.save(tmp_path / "model.json")
    url = database + "?campaign=targets-for-compensation"
    with PgCampaignStore(url) as store:
        record_validated_campaign(store, model, val)
    out = tmp_path / "compensated.csv"
    assert (
        main(["compensate", str(tmp_path / "model.json"), url, "--step", "validation", "-o", str(out)]) == 0
    )
    written = pd.read_csv(out)
    assert list(written["point_id"]) == [f"v{i}" for i in range(len(val))]
    assert (written["status"] == "ok").all() and written["error_mm"].max() < 0.01


def test_campaign_show_and_export_read_a_shared_campaign_as_a_file(database, tmp_path, capsys):
    """`hil campaign show URL` and `hil campaign export URL --csv OUT`: what the file's commands print and
    write, read from the shared store (no password on screen)."""
    from hil.cli import main

    url = database + "?campaign=shown-and-exported"
    with PgCampaignStore(url) as store:
        _fill(store)
    assert main(["campaign", "show", url]) == 0
    shown = capsys.readouterr().out
    assert "5 measurements" in shown and PASSWORD not in shown
    out = tmp_path / "grid.csv"
    assert (
        main(["campaign", "export", url, "--procedure", "grid_sampling", "--step", "grid", "--csv", str(out)])
        == 0
    )
    assert len(pd.read_csv(out)) == 4
