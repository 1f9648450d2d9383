"""``/healthz`` and ``/metrics``: outside ``/api/v1``, for probes and Prometheus."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from lrms import __version__
from service.api.core import JsonBytes
from service.api.deps import ServiceDep
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
    """``status`` "ok" (200) when the service can measure; otherwise 503 with the same body."""

    def build() -> bytes:
        body = HealthOut(
            status="ok",
            version=__version__,
            running=service.runner.running_id,
            queued=service.store.count_by_state()["queued"],
        )
        return body.model_dump_json().encode()

    # the runner changes running_id next to a store write (start, finish), so the store's
    # version covers it; the key holds it too for the instant between the two
    return JsonBytes(service.cache.get(f"healthz:{service.runner.running_id}", build))


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}}}},
)
def metrics(service: ServiceDep) -> Response:
    return Response(generate_latest(service.metrics.registry), media_type=CONTENT_TYPE_LATEST)
