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
  out-of-range values ``sFA 4``; every rejected request is logged (logger ``sim.scanner.device``,
  WARNING) with the telegram and the reason. Requests are handled in :mod:`sim.scanner.requests`.
* What SICK's driver reads at start-up answers as the LMS111 recording does: field definitions,
  ``LIDinputstate``, ``sSN LIDoutputstate`` at subscription and on changes (:mod:`sim.scanner.fieldio`),
  ``SCdevicestate`` 0 while a connection is logged in.
* The output range (``LMPoutputRange``) is kept as written; scans carry the beams from the grid point
  nearest its start to the grid point nearest its stop (ties outward), as the LMS111 sends 541 beams
  from -45 deg for -44.9997..224.9997 deg.

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
import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from drivers.errors import DriverError
from drivers.lms100 import (
    Channel,
    ErrorReply,
    FieldGeometry,
    InputStateEvent,
    Message,
    OutputStateEvent,
    PollScan,
    Scan,
    ScanDataReply,
    WriteScanDataConfig,
    make_channel,
)
from lrms.kinematics import RigCalibration
from sim.scanner.fieldio import DEFAULT_FIELDS, DeviceIO, scan_time_of
from sim.scanner.requests import (
    ALLOWED_SCAN_CONFIGS,
    FIELD_START,
    FIELD_STOP,
    SFA_UNKNOWN_ERROR,
    dispatch,
)
from sim.scene import BeamSamples, Scene, Sensor, SensorModel, cast_beams, get_scene

log = logging.getLogger(__name__)

__all__ = ["ALLOWED_SCAN_CONFIGS", "DeviceClock", "Session", "SimulatedLMS100", "SimulatorError"]

#: The scan is handed to the interface this long after its last beam (us).
TRANSMIT_DELAY_US = 1000
U32 = 1 << 32

MotorAngleFn = Callable[[np.ndarray], np.ndarray]
EventListener = Callable[["Session", Message], None]


