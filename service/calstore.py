"""The calibration store (issue 12): rig calibrations (``lrms.calibration.CalibrationResult``) with
a name, a comment, the rig they belong to and which one is active, in one table of the result
store's database (SQLAlchemy Core).

A calibration is stored as the JSON ``lrms calibrate --json / --out`` writes, checked before it is
stored (:func:`parse_calibration`: schema, a finite, symmetric, positive semi-definite covariance
over the estimated parameters, a valid rig model); nothing malformed is stored. At most one
calibration is active per rig (``rig_id``; ``None`` is a rig of its own): activating one
deactivates the others of that rig in the same transaction. Measurements map and fit with the
active one and record which one they used (:mod:`service.fitting`).

The table is part of the result store's schema (:data:`service.db.schema.calibrations`, created by
migration 0003); the store takes the result store's ``sqlalchemy.Engine`` (:attr:`service.store.Store.engine`).
Its writes are write transactions of that database (:func:`service.db.tx.write_transaction`: one
write lock on SQLite and PostgreSQL), so services of several rigs storing and activating at once
never number two calibrations alike nor leave two active for one rig.
"""

from __future__ import annotations

import datetime
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import sqlalchemy as sa

from lrms.errors import LrmsError
from lrms.kinematics import RigModel
from service.db.schema import calibrations
from service.db.tx import write_transaction
from service.store import NotFound, StoreError

if TYPE_CHECKING:  # imported where a calibration is parsed or read: lrms.calibration loads
    # scipy.spatial and scipy.special (~0.7 s CPU), which the service's start does not need
    from lrms.calibration import CalibrationResult


def parse_calibration(data: Any) -> CalibrationResult:
    """A calibration from its JSON form, checked: :class:`CalibrationError` naming what is wrong.

    Beyond :meth:`CalibrationResult.from_dict`: the estimated parameters are known, distinct rig
    parameters; the covariance is finite, symmetric and positive semi-definite, and zero outside
    the estimated parameters (held ones carry no uncertainty of their own)."""
    from lrms.calibration import CalibrationError, CalibrationResult

    try:
        cal = CalibrationResult.from_dict(data)
    except CalibrationError:
        raise
    except LrmsError as exc:  # the rig model's own checks (unknown or non-finite parameters)
        raise CalibrationError(f"malformed calibration: {exc}") from None
    unknown = [n for n in cal.estimated if n not in RigModel.NAMES]
    if unknown:
        raise CalibrationError(f"estimated: unknown rig parameter(s) {', '.join(unknown)}")
    if len(set(cal.estimated)) != len(cal.estimated):
        raise CalibrationError("estimated: a parameter is named twice")
    cov = cal.covariance
    if not np.all(np.isfinite(cov)):
        raise CalibrationError("covariance: every element must be a finite number")
    scale = max(float(np.max(np.abs(cov))), 1e-300)
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12 * scale):
        raise CalibrationError("covariance: must be symmetric")
    idx = [RigModel.NAMES.index(n) for n in cal.estimated]
    held = [i for i in range(len(RigModel.NAMES)) if i not in idx]
    if held and np.any(cov[held, :] != 0.0):
        names = ", ".join(RigModel.NAMES[i] for i in held if np.any(cov[i] != 0.0))
        raise CalibrationError(f"covariance: rows of parameters not estimated must be zero ({names})")
    if idx and float(np.min(np.linalg.eigvalsh(cov[np.ix_(idx, idx)]))) < -1e-9 * scale:
        raise CalibrationError("covariance: must be positive semi-definite")
    return cal


@dataclass(frozen=True)
class StoredCalibration:
    """One stored calibration: its record and the calibration itself."""

    id: str
    created: str
    name: str
    comment: str
    rig_id: str | None
    active: bool
    calibration: CalibrationResult

    def reference(self) -> dict[str, Any]:
        """What a measurement records of the calibration it used: ``{"id", "name", "created"}``."""
        return {"id": self.id, "name": self.name, "created": self.created}

    def summary(self) -> dict[str, Any]:
        """The record without the whole result: values in display units, the calibration's date,
        the estimated and held parameters and the residual summary."""
        c = self.calibration
        return {
            "id": self.id,
            "created": self.created,
            "name": self.name,
            "comment": self.comment,
            "rig_id": self.rig_id,
            "active": self.active,
            "calibrated": c.created,
            "software_version": c.software_version,
            "estimated": list(c.estimated),
            "held": sorted(c.identifiability.held),
            "model": c.model.display(),
            "residuals": dict(c.residuals),
        }

    def payload(self) -> dict[str, Any]:
        """The record and the calibration's JSON (what the rig process gets and the raw log keeps)."""
        return {**self.reference(), "rig_id": self.rig_id, "calibration": self.calibration.to_dict()}

    @classmethod
    def from_payload(cls, data: dict[str, Any]) -> StoredCalibration:
        return cls(
            id=str(data["id"]),
            created=str(data["created"]),
            name=str(data.get("name", "")),
            comment="",
            rig_id=data.get("rig_id"),
            active=True,
            calibration=parse_calibration(data["calibration"]),
        )


