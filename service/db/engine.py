"""Engines for a storage URL: ``sqlite:///PATH`` (embedded, the default) or ``postgresql://...``.

SQLite: write-ahead log (readers never wait for the writer), foreign keys on, a busy timeout so a
writer waits for another process's write instead of failing, and transactions begun by hand: a
write (a connection with the :data:`WRITE` execution option) begins ``BEGIN IMMEDIATE``, so two
writers never deadlock upgrading read locks; a read is not wrapped in a transaction (each of the
store's reads is one statement, consistent by itself).

PostgreSQL goes through psycopg 3 (``postgresql://`` is read as ``postgresql+psycopg://``); the
password, when there is one, best comes from ``PGPASSWORD`` or ``~/.pgpass`` rather than the URL.
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError
from sqlalchemy.pool import StaticPool

from service.errors import ServiceError

#: How long (s) a SQLite writer waits for another one before giving up.
SQLITE_BUSY_TIMEOUT_S = 30.0
#: Execution option of a connection that writes: SQLite begins its transactions IMMEDIATE.
WRITE = "lrms_write"


class DatabaseError(ServiceError):
    """The storage URL is not usable (malformed, unsupported backend, cannot connect)."""


def sqlite_url(path: str | Path) -> str:
    """The URL of a SQLite file (``:memory:`` for a private in-memory database)."""
    if str(path) == ":memory:":
        return "sqlite://"
    return f"sqlite:///{Path(path)}"


def parse_url(url: str) -> URL:
    """``url`` parsed, with the driver made explicit: psycopg 3 for PostgreSQL, pysqlite for SQLite."""
    try:
        u = make_url(url)
    except ArgumentError as exc:
        raise DatabaseError(f"storage url {url!r} is not a database URL: {exc}") from None
    backend = u.get_backend_name()
    if backend == "postgresql":
        if u.drivername == "postgresql":
            u = u.set(drivername="postgresql+psycopg")
        elif u.drivername != "postgresql+psycopg":
            raise DatabaseError(f"storage url: use postgresql:// (psycopg 3), not {u.drivername}://")
    elif backend == "sqlite":
        if u.drivername not in ("sqlite", "sqlite+pysqlite"):
            raise DatabaseError(f"storage url: use sqlite:///PATH, not {u.drivername}://")
    else:
        raise DatabaseError(f"storage url {shown(url)}: unsupported database {backend!r} (sqlite or postgresql)")
    return u


def shown(url: str | URL) -> str:
    """``url`` for logs and messages: the password masked."""
    try:
        return (make_url(url) if isinstance(url, str) else url).render_as_string(hide_password=True)
    except ArgumentError:
        return "(malformed URL)"


def create(url: str) -> Engine:
    """An engine for ``url`` (see the module's doc for the SQLite settings)."""
    u = parse_url(url)
    if u.get_backend_name() == "sqlite":
        return _sqlite(u)
    return create_engine(u, pool_pre_ping=True, pool_size=5, max_overflow=5)


def _sqlite(u: URL) -> Engine:
    memory = u.database in (None, "", ":memory:")
    if not memory:
        assert u.database is not None
        Path(u.database).parent.mkdir(parents=True, exist_ok=True)
    kwargs: dict[str, Any] = {"connect_args": {"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_S}}
    if memory:  # one connection, or every checkout would see its own empty database
        kwargs["poolclass"] = StaticPool
    engine = create_engine(u, **kwargs)

    def _set_wal(cur: sqlite3.Cursor) -> None:
        # switching a new file to WAL needs it unlocked for a moment, and SQLite answers "database is locked"
        # at once (no busy handler) while another process is creating or migrating it: retry, as long as
        # a busy writer would be waited for
        deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_S
        while True:
            try:
                cur.execute("PRAGMA journal_mode=WAL")
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.02)

    @event.listens_for(engine, "connect")
    def _connect(dbapi_conn: sqlite3.Connection, record: Any) -> None:
        dbapi_conn.isolation_level = None  # the driver's own BEGIN off: ours below
        cur = dbapi_conn.cursor()
        try:
            if not memory:
                _set_wal(cur)
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute(f"PRAGMA busy_timeout={int(SQLITE_BUSY_TIMEOUT_S * 1000)}")
        finally:
            cur.close()

    @event.listens_for(engine, "begin")
    def _begin(conn: Any) -> None:
        # a read runs in autocommit (one statement is its own consistent snapshot; no BEGIN to pay)
        if conn.get_execution_options().get(WRITE):
            conn.exec_driver_sql("BEGIN IMMEDIATE")

    return engine