def scan_channels(
    samples: BeamSamples, data: WriteScanDataConfig, start_deg: float, step_deg: float
) -> tuple[list[Channel], list[Channel]]:
    """The 16-bit and 8-bit channels of one scan as ``LMDscandatacfg`` asks for them.

    Output channel (first byte, a bit mask): 1 first echo (DIST1), 2 second echo (DIST2), 3 both;
    with ``remission`` the matching RSSI1 / RSSI2 follow, as 16-bit channels (resolution 1) or 8-bit
    ones (resolution 0, clipped at 255). A thin-beam sensor has no second echo: DIST2 / RSSI2 are 0.
    """
    mask = data.output_channel[0]
    zeros = np.zeros_like(samples.ranges)
    echoes = []
    if mask & 1:
        echoes.append(("1", samples.ranges, samples.rssi))
    if mask & 2:
        r2 = samples.ranges2 if samples.ranges2 is not None else zeros
        s2 = samples.rssi2 if samples.rssi2 is not None else zeros
        echoes.append(("2", r2, s2))
    channels_16 = []
    for n, ranges, _ in echoes:
        mm = np.clip(np.rint(ranges * 1000.0), 0, 65535).astype(np.uint16)
        channels_16.append(make_channel(f"DIST{n}", mm, start_deg, step_deg))
    channels_8 = []
    if data.remission:
        for n, _, rssi in echoes:
            if data.resolution == 1:
                values16 = np.clip(np.rint(rssi), 0, 65535).astype(np.uint16)
                channels_16.append(make_channel(f"RSSI{n}", values16, start_deg, step_deg))
            else:
                values8 = np.clip(np.rint(rssi), 0, 255).astype(np.uint8)
                channels_8.append(make_channel(f"RSSI{n}", values8, start_deg, step_deg))
    return channels_16, channels_8


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
    events: set[str] = field(default_factory=set)
    """Subscribed events besides LMDscandata (``LIDoutputstate``, ``LIDinputstate``, ``LFErec``)."""


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
    ``fields``: the field definitions ``sRN fieldNNN`` answers (index = position; ``None``: the
    one-byte "no definition" answer; beyond the end: ``sFA 3``), default 10 unconfigured + 20 empty.
    """

    def __init__(
        self,
        scene: Scene | str = "seed003",
        calibration: RigCalibration | None = None,
        motor_angle_at: MotorAngleFn | None = None,
        sensor: Sensor | None = None,
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
        fields: Sequence[FieldGeometry | None] = DEFAULT_FIELDS,
    ) -> None:
        self.scene = get_scene(scene) if isinstance(scene, str) else scene
        if not isinstance(self.scene, Scene):
            raise SimulatorError(f"scene must be a Scene or a scene name, got {scene!r}")
        self.calibration = calibration if calibration is not None else RigCalibration()
        self.motor_angle_at: MotorAngleFn = motor_angle_at if motor_angle_at is not None else _constant_zero
        self.sensor: Sensor = sensor if sensor is not None else SensorModel()
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
        try:
            self.io = DeviceIO(fields)
        except ValueError as exc:
            raise SimulatorError(str(exc)) from None
        self._event_listeners: list[EventListener] = []
        self._saved = _Config()
        self._reset_volatile()

    # ------------------------------------------------------------------ state
    def _reset_volatile(self) -> None:
        self.config = self._saved.copy()
        self.measuring = True
        self.config_mode = False
        self.config_owner: Session | None = None
        self.telegram_counter = 0
        self._busy_until_us = -1
        self.scan_cache: OrderedDict[int, Scan] = OrderedDict()
        self._last_sent: Scan | None = None
        self._start_epoch(self.clock.now_us(), 0)

    def _start_epoch(self, start_us: int, index: int) -> None:
        self.epoch_start_us = int(start_us)
        self.epoch_index = int(index)
        self.measure_start_index = int(index)
        self.scan_cache.clear()

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
        """Beam angles of the output range, 1/10000 deg.

        The beams lie on the scan's grid (``start_angle + k * resolution``); the output range's start
        and stop each go to the nearest grid beam, a tie to the outer one, within the scan area. The
        LMS111 recording fixes this for its case: written -449997..2249997 at 0.5 deg, it sends 541 beams
        from -450000 (rounding inward would give 539 from -445000); the LMS511's -50000..1850000 at
        0.1667 deg gives 1141 beams, its last (1850380) nearest to the stop. Neither recording tells
        "nearest" from "always outward"; nearest is our choice.
        """
        c = self.config
        res = c.angular_resolution
        lo = c.out_start - c.start_angle
        hi = c.out_stop - c.start_angle
        first = max(0, -((res - 2 * lo) // (2 * res)))  # ceil((2 lo - res) / 2 res): nearest, tie outward
        last = min((c.stop_angle - c.start_angle) // res, (2 * hi + res) // (2 * res))  # nearest, tie outward
        return c.start_angle + res * np.arange(first, last + 1, dtype=np.int64)

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
            if self.config_owner is session:  # its connection is gone: leave configuration mode
                self.config_mode = False
                self.config_owner = None
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
            cached = self.scan_cache.get(index)
            if cached is not None:
                return cached
            cfg = self.config.copy()
            t = self.timing(index)
            dev_raw = self.output_angles_raw()
            inc = self.time_increment_us
            meas_freq = self.measurement_frequency
            status = (1, 0) if index - self.measure_start_index < self.startup_status_scans else (0, 0)
            outputs = self.io.output_bits
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
        samples = cast_beams(
            self.scene, self.calibration, self.sensor, dev_rad, motor, rng, time_s=beam_times_s, motor_speed_rad_s=speed
        )
        start_deg, step_deg = float(dev_raw[0]) / 1e4, cfg.angular_resolution / 1e4
        channels_16, channels_8 = scan_channels(samples, cfg.data, start_deg, step_deg)
        time_info = scan_time_of(t.start_us) if cfg.data.time else None
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
            digital_outputs=(outputs, 0),
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
            self.scan_cache[index] = scan
            while len(self.scan_cache) > 8:
                self.scan_cache.popitem(last=False)
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
        """Replies to one decoded request (usually one message; ``sEN LIDoutputstate`` adds the state)."""
        if isinstance(msg, PollScan):
            reply = self.poll()
            if isinstance(reply, ErrorReply):
                self.log_rejection(
                    msg, reply, "no scan leaves the device (configuration mode, stopped or busy) and none was sent"
                )
            return [reply]
        with self.lock:
            replies, rejection = dispatch(self, session, msg)
            self.changed.notify_all()
        if rejection is not None:
            self.log_rejection(msg, rejection.reply, rejection.reason)
        return replies

    @staticmethod
    def log_rejection(request: Message | bytes, reply: Message, reason: str) -> None:
        """Log a turned-down request: the telegram (typed or raw bytes), the answer and why."""
        text = repr(request) if isinstance(request, Message) else f"undecodable telegram {request!r}"
        if len(text) > 300:
            text = text[:300] + "..."
        answer = reply.message if isinstance(reply, ErrorReply) else repr(reply)
        log.warning("simulated LMS100 rejected %s: %s; answered %s", text, reason, answer)

    def restart_epoch(self, measure_start: bool = False) -> None:
        """Scan timing changed: the next scan starts now, its counter continues. Call under the lock."""
        now = self.clock.now_us()
        nxt = max(self.latest_complete_index(now) + 1, self._virtual_next, self.epoch_index)
        start = max(now, self._busy_until_us)
        self._start_epoch(start, nxt)
        if not measure_start:
            self.measure_start_index = -(1 << 40)  # no start-up status after a reconfiguration
        self._virtual_next = nxt

    def start_busy(self) -> None:
        """After a scan reconfiguration: busy (no scans, SCdevicestate 0) for ``reconfigure_busy_s``."""
        self._busy_until_us = self.clock.now_us() + round(self.reconfigure_busy_s * 1e6)

    def save_config(self) -> None:
        """``mEEwriteall``: the current configuration survives a reboot."""
        self._saved = self.config.copy()

    # ------------------------------------------------------------------ digital I/O events
    def add_event_listener(self, listener: EventListener) -> None:
        """``listener(session, event)`` gets every I/O event for a subscribed session (the server sends it)."""
        with self.lock:
            self._event_listeners.append(listener)

    def remove_event_listener(self, listener: EventListener) -> None:
        with self.lock:
            if listener in self._event_listeners:
                self._event_listeners.remove(listener)

    def set_outputs(self, active: Sequence[bool]) -> None:
        """Switch the three outputs; a change sends ``sSN LIDoutputstate`` to its subscribers."""
        with self.lock:
            try:
                if not self.io.set_outputs(active):
                    return
            except ValueError as exc:
                raise SimulatorError(str(exc)) from None
            self.scan_cache.clear()  # the scans' digital-output byte changes
            event: OutputStateEvent | InputStateEvent = self.io.output_state(self.clock.now_us(), self.config.data.time)
            targets = [s for s in self.sessions if "LIDoutputstate" in s.events]
            listeners = list(self._event_listeners)
        self._notify(listeners, targets, event)

    def set_inputs(self, inputs: Sequence[int]) -> None:
        """Set the four input values; a change sends ``sSN LIDinputstate`` to its subscribers."""
        with self.lock:
            try:
                if not self.io.set_inputs(inputs, self.clock.now_us()):
                    return
            except ValueError as exc:
                raise SimulatorError(str(exc)) from None
            event: OutputStateEvent | InputStateEvent = self.io.input_state_event(self.config.data.time)
            targets = [s for s in self.sessions if "LIDinputstate" in s.events]
            listeners = list(self._event_listeners)
        self._notify(listeners, targets, event)

    @staticmethod
    def _notify(listeners: list[EventListener], targets: list[Session], event: Message) -> None:
        """Outside the lock: a listener may block on a socket."""
        for session in targets:
            for listener in listeners:
                listener(session, event)

    def reboot(self) -> None:
        """Power cycle: sessions end, the saved configuration returns, counters restart."""
        with self.lock:
            self.reboot_requested = False
            self.power_on_count += 1
            for s in self.sessions:
                s.access_level = 0
                s.subscribed = False
                s.events.clear()
            self._virtual_next = 0
            self._reset_volatile()
            self.changed.notify_all()