class CalibrationStore:
    """Calibrations in the ``calibrations`` table of ``engine``'s database (the result store's,
    migrated: :class:`service.store.Store` creates it)."""

    def __init__(self, engine: sa.Engine) -> None:
        self.engine = engine

    def add(
        self, calibration: CalibrationResult, *, name: str = "", comment: str = "", rig_id: str | None = None
    ) -> StoredCalibration:
        """Store ``calibration`` (inactive); its id and the time it was stored are new."""
        with write_transaction(self.engine) as conn:
            return self.add_in(conn, calibration, name=name, comment=comment, rig_id=rig_id)

    def add_in(
        self,
        conn: sa.Connection,
        calibration: CalibrationResult,
        *,
        name: str = "",
        comment: str = "",
        rig_id: str | None = None,
        cid: str | None = None,
        activate: bool = False,
    ) -> StoredCalibration:
        """:meth:`add` (and with ``activate`` :meth:`activate`) in the caller's write transaction
        ``conn`` (:func:`service.db.tx.write_transaction`; a measurement's end, for a calibration
        sweep: the calibration is stored with the job's result or not at all). ``cid``: its id
        (default a new one)."""
        for label, text in (("name", name), ("comment", comment)):
            if not isinstance(text, str):
                raise StoreError(f"a calibration's {label} is text")
        created = datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")
        cid = new_id() if cid is None else cid
        seq = conn.execute(sa.select(sa.func.coalesce(sa.func.max(calibrations.c.seq), 0))).scalar_one()
        conn.execute(
            calibrations.insert().values(
                id=cid,
                seq=int(seq) + 1,
                created=created,
                name=name,
                comment=comment,
                rig_id=rig_id,
                result=calibration.to_json(indent=None),
                active=False,
            )
        )
        if activate:
            _activate(conn, cid)
        return StoredCalibration(cid, created, name, comment, rig_id, activate, calibration)

    def get(self, cid: str) -> StoredCalibration:
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(calibrations).where(calibrations.c.id == cid)).first()
        if row is None:
            raise NotFound(f"no calibration {cid}")
        return _record(row)

    def list(self, rig_id: str | None = None, limit: int = 100, offset: int = 0) -> list[StoredCalibration]:
        """Newest first; ``rig_id`` given: that rig's only."""
        q = sa.select(calibrations).order_by(calibrations.c.seq.desc()).limit(limit).offset(offset)
        if rig_id is not None:
            q = q.where(calibrations.c.rig_id == rig_id)
        with self.engine.connect() as conn:
            return [_record(r) for r in conn.execute(q)]

    def active(self, rig_id: str | None) -> StoredCalibration | None:
        """The active calibration of ``rig_id`` (None: none is active)."""
        with self.engine.connect() as conn:
            row = conn.execute(
                sa.select(calibrations).where(calibrations.c.active.is_(True), _same_rig(rig_id)).limit(1)
            ).first()
        return None if row is None else _record(row)

    def activate(self, cid: str) -> StoredCalibration:
        """Make ``cid`` its rig's active calibration (the rig's other calibrations become inactive)."""
        with write_transaction(self.engine) as conn:
            _activate(conn, cid)
        return self.get(cid)

    def close(self) -> None:
        self.engine.dispose()


def new_id() -> str:
    """A new calibration id: 16 hex digits."""
    return uuid.uuid4().hex[:16]


def _activate(conn: sa.Connection, cid: str) -> None:
    row = conn.execute(sa.select(calibrations.c.rig_id).where(calibrations.c.id == cid)).first()
    if row is None:
        raise NotFound(f"no calibration {cid}")
    conn.execute(calibrations.update().where(_same_rig(row.rig_id)).values(active=False))
    conn.execute(calibrations.update().where(calibrations.c.id == cid).values(active=True))


def _same_rig(rig_id: str | None) -> sa.ColumnElement[bool]:
    col = calibrations.c.rig_id
    return col.is_(None) if rig_id is None else col == rig_id


def _record(row: Any) -> StoredCalibration:
    from lrms.calibration import CalibrationResult

    return StoredCalibration(
        id=row.id,
        created=row.created,
        name=row.name,
        comment=row.comment,
        rig_id=row.rig_id,
        active=bool(row.active),
        calibration=CalibrationResult.from_json(row.result),
    )
