"""Request and response models shared by the REST API, the job runner, schedules and the CLI.

Degrees at the edge (``*_deg``), metres for lengths (``*_m``). Unknown fields are rejected so
that a misspelt option is a 422 with the field's name, not a silent default.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer, model_validator

from service.config import MAX_K, MIN_K, MIN_SPEED_DEG_S, MIN_STEP_DEG, RigConfig
from service.errors import Loc, RequestFieldError

#: The speed of the approach to a sweep's start (capped to ``[motor] max_velocity_deg_s``).
APPROACH_SPEED_DEG_S = 30.0
#: Extra travel beyond the constant-speed run-up ``v^2 / 2a`` on both sides of a constant sweep.
RUN_UP_MARGIN_DEG = 0.5
#: Bounds of any coordinate of a region of interest (world frame, m).
ROI_LIMIT_M = 1000.0
#: The most reference spheres and centre distances a calibration artefact may list.
MAX_ARTEFACT_SPHERES = 100
MAX_ARTEFACT_DISTANCES = 1000


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class SweepSpec(_Strict):
    """The sweep of the scan plane. Missing fields take the rig's ``[sweep]`` defaults.

    These are the bounds of any rig; a request is also checked against the rig's own limits
    (``[motor]`` travel and maximum speed, ``[sweep] max_duration_s``) by :func:`resolve_sweep`.
    """

    start_deg: float | None = Field(default=None, ge=-180.0, le=180.0, description="first beta (deg)")
    stop_deg: float | None = Field(default=None, ge=-180.0, le=180.0, description="last beta (deg)")
    speed_deg_s: float | None = Field(
        default=None, ge=MIN_SPEED_DEG_S, le=360.0, description="sweep speed (deg/s); at most the motor's maximum"
    )
    mode: Literal["constant", "step"] | None = Field(default=None, description="constant velocity or step-and-scan")
    step_deg: float | None = Field(
        default=None, ge=MIN_STEP_DEG, le=90.0, description="step of the step-and-scan mode (deg)"
    )
    scans_per_step: int | None = Field(default=None, ge=1, le=1000)


Coordinate = Annotated[float, Field(ge=-ROI_LIMIT_M, le=ROI_LIMIT_M)]


class RoiSpec(_Strict):
    """Axis-aligned box in the world frame (m); points outside are not fitted."""

    min_m: tuple[Coordinate, Coordinate, Coordinate] | None = None
    max_m: tuple[Coordinate, Coordinate, Coordinate] | None = None

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
    k: float | None = Field(
        default=None, ge=MIN_K, le=MAX_K, description="coverage factor of the critical-point interval"
    )
    monte_carlo: int = Field(
        default=0,
        ge=0,
        le=2000,
        description="Monte Carlo refits for the 95 % interval (GUM-S1): 0 = off, else >= 40",
        json_schema_extra={"anyOf": [{"const": 0}, {"minimum": 40}]},
    )
    seed: int | None = Field(default=None, ge=0, le=2**32 - 1, description="random seed of RANSAC and Monte Carlo")
    degree_deg: float | None = Field(
        default=None, ge=1.0, le=180.0, description="elbow: joint degree (deg); none = from the cloud"
    )
    ratio: float | None = Field(default=None, ge=0.5, le=20.0, description="elbow: fixed A/D ratio; none = free")
    flange: bool = Field(default=False, description="elbow: the joint has flanges (fit their diameter Df)")
    nominal_diameter_m: float | None = Field(
        default=None,
        gt=0.0,
        le=10.0,
        description="cylinder: nominal diameter (m); candidates of other sizes are rejected, a final fit outside"
        " the range within 3 of its u is flagged (result diameter_range_excess_m), farther out the measurement fails",
    )
    diameter_tolerance_m: float | None = Field(
        default=None, gt=0.0, le=10.0, description="cylinder: accepted deviation from nominal_diameter_m (default 10 %)"
    )

    @model_validator(mode="after")
    def _enough_replicas(self) -> FitOptions:
        if 0 < self.monte_carlo < 40:
            raise ValueError(f"monte_carlo = {self.monte_carlo}: a 95 % interval needs at least 40 replicas (or 0)")
        return self


class SphereIn(_Strict):
    """A reference sphere of a calibration artefact: its calibrated diameter and that diameter's
    standard uncertainty (m)."""

    diameter_m: float = Field(gt=0.0, le=10.0)
    u_diameter_m: float = Field(default=5e-6, gt=0.0, le=0.01)


class DistanceIn(_Strict):
    """A known centre-to-centre distance between spheres ``a`` and ``b`` (indices into ``spheres``)."""

    a: int = Field(ge=0, le=MAX_ARTEFACT_SPHERES - 1)
    b: int = Field(ge=0, le=MAX_ARTEFACT_SPHERES - 1)
    distance_m: float = Field(gt=0.0, le=100.0)
    u_distance_m: float = Field(default=1e-5, gt=0.0, le=0.01)


class ArtefactIn(_Strict):
    """What a calibration sweep sees (``lrms calibrate --artefact``'s JSON): the planes of the room,
    reference spheres of known diameters at unknown positions, known centre distances."""

    planes: bool = True
    spheres: list[SphereIn] = Field(default_factory=list, max_length=MAX_ARTEFACT_SPHERES)
    distances_m: list[DistanceIn] = Field(default_factory=list, max_length=MAX_ARTEFACT_DISTANCES)

    @model_validator(mode="after")
    def _consistent(self) -> ArtefactIn:
        from lrms.calibration.data import Artefact, ArtefactError

        try:
            Artefact.from_dict(self.model_dump())
        except ArtefactError as exc:
            raise ValueError(str(exc)) from None
        return self


class CalibrationSpec(_Strict):
    """How a calibration sweep's data is adjusted, and what happens to the calibration."""

    artefact: ArtefactIn
    optics: Literal["ideal", "lms1xx"] = Field(
        default="ideal",
        description="the scanner's beam: 'ideal' (thin) or 'lms1xx' (8 mm + 15 mrad spot: the spot scale is "
        "estimated from the reference spheres)",
    )
    plane_points: int = Field(
        default=20000, ge=100, le=1_000_000, description="beams per plane the adjustment uses (a random subset)"
    )
    name: str = Field(default="", max_length=200, description="the stored calibration's name")
    comment: str = Field(default="", max_length=2000, description="the stored calibration's comment")
    activate: bool = Field(default=False, description="make the calibration the rig's active one when it is stored")


#: A calibration sweep's defaults where the request leaves them out: the half turn in front of the
#: rig at 20 deg/s (docs/calibration.md, "How to place the artefacts"), not the rig's ``[sweep]``.
CALIBRATION_SWEEP_DEFAULTS: dict[str, Any] = {
    "start_deg": -90.0,
    "stop_deg": 90.0,
    "speed_deg_s": 20.0,
    "mode": "constant",
}


class CalibrationRequest(CalibrationSpec):
    """``POST /api/v1/calibrations``: run a calibration sweep on the rig and adjust the rig model
    to it (``lrms calibrate`` in the service)."""

    sweep: SweepSpec = Field(
        default_factory=SweepSpec,
        description="the sweep; missing fields: -90..90 deg at 20 deg/s, constant speed (not the rig's [sweep])",
    )

    @model_validator(mode="before")
    @classmethod
    def _not_an_upload(cls, data: Any) -> Any:
        if isinstance(data, dict) and "schema" in data:
            raise ValueError(
                "this is a calibration's JSON (lrms calibrate --out): upload it with POST /api/v1/calibrations/upload;"
                " POST /api/v1/calibrations runs a calibration sweep on the rig"
            )
        return data

    def measurement(self) -> JobRequest:
        """The job's request: target 'calibration' with the sweep's defaults filled in."""
        sweep = {**CALIBRATION_SWEEP_DEFAULTS, **self.sweep.model_dump(exclude_none=True)}
        spec = CalibrationSpec.model_validate(self.model_dump(exclude={"sweep"}))
        return JobRequest(target="calibration", sweep=SweepSpec(**sweep), calibration=spec)


#: Names of recipes (and part ids): letters, digits, ``_`` and ``-`` (no ``.``: ``/recipes/{name}.toml``).
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$"
PART_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.:/-]{0,127}$"
#: The measurement fields a recipe supplies; a request naming a recipe may not give them (422).
RECIPE_FIELDS = ("target", "sweep", "roi", "options")
#: The largest recipe version a request may name (SQLite's integers end at 2^63).
MAX_VERSION = 1_000_000_000


