"""The rig configuration: a TOML file validated by pydantic.

A rig is either real (``[scanner] url`` and ``[motor] url`` name devices, see
:mod:`drivers.url`) or simulated (a ``[sim]`` table: the service starts one simulated rig,
scanner and drive on one clock, and fills in both URLs itself). Angles are in degrees in the
file, lengths in metres (keys say so: ``*_deg``, ``*_m``). Every table rejects unknown keys, so a
typo is an error rather than a silent default. :func:`load_config` raises :class:`ConfigError`
with the file name and the offending key.

The REST API's bearer tokens (``[auth]``): an operator token (start and cancel measurements), an
admin token (everything, schedules included) and optionally a read-only token; each from its key
or, when that is empty, its environment variable (:data:`TOKEN_ENVS`). ``[auth] token`` and
``LRMS_API_TOKEN`` are the deprecated names of the operator token. ``[auth] read`` says whether
reads need a token too (``"token"``, the default of a rig file) or are open (``"open"``, the
built-in simulated rig). ``[api]`` holds the HTTP server's body limit and TLS files.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from lrms import budget as _budget
from lrms.errors import LrmsError
from lrms.kinematics import RigCalibration
from service.db import check_rig_id, default_rig_id
from service.defaults import DEFAULT_K as DEFAULT_K  # re-exported: the config's default k
from service.errors import ConfigError

TOKEN_ENV = "LRMS_API_TOKEN"
"""Deprecated environment name of the operator token (read when ``LRMS_OPERATOR_TOKEN`` is unset)."""
Role = Literal["read", "operator", "admin"]
TOKEN_ENVS: dict[Role, str] = {
    "read": "LRMS_READ_TOKEN",
    "operator": "LRMS_OPERATOR_TOKEN",
    "admin": "LRMS_ADMIN_TOKEN",
}
"""The environment variable of each role's token (used when the config key is empty)."""
DEFAULT_MAX_BODY_BYTES = 1 << 20
DEFAULT_RIG = "default_rig.toml"


#: The slowest sweep speed and the smallest step a request or the ``[sweep]`` table may give: below
#: them a sweep takes hours (the planned duration is checked against ``[sweep] max_duration_s`` too),
#: and ``0.01 deg`` is still 14 encoder counts on the default drive (10000 counts x 50:1 per turn).
MIN_SPEED_DEG_S = 0.1
MIN_STEP_DEG = 0.01
#: Bounds of the coverage factor k (a request's ``options.k``, ``[fit] k``).
MIN_K = 0.5
MAX_K = 10.0


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class DeviceConfig(_Strict):
    """A device by URL (``tcp://10.0.0.5:2112?cola=b``, ``canopen+socketcand://...``)."""

    url: str | None = None

    @field_validator("url")
    @classmethod
    def _url_shape(cls, v: str | None) -> str | None:
        if v is not None and "://" not in v:
            raise ValueError(f"not a device URL (expected scheme://...): {v!r}")
        return v


class OpticsConfig(_Strict):
    """The scanner's light spot as the cylinder fit models it (``[scanner.optics]``): ``model``
    "lms1xx" (a spot ``spot_exit_m + divergence_rad x range`` wide, defaults the LMS1xx's 8 mm and
    15 mrad, SICK 8012471 section 3.6.2; the fit models each beam's expected echo,
    docs/cylinder.md) or "ideal" (the thin beam). Unset, a simulated rig follows its ``[sim]
    sensor`` and a real one takes "ideal": the footprint fit is opt-in until it meets its accuracy
    goal (docs/cylinder.md section 7)."""

    model: Literal["ideal", "lms1xx"] | None = None
    spot_exit_m: float = Field(default=0.008, ge=0.0, le=0.5)
    divergence_rad: float = Field(default=0.015, ge=0.0, le=0.5)


