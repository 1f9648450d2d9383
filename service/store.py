"""The result store: measurements and schedules, in SQLite (embedded, the default) or PostgreSQL.

A measurement goes ``queued -> running -> done | failed``, or ``queued | running -> cancelled``.
It keeps its request, progress (0..1 and a message), the result JSON, the failure reason and the
paths of its raw MCAP log and its cloud (PLY). Everything survives a restart: at start-up the
job runner marks a measurement left ``running`` by a process that died ``failed``
(:meth:`Store.fail_interrupted`, with what is left of its raw log and ``raw_truncated``; the rig's
state after the crash is unknown, so the sweep is not silently resumed), while ``queued`` ones
stay queued and the job runner picks them up again in order.

The store opens a storage URL (``[storage] url``: ``sqlite:///PATH`` or ``postgresql://...``; a
plain path is a SQLite file) with SQLAlchemy Core (:mod:`service.db`), and brings its schema to the
newest migration first. Every row carries the rig id of the store that made it, so the services of
many rigs share one database: a store's queue, running measurements, counts and schedules are its
own rig's; reads of single rows and the measurement list see every rig (the list filters by rig on
request); a store changes only its own rig's rows. Writes are serialised over the whole database
(each write transaction first increments the one row of ``store_version``), so two services never
lose each other's updates. :attr:`Store.version` tells readers when something they cached may be
stale; :attr:`Store.engine` is there for other modules' tables in the same database.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from sqlalchemy import Connection, Engine, RowMapping, Select, bindparam, func, insert, select, update
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.pool import PoolProxiedConnection

from service.db import check_rig_id, default_rig_id, migrate
from service.db import engine as db_engine
from service.db.schema import measurements as M
from service.db.schema import schedules as S
from service.db.schema import store_version
from service.errors import ServiceError

State = Literal["queued", "running", "done", "failed", "cancelled"]
STATES: tuple[str, ...] = ("queued", "running", "done", "failed", "cancelled")
FINAL_STATES = frozenset({"done", "failed", "cancelled"})


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
    rig_id: str = ""  # the rig whose service made it

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
    rig_id: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# statements run per request or per job-runner turn, built once
_GET = select(M).where(M.c.id == bindparam("mid"))
_QUEUED = select(M).where(M.c.rig_id == bindparam("rig"), M.c.state == "queued").order_by(M.c.seq)
_BUMP = update(store_version).where(store_version.c.id == 1).values(n=store_version.c.n + 1)
_NEXT_SEQ = select(func.coalesce(func.max(M.c.seq), 0) + 1)
_INSERT_M = insert(M)
_STATE_OF = select(M.c.state, M.c.rig_id).where(M.c.id == bindparam("m_id"))
# the columns to set are the parameters' other keys
_UPDATE_M = update(M).where(M.c.id == bindparam("m_id"))
_UPDATE_MINE = update(M).where(M.c.id == bindparam("m_id"), M.c.rig_id == bindparam("m_rig"))
_PROGRESS = update(M).where(M.c.id == bindparam("m_id"), M.c.rig_id == bindparam("m_rig"), M.c.state == "running")


def _new_id() -> str:
    return uuid.uuid4().hex[:16]


def store_url(where: str | Path) -> str:
    """A storage URL for ``where``: a URL as it is, a path as the URL of a SQLite file."""
    if isinstance(where, str) and "://" in where:
        return where
    return db_engine.sqlite_url(where)


class Store:
    """The measurements and schedules of rig ``rig_id`` (default: this host's name) in the database
    at ``url`` (a storage URL or the path of a SQLite file), migrated to the newest schema on opening
    unless ``migrate_schema`` is false."""

    def __init__(self, url: str | Path, rig_id: str | None = None, *, migrate_schema: bool = True) -> None:
        self.url = store_url(url)
        try:
            self.rig_id = check_rig_id(rig_id if rig_id is not None else default_rig_id())
        except ValueError as exc:
            raise StoreError(str(exc)) from None
        try:
            self.engine: Engine = db_engine.create(self.url)
            if migrate_schema:
                migrate.upgrade(self.engine, self.rig_id)
        except db_engine.DatabaseError as exc:
            raise StoreError(str(exc)) from None
        except (SQLAlchemyError, OSError) as exc:
            raise StoreError(f"cannot open result store {db_engine.shown(self.url)}: {exc}") from None
        self._lock = threading.Lock()
        self._writes = 0
        self._poll: PoolProxiedConnection | None = None

    @property
    def version(self) -> tuple[int, int]:
        """Changes whenever the stored data may have changed: this store's committed writes and the
        database's write counter (``store_version``, which every store's write moves, whatever its
        rig or process). Readers cache what they built from the store under the version they read
        *before* building it (the API caches its serialised responses this way).

        Polled per API request, so read on a connection of its own in autocommit, in plain SQL
        (a few microseconds on SQLite instead of a pooled SQLAlchemy round)."""
        with self._lock:
            for attempt in (1, 2):
                if self._poll is None:
                    self._poll = self.engine.raw_connection()
                    if self.engine.dialect.name == "postgresql":
                        self._poll.driver_connection.autocommit = True  # type: ignore[union-attr]
                try:
                    cur = self._poll.cursor()
                    cur.execute("SELECT n FROM store_version WHERE id = 1")
                    row = cur.fetchone()
                    cur.close()
                    if row is None:
                        raise StoreError("the result store has no store_version row (not migrated?)")
                    return self._writes, int(row[0])
                except Exception:  # a connection the server dropped: once more on a new one
                    self._poll.invalidate()
                    self._poll = None
                    if attempt == 2:
                        raise
        raise AssertionError("unreachable")

    def close(self) -> None:
        with self._lock:
            if self._poll is not None:
                self._poll.invalidate()  # closed, not returned to the pool in autocommit
                self._poll = None
        self.engine.dispose()

    @contextmanager
    def _tx(self) -> Iterator[Connection]:
        """A write transaction. Its first statement increments ``store_version``: that takes the
        database's one write lock (PostgreSQL: the row's lock until commit; SQLite: the transaction
        began IMMEDIATE), so what the transaction reads stays true until it commits."""
        with self.engine.connect() as conn:
            conn.execution_options(**{db_engine.WRITE: True})
            with conn.begin():
                conn.execute(_BUMP)
                yield conn
        with self._lock:
            self._writes += 1

    def _rows(self, stmt: Select[Any]) -> list[RowMapping]:
        with self.engine.connect() as conn:
            return list(conn.execute(stmt).mappings())

    # -- measurements ---------------------------------------------------------------------
    def create_measurement(self, request: dict[str, Any], schedule_id: str | None = None) -> Measurement:
        mid = _new_id()
        with self._tx() as db:
            seq = db.execute(_NEXT_SEQ).scalar_one()
            db.execute(
                _INSERT_M,
                {
                    "id": mid,
                    "seq": seq,
                    "created_at": time.time(),
                    "state": "queued",
                    "request": json.dumps(request),
                    "schedule_id": schedule_id,
                    "rig_id": self.rig_id,
                },
            )
        return self.get(mid)

    def get(self, mid: str) -> Measurement:
        """The measurement ``mid`` of any rig."""
        with self.engine.connect() as conn:
            rows = list(conn.execute(_GET, {"mid": mid}).mappings())
        if not rows:
            raise NotFound(f"no measurement {mid!r}")
        return _measurement(rows[0])

    def list_measurements(
        self, state: str | None = None, limit: int = 100, offset: int = 0, rig: str | None = None
    ) -> list[Measurement]:
        """Newest first, of every rig or of rig ``rig``."""
        if state is not None and state not in STATES:
            raise StoreError(f"unknown state {state!r} (expected one of {', '.join(STATES)})")
        q = select(M)
        if state is not None:
            q = q.where(M.c.state == state)
        if rig is not None:
            q = q.where(M.c.rig_id == rig)
        q = q.order_by(M.c.seq.desc()).limit(limit).offset(offset)
        return [_measurement(r) for r in self._rows(q)]

    def queued(self) -> list[Measurement]:
        """This rig's queued measurements, oldest first (the order they run in)."""
        with self.engine.connect() as conn:
            rows = conn.execute(_QUEUED, {"rig": self.rig_id}).mappings()
            return [_measurement(r) for r in rows]

    def count_by_state(self) -> dict[str, int]:
        """This rig's measurements per state."""
        q = select(M.c.state, func.count()).where(M.c.rig_id == self.rig_id).group_by(M.c.state)
        with self.engine.connect() as conn:
            rows = conn.execute(q).all()
        out = dict.fromkeys(STATES, 0)
        out.update({str(r[0]): int(r[1]) for r in rows})
        return out

    def _transition(
        self,
        mid: str,
        allowed: tuple[str, ...],
        values: dict[str, Any],
        also: Callable[[Connection], None] | None = None,
    ) -> Measurement:
        with self._tx() as db:
            row = db.execute(_STATE_OF, {"m_id": mid}).first()
            if row is None:
                raise NotFound(f"no measurement {mid!r}")
            if row.rig_id != self.rig_id:
                raise StoreError(f"measurement {mid} belongs to rig {row.rig_id!r}, not to this one ({self.rig_id!r})")
            if row.state not in allowed:
                raise StoreError(f"measurement {mid} is {row.state}")
            db.execute(_UPDATE_M, {"m_id": mid, **values})
            if also is not None:
                also(db)
        return self.get(mid)

    def start(self, mid: str) -> Measurement:
        return self._transition(
            mid, ("queued",), {"state": "running", "started_at": time.time(), "progress": 0.0, "message": "starting"}
        )

    def set_progress(self, mid: str, progress: float, message: str = "") -> None:
        with self._tx() as db:
            db.execute(
                _PROGRESS,
                {
                    "m_id": mid,
                    "m_rig": self.rig_id,
                    "progress": min(max(float(progress), 0.0), 1.0),
                    "message": message,
                },
            )

    def set_paths(
        self, mid: str, raw_path: str | None = None, cloud_path: str | None = None, raw_truncated: bool = False
    ) -> None:
        values: dict[str, Any] = {}
        if raw_path is not None:
            values.update(raw_path=raw_path, raw_truncated=int(raw_truncated))
        if cloud_path is not None:
            values.update(cloud_path=cloud_path)
        if values:
            with self._tx() as db:
                db.execute(_UPDATE_MINE, {"m_id": mid, "m_rig": self.rig_id, **values})

    def finish(self, mid: str, result: dict[str, Any], also: Callable[[Connection], None] | None = None) -> Measurement:
        """Mark ``mid`` done with ``result``; ``also(conn)``: more writes in the same transaction
        (a calibration sweep's calibration: stored with its job's result, or neither)."""
        return self._transition(
            mid,
            ("running",),
            {
                "state": "done",
                "finished_at": time.time(),
                "progress": 1.0,
                "message": "done",
                "result": json.dumps(result),
            },
            also,
        )

    def fail(self, mid: str, reason: str, result: dict[str, Any] | None = None) -> Measurement:
        return self._transition(
            mid,
            ("queued", "running"),
            {
                "state": "failed",
                "finished_at": time.time(),
                "message": "failed",
                "error": reason,
                "result": json.dumps(result) if result is not None else None,
            },
        )

    def cancel(self, mid: str, reason: str = "cancelled by request") -> Measurement:
        return self._transition(
            mid,
            ("queued", "running"),
            {"state": "cancelled", "finished_at": time.time(), "message": "cancelled", "error": reason},
        )

    def interrupted(self) -> list[str]:
        """Ids of this rig's measurements left ``running`` (by a process that died, when read at start-up)."""
        q = select(M.c.id).where(M.c.rig_id == self.rig_id, M.c.state == "running").order_by(M.c.seq)
        with self.engine.connect() as conn:
            return [str(r[0]) for r in conn.execute(q)]

    def fail_interrupted(
        self,
        mid: str,
        reason: str = INTERRUPTED,
        raw_path: str | None = None,
        cloud_path: str | None = None,
        raw_truncated: bool = False,
    ) -> Measurement:
        """Mark one measurement a dead process left ``running`` as failed, with what is left of its data."""
        values: dict[str, Any] = {
            "state": "failed",
            "finished_at": time.time(),
            "message": "failed",
            "error": reason,
            "raw_truncated": int(raw_truncated),
        }
        if raw_path is not None:
            values["raw_path"] = raw_path
        if cloud_path is not None:
            values["cloud_path"] = cloud_path
        return self._transition(mid, ("running",), values)

    def recover_interrupted(self) -> list[str]:
        """Mark this rig's measurements a dead process left ``running`` as failed; return their ids
        (the job runner does this per measurement with :meth:`fail_interrupted`, after recovering
        the raw log)."""
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
                insert(S).values(
                    id=sid,
                    created_at=time.time(),
                    name=name,
                    cron=cron,
                    interval_s=interval_s,
                    template=json.dumps(template),
                    next_run=next_run,
                    rig_id=self.rig_id,
                )
            )
        return self.get_schedule(sid)

    def get_schedule(self, sid: str) -> Schedule:
        """The schedule ``sid`` of any rig."""
        rows = self._rows(select(S).where(S.c.id == sid))
        if not rows:
            raise NotFound(f"no schedule {sid!r}")
        return _schedule(rows[0])

    def list_schedules(self, rig: str | None = None) -> list[Schedule]:
        """Oldest first, of every rig or of rig ``rig`` (the scheduler runs its own rig's)."""
        q = select(S)
        if rig is not None:
            q = q.where(S.c.rig_id == rig)
        return [_schedule(r) for r in self._rows(q.order_by(S.c.created_at))]

    def delete_schedule(self, sid: str) -> None:
        with self._tx() as db:
            row = db.execute(select(S.c.rig_id).where(S.c.id == sid)).first()
            if row is None:
                raise NotFound(f"no schedule {sid!r}")
            if row.rig_id != self.rig_id:
                raise StoreError(f"schedule {sid} belongs to rig {row.rig_id!r}, not to this one ({self.rig_id!r})")
            db.execute(S.delete().where(S.c.id == sid))

    def mark_schedule_run(self, sid: str, last_run: float, next_run: float | None, measurement_id: str | None) -> None:
        with self._tx() as db:
            db.execute(
                update(S)
                .where(S.c.id == sid, S.c.rig_id == self.rig_id)
                .values(last_run=last_run, next_run=next_run, last_measurement_id=measurement_id)
            )

    def count_schedule_measurements(self, sid: str) -> int:
        """How many measurements schedule ``sid`` has queued (every state)."""
        rows = self._rows(select(func.count().label("n")).select_from(M).where(M.c.schedule_id == sid))
        return int(rows[0]["n"])


def _measurement(row: RowMapping) -> Measurement:
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
        rig_id=row["rig_id"],
    )


def _schedule(row: RowMapping) -> Schedule:
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
        rig_id=row["rig_id"],
    )
