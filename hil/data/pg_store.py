"""The shared campaign store: campaigns in a PostgreSQL database, many cells writing at once.

The same contract as the campaign file (hil.data.store.CampaignStore), with the same guarantees:
- every record is committed before its call returns (autocommit: the server has made it durable), so a
  process killed at any moment loses at most the point in flight;
- a resumed campaign asks `has_measurement` and never measures a point twice (UNIQUE on the campaign and the
  point's key makes a duplicate an error);
- recorded rows are never changed or deleted (triggers refuse it);
- two cells write to their own campaigns on their own connections: a row lock at most, never a table lock;
- a lost server is `CampaignStoreLost`, an error that stops the run like a lost instrument (nothing committed is
  lost); the same command resumes once the server is back.
Every campaign has a UUID, given when it is created; the URL names it by its label (or its UUID).
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

import pandas as pd
import psycopg
from psycopg import errors as pg_errors

from hil.data.campaign_copy import COPIED_TABLES, CampaignCopy
from hil.data.pg_errors import CampaignLoginRefused, CampaignStoreLost
from hil.data.pg_schema import NewerSchemaError, upgrade
from hil.data.pg_url import CampaignURL
from hil.data.store import (
    _FLOAT_COLUMNS,
    MEASUREMENT_COLUMNS,
    CampaignError,
    DuplicateMeasurementError,
    MeasurementRecord,
    OutcomeRecord,
    ResultRecord,
    Verdict,
    _json,
    _nullable,
    arm_temperature_c,
    record_from_row,
    result_from_row,
    with_event_objects,
    with_record_objects,
)

T = TypeVar("T")
CONNECT_TIMEOUT_S = 10
# A server that stops answering (a cable pulled, not a refused connection) is given up after this long.
UNANSWERED_TIMEOUT_MS = 15_000


def _login_words(exc: psycopg.OperationalError) -> bool:
    text = str(exc).lower()
    return any(w in text for w in ("password authentication failed", "no password supplied", "role "))


class PgCampaignStore:
    """One campaign in a shared PostgreSQL database: station snapshots, measurements, events, finished steps,
    judged measurements and the log, as a campaign file holds them."""

    def __init__(
        self,
        url: str | CampaignURL,
        *,
        create: bool = True,
        password_file: str | Path | None = None,
        identity: tuple[uuid.UUID, float] | None = None,
    ) -> None:
        """`identity`: the UUID and creation time a new campaign takes (a pushed file's), else a fresh UUID
        and now; with it the campaign is found by its UUID first, under whatever label it was stored."""
        self.url = url if isinstance(url, CampaignURL) else CampaignURL.parse(url, password_file)
        self.path = self.url.shown  # what messages print: the URL without any password
        self._lock = threading.RLock()
        self._lost_error: CampaignStoreLost | None = None
        self._conn: psycopg.Connection | None = self._connect()
        try:
            upgrade(self._connect)
            self.uuid, self.label, self.created_s = self._campaign(create, identity)
        except NewerSchemaError as exc:
            self.close()
            raise CampaignError(f"{self.url.database}: {exc}") from exc
        except psycopg.OperationalError as exc:
            self.close()
            raise self._lost(exc, "opening the campaign") from exc
        except BaseException:
            self.close()
            raise
        self._started_s: float | None = None

    # -- plumbing -------------------------------------------------------------------------------------
    def _connect(self) -> psycopg.Connection:
        return connect(self.url)

    def _lost(self, exc: BaseException, doing: str) -> CampaignStoreLost:
        return lost(self.url, exc, doing)

    def _run(self, doing: str, work: Callable[[psycopg.Connection], T]) -> T:
        """`work` on the connection; a lost server closes the store (the log handler then stays quiet) and
        every later call says the server was lost, as the first did."""
        with self._lock:
            if self._conn is None:
                if self._lost_error is not None:
                    raise self._lost_error
                raise CampaignError(f"campaign store {self.path} is closed")
            try:
                return work(self._conn)
            except (psycopg.OperationalError, psycopg.InterfaceError) as exc:
                self._lost_error = self._lost(exc, doing)
                self.close()
                raise self._lost_error from exc

    def _one(self, sql: str, params: Sequence[object] = ()) -> tuple | None:
        return self._run("reading", lambda c: c.execute(sql, params).fetchone())  # type: ignore[arg-type]

    def _all(self, sql: str, params: Sequence[object] = ()) -> list[tuple]:
        return self._run("reading", lambda c: c.execute(sql, params).fetchall())  # type: ignore[arg-type]

    def _insert(self, sql: str, values: Sequence[object]) -> int:
        row = self._run("recording", lambda c: c.execute(sql + " RETURNING id", values).fetchone())  # type: ignore[arg-type]
        if row is None:
            raise CampaignError(f"campaign store {self.path}: the insert added no row")
        return int(row[0])

    def _frame(self, sql: str, params: Sequence[object] = ()) -> pd.DataFrame:
        def read(conn: psycopg.Connection) -> pd.DataFrame:
            cur = conn.execute(sql, params)  # type: ignore[arg-type]
            columns = [d.name for d in cur.description or ()]
            return pd.DataFrame(cur.fetchall(), columns=columns)

        return self._run("reading", read)

    def _campaign(
        self, create: bool, identity: tuple[uuid.UUID, float] | None
    ) -> tuple[uuid.UUID, str, float]:
        """The campaign the URL names (by label or UUID), created when asked and missing; with `identity`,
        first the campaign of that UUID, and a new one takes it."""
        assert self._conn is not None
        name = self.url.campaign
        by_uuid = _as_uuid(name)
        select = "SELECT uuid, label, created_s FROM campaigns WHERE "
        row = self._conn.execute(select + "uuid = %s", (identity[0],)).fetchone() if identity else None
        if row is None:
            where = "uuid = %s" if by_uuid else "label = %s"
            row = self._conn.execute(select + where, (by_uuid or name,)).fetchone()
            if row is not None and identity is not None:
                raise CampaignError(
                    f"{self.path}: the label {name!r} is taken by another campaign ({row[0]}); "
                    "give this one another ?campaign=LABEL"
                )
        if row is None and create:
            if by_uuid:
                raise CampaignError(
                    f"{self.path}: no campaign has UUID {name}; name a new campaign by a label"
                )
            made, created_s = identity or (uuid.uuid4(), time.time())
            self._conn.execute(
                "INSERT INTO campaigns (uuid, label, created_s) VALUES (%s, %s, %s) ON CONFLICT DO NOTHING",
                (made, name, created_s),
            )  # a second cell creating the same label at once keeps the first one's
            row = self._conn.execute(select + "label = %s", (name,)).fetchone()
            if row is not None and identity is not None and row[0] != identity[0]:
                raise CampaignError(f"{self.path}: the label {name!r} was just taken by another campaign")
        if row is None:
            raise CampaignError(
                f"no campaign {name!r} in {self.url.database}; give the label or UUID of a stored campaign "
                "(hil fleet lists them)"
            )
        return row[0], row[1], float(row[2])

    @property
    def closed(self) -> bool:
        return self._conn is None

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                try:
                    self._conn.close()
                finally:
                    self._conn = None

    def __enter__(self) -> PgCampaignStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- a campaign file copied in (hil campaign push) -------------------------------------------------
    def receive(self, copy: CampaignCopy) -> dict[str, int]:
        """Append what this campaign lacks of the file campaign `copy` (the same UUID), in one transaction:
        the points it does not hold, and of every other table the rows past those it holds (both stores are
        append-only, so a pushed campaign's rows are the file's first rows). Returns the rows added per table:
        all zero when the file was pushed before and has not grown. A campaign recorded in the database
        itself is refused: its rows are not the file's."""
        if copy.uuid != self.uuid:
            raise CampaignError(f"{self.path} is campaign {self.uuid}, the file is {copy.uuid}")
        return self._run("pushing", lambda conn: self._transfer(conn, copy))

    def _transfer(self, conn: psycopg.Connection, copy: CampaignCopy) -> dict[str, int]:
        added: dict[str, int] = {}
        with conn.transaction():
            # one push of a campaign at a time: a row lock (never an UPDATE: the table is append-only)
            conn.execute("SELECT 1 FROM campaigns WHERE uuid = %s FOR UPDATE", (self.uuid,))
            origin = conn.execute(
                "SELECT value FROM campaign_meta WHERE campaign = %s AND key = 'pushed_from'", (self.uuid,)
            ).fetchone()
            held = conn.execute("SELECT count(*) FROM snapshots WHERE campaign = %s", (self.uuid,)).fetchone()
            if origin is None and held is not None and held[0] > 0:
                raise CampaignError(
                    f"{self.path} was recorded in the database, not pushed from a file; push refuses to merge"
                )
            conn.execute(
                "INSERT INTO campaign_meta (campaign, key, value) VALUES (%s, 'pushed_from', %s) "
                "ON CONFLICT DO NOTHING",
                (self.uuid, copy.name),
            )
            for table, columns in COPIED_TABLES.items():
                rows = copy.rows[table]
                if table == "measurements":
                    have = set(
                        conn.execute(
                            "SELECT procedure, step, point_id FROM measurements WHERE campaign = %s",
                            (self.uuid,),
                        ).fetchall()
                    )
                    new = [r for r in rows if tuple(r[:3]) not in have]
                else:
                    count = conn.execute(
                        f"SELECT count(*) FROM {table} WHERE campaign = %s", (self.uuid,)
                    ).fetchone()
                    new = rows[(count[0] if count else 0) :]
                if new:
                    names = ", ".join(f'"{c}"' for c in ("campaign", *columns))
                    with conn.cursor().copy(f"COPY {table} ({names}) FROM STDIN") as sink:
                        for row in new:
                            sink.write_row((self.uuid, *row))
                added[table] = len(new)
        return added

    # -- campaign metadata ----------------------------------------------------------------------------
    def set_meta(self, key: str, value: str) -> bool:
        """Record a campaign fact once (its first value is kept); True when this call recorded it."""
        row = self._run(
            "recording",
            lambda c: c.execute(
                "INSERT INTO campaign_meta (campaign, key, value) VALUES (%s, %s, %s) "
                "ON CONFLICT DO NOTHING RETURNING key",
                (self.uuid, key, value),
            ).fetchone(),
        )
        return row is not None

    def meta(self) -> dict[str, str]:
        return dict(self._all("SELECT key, value FROM campaign_meta WHERE campaign = %s", (self.uuid,)))  # type: ignore[arg-type]

    # -- snapshots ------------------------------------------------------------------------------------
    def add_snapshot(self, snapshot: dict) -> None:
        """Record the station snapshot (cell, robot, tracker, software) of a session start."""
        self._insert(
            "INSERT INTO snapshots (campaign, recorded_s, data) VALUES (%s, %s, %s)",
            (self.uuid, time.time(), _json(snapshot, "snapshot")),
        )

    def snapshots(self) -> list[dict]:
        rows = self._all("SELECT data FROM snapshots WHERE campaign = %s ORDER BY id", (self.uuid,))
        return [json.loads(r[0]) for r in rows]

    # -- measurements ---------------------------------------------------------------------------------
    def record_measurement(self, m: MeasurementRecord) -> int:
        """Append one measurement, committed before return; returns its row id."""
        values: list[object] = [self.uuid, m.procedure, m.step, m.point_id]
        for arr in (m.q_target_rad, m.q_rad, m.T_base_flange, m.p_tracker_m, m.spread_m, m.std_m):
            values.extend(_nullable(float(v)) for v in arr.ravel())
        values += [
            m.shots, json.dumps(list(m.rejected_shots)), m.smr, m.location, _nullable(m.temperature_c),
            _nullable(m.pressure_hpa), _nullable(m.humidity_pct), m.timestamp_s,
            _json(m.extra, "MeasurementRecord.extra"), time.time(),
        ]  # fmt: skip
        columns = ", ".join(f'"{c}"' for c in ("campaign", *MEASUREMENT_COLUMNS))
        marks = ", ".join(["%s"] * (1 + len(MEASUREMENT_COLUMNS)))
        try:
            return self._insert(f"INSERT INTO measurements ({columns}) VALUES ({marks})", values)
        except pg_errors.UniqueViolation as exc:
            raise DuplicateMeasurementError(
                f"point {m.point_id!r} of {m.procedure}/{m.step} is already recorded in {self.path}; "
                "a campaign never measures a point twice (check has_measurement() before measuring)"
            ) from exc

    def has_measurement(self, procedure: str, step: str, point_id: str) -> bool:
        row = self._one(
            "SELECT 1 FROM measurements WHERE campaign = %s AND procedure = %s AND step = %s AND point_id = %s",
            (self.uuid, procedure, step, point_id),
        )
        return row is not None

    def measurements(
        self, procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame:
        """Measurements in recording order, as CampaignStore.measurements gives them."""
        return with_record_objects(self.measurement_columns(MEASUREMENT_COLUMNS, procedure, step))

    def measurement_columns(
        self, columns: Sequence[str], procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame:
        """Only the given stored columns (plus id) of the measurements, in recording order, JSON left as text."""
        unknown = [c for c in columns if c not in MEASUREMENT_COLUMNS]
        if unknown:
            raise ValueError(
                f"unknown measurement column(s) {unknown}; known: {', '.join(MEASUREMENT_COLUMNS)}"
            )
        where, params = self._where(procedure=procedure, step=step)
        names = ", ".join(f'"{c}"' for c in ("id", *columns))
        df = self._frame(f"SELECT {names} FROM measurements{where} ORDER BY id", params)
        for col in columns:
            if col in _FLOAT_COLUMNS:
                df[col] = df[col].astype(float)  # NULL (a NaN when recorded) -> NaN
        return df

    def _where(self, **conditions: str | Sequence[str] | None) -> tuple[str, list[object]]:
        clauses: list[str] = ["campaign = %s"]
        params: list[object] = [self.uuid]
        for column, value in conditions.items():
            if value is None:
                continue
            if isinstance(value, str):
                clauses.append(f"{column} = %s")
                params.append(value)
            else:
                clauses.append(f"{column} = ANY(%s)")
                params.append(list(value))
        return " WHERE " + " AND ".join(clauses), params

    def records(self, procedure: str | None = None, step: str | None = None) -> list[MeasurementRecord]:
        """The measurements as MeasurementRecord objects, in recording order."""
        return [record_from_row(row) for row in self.measurements(procedure, step).to_dict("records")]

    def point_counts(self) -> pd.DataFrame:
        """Number of measurements per (procedure, step), in order of first measurement (as the file's)."""
        return self._frame(
            "SELECT procedure, step, COUNT(*) AS points, MIN(timestamp_s) AS first_s, MAX(timestamp_s) AS last_s, "
            "MIN(recorded_s) AS first_recorded_s, MAX(recorded_s) AS last_recorded_s "
            "FROM measurements WHERE campaign = %s GROUP BY procedure, step ORDER BY MIN(id)",
            (self.uuid,),
        )

    @property
    def started_s(self) -> float:
        """UNIX time of the campaign's first measurement (its creation time until there is one)."""
        if self._started_s is None:
            row = self._one(
                "SELECT timestamp_s FROM measurements WHERE campaign = %s ORDER BY id LIMIT 1", (self.uuid,)
            )
            if row is None:
                return self.created_s
            self._started_s = float(row[0])  # append-only: the first measurement never changes
        return self._started_s

    def last_temperature_c(self) -> float | None:
        """The temperature at the campaign's latest measurement (as CampaignStore.last_temperature_c)."""
        row = self._one(
            "SELECT temperature_c, extra FROM measurements WHERE campaign = %s ORDER BY id DESC LIMIT 1",
            (self.uuid,),
        )
        return None if row is None else arm_temperature_c(row[0], row[1])

    @property
    def last_timestamp_s(self) -> float | None:
        """UNIX time of the campaign's latest measurement; None while it has none."""
        row = self._one("SELECT MAX(timestamp_s) FROM measurements WHERE campaign = %s", (self.uuid,))
        return None if row is None or row[0] is None else float(row[0])

    # -- events, steps, outcomes, log -----------------------------------------------------------------
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
            "INSERT INTO events (campaign, recorded_s, kind, message, procedure, step, point_id, data) "
            "VALUES (%s, %s, %s, %s, %s, %s, %s, %s)",
            (self.uuid, time.time(), str(kind), str(message), procedure, step, point_id, _json(data or {}, "event data")),
        )  # fmt: skip

    def events(self) -> pd.DataFrame:
        return with_event_objects(
            self._frame(
                "SELECT id, recorded_s, kind, message, procedure, step, point_id, data FROM events "
                "WHERE campaign = %s ORDER BY id",
                (self.uuid,),
            )
        )

    def record_outcome(self, outcome: OutcomeRecord) -> None:
        """Append a judged measurement (committed when this returns)."""
        self._insert(
            "INSERT INTO outcomes (campaign, recorded_s, procedure, measurement, value, unit, limit_value, bound, "
            "outcome, note) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s)",
            (
                self.uuid, time.time(), outcome.procedure, outcome.measurement,
                None if outcome.value is None else _nullable(float(outcome.value)), outcome.unit,
                None if outcome.limit_value is None else float(outcome.limit_value), outcome.bound,
                outcome.verdict.value, outcome.note,
            ),
        )  # fmt: skip

    def outcomes(self) -> list[OutcomeRecord]:
        """Every judged measurement in the order recorded."""
        rows = self._all(
            "SELECT procedure, measurement, value, unit, limit_value, bound, outcome, note "
            "FROM outcomes WHERE campaign = %s ORDER BY id",
            (self.uuid,),
        )
        return [
            OutcomeRecord(procedure, measurement, value, unit, limit, bound, Verdict(verdict), note)
            for procedure, measurement, value, unit, limit, bound, verdict, note in rows
        ]

    def record_result(self, result: ResultRecord) -> None:
        """Append an analysis' model and summary (committed when this returns)."""
        self._insert(
            "INSERT INTO results (campaign, recorded_s, kind, summary, model) VALUES (%s, %s, %s, %s, %s)",
            (
                self.uuid,
                time.time(),
                result.kind,
                _json(result.summary, "result summary"),
                None if result.model is None else _json(result.model, "result model"),
            ),
        )

    def results(self) -> list[ResultRecord]:
        """Every recorded analysis result, oldest first."""
        rows = self._all(
            "SELECT kind, summary, model, recorded_s FROM results WHERE campaign = %s ORDER BY id",
            (self.uuid,),
        )
        return [result_from_row(*row) for row in rows]

    def finish_step(self, procedure: str, step: str, result: dict) -> None:
        """Mark a step finished with its result; a later call for the same step appends a newer result."""
        self._insert(
            "INSERT INTO steps (campaign, recorded_s, procedure, step, result) VALUES (%s, %s, %s, %s, %s)",
            (self.uuid, time.time(), procedure, step, _json(result, "step result")),
        )

    def step_result(self, procedure: str, step: str) -> dict | None:
        """The latest result of a finished step; None when the step is not finished (redo it)."""
        row = self._one(
            "SELECT result FROM steps WHERE campaign = %s AND procedure = %s AND step = %s ORDER BY id DESC LIMIT 1",
            (self.uuid, procedure, step),
        )
        return None if row is None else json.loads(row[0])

    def steps(self) -> pd.DataFrame:
        """Every finish_step record in order (columns id, recorded_s, procedure, step, result)."""
        df = self._frame(
            "SELECT id, recorded_s, procedure, step, result FROM steps WHERE campaign = %s ORDER BY id",
            (self.uuid,),
        )
        df["result"] = [json.loads(s) for s in df["result"]]
        return df

    def log(self, level: str, message: str, logger: str = "hil", *, time_s: float | None = None) -> None:
        self._insert(
            "INSERT INTO log (campaign, recorded_s, level, logger, message) VALUES (%s, %s, %s, %s, %s)",
            (
                self.uuid,
                time.time() if time_s is None else float(time_s),
                str(level),
                str(logger),
                str(message),
            ),
        )

    def log_lines(self, last: int | None = None) -> pd.DataFrame:
        """The log in order (the `last` lines only when given)."""
        columns = "id, recorded_s, level, logger, message"
        if last is None:
            return self._frame(f"SELECT {columns} FROM log WHERE campaign = %s ORDER BY id", (self.uuid,))
        return self._frame(
            f"SELECT * FROM (SELECT {columns} FROM log WHERE campaign = %s ORDER BY id DESC LIMIT %s) AS tail "
            "ORDER BY id",
            (self.uuid, int(last)),
        )

    def integrity_ok(self) -> bool:
        """The server keeps the tables consistent; this checks that it answers and still holds the campaign."""
        row = self._one("SELECT count(*) FROM campaigns WHERE uuid = %s", (self.uuid,))
        return row is not None and row[0] == 1


def connect(url: CampaignURL) -> psycopg.Connection:
    """A new autocommit connection to the store's database; a refused login or an unreachable server says so
    in one line (CampaignLoginRefused, CampaignStoreLost)."""
    options: dict[str, object] = {
        "autocommit": True,
        "connect_timeout": CONNECT_TIMEOUT_S,
        "application_name": "hil",
        "keepalives": 1,
        "keepalives_idle": 5,
        "keepalives_interval": 2,
        "keepalives_count": 3,
        "tcp_user_timeout": UNANSWERED_TIMEOUT_MS,
    }
    if url.password_file is not None:
        if not url.password_file.is_file():
            raise CampaignError(f"password file {url.password_file} not found (store.password_file)")
        options["password"] = url.password_file.read_text().strip()
    try:
        return psycopg.connect(url.conninfo, **options)  # type: ignore[arg-type]
    except psycopg.OperationalError as exc:
        if _login_words(exc):
            raise CampaignLoginRefused(
                f"{url.database}: the database refused the login ({_first_line(exc)}); set the right "
                "password in PGPASSWORD or in the cell config's store.password_file, then run again"
            ) from None
        raise lost(url, exc, "connecting") from None


def lost(url: CampaignURL, exc: BaseException, doing: str) -> CampaignStoreLost:
    """The error of a server that did not answer while `doing`."""
    return CampaignStoreLost(
        f"the campaign database {url.database} did not answer while {doing} ({_first_line(exc)}); "
        "everything recorded before is kept"
    )


def query_database(url: CampaignURL, sql: str, params: Sequence[object] = ()) -> pd.DataFrame:
    """One read across the whole store (every campaign: hil fleet), its schema brought up to date first."""
    upgrade(lambda: connect(url))
    with connect(url) as conn:
        try:
            cur = conn.execute(sql, params)  # type: ignore[arg-type]
            return pd.DataFrame(cur.fetchall(), columns=[d.name for d in cur.description or ()])
        except psycopg.OperationalError as exc:
            raise lost(url, exc, "reading") from exc


def _as_uuid(name: str) -> uuid.UUID | None:
    try:
        return uuid.UUID(name)
    except ValueError:
        return None


def _first_line(exc: BaseException) -> str:
    """The driver's message in one line (libpq adds guesses on the lines after it)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__
