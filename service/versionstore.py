"""Result versions: what re-processing an archived raw log gave, beside the original result.

A measurement's original result stays where the rig wrote it (the ``measurements`` table of
:mod:`service.store`, untouched). Each re-evaluation of its raw log (``lrms reprocess``: a new
calibration, a corrected model, a newer software) adds one row to ``result_versions``, numbered
1, 2, ... per measurement, with what made it: the software version, the calibration (its id, or
:data:`LOGGED_CALIBRATION` for the rig model the log itself carries) and the SHA-256 of the raw
log it was computed from. ``(measurement, raw-log hash, calibration, software version)`` is
unique: a result is computed once per such key, and a re-run skips it.

SQLAlchemy Core 2.x on an :class:`sqlalchemy.Engine` (SQLite file or PostgreSQL: the same
tables of :mod:`service.db.schema`, created by migration 0005).
Calibrations given as files are kept in ``reprocess_calibrations`` under their id (the first 16 hex digits of the
SHA-256 of their canonical JSON), so ``lrms reprocess --calibration ID`` can name one again.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import (
    Engine,
    func,
    insert,
    select,
)
from sqlalchemy.exc import IntegrityError, SQLAlchemyError

from service.db import schema
from service.errors import ServiceError

#: The calibration id of a result computed with the rig model logged in the raw log itself.
LOGGED_CALIBRATION = "logged"

result_versions = schema.result_versions
calibrations = schema.reprocess_calibrations


class VersionStoreError(ServiceError):
    """The result-version store could not be read or written, or was asked for something missing."""


@dataclass(frozen=True)
class ResultVersion:
    measurement_id: str
    version: int
    created_at: float
    software_version: str
    calibration_id: str
    raw_sha256: str
    result: dict[str, Any]


def calibration_id(calibration: dict[str, Any]) -> str:
    """The id of a calibration: SHA-256 (first 16 hex digits) of its canonical JSON."""
    text = json.dumps(calibration, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


class VersionStore:
    """``result_versions`` and ``reprocess_calibrations`` on ``engine`` (the result store's, migrated)."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine

    # -- calibrations ---------------------------------------------------------------------
    def put_calibration(self, calibration: dict[str, Any], source: str = "") -> str:
        """Keep ``calibration`` (idempotent); returns its id."""
        cid = calibration_id(calibration)
        with self.engine.begin() as conn:
            if conn.execute(select(calibrations.c.id).where(calibrations.c.id == cid)).first() is None:
                conn.execute(
                    insert(calibrations).values(
                        id=cid, created_at=time.time(), source=source[:1024], calibration=calibration
                    )
                )
        return cid

    def get_calibration(self, ref: str) -> tuple[str, dict[str, Any]]:
        """The calibration whose id is ``ref`` or starts with it (at least 6 hex digits)."""
        if len(ref) < 6:
            raise VersionStoreError(f"calibration id {ref!r}: give at least 6 of its hex digits")
        with self.engine.connect() as conn:
            rows = conn.execute(
                select(calibrations.c.id, calibrations.c.calibration).where(calibrations.c.id.startswith(ref))
            ).all()
        if not rows:
            raise VersionStoreError(f"no calibration {ref!r} in the result-version store (and no such file)")
        if len(rows) > 1:
            raise VersionStoreError(f"calibration id {ref!r} is ambiguous: {', '.join(r[0] for r in rows)}")
        return str(rows[0][0]), dict(rows[0][1])

    # -- versions -------------------------------------------------------------------------
    def done_hashes(
        self, measurement_ids: Sequence[str], calibration: str, software_version: str
    ) -> dict[str, set[str]]:
        """Per measurement: the raw-log hashes already evaluated with this calibration and software."""
        out: dict[str, set[str]] = {}
        rv = result_versions.c
        ids = list(measurement_ids)
        with self.engine.connect() as conn:
            for i in range(0, len(ids), 500):  # bounded IN lists
                rows = conn.execute(
                    select(rv.measurement_id, rv.raw_sha256).where(
                        rv.measurement_id.in_(ids[i : i + 500]),
                        rv.calibration_id == calibration,
                        rv.software_version == software_version,
                    )
                )
                for mid, sha in rows:
                    out.setdefault(str(mid), set()).add(str(sha))
        return out

    def add(
        self,
        measurement_id: str,
        raw_sha256: str,
        calibration: str,
        software_version: str,
        result: dict[str, Any],
    ) -> int | None:
        """Store a new version; returns its number, or None when these inputs are already stored
        (another run got there first)."""
        rv = result_versions.c
        for _ in range(5):  # a concurrent writer may take the next number first
            try:
                with self.engine.begin() as conn:
                    same = conn.execute(
                        select(rv.version).where(
                            rv.measurement_id == measurement_id,
                            rv.raw_sha256 == raw_sha256,
                            rv.calibration_id == calibration,
                            rv.software_version == software_version,
                        )
                    ).first()
                    if same is not None:
                        return None
                    last = conn.execute(
                        select(func.max(rv.version)).where(rv.measurement_id == measurement_id)
                    ).scalar_one()
                    number = int(last or 0) + 1
                    conn.execute(
                        insert(result_versions).values(
                            measurement_id=measurement_id,
                            version=number,
                            created_at=time.time(),
                            software_version=software_version,
                            calibration_id=calibration,
                            raw_sha256=raw_sha256,
                            result=result,
                        )
                    )
                return number
            except IntegrityError:
                continue
            except SQLAlchemyError as exc:
                raise VersionStoreError(f"cannot store a result version of {measurement_id}: {exc}") from None
        raise VersionStoreError(f"cannot number a result version of {measurement_id} (concurrent writers)")

    def versions(self, measurement_ids: Iterable[str] | None = None) -> list[ResultVersion]:
        """Every stored version (of ``measurement_ids`` when given), by measurement and number."""
        rv = result_versions.c
        q = select(result_versions).order_by(rv.measurement_id, rv.version)
        rows: list[Any] = []
        with self.engine.connect() as conn:
            if measurement_ids is None:
                rows = list(conn.execute(q))
            else:
                ids = list(measurement_ids)
                for i in range(0, len(ids), 500):
                    rows += list(conn.execute(q.where(rv.measurement_id.in_(ids[i : i + 500]))))
        return [
            ResultVersion(
                measurement_id=r.measurement_id,
                version=r.version,
                created_at=r.created_at,
                software_version=r.software_version,
                calibration_id=r.calibration_id,
                raw_sha256=r.raw_sha256,
                result=r.result,
            )
            for r in sorted(rows, key=lambda r: (r.measurement_id, r.version))
        ]