class ScannerErrors(_Strict):
    """The scanner's type-B inputs of the uncertainty budget, as standard uncertainties
    (:class:`lrms.budget.SensorErrors`; docs/cylinder.md, "The budget"). Defaults: an uncalibrated
    LMS1xx (SICK's +-30 mm typical systematic range error, rectangular: 17.3 mm)."""

    range_offset_u_m: float = Field(default=_budget.LMS1XX_RANGE_OFFSET_U, ge=0.0, le=1.0)
    range_offset_distribution: Literal["rectangular", "normal"] = "rectangular"
    range_scale_u_ppm: float = Field(default=0.0, ge=0.0, le=1e5)
    range_scale_distribution: Literal["rectangular", "normal"] = "normal"
    temperature_coeff_m_per_k: float = Field(default=0.0, ge=-1.0, le=1.0)
    temperature_u_k: float = Field(default=5.0, ge=0.0, le=1000.0)
    alpha_zero_u_deg: float = Field(default=math.degrees(_budget.DEFAULT_ZERO_U), ge=0.0, le=10.0)


class MotorErrors(_Strict):
    """The drive's type-B inputs of the uncertainty budget (per scan: every beam of a scan shares
    its motor angle): zero, encoder quantisation (one count of the default drive, rectangular),
    timing error of the motor angle read for a scan (ours: 1 ms)."""

    beta_zero_u_deg: float = Field(default=math.degrees(_budget.DEFAULT_ZERO_U), ge=0.0, le=10.0)
    encoder_u_deg: float = Field(default=math.degrees(_budget.DEFAULT_ENCODER_U), ge=0.0, le=10.0)
    timing_jitter_u_s: float = Field(default=_budget.DEFAULT_TIMING_JITTER_U, ge=0.0, le=1.0)


class ScannerConfig(DeviceConfig):
    """The scanner: URL and the scan mode the service sets (an LMS1xx: 25 Hz / 0.25 deg or 50 Hz / 0.5 deg),
    and the type-B inputs of the uncertainty budget (``[scanner.errors]``)."""

    errors: ScannerErrors = Field(default_factory=ScannerErrors)
    scan_frequency_hz: Literal[25, 50] = 25
    optics: OpticsConfig = Field(default_factory=OpticsConfig)
    resolution_deg: float = 0.25

    @field_validator("resolution_deg")
    @classmethod
    def _resolution(cls, v: float) -> float:
        if v not in (0.25, 0.5):
            raise ValueError(f"an LMS1xx scans at 0.25 or 0.5 deg, not {v}")
        return v

    login_password_hash: int | None = Field(default=None, ge=0, le=0xFFFFFFFF, repr=False)
    """A secret: never in ``/rig``, logs or error messages."""

    @model_validator(mode="after")
    def _mode(self) -> ScannerConfig:
        if self.scan_frequency_hz == 50 and self.resolution_deg == 0.25:
            raise ValueError("an LMS1xx cannot scan at 50 Hz with 0.25 deg (use 25 Hz/0.25 deg or 50 Hz/0.5 deg)")
        return self


class MotorConfig(DeviceConfig):
    """The motor: URL and the limits of the output shaft in the drive's own frame (degrees, the
    angles of ``lrms motor move``; beta = shaft angle - ``[kinematics] motor_zero_deg``).

    Every sweep is checked against them when it is requested (the approach and run-out included),
    again before the drive is commanded, and they are handed to the driver (which refuses targets
    outside them and writes them to a CiA 402 drive's software position limits, 0x607D). The
    defaults are one turn either way of the zero and the CiA 402 driver's own maxima.
    """

    errors: MotorErrors = Field(default_factory=MotorErrors)
    """The type-B inputs of the uncertainty budget (``[motor.errors]``)."""
    min_angle_deg: float = Field(default=-180.0, ge=-3600.0, le=3600.0)
    max_angle_deg: float = Field(default=180.0, ge=-3600.0, le=3600.0)
    max_velocity_deg_s: float = Field(default=90.0, ge=MIN_SPEED_DEG_S, le=3600.0)
    max_acceleration_deg_s2: float = Field(default=720.0, gt=0.0, le=100000.0)

    @model_validator(mode="after")
    def _travel(self) -> MotorConfig:
        if not self.min_angle_deg < self.max_angle_deg:
            raise ValueError(f"min_angle_deg {self.min_angle_deg} must be below max_angle_deg {self.max_angle_deg}")
        return self

    def drive_config(self) -> dict[str, float]:
        """The limits as :meth:`drivers.servo.interface.DriveConfig.from_dict` keys (the driver's
        default velocity and acceleration capped to them)."""
        return {
            "min_angle_deg": self.min_angle_deg,
            "max_angle_deg": self.max_angle_deg,
            "max_velocity_deg_s": self.max_velocity_deg_s,
            "max_acceleration_deg_s2": self.max_acceleration_deg_s2,
            "velocity_deg_s": min(20.0, self.max_velocity_deg_s),
            "acceleration_deg_s2": min(90.0, self.max_acceleration_deg_s2),
        }


