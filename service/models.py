"""Request and response models shared by the REST API, the job runner, schedules and the CLI.

Degrees at the edge (``*_deg``), metres for lengths (``*_m``). Unknown fields are rejected so
that a misspelt option is a 422 with the field's name, not a silent default.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.config import RigConfig


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class SweepSpec(_Strict):
    """The sweep of the scan plane. Missing fields take the rig's ``[sweep]`` defaults."""

    start_deg: float | None = Field(default=None, ge=-180.0, le=180.0, description="first beta (deg)")
    stop_deg: float | None = Field(default=None, ge=-180.0, le=180.0, description="last beta (deg)")
    speed_deg_s: float | None = Field(default=None, gt=0.0, le=360.0, description="constant sweep speed")
    mode: Literal["constant", "step"] | None = Field(default=None, description="constant velocity or step-and-scan")
    step_deg: float | None = Field(default=None, gt=0.0, le=90.0, description="step of the step-and-scan mode")
    scans_per_step: int | None = Field(default=None, ge=1, le=1000)


class RoiSpec(_Strict):
    """Axis-aligned box in the world frame (m); points outside are not fitted."""

    min_m: tuple[float, float, float] | None = None
    max_m: tuple[float, float, float] | None = None

    @model_validator(mode="after")
    def _ordered(self) -> RoiSpec:
        if (
            self.min_m is not None
            and self.max_m is not None
            and any(a >= b for a, b in zip(self.min_m, self.max_m, strict=True))
        ):
            raise ValueError("roi min_m must be below max_m on every axis")
        return self


class FitOptions(_Strict):
    k: float | None = Field(default=None, gt=0.0, le=10.0, description="coverage factor of the critical-point interval")
    monte_carlo: int = Field(
        default=0, ge=0, le=2000, description="Monte Carlo refits for the 95 % interval (GUM-S1): 0 = off, else >= 40"
    )
    seed: int | None = Field(default=None, description="random seed of RANSAC and Monte Carlo")
    degree_deg: float | None = Field(
        default=None, gt=0.0, le=180.0, description="elbow: joint degree (deg); none = from the cloud"
    )
    ratio: float | None = Field(default=None, ge=0.5, le=20.0, description="elbow: fixed A/D ratio; none = free")
    flange: bool = Field(default=False, description="elbow: the joint has flanges (fit their diameter Df)")
    nominal_diameter_m: float | None = Field(
        default=None,
        gt=0.0,
        le=10.0,
        description="cylinder: nominal diameter (m); other sizes are rejected",
    )
    diameter_tolerance_m: float | None = Field(
        default=None, gt=0.0, le=10.0, description="cylinder: accepted deviation from nominal_diameter_m (default 10 %)"
    )

    @model_validator(mode="after")
    def _enough_replicas(self) -> FitOptions:
        if 0 < self.monte_carlo < 40:
            raise ValueError(f"monte_carlo = {self.monte_carlo}: a 95 % interval needs at least 40 replicas (or 0)")
        return self


class MeasurementRequest(_Strict):
    target: Literal["cylinder", "elbow"]
    sweep: SweepSpec = Field(default_factory=SweepSpec)
    roi: RoiSpec | None = None
    options: FitOptions = Field(default_factory=FitOptions)

    @model_validator(mode="after")
    def _options_fit_target(self) -> MeasurementRequest:
        o = self.options
        if self.target != "elbow" and (o.degree_deg is not None or o.ratio is not None or o.flange):
            raise ValueError("options degree_deg, ratio and flange apply to target 'elbow' only")
        if self.target != "cylinder" and (o.nominal_diameter_m is not None or o.diameter_tolerance_m is not None):
            raise ValueError("options nominal_diameter_m and diameter_tolerance_m apply to target 'cylinder' only")
        if o.diameter_tolerance_m is not None and o.nominal_diameter_m is None:
            raise ValueError("diameter_tolerance_m needs nominal_diameter_m")
        tol, nominal = o.diameter_tolerance_m, o.nominal_diameter_m
        if tol is not None and nominal is not None and tol >= nominal:
            raise ValueError("diameter_tolerance_m must be below nominal_diameter_m")
        return self


class ResolvedSweep(BaseModel):
    """A sweep with every field filled in (rig defaults applied)."""

    start_deg: float
    stop_deg: float
    speed_deg_s: float
    mode: Literal["constant", "step"]
    step_deg: float
    scans_per_step: int
    acceleration_deg_s2: float


