"""Request and response models of schedules (``/api/v1/schedules``): a cron expression or an
interval, the measurement each run queues (:class:`ScheduledMeasurement`, whose part id may be a
pattern), and their checks against the rig. The measurement's own models are
:mod:`service.models`.
"""

from __future__ import annotations

import math
import re
import string
from datetime import UTC, datetime
from typing import Any

from pydantic import BaseModel, Field, field_validator, model_validator

from service.config import RigConfig
from service.errors import Loc, RequestFieldError
from service.models import PART_ID_PATTERN, MeasurementRequest, _Strict, resolve_sweep

#: Cron strings: at most this many characters, and exactly five fields (minute hour day month weekday).
CRON_MAX_LENGTH = 120
#: Five fields separated by white space (croniter checks each field, and that the dates occur).
CRON_PATTERN = r"^\s*\S+(\s+\S+){4}\s*$"
#: Upcoming firings of a cron schedule checked against ``[schedules] min_interval_s``: at most this
#: many, and none beyond the horizon (two leap-year cycles, for gaps that occur around 29 February).
CRON_FIRINGS_CHECKED = 512
CRON_HORIZON_S = 8 * 366 * 86400.0


def check_cron(cron: str) -> str:
    """A 5-field cron expression (UTC) that fires: the reason it is refused, else ``""``."""
    from croniter import croniter

    if len(cron.split()) != 5:
        return f"a cron expression has exactly 5 fields (minute hour day month weekday), not {len(cron.split())}"
    if not croniter.is_valid(cron):
        return f"not a valid cron expression: {cron!r}"
    try:
        croniter(cron, datetime.now(UTC)).get_next(float)
    except Exception:  # croniter's CroniterBadDateError and kin: no such date (30 February)
        return f"the cron expression {cron!r} never fires (no such date)"
    return ""


def cron_min_interval_s(cron: str, firings: int = CRON_FIRINGS_CHECKED, below: float = math.inf) -> float:
    """The shortest time between two of the next ``firings`` firings of ``cron`` within
    :data:`CRON_HORIZON_S` (stops early at one shorter than ``below``); ``inf`` when fewer than
    two are found."""
    from croniter import croniter

    it = croniter(cron, datetime.now(UTC))
    shortest = math.inf
    try:
        prev = first = float(it.get_next(float))
        for _ in range(firings - 1):
            t = float(it.get_next(float))
            if t - first > CRON_HORIZON_S:
                break
            shortest = min(shortest, t - prev)
            if shortest < below:
                break
            prev = t
    except Exception:  # no further date (a pattern that fires a few times only)
        pass
    return shortest


#: A schedule's part id: a part id with placeholders (:func:`render_part_id`).
PART_ID_TEMPLATE_PATTERN = r"^[A-Za-z0-9{][A-Za-z0-9_.:/{}-]{0,127}$"
PART_ID_FIELDS = ("date", "time", "n")


def render_part_id(template: str, when: float, n: int) -> str:
    """The part id of a schedule's ``n``-th run (from 1) at ``when`` (Unix time): ``{date}`` is the
    UTC date ``YYYYMMDD``, ``{time}`` the UTC time ``HHMMSS``, ``{n}`` the run number (format specs
    as Python's: ``{n:04d}``). ValueError for another placeholder, a bad format spec, or an id that
    is not a valid part id."""
    t = datetime.fromtimestamp(when, tz=UTC)
    values: dict[str, Any] = {"date": t.strftime("%Y%m%d"), "time": t.strftime("%H%M%S"), "n": n}
    try:
        for _, field, _, conversion in string.Formatter().parse(template):
            if field is not None and (field not in PART_ID_FIELDS or conversion is not None):
                raise ValueError(
                    f"unknown placeholder {{{field}}} in {template!r}; known: "
                    + ", ".join(f"{{{f}}}" for f in PART_ID_FIELDS)
                )
        out = template.format(**values)
    except (IndexError, KeyError, ValueError) as exc:
        raise ValueError(f"part id pattern {template!r}: {exc}") from None
    if re.fullmatch(PART_ID_PATTERN, out) is None:
        raise ValueError(f"part id pattern {template!r} makes {out!r}, which is not a part id ({PART_ID_PATTERN})")
    return out


