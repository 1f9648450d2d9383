"""``/api/v1/schedules``: measurements run by cron expression or interval."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response
from pydantic import TypeAdapter

from service.api.core import JsonBytes
from service.api.deps import ADMIN, READ, READ_RESPONSES, WRITE_RESPONSES, ServiceDep
from service.models import ScheduleOut, ScheduleRequest, resolve_sweep
from service.store import Schedule

router = APIRouter(prefix="/schedules", tags=["schedules"], dependencies=READ, responses=READ_RESPONSES)
_SCHEDULES = TypeAdapter(list[ScheduleOut])


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
    )


@router.post("", status_code=201, response_model=ScheduleOut, dependencies=ADMIN, responses=WRITE_RESPONSES)
def create_schedule(req: ScheduleRequest, service: ServiceDep) -> ScheduleOut:
    try:
        resolve_sweep(req.measurement.sweep, service.config)
    except ValueError as exc:
        raise HTTPException(422, f"measurement.sweep: {exc}") from None
    return schedule_out(service.scheduler.add(req))


@router.get("", response_model=list[ScheduleOut])
async def list_schedules(service: ServiceDep) -> Response:
    def build() -> bytes:
        return _SCHEDULES.dump_json([schedule_out(s) for s in service.store.list_schedules()])

    return JsonBytes(service.cache.get("schedules", build))


@router.get("/{sid}", response_model=ScheduleOut)
async def get_schedule(sid: str, service: ServiceDep) -> ScheduleOut:
    return schedule_out(service.store.get_schedule(sid))


@router.delete("/{sid}", status_code=204, dependencies=ADMIN)
def delete_schedule(sid: str, service: ServiceDep) -> Response:
    service.store.delete_schedule(sid)
    return Response(status_code=204)
