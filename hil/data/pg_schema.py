"""The shared campaign store's schema, versioned with Alembic: `upgrade` takes a database to the newest
revision (hil/data/pg_migrations/versions), and does nothing when it is there already.

Alembic runs on the connection the store made (its SQLAlchemy engine wraps that psycopg connection), inside one
transaction that first takes an advisory lock: two cells opening a fresh database at once migrate it once.
A database migrated by a newer hil (a revision this one does not know) is refused, never touched.
"""

from __future__ import annotations

from pathlib import Path

import psycopg

MIGRATIONS = Path(__file__).with_name("pg_migrations")
# The newest revision in MIGRATIONS (a test holds the two together): a database already there is opened
# without loading Alembic and SQLAlchemy (half a second of every cell's start).
HEAD_REVISION = "0002"
# pg_advisory_xact_lock key of the schema upgrade: "hilS" as a 32-bit number
_UPGRADE_LOCK = 0x68696C53


class NewerSchemaError(RuntimeError):
    """The database was migrated by a newer hil."""


def head_revision() -> str:
    """The newest revision this hil knows."""
    script = _script_directory()
    head = script.get_current_head()
    assert head is not None
    return head


def _script_directory():
    from alembic.script import ScriptDirectory

    return ScriptDirectory(str(MIGRATIONS))


def current_revision(conn: psycopg.Connection) -> str | None:
    """The database's revision; None when it holds no hil schema yet."""
    exists = conn.execute("SELECT to_regclass('hil_schema_version') IS NOT NULL").fetchone()
    if not exists or not exists[0]:
        return None
    row = conn.execute("SELECT version_num FROM hil_schema_version").fetchone()
    return None if row is None else str(row[0])


def upgrade(connect) -> None:
    """Take the database to the head revision. `connect()` returns a new psycopg connection to it."""
    with connect() as probe:
        revision = current_revision(probe)
    if revision == HEAD_REVISION:
        return
    script = _script_directory()
    if revision is not None and not _known(script, revision):
        raise NewerSchemaError(
            f"the database's campaign schema is at revision {revision}, which this hil does not know "
            f"(it knows up to {script.get_current_head()}): upgrade hil to use it"
        )
    if revision == script.get_current_head():
        return
    from alembic import command
    from alembic.config import Config
    from sqlalchemy import create_engine, text
    from sqlalchemy.pool import NullPool

    def transactional() -> psycopg.Connection:
        # the store's connections commit each statement; the migration must be one transaction, or the
        # advisory lock would end at once and a half-run upgrade could be seen by another cell
        conn = connect()
        conn.autocommit = False
        return conn

    engine = create_engine("postgresql+psycopg://", creator=transactional, poolclass=NullPool)
    try:
        with engine.begin() as connection:
            connection.execute(text(f"SELECT pg_advisory_xact_lock({_UPGRADE_LOCK})"))
            config = Config()
            config.set_main_option("script_location", str(MIGRATIONS))
            config.attributes["connection"] = connection
            command.upgrade(config, "head")
    finally:
        engine.dispose()


def _known(script, revision: str) -> bool:
    from alembic.util import CommandError

    try:
        return script.get_revision(revision) is not None
    except CommandError:
        return False
