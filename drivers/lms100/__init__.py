"""SICK LMS100 (LMS1xx family) CoLa A / CoLa B codec, sans-I/O.

Layers, each usable alone:

- :mod:`drivers.lms100.framing`: :func:`frame` wraps a payload; :class:`Framer` cuts a byte stream
  (any chunking) back into payloads, resynchronising after garbage.
- :mod:`drivers.lms100.messages`: one frozen dataclass per telegram (requests and replies) with
  ``encode(dialect)``; :func:`decode_payload` turns a payload back into a message.
- :mod:`drivers.lms100.scan`: :class:`Scan`, the fully decoded LMDscandata body with numpy channels.
- :mod:`drivers.lms100.protocol`: :class:`CoLaConnection`, h11-style: ``send(msg) -> bytes``,
  ``receive_data(bytes)``, ``next_message()``.

Example (client side; the socket is yours)::

    from drivers.lms100 import CoLaConnection, Dialect, SetAccessMode, SubscribeScanData, ScanDataEvent

    conn = CoLaConnection(Dialect.B, role="client")
    sock.sendall(conn.send(SetAccessMode()))          # level 3, default "client" password hash
    sock.sendall(conn.send(SubscribeScanData(True)))  # sEN LMDscandata 1
    while True:
        conn.receive_data(sock.recv(65536))
        while (msg := conn.next_message()) is not None:
            if isinstance(msg, ScanDataEvent):
                scan = msg.scan
                print(scan.scan_counter, scan.ranges_m.shape, scan.angles_rad[0], scan.rssi is None)

Errors: :class:`CoLaError` (a :class:`drivers.errors.DriverError`) with :class:`FramingError`,
:class:`TelegramError` and :class:`DeviceErrorReply` (from an ``sFA`` reply; ``.code``, ``.message``).
"""

from drivers.lms100.errors import SFA_ERRORS, CoLaError, DeviceErrorReply, FramingError, TelegramError, sfa_message
from drivers.lms100.framing import DEFAULT_MAX_PAYLOAD, Dialect, Framer, frame, xor_checksum
from drivers.lms100.messages import (
    DEVICE_STATES,
    PASSWORD_HASHES,
    SCAN_CONFIG_STATUS,
    AccessLevel,
    DeviceIdent,
    DeviceReady,
    DeviceState,
    ErrorReply,
    FirmwareVersion,
    LMDScanData,
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
    ScanConfig,
    ScanDataConfig,
    ScanDataEvent,
    ScanDataReply,
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
    cast,
    decode_payload,
    is_reply_to,
    message_classes,
    reply_kind,
)
from drivers.lms100.protocol import CoLaConnection
from drivers.lms100.scan import RAD_PER_UNIT, Channel, Encoder, Position, Scan, ScanEvent, ScanTime, make_channel

__all__ = [
    "DEFAULT_MAX_PAYLOAD",
    "DEVICE_STATES",
    "PASSWORD_HASHES",
    "RAD_PER_UNIT",
    "SCAN_CONFIG_STATUS",
    "SFA_ERRORS",
    "AccessLevel",
    "Channel",
    "CoLaConnection",
    "CoLaError",
    "DeviceErrorReply",
    "DeviceIdent",
    "DeviceReady",
    "DeviceState",
    "Dialect",
    "Encoder",
    "ErrorReply",
    "FirmwareVersion",
    "Framer",
    "FramingError",
    "LMDScanData",
    "LocationName",
    "Message",
    "OperatingHours",
    "OutputRange",
    "PollScan",
    "Position",
    "PowerOnCount",
    "RawTelegram",
    "ReadDeviceIdent",
    "ReadDeviceReady",
    "ReadDeviceState",
    "ReadFirmwareVersion",
    "ReadLocationName",
    "ReadOperatingHours",
    "ReadOutputRange",
    "ReadPowerOnCount",
    "ReadScanConfig",
    "ReadScanDataConfig",
    "ReadSerialNumber",
    "Reboot",
    "RebootReply",
    "Run",
    "RunReply",
    "SaveParameters",
    "SaveParametersReply",
    "Scan",
    "ScanConfig",
    "ScanDataConfig",
    "ScanDataEvent",
    "ScanDataReply",
    "ScanEvent",
    "ScanTime",
    "SerialNumber",
    "SetAccessMode",
    "SetAccessModeReply",
    "SetHostDialect",
    "SetHostDialectReply",
    "SetScanConfig",
    "SetScanConfigReply",
    "StartMeasurement",
    "StartMeasurementReply",
    "StopMeasurement",
    "StopMeasurementReply",
    "SubscribeScanData",
    "SubscribeScanDataReply",
    "TelegramError",
    "WriteOutputRange",
    "WriteOutputRangeReply",
    "WriteScanDataConfig",
    "WriteScanDataConfigReply",
    "cast",
    "decode_payload",
    "frame",
    "is_reply_to",
    "make_channel",
    "message_classes",
    "reply_kind",
    "sfa_message",
    "xor_checksum",
]