class NoiseConfig(_Strict):
    """The sensor's noise model (seed 003: sigma_l^2 = 136.11 mm^2)."""

    sigma_l_m: float = Field(default=0.01167, ge=0.0, le=1.0)
    sigma_alpha_deg: float = Field(default=1.74e-3, ge=0.0, le=10.0)
    sigma_beta_deg: float = Field(default=3.6e-5, ge=0.0, le=10.0)

    def si(self) -> dict[str, float]:
        """``sigma_l`` (m), ``sigma_alpha`` and ``sigma_beta`` (rad): the one place degrees become
        radians (for :class:`lrms.covariance.NoiseModel`, the simulated sensor, ``python -m sim.rig``)."""
        return {
            "sigma_l": float(self.sigma_l_m),
            "sigma_alpha": math.radians(self.sigma_alpha_deg),
            "sigma_beta": math.radians(self.sigma_beta_deg),
        }


class StorageConfig(_Strict):
    """Where results, raw logs and clouds go. Relative paths are relative to the config file.

    ``url`` names the result database (``sqlite:///PATH`` or ``postgresql://user@host/db``); without
    it, the SQLite file ``database`` in ``dir``. ``rig_id`` tags every row this rig's service
    writes (default: the host name), so the services of many rigs can share one database."""

    dir: Path = Path("lrms-data")
    database: str = "lrms.sqlite"
    url: str | None = Field(default=None, repr=False)  # may hold a password
    rig_id: str = Field(default_factory=default_rig_id)

    @field_validator("rig_id")
    @classmethod
    def _rig_id(cls, v: str) -> str:
        return check_rig_id(v)

    @field_validator("url")
    @classmethod
    def _url(cls, v: str | None) -> str | None:
        if v is not None and not re.match(r"(sqlite|postgresql)(\+\w+)?://", v):
            raise ValueError("a database URL: sqlite:///PATH or postgresql://user@host/db")
        return v

    @property
    def db_path(self) -> Path:
        return self.dir / self.database

    @property
    def db_url(self) -> str:
        """The result database's URL: ``url``, else the SQLite file ``dir/database``."""
        return self.url if self.url is not None else f"sqlite:///{self.db_path}"

    @property
    def raw_dir(self) -> Path:
        return self.dir / "raw"

    @property
    def cloud_dir(self) -> Path:
        return self.dir / "clouds"


class AuthConfig(_Strict):
    """Bearer tokens of the REST API per role, and whether reads need one. Token values are
    secrets: excluded from ``repr`` (tracebacks, debug logs) and never echoed in errors."""

    operator_token: str = Field(default="", repr=False)
    admin_token: str = Field(default="", repr=False)
    read_token: str = Field(default="", repr=False)
    token: str = Field(default="", repr=False)
    """Deprecated name of ``operator_token``."""
    read: Literal["open", "token"] = "token"

    @model_validator(mode="after")
    def _one_operator_token(self) -> AuthConfig:
        if self.token and self.operator_token:
            raise ValueError("token is the deprecated name of operator_token: give only operator_token")
        keys = {"operator_token": self.operator_token or self.token, "admin_token": self.admin_token}
        keys["read_token"] = self.read_token
        given = [(k, v) for k, v in keys.items() if v]
        for i, (k1, v1) in enumerate(given):
            for k2, v2 in given[i + 1 :]:
                if v1 == v2:  # the values are secrets: name the keys only
                    raise ValueError(f"{k1} and {k2} are the same token: each role needs its own")
        return self


