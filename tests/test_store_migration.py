"""A campaign written before the schema's version step (outcomes) opens, resumes and exports as before.

The old campaign is built here from `fixtures/campaign_v1.sql`: the SQL dump (sqlite3 iterdump) of a small
campaign that the schema-1 store of hil at commit 36d2f7f wrote; `fixtures/campaign_v1_grid_sampling.csv` is
what that hil exported from it (`export_csv`).
"""

from __future__ import annotations

import sqlite3
import uuid
from pathlib import Path

import numpy as np
import pytest

from hil.data.store import (
    SCHEMA_VERSION,
    CampaignStore,
    DuplicateMeasurementError,
    MeasurementRecord,
    OutcomeRecord,
    Verdict,
    export_csv,
)

FIXTURES = Path(__file__).parent / "fixtures"


def _old_campaign(folder: Path) -> Path:
    path = folder / "old.sqlite"
    conn = sqlite3.connect(path)
    conn.executescript((FIXTURES / "campaign_v1.sql").read_text())
    conn.close()
    return path


def _version(path: Path) -> int:
    with sqlite3.connect(path) as conn:
        return conn.execute("PRAGMA user_version").fetchone()[0]


def test_an_old_campaign_opens_at_the_new_version_with_nothing_recorded_changed(tmp_path):
    path = _old_campaign(tmp_path)
    assert _version(path) == 1
    with sqlite3.connect(path) as conn:
        before = {t: conn.execute(f"SELECT * FROM {t} ORDER BY id").fetchall() for t in ("measurements", "events", "steps", "log", "snapshots")}  # fmt: skip
    with CampaignStore(path, create=False) as store:
        assert store.outcomes() == []
        assert store.step_result("registration", "fit")["rms_mm"] == 0.9
    assert _version(path) == SCHEMA_VERSION == 3
    with sqlite3.connect(path) as conn:
        after = {t: conn.execute(f"SELECT * FROM {t} ORDER BY id").fetchall() for t in before}
        meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    assert after == before
    assert meta["schema_version"] == "1" and "migrated_to_2_s" in meta  # when the step was taken, kept
    assert (
        "migrated_to_3_s" in meta and uuid.UUID(meta["uuid"]).version == 4
    )  # the campaign's UUID, given once
    with CampaignStore(path, create=False) as store:  # opened again: nothing left to migrate
        assert str(store.uuid) == meta["uuid"]
    assert _version(path) == 3


def test_an_old_campaign_exports_as_the_old_hil_exported_it(tmp_path):
    path = _old_campaign(tmp_path)
    out = tmp_path / "grid.csv"
    assert export_csv(path, out, procedure="grid_sampling") == 11
    assert out.read_text() == (FIXTURES / "campaign_v1_grid_sampling.csv").read_text()


def test_an_old_campaign_resumes_skipping_what_it_holds_and_records_outcomes(tmp_path):
    path = _old_campaign(tmp_path)
    with CampaignStore(path, create=False) as store:
        recorded = store.records("grid_sampling", "grid")
        assert len(recorded) == 8 and store.has_measurement("grid_sampling", "grid", "g1-0007")
        with pytest.raises(DuplicateMeasurementError):
            store.record_measurement(recorded[0])
        new = MeasurementRecord(**{**recorded[-1].__dict__, "point_id": "g1-0008", "timestamp_s": 1.8e9})
        store.record_measurement(new)
        judged = OutcomeRecord("tool_fit", "circle_residual", 12e-6, "m", 30e-6, "max", Verdict.PASS, "RMS")
        store.record_outcome(judged)
        assert store.outcomes() == [judged]
        np.testing.assert_array_equal(store.records("grid_sampling", "grid")[-1].q_rad, new.q_rad)
    with sqlite3.connect(path) as conn, pytest.raises(sqlite3.DatabaseError, match="append-only"):
        conn.execute("UPDATE outcomes SET outcome = 'fail'")


def test_a_new_campaign_is_created_at_the_new_version_with_its_outcomes_table(tmp_path):
    path = tmp_path / "new.sqlite"
    with CampaignStore(path) as store:
        store.record_outcome(OutcomeRecord("p", "m", None, "m", None, "max", Verdict.NOT_JUDGED, "no value"))
        assert store.outcomes()[0].verdict is Verdict.NOT_JUDGED
        assert store.uuid.version == 4
    with CampaignStore(tmp_path / "other.sqlite") as other, CampaignStore(path) as again:
        assert other.uuid != again.uuid  # each campaign its own
    assert _version(path) == 3
