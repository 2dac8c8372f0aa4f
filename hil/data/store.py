"""The campaign store: one append-only, crash-safe SQLite file per measurement campaign.

Every measurement is committed (WAL journal, synchronous=FULL) before `record_measurement` returns, so a
process killed at any moment loses at most the point in flight; a resumed campaign asks `has_measurement`
and never measures a point twice (a UNIQUE index on (procedure, step, point_id) makes a duplicate an error).
Recorded rows are never updated or deleted (triggers refuse it).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sqlite3
import threading
import time
import uuid
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Protocol

import numpy as np
import pandas as pd

from hil.data.dataset import DatasetError, validate_dataset, write_dataset
from hil.data.jsonable import to_jsonable

# 2: the outcomes table (declared measurements judged against their limits); 3: the campaign's UUID (meta 'uuid')
# and its results table (the models and summaries hil calibrate and hil diagnose made from it)
SCHEMA_VERSION = 3
APPLICATION_ID = 0x48494C43  # "HILC" in the SQLite header (offset 68): marks the file as a hil campaign
SQLITE_MAGIC = b"SQLite format 3\x00"

_AXES = ("x", "y", "z")
# The arm's own temperature in a measurement's extra JSON, in order of preference: the tracker's object probe on
# the arm, then the robot's joint sensors (the air's, in the temperature_c column, comes after both).
ARM_TEMPERATURE_KEYS = ("object_temperature_c", "robot_temperature_c")
Q_TARGET_COLUMNS = tuple(f"q{i}_target_rad" for i in range(1, 7))
Q_COLUMNS = tuple(f"q{i}_rad" for i in range(1, 7))
T_COLUMNS = tuple(f"T_base_flange_{r}{c}" for r in range(4) for c in range(4))
P_COLUMNS = tuple(f"{a}_m" for a in _AXES)
SPREAD_COLUMNS = tuple(f"spread_{a}_m" for a in _AXES)
STD_COLUMNS = tuple(f"std_{a}_m" for a in _AXES)
_REAL_COLUMNS = Q_TARGET_COLUMNS + Q_COLUMNS + T_COLUMNS + P_COLUMNS + SPREAD_COLUMNS + STD_COLUMNS
_FLOAT_COLUMNS = frozenset(_REAL_COLUMNS + ("temperature_c", "pressure_hpa", "humidity_pct", "timestamp_s"))
# MeasurementRecord array fields -> their flat REAL columns and shape
ARRAY_FIELDS: dict[str, tuple[tuple[str, ...], tuple[int, ...]]] = {
    "q_target_rad": (Q_TARGET_COLUMNS, (6,)),
    "q_rad": (Q_COLUMNS, (6,)),
    "T_base_flange": (T_COLUMNS, (4, 4)),
    "p_tracker_m": (P_COLUMNS, (3,)),
    "spread_m": (SPREAD_COLUMNS, (3,)),
    "std_m": (STD_COLUMNS, (3,)),
}
MEASUREMENT_COLUMNS: tuple[str, ...] = (
    ("procedure", "step", "point_id")
    + _REAL_COLUMNS
    + ("shots", "rejected_shots", "smr", "location", "temperature_c", "pressure_hpa", "humidity_pct")
    + ("timestamp_s", "extra", "recorded_s")
)

_SCHEMA_1 = f"""
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE snapshots (id INTEGER PRIMARY KEY, recorded_s REAL NOT NULL, data TEXT NOT NULL);
CREATE TABLE measurements (
    id INTEGER PRIMARY KEY,
    procedure TEXT NOT NULL, step TEXT NOT NULL, point_id TEXT NOT NULL,
    {", ".join(f'"{c}" REAL' for c in _REAL_COLUMNS)},
    shots INTEGER NOT NULL, rejected_shots TEXT NOT NULL, smr INTEGER NOT NULL, location TEXT NOT NULL,
    temperature_c REAL, pressure_hpa REAL, humidity_pct REAL,
    timestamp_s REAL NOT NULL, extra TEXT NOT NULL, recorded_s REAL NOT NULL
);
CREATE UNIQUE INDEX measurement_point ON measurements (procedure, step, point_id);
CREATE TABLE events (
    id INTEGER PRIMARY KEY, recorded_s REAL NOT NULL, kind TEXT NOT NULL, message TEXT NOT NULL,
    procedure TEXT, step TEXT, point_id TEXT, data TEXT NOT NULL
);
CREATE TABLE steps (
    id INTEGER PRIMARY KEY, recorded_s REAL NOT NULL, procedure TEXT NOT NULL, step TEXT NOT NULL,
    result TEXT NOT NULL
);
CREATE INDEX step_key ON steps (procedure, step);
CREATE TABLE log (
    id INTEGER PRIMARY KEY, recorded_s REAL NOT NULL, level TEXT NOT NULL, logger TEXT NOT NULL,
    message TEXT NOT NULL
);
"""


def _append_only(*tables: str) -> str:
    """Triggers that refuse to change or delete a row of these tables."""
    return "".join(
        f"""
