"""The one motor interface every servo backend implements (CANopen CiA 402, Modbus RTU, ...).

Angles are radians at the **output shaft** (after the speed reducer); the drive works in
encoder counts of the motor, and :class:`DriveConfig` converts (counts per motor revolution and
gear ratio, from a TOML table or dict). Position user units on the drive are taken to be
encoder increments (position factor 1), velocities counts/s and accelerations counts/s².

:class:`Motor` is the abstract interface plus the sample ring buffer shared by all backends.
:class:`Cia402Motor` implements the whole CiA 402 behaviour (state machine walk, profile
position handshake, profile velocity, homing, halt / quick stop, fault decoding) on top of four
primitives that a backend supplies: read an object, write an object, write the controlword and
obtain a statusword observed after a given instant. The CANopen backend feeds it from SDO and
SYNC'ed TPDOs, the Modbus backend from holding registers.

Timestamps are host seconds from the motor's ``clock`` (``time.monotonic`` unless given; on
Linux it is system-wide, so stamps from several processes compare).
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, DriverError
from drivers.servo import cia402
from drivers.servo.cia402 import Mode, State

Clock = Callable[[], float]
_log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


class ServoError(DriverError):
    """Base class of the servo drivers' errors."""


class DriveConfigError(ServoError, ValueError):
    """A drive configuration value is missing, unknown or out of range."""


class MotorFault(ServoError):
    """The drive is in *Fault* (or was lost); ``code`` is the CiA 402 error code (0x603F / EMCY)."""

    def __init__(self, code: int, reason: str, statusword: int | None = None, detail: str = "") -> None:
        self.code = code
        self.reason = reason
        self.statusword = statusword
        self.detail = detail
        text = f"motor fault 0x{code:04X}: {reason}"
        if detail:
            text += f" ({detail})"
        super().__init__(text)


class ConnectionLost(MotorFault, DeviceConnectionError):
    """The link to the drive is gone (bus closed, receive thread stopped)."""


class HeartbeatLost(ConnectionLost):
    """The drive stopped producing heartbeats: a silent drive is a fault."""


class SdoAbort(ServoError):
    """An SDO transfer was aborted; ``code`` is the CiA 301 abort code, ``reason`` its meaning."""

    def __init__(self, index: int, subindex: int, code: int) -> None:
        self.index = index
        self.subindex = subindex
        self.code = code
        self.reason = cia402.describe_sdo_abort(code)
        super().__init__(f"SDO abort on 0x{index:04X}:{subindex:02X}: 0x{code:08X} {self.reason}")


class MotorStateError(ServoError):
    """The command is not possible in the drive's present state (e.g. a move while disabled)."""


class ServoValueError(ServoError, ValueError):
    """A bad argument (a non-finite velocity, an out-of-range object value, ...)."""


class TargetOutOfRange(ServoValueError):
    """A target lies outside the configured software limits or the drive's number range."""


class SampleRangeError(ServoError, ValueError):
    """Interpolation asked for times the sample buffer does not cover."""


class MotionTimeout(ServoError, DeviceTimeoutError):
    """A state transition, move or homing did not finish within the timeout."""


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


_DEG_KEYS = {  # accepted *_deg spellings at the edges (TOML files), converted to radians
    "velocity_deg_s": "velocity_rad_s",
    "acceleration_deg_s2": "acceleration_rad_s2",
    "max_velocity_deg_s": "max_velocity_rad_s",
    "max_acceleration_deg_s2": "max_acceleration_rad_s2",
    "quick_stop_deceleration_deg_s2": "quick_stop_deceleration_rad_s2",
    "min_angle_deg": "min_angle_rad",
    "max_angle_deg": "max_angle_rad",
    "home_offset_deg": "home_offset_rad",
    "position_window_deg": "position_window_rad",
    "following_error_window_deg": "following_error_window_rad",
}


