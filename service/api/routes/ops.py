"""``/healthz`` and ``/metrics``: outside ``/api/v1``, for probes and Prometheus.

``/healthz`` is always open (liveness probes carry no token; it tells only status, version, the
running measurement's id and the queue length). ``/metrics`` needs a read token when ``[auth] read
= "token"`` (Prometheus sends one with ``authorization: {credentials: ...}`` in its scrape config)."""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from lrms import __version__
from service.api.core import JsonBytes
from service.api.deps import READ, READ_RESPONSES, ServiceDep
from service.api.errors import responses
from service.api.schemas import HealthOut

router = APIRouter(tags=["ops"])


@router.get(
    "/healthz",
    response_class=JsonBytes,
    response_model=HealthOut,
    responses=responses(503, _503=HealthOut),
)
async def healthz(service: ServiceDep) -> Response:
    """``status`` ``ok`` (200) only when the rig process is alive and reporting, the drive is not
    faulted and the scanner is connected; else ``degraded`` (503) with ``reasons``. The API itself
    answers either way: a probe reads the status code as "can this rig measure now"."""
    # the queue count from the response cache (a store query only after a write); the rig part
    # fresh: it is the rig supervisor's newest report, read without a device or bus access
    queued = int(service.cache.get("healthz:queued", lambda: str(service.store.count_by_state()["queued"]).encode()))
    body: dict[str, Any] = {
        "status": "ok",
        "version": __version__,
        "running": service.runner.running_id,
        "queued": queued,
    }
    if service.rig_health is not None:
        body.update(service.rig_health())
    code = 200 if body["status"] == "ok" else 503
    return JsonBytes(json.dumps(body).encode(), status_code=code)


@router.get(
    "/metrics",
    response_class=Response,
    dependencies=READ,
    responses={200: {"content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}}}, **READ_RESPONSES},
)
def metrics(service: ServiceDep) -> Response:
    return Response(generate_latest(service.metrics.registry), media_type=CONTENT_TYPE_LATEST)
