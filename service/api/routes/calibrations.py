"""``/api/v1/calibrations``: run a calibration sweep, upload, list, read and activate rig
calibrations (issue 12).

``POST /api/v1/calibrations`` queues a calibration sweep on the rig: a measurement job with target
``"calibration"`` (:mod:`service.calibrating`), followed like any measurement at
``/api/v1/measurements/{id}`` (progress, events, its raw log, failure with the reason); when it is
done the calibration is stored (and activated if asked) and the job's result names it
(``calibration_id``). A calibration computed elsewhere (``lrms calibrate --out``, several rig
poses) is uploaded by ``POST /api/v1/calibrations/upload`` as the JSON ``lrms calibrate --json /
--out`` writes (schema ``lrms.calibration/1``), checked by
:func:`service.calstore.parse_calibration` (a malformed one is a 422 naming what is wrong, and
nothing is stored). The rig's active calibration is what every measurement maps and fits with;
the result names it (``result.calibration``).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Path, Query, Response, status
from pydantic import BaseModel, Field

from service.api.core import Service
from service.api.deps import ADMIN, READ, READ_RESPONSES, ServiceDep
from service.api.errors import responses
from service.api.paths import register_path_pattern
from service.api.routes.measurements import measurement_out
from service.calstore import StoredCalibration, parse_calibration
from service.errors import RequestFieldError
from service.models import CalibrationRequest, MeasurementOut, resolve_sweep
from service.store import NotFound

#: Calibration ids as the store makes them (``uuid4().hex[:16]``).
ID_PATTERN = r"^[0-9a-f]{16}$"


# so /calibrations/upload and /calibrations/active are never taken for /calibrations/{cid}
register_path_pattern("calibration_id", ID_PATTERN)

router = APIRouter(prefix="/calibrations", tags=["calibrations"], dependencies=READ, responses=READ_RESPONSES)

#: Longest name and comment of a stored calibration.
NAME_MAX_LENGTH = 200
COMMENT_MAX_LENGTH = 2000

CalibrationId = Annotated[str, Path(pattern=ID_PATTERN, description="calibration id (16 hex digits)")]


class CalibrationSummary(BaseModel):
    """A stored calibration without its whole result."""

    id: str
    created: str = Field(description="when it was stored (UTC, ISO 8601)")
    name: str
    comment: str
    rig_id: str | None = Field(description="the rig it belongs to (by default the service's `[storage] rig_id`)")
    active: bool = Field(description="the rig's measurements use it")
    calibrated: str = Field(description="when the calibration was computed (its own date)")
    software_version: str
    estimated: list[str] = Field(description="the parameters it estimated (RigModel names)")
    held: list[str] = Field(description="the parameters held at their nominal values")
    model: dict[str, float] = Field(description="the rig model in display units (mm, ppm, deg, ms)")
    residuals: dict[str, float]


class CalibrationOut(CalibrationSummary):
    """A stored calibration with its whole result (as ``lrms calibrate --json`` prints it)."""

    calibration: dict[str, Any]


def _summary(c: StoredCalibration) -> CalibrationSummary:
    return CalibrationSummary(**c.summary())


def _out(c: StoredCalibration) -> CalibrationOut:
    return CalibrationOut(**c.summary(), calibration=c.calibration.to_dict())


def _rig(service: Service, rig_id: str | None) -> str:
    return service.store.rig_id if rig_id is None else rig_id


RigId = Annotated[
    str | None,
    Query(min_length=1, max_length=NAME_MAX_LENGTH, description="the rig (default: this service's rig)"),
]


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=MeasurementOut,
    dependencies=ADMIN,
    responses=responses(400, 401, 403, 413, 422, 429),
)
def run_calibration(req: CalibrationRequest, response: Response, service: ServiceDep) -> MeasurementOut:
    """Queue a calibration sweep: the rig sweeps (``sweep``; missing fields -90..90 deg at 20 deg/s)
    and the rig model is adjusted to it with ``artefact`` (the room's planes, reference spheres,
    centre distances), as ``lrms calibrate`` does. Answers the job (a measurement with target
    ``"calibration"``, ``Location: /api/v1/measurements/{id}``); when it is done its result has
    ``calibration_id`` (stored, and active if ``activate``), the summary and the identifiability
    report. A sweep the rig cannot run is a 422 naming the field; nothing is queued then."""
    job = req.measurement()
    try:
        resolve_sweep(job.sweep, service.config)
    except RequestFieldError as exc:
        raise exc.under("body") from None
    m = service.runner.submit(job)
    response.headers["Location"] = f"/api/v1/measurements/{m.id}"
    return measurement_out(m)


@router.post(
    "/upload",
    status_code=status.HTTP_201_CREATED,
    response_model=CalibrationOut,
    dependencies=ADMIN,
    responses=responses(400, 401, 403, 413, 422),
)
def create_calibration(
    response: Response,
    service: ServiceDep,
    body: Annotated[dict[str, Any], Body(description="a calibration as `lrms calibrate --json` prints it")],
    name: Annotated[str, Query(max_length=NAME_MAX_LENGTH)] = "",
    comment: Annotated[str, Query(max_length=COMMENT_MAX_LENGTH)] = "",
    rig_id: RigId = None,
    activate: Annotated[bool, Query(description="make it the rig's active calibration at once")] = False,
) -> CalibrationOut:
    """Store a calibration (inactive unless ``activate``). A body that is not a valid calibration
    is a 422 saying why; nothing is stored then."""
    from lrms.calibration import CalibrationError

    try:
        cal = parse_calibration(body)
    except CalibrationError as exc:
        raise RequestFieldError([(("body",), str(exc))]) from None
    stored = service.calibrations.add(cal, name=name, comment=comment, rig_id=_rig(service, rig_id))
    if activate:
        stored = service.calibrations.activate(stored.id)
    response.headers["Location"] = f"/api/v1/calibrations/{stored.id}"
    return _out(stored)


@router.get("", response_model=list[CalibrationSummary], responses=responses(422))
def list_calibrations(
    service: ServiceDep,
    rig_id: RigId = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="page size")] = 100,
    offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
) -> list[CalibrationSummary]:
    """The rig's calibrations, newest first."""
    return [_summary(c) for c in service.calibrations.list(_rig(service, rig_id), limit, offset)]


@router.get("/active", response_model=CalibrationOut, responses=responses(404, 422))
def get_active_calibration(service: ServiceDep, rig_id: RigId = None) -> CalibrationOut:
    """The rig's active calibration; 404 when none is active (measurements use ``[kinematics]``)."""
    rig = _rig(service, rig_id)
    active = service.calibrations.active(rig)
    if active is None:
        raise NotFound(f"no active calibration for rig {rig!r}")
    return _out(active)


@router.get("/{cid:calibration_id}", response_model=CalibrationOut, responses=responses(404, 422))
def get_calibration(cid: CalibrationId, service: ServiceDep) -> CalibrationOut:
    return _out(service.calibrations.get(cid))


@router.post(
    "/{cid:calibration_id}/activate",
    response_model=CalibrationSummary,
    dependencies=ADMIN,
    responses=responses(401, 403, 404, 413, 422),
)
def activate_calibration(cid: CalibrationId, service: ServiceDep) -> CalibrationSummary:
    """Make this its rig's active calibration (the rig's others become inactive); measurements
    queued or started from now on use it."""
    return _summary(service.calibrations.activate(cid))
