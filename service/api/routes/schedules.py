"""``/api/v1/schedules``: measurements run by cron expression or interval."""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Path, Response
from pydantic import TypeAdapter

from service.api.core import JsonBytes
from service.api.deps import ADMIN, READ, READ_RESPONSES, ServiceDep
from service.api.errors import responses
from service.api.routes.measurements import ID_MAX_LENGTH, RigFilter
from service.errors import RequestFieldError
from service.models import resolve_sweep
from service.parts import resolve_part
from service.schedulemodels import ScheduleOut, ScheduleRequest, check_schedule
from service.store import Schedule

router = APIRouter(prefix="/schedules", tags=["schedules"], dependencies=READ, responses=READ_RESPONSES)
_SCHEDULES = TypeAdapter(list[ScheduleOut])

ScheduleId = Annotated[str, Path(min_length=1, max_length=ID_MAX_LENGTH, description="schedule id")]


def schedule_out(s: Schedule) -> ScheduleOut:
    return ScheduleOut(
        id=s.id,
        name=s.name,
        cron=s.cron,
        interval_s=s.interval_s,
        measurement=s.template,
        next_run=s.next_run,
        last_run=s.last_run,
        last_measurement_id=s.last_measurement_id,
        rig_id=s.rig_id,
    )


@router.post(
    "",
    status_code=201,
    response_model=ScheduleOut,
    dependencies=ADMIN,
    responses=responses(400, 401, 403, 413, 422, 429),
)
def create_schedule(req: ScheduleRequest, service: ServiceDep) -> ScheduleOut:
    """Add a schedule. Its measurement is checked against the rig as ``POST /measurements`` is,
    and its firings must be at least ``[schedules] min_interval_s`` apart. A measurement may be a
    part of a recipe (``recipe``, ``part_id`` as a pattern such as ``"{date}-{n}"``; the recipe's
    latest version when each run fires, unless ``recipe_version`` pins one)."""
    try:
        check_schedule(req, service.config)
    except RequestFieldError as exc:
        raise exc.under("body") from None
    if req.measurement.recipe is not None:  # the recipe exists, is in use, and supplies the measurement
        try:
            part = resolve_part(req.measurement.for_run(time.time(), 1), service.recipes)
        except RequestFieldError as exc:
            raise exc.under("body", "measurement") from None
        try:
            resolve_sweep(part.sweep, service.config)
        except RequestFieldError as exc:
            msg = f"recipe {part.recipe!r}'s sweep does not fit this rig: {exc}"
            raise RequestFieldError([(("body", "measurement", "recipe"), msg)]) from None
    return schedule_out(service.scheduler.add(req))


@router.get("", response_model=list[ScheduleOut], responses=responses(422))
async def list_schedules(service: ServiceDep, rig: RigFilter = None) -> Response:
    """Oldest first, of every rig whose service shares this database (``rig`` picks one; each
    rig's service runs its own schedules only)."""

    def build() -> bytes:
        return _SCHEDULES.dump_json([schedule_out(s) for s in service.store.list_schedules(rig=rig)])

    return JsonBytes(service.cache.get(f"schedules:{rig}", build))


@router.get("/{sid}", response_model=ScheduleOut, responses=responses(404, 422))
async def get_schedule(sid: ScheduleId, service: ServiceDep) -> ScheduleOut:
    return schedule_out(service.store.get_schedule(sid))


@router.delete(
    "/{sid}",
    status_code=204,
    dependencies=ADMIN,
    response_class=Response,
    responses=responses(401, 403, 404, 409, 413, 422),
)
def delete_schedule(sid: ScheduleId, service: ServiceDep) -> Response:
    service.store.delete_schedule(sid)
    return Response(status_code=204)
