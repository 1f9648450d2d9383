"""Scheduled measurements: a cron expression (UTC, via croniter) or a fixed interval.

Each schedule holds a measurement template. A scheduler thread wakes at the earliest due time
(at least once a second), queues one measurement per due schedule through the job runner and
computes the next due time from *now*: runs missed while the service was down are not replayed
one by one; a schedule that came due during the outage runs once at start-up. A run that comes
due while the job queue is full (``[jobs] max_queued``) is skipped, not piled up: logged with
the reason, counted (``lrms_schedule_runs_skipped_total{reason="queue_full"}``), and the
schedule's ``last_run`` moves on with ``last_measurement_id`` null.

A schedule may measure parts of a recipe: its template names the recipe (and optionally a pinned
``recipe_version``; default: the latest version when the run fires) and a part id, which may be a
pattern (``"{date}-{n}"``, :func:`service.schedulemodels.render_part_id`; ``{n}`` counts the schedule's
measurements from 1). A run the recipe store refuses (the recipe retired or gone since) is skipped
the same way (``reason="refused"``), with the reason logged.
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import UTC, datetime

from service.errors import RequestFieldError
from service.jobs import JobRunner, QueueFull
from service.models import MeasurementRequest
from service.parts import resolve_part
from service.recipestore import RecipeStore
from service.schedulemodels import ScheduledMeasurement, ScheduleRequest
from service.store import Schedule, Store

log = logging.getLogger(__name__)


def next_run(cron: str | None, interval_s: float | None, after: float) -> float:
    """The first due time strictly after ``after`` (epoch seconds)."""
    if cron is not None:
        from croniter import croniter  # only when a cron schedule is parsed (not at the service's start)

        it = croniter(cron, datetime.fromtimestamp(after, tz=UTC))
        return float(it.get_next(float))
    if interval_s is None or interval_s <= 0:
        raise ValueError("a schedule needs a cron expression or a positive interval")
    return after + interval_s


class Scheduler:
    def __init__(self, store: Store, runner: JobRunner, recipes: RecipeStore | None = None) -> None:
        self.store = store
        self.runner = runner
        self.recipes = recipes
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self.fired = 0
        self.skipped = 0

    def add(self, req: ScheduleRequest) -> Schedule:
        now = time.time()
        nxt = next_run(req.cron, req.interval_s, now)
        m = req.measurement  # a recipe's template keeps what was given: the recipe supplies the rest
        s = self.store.add_schedule(
            m.model_dump(mode="json", exclude_unset=m.recipe is not None),
            cron=req.cron,
            interval_s=req.interval_s,
            next_run=nxt,
            name=req.name,
        )
        self._wake.set()
        return s

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="lrms-scheduler", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def tick(self, now: float | None = None) -> float:
        """Queue every due schedule; return the earliest next due time (or now + 1 s)."""
        t = time.time() if now is None else now
        earliest = t + 1.0
        for s in self.store.list_schedules(rig=self.store.rig_id):
            if not s.enabled:
                continue
            due = s.next_run if s.next_run is not None else t
            if due <= t:
                mid = None
                try:
                    req = self.request(s, t)
                    m = self.runner.submit(req, schedule_id=s.id)
                    mid = m.id
                    if req.recipe is not None and req.recipe_version is not None and req.part_id is not None:
                        assert self.recipes is not None
                        self.recipes.link(m.id, req.recipe, req.recipe_version, req.part_id, req.operator)
                    self.fired += 1
                except (QueueFull, RequestFieldError) as exc:
                    self.skipped += 1
                    reason = "queue_full" if isinstance(exc, QueueFull) else "refused"
                    self.runner.metrics.schedule_skipped.labels(reason).inc()
                    log.warning("schedule %s (%s): run skipped: %s", s.id, s.name, exc)
                except Exception:  # a bad stored template must not stop the other schedules
                    log.exception("schedule %s could not queue its measurement", s.id)
                due = next_run(s.cron, s.interval_s, t)
                self.store.mark_schedule_run(s.id, t, due, mid)
            earliest = min(earliest, due)
        return earliest

    def request(self, s: Schedule, when: float) -> MeasurementRequest:
        """The measurement schedule ``s`` queues at ``when``: its template, or for a recipe's part
        the part id rendered for this run and the recipe (latest or pinned version) filled in."""
        template = ScheduledMeasurement.model_validate(s.template)
        if template.recipe is None:
            return MeasurementRequest.model_validate(s.template)
        if self.recipes is None:
            raise RequestFieldError([(("recipe",), "this scheduler has no recipe store")])
        n = self.store.count_schedule_measurements(s.id) + 1
        return resolve_part(template.for_run(when, n), self.recipes)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                nxt = self.tick()
            except Exception:
                log.exception("scheduler tick failed")
                nxt = time.time() + 1.0
            self._wake.wait(max(0.05, min(1.0, nxt - time.time())))
            self._wake.clear()
