"""``/healthz`` and ``/metrics``: outside ``/api/v1``, for probes and Prometheus.

``/healthz`` is always open (liveness probes carry no token; it tells only status, version, the
running measurement's id and the queue length). ``/metrics`` needs a read token when ``[auth] read
= "token"`` (Prometheus sends one with ``authorization: {credentials: ...}`` in its scrape config)."""

from __future__ import annotations

import json

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from lrms import __version__
from service.api.core import JsonBytes
from service.api.deps import READ, READ_RESPONSES, ServiceDep

router = APIRouter(tags=["ops"])


@router.get("/healthz", response_class=JsonBytes)
async def healthz(service: ServiceDep) -> Response:
    def build() -> bytes:
        body = {
            "status": "ok",
            "version": __version__,
            "running": service.runner.running_id,
            "queued": service.store.count_by_state()["queued"],
        }
        return json.dumps(body).encode()

    # the runner changes running_id next to a store write (start, finish), so the store's
    # version covers it; the key holds it too for the instant between the two
    return JsonBytes(service.cache.get(f"healthz:{service.runner.running_id}", build))


@router.get("/metrics", response_class=Response, dependencies=READ, responses=READ_RESPONSES)
def metrics(service: ServiceDep) -> Response:
    return Response(generate_latest(service.metrics.registry), media_type=CONTENT_TYPE_LATEST)