CREATE TRIGGER {table}_no_update BEFORE UPDATE ON {table}
BEGIN SELECT RAISE(ABORT, 'hil campaign store is append-only: {table} rows are never changed'); END;
CREATE TRIGGER {table}_no_delete BEFORE DELETE ON {table}
BEGIN SELECT RAISE(ABORT, 'hil campaign store is append-only: {table} rows are never deleted'); END;
"""
        for table in tables
    )


# Each schema step: the SQL that takes a campaign of the version before to this one (applied in order, each in
# one transaction with its user_version, so a campaign is never half-migrated).
_MIGRATIONS: dict[int, str] = {
    2: """
CREATE TABLE outcomes (
    id INTEGER PRIMARY KEY, recorded_s REAL NOT NULL, procedure TEXT NOT NULL, measurement TEXT NOT NULL,
    value REAL, unit TEXT NOT NULL, limit_value REAL, bound TEXT NOT NULL, outcome TEXT NOT NULL
        CHECK (outcome IN ('pass', 'fail', 'not judged')),
    note TEXT NOT NULL
);
"""
    + _append_only("outcomes"),
    # A random (version 4) UUID from SQLite's own random bytes, so a campaign written by an older hil gets
    # one too when it is first opened; the shared store knows a pushed campaign by it.
    3: """
INSERT INTO meta (key, value) SELECT 'uuid', lower(
    substr(h, 1, 8) || '-' || substr(h, 9, 4) || '-4' || substr(h, 14, 3) || '-'
    || substr('89ab', 1 + (abs(random()) % 4), 1) || substr(h, 18, 3) || '-' || substr(h, 21, 12)
) FROM (SELECT hex(randomblob(16)) AS h);
CREATE TABLE results (
    id INTEGER PRIMARY KEY, recorded_s REAL NOT NULL, kind TEXT NOT NULL, summary TEXT NOT NULL, model TEXT
);
"""
    + _append_only("results"),
}
_SCHEMA = (
    _SCHEMA_1
    + _append_only("meta", "snapshots", "measurements", "events", "steps", "log")
    + "".join(_MIGRATIONS[v] for v in range(2, SCHEMA_VERSION + 1))
)


class Verdict(StrEnum):
    """A declared measurement's outcome against its limits."""

    PASS = "pass"
    FAIL = "fail"
    NOT_JUDGED = "not judged"  # no limit declared for it, or no finite value to judge


@dataclass(frozen=True)
class OutcomeRecord:
    """One declared measurement of a procedure, judged: its value and limit in SI (`unit` names the SI unit:
    m, rad, or "" for a count or a ratio), which side the limit bounds (`bound`: "max" or "min") and why
    (`note`: what was measured, what the outcome rests on)."""

    procedure: str
    measurement: str
    value: float | None
    unit: str
    limit_value: float | None
    bound: str
    verdict: Verdict
    note: str = ""


@dataclass(frozen=True)
class ResultRecord:
    """What an analysis made of the campaign: `kind` ("calibration", "diagnosis"), its summary (errors before and
    after, parameters with their uncertainties, effects found and assumed; JSON-able, SI units) and the model
    it wrote (its JSON, as the model file holds it), recorded at `recorded_s` (UNIX time)."""

    kind: str
    summary: dict
    model: dict | None
    recorded_s: float = 0.0


class CampaignError(ValueError):
    """A file that cannot be used as a campaign store; the message says what to do."""


class DuplicateMeasurementError(CampaignError):
    """A second record of a point already in the campaign (check `has_measurement` before measuring)."""