class ApiConfig(_Strict):
    """The HTTP server: largest request body, TLS certificate and key (PEM files; relative paths
    are relative to the config file)."""

    max_body_bytes: int = Field(default=DEFAULT_MAX_BODY_BYTES, ge=1024, le=1 << 30)
    tls_cert: Path | None = None
    tls_key: Path | None = None

    @model_validator(mode="after")
    def _tls_pair(self) -> ApiConfig:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together: give both or neither")
        return self


class SweepConfig(_Strict):
    """Default sweep: over [start_deg, stop_deg] of the scan-plane angle beta."""

    start_deg: float = Field(default=-20.0, ge=-180.0, le=180.0)
    stop_deg: float = Field(default=70.0, ge=-180.0, le=180.0)
    speed_deg_s: float = Field(default=10.0, ge=MIN_SPEED_DEG_S, le=360.0)
    mode: Literal["constant", "step"] = "constant"
    step_deg: float = Field(default=1.0, ge=MIN_STEP_DEG, le=90.0)
    scans_per_step: int = Field(default=1, ge=1, le=1000)
    acceleration_deg_s2: float = Field(default=90.0, gt=0.0, le=100000.0)
    max_duration_s: float = Field(default=600.0, gt=0.0, le=86400.0)
    """The longest a sweep may run: a request whose plan (``service.models.planned_duration_s``) is
    longer is refused (422); at run time the rig process stops the motor and fails the measurement
    past it (``exceeded max duration N s``)."""

    @model_validator(mode="after")
    def _range(self) -> SweepConfig:
        if self.stop_deg == self.start_deg:
            raise ValueError("sweep start_deg and stop_deg must differ")
        return self


class JobsConfig(_Strict):
    """The job queue: at most ``max_queued`` measurements wait (POST beyond it: 429; schedules skip)."""

    max_queued: int = Field(default=20, ge=1, le=10000)


class FitConfig(_Strict):
    """Fit defaults: the region of interest (world frame, metres), the ellipsoid factor k of the
    critical-point interval and the coverage factor of the budget's expanded uncertainty."""

    roi_min_m: tuple[float, float, float] | None = None
    roi_max_m: tuple[float, float, float] | None = None
    k: float = Field(default=DEFAULT_K, ge=MIN_K, le=MAX_K)
    coverage_factor: float = Field(default=2.0, gt=0.0, le=10.0)
    """k of the budget's expanded uncertainty U = k u_c."""
    min_range_m: float = Field(default=0.05, ge=0.0)
    max_range_m: float = Field(default=20.0, gt=0.0)


class SchedulesConfig(_Strict):
    """Schedules: the shortest time between two firings of one schedule (cron or interval)."""

    min_interval_s: float = Field(default=60.0, ge=1.0, le=86400.0)


