"""Response models of ``/healthz`` and ``/api/v1/rig`` (the measurement and schedule models are in
service.models). Device state comes from drivers that may know more in a later version, so the
device objects allow further fields (``additionalProperties``) besides the documented ones."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from service.config import FitConfig, NoiseConfig, SweepConfig


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


class MotorFault(BaseModel):
    code: int = Field(description="CiA 402 error code (0x8130: heartbeat lost, ...)")
    reason: str


class RigProcessHealth(_Open):
    """The process that runs the rig's real-time work (service.rigproc), where there is one."""

    alive: bool | None = None
    pid: int | None = None
    restarts: int | None = Field(default=None, description="times the supervisor restarted it")
    last_exit: str | None = Field(default=None, description="how the previous one ended, e.g. 'killed by SIGKILL'")
    state_age_s: float | None = Field(default=None, description="seconds since its last state report")


class DriveHealth(_Open):
    state: str | None = Field(default=None, description="CiA 402 state name, e.g. OPERATION_ENABLED, FAULT")
    fault: MotorFault | None = None


class HealthOut(_Open):
    """``GET /healthz``."""

    status: str = Field(description='"ok" (200) when the rig can measure now; else "degraded" (503)')
    reasons: list[str] = Field(default_factory=list, description="one line per problem when degraded")
    version: str
    running: str | None = Field(description="id of the running measurement")
    queued: int = Field(ge=0, description="measurements waiting")
    rig_process: RigProcessHealth | None = None
    drive: DriveHealth | None = None
    scanner_connected: bool | None = None


class ScannerState(_Open):
    url: str | None = None
    connected: bool | None = None
    streaming: bool | None = None
    stats: dict[str, Any] | None = Field(default=None, description="the client's counters (lost, gaps, reconnects...)")


class MotorState(_Open):
    url: str | None = None
    state: str | None = Field(default=None, description="CiA 402 state of the newest sample")
    position_deg: float | None = None
    velocity_deg_s: float | None = None
    fault: MotorFault | None = None
    error: str | None = Field(default=None, description="why the state could not be read")


class MotorLimits(BaseModel):
    """The ``[motor]`` limits every sweep is checked against (shaft angles, drive frame)."""

    min_angle_deg: float
    max_angle_deg: float
    max_velocity_deg_s: float
    max_acceleration_deg_s2: float


class RigOut(_Open):
    """``GET /api/v1/rig``: the configuration (no token) and the devices' state."""

    name: str
    simulated: bool
    scanner_url: str | None
    motor_url: str | None
    kinematics: dict[str, Any]
    noise: NoiseConfig
    sweep_defaults: SweepConfig
    fit_defaults: FitConfig
    motor_limits: MotorLimits
    min_schedule_interval_s: float
    sim: dict[str, Any] | None = Field(
        description="the [sim] table; with a running simulated rig its URLs, pid and whether it is alive"
    )
    write_enabled: bool
    busy: bool
    scanner: ScannerState | None = None
    motor: MotorState | None = None
