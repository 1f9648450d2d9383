"""The job runner: one sweep at a time, the others wait in the store's queue.

A worker thread takes the oldest queued measurement, marks it running, calls the measurement
function with a :class:`JobContext` (progress reporting, cancellation, where to put the raw log
and the cloud), and records the outcome: ``done`` with the result, ``failed`` with the reason
(the error's message; an unexpected exception is reported with its type), or ``cancelled``.
The queue lives in SQLite, so queued work survives a restart and resumes in order;
:meth:`JobRunner.start` first marks measurements a dead process left running as failed, after
rebuilding the raw log such a process left cut short into a complete one (served as truncated).

Progress goes to the store (throttled) and to a :class:`ProgressHub`, an in-memory board of the
latest event per measurement with a version number, which the server-sent-events endpoint polls
without touching the database.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from drivers.errors import DriverError
from lrms.errors import LrmsError
from service import mcaprecovery
from service.errors import ServiceError
from service.models import JobRequest, MeasurementRequest

if TYPE_CHECKING:  # the store (SQLAlchemy, Alembic) is imported where it is used: the rig process
    # imports this module for JobContext and Cancelled only, and never opens a store
    from service.store import Measurement, Store

log = logging.getLogger(__name__)


class Cancelled(ServiceError):
    """The measurement was cancelled while it ran."""


class QueueFull(ServiceError):
    """``max_queued`` measurements already wait; ``retry_after_s`` estimates when one will have started."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class ProgressHub:
    """Latest progress event per measurement, with a version counter for cheap polling."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._events: dict[str, tuple[int, dict[str, Any]]] = {}
        self._version = 0

    def publish(self, m: Measurement, **extra: Any) -> None:
        event = {
            "id": m.id,
            "state": m.state,
            "progress": m.progress,
            "message": m.message,
            "error": m.error,
            **extra,
        }
        with self._lock:
            self._version += 1
            self._events[m.id] = (self._version, event)
            if len(self._events) > 10_000:  # forget the oldest finished ones
                from service.store import FINAL_STATES

                for key in list(self._events)[:1000]:
                    if self._events[key][1]["state"] in FINAL_STATES:
                        del self._events[key]

    def progress(self, mid: str, fraction: float, message: str) -> None:
        with self._lock:
            old = self._events.get(mid)
            base: dict[str, Any] = dict(old[1]) if old else {"id": mid, "state": "running", "error": None}
            base.update(progress=fraction, message=message)
            self._version += 1
            self._events[mid] = (self._version, base)

    def latest(self, mid: str) -> tuple[int, dict[str, Any]] | None:
        with self._lock:
            return self._events.get(mid)


class Metrics:
    """Prometheus metrics of the service (own registry, so several apps can live in one process)."""

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        self.registry = registry or CollectorRegistry()
        self.finished = Counter(
            "lrms_measurements_finished", "Measurements finished, by final state", ["state"], registry=self.registry
        )
        self.queued = Gauge("lrms_measurements_queued", "Measurements waiting in the queue", registry=self.registry)
        self.running = Gauge("lrms_measurement_running", "1 while a sweep runs", registry=self.registry)
        self.duration = Histogram(
            "lrms_measurement_seconds",
            "Wall time of a measurement (sweep, mapping, fit)",
            buckets=(1, 2, 5, 10, 20, 30, 60, 120, 300, 600),
            registry=self.registry,
        )
        self.scans = Counter("lrms_scans_received", "Scans received from the scanner", registry=self.registry)
        self.scans_missing = Counter("lrms_scans_missing", "Scans missing (scan counter gaps)", registry=self.registry)
        self.schedule_skipped = Counter(
            "lrms_schedule_runs_skipped",
            "Due schedule runs not queued, by reason",
            ["reason"],
            registry=self.registry,
        )
        self.queue_rejected = Counter(
            "lrms_measurements_rejected",
            "Measurements refused because the queue was full (requests and schedule runs)",
            registry=self.registry,
        )
        self.http_requests = Counter(
            "lrms_http_requests", "HTTP requests", ["method", "route", "status"], registry=self.registry
        )
        self.loop_lag = Histogram(
            "lrms_event_loop_lag_seconds",
            "How late the API's event loop wakes a 20 ms sleep (GIL held by other threads, CPU starvation)",
            buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0),
            registry=self.registry,
        )
        self.http_seconds = Histogram(
            "lrms_http_request_seconds",
            "Time from a request reaching the app to its response headers being sent",
            buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0),
            registry=self.registry,
        )


@dataclass
class JobContext:
    """What a measurement function gets: the request, where to write, progress and cancellation."""

    measurement: Measurement
    request: JobRequest
    raw_path: Path
    cloud_path: Path
    cancel_event: threading.Event
    report: Callable[[float, str], None]
    metrics: Metrics | None = None
    info: dict[str, Any] = field(default_factory=dict)
    calibration: dict[str, Any] | None = None
    """The rig's active calibration (:meth:`service.calstore.StoredCalibration.payload`), set by
    the service when the measurement starts; None: the rig's ``[kinematics]`` as configured."""
    finish_also: Callable[[Any], None] | None = None
    """More writes in the transaction that marks the measurement done (``(connection) -> None``,
    :meth:`service.store.Store.finish`): a calibration sweep's calibration is stored with its
    job's result or not at all."""

    def progress(self, fraction: float, message: str) -> None:
        self.report(fraction, message)

    @property
    def cancelled(self) -> bool:
        return self.cancel_event.is_set()

    def check_cancelled(self) -> None:
        if self.cancel_event.is_set():
            raise Cancelled("cancelled by request")


