"""A campaign file's rows as they are stored, table by table, for copying it into the shared store (hil campaign
push). Read through a read-only connection after the file store opened the file (and so migrated it)."""

from __future__ import annotations

import sqlite3
import uuid
from dataclasses import dataclass
from pathlib import Path

from hil.data.store import MEASUREMENT_COLUMNS, CampaignStore

# Each table's copied columns in the order stored (both stores give them the same names).
COPIED_TABLES: dict[str, tuple[str, ...]] = {
    "snapshots": ("recorded_s", "data"),
    "measurements": MEASUREMENT_COLUMNS,
    "events": ("recorded_s", "kind", "message", "procedure", "step", "point_id", "data"),
    "steps": ("recorded_s", "procedure", "step", "result"),
    "log": ("recorded_s", "level", "logger", "message"),
    "outcomes": (
        "recorded_s", "procedure", "measurement", "value", "unit", "limit_value", "bound", "outcome", "note",
    ),
    "results": ("recorded_s", "kind", "summary", "model"),
}  # fmt: skip


@dataclass(frozen=True)
class CampaignCopy:
    """A campaign file's identity and its rows, oldest first per table."""

    uuid: uuid.UUID
    name: str  # the file's name without its folder
    created_s: float
    rows: dict[str, list[tuple]]


def read_campaign_copy(path: str | Path) -> CampaignCopy:
    """Every row of the campaign file `path` (opened, so migrated, by the file store first)."""
    path = Path(path)
    with CampaignStore(path, create=False) as store:
        identity, created_s = store.uuid, store.created_s
    conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    try:
        rows = {
            table: conn.execute(f"SELECT {_names(columns)} FROM {table} ORDER BY id").fetchall()
            for table, columns in COPIED_TABLES.items()
        }
    finally:
        conn.close()
    return CampaignCopy(identity, path.name, created_s, rows)


def _names(columns: tuple[str, ...]) -> str:
    return ", ".join(f'"{c}"' for c in columns)
