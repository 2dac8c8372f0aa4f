"""Every calibration and diagnosis of a fleet, read in bulk: from the shared store (one query over its results
and the campaign_keys view) or from a folder of campaign files (one read per file, never one per point).

`FleetHistory.results`: one row per recorded result (robot, campaign, kind, when, errors before and after,
temperature); `FleetHistory.parameters`: one row per result and free parameter (its change from the nominal
and its standard error, SI), with `own` telling the robot's own parameters from the cell's (the base frame and
the tool points move with the cell, not with the arm).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hil.data.pg_url import is_campaign_url
from hil.data.store import CampaignStore, is_campaign_file

CELL_PARAMETER_PREFIXES = ("base_", "tool", "probe")  # fitted per cell set-up, not properties of the arm
RESULT_COLUMNS = (
    "robot", "robot_model", "robot_serial", "cell_name", "campaign", "label", "kind", "time_s", "recorded_s",
    "rms_before_m", "rms_after_m", "validation_rms_m", "temperature_c", "effects_found", "effects_assumed",
)  # fmt: skip


@dataclass(frozen=True)
class FleetHistory:
    """A fleet's results (one row each) and their parameters (one row per result and parameter)."""

    results: pd.DataFrame
    parameters: pd.DataFrame
    source: str  # what was read: the database (without a password) or the folder


def robot_key(serial: pd.Series, model: pd.Series, cell: pd.Series) -> pd.Series:
    """A robot's name in the fleet: its serial number, else (a controller that does not report one) its model
    in its cell."""
    fallback = model.fillna("robot").astype(str) + " in " + cell.fillna("unnamed cell").astype(str)
    return serial.where(serial.notna() & (serial.astype(str) != ""), fallback).astype(str)


def read_fleet(
    source: str | Path, serial: str | None = None, password_file: str | Path | None = None
) -> FleetHistory:
    """The results of every campaign at `source` (a postgresql:// URL of the shared store, or a folder of
    campaign files); only robot `serial`'s when given."""
    rows = (
        _from_database(str(source), password_file) if is_campaign_url(source) else _from_folder(Path(source))
    )
    frame, shown = rows
    if frame.empty:
        return FleetHistory(pd.DataFrame(columns=RESULT_COLUMNS), _parameters(frame), shown)
    frame["robot"] = robot_key(frame["robot_serial"], frame["robot_model"], frame["cell_name"])
    if serial is not None:
        frame = frame[(frame["robot_serial"] == serial) | (frame["robot"] == serial)].reset_index(drop=True)
    summaries = [json.loads(s) if isinstance(s, str) else s for s in frame["summary"]]  # one per result
    for key in ("rms_before_m", "rms_after_m", "validation_rms_m", "temperature_mean_c"):
        frame[key] = np.array([_number(s.get(key)) for s in summaries], dtype=float)
    frame["temperature_c"] = frame.pop("temperature_mean_c")
    frame["effects_found"] = [_effects(s.get("effects_found")) for s in summaries]
    frame["effects_assumed"] = [_effects(s.get("effects_assumed")) for s in summaries]
    frame["summary"] = summaries
    frame["time_s"] = frame["last_s"].where(frame["last_s"].notna(), frame["recorded_s"]).astype(float)
    frame = frame.sort_values(["robot", "time_s", "recorded_s"], kind="stable").reset_index(drop=True)
    return FleetHistory(frame[list(RESULT_COLUMNS)], _parameters(frame), shown)


def _number(value: object) -> float:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else np.nan


def _effects(effects: object) -> str:
    if not isinstance(effects, list):
        return ""
    return ", ".join(
        f"{e.get('name')}" + (f" (joint {e['joint']})" if e.get("joint") is not None else "")
        for e in effects
        if isinstance(e, dict)
    )


def _parameters(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per result and parameter: result (its row in `results`), name, delta, std, unit, own."""
    columns = ["result", "name", "delta", "std", "unit"]
    if frame.empty or "summary" not in frame:
        return pd.DataFrame(columns=[*columns, "own"])
    counts = [len(s.get("parameters") or []) for s in frame["summary"]]
    flat = [p for s in frame["summary"] for p in (s.get("parameters") or [])]
    out = pd.DataFrame.from_records(flat, columns=columns[1:]) if flat else pd.DataFrame(columns=columns[1:])
    out.insert(0, "result", np.repeat(np.arange(len(frame)), counts))
    out["delta"] = pd.to_numeric(out["delta"], errors="coerce")
    out["std"] = pd.to_numeric(out["std"], errors="coerce")
    out["own"] = ~out["name"].astype(str).str.startswith(CELL_PARAMETER_PREFIXES)
    return out


_DATABASE_QUERY = """
SELECT r.campaign::text AS campaign, k.label, k.robot_model, k.robot_serial, k.cell_name, k.last_s,
    r.kind, r.recorded_s, r.summary
FROM results r JOIN campaign_keys k ON k.uuid = r.campaign
WHERE r.kind IN ('calibration', 'diagnosis')
ORDER BY r.id
"""


def _from_database(url: str, password_file: str | Path | None) -> tuple[pd.DataFrame, str]:
    from hil.data.pg_store import query_database
    from hil.data.pg_url import CampaignURL, with_default_campaign

    target = CampaignURL.parse(with_default_campaign(url, "every campaign"), password_file)
    return query_database(target, _DATABASE_QUERY), target.database


def _from_folder(folder: Path) -> tuple[pd.DataFrame, str]:
    if not folder.is_dir():
        raise FileNotFoundError(
            f"{folder}: no such folder; give a folder of campaign files or a postgresql:// URL"
        )
    rows: list[dict] = []
    for path in sorted(p for p in folder.iterdir() if p.is_file() and is_campaign_file(p)):
        with CampaignStore(path, create=False) as store:
            results = store.results()
            if not results:
                continue
            keys = file_keys(store)
        rows += [
            {**keys, "label": path.name, "kind": r.kind, "recorded_s": r.recorded_s, "summary": r.summary}
            for r in results
            if r.kind in ("calibration", "diagnosis")
        ]
    return pd.DataFrame(rows), str(folder)


def file_keys(store: CampaignStore) -> dict:
    """A campaign file's keys, as the shared store's campaign_keys view gives them."""
    snapshots = store.snapshots()
    last = snapshots[-1] if snapshots else {}
    station, definition = _section(last, "station"), _section(last, "robot_definition")
    tracker = _section(station, "tracker")
    times = store.measurement_columns(["timestamp_s"])["timestamp_s"]

    def text(value: object) -> str | None:
        return None if value in (None, "") else str(value)

    return {
        "campaign": str(store.uuid),
        "robot_model": text(station.get("robot_model_reported")) or text(definition.get("model")),
        "robot_serial": text(station.get("robot_serial_number")),
        "cell_name": text(station.get("cell_name")),
        "tracker_serial": text(tracker.get("serial_number")),
        "last_s": float(times.max()) if len(times) else np.nan,
    }


def _section(parent: dict, key: str) -> dict:
    value = parent.get(key)
    return value if isinstance(value, dict) else {}
