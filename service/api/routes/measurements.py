"""``/api/v1/measurements``: start, list, read, cancel; raw logs, clouds and progress events."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request, Response, status
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import TypeAdapter

from service.api.core import JsonBytes, Service
from service.api.deps import OPERATE, READ, READ_RESPONSES, WRITE_RESPONSES, ServiceDep
from service.models import MeasurementOut, MeasurementRequest, resolve_sweep
from service.store import FINAL_STATES, STATES, Measurement

router = APIRouter(prefix="/measurements", tags=["measurements"], dependencies=READ, responses=READ_RESPONSES)
_MEASUREMENTS = TypeAdapter(list[MeasurementOut])


def measurement_out(m: Measurement) -> MeasurementOut:
    return MeasurementOut(
        id=m.id,
        state=m.state,  # type: ignore[arg-type]
        created_at=m.created_at,
        started_at=m.started_at,
        finished_at=m.finished_at,
        progress=m.progress,
        message=m.message,
        request=m.request,
        result=m.result,
        error=m.error,
        has_raw=m.raw_path is not None,
        raw_truncated=m.raw_truncated,
        has_cloud=m.cloud_path is not None,
        schedule_id=m.schedule_id,
    )


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=MeasurementOut,
    dependencies=OPERATE,
    responses=WRITE_RESPONSES,
)
def create_measurement(req: MeasurementRequest, response: Response, service: ServiceDep) -> MeasurementOut:
    try:
        resolve_sweep(req.sweep, service.config)
    except ValueError as exc:
        raise HTTPException(422, f"sweep: {exc}") from None
    if service.validate is not None:
        service.validate(req)
    m = service.runner.submit(req)
    response.headers["Location"] = f"/api/v1/measurements/{m.id}"
    return measurement_out(m)


@router.get("", response_model=list[MeasurementOut])
async def list_measurements(
    service: ServiceDep,
    state: Annotated[str | None, Query(description=f"one of {', '.join(STATES)}")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0)] = 0,
) -> Response:
    if state is not None and state not in STATES:
        raise HTTPException(422, f"unknown state {state!r}: expected one of {', '.join(STATES)}")

    def build() -> bytes:
        ms = service.store.list_measurements(state, limit, offset)
        return _MEASUREMENTS.dump_json([measurement_out(m) for m in ms])

    return JsonBytes(service.cache.get(f"list:{state}:{limit}:{offset}", build))


@router.get("/{mid}", response_model=MeasurementOut)
async def get_measurement(mid: str, service: ServiceDep) -> Response:
    def build() -> bytes:
        return measurement_out(service.store.get(mid)).model_dump_json().encode()

    return JsonBytes(service.cache.get(f"m:{mid}", build))


@router.post("/{mid}/cancel", response_model=MeasurementOut, dependencies=OPERATE, responses=WRITE_RESPONSES)
def cancel_measurement(mid: str, service: ServiceDep) -> MeasurementOut:
    return measurement_out(service.runner.cancel(mid))


def _file(service: Service, mid: str, which: str) -> str:
    m = service.store.get(mid)
    path = m.raw_path if which == "raw" else m.cloud_path
    if m.state not in FINAL_STATES:
        raise HTTPException(409, f"measurement {mid} is {m.state}: its {which} data is not complete yet")
    if path is None:
        raise HTTPException(404, f"measurement {mid} ({m.state}) has no {which} data")
    return path


@router.get(
    "/{mid}/raw",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-mcap": {}}}},
)
def get_raw(mid: str, service: ServiceDep) -> FileResponse:
    return FileResponse(_file(service, mid, "raw"), media_type="application/x-mcap", filename=f"{mid}.mcap")


@router.get(
    "/{mid}/cloud",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-ply": {}}}},
)
def get_cloud(mid: str, service: ServiceDep) -> FileResponse:
    return FileResponse(_file(service, mid, "cloud"), media_type="application/x-ply", filename=f"{mid}.ply")


@router.get(
    "/{mid}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def events(mid: str, request: Request, service: ServiceDep) -> StreamingResponse:
    """Server-sent events: one ``progress`` event per change, the stream ends at a final state."""
    first = service.store.get(mid)  # 404 if unknown

    async def gen() -> AsyncIterator[str]:
        last_version = -1
        last_payload = ""
        while True:
            latest = service.hub.latest(mid)
            if latest is None:
                m = service.store.get(mid) if last_version == -1 else first
                version, event = (
                    0,
                    {
                        "id": m.id,
                        "state": m.state,
                        "progress": m.progress,
                        "message": m.message,
                        "error": m.error,
                    },
                )
            else:
                version, event = latest
            if version != last_version:
                payload = json.dumps(event)
                if payload != last_payload:
                    yield f"event: progress\ndata: {payload}\n\n"
                    last_payload = payload
                last_version = version
            if event["state"] in FINAL_STATES:
                return
            if await request.is_disconnected():
                return
            await asyncio.sleep(0.1)

    return StreamingResponse(gen(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})
