"""What the REST API's routes share: :class:`Service` (config, store, job runner, scheduler,
metrics and the rig's description of one rig), the response cache of the read endpoints, and the
JSON-bytes response class."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from starlette.responses import JSONResponse  # what fastapi.responses re-exports, without FastAPI itself

from service.calibrating import RESULT_KEY, store_calibration
from service.calstore import CalibrationStore
from service.config import RigConfig
from service.jobs import JobContext, JobRunner, MeasureFn, Metrics, ProgressHub
from service.models import JobRequest, MeasurementRequest, planned_duration_s, resolve_sweep
from service.parts import with_parts
from service.recipestore import RecipeStore
from service.scheduler import Scheduler
from service.store import Store

RigInfo = Callable[[], dict[str, Any]]


class JsonBytes(JSONResponse):
    """A response whose body is JSON already serialised (cached or built by pydantic). A
    ``JSONResponse`` to FastAPI, so a route's ``response_model`` is its documented body."""

    def render(self, content: Any) -> bytes:
        if not isinstance(content, bytes):
            raise TypeError(f"JsonBytes takes serialised JSON (bytes), not {type(content).__name__}")
        return content


@dataclass
class RigLive:
    """The last reading of the rig's devices (``rig_info()``) and when it was taken (monotonic s)."""

    read_at: float = -1e9
    info: dict[str, Any] = field(default_factory=dict)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    body: tuple[tuple[float, bool, bool], bytes] | None = None
    """The serialised ``GET /rig`` body and what it was built from (reading time, token, busy)."""


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
        rig_health: RigInfo | None = None,
        rig_reset: RigInfo | None = None,
        recipes: RecipeStore | None = None,
    ) -> None:
        self.config = config
        self.store = store or Store(config.storage.db_url, config.storage.rig_id)
        self.calibrations = CalibrationStore(self.store.engine)
        """Rig calibrations (``/api/v1/calibrations``); the active one of the store's ``rig_id`` is used by
        every measurement."""
        self.recipes = recipes or RecipeStore(self.store.engine)
        """Versioned recipes and the parts measured with them (service.recipestore)."""
        measure = with_parts(measure, self.recipes)
        self.metrics = Metrics()
        self.hub = ProgressHub()

        def measure_calibrated(ctx: JobContext) -> dict[str, Any]:
            if ctx.request.target == "calibration":  # a calibration sweep starts from the nominal rig
                ctx.calibration = None
                result = measure(ctx)
                ctx.info["partial_result"] = {k: v for k, v in result.items() if k != RESULT_KEY}
                ctx.check_cancelled()  # cancelled during the adjustment: nothing is stored
                return store_calibration(result, ctx, self.calibrations, self.store.rig_id)
            active = self.calibrations.active(self.store.rig_id)
            ctx.calibration = None if active is None else active.payload()
            return measure(ctx)

        self.runner = JobRunner(
            self.store,
            measure_calibrated,
            config.storage.raw_dir,
            config.storage.cloud_dir,
            self.hub,
            self.metrics,
            max_queued=config.jobs.max_queued,
            expected_duration_s=lambda req: expected_duration_s(req, config),
        )
        self.scheduler = Scheduler(self.store, self.runner, self.recipes)
        self.rig_info = rig_info or (lambda: {})
        self.rig_health = rig_health
        """``/healthz``'s rig part (``status``, ``reasons``, rig process, drive); None: no rig to check."""
        self.rig_reset = rig_reset
        """Clear a drive fault (``POST /api/v1/rig/reset``); None: not available."""
        self.validate = validate
        self.cache = ResponseCache(self.store)
        self.rig_live = RigLive()
        self._started = False

    def start(self, settle_heap: bool = True) -> None:
        """Start the job runner and the scheduler, after :func:`_settle_heap` unless
        ``settle_heap=False`` (``lrms measure``: its sweep and fit run in the rig process, and the
        second of imports would only delay the sweep's start)."""
        if not self._started:
            self._started = True
            if settle_heap:
                _settle_heap()
            self.runner.start()
            self.scheduler.start()

    def stop(self) -> None:
        if self._started:
            self._started = False
            self.scheduler.stop()
            self.runner.stop()
            self.recipes.close()  # its connections; the store opens new ones if asked again

    def token(self) -> str | None:
        """The operator token (None: not configured)."""
        return self.config.role_token("operator")

    def write_enabled(self) -> bool:
        """Whether any token may write (an operator or an admin token is configured)."""
        return self.token() is not None or self.config.role_token("admin") is not None


def expected_duration_s(req: MeasurementRequest, config: RigConfig) -> float:
    """A guess of a measurement's wall time before any has finished: its planned sweep plus 10 s
    (approach, run-out, mapping and fit), plus 60 s for a calibration sweep's adjustment."""
    try:
        return planned_duration_s(
            resolve_sweep(req.sweep, config), scan_frequency_hz=config.scanner.scan_frequency_hz
        ) + (70.0 if isinstance(req, JobRequest) and req.target == "calibration" else 10.0)
    except ValueError:
        return 60.0


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