@dataclass(frozen=True)
class DriveConfig:
    """Mechanics and motion defaults of one axis.

    ``counts_per_rev`` encoder counts per motor revolution, ``gear_ratio`` motor revolutions per
    output revolution (a 50:1 reducer is 50; negative reverses the direction), velocities in
    rad/s and accelerations in rad/s² at the output shaft, limits in rad (``None`` = none).
    """

    counts_per_rev: int = 10_000
    gear_ratio: float = 50.0
    velocity_rad_s: float = math.radians(20.0)
    acceleration_rad_s2: float = math.radians(90.0)
    max_velocity_rad_s: float = math.radians(90.0)
    max_acceleration_rad_s2: float = math.radians(720.0)
    quick_stop_deceleration_rad_s2: float = math.radians(720.0)
    min_angle_rad: float | None = None
    max_angle_rad: float | None = None
    homing_method: int = 37
    home_offset_rad: float = 0.0
    position_window_rad: float = math.radians(0.01)
    following_error_window_rad: float = math.radians(1.0)

    def __post_init__(self) -> None:
        if not isinstance(self.counts_per_rev, int) or self.counts_per_rev <= 0:
            raise DriveConfigError(f"counts_per_rev must be a positive integer, got {self.counts_per_rev!r}")
        if not math.isfinite(self.gear_ratio) or self.gear_ratio == 0:
            raise DriveConfigError(f"gear_ratio must be finite and non-zero, got {self.gear_ratio!r}")
        for name in (
            "velocity_rad_s",
            "acceleration_rad_s2",
            "max_velocity_rad_s",
            "max_acceleration_rad_s2",
            "quick_stop_deceleration_rad_s2",
            "position_window_rad",
            "following_error_window_rad",
        ):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                raise DriveConfigError(f"{name} must be finite and > 0, got {value!r}")
        if self.velocity_rad_s > self.max_velocity_rad_s:
            raise DriveConfigError("velocity_rad_s exceeds max_velocity_rad_s")
        if self.acceleration_rad_s2 > self.max_acceleration_rad_s2:
            raise DriveConfigError("acceleration_rad_s2 exceeds max_acceleration_rad_s2")
        if (
            self.min_angle_rad is not None
            and self.max_angle_rad is not None
            and not self.min_angle_rad < self.max_angle_rad
        ):
            raise DriveConfigError(f"min_angle_rad {self.min_angle_rad} must be < max_angle_rad {self.max_angle_rad}")
        if not -128 <= self.homing_method <= 127:
            raise DriveConfigError(f"homing_method must fit an i8, got {self.homing_method}")

    # -- loading ------------------------------------------------------------------------------

    @classmethod
    def from_dict(cls, table: Mapping[str, Any]) -> DriveConfig:
        """Build from a dict / TOML table; keys are the field names or their ``*_deg`` forms."""
        names = {f.name for f in fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in table.items():
            if key in _DEG_KEYS:
                target = _DEG_KEYS[key]
                if not isinstance(value, int | float) or isinstance(value, bool):
                    raise DriveConfigError(f"{key} must be a number, got {value!r}")
                value = math.radians(value)
            elif key in names:
                target = key
            else:
                raise DriveConfigError(f"unknown drive config key {key!r} (known: {', '.join(sorted(names))})")
            if target in kwargs:
                raise DriveConfigError(f"{target} given twice ({key!r})")
            if target in ("counts_per_rev", "homing_method"):
                if not isinstance(value, int) or isinstance(value, bool):
                    raise DriveConfigError(f"{key} must be an integer, got {value!r}")
            elif value is not None and (not isinstance(value, int | float) or isinstance(value, bool)):
                raise DriveConfigError(f"{key} must be a number, got {value!r}")
            if isinstance(value, int) and target not in ("counts_per_rev", "homing_method"):
                value = float(value)
            kwargs[target] = value
        return cls(**kwargs)

    @classmethod
    def from_toml(cls, source: str | Path, table: str | None = "motor") -> DriveConfig:
        """Load from a TOML file path (or TOML text); ``table`` selects e.g. ``[motor]`` (``None`` = top level)."""
        try:
            is_text = isinstance(source, str) and ("\n" in source or "=" in source)
            text = str(source) if is_text else Path(source).read_text()
            data: dict[str, Any] = tomllib.loads(text)
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise DriveConfigError(f"cannot read drive config: {exc}") from exc
        if table is not None:
            for part in table.split("."):
                sub = data.get(part)
                if not isinstance(sub, dict):
                    raise DriveConfigError(f"drive config has no [{table}] table")
                data = sub
        return cls.from_dict(data)

    # -- unit conversion ----------------------------------------------------------------------
    @property
    def counts_per_rad(self) -> float:
        """Encoder counts per radian of the output shaft (sign follows ``gear_ratio``)."""
        return self.counts_per_rev * self.gear_ratio / (2.0 * math.pi)

    def rad_to_counts(self, angle_rad: float) -> int:
        counts = round(angle_rad * self.counts_per_rad)
        if not -(1 << 31) <= counts < (1 << 31):
            raise TargetOutOfRange(f"{angle_rad} rad is {counts} counts, beyond the drive's 32-bit position range")
        return counts

    def counts_to_rad(self, counts: int | float) -> float:
        return float(counts) / self.counts_per_rad

    def rate_to_counts(self, rate_rad: float) -> int:
        """A velocity (rad/s) or acceleration (rad/s²) as counts/s (counts/s²), magnitude kept signed."""
        return round(rate_rad * abs(self.counts_per_rad))

    def check_angle(self, angle_rad: float) -> None:
        if not math.isfinite(angle_rad):
            raise TargetOutOfRange(f"target angle must be finite, got {angle_rad}")
        if self.min_angle_rad is not None and angle_rad < self.min_angle_rad:
            raise TargetOutOfRange(
                f"target {math.degrees(angle_rad):.3f} deg is below the software limit "
                f"{math.degrees(self.min_angle_rad):.3f} deg"
            )
        if self.max_angle_rad is not None and angle_rad > self.max_angle_rad:
            raise TargetOutOfRange(
                f"target {math.degrees(angle_rad):.3f} deg is above the software limit "
                f"{math.degrees(self.max_angle_rad):.3f} deg"
            )

    def software_limits_counts(self) -> tuple[int, int] | None:
        """(min, max) in counts for 0x607D, or ``None`` when no limits are configured."""
        if self.min_angle_rad is None and self.max_angle_rad is None:
            return None
        lo = self.rad_to_counts(self.min_angle_rad) if self.min_angle_rad is not None else -(1 << 31)
        hi = self.rad_to_counts(self.max_angle_rad) if self.max_angle_rad is not None else (1 << 31) - 1
        return (min(lo, hi), max(lo, hi))


# --------------------------------------------------------------------------------------------
# Samples
# --------------------------------------------------------------------------------------------


class MotorSample(NamedTuple):
    """One position/velocity sample: host time of the sampling instant (for CANopen the SYNC).

    A drive that reports when it latched the sample (CANopen 0x1013 mapped next to the position)
    adds that time stamp, raw (``drive_stamp_us``: its own microsecond clock, 32-bit wrapping),
    and the host time the sample was received (``t_rx_host_s``): the pairs a clock model needs
    to map the drive's clock to host time (done in the service, not here). None: not reported."""

    t_host_s: float
    position_rad: float
    velocity_rad_s: float
    statusword: int
    drive_stamp_us: int | None = None
    t_rx_host_s: float | None = None


class SampleArrays(NamedTuple):
    t_host_s: npt.NDArray[np.float64]
    position_rad: npt.NDArray[np.float64]
    velocity_rad_s: npt.NDArray[np.float64]
    statusword: npt.NDArray[np.uint16]
    #: the drive's raw time stamp per sample (-1 = none; see :class:`MotorSample`)
    drive_stamp_us: npt.NDArray[np.int64]
    #: host receive time per sample (NaN when the backend does not record it)
    t_rx_host_s: npt.NDArray[np.float64]


def _sample(t: float, p: float, v: float, s: int, d: int, rx: float) -> MotorSample:
    stamped = int(d) >= 0
    return MotorSample(
        float(t), float(p), float(v), int(s), int(d) if stamped else None, float(rx) if stamped else None
    )


class SampleBuffer:
    """Thread-safe ring buffer of :class:`MotorSample` in numpy arrays (oldest overwritten)."""

    def __init__(self, capacity: int = 65536) -> None:
        if capacity < 2:
            raise ServoValueError("capacity must be >= 2")
        self._cap = capacity
        self._t = np.zeros(capacity)
        self._p = np.zeros(capacity)
        self._v = np.zeros(capacity)
        self._s = np.zeros(capacity, dtype=np.uint16)
        self._d = np.full(capacity, -1, dtype=np.int64)
        self._rx = np.full(capacity, math.nan)
        self._n = 0  # total ever pushed
        self._lock = threading.Lock()

    def push(self, sample: MotorSample) -> None:
        with self._lock:
            i = self._n % self._cap
            self._t[i], self._p[i], self._v[i], self._s[i] = sample[:4]
            self._d[i] = -1 if sample.drive_stamp_us is None else sample.drive_stamp_us
            self._rx[i] = math.nan if sample.t_rx_host_s is None else sample.t_rx_host_s
            self._n += 1

    @property
    def total(self) -> int:
        """Number of samples pushed since creation (including overwritten ones)."""
        return self._n

    def latest(self) -> MotorSample | None:
        with self._lock:
            if self._n == 0:
                return None
            i = (self._n - 1) % self._cap
            return _sample(self._t[i], self._p[i], self._v[i], self._s[i], self._d[i], self._rx[i])

    def arrays_since(self, t_host_s: float = -math.inf) -> SampleArrays:
        """Samples with ``t_host_s`` strictly after ``t_host_s``, oldest first, as arrays (copies)."""
        with self._lock:
            n = min(self._n, self._cap)
            start = self._n - n
            order = (np.arange(start, self._n)) % self._cap
            t = self._t[order]
            keep = t > t_host_s
            return SampleArrays(
                t[keep],
                self._p[order][keep],
                self._v[order][keep],
                self._s[order][keep],
                self._d[order][keep],
                self._rx[order][keep],
            )

    def positions_at(self, t_host_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Positions interpolated linearly between samples at the host times ``t_host_s``
        (vectorised). Times outside the buffered span raise :class:`SampleRangeError`."""
        t = np.asarray(t_host_s, dtype=np.float64)
        a = self.arrays_since()
        if len(a.t_host_s) < 2:
            raise SampleRangeError(f"need at least 2 samples to interpolate, have {len(a.t_host_s)}")
        if t.size and not np.all(np.isfinite(t)):
            raise SampleRangeError("times must be finite: NaN or inf is outside the sampled span")
        if t.size and (t.min() < a.t_host_s[0] or t.max() > a.t_host_s[-1]):
            raise SampleRangeError(
                f"times [{t.min():.6f}, {t.max():.6f}] s outside the sampled span "
                f"[{a.t_host_s[0]:.6f}, {a.t_host_s[-1]:.6f}] s (no extrapolation)"
            )
        return np.interp(t, a.t_host_s, a.position_rad)

    def since(self, t_host_s: float = -math.inf) -> list[MotorSample]:
        a = self.arrays_since(t_host_s)
        return [
            _sample(t, p, v, s, d, rx)
            for t, p, v, s, d, rx in zip(
                a.t_host_s, a.position_rad, a.velocity_rad_s, a.statusword, a.drive_stamp_us, a.t_rx_host_s, strict=True
            )
        ]


@dataclass(frozen=True)
class FaultInfo:
    """Why the drive is faulted: error code (0x603F / EMCY), its meaning, and when it was seen."""

    code: int
    reason: str
    error_register: int = 0
    t_host_s: float = math.nan
    source: str = "drive"  # "drive" (0x603F / EMCY), "heartbeat" or "bus" (found by the host)

    def to_exception(self, statusword: int | None = None) -> MotorFault:
        if self.source == "heartbeat":
            return HeartbeatLost(self.code, self.reason, statusword)
        if self.source == "bus":
            return ConnectionLost(self.code, self.reason, statusword)
        return MotorFault(self.code, self.reason, statusword)


# --------------------------------------------------------------------------------------------
# The interface
# --------------------------------------------------------------------------------------------

SampleCallback = Callable[[MotorSample], None]


class Motor(abc.ABC):
    """One servo axis. Angles in rad at the output shaft, times in host seconds.

    Every backend implements the abstract methods; the sample buffer, callbacks and the context
    manager are shared here. Commands raise :class:`MotorFault` while the drive is faulted,
    :class:`MotorStateError` when the drive is not in a state that allows them.
    """

    def __init__(self, config: DriveConfig, clock: Clock = time.monotonic, buffer_size: int = 65536) -> None:
        self.config = config
        self.clock = clock
        self._samples = SampleBuffer(buffer_size)
        self._callbacks: list[SampleCallback] = []
        self._cb_lock = threading.Lock()

    # -- commands ---------------------------------------------------------------------------
    @abc.abstractmethod
    def enable(self, timeout: float = 2.0) -> None:
        """Walk the drive to *Operation enabled* (raises :class:`MotorFault` if it is faulted)."""

    @abc.abstractmethod
    def disable(self, timeout: float = 2.0) -> None:
        """Disable operation (power stage off, drive in *Ready to switch on*)."""

    @abc.abstractmethod
    def home(self, method: int | None = None, timeout: float = 30.0) -> None:
        """Run the drive's homing (method from config unless given) and wait for completion."""

    @abc.abstractmethod
    def move_to(
        self,
        angle_rad: float,
        velocity: float | None = None,
        acceleration: float | None = None,
        *,
        wait: bool = False,
        timeout: float | None = None,
    ) -> None:
        """Start an absolute move (profile position); with ``wait`` also wait until reached."""

    @abc.abstractmethod
    def jog(self, velocity: float, acceleration: float | None = None) -> None:
        """Turn at constant ``velocity`` rad/s (profile velocity) until stopped."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Decelerate to standstill with the profile deceleration, staying enabled (halt)."""

    @abc.abstractmethod
    def quick_stop(self) -> None:
        """Quick stop: decelerate with the quick-stop ramp; the drive then leaves *Operation enabled*."""

    @abc.abstractmethod
    def wait_reached(self, timeout: float = 10.0) -> None:
        """Wait until the target (position, velocity or halt standstill) is reached."""

    @abc.abstractmethod
    def fault(self) -> FaultInfo | None:
        """The present fault with its decoded reason, or ``None``."""

    @abc.abstractmethod
    def reset_fault(self, timeout: float = 2.0) -> None:
        """Fault reset (rising edge of controlword bit 7); the drive ends in *Switch on disabled*."""

    @property
    @abc.abstractmethod
    def statusword(self) -> int:
        """The latest statusword known to the host."""

    @property
    def state(self) -> State:
        return cia402.decode_state(self.statusword)

    @abc.abstractmethod
    def position_rad(self) -> float:
        """The latest position (rad at the output shaft)."""

    @abc.abstractmethod
    def velocity_rad_s(self) -> float:
        """The latest velocity (rad/s at the output shaft)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the bus / port; calling it twice is harmless."""

    def __enter__(self) -> Motor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- samples ----------------------------------------------------------------------------
    def samples_since(self, t_host_s: float = -math.inf) -> list[MotorSample]:
        return self._samples.since(t_host_s)

    def sample_arrays_since(self, t_host_s: float = -math.inf) -> SampleArrays:
        """Samples after ``t_host_s`` as numpy arrays (for interpolating beta at scan times)."""
        return self._samples.arrays_since(t_host_s)

    def latest_sample(self) -> MotorSample | None:
        return self._samples.latest()

    def positions_at(self, t_host_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Output-shaft angles (rad) at host times, interpolated between samples (vectorised);
        :class:`SampleRangeError` for times outside the buffered samples."""
        return self._samples.positions_at(t_host_s)

    @property
    def sample_count(self) -> int:
        return self._samples.total

    def add_sample_callback(self, callback: SampleCallback) -> Callable[[], None]:
        """Call ``callback(sample)`` for every new sample (from the backend's thread; keep it short).
        Returns a function that removes the callback."""
        with self._cb_lock:
            self._callbacks.append(callback)

        def remove() -> None:
            with self._cb_lock:
                if callback in self._callbacks:
                    self._callbacks.remove(callback)

        return remove

    def _push_sample(self, sample: MotorSample) -> None:
        self._samples.push(sample)
        with self._cb_lock:
            callbacks = list(self._callbacks)
        for cb in callbacks:
            try:
                cb(sample)
            except Exception:  # a failing consumer must not stop the backend's receive thread
                _log.exception("sample callback %r failed", cb)


# --------------------------------------------------------------------------------------------
# CiA 402 behaviour on top of object access
# --------------------------------------------------------------------------------------------


class Cia402Motor(Motor):
    """:class:`Motor` for any drive that exposes the CiA 402 objects.

    Backends implement :meth:`_read_object`, :meth:`_write_object`, :meth:`_write_controlword`
    and :meth:`_statusword_after`; everything else (the state machine walk, the profile position
    handshake, profile velocity, homing, halt, quick stop, fault decoding) lives here once.
    """

    poll_interval_s = 0.002

    def __init__(self, config: DriveConfig, clock: Clock = time.monotonic, buffer_size: int = 65536) -> None:
        super().__init__(config, clock, buffer_size)
        self._cmd_lock = threading.RLock()
        self._controlword = 0
        self._host_fault: FaultInfo | None = None  # faults the host detects itself (heartbeat)

    # -- backend primitives -------------------------------------------------------------------
    @abc.abstractmethod
    def _read_object(self, index: int, subindex: int = 0) -> int:
        """Read an integer object (typed by :data:`cia402.OBJECTS`)."""

    @abc.abstractmethod
    def _write_object(self, index: int, subindex: int, value: int) -> None:
        """Write an integer object (typed by :data:`cia402.OBJECTS`)."""

    def _write_controlword(self, controlword: int) -> None:
        self._write_object(cia402.CONTROLWORD, 0, controlword)

    @abc.abstractmethod
    def _statusword_after(self, t: float, timeout: float) -> int:
        """A statusword sampled by the drive after host time ``t`` (waits up to ``timeout``)."""

    # -- helpers ------------------------------------------------------------------------------
    def _cw(self, controlword: int) -> None:
        self._write_controlword(controlword)
        self._controlword = controlword

    def _fresh_statusword(self, timeout: float = 1.0) -> int:
        return self._statusword_after(self.clock(), timeout)

    def _raise_if_faulted(self, statusword: int | None = None) -> None:
        if self._host_fault is not None:
            raise self._host_fault.to_exception(statusword)
        sw = self._fresh_statusword() if statusword is None else statusword
        if cia402.decode_state(sw) in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            info = self.fault()
            if info is None:  # cleared between the two reads
                return
            raise info.to_exception(sw)

    def _wait_state(self, wanted: State, timeout: float, what: str) -> int:
        deadline = self.clock() + timeout
        t = self.clock()  # callers have written their command before: later statuswords reflect it
        while True:
            sw = self._statusword_after(t, max(0.0, deadline - self.clock()))
            state = cia402.decode_state(sw)
            if state is wanted:
                return sw
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) and wanted is not State.FAULT:
                self._raise_if_faulted(sw)
            if self.clock() >= deadline:
                raise MotionTimeout(
                    f"{what}: drive still in {cia402.describe_statusword(sw)} after {timeout:.3g} s "
                    f"(waiting for {wanted.label})"
                )
            t = self.clock()

    def _set_mode(self, mode: Mode, timeout: float = 1.0) -> None:
        if self._read_object(cia402.MODES_OF_OPERATION_DISPLAY) == mode:
            return
        self._write_object(cia402.MODES_OF_OPERATION, 0, int(mode))
        deadline = self.clock() + timeout
        while self._read_object(cia402.MODES_OF_OPERATION_DISPLAY) != mode:
            if self.clock() > deadline:
                raise MotionTimeout(f"drive did not switch to mode {mode.name} within {timeout} s")
            time.sleep(self.poll_interval_s)

    def _require_enabled(self, what: str) -> int:
        sw = self._fresh_statusword()
        self._raise_if_faulted(sw)
        state = cia402.decode_state(sw)
        if state is not State.OPERATION_ENABLED:
            raise MotorStateError(f"cannot {what}: drive is in {state.label}, call enable() first")
        return sw

    def _rate(self, value: float | None, default: float, limit: float, name: str) -> int:
        v = default if value is None else value
        if not math.isfinite(v) or v <= 0:
            raise ServoValueError(f"{name} must be finite and > 0, got {v}")
        if v > limit:
            raise TargetOutOfRange(f"{name} {v:.4g} exceeds the configured maximum {limit:.4g}")
        return max(1, self.config.rate_to_counts(v))

    # -- configuration pushed to the drive ------------------------------------------------------
    def _configure_drive(self) -> None:
        """Write the config's windows, quick-stop ramp, homing and software limits to the drive."""
        c = self.config
        self._write_object(cia402.POSITION_WINDOW, 0, max(1, abs(round(c.position_window_rad * c.counts_per_rad))))
        self._write_object(
            cia402.FOLLOWING_ERROR_WINDOW, 0, max(1, abs(round(c.following_error_window_rad * c.counts_per_rad)))
        )
        self._write_object(
            cia402.QUICK_STOP_DECELERATION, 0, max(1, c.rate_to_counts(c.quick_stop_deceleration_rad_s2))
        )
        self._write_object(cia402.HOME_OFFSET, 0, c.rad_to_counts(c.home_offset_rad))
        limits = c.software_limits_counts()
        if limits is not None:
            self._write_object(cia402.SOFTWARE_POSITION_LIMIT, 1, limits[0])
            self._write_object(cia402.SOFTWARE_POSITION_LIMIT, 2, limits[1])

    # -- Motor ----------------------------------------------------------------------------------
    @property
    def statusword(self) -> int:
        return self._fresh_statusword()

    def enable(self, timeout: float = 2.0) -> None:
        with self._cmd_lock:
            deadline = self.clock() + timeout
            sw = self._fresh_statusword()
            self._raise_if_faulted(sw)
            for _ in range(8):
                state = cia402.decode_state(sw)
                if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    self._raise_if_faulted(sw)
                if state is State.NOT_READY_TO_SWITCH_ON:  # still initialising: it leaves by itself
                    sw = self._wait_state(State.SWITCH_ON_DISABLED, max(0.0, deadline - self.clock()), "enable")
                    continue
                cw = cia402.next_enable_command(state)
                if cw is None:
                    return
                want = {
                    cia402.CMD_SHUTDOWN: State.READY_TO_SWITCH_ON,
                    cia402.CMD_SWITCH_ON: State.SWITCHED_ON,
                    cia402.CMD_ENABLE_OPERATION: State.OPERATION_ENABLED,
                }[cw]
                self._cw(cw)
                sw = self._wait_state(want, max(0.0, deadline - self.clock()), "enable")
            raise MotorStateError(f"enable: drive did not reach Operation enabled ({cia402.describe_statusword(sw)})")

    def disable(self, timeout: float = 2.0) -> None:
        with self._cmd_lock:
            sw = self._fresh_statusword()
            state = cia402.decode_state(sw)
            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE, State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON):
                return  # the power stage is already off
            if state is State.QUICK_STOP_ACTIVE:  # only "disable voltage" leaves it (transition 12)
                self._cw(cia402.CMD_DISABLE_VOLTAGE)
                self._wait_state(State.SWITCH_ON_DISABLED, timeout, "disable")
                return
            self._cw(cia402.CMD_SHUTDOWN)
            self._wait_state(State.READY_TO_SWITCH_ON, timeout, "disable")

    def move_to(
        self,
        angle_rad: float,
        velocity: float | None = None,
        acceleration: float | None = None,
        *,
        wait: bool = False,
        timeout: float | None = None,
    ) -> None:
        c = self.config
        c.check_angle(angle_rad)
        target = c.rad_to_counts(angle_rad)
        v = self._rate(velocity, c.velocity_rad_s, c.max_velocity_rad_s, "velocity")
        a = self._rate(acceleration, c.acceleration_rad_s2, c.max_acceleration_rad_s2, "acceleration")
        with self._cmd_lock:
            self._require_enabled("move")
            self._set_mode(Mode.PROFILE_POSITION)
            self._write_object(cia402.PROFILE_VELOCITY, 0, v)
            self._write_object(cia402.PROFILE_ACCELERATION, 0, a)
            self._write_object(cia402.PROFILE_DECELERATION, 0, a)
            self._write_object(cia402.TARGET_POSITION, 0, target)
            base = cia402.CMD_ENABLE_OPERATION
            if self._controlword & cia402.CW_NEW_SET_POINT:  # need a rising edge of bit 4
                self._cw(base)
            t0 = self.clock()
            self._cw(base | cia402.CW_NEW_SET_POINT | cia402.CW_CHANGE_SET_IMMEDIATELY)
            deadline = t0 + 1.0
            while True:  # wait for set-point acknowledge (statusword bit 12)
                remaining = deadline - self.clock()
                if remaining <= 0:
                    self._cw(base)
                    raise MotionTimeout("drive did not acknowledge the new set-point within 1 s")
                sw = self._statusword_after(t0, remaining)
                self._raise_if_faulted(sw)
                if sw & cia402.SW_SET_POINT_ACK:
                    break
                t0 = self.clock()
            self._cw(base)
        if wait:
            if timeout is None:
                dist = abs(angle_rad - self.position_rad())
                vv, aa = v / abs(c.counts_per_rad), a / abs(c.counts_per_rad)
                timeout = 2.0 + 2.0 * (dist / vv + vv / aa)
            self.wait_reached(timeout)

    def jog(self, velocity: float, acceleration: float | None = None) -> None:
        c = self.config
        if not math.isfinite(velocity):
            raise ServoValueError(f"velocity must be finite, got {velocity}")
        if abs(velocity) > c.max_velocity_rad_s:
            raise TargetOutOfRange(f"jog velocity {velocity:.4g} rad/s exceeds {c.max_velocity_rad_s:.4g} rad/s")
        a = self._rate(acceleration, c.acceleration_rad_s2, c.max_acceleration_rad_s2, "acceleration")
        target = round(velocity * c.counts_per_rad)
        with self._cmd_lock:
            self._require_enabled("jog")
            self._set_mode(Mode.PROFILE_VELOCITY)
            self._write_object(cia402.PROFILE_ACCELERATION, 0, a)
            self._write_object(cia402.PROFILE_DECELERATION, 0, a)
            self._write_object(cia402.TARGET_VELOCITY, 0, target)
            self._cw(cia402.CMD_ENABLE_OPERATION)  # clears halt

    def stop(self) -> None:
        with self._cmd_lock:
            sw = self._fresh_statusword()
            if cia402.decode_state(sw) is State.OPERATION_ENABLED:
                self._cw(cia402.CMD_ENABLE_OPERATION | cia402.CW_HALT)

    def quick_stop(self) -> None:
        with self._cmd_lock:
            self._cw(cia402.CMD_QUICK_STOP)

    def wait_reached(self, timeout: float = 10.0) -> None:
        deadline = self.clock() + timeout
        t = self.clock()
        while True:
            remaining = deadline - self.clock()
            if remaining <= 0:
                raise MotionTimeout(
                    f"target not reached within {timeout:.3g} s (at {math.degrees(self.position_rad()):.3f} deg)"
                )
            sw = self._statusword_after(t, remaining)
            self._raise_if_faulted(sw)
            state = cia402.decode_state(sw)
            if state is not State.OPERATION_ENABLED:
                raise MotorStateError(f"motion ended: drive left Operation enabled ({cia402.describe_statusword(sw)})")
            if sw & cia402.SW_TARGET_REACHED:
                return
            t = self.clock()

    def home(self, method: int | None = None, timeout: float = 30.0) -> None:
        m = self.config.homing_method if method is None else method
        if not -128 <= m <= 127:
            raise ServoValueError(f"homing method must fit an i8, got {m}")
        with self._cmd_lock:
            self._require_enabled("home")
            self._set_mode(Mode.HOMING)
            self._write_object(cia402.HOMING_METHOD, 0, m)
            self._cw(cia402.CMD_ENABLE_OPERATION)
            t = self.clock()
            self._cw(cia402.CMD_ENABLE_OPERATION | cia402.CW_NEW_SET_POINT)  # homing operation start
            deadline = t + timeout
            try:
                while True:
                    remaining = deadline - self.clock()
                    if remaining <= 0:
                        raise MotionTimeout(f"homing (method {m}) did not complete within {timeout:.3g} s")
                    sw = self._statusword_after(t, remaining)
                    self._raise_if_faulted(sw)
                    status = cia402.decode_homing_status(sw)
                    if status is cia402.HomingStatus.COMPLETED:
                        return
                    if status in (cia402.HomingStatus.ERROR_MOVING, cia402.HomingStatus.ERROR_STOPPED):
                        raise MotorStateError(f"homing method {m} failed: {status.value}")
                    t = self.clock()
            finally:
                self._cw(cia402.CMD_ENABLE_OPERATION)  # clear bit 4 for the next set-point

    def fault(self) -> FaultInfo | None:
        if self._host_fault is not None:
            return self._host_fault
        try:
            sw = self._fresh_statusword()
        except MotorFault:
            if self._host_fault is not None:  # detected meanwhile
                return self._host_fault
            raise
        if cia402.decode_state(sw) not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return None
        code = self._read_object(cia402.ERROR_CODE)
        return FaultInfo(code, cia402.describe_error_code(code), self._error_register(), self.clock())

    def _error_register(self) -> int:
        """Object 0x1001 (error register) of a drive in fault; a backend that cannot read it returns 0."""
        return self._read_object(cia402.ERROR_REGISTER)

    def reset_fault(self, timeout: float = 2.0) -> None:
        with self._cmd_lock:
            self._clear_host_fault()
            sw = self._fresh_statusword()
            if cia402.decode_state(sw) not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                return
            if cia402.decode_state(sw) is State.FAULT_REACTION_ACTIVE:  # commands are ignored until it ends
                self._wait_state(State.FAULT, timeout, "fault reaction")
            self._cw(cia402.CMD_DISABLE_VOLTAGE)  # bit 7 low, for the rising edge
            self._cw(cia402.CMD_FAULT_RESET)
            try:
                self._wait_state(State.SWITCH_ON_DISABLED, timeout, "fault reset")
            except MotorFault as exc:  # still faulted: report why
                raise MotorFault(exc.code, exc.reason, exc.statusword, "fault reset did not clear it") from None
            finally:
                self._cw(cia402.CMD_DISABLE_VOLTAGE)

    def _clear_host_fault(self) -> None:
        """Backends re-check their own condition (e.g. heartbeat back) and clear or keep it."""
        self._host_fault = None

    def position_rad(self) -> float:
        s = self.latest_sample()
        if s is not None:
            return s.position_rad
        return self.config.counts_to_rad(self._read_object(cia402.POSITION_ACTUAL))

    def velocity_rad_s(self) -> float:
        s = self.latest_sample()
        if s is not None:
            return s.velocity_rad_s
        return self.config.counts_to_rad(self._read_object(cia402.VELOCITY_ACTUAL))
