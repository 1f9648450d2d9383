"""The FastAPI application: REST under ``/api/v1``, ``/healthz``, ``/metrics``, OpenAPI at ``/docs``.

:class:`Service` bundles what the routes need (config, store, job runner, scheduler, metrics and
the rig's description); :func:`create_app` builds the app around one. The app starts the job
runner and the scheduler when it starts serving and stops them on shutdown.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import secrets
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import TypeAdapter

from lrms import __version__
from service.config import RigConfig
from service.errors import ServiceError
from service.jobs import JobRunner, MeasureFn, Metrics, ProgressHub
from service.models import (
    MeasurementOut,
    MeasurementRequest,
    ScheduleOut,
    ScheduleRequest,
    resolve_sweep,
)
from service.scheduler import Scheduler
from service.store import FINAL_STATES, STATES, Measurement, NotFound, Schedule, Store, StoreError

RigInfo = Callable[[], dict[str, Any]]
_bearer = HTTPBearer(auto_error=False)
_MEASUREMENTS = TypeAdapter(list[MeasurementOut])
_SCHEDULES = TypeAdapter(list[ScheduleOut])


class _JsonBytes(Response):
    media_type = "application/json"


class ResponseCache:
    """Serialised JSON bodies of the read endpoints, keyed by request and valid for one
    :attr:`Store.version`: a polling HMI gets the bytes built for the previous poll until a
    measurement or schedule changes, instead of an SQLite query, JSON decoding of stored results,
    pydantic validation and serialisation per request (the event loop's main cost under load).

    The version is read *before* the body is built, so a write racing with the build leaves the
    entry stale-marked and the next request builds it again."""

    def __init__(self, store: Store, max_entries: int = 512) -> None:
        self.store = store
        self.max_entries = max_entries
        self._entries: dict[str, tuple[tuple[int, int], bytes]] = {}
        self.hits = 0
        self.misses = 0

    def get(self, key: str, build: Callable[[], bytes]) -> bytes:
        version = self.store.version
        hit = self._entries.get(key)
        if hit is not None and hit[0] == version:
            self.hits += 1
            return hit[1]
        self.misses += 1
        body = build()
        if len(self._entries) >= self.max_entries:
            self._entries.clear()
        self._entries[key] = (version, body)
        return body


class Service:
    """Everything behind the REST API for one rig."""

    def __init__(
        self,
        config: RigConfig,
        measure: MeasureFn,
        rig_info: RigInfo | None = None,
        store: Store | None = None,
        validate: Callable[[MeasurementRequest], None] | None = None,
    ) -> None:
        self.config = config
        self.store = store or Store(config.storage.db_path)
        self.metrics = Metrics()
        self.hub = ProgressHub()
        self.runner = JobRunner(
            self.store, measure, config.storage.raw_dir, config.storage.cloud_dir, self.hub, self.metrics
        )
        self.scheduler = Scheduler(self.store, self.runner)
        self.rig_info = rig_info or (lambda: {})
        self.validate = validate
        self.cache = ResponseCache(self.store)
        self._started = False

    def start(self) -> None:
        if not self._started:
            self._started = True
            _settle_heap()
            self.runner.start()
            self.scheduler.start()

    def stop(self) -> None:
        if self._started:
            self._started = False
            self.scheduler.stop()
            self.runner.stop()

    def token(self) -> str | None:
        return self.config.api_token()


def _settle_heap() -> None:
    """Import what a measurement needs, then move everything alive into the GC's permanent
    generation (``gc.freeze``): a full collection then walks only what requests and sweeps
    allocate, instead of the hundreds of thousands of objects of numpy, scipy, pydantic and
    FastAPI, which otherwise stalled every thread for up to a second in the middle of a sweep."""
    import gc
    import importlib

    for name in ("service.fitting", "lrms.cylinder", "lrms.uncertainty", "scipy.optimize", "scipy.stats"):
        with contextlib.suppress(ImportError):  # a missing module is reported when a measurement needs it
            importlib.import_module(name)
    gc.collect()
    gc.freeze()


def _measurement_out(m: Measurement) -> MeasurementOut:
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


def _schedule_out(s: Schedule) -> ScheduleOut:
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
    )
    app.state.service = service

    def require_token(
        creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    ) -> None:
        expected = service.token()
        if expected is None:
            raise HTTPException(
                status.HTTP_403_FORBIDDEN,
                "write endpoints are disabled: no API token configured ([auth] token or LRMS_API_TOKEN)",
            )
        if creds is None or creds.scheme.lower() != "bearer":
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                "missing bearer token (Authorization: Bearer <token>)",
                headers={"WWW-Authenticate": "Bearer"},
            )
        if not secrets.compare_digest(creds.credentials.encode(), expected.encode()):
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED, "invalid bearer token", headers={"WWW-Authenticate": "Bearer"}
            )

    write = [Depends(require_token)]

    # -- errors ---------------------------------------------------------------------------
    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        parts = []
        for e in errors:
            loc = ".".join(str(x) for x in e.get("loc", ()))
            parts.append(f"{loc}: {str(e.get('msg', '')).removeprefix('Value error, ')}")
        return JSONResponse(
            status_code=422,
            content={"message": "; ".join(parts), "detail": json.loads(json.dumps(errors, default=str))},
        )

    @app.exception_handler(NotFound)
    async def _not_found(request: Request, exc: NotFound) -> JSONResponse:
        return JSONResponse(status_code=404, content={"detail": str(exc)})

    @app.exception_handler(StoreError)
    async def _conflict(request: Request, exc: StoreError) -> JSONResponse:
        return JSONResponse(status_code=409, content={"detail": str(exc)})

    @app.exception_handler(ServiceError)
    async def _bad(request: Request, exc: ServiceError) -> JSONResponse:
        return JSONResponse(status_code=400, content={"detail": str(exc)})

    # -- health and metrics ---------------------------------------------------------------
    @app.get("/healthz", tags=["ops"], response_class=_JsonBytes)
    async def healthz() -> Response:
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
        return _JsonBytes(service.cache.get(f"healthz:{service.runner.running_id}", build))

    @app.get("/metrics", tags=["ops"], response_class=Response)
    def metrics() -> Response:
        return Response(generate_latest(service.metrics.registry), media_type=CONTENT_TYPE_LATEST)

    api = APIRouter(prefix="/api/v1")

    # -- rig ------------------------------------------------------------------------------
    cfg = service.config
    rig_static: dict[str, Any] = {  # the configuration does not change while the app runs
        "name": cfg.name,
        "simulated": cfg.is_sim,
        "scanner_url": cfg.scanner.url,
        "motor_url": cfg.motor.url,
        "kinematics": cfg.kinematics,
        "noise": cfg.noise.model_dump(mode="json"),
        "sweep_defaults": cfg.sweep.model_dump(mode="json"),
        "fit_defaults": cfg.fit.model_dump(mode="json"),
        "sim": cfg.sim.model_dump(mode="json") if cfg.sim is not None else None,
    }
    rig_live: list[Any] = [-1e9, {}]  # (monotonic time, rig_info()) of the last device query
    rig_refresh = asyncio.Lock()

    @api.get("/rig", tags=["rig"], response_class=_JsonBytes)
    async def rig() -> Response:
        """Configuration and device state. The device part is read at most every 0.25 s (on a
        worker thread, as a driver may block); requests in between get that reading."""
        if time.monotonic() - rig_live[0] >= 0.25:
            async with rig_refresh:  # one device query for all the requests that found it stale
                if time.monotonic() - rig_live[0] >= 0.25:
                    rig_live[1] = await run_in_threadpool(service.rig_info)
                    rig_live[0] = time.monotonic()
        info = {
            **rig_static,
            "write_enabled": service.token() is not None,
            "busy": service.runner.running_id is not None,
            **rig_live[1],
        }
        return _JsonBytes(json.dumps(jsonable_encoder(info)).encode())

    # -- measurements ---------------------------------------------------------------------
    @api.post(
        "/measurements",
        status_code=status.HTTP_202_ACCEPTED,
        response_model=MeasurementOut,
        dependencies=write,
        tags=["measurements"],
    )
    def create_measurement(req: MeasurementRequest, response: Response) -> MeasurementOut:
        try:
            resolve_sweep(req.sweep, service.config)
        except ValueError as exc:
            raise HTTPException(422, f"sweep: {exc}") from None
        if service.validate is not None:
            service.validate(req)
        m = service.runner.submit(req)
        response.headers["Location"] = f"/api/v1/measurements/{m.id}"
        return _measurement_out(m)

    @api.get("/measurements", response_model=list[MeasurementOut], tags=["measurements"])
    async def list_measurements(
        state: Annotated[str | None, Query(description=f"one of {', '.join(STATES)}")] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
        offset: Annotated[int, Query(ge=0)] = 0,
    ) -> Response:
        if state is not None and state not in STATES:
            raise HTTPException(422, f"unknown state {state!r}: expected one of {', '.join(STATES)}")

        def build() -> bytes:
            ms = service.store.list_measurements(state, limit, offset)
            return _MEASUREMENTS.dump_json([_measurement_out(m) for m in ms])

        return _JsonBytes(service.cache.get(f"list:{state}:{limit}:{offset}", build))

    @api.get("/measurements/{mid}", response_model=MeasurementOut, tags=["measurements"])
    async def get_measurement(mid: str) -> Response:
        def build() -> bytes:
            return _measurement_out(service.store.get(mid)).model_dump_json().encode()

        return _JsonBytes(service.cache.get(f"m:{mid}", build))

    @api.post("/measurements/{mid}/cancel", response_model=MeasurementOut, dependencies=write, tags=["measurements"])
    def cancel_measurement(mid: str) -> MeasurementOut:
        return _measurement_out(service.runner.cancel(mid))

    def _file(mid: str, which: str) -> str:
        m = service.store.get(mid)
        path = m.raw_path if which == "raw" else m.cloud_path
        if m.state not in FINAL_STATES:
            raise HTTPException(409, f"measurement {mid} is {m.state}: its {which} data is not complete yet")
        if path is None:
            raise HTTPException(404, f"measurement {mid} ({m.state}) has no {which} data")
        return path

    @api.get(
        "/measurements/{mid}/raw",
        tags=["measurements"],
        response_class=FileResponse,
        responses={200: {"content": {"application/x-mcap": {}}}},
    )
    def get_raw(mid: str) -> FileResponse:
        return FileResponse(_file(mid, "raw"), media_type="application/x-mcap", filename=f"{mid}.mcap")

    @api.get(
        "/measurements/{mid}/cloud",
        tags=["measurements"],
        response_class=FileResponse,
        responses={200: {"content": {"application/x-ply": {}}}},
    )
    def get_cloud(mid: str) -> FileResponse:
        return FileResponse(_file(mid, "cloud"), media_type="application/x-ply", filename=f"{mid}.ply")

    @api.get(
        "/measurements/{mid}/events",
        tags=["measurements"],
        response_class=StreamingResponse,
        responses={200: {"content": {"text/event-stream": {}}}},
    )
    async def events(mid: str, request: Request) -> StreamingResponse:
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

    # -- schedules ------------------------------------------------------------------------
    @api.post("/schedules", status_code=201, response_model=ScheduleOut, dependencies=write, tags=["schedules"])
    def create_schedule(req: ScheduleRequest) -> ScheduleOut:
        try:
            resolve_sweep(req.measurement.sweep, service.config)
        except ValueError as exc:
            raise HTTPException(422, f"measurement.sweep: {exc}") from None
        return _schedule_out(service.scheduler.add(req))

    @api.get("/schedules", response_model=list[ScheduleOut], tags=["schedules"])
    async def list_schedules() -> Response:
        def build() -> bytes:
            return _SCHEDULES.dump_json([_schedule_out(s) for s in service.store.list_schedules()])

        return _JsonBytes(service.cache.get("schedules", build))

    @api.get("/schedules/{sid}", response_model=ScheduleOut, tags=["schedules"])
    async def get_schedule(sid: str) -> ScheduleOut:
        return _schedule_out(service.store.get_schedule(sid))

    @api.delete("/schedules/{sid}", status_code=204, dependencies=write, tags=["schedules"])
    def delete_schedule(sid: str) -> Response:
        service.store.delete_schedule(sid)
        return Response(status_code=204)

    app.include_router(api)
    app.add_middleware(_CountRequests, metrics=service.metrics)
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
