"""The campaign store: round trip, resume, duplicates, events/steps/snapshots/log, export, SIGKILL safety."""

import logging
import random
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from hil.data.dataset import load_dataset
from hil.data.store import (
    CampaignError,
    CampaignStore,
    DuplicateMeasurementError,
    MeasurementRecord,
    StoreLogHandler,
    campaign_dataset,
    export_csv,
    export_parquet,
    is_campaign_file,
    load_campaign,
)

REPO_ROOT = Path(__file__).resolve().parents[1]


def make_record(
    i: int, procedure="grid_sampling", step="grid", rng=None, t0=1.7e9, **over
) -> MeasurementRecord:
    rng = rng or np.random.default_rng(i)
    T = np.eye(4)
    T[:3, 3] = rng.normal(size=3)
    fields = dict(
        procedure=procedure,
        step=step,
        point_id=f"p{i:04d}",
        q_target_rad=rng.uniform(-3, 3, 6),
        q_rad=rng.uniform(-3, 3, 6),
        T_base_flange=T,
        p_tracker_m=rng.normal(size=3),
        spread_m=rng.uniform(0, 1e-5, 3),
        std_m=rng.uniform(0, 1e-5, 3),
        shots=10,
        rejected_shots=(2, 7) if i % 2 else (),
        smr=1 + i % 3,
        location=f"nest{1 + i % 3}",
        temperature_c=20.0 + 0.01 * i,
        pressure_hpa=1013.25,
        humidity_pct=40.0 + i % 5,
        timestamp_s=t0 + 2.0 * i,
        extra={"attempts": 1 + i % 2, "predicted_m": rng.normal(size=3)},
    )
    fields.update(over)
    return MeasurementRecord(**fields)


