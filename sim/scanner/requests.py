"""Request handling of the simulated LMS100: one decoded request in, its replies out.

:func:`dispatch` runs under the device's lock (``SimulatedLMS100.handle`` takes it). Every request the
device turns down gets a :class:`Rejection` with the reason, which ``handle`` logs (``sFA`` replies and
the method-level refusals ``sAN SetAccessMode 0`` / ``sAN mLMPsetscancfg`` status 1..5).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from drivers.lms100 import (
    PASSWORD_HASHES,
    AccessLevel,
    DeviceIdent,
    DeviceReady,
    DeviceState,
    ErrorReply,
    FieldDefinition,
    FirmwareVersion,
    LocationName,
    Message,
    OperatingHours,
    OutputRange,
    PowerOnCount,
    ReadDeviceIdent,
    ReadDeviceReady,
    ReadDeviceState,
    ReadFieldDefinition,
    ReadFirmwareVersion,
    ReadInputState,
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
    ScanConfig,
    ScanDataConfig,
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
    SubscribeFieldResults,
    SubscribeFieldResultsReply,
    SubscribeInputState,
    SubscribeInputStateReply,
    SubscribeOutputState,
    SubscribeOutputStateReply,
    SubscribeScanData,
    SubscribeScanDataReply,
    WriteOutputRange,
    WriteOutputRangeReply,
    WriteScanDataConfig,
    WriteScanDataConfigReply,
)

if TYPE_CHECKING:
    from sim.scanner.device import Session, SimulatedLMS100

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


@dataclass(frozen=True)
class Rejection:
    """Why a request was turned down (logged with the request)."""

    reply: Message
    reason: str


class _Reject(Exception):
    def __init__(self, reply: Message, reason: str) -> None:
        super().__init__(reason)
        self.reply = reply
        self.reason = reason


def _fail(code: int, reason: str) -> _Reject:
    return _Reject(ErrorReply(code), reason)


def _need_login(session: Session, method: bool) -> None:
    if session.access_level >= AccessLevel.AUTHORIZED_CLIENT:
        return
    what = "this method" if method else "writing this variable"
    raise _fail(
        SFA_METHOD_ACCESS_DENIED if method else SFA_WRITE_ACCESS_DENIED,
        f"{what} needs access level 3 (authorized client) or 4, the connection is at level {session.access_level}",
    )


def dispatch(dev: SimulatedLMS100, session: Session, msg: Message) -> tuple[list[Message], Rejection | None]:
    """Replies to ``msg`` and, if the device turned it down, why."""
    try:
        replies = _dispatch(dev, session, msg)
    except _Reject as r:
        return [r.reply], Rejection(r.reply, r.reason)
    first = replies[0]
    if isinstance(first, SetAccessModeReply) and not first.success:
        return replies, Rejection(first, "wrong access level or password hash")
    if isinstance(first, SetScanConfigReply) and not first.ok:
        return replies, Rejection(first, f"scan configuration refused: {first.status_text}")
    return replies, None


def _dispatch(dev: SimulatedLMS100, session: Session, msg: Message) -> list[Message]:
    c = dev.config
    if isinstance(msg, SetAccessMode):
        try:
            level = AccessLevel(msg.level)
        except ValueError:
            return [SetAccessModeReply(False)]
        if PASSWORD_HASHES[level] != msg.password_hash:
            return [SetAccessModeReply(False)]
        session.access_level = int(level)
        dev.config_mode = True
        dev.config_owner = session
        return [SetAccessModeReply(True)]
    if isinstance(msg, Run):
        session.access_level = 0
        dev.config_mode = False
        dev.config_owner = None
        return [RunReply(True)]
    if isinstance(msg, ReadScanConfig):
        return [ScanConfig(c.scan_frequency, 1, c.angular_resolution, c.start_angle, c.stop_angle)]
    if isinstance(msg, SetScanConfig):
        _need_login(session, method=True)
        return [_set_scan_config(dev, msg)]
    if isinstance(msg, ReadOutputRange):
        return [OutputRange(1, c.angular_resolution, c.out_start, c.out_stop)]
    if isinstance(msg, WriteOutputRange):
        _need_login(session, method=False)
        if msg.sectors != 1:
            raise _fail(SFA_OUT_OF_RANGE, f"one output sector only, got {msg.sectors}")
        if msg.angular_resolution != c.angular_resolution:
            raise _fail(
                SFA_OUT_OF_RANGE,
                f"output resolution {msg.angular_resolution} differs from the scan's {c.angular_resolution}",
            )
        if not c.start_angle <= msg.start_angle < msg.stop_angle <= c.stop_angle:
            raise _fail(
                SFA_OUT_OF_RANGE,
                f"output range {msg.start_angle}..{msg.stop_angle} is not an interval within the scan area "
                f"{c.start_angle}..{c.stop_angle} (1/10000 deg)",
            )
        c.out_start, c.out_stop = msg.start_angle, msg.stop_angle
        dev.restart_epoch()
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
        _need_login(session, method=False)
        problems = [
            text
            for bad, text in (
                (
                    msg.output_channel[0] not in (1, 2, 3) or msg.output_channel[1] != 0,
                    f"output channel {msg.output_channel} (1 first echo, 2 second echo, 3 both; second byte 0)",
                ),
                (msg.resolution not in (0, 1), f"RSSI resolution {msg.resolution} (0 or 1)"),
                (msg.unit != 0, f"unit {msg.unit} (only 0)"),
                (tuple(msg.encoder) != (0, 0), f"encoder {msg.encoder} (none)"),
                (msg.position, "position block (not offered)"),
                (not 1 <= msg.output_rate <= 50000, f"output rate {msg.output_rate} (1..50000)"),
            )
            if bad
        ]
        if problems:
            raise _fail(SFA_OUT_OF_RANGE, "LMDscandatacfg not supported: " + "; ".join(problems))
        c.data = msg
        dev.scan_cache.clear()
        return [WriteScanDataConfigReply()]
    if isinstance(msg, StartMeasurement):
        _need_login(session, method=True)
        if not dev.measuring:
            dev.measuring = True
            dev.restart_epoch(measure_start=True)
        return [StartMeasurementReply(0)]
    if isinstance(msg, StopMeasurement):
        _need_login(session, method=True)
        dev.measuring = False
        return [StopMeasurementReply(0)]
    if isinstance(msg, SaveParameters):
        _need_login(session, method=True)
        dev.save_config()
        return [SaveParametersReply(True)]
    if isinstance(msg, Reboot):
        _need_login(session, method=True)
        dev.reboot_requested = True
        return [RebootReply()]
    if isinstance(msg, SetHostDialect):
        _need_login(session, method=False)
        if msg.dialect not in (0, 1):
            raise _fail(SFA_OUT_OF_RANGE, f"host dialect must be 0 (CoLa A) or 1 (CoLa B), got {msg.dialect}")
        dev.host_dialect = msg.dialect
        return [SetHostDialectReply()]
    if isinstance(msg, ReadDeviceState):
        now = dev.clock.now_us() // 1_000_000
        hms = f"{now // 3600 % 24:02d}:{now // 60 % 60:02d}:{now % 60:02d}"
        return [DeviceState(dev.device_state(), False, hms, f"{1 + now // 86400:02d}.01.1970")]
    if isinstance(msg, ReadDeviceReady):
        # 0 (busy) while a connection is logged in (configuration mode), as the LMS111 answers, or
        # while busy after a scan reconfiguration; else 1
        return [DeviceReady(0 if dev.busy() or dev.config_mode else 1)]
    if isinstance(msg, ReadDeviceIdent):
        return [DeviceIdent(dev.device_name, dev.device_version)]
    if isinstance(msg, ReadSerialNumber):
        return [SerialNumber(f"{dev.serial_number:08d}")]
    if isinstance(msg, ReadFirmwareVersion):
        return [FirmwareVersion(dev.firmware_version)]
    if isinstance(msg, ReadLocationName):
        return [LocationName(dev.location_name)]
    if isinstance(msg, ReadOperatingHours):
        return [OperatingHours(dev.clock.now_us() // 360_000_000)]
    if isinstance(msg, ReadPowerOnCount):
        return [PowerOnCount(dev.power_on_count)]
    if isinstance(msg, ReadFieldDefinition):
        known, geometry = dev.io.field(msg.index)
        if not known:
            raise _fail(SFA_UNKNOWN_VARIABLE, f"the device has {len(dev.io.fields)} field definitions")
        return [FieldDefinition(msg.index, geometry)]
    if isinstance(msg, ReadInputState):
        return [dev.io.input_state(c.data.time)]
    if isinstance(msg, SubscribeScanData):
        session.subscribed = bool(msg.enable)
        return [SubscribeScanDataReply(bool(msg.enable))]
    if isinstance(msg, SubscribeOutputState):
        _subscribe(session, msg.name, msg.enable)
        if not msg.enable:
            return [SubscribeOutputStateReply(False)]
        # the LMS111 sends the current output state right after the subscription (then on changes)
        return [SubscribeOutputStateReply(True), dev.io.output_state(dev.clock.now_us(), c.data.time)]
    if isinstance(msg, SubscribeInputState):
        _subscribe(session, msg.name, msg.enable)
        return [SubscribeInputStateReply(msg.enable)]
    if isinstance(msg, SubscribeFieldResults):
        # accepted; nothing in the simulation evaluates fields, so no sSN LFErec ever comes
        _subscribe(session, msg.name, msg.enable)
        return [SubscribeFieldResultsReply(msg.enable)]
    raise _unknown(msg)


def _subscribe(session: Session, name: str, enable: bool) -> None:
    if enable:
        session.events.add(name)
    else:
        session.events.discard(name)


def _unknown(msg: Message) -> _Reject:
    kind = msg.kind
    if kind in ("sRN", "sWN", "sRI", "sWI"):
        return _fail(SFA_UNKNOWN_VARIABLE, f"variable {msg.name!r} is not simulated")
    if kind == "sMN":
        return _fail(SFA_UNKNOWN_METHOD, f"method {msg.name!r} is not simulated")
    if kind == "sEN":
        return _fail(SFA_UNKNOWN_EVENT, f"event {msg.name!r} is not simulated")
    return _fail(SFA_UNKNOWN_COLA_COMMAND, f"{kind} is not a request")


def _set_scan_config(dev: SimulatedLMS100, msg: SetScanConfig) -> SetScanConfigReply:
    c = dev.config
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
        dev.start_busy()
        dev.restart_epoch()
    return SetScanConfigReply(status, c.scan_frequency, 1, c.angular_resolution, c.start_angle, c.stop_angle)
