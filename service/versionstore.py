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
SHA-256 of their canonical JSON), so ``lrms reprocess --calibration ID`` can name one again; an id
may also name a calibration of the service's calibration store (the ``calibrations`` table,
:mod:`service.calstore`). Writes are write transactions of the database
(:func:`service.db.tx.write_transaction`): numbering a new version is safe with several
``lrms reprocess`` clients and the rigs writing at once.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy import (
    Engine,
    func,
    insert,
    select,
)
from sqlalchemy.exc import IntegrityError, SQLAlchemyError

from service.db import schema
from service.db.tx import write_transaction
from service.errors import ServiceError

#: The calibration id of a result computed with the rig model logged in the raw log itself.
LOGGED_CALIBRATION = "logged"

result_versions = schema.result_versions
calibrations = schema.reprocess_calibrations


class VersionStoreError(ServiceError):
    """The result-version store could not be read or written, or was asked for something missing."""


@dataclass(frozen=True)
class KnownCalibration:
    """A calibration found by its id (:meth:`VersionStore.find_calibration`)."""

    id: str
    calibration: dict[str, Any]
    """``lrms calibrate --out``'s JSON (a ``CalibrationResult``)."""
    rig_id: str | None
    """The rig it belongs to (the service's calibrations; None: any rig, or not known)."""
    origin: Literal["reprocess", "service"]
    """Where it is kept: ``reprocess_calibrations`` or the service's ``calibrations`` table."""


def _as_dict(value: Any) -> dict[str, Any]:
    data = json.loads(value) if isinstance(value, str | bytes) else value
    if not isinstance(data, dict):
        raise VersionStoreError("a stored calibration is not a JSON object")
    return data


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
        with write_transaction(self.engine) as conn:
            if conn.execute(select(calibrations.c.id).where(calibrations.c.id == cid)).first() is None:
                conn.execute(
                    insert(calibrations).values(
                        id=cid, created_at=time.time(), source=source[:1024], calibration=calibration
                    )
                )
        return cid

    def get_calibration(self, ref: str) -> tuple[str, dict[str, Any]]:
        """The calibration whose id is ``ref`` or starts with it (at least 6 hex digits), of those
        kept here or of the service's calibration store (:meth:`find_calibration`)."""
        found = self.find_calibration(ref)
        return found.id, found.calibration

    def find_calibration(self, ref: str) -> KnownCalibration:
        """The calibration whose id is ``ref`` or starts with it (at least 6 characters): one kept in
        ``reprocess_calibrations`` (a file given to ``lrms reprocess`` before), or one of the
        service's calibration store (the ``calibrations`` table: uploaded by ``POST
        /api/v1/calibrations`` or ``lrms calibrate --upload``). :class:`VersionStoreError` when no
        calibration or more than one matches."""
        if len(ref) < 6:
            raise VersionStoreError(f"calibration id {ref!r}: give at least 6 of its hex digits")
        svc = schema.calibrations
        with self.engine.connect() as conn:
            kept = conn.execute(
                select(calibrations.c.id, calibrations.c.calibration).where(
                    calibrations.c.id.startswith(ref, autoescape=True)
                )
            ).all()
            stored = conn.execute(
                select(svc.c.id, svc.c.result, svc.c.rig_id).where(svc.c.id.startswith(ref, autoescape=True))
            ).all()
        found = [KnownCalibration(str(r[0]), _as_dict(r[1]), None, "reprocess") for r in kept]
        found += [KnownCalibration(str(r[0]), _as_dict(r[1]), r[2], "service") for r in stored]
        if not found:
            raise VersionStoreError(
                f"no calibration {ref!r}: not a file, not kept by lrms reprocess,"
                " not in the service's calibration store"
            )
        if len(found) > 1:
            names = ", ".join(f"{c.id} ({c.origin})" for c in found)
            raise VersionStoreError(f"calibration id {ref!r} is ambiguous: {names}")
        return found[0]

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
        (another run got there first). A result holding NaN or an infinity is refused
        (:class:`VersionStoreError`), on SQLite as on PostgreSQL."""
        try:  # PostgreSQL's JSON refuses NaN and infinity; SQLite would keep them: refuse on both
            json.dumps(result, allow_nan=False)
        except ValueError as exc:
            raise VersionStoreError(
                f"a result of {measurement_id} is not finite JSON (NaN or infinity): {exc}"
            ) from None
        except TypeError as exc:
            raise VersionStoreError(f"a result of {measurement_id} is not JSON: {exc}") from None
        rv = result_versions.c
        for _ in range(5):  # a concurrent writer may take the next number first
            try:
                with write_transaction(self.engine) as conn:
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