def assert_same(a: MeasurementRecord, b: MeasurementRecord) -> None:
    for name in ("q_target_rad", "q_rad", "T_base_flange", "p_tracker_m", "spread_m", "std_m"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in (
        "procedure",
        "step",
        "point_id",
        "shots",
        "rejected_shots",
        "smr",
        "location",
        "timestamp_s",
    ):
        assert getattr(a, name) == getattr(b, name), name
    for name in ("temperature_c", "pressure_hpa", "humidity_pct"):
        assert getattr(a, name) == getattr(b, name) or (
            np.isnan(getattr(a, name)) and np.isnan(getattr(b, name))
        )
    assert a.extra.keys() == b.extra.keys()
    np.testing.assert_array_equal(np.asarray(a.extra["predicted_m"]), np.asarray(b.extra["predicted_m"]))


def test_round_trip_is_bit_exact_and_survives_reopen(tmp_path):
    path = tmp_path / "c.hilc"
    recs = [make_record(i) for i in range(30)] + [make_record(i, step="validation") for i in range(5)]
    recs[3] = make_record(3, humidity_pct=float("nan"))  # a missing sensor reading stays missing
    with CampaignStore(path) as store:
        ids = [store.record_measurement(r) for r in recs]
        assert ids == sorted(ids) and len(set(ids)) == len(ids)
    assert is_campaign_file(path)
    with CampaignStore(path) as store:
        back = store.records()
        assert len(back) == len(recs)
        for a, b in zip(recs, back, strict=True):
            assert_same(a, b)
        assert len(store.measurements(step="validation")) == 5
        assert len(store.measurements("grid_sampling", "grid")) == 30
        assert store.measurements("registration").empty
        assert store.started_s == recs[0].timestamp_s
    df = load_campaign(path, "grid_sampling", "grid")
    # the record's arrays as columns too (flat REAL columns stay alongside: q1_rad.., x_m..)
    np.testing.assert_array_equal(np.stack(df["T_base_flange"]), [r.T_base_flange for r in recs[:30]])
    np.testing.assert_array_equal(np.stack(df["q_rad"]), df[[f"q{j}_rad" for j in range(1, 7)]].to_numpy())
    np.testing.assert_array_equal(np.stack(df["p_tracker_m"])[:, 2], df["z_m"])
    assert load_campaign(path, "tool_fit")["q_rad"].tolist() == []
    assert list(df["point_id"]) == [r.point_id for r in recs[:30]]
    assert np.isnan(df["humidity_pct"].iloc[3])


def test_record_validation_says_what_is_wrong():
    with pytest.raises(ValueError, match=r"q_rad: expected shape \(6,\)"):
        make_record(0, q_rad=np.zeros(5))
    with pytest.raises(ValueError, match="T_base_flange"):
        make_record(0, T_base_flange=np.eye(3))
    with pytest.raises(ValueError, match="p_tracker_m: holds NaN"):
        make_record(0, p_tracker_m=[0.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="point_id"):
        make_record(0, point_id="")


def test_duplicate_refused_and_resume_skips_recorded_points(tmp_path):
    path = tmp_path / "c.hilc"
    with CampaignStore(path) as store:
        for i in range(4):
            store.record_measurement(make_record(i))
        with pytest.raises(DuplicateMeasurementError, match="already recorded"):
            store.record_measurement(make_record(2))
        store.record_measurement(make_record(2, step="validation"))  # same id, other step: a different point
    # "resume": a new session on the same file measures only what is missing
    with CampaignStore(path) as store:
        todo = [i for i in range(8) if not store.has_measurement("grid_sampling", "grid", f"p{i:04d}")]
        assert todo == [4, 5, 6, 7]
        with pytest.raises(DuplicateMeasurementError):
            store.record_measurement(make_record(0))
        for i in todo:
            store.record_measurement(make_record(i))
        df = store.measurements("grid_sampling", "grid")
    assert list(df["point_id"]) == [f"p{i:04d}" for i in range(8)]
    assert not df.duplicated(["procedure", "step", "point_id"]).any()


def test_snapshots_events_steps_and_log(tmp_path):
    path = tmp_path / "c.hilc"
    with CampaignStore(path) as store:
        store.add_snapshot({"robot": {"model": "ur10", "serial": "X1"}, "tracker": {"model": "AT960"}})
        assert store.step_result("grid_sampling", "grid") is None
        store.record_event(
            "fault",
            "protective stop",
            procedure="grid_sampling",
            step="grid",
            point_id="p0003",
            data={"attempt": 1, "q_rad": np.zeros(6)},
        )
        store.record_event("resume", "session resumed")
        store.finish_step("grid_sampling", "grid", {"points": 324, "rms_m": np.float64(1e-4)})
        store.log("INFO", "first line")
    with CampaignStore(path) as store:
        store.add_snapshot({"robot": {"model": "ur10", "serial": "X2"}})
        assert [s["robot"]["serial"] for s in store.snapshots()] == ["X1", "X2"]
        ev = store.events()
        assert list(ev["kind"]) == ["fault", "resume"]
        assert ev["data"].iloc[0] == {"attempt": 1, "q_rad": [0.0] * 6}
        assert ev["point_id"].iloc[0] == "p0003" and ev["point_id"].iloc[1] is None
        assert store.step_result("grid_sampling", "grid") == {"points": 324, "rms_m": 1e-4}
        store.finish_step("grid_sampling", "grid", {"points": 325})  # a newer result wins, the old one stays
        assert store.step_result("grid_sampling", "grid") == {"points": 325}
        assert len(store.steps()) == 2
        logger = logging.getLogger("hil.test_store")
        logger.setLevel(logging.INFO)
        handler = StoreLogHandler(store)
        logger.addHandler(handler)
        try:
            logger.info("measured %d points", 5)
            logger.debug("not kept at INFO")
        finally:
            logger.removeHandler(handler)
        lines = store.log_lines()
        assert list(lines["message"]) == ["first line", "measured 5 points"]
        assert lines["logger"].iloc[1] == "hil.test_store"
        assert list(store.log_lines(last=1)["message"]) == ["measured 5 points"]
    with pytest.raises(ValueError, match="not JSON-able"):
        CampaignStore(path).record_event("x", "y", data={"obj": object()})


def test_store_is_append_only_at_the_sql_level(tmp_path):
    path = tmp_path / "c.hilc"
    with CampaignStore(path) as store:
        store.record_measurement(make_record(0))
    conn = sqlite3.connect(path)
    try:
        with pytest.raises(sqlite3.DatabaseError, match="append-only"):
            conn.execute("UPDATE measurements SET x_m = 0")
        with pytest.raises(sqlite3.DatabaseError, match="append-only"):
            conn.execute("DELETE FROM measurements")
    finally:
        conn.close()
    assert len(load_campaign(path)) == 1


def test_foreign_files_and_newer_schema_refused(tmp_path):
    text = tmp_path / "data.csv"
    text.write_text("q1_rad,x_mm\n0,1\n")
    with pytest.raises(CampaignError, match="not a hil campaign"):
        CampaignStore(text)
    other = tmp_path / "other.sqlite"
    sqlite3.connect(other).execute("CREATE TABLE t (x)").connection.close()
    assert (
        not is_campaign_file(other) and not is_campaign_file(text) and not is_campaign_file(tmp_path / "none")
    )
    with pytest.raises(CampaignError, match="not a hil campaign"):
        CampaignStore(other)
    with pytest.raises(CampaignError, match="not found"):
        CampaignStore(tmp_path / "missing.hilc", create=False)
    with pytest.raises(CampaignError, match="does not exist"):
        CampaignStore(tmp_path / "no_dir" / "c.hilc")
    newer = tmp_path / "newer.hilc"
    CampaignStore(newer).close()
    conn = sqlite3.connect(newer)
    conn.execute("PRAGMA user_version=99")
    conn.close()
    with pytest.raises(CampaignError, match="schema version 99.*upgrade hil"):
        CampaignStore(newer)
    empty = tmp_path / "empty.hilc"  # a process killed while creating the file leaves zero bytes
    empty.touch()
    with CampaignStore(empty) as store:
        store.record_measurement(make_record(0))
    assert is_campaign_file(empty)


def test_dataset_export_csv_and_parquet(tmp_path):
    path = tmp_path / "c.hilc"
    with CampaignStore(path) as store:
        store.record_measurement(make_record(0, procedure="registration", step="nests", t0=1.7e9 - 100))
        for i in range(12):
            store.record_measurement(make_record(i))
        for i in range(4):  # other poses than the grid's (an exact copy would be dropped as a duplicate row)
            store.record_measurement(
                make_record(i, step="validation", rng=np.random.default_rng(100 + i), t0=1.7e9 + 1000)
            )
        df = campaign_dataset(store, "grid_sampling")
    assert len(df) == 16
    np.testing.assert_allclose(df["t_s"].iloc[0], 100.0)  # since the campaign's first measurement
    assert list(df["step_id"]) == ["grid"] * 12 + ["validation"] * 4
    recs = [make_record(i) for i in range(12)]
    np.testing.assert_allclose(
        df[["x_mm", "y_mm", "z_mm"]].to_numpy()[:12], [r.p_tracker_m * 1000 for r in recs]
    )
    np.testing.assert_allclose(
        df[[f"q{j}_rad" for j in range(1, 7)]].to_numpy()[:12], [r.q_rad for r in recs]
    )
    assert list(df["smr"])[:3] == [1, 2, 3]

    csv = tmp_path / "grid.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # hil.data.dataset warns about unit-less columns
        assert export_csv(path, csv, "grid_sampling", step="grid") == 12
        back = load_dataset(csv)
    assert list(back["point_id"]) == [f"p{i:04d}" for i in range(12)]
    np.testing.assert_allclose(back["x_mm"], df["x_mm"].iloc[:12], rtol=1e-9)
    np.testing.assert_allclose(back["spread_x_mm"], df["spread_x_mm"].iloc[:12], rtol=1e-9)

    pq = tmp_path / "all.parquet"
    assert export_parquet(path, pq, "grid_sampling") == 16
    pd.testing.assert_frame_equal(pd.read_parquet(pq), df)

    with CampaignStore(path) as store:
        store.record_measurement(make_record(0, step="warm", temperature_c=float("nan")))
        store.record_measurement(make_record(1, step="warm"))
        store.record_measurement(make_record(0, step="cold", temperature_c=float("nan")))
        with pytest.warns(UserWarning, match="temperature_c missing in 1 of 2"):
            assert "temperature_c" not in campaign_dataset(store, "grid_sampling", step="warm")
        assert "temperature_c" not in campaign_dataset(
            store, "grid_sampling", step="cold"
        )  # no sensor: no column
    with pytest.raises(ValueError, match="no measurements of tool_fit.*grid_sampling/grid \\(12\\)"):
        campaign_dataset(path, "tool_fit")


def test_dataset_temperature_is_the_arm_s_where_the_probe_read_every_point(tmp_path):
    """temperature_c: the object probe's reading when every point has one, else the air's (old campaigns)."""
    path = tmp_path / "c.hilc"
    with CampaignStore(path) as store:
        for i in range(4):
            store.record_measurement(make_record(i, step="probe", extra={"object_temperature_c": 25.0 + i}))
            store.record_measurement(make_record(i, step="old"))
        store.record_measurement(make_record(0, step="mixed", extra={"object_temperature_c": 30.0}))
        store.record_measurement(make_record(1, step="mixed"))
        probe, old = (
            campaign_dataset(store, "grid_sampling", step="probe"),
            campaign_dataset(store, "grid_sampling", step="old"),
        )
        with pytest.warns(UserWarning, match="object probe read only 1 of 2"):
            mixed = campaign_dataset(store, "grid_sampling", step="mixed")
    np.testing.assert_allclose(probe["temperature_c"], 25.0 + np.arange(4))
    np.testing.assert_allclose(probe["air_temperature_c"], 20.0 + 0.01 * np.arange(4))
    np.testing.assert_allclose(old["temperature_c"], old["air_temperature_c"])
    np.testing.assert_allclose(mixed["temperature_c"], 20.0 + 0.01 * np.arange(2))


def test_dataset_temperature_is_the_robot_s_own_reading_where_no_probe_read_every_point(tmp_path):
    """Without a probe on every point the robot's joint sensors give the arm's temperature (their column is
    kept beside the air's); with one, the probe's reading stays first."""
    with CampaignStore(tmp_path / "c.hilc") as store:
        for i in range(3):
            store.record_measurement(make_record(i, step="robot", extra={"robot_temperature_c": 31.0 + i}))
            both = {"robot_temperature_c": 31.0 + i, "object_temperature_c": 24.0 + i}
            store.record_measurement(make_record(i, step="both", extra=both))
        robot, both_ = (
            campaign_dataset(store, "grid_sampling", step="robot"),
            campaign_dataset(store, "grid_sampling", step="both"),
        )
    np.testing.assert_allclose(robot["temperature_c"], 31.0 + np.arange(3))
    np.testing.assert_allclose(robot["robot_temperature_c"], 31.0 + np.arange(3))
    np.testing.assert_allclose(robot["air_temperature_c"], 20.0 + 0.01 * np.arange(3))
    np.testing.assert_allclose(both_["temperature_c"], 24.0 + np.arange(3))


WRITER = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from hil.data.store import CampaignStore, MeasurementRecord

    print("open", flush=True)
    store = CampaignStore(sys.argv[1])
    store.record_event("resume", "writer started")
    for i in range(100000):
        pid = f"p{i:05d}"
        if store.has_measurement("grid_sampling", "grid", pid):
            continue
        q = np.full(6, i * 1e-4)
        store.record_measurement(MeasurementRecord(
            "grid_sampling", "grid", pid, q, q, np.eye(4), np.array([i, 0.0, 1.0]), np.zeros(3), np.zeros(3),
            5, (), 1, "nest1", 20.0, 1013.0, 40.0, time.time(), {"i": i}))
        print(i, flush=True)  # printed only after record_measurement returned: committed
        if i % 5 == 0:
            store.log("INFO", f"point {i}")
    """
)


def test_sigkill_at_random_moments_loses_no_committed_record(tmp_path):
    path = tmp_path / "killed.hilc"
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    rng = random.Random(1234)
    committed: set[int] = set()
    for _ in range(6):
        child = subprocess.Popen(
            [sys.executable, str(script), str(path)], stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT
        )
        try:
            assert child.stdout.readline() == "open\n"
            wanted = rng.randint(1, 40)
            for _ in range(wanted):  # wait for progress, not for a clock
                line = child.stdout.readline()
                assert line, f"writer died early: exit {child.poll()}"
                committed.add(int(line))
            time.sleep(rng.uniform(0.0, 0.01))  # land the kill somewhere inside the next record
            child.send_signal(signal.SIGKILL)
            committed.update(int(line) for line in child.stdout.read().split())
        finally:
            child.kill()
            child.wait(timeout=30)
            child.stdout.close()
        assert child.returncode == -signal.SIGKILL
        assert is_campaign_file(path)
        with CampaignStore(path) as store:
            assert store.integrity_ok()
            df = store.measurements()
        stored = [int(p[1:]) for p in df["point_id"]]
        assert not df.duplicated(["procedure", "step", "point_id"]).any()
        assert committed <= set(stored), "a committed record was lost"
        # resumed writers skip recorded points, so the store holds p0..pN without a gap;
        # at most the one point in flight was committed without being reported
        assert stored == list(range(len(stored)))
        assert len(stored) - len(committed) in (0, 1)
        assert [r["i"] for r in df["extra"]] == stored
        committed = set(stored)  # what survived this kill must survive the next ones too


def test_sigkill_while_creating_leaves_no_or_a_whole_campaign(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    rng = random.Random(99)
    for trial in range(3):
        path = tmp_path / f"new{trial}.hilc"
        child = subprocess.Popen(
            [sys.executable, str(script), str(path)], stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT
        )
        try:
            assert child.stdout.readline() == "open\n"  # about to create the file
            time.sleep(rng.uniform(0.0, 0.02))
            child.send_signal(signal.SIGKILL)
            reported = [int(line) for line in child.stdout.read().split()]
        finally:
            child.kill()
            child.wait(timeout=30)
            child.stdout.close()
        assert path.exists() or not reported
        if path.exists():
            assert is_campaign_file(path)
        with CampaignStore(path) as store:  # absent: created now; present: whole and readable
            assert store.integrity_ok()
            stored = [int(p[1:]) for p in store.measurements()["point_id"]]
        assert set(reported) <= set(stored) and stored == list(range(len(stored)))
        assert not list(tmp_path.glob(f".{path.name}.*")), "a half-built campaign was left behind"


def test_the_latest_temperature_is_the_arms_probe_else_the_robots_sensors_else_the_trackers_air(tmp_path):
    with CampaignStore(tmp_path / "t.sqlite") as store:
        assert store.last_temperature_c() is None
        store.record_measurement(make_record(1, temperature_c=21.5))
        assert store.last_temperature_c() == 21.5
        store.record_measurement(make_record(2, extra={"object_temperature_c": 23.25}))
        assert store.last_temperature_c() == 23.25
        store.record_measurement(make_record(3, temperature_c=20.0, extra={"robot_temperature_c": 24.5}))
        assert store.last_temperature_c() == 24.5  # the export's order: probe, robot, air
        store.record_measurement(
            make_record(4, extra={"object_temperature_c": 22.0, "robot_temperature_c": 24.5})
        )
        assert store.last_temperature_c() == 22.0
        store.record_measurement(make_record(5, temperature_c=float("nan")))
        assert store.last_temperature_c() is None


def test_a_campaign_says_which_joints_its_session_recorded(tmp_path):
    """A session's snapshot records the controller's joints; the dataset carries it for the coupled-joint
    edge (hil.data.joint_conventions), and a campaign of older sessions says nothing."""
    from hil.runner.cell_config import parse_cell_config
    from tests.cell_fixtures import sim_cell_toml

    path = tmp_path / "c.hilc"
    with CampaignStore(path) as store:
        for i in range(3):
            store.record_measurement(make_record(i))
        assert "joint_convention" not in campaign_dataset(store, "grid_sampling").attrs
        store.add_snapshot(parse_cell_config(tomllib.loads(sim_cell_toml())).snapshot())
        assert campaign_dataset(store, "grid_sampling").attrs["joint_convention"] == "controller"