class MeasurementRequest(_Strict):
    """Free form (``target``, ``sweep``, ``roi``, ``options``) or a part of a recipe (``recipe``,
    ``part_id`` and optionally the part's temperature and the operator). The API expands a recipe
    into the free-form fields before the request is stored, with ``recipe_version`` pinned."""

    target: Literal["cylinder", "elbow"] | None = Field(
        default=None, description="the model to fit; required unless a recipe is named"
    )
    sweep: SweepSpec = Field(default_factory=SweepSpec)
    roi: RoiSpec | None = None
    options: FitOptions = Field(default_factory=FitOptions)
    recipe: str | None = Field(
        default=None,
        pattern=NAME_PATTERN,
        description="measure a part of this recipe: the recipe supplies target, sweep, roi and options",
    )
    recipe_version: int | None = Field(
        default=None, ge=1, le=MAX_VERSION, description="the recipe's version (default: the latest)"
    )
    part_id: str | None = Field(default=None, pattern=PART_ID_PATTERN, description="the part's id (with a recipe)")
    part_temperature_c: float | None = Field(
        default=None, ge=-273.15, le=2000.0, description="the part's temperature (°C): the result is corrected to 20 °C"
    )
    temperature_uncertainty_c: float | None = Field(
        default=None, ge=0.0, le=500.0, description="standard uncertainty of part_temperature_c (K)"
    )
    operator: str | None = Field(default=None, max_length=200, description="who measured (for the record)")

    @model_validator(mode="after")
    def _options_fit_target(self) -> MeasurementRequest:
        if self.recipe is None:
            part = [f for f in ("recipe_version", "part_id", "part_temperature_c", "operator") if getattr(self, f)]
            if self.temperature_uncertainty_c is not None:
                part.append("temperature_uncertainty_c")
            if part:
                raise ValueError(f"{', '.join(part)}: only with a recipe (a part's measurement)")
            if self.target is None:
                raise ValueError("target: Field required (give a target, 'cylinder' or 'elbow', or a recipe)")
        elif self.part_id is None:
            raise ValueError("part_id: Field required (a measurement of a recipe is of a part)")
        if (self.temperature_uncertainty_c is None) != (self.part_temperature_c is None):
            raise ValueError(
                "part_temperature_c and temperature_uncertainty_c go together: a hot part's temperature needs its "
                "standard uncertainty (K)"
            )
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