def _vector(name: str, value: object, shape: tuple[int, ...], finite: bool) -> np.ndarray:
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"MeasurementRecord.{name}: not numeric ({exc})") from exc
    if arr.shape != shape:
        raise ValueError(f"MeasurementRecord.{name}: expected shape {shape}, got {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        raise ValueError(f"MeasurementRecord.{name}: holds NaN or infinity")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class MeasurementRecord:
    """One measured robot pose: what was commanded, what the robot and the tracker reported, conditions."""

    procedure: str  # the procedure's registered name
    step: str  # e.g. "grid", "validation", "pose2/hole3"
    point_id: str  # unique within (procedure, step)
    q_target_rad: np.ndarray  # (6,) commanded joints
    q_rad: np.ndarray  # (6,) joints the robot reported after settling
    T_base_flange: np.ndarray  # (4,4) flange pose the controller reported
    p_tracker_m: np.ndarray  # (3,) measured SMR centre, tracker frame
    spread_m: np.ndarray  # (3,) std-dev over the kept shots
    std_m: np.ndarray  # (3,) tracker-reported std-devs
    shots: int
    rejected_shots: tuple[int, ...]
    smr: int  # nest id on the tool (1..), 0 when not on a nest
    location: str  # where the SMR sat: "nest1", "hole3", "face", ...
    temperature_c: float
    pressure_hpa: float
    humidity_pct: float
    timestamp_s: float  # UNIX time of the measurement
    extra: dict = field(default_factory=dict)  # JSON-able, anything else (attempts, predicted point..)

    def __post_init__(self) -> None:
        for name in ("procedure", "step", "point_id"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise ValueError(f"MeasurementRecord.{name} must be a non-empty string, got {value!r}")
        arrays = {
            "q_target_rad": ((6,), True),
            "q_rad": ((6,), True),
            "T_base_flange": ((4, 4), True),
            "p_tracker_m": ((3,), True),
            "spread_m": ((3,), False),
            "std_m": ((3,), False),
        }
        for name, (shape, finite) in arrays.items():
            object.__setattr__(self, name, _vector(name, getattr(self, name), shape, finite))
        object.__setattr__(self, "rejected_shots", tuple(int(i) for i in self.rejected_shots))
        object.__setattr__(self, "shots", int(self.shots))
        object.__setattr__(self, "smr", int(self.smr))
        object.__setattr__(self, "location", str(self.location))
        for name in ("temperature_c", "pressure_hpa", "humidity_pct", "timestamp_s"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not math.isfinite(self.timestamp_s):
            raise ValueError("MeasurementRecord.timestamp_s must be a finite UNIX time")
        if not isinstance(self.extra, dict):
            raise ValueError(f"MeasurementRecord.extra must be a dict, got {type(self.extra).__name__}")


def _json(value: object, what: str) -> str:
    try:
        return json.dumps(to_jsonable(value), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} is not JSON-able ({exc}); pass numbers, strings, lists and dicts") from exc


def _nullable(x: float) -> float | None:
    return x if math.isfinite(x) else None


def is_campaign_file(path: str | Path) -> bool:
    """True when `path` is an SQLite file marked as a hil campaign (reads the 100-byte header only)."""
    try:
        with open(path, "rb") as fh:
            header = fh.read(100)
    except OSError:
        return False
    return (
        len(header) == 100
        and header.startswith(SQLITE_MAGIC)
        and int.from_bytes(header[68:72], "big") == APPLICATION_ID
    )


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _create(path: Path) -> None:
    """Build an empty campaign beside `path` and link it into place, so `path` is never half-made."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.creating")
    for leftover in (tmp, Path(f"{tmp}-journal")):
        leftover.unlink(missing_ok=True)
    conn = sqlite3.connect(tmp, isolation_level=None)
    try:
        conn.execute("PRAGMA synchronous=FULL")
        conn.executescript(
            f"BEGIN; PRAGMA application_id={APPLICATION_ID}; PRAGMA user_version={SCHEMA_VERSION};"
            + _SCHEMA
            + "INSERT INTO meta (key, value) VALUES ('format', 'hil campaign'), "
            + f"('schema_version', '{SCHEMA_VERSION}'), ('created_s', '{time.time()!r}'); COMMIT;"
        )
        conn.execute("PRAGMA journal_mode=WAL")
    finally:
        conn.close()
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    try:
        os.link(tmp, path)  # fails if another process created the campaign meanwhile: keep theirs
    except FileExistsError:
        pass
    except OSError:  # a file system without hard links
        if not path.exists():
            os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(path.parent)
    _remove_stale_temporaries(path)


def _remove_stale_temporaries(path: Path) -> None:
    """Remove half-built campaigns a killed process left beside `path` (its pid is in the name)."""
    for leftover in path.parent.glob(f".{path.name}.*.creating*"):
        try:
            pid = int(leftover.name[len(path.name) + 2 :].split(".")[0])
        except ValueError:
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            leftover.unlink(missing_ok=True)
        except OSError:
            pass


def _migrate(conn: sqlite3.Connection, version: int) -> None:
    """Take a campaign written by an older hil to SCHEMA_VERSION, one step per transaction. Nothing recorded
    is changed: a step only adds tables; the meta table notes when each step was taken."""
    for step in range(version + 1, SCHEMA_VERSION + 1):
        conn.execute("BEGIN IMMEDIATE")  # another process migrating the same file waits here
        try:
            if conn.execute("PRAGMA user_version").fetchone()[0] < step:  # ... and finds it done
                for statement in _statements(_MIGRATIONS[step]):
                    conn.execute(statement)
                conn.execute(
                    "INSERT INTO meta (key, value) VALUES (?, ?)",
                    (f"migrated_to_{step}_s", repr(time.time())),
                )
                conn.execute(f"PRAGMA user_version={step}")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        conn.execute("COMMIT")


def _statements(sql: str) -> list[str]:
    """The complete SQL statements of a script (a trigger's body holds semicolons of its own)."""
    out, pending = [], ""
    for piece in sql.split(";"):
        pending += piece + ";"
        if sqlite3.complete_statement(pending):
            if pending.strip(" \n;"):
                out.append(pending.strip())
            pending = ""
    return out


class CampaignStore:
    """One campaign file: station snapshots, measurements, events, finished steps and the log."""

    def __init__(self, path: str | Path, *, create: bool = True) -> None:
        self.path = Path(path)
        if not self.path.exists() or self.path.stat().st_size == 0:
            if not create:
                what = "is empty" if self.path.exists() else "not found"
                raise CampaignError(f"campaign file {what}: {self.path}; give the file a session wrote")
            if not self.path.parent.is_dir():
                raise CampaignError(
                    f"cannot create campaign {self.path}: folder {self.path.parent} does not exist"
                )
            if self.path.exists():  # a zero-byte file: nothing was ever committed to it
                self.path.unlink()
            _create(self.path)
        if not is_campaign_file(self.path):
            raise CampaignError(
                f"{self.path} is not a hil campaign file (no hil campaign SQLite header); "
                "give the path of a campaign written by hil, or a new file name to start one"
            )
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = sqlite3.connect(
            self.path, isolation_level=None, check_same_thread=False, timeout=30.0
        )
        try:
            version = self._conn.execute("PRAGMA user_version").fetchone()[0]
            if version > SCHEMA_VERSION:
                raise CampaignError(
                    f"{self.path} has campaign schema version {version}, this hil reads up to "
                    f"{SCHEMA_VERSION}: upgrade hil to open it"
                )
            if version < 1:
                raise CampaignError(f"{self.path}: campaign schema version {version} is not valid")
            if version < SCHEMA_VERSION:
                _migrate(self._conn, version)
            self._conn.execute("PRAGMA journal_mode=WAL")
            self._conn.execute("PRAGMA synchronous=FULL")
            meta = dict(self._conn.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            self._conn.close()
            self._conn = None
            raise CampaignError(f"{self.path}: unreadable campaign file ({exc})") from exc
        except CampaignError:
            self._conn.close()
            self._conn = None
            raise
        self.created_s = float(meta.get("created_s", "nan"))
        self.uuid = uuid.UUID(meta["uuid"])  # given at creation (or by the step to schema 3), never changed
        self._started_s: float | None = None

    # -- plumbing -------------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._conn is None

    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise CampaignError(f"campaign store {self.path} is closed")
        return self._conn

    def _insert(self, sql: str, values: Sequence[object]) -> int:
        with self._lock:
            cur = self._db().execute(sql, values)  # autocommit: durable when execute returns
            if cur.lastrowid is None:
                raise CampaignError(f"campaign store {self.path}: the insert added no row")
            return cur.lastrowid

    def _frame(self, sql: str, params: Sequence[object] = ()) -> pd.DataFrame:
        with self._lock:
            return pd.read_sql_query(sql, self._db(), params=list(params))

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> CampaignStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- snapshots ------------------------------------------------------------------------------------
    def add_snapshot(self, snapshot: dict) -> None:
        """Record the station snapshot (cell, robot, tracker, software) of a session start."""
        self._insert(
            "INSERT INTO snapshots (recorded_s, data) VALUES (?, ?)",
            (time.time(), _json(snapshot, "snapshot")),
        )

    def snapshots(self) -> list[dict]:
        with self._lock:
            rows = self._db().execute("SELECT data FROM snapshots ORDER BY id").fetchall()
        return [json.loads(r[0]) for r in rows]

    # -- measurements ---------------------------------------------------------------------------------
    def record_measurement(self, m: MeasurementRecord) -> int:
        """Append one measurement, committed before return; returns its row id."""
        values: list[object] = [m.procedure, m.step, m.point_id]
        for arr in (m.q_target_rad, m.q_rad, m.T_base_flange, m.p_tracker_m, m.spread_m, m.std_m):
            values.extend(_nullable(float(v)) for v in arr.ravel())
        values += [
            m.shots,
            json.dumps(list(m.rejected_shots)),
            m.smr,
            m.location,
            _nullable(m.temperature_c),
            _nullable(m.pressure_hpa),
            _nullable(m.humidity_pct),
            m.timestamp_s,
            _json(m.extra, "MeasurementRecord.extra"),
            time.time(),
        ]
        columns = ", ".join(f'"{c}"' for c in MEASUREMENT_COLUMNS)
        marks = ", ".join("?" * len(MEASUREMENT_COLUMNS))
        try:
            return self._insert(f"INSERT INTO measurements ({columns}) VALUES ({marks})", values)
        except sqlite3.IntegrityError as exc:
            if not self.has_measurement(m.procedure, m.step, m.point_id):
                raise
            raise DuplicateMeasurementError(
                f"point {m.point_id!r} of {m.procedure}/{m.step} is already recorded in {self.path}; "
                "a campaign never measures a point twice (check has_measurement() before measuring)"
            ) from exc

    def has_measurement(self, procedure: str, step: str, point_id: str) -> bool:
        with self._lock:
            row = (
                self._db()
                .execute(
                    "SELECT 1 FROM measurements WHERE procedure=? AND step=? AND point_id=?",
                    (procedure, step, point_id),
                )
                .fetchone()
            )
        return row is not None

    def measurements(
        self, procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame:
        """Measurements in recording order, one row each (SI units): id, the MEASUREMENT_COLUMNS (arrays
        flattened: q1_rad.., x_m.., T_base_flange_00..) and the record's arrays as object columns
        (q_target_rad, q_rad, T_base_flange (4, 4), p_tracker_m, spread_m, std_m)."""
        return with_record_objects(self.measurement_columns(MEASUREMENT_COLUMNS, procedure, step))

    def measurement_columns(
        self, columns: Sequence[str], procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame:
        """Only the given stored columns (plus id) of the measurements, in recording order, JSON left as text:
        the fast read for analysis (`campaign_dataset`)."""
        unknown = [c for c in columns if c not in MEASUREMENT_COLUMNS]
        if unknown:
            raise ValueError(
                f"unknown measurement column(s) {unknown}; known: {', '.join(MEASUREMENT_COLUMNS)}"
            )
        where, params = _where(procedure=procedure, step=step)
        names = ", ".join(f'"{c}"' for c in ("id", *columns))
        df = self._frame(f"SELECT {names} FROM measurements{where} ORDER BY id", params)
        for col in columns:
            if col in _FLOAT_COLUMNS:
                df[col] = df[col].astype(float)  # NULL (a NaN when recorded) -> NaN
        return df

    def records(self, procedure: str | None = None, step: str | None = None) -> list[MeasurementRecord]:
        """The measurements as MeasurementRecord objects, in recording order."""
        return [record_from_row(row) for row in self.measurements(procedure, step).to_dict("records")]

    def point_counts(self) -> pd.DataFrame:
        """Number of measurements per (procedure, step), in order of first measurement: the first and last
        instrument times (`first_s`, `last_s`: the cell's clock, which a simulated cell runs faster) and the
        first and last times they were recorded (`first_recorded_s`, `last_recorded_s`: this computer's clock)."""
        return self._frame(
            "SELECT procedure, step, COUNT(*) AS points, MIN(timestamp_s) AS first_s, MAX(timestamp_s) AS last_s, "
            "MIN(recorded_s) AS first_recorded_s, MAX(recorded_s) AS last_recorded_s "
            "FROM measurements GROUP BY procedure, step ORDER BY MIN(id)"
        )

    @property
    def started_s(self) -> float:
        """UNIX time of the campaign's first measurement (the file's creation time until there is one)."""
        if self._started_s is None:
            with self._lock:
                row = (
                    self._db().execute("SELECT timestamp_s FROM measurements ORDER BY id LIMIT 1").fetchone()
                )
            if row is None:
                return self.created_s
            self._started_s = float(row[0])  # append-only: the first measurement never changes
        return self._started_s

    def last_temperature_c(self) -> float | None:
        """The temperature at the campaign's latest measurement, in the export's order (`ARM_TEMPERATURE_KEYS`):
        the object probe's (the arm's own), else the robot's joint sensors', else the air's the tracker used;
        None when none was recorded."""
        with self._lock:
            row = (
                self._db()
                .execute("SELECT temperature_c, extra FROM measurements ORDER BY id DESC LIMIT 1")
                .fetchone()
            )
        return None if row is None else arm_temperature_c(row[0], row[1])

    @property
    def last_timestamp_s(self) -> float | None:
        """UNIX time of the campaign's latest measurement; None while it has none."""
        with self._lock:
            row = self._db().execute("SELECT MAX(timestamp_s) FROM measurements").fetchone()
        return None if row is None or row[0] is None else float(row[0])

    # -- events, steps, log ---------------------------------------------------------------------------
    def record_event(
        self,
        kind: str,
        message: str,
        *,
        procedure: str | None = None,
        step: str | None = None,
        point_id: str | None = None,
        data: dict | None = None,
    ) -> None:
        """Append an event (fault, retry, resume, operator action...)."""
        self._insert(
            "INSERT INTO events (recorded_s, kind, message, procedure, step, point_id, data) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (
                time.time(),
                str(kind),
                str(message),
                procedure,
                step,
                point_id,
                _json(data or {}, "event data"),
            ),
        )

    def events(self) -> pd.DataFrame:
        return with_event_objects(
            self._frame(
                "SELECT id, recorded_s, kind, message, procedure, step, point_id, data FROM events ORDER BY id"
            )
        )

    def record_outcome(self, outcome: OutcomeRecord) -> None:
        """Append a judged measurement (committed when this returns)."""
        self._insert(
            "INSERT INTO outcomes (recorded_s, procedure, measurement, value, unit, limit_value, bound, outcome, "
            "note) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                time.time(), outcome.procedure, outcome.measurement,
                None if outcome.value is None else _nullable(float(outcome.value)), outcome.unit,
                None if outcome.limit_value is None else float(outcome.limit_value), outcome.bound,
                outcome.verdict.value, outcome.note,
            ),
        )  # fmt: skip

    def outcomes(self) -> list[OutcomeRecord]:
        """Every judged measurement in the order recorded (a procedure run again appends newer ones)."""
        with self._lock:
            rows = (
                self._db()
                .execute(
                    "SELECT procedure, measurement, value, unit, limit_value, bound, outcome, note "
                    "FROM outcomes ORDER BY id"
                )
                .fetchall()
            )
        return [
            OutcomeRecord(procedure, measurement, value, unit, limit, bound, Verdict(verdict), note)
            for procedure, measurement, value, unit, limit, bound, verdict, note in rows
        ]

    def record_result(self, result: ResultRecord) -> None:
        """Append an analysis' model and summary (committed when this returns)."""
        self._insert(
            "INSERT INTO results (recorded_s, kind, summary, model) VALUES (?, ?, ?, ?)",
            (
                time.time(),
                result.kind,
                _json(result.summary, "result summary"),
                None if result.model is None else _json(result.model, "result model"),
            ),
        )

    def results(self) -> list[ResultRecord]:
        """Every recorded analysis result, oldest first."""
        with self._lock:
            rows = (
                self._db()
                .execute("SELECT kind, summary, model, recorded_s FROM results ORDER BY id")
                .fetchall()
            )
        return [result_from_row(*row) for row in rows]

    def finish_step(self, procedure: str, step: str, result: dict) -> None:
        """Mark a step finished with its result; a later call for the same step appends a newer result."""
        self._insert(
            "INSERT INTO steps (recorded_s, procedure, step, result) VALUES (?, ?, ?, ?)",
            (time.time(), procedure, step, _json(result, "step result")),
        )

    def step_result(self, procedure: str, step: str) -> dict | None:
        """The latest result of a finished step; None when the step is not finished (redo it)."""
        with self._lock:
            row = (
                self._db()
                .execute(
                    "SELECT result FROM steps WHERE procedure=? AND step=? ORDER BY id DESC LIMIT 1",
                    (procedure, step),
                )
                .fetchone()
            )
        return None if row is None else json.loads(row[0])

    def steps(self) -> pd.DataFrame:
        """Every finish_step record in order (columns id, recorded_s, procedure, step, result)."""
        df = self._frame("SELECT id, recorded_s, procedure, step, result FROM steps ORDER BY id")
        df["result"] = [json.loads(s) for s in df["result"]]
        return df

    def log(self, level: str, message: str, logger: str = "hil", *, time_s: float | None = None) -> None:
        self._insert(
            "INSERT INTO log (recorded_s, level, logger, message) VALUES (?, ?, ?, ?)",
            (time.time() if time_s is None else float(time_s), str(level), str(logger), str(message)),
        )

    def log_lines(self, last: int | None = None) -> pd.DataFrame:
        """The log in order (the `last` lines only when given)."""
        if last is None:
            return self._frame("SELECT id, recorded_s, level, logger, message FROM log ORDER BY id")
        return self._frame(
            "SELECT * FROM (SELECT id, recorded_s, level, logger, message FROM log ORDER BY id DESC LIMIT ?) "
            "ORDER BY id",
            (int(last),),
        )

    def integrity_ok(self) -> bool:
        with self._lock:
            return self._db().execute("PRAGMA integrity_check").fetchone()[0] == "ok"


class Campaign(Protocol):
    """What a campaign store offers (CampaignStore is the reference; hil.data.pg_store keeps it too)."""

    @property
    def path(self) -> str | Path: ...  # what messages print: a file's path, a URL without its password

    created_s: float
    uuid: uuid.UUID

    @property
    def closed(self) -> bool: ...
    def close(self) -> None: ...
    def add_snapshot(self, snapshot: dict) -> None: ...
    def snapshots(self) -> list[dict]: ...
    def record_measurement(self, m: MeasurementRecord) -> int: ...
    def has_measurement(self, procedure: str, step: str, point_id: str) -> bool: ...
    def measurements(
        self, procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame: ...
    def measurement_columns(
        self, columns: Sequence[str], procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame: ...
    def records(self, procedure: str | None = None, step: str | None = None) -> list[MeasurementRecord]: ...
    def point_counts(self) -> pd.DataFrame: ...
    @property
    def started_s(self) -> float: ...
    def last_temperature_c(self) -> float | None: ...
    @property
    def last_timestamp_s(self) -> float | None: ...
    def record_event(
        self,
        kind: str,
        message: str,
        *,
        procedure: str | None = None,
        step: str | None = None,
        point_id: str | None = None,
        data: dict | None = None,
    ) -> None: ...
    def events(self) -> pd.DataFrame: ...
    def record_outcome(self, outcome: OutcomeRecord) -> None: ...
    def outcomes(self) -> list[OutcomeRecord]: ...
    def finish_step(self, procedure: str, step: str, result: dict) -> None: ...
    def step_result(self, procedure: str, step: str) -> dict | None: ...
    def steps(self) -> pd.DataFrame: ...
    def log(self, level: str, message: str, logger: str = "hil", *, time_s: float | None = None) -> None: ...
    def log_lines(self, last: int | None = None) -> pd.DataFrame: ...
    def integrity_ok(self) -> bool: ...
    def record_result(self, result: ResultRecord) -> None: ...
    def results(self) -> list[ResultRecord]: ...
    def __enter__(self) -> Campaign: ...
    def __exit__(self, *exc: object) -> None: ...


def _where(**conditions: str | Sequence[str] | None) -> tuple[str, list[object]]:
    clauses: list[str] = []
    params: list[object] = []
    for column, value in conditions.items():
        if value is None:
            continue
        if isinstance(value, str):
            clauses.append(f"{column} = ?")
            params.append(value)
        else:
            values = list(value)
            clauses.append(f"{column} IN ({', '.join('?' * len(values))})")
            params.extend(values)
    return (" WHERE " + " AND ".join(clauses) if clauses else ""), params


def with_record_objects(df: pd.DataFrame) -> pd.DataFrame:
    """Stored measurement rows (every MEASUREMENT_COLUMNS, JSON as text) with the record's objects: the
    rejected shots as a tuple, extra as a dict and the record's arrays, one per row (either back-end)."""
    df["rejected_shots"] = pd.Series(
        [() if s == "[]" else tuple(json.loads(s)) for s in df["rejected_shots"]],
        index=df.index,
        dtype=object,
    )
    df["extra"] = pd.Series(
        [{} if s == "{}" else json.loads(s) for s in df["extra"]], index=df.index, dtype=object
    )
    for name, (columns, shape) in ARRAY_FIELDS.items():  # the record's arrays, one per row
        values = df[list(columns)].to_numpy(float).reshape(len(df), *shape)
        df[name] = pd.Series(list(values), index=df.index, dtype=object)
    return df


def result_from_row(kind: str, summary: str, model: str | None, recorded_s: float) -> ResultRecord:
    """A ResultRecord back from its stored row (either back-end)."""
    return ResultRecord(
        kind, json.loads(summary), None if model is None else json.loads(model), float(recorded_s)
    )


def with_event_objects(df: pd.DataFrame) -> pd.DataFrame:
    """Stored event rows with their data as a dict and an absent procedure, step or point as None (not NaN)."""
    df["data"] = [json.loads(s) for s in df["data"]]
    for col in ("procedure", "step", "point_id"):
        df[col] = pd.Series(
            [v if isinstance(v, str) else None for v in df[col]], index=df.index, dtype=object
        )
    return df


def arm_temperature_c(air_temperature_c: float | None, extra_json: str | None) -> float | None:
    """One measurement's temperature in the order of `ARM_TEMPERATURE_KEYS`, then the air's; None if none."""
    extra = json.loads(extra_json or "{}")
    readings = [extra.get(key) for key in ARM_TEMPERATURE_KEYS] + [air_temperature_c]
    return next((float(v) for v in readings if v is not None and np.isfinite(v)), None)


def record_from_row(row: dict) -> MeasurementRecord:
    """A MeasurementRecord back from one row of `CampaignStore.measurements()`."""

    return MeasurementRecord(
        procedure=row["procedure"],
        step=row["step"],
        point_id=row["point_id"],
        **{name: np.array(row[name], float) for name in ARRAY_FIELDS},
        shots=int(row["shots"]),
        rejected_shots=tuple(row["rejected_shots"]),
        smr=int(row["smr"]),
        location=row["location"],
        temperature_c=row["temperature_c"],
        pressure_hpa=row["pressure_hpa"],
        humidity_pct=row["humidity_pct"],
        timestamp_s=row["timestamp_s"],
        extra=dict(row["extra"]),
    )


class StoreLogHandler(logging.Handler):
    """A logging handler that writes every record into the campaign's log table."""

    def __init__(self, store: Campaign, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.store = store

    def emit(self, record: logging.LogRecord) -> None:
        if self.store.closed:
            return
        try:
            self.store.log(record.levelname, self.format(record), record.name, time_s=record.created)
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


def load_campaign(
    path: str | Path, procedure: str | None = None, step: str | Sequence[str] | None = None
) -> pd.DataFrame:
    """The measurements of a campaign file as a DataFrame (see CampaignStore.measurements)."""
    with CampaignStore(path, create=False) as store:
        return store.measurements(procedure, step)


def campaign_dataset(
    path_or_store: str | Path | CampaignStore | Campaign,
    procedure: str,
    step: str | Sequence[str] | None = None,
) -> pd.DataFrame:
    """The measurements of one procedure (one or several steps) in the hil.data.dataset contract, validated."""
    store: CampaignStore | Campaign
    if isinstance(path_or_store, str | Path):
        store, own = CampaignStore(path_or_store, create=False), True
    else:
        store, own = path_or_store, False
    try:
        needed = Q_COLUMNS + P_COLUMNS + SPREAD_COLUMNS + STD_COLUMNS
        needed += (
            "timestamp_s",
            "temperature_c",
            "smr",
            "pressure_hpa",
            "humidity_pct",
            "shots",
            "point_id",
            "step",
            "extra",
        )
        m = store.measurement_columns(needed, procedure, step)
        started_s = store.started_s
        snapshots = store.snapshots()
        station = _station(snapshots)
        if m.empty:
            counts = store.point_counts()
            have = ", ".join(f"{r.procedure}/{r.step} ({r.points})" for r in counts.itertuples()) or "none"
            wanted = (
                procedure
                if step is None
                else f"{procedure}/{step if isinstance(step, str) else ','.join(step)}"
            )
            raise DatasetError(f"{store.path}: no measurements of {wanted}; the campaign holds: {have}")
    finally:
        if own:
            store.close()
    data: dict[str, object] = {c: m[c].to_numpy(float) for c in Q_COLUMNS}
    for a in _AXES:
        data[f"{a}_mm"] = m[f"{a}_m"].to_numpy(float) * 1000.0
    data["t_s"] = m["timestamp_s"].to_numpy(float) - started_s
    air = m["temperature_c"].to_numpy(float)
    arm, robot = (_extra_temperatures(m["extra"], key) for key in ARM_TEMPERATURE_KEYS)
    # The arm's own temperature where a sensor read every point: the tracker's object probe on the arm, else
    # the robot's joint sensors; else the air's.
    if np.all(np.isfinite(arm)):
        temperature = arm
    elif np.all(np.isfinite(robot)):
        temperature = robot
    else:
        temperature = air
    if np.any(np.isfinite(arm)) and not np.all(np.isfinite(arm)):
        warnings.warn(
            f"{store.path}: the object probe read only {int(np.sum(np.isfinite(arm)))} of {len(arm)} "
            f"measurements of {procedure}; temperature_c is the "
            + ("robot's (its joint sensors)" if temperature is robot else "air temperature"),
            stacklevel=2,
        )
    missing = int(np.sum(~np.isfinite(temperature)))
    if missing == 0:
        data["temperature_c"] = temperature
    elif missing < len(temperature):  # all missing: no sensor, nothing to say
        warnings.warn(
            f"{store.path}: temperature_c missing in {missing} of {len(temperature)} measurements of "
            f"{procedure}; the dataset leaves the column out",
            stacklevel=2,
        )
    if np.all(np.isfinite(air)):
        data["air_temperature_c"] = air
    if np.all(np.isfinite(robot)):
        data["robot_temperature_c"] = robot
    data["smr"] = m["smr"].to_numpy(int)
    for kind in ("spread", "std"):
        for a in _AXES:
            data[f"{kind}_{a}_mm"] = m[f"{kind}_{a}_m"].to_numpy(float) * 1000.0
    data["pressure_hpa"] = m["pressure_hpa"].to_numpy(float)
    data["humidity_pct"] = m["humidity_pct"].to_numpy(float)
    data["shots_count"] = m["shots"].to_numpy(int)
    data["point_id"] = m["point_id"].astype(str).to_numpy()
    data["step_id"] = m["step"].astype(str).to_numpy()
    out = validate_dataset(pd.DataFrame(data), source=f"{store.path} ({procedure})")
    out.attrs["source"] = f"{store.path} ({procedure}" + (f"/{step}" if isinstance(step, str) else "") + ")"
    out.attrs["station"] = station
    recorded = [s["joint_convention"] for s in snapshots if isinstance(s, dict) and "joint_convention" in s]
    if recorded:  # the robot's readings as the session recorded them (hil.geometry.coupling)
        out.attrs["joint_convention"] = recorded[-1]
    return out


def _station(snapshots: list[dict]) -> dict:
    """The instruments of the campaign's last session start, as a report names them (robot model and
    controller version, tracker type and serial); empty when the campaign recorded none."""
    if not snapshots:
        return {}
    last = snapshots[-1]

    def section(parent: object, key: str) -> dict:  # a snapshot written by an older or another session
        value = parent.get(key) if isinstance(parent, dict) else None
        return value if isinstance(value, dict) else {}

    cell, station = section(last, "cell"), section(last, "station")
    robot = {**section(cell, "robot"), "controller_version": station.get("robot_controller_version")}
    tracker = {**section(cell, "tracker"), **section(station, "tracker")}
    wanted = {
        "robot": [robot.get(k) for k in ("model", "controller_version")],
        "tracker": [tracker.get(k) for k in ("name", "serial_number")],
    }
    return {k: " ".join(str(v) for v in values if v) for k, values in wanted.items() if any(values)}


def _extra_temperatures(extra: pd.Series, key: str) -> np.ndarray:
    """A temperature per measurement from the stored extra JSON (the object probe's `object_temperature_c`,
    the robot's `robot_temperature_c`); NaN where none."""
    return np.array([json.loads(e).get(key, np.nan) for e in extra], dtype=float)


def export_csv(
    path: str | Path | Campaign,
    out: str | Path,
    procedure: str,
    step: str | Sequence[str] | None = None,
) -> int:
    """Write one procedure's measurements as a dataset CSV; returns the number of rows written."""
    return _export(path, procedure, step, lambda df: write_dataset(df, out))


def export_parquet(
    path: str | Path | Campaign,
    out: str | Path,
    procedure: str,
    step: str | Sequence[str] | None = None,
) -> int:
    """Write one procedure's measurements (dataset columns) as a Parquet file; returns rows written."""
    return _export(path, procedure, step, lambda df: _without_attrs(df).to_parquet(out, index=False))


def _without_attrs(df: pd.DataFrame) -> pd.DataFrame:
    """The frame without its in-memory annotations (data row numbers, dropped duplicates): pandas writes attrs
    into a Parquet file's metadata as JSON, and they describe this reading, not the campaign."""
    plain = df.copy(deep=False)
    plain.attrs = {}
    return plain


def _export(
    path: str | Path | Campaign,
    procedure: str,
    step: str | Sequence[str] | None,
    write: Callable[[pd.DataFrame], object],
) -> int:
    """Read one procedure's measurements in the dataset contract, write them, count them."""
    df = campaign_dataset(path, procedure, step)
    write(df)
    return len(df)
