"""The result store: measurements and schedules in one SQLite file.

A measurement goes ``queued -> running -> done | failed``, or ``queued | running -> cancelled``.
It keeps its request, progress (0..1 and a message), the result JSON, the failure reason and the
paths of its raw MCAP log and its cloud (PLY). Everything survives a restart: at start-up the
job runner marks a measurement left ``running`` by a process that died ``failed``
(:meth:`Store.fail_interrupted`, with what is left of its raw log and ``raw_truncated``; the rig's
state after the crash is unknown, so the sweep is not silently resumed), while ``queued`` ones
stay queued and the job runner picks them up again in order.

The connection is shared by the threads of one process behind a lock; the file uses SQLite's
write-ahead log so readers never wait for a writer. :attr:`Store.version` tells readers when
something they cached may be stale.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from service.errors import ServiceError

State = Literal["queued", "running", "done", "failed", "cancelled"]
STATES: tuple[str, ...] = ("queued", "running", "done", "failed", "cancelled")
FINAL_STATES = frozenset({"done", "failed", "cancelled"})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS measurements (
    id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    state TEXT NOT NULL,
    request TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    result TEXT,
    error TEXT,
    raw_path TEXT,
    cloud_path TEXT,
    schedule_id TEXT,
    raw_truncated INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS measurements_state ON measurements(state, seq);
CREATE TABLE IF NOT EXISTS schedules (
    id TEXT PRIMARY KEY,
    created_at REAL NOT NULL,
    name TEXT NOT NULL DEFAULT '',
    cron TEXT,
    interval_s REAL,
    template TEXT NOT NULL,
    enabled INTEGER NOT NULL DEFAULT 1,
    next_run REAL,
    last_run REAL,
    last_measurement_id TEXT
);
"""


#: The failure reason of a measurement a dead process left running (the job runner adds what it
#: recovered of the raw log).
INTERRUPTED = "the service process died during this measurement (found at restart); it was not resumed"


class StoreError(ServiceError):
    """The store was asked for something that does not exist or is not allowed."""


class NotFound(StoreError):
    pass


@dataclass(frozen=True)
class Measurement:
    id: str
    created_at: float
    started_at: float | None
    finished_at: float | None
    state: str
    request: dict[str, Any]
    progress: float
    message: str
    result: dict[str, Any] | None
    error: str | None
    raw_path: str | None
    cloud_path: str | None
    schedule_id: str | None
    raw_truncated: bool = False  # the raw log was rebuilt from a file cut short (the process died)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Schedule:
    id: str
    created_at: float
    name: str
    cron: str | None
    interval_s: float | None
    template: dict[str, Any]
    enabled: bool
    next_run: float | None
    last_run: float | None
    last_measurement_id: str | None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _new_id() -> str:
    return uuid.uuid4().hex[:16]