def resolve_sweep(spec: SweepSpec, config: RigConfig) -> ResolvedSweep:
    d = config.sweep
    out = ResolvedSweep(
        start_deg=d.start_deg if spec.start_deg is None else spec.start_deg,
        stop_deg=d.stop_deg if spec.stop_deg is None else spec.stop_deg,
        speed_deg_s=d.speed_deg_s if spec.speed_deg_s is None else spec.speed_deg_s,
        mode=d.mode if spec.mode is None else spec.mode,
        step_deg=d.step_deg if spec.step_deg is None else spec.step_deg,
        scans_per_step=d.scans_per_step if spec.scans_per_step is None else spec.scans_per_step,
        acceleration_deg_s2=d.acceleration_deg_s2,
    )
    if out.start_deg == out.stop_deg:
        raise ValueError("sweep start_deg and stop_deg must differ")
    return out


#: Speed of the approach move to the sweep's run-up point (``service.sweep.SweepPlan.approach_speed``).
APPROACH_SPEED_DEG_S = 30.0


def _move_time_s(distance_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> float:
    """A point-to-point move of a trapezoidal profile (a triangle when too short to reach speed)."""
    d = abs(distance_deg)
    if d == 0.0:
        return 0.0
    ramp = speed_deg_s * speed_deg_s / acceleration_deg_s2  # distance of the two ramps together
    if d >= ramp:
        return d / speed_deg_s + speed_deg_s / acceleration_deg_s2
    return 2.0 * math.sqrt(d / acceleration_deg_s2)


def planned_duration_s(sweep: ResolvedSweep, config: RigConfig, start_from_deg: float | None = None) -> float:
    """Planned motion time of a sweep (s), to compare with ``[sweep] max_duration_s``.

    Constant speed: the move from ``start - run_up`` to ``stop + run_up`` (``run_up = v^2 / 2a +
    0.5 deg``, as :attr:`service.sweep.SweepPlan.run_up`). Step-and-scan: one move per step plus
    the dwell of ``scans_per_step + 1`` scan periods and 50 ms at each stop (as
    :func:`service.sweep.run_sweep`). The approach (at 30 deg/s) is included only when
    ``start_from_deg`` (the beta the motor starts from) is given: the motor's position is known
    at run time only. Scanner run-out, mapping and the fit are not included.
    """
    v, a = sweep.speed_deg_s, sweep.acceleration_deg_s2
    direction = 1.0 if sweep.stop_deg > sweep.start_deg else -1.0
    span = abs(sweep.stop_deg - sweep.start_deg)
    if sweep.mode == "constant":
        run_up = v * v / (2.0 * a) + 0.5
        first = sweep.start_deg - direction * run_up
        t = _move_time_s(span + 2.0 * run_up, v, a)
    else:
        first = sweep.start_deg
        n = math.floor(span / sweep.step_deg + 1e-9) + 1
        dwell = 0.05 + (sweep.scans_per_step + 1) / float(config.scanner.scan_frequency_hz)
        t = (n - 1) * _move_time_s(sweep.step_deg, v, a) + n * dwell
    if start_from_deg is not None:
        t += _move_time_s(first - start_from_deg, APPROACH_SPEED_DEG_S, a)
    return t


class ScheduleRequest(_Strict):
    """A schedule: a cron expression (UTC) or an interval, and the measurement to run."""

    name: str = Field(default="", max_length=200)
    cron: str | None = Field(default=None, description="5-field cron expression, UTC, e.g. '0 */2 * * *'")
    interval_s: float | None = Field(default=None, ge=1.0, le=366 * 86400.0)
    measurement: MeasurementRequest

    @model_validator(mode="after")
    def _one_trigger(self) -> ScheduleRequest:
        if (self.cron is None) == (self.interval_s is None):
            raise ValueError("give exactly one of cron or interval_s")
        if self.cron is not None:
            from croniter import croniter

            if not croniter.is_valid(self.cron):
                raise ValueError(f"not a valid cron expression: {self.cron!r}")
        return self


class MeasurementOut(BaseModel):
    id: str
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    created_at: float
    started_at: float | None
    finished_at: float | None
    progress: float
    message: str
    request: dict[str, Any]
    result: dict[str, Any] | None
    error: str | None
    has_raw: bool
    raw_truncated: bool = Field(
        default=False,
        description="the raw log was rebuilt from a file cut short when the service process died: "
        "complete and indexed, but it ends where the process stopped (the error says where)",
    )
    has_cloud: bool
    schedule_id: str | None


class ScheduleOut(BaseModel):
    id: str
    name: str
    cron: str | None
    interval_s: float | None
    measurement: dict[str, Any]
    next_run: float | None
    last_run: float | None
    last_measurement_id: str | None