class JobRequest(MeasurementRequest):
    """What the job runner runs and stores: a measurement (:class:`MeasurementRequest`, what
    ``POST /api/v1/measurements`` and schedules take), or a calibration sweep (target
    ``"calibration"`` with ``calibration``, made by ``POST /api/v1/calibrations`` only:
    :meth:`CalibrationRequest.measurement`). ``calibration`` is left out of the JSON when unset,
    so a measurement's stored request is what was asked."""

    target: Literal["cylinder", "elbow", "calibration"] | None = Field(  # type: ignore[assignment]
        default=None, description="the model to fit, or 'calibration' (a calibration sweep)"
    )
    calibration: CalibrationSpec | None = Field(
        default=None, description="target 'calibration' only: what the calibration sweep sees and how it is adjusted"
    )

    @model_validator(mode="after")
    def _calibration_sweep(self) -> JobRequest:
        if (self.target == "calibration") != (self.calibration is not None):
            raise ValueError("calibration: given with target 'calibration' and only then")
        if self.target == "calibration" and (
            self.recipe is not None or self.roi is not None or self.options != FitOptions()
        ):
            raise ValueError("a calibration sweep takes no recipe, roi or options")
        return self

    @model_serializer(mode="wrap")
    def _without_unset_calibration(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        data: dict[str, Any] = handler(self)
        if data.get("calibration", 0) is None:
            del data["calibration"]
        return data


class ResolvedSweep(BaseModel):
    """A sweep with every field filled in (rig defaults applied)."""

    start_deg: float
    stop_deg: float
    speed_deg_s: float
    mode: Literal["constant", "step"]
    step_deg: float
    scans_per_step: int
    acceleration_deg_s2: float


def run_up_deg(speed_deg_s: float, acceleration_deg_s2: float) -> float:
    """Travel before ``start`` and after ``stop`` of a constant sweep, to be at speed over the
    window (:attr:`service.sweep.SweepPlan.run_up`)."""
    return speed_deg_s * speed_deg_s / (2.0 * acceleration_deg_s2) + RUN_UP_MARGIN_DEG


def step_dwell_s(scans_per_step: int, scan_frequency_hz: float) -> float:
    """How long step-and-scan waits at each step (:func:`service.sweep.run_sweep`)."""
    return 0.05 + (scans_per_step + 1) / scan_frequency_hz


def travel_deg(sweep: ResolvedSweep) -> tuple[float, float]:
    """The lowest and highest beta (deg) the sweep moves to: the window plus the run-up on both
    sides in constant mode, the window itself in step mode."""
    lo, hi = min(sweep.start_deg, sweep.stop_deg), max(sweep.start_deg, sweep.stop_deg)
    extra = run_up_deg(sweep.speed_deg_s, sweep.acceleration_deg_s2) if sweep.mode == "constant" else 0.0
    return lo - extra, hi + extra


def _move_s(distance_deg: float, speed_deg_s: float, acceleration_deg_s2: float) -> float:
    """A point-to-point move with a trapezoidal (or, if short, triangular) velocity profile."""
    d = abs(distance_deg)
    if d == 0.0:
        return 0.0
    if d >= speed_deg_s * speed_deg_s / acceleration_deg_s2:
        return d / speed_deg_s + speed_deg_s / acceleration_deg_s2
    return 2.0 * math.sqrt(d / acceleration_deg_s2)


def planned_duration_s(
    sweep: ResolvedSweep,
    approach_speed_deg_s: float = APPROACH_SPEED_DEG_S,
    scan_frequency_hz: float = 25.0,
) -> float:
    """The sweep's planned duration (s): the approach, the sweep and, in step-and-scan mode, the
    dwell at every step, with the acceleration ramps.

    The approach is counted from the far end of the same sweep (where an identical previous
    measurement left the shaft). ``scan_frequency_hz`` sets the dwell; the default 25 Hz is the
    slower LMS1xx mode, so the figure is an upper bound for either mode.
    """
    lo, hi = travel_deg(sweep)
    a = sweep.acceleration_deg_s2
    approach = _move_s(hi - lo, approach_speed_deg_s, a)
    if sweep.mode == "constant":
        return approach + _move_s(hi - lo, sweep.speed_deg_s, a)
    n = math.floor(abs(sweep.stop_deg - sweep.start_deg) / sweep.step_deg + 1e-9) + 1
    moves = (n - 1) * _move_s(sweep.step_deg, sweep.speed_deg_s, a)
    return approach + moves + n * step_dwell_s(sweep.scans_per_step, scan_frequency_hz)


def check_sweep(sweep: ResolvedSweep, config: RigConfig) -> list[tuple[Loc, str]]:
    """What keeps ``sweep`` from running on the rig of ``config``: ``(field, reason)`` pairs, empty
    when it fits (travel limits with the run-up, maximum speed and acceleration, duration)."""
    errors: list[tuple[Loc, str]] = []
    motor = config.motor
    if sweep.start_deg == sweep.stop_deg:
        errors.append((("stop_deg",), "sweep start_deg and stop_deg must differ"))
        return errors
    if sweep.speed_deg_s > motor.max_velocity_deg_s:
        errors.append(
            (
                ("speed_deg_s",),
                f"{sweep.speed_deg_s:g} deg/s exceeds the motor's maximum speed "
                f"{motor.max_velocity_deg_s:g} deg/s ([motor] max_velocity_deg_s)",
            )
        )
    if sweep.acceleration_deg_s2 > motor.max_acceleration_deg_s2:
        errors.append(
            (
                ("acceleration_deg_s2",),
                f"{sweep.acceleration_deg_s2:g} deg/s^2 ([sweep] acceleration_deg_s2) exceeds the motor's maximum "
                f"{motor.max_acceleration_deg_s2:g} deg/s^2 ([motor] max_acceleration_deg_s2)",
            )
        )
    span = abs(sweep.stop_deg - sweep.start_deg)
    if sweep.mode == "step" and sweep.step_deg > span:
        errors.append((("step_deg",), f"a step of {sweep.step_deg:g} deg is wider than the sweep ({span:g} deg)"))
    zero = math.degrees(config.calibration.motor_zero)
    lo, hi = travel_deg(sweep)
    low_field = "start_deg" if sweep.start_deg < sweep.stop_deg else "stop_deg"
    high_field = "stop_deg" if low_field == "start_deg" else "start_deg"
    how = (
        f" (with the {run_up_deg(sweep.speed_deg_s, sweep.acceleration_deg_s2):g} deg run-up of "
        f"{sweep.speed_deg_s:g} deg/s)"
        if sweep.mode == "constant"
        else ""
    )
    if lo + zero < motor.min_angle_deg:
        errors.append(
            (
                (low_field,),
                f"the sweep needs the shaft at {lo + zero:g} deg{how}, below the motor's travel limit "
                f"{motor.min_angle_deg:g} deg ([motor] min_angle_deg)",
            )
        )
    if hi + zero > motor.max_angle_deg:
        errors.append(
            (
                (high_field,),
                f"the sweep needs the shaft at {hi + zero:g} deg{how}, above the motor's travel limit "
                f"{motor.max_angle_deg:g} deg ([motor] max_angle_deg)",
            )
        )
    if not errors:
        duration = planned_duration_s(sweep, min(APPROACH_SPEED_DEG_S, motor.max_velocity_deg_s))
        if duration > config.sweep.max_duration_s:
            field = "speed_deg_s" if sweep.mode == "constant" else "step_deg"
            errors.append(
                (
                    (field,),
                    f"the sweep would take {duration:.0f} s, more than [sweep] max_duration_s = "
                    f"{config.sweep.max_duration_s:g} s (raise the speed or the step, or narrow the range)",
                )
            )
    return errors


def resolve_sweep(spec: SweepSpec, config: RigConfig) -> ResolvedSweep:
    """The request's sweep with the rig's defaults filled in, checked against the rig
    (:func:`check_sweep`); :class:`RequestFieldError` names the fields (``("sweep", name)``)."""
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
    errors = check_sweep(out, config)
    if errors:
        raise RequestFieldError([(("sweep", *loc), msg) for loc, msg in errors])
    return out


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
    rig_id: str = Field(default="", description="the rig whose service made it ([storage] rig_id)")
