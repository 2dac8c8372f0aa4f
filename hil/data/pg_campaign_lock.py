"""Who drives a campaign in the shared store: one holder at a time, as for a campaign file (hil.data.campaign_lock).

The holder keeps a PostgreSQL advisory lock on the campaign's key for as long as it may move the robot, on a
connection of its own whose application name says who it is. A second holder is refused with that name, read
from the server's own view of its locks (pg_locks joined with pg_stat_activity). The server releases the lock
when the holder's connection ends, however it ends: a killed run or a lost network leaves no stale lock.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import psycopg

from hil.data.campaign_lock import CampaignBusyError, Holder
from hil.data.pg_store import connect
from hil.data.pg_url import CampaignURL

APPLICATION_NAME_BYTES = 63  # the server keeps this much of a connection's application name


def lock_key(campaign: str) -> int:
    """The advisory lock's key of a campaign label (a signed 64-bit number, as the server takes it)."""
    digest = hashlib.sha256(f"hil campaign {campaign}".encode()).digest()
    return int.from_bytes(digest[:8], "big", signed=True)


def holder_name(holder: Holder) -> str:
    """What the holder's connection calls itself (kept to the server's 63 bytes)."""
    since = time.strftime("%Y-%m-%d %H:%M", time.localtime(holder.since_s))
    text = f"{holder.what}, process {holder.pid} on {holder.host} since {since}"
    return text.encode()[:APPLICATION_NAME_BYTES].decode(errors="ignore")


class PgCampaignLock:
    """`with PgCampaignLock(url, holder):` the shared campaign is this run's until the block ends; a second
    holder anywhere is refused with CampaignBusyError naming the first."""

    def __init__(self, url: str, holder: Holder, password_file: str | Path | None = None) -> None:
        self.url = CampaignURL.parse(url, password_file)
        self.holder = holder
        self.key = lock_key(self.url.campaign)
        self._conn: psycopg.Connection | None = None

    def __enter__(self) -> PgCampaignLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def acquire(self) -> None:
        conn = connect(self.url)
        try:
            conn.execute("SELECT set_config('application_name', %s, false)", (holder_name(self.holder),))
            row = conn.execute("SELECT pg_try_advisory_lock(%s)", (self.key,)).fetchone()
            if row is None or not row[0]:
                raise CampaignBusyError(f"campaign {self.url.campaign} is driven by {self._current(conn)}")
        except BaseException:
            conn.close()
            raise
        self._conn = conn

    def _current(self, conn: psycopg.Connection) -> str:
        """The holder's name as its connection gives it (the key split as the server shows it in pg_locks)."""
        unsigned = self.key & 0xFFFFFFFFFFFFFFFF
        row = conn.execute(
            "SELECT a.application_name FROM pg_locks l JOIN pg_stat_activity a ON a.pid = l.pid "
            "WHERE l.locktype = 'advisory' AND l.granted AND l.classid = %s AND l.objid = %s AND l.objsubid = 1",
            (unsigned >> 32, unsigned & 0xFFFFFFFF),
        ).fetchone()
        return "another run (its connection did not say who)" if row is None or not row[0] else str(row[0])

    def release(self) -> None:
        """Closing the connection releases the lock."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