class ScheduledMeasurement(MeasurementRequest):
    """A schedule's measurement: free form, or a part of a recipe whose ``part_id`` may be a
    pattern (``"{date}-{n}"``), filled in at each run (:func:`render_part_id`)."""

    part_id: str | None = Field(
        default=None,
        pattern=PART_ID_TEMPLATE_PATTERN,
        description="the part id, or a pattern of one: {date} (UTC, YYYYMMDD), {time} (UTC, HHMMSS), {n} (the "
        "schedule's run number, from 1; {n:04d} pads it)",
    )

    @field_validator("part_id")
    @classmethod
    def _renders(cls, v: str | None) -> str | None:
        if v is not None:
            render_part_id(v, 0.0, 1)
        return v

    def for_run(self, when: float, n: int) -> MeasurementRequest:
        """The measurement request of the schedule's ``n``-th run at ``when``."""
        data = self.model_dump(exclude_unset=True)
        if self.part_id is not None:
            data["part_id"] = render_part_id(self.part_id, when, n)
        return MeasurementRequest.model_validate(data)


class ScheduleRequest(_Strict):
    """A schedule: a cron expression (UTC) or an interval, and the measurement to run."""

    name: str = Field(default="", max_length=200)
    cron: str | None = Field(
        default=None,
        min_length=9,
        max_length=CRON_MAX_LENGTH,
        json_schema_extra={"pattern": CRON_PATTERN},  # checked by _cron_fires, with a clearer message
        examples=["0 */2 * * *", "30 6 * * 1-5"],
        description="5-field cron expression, UTC, e.g. '0 */2 * * *'; it must fire, and not more often than "
        "the rig's [schedules] min_interval_s",
    )
    interval_s: float | None = Field(
        default=None, ge=1.0, le=366 * 86400.0, description="at least the rig's [schedules] min_interval_s"
    )
    measurement: ScheduledMeasurement

    @field_validator("cron")
    @classmethod
    def _cron_fires(cls, v: str | None) -> str | None:
        if v is not None:
            reason = check_cron(v)
            if reason:
                raise ValueError(reason)
        return v

    @model_validator(mode="after")
    def _one_trigger(self) -> ScheduleRequest:
        if (self.cron is None) == (self.interval_s is None):
            raise ValueError("give exactly one of cron or interval_s")
        return self


def check_schedule(req: ScheduleRequest, config: RigConfig) -> None:
    """Check a schedule against the rig: its measurement's sweep (:func:`resolve_sweep`) and the
    minimum interval between firings; :class:`RequestFieldError` names the fields."""
    errors: list[tuple[Loc, str]] = []
    try:
        resolve_sweep(req.measurement.sweep, config)
    except RequestFieldError as exc:
        errors += exc.under("measurement").errors
    least = config.schedules.min_interval_s
    if req.interval_s is not None and req.interval_s < least:
        errors.append(
            (("interval_s",), f"{req.interval_s:g} s is shorter than [schedules] min_interval_s = {least:g} s")
        )
    if req.cron is not None and least > 60.0:  # five fields fire at most once a minute
        shortest = cron_min_interval_s(req.cron, below=least)
        if shortest < least:
            errors.append(
                (
                    ("cron",),
                    f"{req.cron!r} fires {shortest:g} s apart, more often than "
                    f"[schedules] min_interval_s = {least:g} s",
                )
            )
    if errors:
        raise RequestFieldError(errors)


class ScheduleOut(BaseModel):
    id: str
    name: str
    cron: str | None
    interval_s: float | None
    measurement: dict[str, Any]
    next_run: float | None
    last_run: float | None
    last_measurement_id: str | None
    rig_id: str = Field(default="", description="the rig whose service runs it ([storage] rig_id)")