class SimConfig(_Strict):
    """The embedded simulated rig: scene, real-time factor, CAN transport, fault injection."""

    scene: str = "seed003"
    sensor: Literal["ideal", "lms1xx"] = "ideal"
    """The simulated scanner's sensor model: "ideal" (thin beam, the [noise] figures) or "lms1xx"
    (beam footprint, echoes, RSSI; docs/sensor-model.md; takes only the angle noise from [noise])."""
    seed: int = Field(default=0, ge=0)
    cola: Literal["a", "b"] = "b"
    can: Literal["socketcand", "virtual"] = "socketcand"
    node: int = Field(default=1, ge=1, le=127)
    process: bool = True
    """Run the simulated rig in its own process (``python -m sim.rig``), as a real rig is."""
    rig_errors: dict[str, float] = Field(default_factory=dict)
    """The simulated rig's *true* departures from ``[kinematics]`` (issue 12): ``p_m`` and the keys
    of :attr:`lrms.kinematics.RigCalibration.MODEL_KEYS` (``range_offset_m``, ``range_scale_ppm``,
    ``q_m``, ``tilt_x_deg``, ...). The service maps with ``[kinematics]``; the simulator casts
    beams through ``[kinematics]`` updated by these, so a calibration has something to find."""

    @field_validator("rig_errors")
    @classmethod
    def _rig_errors(cls, v: dict[str, float]) -> dict[str, float]:
        allowed = {"p_m", *RigCalibration.MODEL_KEYS}
        unknown = set(v) - allowed
        if unknown:
            raise ValueError(f"unknown rig error(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(allowed))})")
        try:
            RigCalibration.from_dict(v)
        except (LrmsError, TypeError, ValueError) as exc:
            raise ValueError(str(exc)) from None
        return v

    @model_validator(mode="after")
    def _transport(self) -> SimConfig:
        if self.process and self.can == "virtual":
            raise ValueError("can = 'virtual' is an in-process bus: it needs process = false")
        return self


class RigConfig(_Strict):
    """The whole rig configuration (the TOML file)."""

    name: str = "rig"
    scanner: ScannerConfig = Field(default_factory=ScannerConfig)
    motor: MotorConfig = Field(default_factory=MotorConfig)
    sim: SimConfig | None = None
    kinematics: dict[str, Any] = Field(default_factory=dict)
    noise: NoiseConfig = Field(default_factory=NoiseConfig)
    storage: StorageConfig = Field(default_factory=StorageConfig)
    auth: AuthConfig = Field(default_factory=AuthConfig)
    api: ApiConfig = Field(default_factory=ApiConfig)
    sweep: SweepConfig = Field(default_factory=SweepConfig)
    jobs: JobsConfig = Field(default_factory=JobsConfig)
    fit: FitConfig = Field(default_factory=FitConfig)
    schedules: SchedulesConfig = Field(default_factory=SchedulesConfig)

    @model_validator(mode="after")
    def _devices(self) -> RigConfig:
        if self.sim is None:
            missing = [k for k, d in (("scanner", self.scanner), ("motor", self.motor)) if d.url is None]
            if missing:
                raise ValueError(f"[{'] and ['.join(missing)}] url missing (or add a [sim] table for a simulated rig)")
        else:
            given = [k for k, d in (("scanner", self.scanner), ("motor", self.motor)) if d.url is not None]
            if given:
                raise ValueError(f"[{given[0]}] url and [sim] are exclusive: the simulated rig supplies its own URLs")
        try:
            RigCalibration.from_dict(self.kinematics)
        except (LrmsError, ValueError, TypeError) as exc:
            raise ValueError(f"[kinematics]: {exc}") from None
        return self

    @property
    def calibration(self) -> RigCalibration:
        return RigCalibration.from_dict(self.kinematics)

    def sensor_errors(self) -> _budget.SensorErrors:
        """``[scanner.errors]`` and ``[motor.errors]`` in SI for :mod:`lrms.budget`."""
        se, me = self.scanner.errors, self.motor.errors
        return _budget.SensorErrors(
            range_offset_u_m=se.range_offset_u_m,
            range_offset_distribution=se.range_offset_distribution,
            range_scale_u_ppm=se.range_scale_u_ppm,
            range_scale_distribution=se.range_scale_distribution,
            temperature_coeff_m_per_k=se.temperature_coeff_m_per_k,
            temperature_u_k=se.temperature_u_k,
            alpha_zero_u_rad=math.radians(se.alpha_zero_u_deg),
            beta_zero_u_rad=math.radians(me.beta_zero_u_deg),
            encoder_u_rad=math.radians(me.encoder_u_deg),
            timing_jitter_u_s=me.timing_jitter_u_s,
        )

    @property
    def sim_kinematics(self) -> dict[str, Any]:
        """The simulated rig's true ``[kinematics]``: ours updated by ``[sim] rig_errors``."""
        return {**self.kinematics, **(self.sim.rig_errors if self.sim is not None else {})}

    @property
    def optics_model(self) -> Literal["ideal", "lms1xx"]:
        """The beam model of the cylinder fit: ``[scanner.optics] model``, else the simulated
        rig's sensor, else "ideal"."""
        if self.scanner.optics.model is not None:
            return self.scanner.optics.model
        return self.sim.sensor if self.sim is not None else "ideal"

    @property
    def is_sim(self) -> bool:
        return self.sim is not None

    def role_token(self, role: Role) -> str | None:
        """The bearer token of ``role``, or None when none is configured: the ``[auth]`` key, else
        the role's environment variable (read on every call, so a changed environment counts)."""
        a = self.auth
        if role == "operator":
            return a.operator_token or a.token or os.environ.get(TOKEN_ENVS[role]) or os.environ.get(TOKEN_ENV) or None
        key = a.admin_token if role == "admin" else a.read_token
        return key or os.environ.get(TOKEN_ENVS[role]) or None

    def api_token(self) -> str | None:
        """The operator token (the old single write token's role)."""
        return self.role_token("operator")


