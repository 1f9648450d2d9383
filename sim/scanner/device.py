"""The simulated SICK LMS100: state machine, device clock, counters, and ray-cast scans.

Transport-free: :class:`SimulatedLMS100` answers decoded CoLa requests (``handle``) and makes
scans (``make_scan``); :mod:`sim.scanner.server` moves the bytes over TCP.

Behaviour modelled after the LMS1xx (``shared/reference/sick-cola.md``):

* Access levels per connection: 0 (run) after connecting; ``SetAccessMode`` with level 2
  (maintenance, "main"), 3 (authorized client, "client") or 4 (service) and the matching password
  hash logs in (``sAN SetAccessMode 1``), a wrong hash is refused (``0``). Writes and the
  configuration methods need level 3 or 4: otherwise methods answer ``sFA 1``
  (METHODIN_ACCESSDENIED) and variable writes ``sFA A`` (VARIABLE_WRITE_ACCESSDENIED).
* Logging in puts the device in configuration mode: no scans leave it (stream or poll) until
  ``sMN Run``, which also ends that connection's login.
* ``mLMPsetscancfg`` accepts only what an LMS1xx accepts: 25 Hz at 0.25 deg and 50 Hz at
  0.5 deg (both 36,000 shots/s), one sector, a scan area within -45..225 deg; otherwise the reply's status byte says
  why (1 frequency, 2 resolution, 3 both, 4 area, 5 other) and the applied configuration stays.
* ``LMCstartmeas`` / ``LMCstopmeas`` switch measuring (STlms 7) on and off; the device boots
  measuring. ``mEEwriteall`` saves the configuration, ``mSCreboot`` restores the saved one.
* Unknown variables answer ``sFA 3``, unknown methods ``sFA 2``, unknown events ``sFA F``,
  out-of-range values ``sFA 4``.

Clock: microseconds since start-up (uint32 on the wire, wrapping after 71.6 min). In real-time
mode it follows the host's monotonic clock (times ``time_scale``); otherwise it is virtual and
advances by one scan period per scan made. Scan ``k`` of a measuring epoch starts (beam 0 of
the output range) at ``epoch_start + (k - epoch_index) * period``; beam ``j`` is fired
``j * time_increment`` later, with ``time_increment = period * resolution / 360 deg`` (the mirror
turns once per period; 27.8 us at 25 Hz / 0.25 deg). The time of transmission is the end of the
scan plus :data:`TRANSMIT_DELAY_US`.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from drivers.errors import DriverError
from drivers.lms100 import (
    PASSWORD_HASHES,
    AccessLevel,
    DeviceIdent,
    DeviceReady,
    DeviceState,
    ErrorReply,
    FirmwareVersion,
    LocationName,
    Message,
    OperatingHours,
    OutputRange,
    PollScan,
    PowerOnCount,
    RawTelegram,
    ReadDeviceIdent,
    ReadDeviceReady,
    ReadDeviceState,
    ReadFirmwareVersion,
    ReadLocationName,
    ReadOperatingHours,
    ReadOutputRange,
    ReadPowerOnCount,
    ReadScanConfig,
    ReadScanDataConfig,
    ReadSerialNumber,
    Reboot,
    RebootReply,
    Run,
    RunReply,
    SaveParameters,
    SaveParametersReply,
    Scan,
    ScanConfig,
    ScanDataConfig,
    ScanDataReply,
    ScanTime,
    SerialNumber,
    SetAccessMode,
    SetAccessModeReply,
    SetHostDialect,
    SetHostDialectReply,
    SetScanConfig,
    SetScanConfigReply,
    StartMeasurement,
    StartMeasurementReply,
    StopMeasurement,
    StopMeasurementReply,
    SubscribeScanData,
    SubscribeScanDataReply,
    WriteOutputRange,
    WriteOutputRangeReply,
    WriteScanDataConfig,
    WriteScanDataConfigReply,
    make_channel,
)
from lrms.kinematics import RigCalibration
from sim.scene import Scene, SensorModel, cast_beams, get_scene

# sFA codes used by the simulated device.
SFA_METHOD_ACCESS_DENIED = 0x01
SFA_UNKNOWN_METHOD = 0x02
SFA_UNKNOWN_VARIABLE = 0x03
SFA_OUT_OF_RANGE = 0x04
SFA_UNKNOWN_ERROR = 0x06
SFA_BUFFER_UNDERFLOW = 0x08
SFA_WRITE_ACCESS_DENIED = 0x0A
SFA_UNKNOWN_COLA_COMMAND = 0x0C
SFA_UNKNOWN_EVENT = 0x0F
SFA_COLA_A_INVALID_CHARACTER = 0x11
SFA_INTERNAL = 0x14

#: Accepted (scan frequency 1/100 Hz, angular resolution 1/10000 deg) pairs of an LMS1xx.
ALLOWED_SCAN_CONFIGS = frozenset({(2500, 2500), (5000, 5000)})
FIELD_START = -450000  # 1/10000 deg
FIELD_STOP = 2250000
#: The scan is handed to the interface this long after its last beam (us).
TRANSMIT_DELAY_US = 1000
U32 = 1 << 32
#: Events an LMS1xx offers besides LMDscandata (accepted, never fired in the simulation).
QUIET_EVENTS = frozenset({"LIDoutputstate", "LIDinputstate", "LFErec"})

MotorAngleFn = Callable[[np.ndarray], np.ndarray]


class SimulatorError(DriverError):
    """A simulated device was configured or driven with bad arguments."""


def _constant_zero(times_s: np.ndarray) -> np.ndarray:
    return np.zeros_like(np.asarray(times_s, dtype=np.float64))


class DeviceClock:
    """Microseconds since the simulated device started.

    ``realtime=True``: follows ``time.monotonic()`` scaled by ``time_scale``. ``realtime=False``:
    virtual, moved forward only by :meth:`advance_to`.
    """

    def __init__(self, realtime: bool = True, time_scale: float = 1.0, start_us: int = 0) -> None:
        if not (math.isfinite(time_scale) and time_scale > 0):
            raise SimulatorError(f"time_scale must be a positive number, got {time_scale!r}")
        self.realtime = bool(realtime)
        self.time_scale = float(time_scale)
        self._boot = time.monotonic()
        self._start_us = int(start_us)
        self._virtual_us = int(start_us)
        self._lock = threading.Lock()

    def now_us(self) -> int:
        if self.realtime:
            return self._start_us + int((time.monotonic() - self._boot) * 1e6 * self.time_scale)
        with self._lock:
            return self._virtual_us

    def advance_to(self, us: int) -> None:
        """Virtual clock: move forward to ``us`` (never backwards). Real-time clock: no effect."""
        if not self.realtime:
            with self._lock:
                self._virtual_us = max(self._virtual_us, int(us))

    def monotonic_at(self, us: int) -> float:
        """Host ``time.monotonic()`` value at which a real-time clock reads ``us``."""
        return self._boot + (us - self._start_us) / 1e6 / self.time_scale


@dataclass
class Session:
    """Per-connection state: login level and the scan subscription."""

    access_level: int = 0
    subscribed: bool = False
    id: int = 0


@dataclass
class _Config:
    scan_frequency: int = 2500
    angular_resolution: int = 2500
    start_angle: int = FIELD_START
    stop_angle: int = FIELD_STOP
    out_start: int = FIELD_START
    out_stop: int = FIELD_STOP
    data: WriteScanDataConfig = field(
        default_factory=lambda: WriteScanDataConfig(remission=False, resolution=0, time=False, output_rate=1)
    )

    def copy(self) -> _Config:
        return dataclasses.replace(self)


@dataclass(frozen=True)
class ScanTiming:
    """When scan ``index`` happened, in device-clock microseconds."""

    index: int
    start_us: int
    end_us: int
    transmit_us: int


class SimulatedLMS100:
    """An LMS100 in a ray-cast scene. Thread-safe: all state changes happen under ``self.lock``.

    ``scene``: a :class:`Scene` or a scene name; ``calibration``: places the rig (and defines
    how device angles and motor angles become rays); ``motor_angle_at``: motor angle (rad) at
    device-clock times (s), called with one time per beam; ``sensor``: noise and echo model;
    ``seed``: scan ``k``'s noise comes from ``default_rng([seed, k])`` (reproducible, and the
    same scan for every client). ``startup_status_scans``: the first scans after measuring
    starts carry device status ``(1, 0)`` as real LMS1xx do (0 turns this off).
    ``reconfigure_busy_s``: after a successful ``mLMPsetscancfg`` the device reports
    ``SCdevicestate`` 0 (busy) and sends no scans for this long (device-clock seconds).
    """

    def __init__(
        self,
        scene: Scene | str = "seed003",
        calibration: RigCalibration | None = None,
        motor_angle_at: MotorAngleFn | None = None,
        sensor: SensorModel | None = None,
        *,
        seed: int = 0,
        realtime: bool = True,
        time_scale: float = 1.0,
        clock: DeviceClock | None = None,
        serial_number: int = 19060042,
        device_name: str = "LMS10x_FieldEval",
        device_version: str = "V1.36-21.10.2010",
        firmware_version: str = "V1.80.2  ",
        location_name: str = "simulated LMS100",
        startup_status_scans: int = 7,
        reconfigure_busy_s: float = 0.0,
    ) -> None:
        self.scene = get_scene(scene) if isinstance(scene, str) else scene
        if not isinstance(self.scene, Scene):
            raise SimulatorError(f"scene must be a Scene or a scene name, got {scene!r}")
        self.calibration = calibration if calibration is not None else RigCalibration()
        self.motor_angle_at: MotorAngleFn = motor_angle_at if motor_angle_at is not None else _constant_zero
        self.sensor = sensor if sensor is not None else SensorModel()
        if not 0 < serial_number < U32:
            raise SimulatorError(f"serial number must fit uint32, got {serial_number}")
        if startup_status_scans < 0 or reconfigure_busy_s < 0:
            raise SimulatorError("startup_status_scans and reconfigure_busy_s must be >= 0")
        self.seed = int(seed)
        self.clock = clock if clock is not None else DeviceClock(realtime, time_scale)
        self.serial_number = int(serial_number)
        self.device_name = device_name
        self.device_version = device_version
        self.firmware_version = firmware_version
        self.location_name = location_name
        self.startup_status_scans = int(startup_status_scans)
        self.reconfigure_busy_s = float(reconfigure_busy_s)
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        """Notified whenever something that affects streaming changes."""
        self.sessions: list[Session] = []
        self._next_session = 1
        self.power_on_count = 1
        self.host_dialect = 1
        self.reboot_requested = False
        self._virtual_next = 0
        self._saved = _Config()
        self._reset_volatile()

    # ------------------------------------------------------------------ state
    def _reset_volatile(self) -> None:
        self.config = self._saved.copy()
        self.measuring = True
        self.config_mode = False
        self._config_owner: Session | None = None
        self.telegram_counter = 0
        self._busy_until_us = -1
        self._scan_cache: OrderedDict[int, Scan] = OrderedDict()
        self._last_sent: Scan | None = None
        self._start_epoch(self.clock.now_us(), 0)

    def _start_epoch(self, start_us: int, index: int) -> None:
        self.epoch_start_us = int(start_us)
        self.epoch_index = int(index)
        self.measure_start_index = int(index)
        self._scan_cache.clear()

    @property
    def period_us(self) -> int:
        return round(1e8 / self.config.scan_frequency)

    @property
    def time_increment_us(self) -> float:
        """Time between neighbouring beams (us): one mirror turn per scan period."""
        return self.period_us * (self.config.angular_resolution / 1e4) / 360.0

    @property
    def measurement_frequency(self) -> int:
        """Shots per second / 100 (the LMDscandata field): 360 at 25 Hz/0.25 deg and 50 Hz/0.5 deg."""
        return round(self.config.scan_frequency / 100 * 360 / (self.config.angular_resolution / 1e4) / 100)

    def output_angles_raw(self) -> np.ndarray:
        """Beam angles of the output range, 1/10000 deg."""
        c = self.config
        first = c.start_angle + math.ceil((c.out_start - c.start_angle) / c.angular_resolution) * c.angular_resolution
        count = (c.out_stop - first) // c.angular_resolution + 1
        return first + c.angular_resolution * np.arange(count, dtype=np.int64)

    def open_session(self) -> Session:
        with self.lock:
            s = Session(id=self._next_session)
            self._next_session += 1
            self.sessions.append(s)
            return s

    def close_session(self, session: Session) -> None:
        with self.lock:
            if session in self.sessions:
                self.sessions.remove(session)
            if self._config_owner is session:  # its connection is gone: leave configuration mode
                self.config_mode = False
                self._config_owner = None
            self.changed.notify_all()

    def busy(self) -> bool:
        return self.clock.now_us() < self._busy_until_us

    def streaming(self) -> bool:
        """True when scans leave the device: measuring, not in configuration mode, not busy."""
        return self.measuring and not self.config_mode and not self.busy()

    def subscribers(self) -> list[Session]:
        with self.lock:
            return [s for s in self.sessions if s.subscribed]

    def device_state(self) -> int:
        """STlms status: 7 measuring, 6 ready (laser stopped), 2 configuration mode while not measuring."""
        if self.measuring and not self.busy():
            return 7
        return 2 if self.config_mode else 6

    # ------------------------------------------------------------------ scan timing
    def timing(self, index: int) -> ScanTiming:
        if index < self.epoch_index:
            raise SimulatorError(f"scan {index} lies before the current measuring epoch ({self.epoch_index})")
        start = self.epoch_start_us + (index - self.epoch_index) * self.period_us
        n = len(self.output_angles_raw())
        end = start + round((n - 1) * self.time_increment_us)
        return ScanTiming(index, start, end, end + TRANSMIT_DELAY_US)

    def latest_complete_index(self, now_us: int | None = None) -> int:
        """Index of the newest scan transmitted by ``now_us`` (``epoch_index - 1`` if none yet)."""
        now = self.clock.now_us() if now_us is None else now_us
        first = self.timing(self.epoch_index)
        if now < first.transmit_us:
            return self.epoch_index - 1
        return self.epoch_index + (now - first.transmit_us) // self.period_us

    def is_output_scan(self, index: int) -> bool:
        """LMDscandatacfg output rate n: only every n-th scan is sent."""
        return index % max(1, self.config.data.output_rate) == 0

    # ------------------------------------------------------------------ scans
    def make_scan(self, index: int) -> Scan:
        """Scan ``index`` of the current epoch, ray-cast (cached; counters are set on sending)."""
        with self.lock:
            cached = self._scan_cache.get(index)
            if cached is not None:
                return cached
            cfg = self.config.copy()
            t = self.timing(index)
            dev_raw = self.output_angles_raw()
            inc = self.time_increment_us
            meas_freq = self.measurement_frequency
            status = (1, 0) if index - self.measure_start_index < self.startup_status_scans else (0, 0)
        beam_times_s = (t.start_us + inc * np.arange(len(dev_raw))) / 1e6
        motor = np.asarray(self.motor_angle_at(beam_times_s), dtype=np.float64)
        if motor.shape != beam_times_s.shape or not np.all(np.isfinite(motor)):
            raise SimulatorError(f"motor_angle_at must return one finite angle per beam time, got shape {motor.shape}")
        dev_rad = np.deg2rad(dev_raw / 1e4)
        rng = np.random.default_rng([self.seed, index])
        rig = self.calibration.rig
        speed = None  # the motor speed at each beam, for a rig with backlash or a scan/motor time offset
        if (rig.backlash != 0.0 or rig.time_offset != 0.0) and motor.size > 1:
            speed = np.gradient(motor, beam_times_s)
        samples = cast_beams(self.scene, self.calibration, self.sensor, dev_rad, motor, rng, speed)
        mm = np.clip(np.rint(samples.ranges * 1000.0), 0, 65535).astype(np.uint16)
        start_deg, step_deg = float(dev_raw[0]) / 1e4, cfg.angular_resolution / 1e4
        channels_16 = [make_channel("DIST1", mm, start_deg, step_deg)]
        channels_8 = []
        if cfg.data.remission:
            if cfg.data.resolution == 1:
                channels_16.append(
                    make_channel(
                        "RSSI1", np.clip(np.rint(samples.rssi), 0, 65535).astype(np.uint16), start_deg, step_deg
                    )
                )
            else:
                channels_8.append(
                    make_channel("RSSI1", np.clip(np.rint(samples.rssi), 0, 255).astype(np.uint8), start_deg, step_deg)
                )
        time_info = None
        if cfg.data.time:
            secs, micro = divmod(t.start_us, 1_000_000)
            mins, s = divmod(secs, 60)
            hours, m = divmod(mins, 60)
            time_info = ScanTime(1970, 1, 1 + hours // 24, hours % 24, m, s, micro)
        scan = Scan(
            version=1,
            device_number=1,
            serial_number=self.serial_number,
            device_status=status,
            telegram_counter=0,
            scan_counter=index % 65536,
            time_since_startup_us=t.start_us % U32,
            time_of_transmission_us=t.transmit_us % U32,
            digital_inputs=(0, 0),
            digital_outputs=(0, 0),
            layer_angle=0,
            scan_frequency=cfg.scan_frequency,
            measurement_frequency=meas_freq,
            channels_16=channels_16,
            channels_8=channels_8,
            name=self.location_name if cfg.data.device_name else None,
            comment="" if cfg.data.comment else None,
            time_info=time_info,
        )
        with self.lock:
            self._scan_cache[index] = scan
            while len(self._scan_cache) > 8:
                self._scan_cache.popitem(last=False)
        return scan

    def stamp(self, scan: Scan) -> Scan:
        """The scan as one sent telegram: the next telegram counter value."""
        with self.lock:
            self.telegram_counter = (self.telegram_counter + 1) % 65536
            out = dataclasses.replace(scan, telegram_counter=self.telegram_counter)
            self._last_sent = out
            return out

    def poll(self) -> Message:
        """Answer to ``sRN LMDscandata``: the newest complete scan (virtual clock: the next scan).

        Real time: if no scan of the current epoch is complete yet, waits for the first one.
        """
        wait_until = 0.0
        with self.lock:
            if not self.streaming():
                if self._last_sent is not None:
                    return ScanDataReply(self._last_sent)
                return ErrorReply(SFA_UNKNOWN_ERROR)
            if self.clock.realtime:
                index = max(self.latest_complete_index(), self.epoch_index)
                wait_until = self.clock.monotonic_at(self.timing(index).transmit_us)
            else:
                index = self.next_virtual_index()
                self.clock.advance_to(self.timing(index).transmit_us)
                self._virtual_next = index + 1
        delay = wait_until - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        return ScanDataReply(self.stamp(self.make_scan(index)))

    def next_virtual_index(self) -> int:
        """Virtual clock: the first scan that has not been transmitted yet."""
        with self.lock:
            return max(self._virtual_next, self.epoch_index, self.latest_complete_index() + 1)

    def mark_virtual_sent(self, index: int) -> None:
        with self.lock:
            self._virtual_next = index + 1

    # ------------------------------------------------------------------ requests
    def handle(self, session: Session, msg: Message) -> list[Message]:
        """Replies to one decoded request (usually one message; ``sEN`` subscriptions notify)."""
        if isinstance(msg, PollScan):
            return [self.poll()]
        with self.lock:
            replies = self._dispatch(session, msg)
            self.changed.notify_all()
            return replies

    def _need(self, session: Session, method: bool) -> ErrorReply | None:
        if session.access_level >= AccessLevel.AUTHORIZED_CLIENT:
            return None
        return ErrorReply(SFA_METHOD_ACCESS_DENIED if method else SFA_WRITE_ACCESS_DENIED)

    def _dispatch(self, session: Session, msg: Message) -> list[Message]:
        c = self.config
        if isinstance(msg, SetAccessMode):
            try:
                level = AccessLevel(msg.level)
            except ValueError:
                return [SetAccessModeReply(False)]
            if PASSWORD_HASHES[level] != msg.password_hash:
                return [SetAccessModeReply(False)]
            session.access_level = int(level)
            self.config_mode = True
            self._config_owner = session
            return [SetAccessModeReply(True)]
        if isinstance(msg, Run):
            session.access_level = 0
            self.config_mode = False
            self._config_owner = None
            return [RunReply(True)]
        if isinstance(msg, ReadScanConfig):
            return [ScanConfig(c.scan_frequency, 1, c.angular_resolution, c.start_angle, c.stop_angle)]
        if isinstance(msg, SetScanConfig):
            denied = self._need(session, method=True)
            if denied:
                return [denied]
            return [self._set_scan_config(msg)]
        if isinstance(msg, ReadOutputRange):
            return [OutputRange(1, c.angular_resolution, c.out_start, c.out_stop)]
        if isinstance(msg, WriteOutputRange):
            denied = self._need(session, method=False)
            if denied:
                return [denied]
            ok = (
                msg.sectors == 1
                and msg.angular_resolution == c.angular_resolution
                and c.start_angle <= msg.start_angle < msg.stop_angle <= c.stop_angle
            )
            if not ok:
                return [ErrorReply(SFA_OUT_OF_RANGE)]
            c.out_start, c.out_stop = msg.start_angle, msg.stop_angle
            self._restart_epoch()
            return [WriteOutputRangeReply()]
        if isinstance(msg, ReadScanDataConfig):
            d = c.data
            return [
                ScanDataConfig(
                    d.output_channel, d.remission, d.resolution, d.unit, d.encoder, d.position,
                    d.device_name, d.comment, d.time, d.output_rate,
                )
            ]  # fmt: skip
        if isinstance(msg, WriteScanDataConfig):
            denied = self._need(session, method=False)
            if denied:
                return [denied]
            ok = (
                tuple(msg.output_channel) == (1, 0)
                and msg.resolution in (0, 1)
                and msg.unit == 0
                and tuple(msg.encoder) == (0, 0)
                and not msg.position
                and 1 <= msg.output_rate <= 50000
            )
            if not ok:
                return [ErrorReply(SFA_OUT_OF_RANGE)]
            c.data = msg
            self._scan_cache.clear()
            return [WriteScanDataConfigReply()]
        if isinstance(msg, StartMeasurement):
            denied = self._need(session, method=True)
            if denied:
                return [denied]
            if not self.measuring:
                self.measuring = True
                self._restart_epoch(measure_start=True)
            return [StartMeasurementReply(0)]
        if isinstance(msg, StopMeasurement):
            denied = self._need(session, method=True)
            if denied:
                return [denied]
            self.measuring = False
            return [StopMeasurementReply(0)]
        if isinstance(msg, SaveParameters):
            denied = self._need(session, method=True)
            if denied:
                return [denied]
            self._saved = c.copy()
            return [SaveParametersReply(True)]
        if isinstance(msg, Reboot):
            denied = self._need(session, method=True)
            if denied:
                return [denied]
            self.reboot_requested = True
            return [RebootReply()]
        if isinstance(msg, SetHostDialect):
            denied = self._need(session, method=False)
            if denied:
                return [denied]
            if msg.dialect not in (0, 1):
                return [ErrorReply(SFA_OUT_OF_RANGE)]
            self.host_dialect = msg.dialect
            return [SetHostDialectReply()]
        if isinstance(msg, ReadDeviceState):
            now = self.clock.now_us() // 1_000_000
            hms = f"{now // 3600 % 24:02d}:{now // 60 % 60:02d}:{now % 60:02d}"
            return [DeviceState(self.device_state(), False, hms, f"{1 + now // 86400:02d}.01.1970")]
        if isinstance(msg, ReadDeviceReady):
            return [DeviceReady(0 if self.busy() else 1)]
        if isinstance(msg, ReadDeviceIdent):
            return [DeviceIdent(self.device_name, self.device_version)]
        if isinstance(msg, ReadSerialNumber):
            return [SerialNumber(f"{self.serial_number:08d}")]
        if isinstance(msg, ReadFirmwareVersion):
            return [FirmwareVersion(self.firmware_version)]
        if isinstance(msg, ReadLocationName):
            return [LocationName(self.location_name)]
        if isinstance(msg, ReadOperatingHours):
            return [OperatingHours(self.clock.now_us() // 360_000_000)]
        if isinstance(msg, ReadPowerOnCount):
            return [PowerOnCount(self.power_on_count)]
        if isinstance(msg, SubscribeScanData):
            session.subscribed = bool(msg.enable)
            return [SubscribeScanDataReply(bool(msg.enable))]
        if isinstance(msg, RawTelegram) and msg.kind == "sEN" and msg.name in QUIET_EVENTS:
            # Field-evaluation and I/O events exist on an LMS1xx; nothing in the simulation ever
            # changes a field or an input, so a subscription is accepted and stays silent.
            return [RawTelegram("sEA", msg.name, msg.params)]
        return [self._unknown(msg)]

    def _unknown(self, msg: Message) -> ErrorReply:
        kind = msg.kind
        if kind in ("sRN", "sWN", "sRI", "sWI"):
            return ErrorReply(SFA_UNKNOWN_VARIABLE)
        if kind == "sMN":
            return ErrorReply(SFA_UNKNOWN_METHOD)
        if kind == "sEN":
            return ErrorReply(SFA_UNKNOWN_EVENT)
        return ErrorReply(SFA_UNKNOWN_COLA_COMMAND)

    def _restart_epoch(self, measure_start: bool = False) -> None:
        """Scan timing changed: the next scan starts now, its counter continues."""
        now = self.clock.now_us()
        nxt = max(self.latest_complete_index(now) + 1, self._virtual_next, self.epoch_index)
        start = max(now, self._busy_until_us)
        self._start_epoch(start, nxt)
        if not measure_start:
            self.measure_start_index = -(1 << 40)  # no start-up status after a reconfiguration
        self._virtual_next = nxt

    def _set_scan_config(self, msg: SetScanConfig) -> SetScanConfigReply:
        c = self.config
        freq_ok = msg.scan_frequency in (2500, 5000)
        res_ok = msg.angular_resolution in (2500, 5000)
        if freq_ok and res_ok and (msg.scan_frequency, msg.angular_resolution) not in ALLOWED_SCAN_CONFIGS:
            res_ok = False
        status = 0
        if not freq_ok and not res_ok:
            status = 3
        elif not freq_ok:
            status = 1
        elif not res_ok:
            status = 2
        elif not (FIELD_START <= msg.start_angle < msg.stop_angle <= FIELD_STOP):
            status = 4
        elif msg.sectors != 1:
            status = 5
        if status == 0:
            c.scan_frequency, c.angular_resolution = msg.scan_frequency, msg.angular_resolution
            c.start_angle, c.stop_angle = msg.start_angle, msg.stop_angle
            c.out_start, c.out_stop = max(c.out_start, c.start_angle), min(c.out_stop, c.stop_angle)
            if c.out_start >= c.out_stop:
                c.out_start, c.out_stop = c.start_angle, c.stop_angle
            self._busy_until_us = self.clock.now_us() + round(self.reconfigure_busy_s * 1e6)
            self._restart_epoch()
        return SetScanConfigReply(status, c.scan_frequency, 1, c.angular_resolution, c.start_angle, c.stop_angle)

    def reboot(self) -> None:
        """Power cycle: sessions end, the saved configuration returns, counters restart."""
        with self.lock:
            self.reboot_requested = False
            self.power_on_count += 1
            for s in self.sessions:
                s.access_level = 0
                s.subscribed = False
            self._virtual_next = 0
            self._reset_volatile()
            self.changed.notify_all()