MeasureFn = Callable[[JobContext], dict[str, Any]]


class JobRunner:
    """Runs queued measurements one at a time on a worker thread."""

    def __init__(
        self,
        store: Store,
        measure: MeasureFn,
        raw_dir: Path,
        cloud_dir: Path,
        hub: ProgressHub | None = None,
        metrics: Metrics | None = None,
        progress_interval_s: float = 0.25,
        max_queued: int | None = None,
        expected_duration_s: Callable[[MeasurementRequest], float] | None = None,
    ) -> None:
        self.store = store
        self.measure = measure
        self.raw_dir = Path(raw_dir)
        self.cloud_dir = Path(cloud_dir)
        self.hub = hub or ProgressHub()
        self.metrics = metrics or Metrics()
        self.progress_interval_s = progress_interval_s
        self.max_queued = max_queued
        self.expected_duration_s = expected_duration_s
        self._durations: deque[float] = deque(maxlen=10)
        self._running_since: float | None = None
        self._running_request: MeasurementRequest | None = None
        self._submit_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._running_id: str | None = None
        self._cancel = threading.Event()
        self._thread: threading.Thread | None = None
        self.recovered: list[str] = []

    # -- control --------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            return
        self.raw_dir.mkdir(parents=True, exist_ok=True)
        self.cloud_dir.mkdir(parents=True, exist_ok=True)
        self.recovered = [self._recover(mid) for mid in self.store.interrupted()]
        for mid in self.recovered:
            self.metrics.finished.labels("failed").inc()
            self.hub.publish(self.store.get(mid))
        self._thread = threading.Thread(target=self._loop, name="lrms-jobs", daemon=True)
        self._thread.start()
        self._wake.set()

    def _recover(self, mid: str) -> str:
        """Fail a measurement a dead process left running, keeping what its raw log holds: a log
        cut short is rebuilt into a complete MCAP file (:func:`service.mcaprecovery.recover_log`), served
        with ``raw_truncated``; the failure reason says where it ends and how much it holds."""
        raw = self.raw_dir / f"{mid}.mcap"
        from service.store import INTERRUPTED

        cloud = self.cloud_dir / f"{mid}.ply"
        reason = INTERRUPTED
        raw_path: str | None = None
        truncated = False
        if raw.exists():
            try:
                rec = mcaprecovery.recover_log(raw)
            except (OSError, ServiceError) as exc:
                log.error("measurement %s: its raw log %s could not be recovered: %s", mid, raw, exc)
                reason += f"; its raw log could not be recovered: {exc}"
            else:
                if rec.messages:
                    raw_path, truncated = str(raw), rec.truncated
                if rec.truncated:
                    reason += f"; {rec.describe()}"
                log.warning("measurement %s failed: %s", mid, reason)
        else:
            reason += "; it had no raw log"
        self.store.fail_interrupted(
            mid, reason, raw_path=raw_path, cloud_path=str(cloud) if cloud.exists() else None, raw_truncated=truncated
        )
        return mid

    def stop(self, timeout: float = 30.0) -> None:
        """Stop the worker; a running measurement is cancelled (its motor stopped by the rig)."""
        self._stop.set()
        self._cancel.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    @property
    def running_id(self) -> str | None:
        return self._running_id

    def retry_after_s(self) -> int:
        """Seconds until the queue probably has room: what the running measurement probably still
        needs (the mean wall time of the last ten, else ``expected_duration_s`` of its request,
        else 60 s), at least 1."""
        since, req = self._running_since, self._running_request
        if since is None:
            return 1
        if self._durations:
            expected = sum(self._durations) / len(self._durations)
        elif self.expected_duration_s is not None and req is not None:
            expected = self.expected_duration_s(req)
        else:
            expected = 60.0
        return max(1, math.ceil(expected - (time.monotonic() - since)))

    def submit(self, request: MeasurementRequest, schedule_id: str | None = None) -> Measurement:
        """Queue a measurement; :class:`QueueFull` when ``max_queued`` already wait."""
        with self._submit_lock:  # the count and the insert together: concurrent posts cannot overfill
            if self.max_queued is not None:
                queued = self.store.count_by_state()["queued"]
                if queued >= self.max_queued:
                    self.metrics.queue_rejected.inc()
                    raise QueueFull(
                        f"the queue is full ({queued} of {self.max_queued} measurements waiting)", self.retry_after_s()
                    )
            m = self.store.create_measurement(request.model_dump(mode="json"), schedule_id=schedule_id)
        self.hub.publish(m)
        self.metrics.queued.set(len(self.store.queued()))
        self._wake.set()
        return m

    def cancel(self, mid: str) -> Measurement:
        """Cancel a queued measurement at once, or ask the running one to stop."""
        from service.store import FINAL_STATES, StoreError

        with self._lock:
            m = self.store.get(mid)
            if m.state in FINAL_STATES:
                raise StoreError(f"measurement {mid} is already {m.state}")
            if m.state == "queued":
                m = self.store.cancel(mid)
                self.metrics.finished.labels("cancelled").inc()
                self.hub.publish(m)
                return m
            if self._running_id == mid:
                self._cancel.set()
            return m

    def wait_idle(self, timeout: float) -> bool:
        """Block until nothing is queued or running (for tests and the CLI)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self._running_id is None and not self.store.queued():
                return True
            time.sleep(0.02)
        return False

    # -- worker ---------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(1.0)
            self._wake.clear()
            while not self._stop.is_set():
                queued = self.store.queued()
                self.metrics.queued.set(len(queued))
                if not queued:
                    break
                self._run_one(queued[0])

    def _run_one(self, m: Measurement) -> None:
        from service.store import StoreError

        with self._lock:
            try:
                m = self.store.start(m.id)
            except StoreError:  # cancelled between listing and starting
                return
            self._running_id = m.id
            self._cancel.clear()
        self.metrics.running.set(1)
        self.hub.publish(m)
        t_start = time.monotonic()
        self._running_since = t_start
        last = [0.0]

        def report(fraction: float, message: str) -> None:
            now = time.monotonic()
            self.hub.progress(m.id, fraction, message)
            if now - last[0] >= self.progress_interval_s or fraction >= 1.0:
                last[0] = now
                self.store.set_progress(m.id, fraction, message)

        request = JobRequest.model_validate(m.request)
        self._running_request = request
        ctx = JobContext(
            measurement=m,
            request=request,
            raw_path=self.raw_dir / f"{m.id}.mcap",
            cloud_path=self.cloud_dir / f"{m.id}.ply",
            cancel_event=self._cancel,
            report=report,
            metrics=self.metrics,
        )
        state = "failed"
        try:
            result = self.measure(ctx)
            self._record_paths(ctx)
            done = self.store.finish(m.id, result, ctx.finish_also)
            state = "done"
            self.hub.publish(done)
        except Cancelled as exc:
            self._record_paths(ctx)
            state = "cancelled"
            self.hub.publish(self.store.cancel(m.id, str(exc)))
        except (ServiceError, DriverError, LrmsError) as exc:
            reason = (str(exc) or type(exc).__name__) + self._record_paths(ctx)
            self.hub.publish(self.store.fail(m.id, reason, ctx.info.get("partial_result")))
        except Exception as exc:  # a bug: keep the traceback in the log, the reason in the store
            log.exception("measurement %s crashed", m.id)
            reason = f"internal error: {type(exc).__name__}: {exc}" + self._record_paths(ctx)
            self.hub.publish(self.store.fail(m.id, reason))
        finally:
            self.metrics.finished.labels(state).inc()
            self.metrics.duration.observe(time.monotonic() - t_start)
            if state == "done":
                self._durations.append(time.monotonic() - t_start)
            self.metrics.running.set(0)
            with self._lock:
                self._running_id = None
                self._running_since = self._running_request = None

    def _record_paths(self, ctx: JobContext) -> str:
        """Store where the raw log and the cloud are. A raw log without its summary (the process
        that wrote it died: the rig process, or its fit worker) is rebuilt into a complete one
        first and served as truncated; the text returned then says so, for the failure reason."""
        raw = str(ctx.raw_path) if ctx.raw_path.exists() else None
        cloud = str(ctx.cloud_path) if ctx.cloud_path.exists() else None
        note, truncated = "", False
        if raw is not None and not mcaprecovery.has_summary(raw):
            try:
                rec = mcaprecovery.recover_log(raw)
            except (OSError, ServiceError) as exc:
                log.error("measurement %s: its raw log %s could not be recovered: %s", ctx.measurement.id, raw, exc)
                note = f"; its raw log could not be recovered: {exc}"
            else:
                truncated = rec.truncated
                note = f"; {rec.describe()}" if rec.truncated else ""
                if not rec.messages:
                    raw = None
        if raw or cloud:
            self.store.set_paths(ctx.measurement.id, raw_path=raw, cloud_path=cloud, raw_truncated=truncated)
        return note