class Store:
    """SQLite-backed store of measurements and schedules."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
            self._db.row_factory = sqlite3.Row
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
            columns = {r[1] for r in self._db.execute("PRAGMA table_info(measurements)")}
            if "raw_truncated" not in columns:  # a store written before the column existed
                self._db.execute("ALTER TABLE measurements ADD COLUMN raw_truncated INTEGER NOT NULL DEFAULT 0")
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open result store {path}: {exc}") from None
        self._lock = threading.RLock()
        self._writes = 0

    @property
    def version(self) -> tuple[int, int]:
        """Changes whenever the stored data may have changed: this store's committed writes and
        SQLite's ``data_version`` (which moves when another connection to the file commits).
        Readers cache what they built from the store under the version they read *before* building
        it (the API caches its serialised responses this way)."""
        with self._lock:
            return self._writes, int(self._db.execute("PRAGMA data_version").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")
            self._writes += 1

    # -- measurements ---------------------------------------------------------------------
    def create_measurement(self, request: dict[str, Any], schedule_id: str | None = None) -> Measurement:
        mid = _new_id()
        with self._tx() as db:
            seq = db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM measurements").fetchone()[0]
            db.execute(
                "INSERT INTO measurements (id, seq, created_at, state, request, schedule_id) VALUES (?, ?, ?, ?, ?, ?)",
                (mid, seq, time.time(), "queued", json.dumps(request), schedule_id),
            )
        return self.get(mid)

    def get(self, mid: str) -> Measurement:
        with self._lock:
            row = self._db.execute("SELECT * FROM measurements WHERE id = ?", (mid,)).fetchone()
        if row is None:
            raise NotFound(f"no measurement {mid!r}")
        return _measurement(row)

    def list_measurements(self, state: str | None = None, limit: int = 100, offset: int = 0) -> list[Measurement]:
        """Newest first."""
        if state is not None and state not in STATES:
            raise StoreError(f"unknown state {state!r} (expected one of {', '.join(STATES)})")
        q = "SELECT * FROM measurements"
        args: list[Any] = []
        if state is not None:
            q += " WHERE state = ?"
            args.append(state)
        q += " ORDER BY seq DESC LIMIT ? OFFSET ?"
        args += [limit, offset]
        with self._lock:
            rows = self._db.execute(q, args).fetchall()
        return [_measurement(r) for r in rows]

    def queued(self) -> list[Measurement]:
        """Queued measurements, oldest first (the order they run in)."""
        with self._lock:
            rows = self._db.execute("SELECT * FROM measurements WHERE state = 'queued' ORDER BY seq").fetchall()
        return [_measurement(r) for r in rows]

    def count_by_state(self) -> dict[str, int]:
        with self._lock:
            rows = self._db.execute("SELECT state, COUNT(*) FROM measurements GROUP BY state").fetchall()
        out = dict.fromkeys(STATES, 0)
        out.update({r[0]: r[1] for r in rows})
        return out

    def _transition(self, mid: str, allowed: tuple[str, ...], sets: str, args: tuple[Any, ...]) -> Measurement:
        with self._tx() as db:
            row = db.execute("SELECT state FROM measurements WHERE id = ?", (mid,)).fetchone()
            if row is None:
                raise NotFound(f"no measurement {mid!r}")
            if row[0] not in allowed:
                raise StoreError(f"measurement {mid} is {row[0]}")
            db.execute(f"UPDATE measurements SET {sets} WHERE id = ?", (*args, mid))
        return self.get(mid)

    def start(self, mid: str) -> Measurement:
        return self._transition(
            mid, ("queued",), "state = 'running', started_at = ?, progress = 0, message = ?", (time.time(), "starting")
        )

    def set_progress(self, mid: str, progress: float, message: str = "") -> None:
        with self._tx() as db:
            db.execute(
                "UPDATE measurements SET progress = ?, message = ? WHERE id = ? AND state = 'running'",
                (min(max(float(progress), 0.0), 1.0), message, mid),
            )

    def set_paths(
        self, mid: str, raw_path: str | None = None, cloud_path: str | None = None, raw_truncated: bool = False
    ) -> None:
        with self._tx() as db:
            if raw_path is not None:
                db.execute(
                    "UPDATE measurements SET raw_path = ?, raw_truncated = ? WHERE id = ?",
                    (raw_path, int(raw_truncated), mid),
                )
            if cloud_path is not None:
                db.execute("UPDATE measurements SET cloud_path = ? WHERE id = ?", (cloud_path, mid))

    def finish(self, mid: str, result: dict[str, Any]) -> Measurement:
        return self._transition(
            mid,
            ("running",),
            "state = 'done', finished_at = ?, progress = 1, message = 'done', result = ?",
            (time.time(), json.dumps(result)),
        )

    def fail(self, mid: str, reason: str, result: dict[str, Any] | None = None) -> Measurement:
        return self._transition(
            mid,
            ("queued", "running"),
            "state = 'failed', finished_at = ?, message = 'failed', error = ?, result = ?",
            (time.time(), reason, json.dumps(result) if result is not None else None),
        )

    def cancel(self, mid: str, reason: str = "cancelled by request") -> Measurement:
        return self._transition(
            mid,
            ("queued", "running"),
            "state = 'cancelled', finished_at = ?, message = 'cancelled', error = ?",
            (time.time(), reason),
        )

    def interrupted(self) -> list[str]:
        """Ids of the measurements left ``running`` (by a process that died, when read at start-up)."""
        with self._lock:
            return [r[0] for r in self._db.execute("SELECT id FROM measurements WHERE state = 'running' ORDER BY seq")]

    def fail_interrupted(
        self,
        mid: str,
        reason: str = INTERRUPTED,
        raw_path: str | None = None,
        cloud_path: str | None = None,
        raw_truncated: bool = False,
    ) -> Measurement:
        """Mark one measurement a dead process left ``running`` as failed, with what is left of its data."""
        return self._transition(
            mid,
            ("running",),
            "state = 'failed', finished_at = ?, message = 'failed', error = ?, "
            "raw_path = COALESCE(?, raw_path), cloud_path = COALESCE(?, cloud_path), raw_truncated = ?",
            (time.time(), reason, raw_path, cloud_path, int(raw_truncated)),
        )

    def recover_interrupted(self) -> list[str]:
        """Mark measurements a dead process left ``running`` as failed; return their ids (the job
        runner does this per measurement with :meth:`fail_interrupted`, after recovering the raw log)."""
        ids = self.interrupted()
        for mid in ids:
            self.fail_interrupted(mid)
        return ids

    # -- schedules ------------------------------------------------------------------------
    def add_schedule(
        self,
        template: dict[str, Any],
        cron: str | None = None,
        interval_s: float | None = None,
        next_run: float | None = None,
        name: str = "",
    ) -> Schedule:
        if (cron is None) == (interval_s is None):
            raise StoreError("a schedule needs exactly one of cron or interval_s")
        sid = _new_id()
        with self._tx() as db:
            db.execute(
                "INSERT INTO schedules (id, created_at, name, cron, interval_s, template, next_run) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (sid, time.time(), name, cron, interval_s, json.dumps(template), next_run),
            )
        return self.get_schedule(sid)

    def get_schedule(self, sid: str) -> Schedule:
        with self._lock:
            row = self._db.execute("SELECT * FROM schedules WHERE id = ?", (sid,)).fetchone()
        if row is None:
            raise NotFound(f"no schedule {sid!r}")
        return _schedule(row)

    def list_schedules(self) -> list[Schedule]:
        with self._lock:
            rows = self._db.execute("SELECT * FROM schedules ORDER BY created_at").fetchall()
        return [_schedule(r) for r in rows]

    def delete_schedule(self, sid: str) -> None:
        with self._tx() as db:
            cur = db.execute("DELETE FROM schedules WHERE id = ?", (sid,))
            if cur.rowcount == 0:
                raise NotFound(f"no schedule {sid!r}")

    def mark_schedule_run(self, sid: str, last_run: float, next_run: float | None, measurement_id: str | None) -> None:
        with self._tx() as db:
            db.execute(
                "UPDATE schedules SET last_run = ?, next_run = ?, last_measurement_id = ? WHERE id = ?",
                (last_run, next_run, measurement_id, sid),
            )


def _measurement(row: sqlite3.Row) -> Measurement:
    return Measurement(
        id=row["id"],
        created_at=row["created_at"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        state=row["state"],
        request=json.loads(row["request"]),
        progress=row["progress"],
        message=row["message"],
        result=json.loads(row["result"]) if row["result"] is not None else None,
        error=row["error"],
        raw_path=row["raw_path"],
        cloud_path=row["cloud_path"],
        schedule_id=row["schedule_id"],
        raw_truncated=bool(row["raw_truncated"]),
    )


def _schedule(row: sqlite3.Row) -> Schedule:
    return Schedule(
        id=row["id"],
        created_at=row["created_at"],
        name=row["name"],
        cron=row["cron"],
        interval_s=row["interval_s"],
        template=json.loads(row["template"]),
        enabled=bool(row["enabled"]),
        next_run=row["next_run"],
        last_run=row["last_run"],
        last_measurement_id=row["last_measurement_id"],
    )