def _format_errors(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "(top level)"
        msg = err["msg"].removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}")
    return "; ".join(parts)


def parse_config(data: dict[str, Any], base_dir: Path | None = None, source: str = "config") -> RigConfig:
    """Validate a config mapping; relative storage paths are resolved against ``base_dir``."""
    try:
        cfg = RigConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {_format_errors(exc)}") from None
    from service.models import SweepSpec, resolve_sweep  # models import this module

    try:  # the [sweep] defaults must fit the motor's limits and the maximum duration
        resolve_sweep(SweepSpec(), cfg)
    except ValueError as exc:
        raise ConfigError(f"{source}: [sweep] defaults: {exc}") from None
    if base_dir is not None and not cfg.storage.dir.is_absolute():
        storage = cfg.storage.model_copy(update={"dir": (base_dir / cfg.storage.dir).resolve()})
        cfg = cfg.model_copy(update={"storage": storage})
    url = cfg.storage.url
    if base_dir is not None and url is not None and url.startswith("sqlite:///"):
        file = url.removeprefix("sqlite:///")
        if file and file != ":memory:" and not Path(file).is_absolute():  # relative to the config file too
            storage = cfg.storage.model_copy(update={"url": f"sqlite:///{(base_dir / file).resolve()}"})
            cfg = cfg.model_copy(update={"storage": storage})
    if base_dir is not None and cfg.api.tls_cert is not None and cfg.api.tls_key is not None:
        api = cfg.api.model_copy(
            update={"tls_cert": base_dir / cfg.api.tls_cert, "tls_key": base_dir / cfg.api.tls_key}
        )
        cfg = cfg.model_copy(update={"api": api})
    return cfg


def parse_toml(text: str, base_dir: Path | None = None, source: str = "config") -> RigConfig:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    return parse_config(data, base_dir, source)


def load_config(path: str | Path | None = None, storage_dir: str | Path | None = None) -> RigConfig:
    """Load a rig TOML file; ``None`` loads the default simulated rig.

    The default rig keeps its data under ``$LRMS_DATA`` or ``./lrms-data``; ``storage_dir``
    overrides the storage folder of any config.
    """
    if path is None:
        text = resources.files("service").joinpath(DEFAULT_RIG).read_text(encoding="utf-8")
        base = Path(os.environ.get("LRMS_DATA", ".")).resolve()
        cfg = parse_toml(text, base, source=f"(built-in {DEFAULT_RIG})")
    else:
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot read config {p}: {exc.strerror or exc}") from None
        cfg = parse_toml(text, p.resolve().parent, source=str(p))
    if storage_dir is not None:
        storage = cfg.storage.model_copy(update={"dir": Path(storage_dir).resolve()})
        cfg = cfg.model_copy(update={"storage": storage})
    return cfg
