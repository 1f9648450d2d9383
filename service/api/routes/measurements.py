"""``/api/v1/measurements``: start, list, read, cancel; raw logs, clouds and progress events."""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import AsyncIterator
from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import TypeAdapter

from service.api.core import JsonBytes, Service
from service.api.deps import OPERATE, READ, READ_RESPONSES, ServiceDep
from service.api.errors import responses
from service.db import RIG_ID_LENGTH, RIG_ID_RE
from service.errors import RequestFieldError
from service.models import MeasurementOut, MeasurementRequest, resolve_sweep
from service.parts import resolve_part
from service.store import FINAL_STATES, Measurement

router = APIRouter(prefix="/measurements", tags=["measurements"], dependencies=READ, responses=READ_RESPONSES)
_MEASUREMENTS = TypeAdapter(list[MeasurementOut])

#: The largest ``offset`` of a listing (a store holds far fewer; SQLite's integers end at 2^63).
MAX_OFFSET = 1_000_000_000
#: The largest ``limit`` (page size) of a listing.
MAX_LIMIT = 1000
#: Ids are 16 hex digits; longer path segments are refused before the store is asked.
ID_MAX_LENGTH = 64

MeasurementId = Annotated[str, Path(min_length=1, max_length=ID_MAX_LENGTH, description="measurement id")]
RigFilter = Annotated[
    str | None,
    Query(
        min_length=1,
        max_length=RIG_ID_LENGTH,
        pattern=RIG_ID_RE.pattern,
        description="only this rig's (its [storage] rig_id); default: every rig sharing the database",
    ),
]


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
        rig_id=m.rig_id,
    )


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=MeasurementOut,
    dependencies=OPERATE,
    responses=responses(400, 401, 403, 413, 422, 429),
)
def create_measurement(req: MeasurementRequest, response: Response, service: ServiceDep) -> MeasurementOut:
    """Queue a measurement: free form (``target``, ``sweep``, ``roi``, ``options``) or a part of a
    recipe (``recipe``, ``part_id``, optionally ``recipe_version``, ``part_temperature_c``,
    ``temperature_uncertainty_c``, ``operator``; the recipe supplies the rest, and giving ``target``,
    ``sweep``, ``roi`` or ``options`` beside it is a 422). The sweep is checked against the rig
    (travel limits with the run-up, maximum speed, ``[sweep] max_duration_s``); a refusal is a 422
    naming the field. Nothing is stored for a refused request."""
    if req.recipe is not None:
        req = _expand(req, service)
    try:
        resolve_sweep(req.sweep, service.config)
    except RequestFieldError as exc:
        raise exc.under("body") from None
    if service.validate is not None:
        service.validate(req)
    m = service.runner.submit(req)
    if req.recipe is not None and req.recipe_version is not None and req.part_id is not None:
        service.recipes.link(m.id, req.recipe, req.recipe_version, req.part_id, req.operator)
    response.headers["Location"] = f"/api/v1/measurements/{m.id}"
    return measurement_out(m)


@router.get("", response_model=list[MeasurementOut], responses=responses(422))
async def list_measurements(
    service: ServiceDep,
    state: Annotated[Literal["queued", "running", "done", "failed", "cancelled"] | None, Query()] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT, description="page size")] = 100,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
    rig: RigFilter = None,
) -> Response:
    """Newest first, of every rig whose service shares this database (``rig`` picks one)."""

    def build() -> bytes:
        ms = service.store.list_measurements(state, limit, offset, rig=rig)
        return _MEASUREMENTS.dump_json([measurement_out(m) for m in ms])

    return JsonBytes(service.cache.get(f"list:{state}:{limit}:{offset}:{rig}", build))


@router.get("/{mid}", response_model=MeasurementOut, responses=responses(404, 422))
async def get_measurement(mid: MeasurementId, service: ServiceDep) -> Response:
    def build() -> bytes:
        return measurement_out(service.store.get(mid)).model_dump_json().encode()

    return JsonBytes(service.cache.get(f"m:{mid}", build))


@router.post(
    "/{mid}/cancel",
    response_model=MeasurementOut,
    dependencies=OPERATE,
    responses=responses(401, 403, 404, 409, 413, 422),
)
def cancel_measurement(mid: MeasurementId, service: ServiceDep) -> MeasurementOut:
    return measurement_out(service.runner.cancel(mid))


def _expand(req: MeasurementRequest, service: Service) -> MeasurementRequest:
    """A part's request with its recipe's measurement filled in (:func:`service.parts.resolve_part`)."""
    try:
        return resolve_part(req, service.recipes)
    except RequestFieldError as exc:
        raise exc.under("body") from None


def _file(service: Service, mid: str, which: str) -> str:
    m = service.store.get(mid)
    path = m.raw_path if which == "raw" else m.cloud_path
    if m.state not in FINAL_STATES:
        raise HTTPException(409, f"measurement {mid} is {m.state}: its {which} data is not complete yet")
    # 404 is kept for an unknown id: a measurement that exists but has no such file (cancelled
    # before it ran, failed before anything was recorded, the file removed from storage) is a 409
    if path is None:
        raise HTTPException(409, f"measurement {mid} ({m.state}) has no {which} data")
    if not os.path.isfile(path):
        raise HTTPException(409, f"measurement {mid} ({m.state}): its {which} file is missing from storage")
    return path


@router.get(
    "/{mid}/raw",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-mcap": {}}}, **responses(404, 409, 422)},
)
def get_raw(mid: MeasurementId, service: ServiceDep) -> FileResponse:
    return FileResponse(_file(service, mid, "raw"), media_type="application/x-mcap", filename=f"{mid}.mcap")


@router.get(
    "/{mid}/cloud",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-ply": {}}}, **responses(404, 409, 422)},
)
def get_cloud(mid: MeasurementId, service: ServiceDep) -> FileResponse:
    return FileResponse(_file(service, mid, "cloud"), media_type="application/x-ply", filename=f"{mid}.ply")


@router.get(
    "/{mid}/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}, **responses(404, 422)},
)
async def events(mid: MeasurementId, request: Request, service: ServiceDep) -> StreamingResponse:
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
