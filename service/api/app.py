"""The FastAPI application: REST under ``/api/v1``, ``/healthz``, ``/metrics``, OpenAPI at ``/docs``.

:class:`Service` (service.api.core) bundles what the routes need (config, store, job runner,
scheduler, metrics and the rig's description); :func:`create_app` builds the app around one, from
one router module per resource (service.api.routes), with the error handlers of
service.api.errors and the middleware: request counting outermost, then the body guard (token of
a POST/PUT/PATCH and the body size, decided before the body is read: service.api.guard). The docs
pages are served from local assets (service.api.docs). The app starts the job runner and the
scheduler when it starts serving and stops them on shutdown.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI

from lrms import __version__
from service.api.core import Service
from service.api.docs import mount_docs
from service.api.errors import install_handlers
from service.api.guard import BodyGuard
from service.api.routes import calibrations, measurements, ops, recipes, reports, rig, schedules
from service.jobs import Metrics

__all__ = ["Service", "create_app"]


async def _watch_loop_lag(metrics: Metrics, period_s: float = 0.02) -> None:
    """Observe how late the event loop wakes from a ``period_s`` sleep: every request waits at
    least that long before the app sees it, so it tells a stalled process (another thread holding
    the GIL, the process not scheduled) from slow handlers (``lrms_http_request_seconds``)."""
    loop = asyncio.get_running_loop()
    while True:
        t = loop.time()
        await asyncio.sleep(period_s)
        metrics.loop_lag.observe(max(loop.time() - t - period_s, 0.0))


def create_app(service: Service, manage_lifecycle: bool = True) -> FastAPI:
    """The FastAPI app for ``service`` (started and stopped with the app unless told otherwise)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if manage_lifecycle:
            service.start()
        watch = asyncio.create_task(_watch_loop_lag(service.metrics))
        try:
            yield
        finally:
            watch.cancel()
            if manage_lifecycle:
                service.stop()

    app = FastAPI(
        title="lrms acquisition service",
        version=__version__,
        description="Sweeps of the laser radar measurement system: measurements, raw logs, clouds, schedules.",
        lifespan=lifespan,
        docs_url=None,  # mount_docs: Swagger UI and ReDoc from local assets, not a CDN
        redoc_url=None,
        generate_unique_id_function=lambda route: route.name,  # operationId = the route function's name
    )
    app.state.service = service

    install_handlers(app)  # every error body as documented (service.api.errors)
    app.include_router(ops.router)
    for module in (rig, measurements, reports, schedules, calibrations, recipes):
        app.include_router(module.router, prefix="/api/v1")
    mount_docs(app)
    reports.mount_web(app)  # the engineer's page at / (service/web)
    app.add_middleware(BodyGuard, service=service)
    app.add_middleware(_CountRequests, metrics=service.metrics)  # added last: outermost, counts the guard's answers
    return app


class _CountRequests:
    """Pure ASGI middleware counting requests by route template and status, timing them into
    ``lrms_http_request_seconds`` and a ``Server-Timing: app;dur=<ms>`` response header (the time
    in the app, so a client can tell it from the time on the wire and in its own queue). Cheaper
    than Starlette's ``BaseHTTPMiddleware``, which wraps every response in extra tasks."""

    def __init__(self, app: Any, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status_code = [500]
        t0 = time.perf_counter()

        async def send_wrapper(message: dict[str, Any]) -> None:
            if message["type"] == "http.response.start":
                status_code[0] = int(message["status"])
                dt = time.perf_counter() - t0
                self.metrics.http_seconds.observe(dt)
                headers = list(message.get("headers", ()))
                headers.append((b"server-timing", f"app;dur={dt * 1e3:.3f}".encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", "unmatched")
            self.metrics.http_requests.labels(scope.get("method", ""), path, str(status_code[0])).inc()
