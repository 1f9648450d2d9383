"""Typed CoLa telegrams (requests and replies) for the LMS1xx, in both dialects.

Every telegram is a frozen dataclass with ``encode(dialect) -> bytes`` (the unframed payload) and is
recovered by :func:`decode_payload`, which dispatches on the command type (``sRN``, ``sRA``, ``sWN``,
``sWA``, ``sMN``, ``sMA``, ``sAN``, ``sEN``, ``sEA``, ``sSN``, ``sFA``) and the name. A telegram with
a valid command type but a name this module does not model (``sSN LFErec``, ``sRA field000``...)
decodes to :class:`RawTelegram`, which keeps the parameters as bytes, so a driver can skip it.

Numeric fields keep the device's units (1/100 Hz, 1/10000 deg); properties give SI/degree views.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass, fields
from enum import IntEnum
from typing import Any, ClassVar, TypeVar, dataclass_transform

from drivers.lms100._values import (
    BOOL,
    I32,
    PAIR02,
    STR,
    U8,
    U16,
    U32,
    AsciiReader,
    AsciiWriter,
    BinReader,
    BinWriter,
    Field,
    Style,
)
from drivers.lms100.errors import DeviceErrorReply, TelegramError, sfa_message
from drivers.lms100.framing import Dialect
from drivers.lms100.scan import Scan, decode_scan, encode_scan

REQUEST_KINDS = frozenset({"sRN", "sWN", "sMN", "sEN", "sRI", "sWI"})
REPLY_KINDS = frozenset({"sRA", "sWA", "sAN", "sMA", "sEA", "sSN", "sFA"})
_REPLY_OF = {"sRN": "sRA", "sWN": "sWA", "sMN": "sAN", "sEN": "sEA", "sRI": "sRA", "sWI": "sWA"}
_NAME_RE = re.compile(rb"[A-Za-z0-9_]{1,64}\Z")

_REGISTRY: dict[tuple[str, str], type[Message]] = {}
FamilyDecoder = Callable[[str, bytes, int, "Dialect"], "Message"]
"""Decodes a telegram of a name family: ``(name, payload, parameter offset, dialect) -> Message``."""
_FAMILIES: list[tuple[str, re.Pattern[str], FamilyDecoder]] = []


class AccessLevel(IntEnum):
    """SetAccessMode user levels of the LMS1xx."""

    MAINTENANCE = 2
    AUTHORIZED_CLIENT = 3
    SERVICE = 4


PASSWORD_HASHES: dict[AccessLevel, int] = {
    AccessLevel.MAINTENANCE: 0xB21ACE26,  # "main"
    AccessLevel.AUTHORIZED_CLIENT: 0xF4724744,  # "client"
    AccessLevel.SERVICE: 0x81BE23AA,  # "servicelevel"
}
"""Factory-default password hashes per level, as SetAccessMode sends them."""

SCAN_CONFIG_STATUS: dict[int, str] = {
    0: "ok",
    1: "frequency not allowed",
    2: "angular resolution not allowed",
    3: "frequency and angular resolution not allowed",
    4: "scan area not allowed",
    5: "other error",
}
"""Status byte of the ``sAN mLMPsetscancfg`` reply."""

DEVICE_STATES: dict[int, str] = {
    0: "undefined",
    1: "initialisation",
    2: "configuration",
    3: "idle",
    4: "rotating",
    5: "in preparation",
    6: "ready",
    7: "measuring",
}
"""STlms device status."""


@dataclass(frozen=True)
class Message:
    """Base of all telegrams. Subclasses set ``KIND``, ``NAME`` and ``FIELDS`` (name, layout) in order."""

    KIND: ClassVar[str] = ""
    NAME: ClassVar[str] = ""
    FIELDS: ClassVar[tuple[tuple[str, Field], ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.KIND and cls.NAME:
            key = (cls.KIND, cls.NAME)
            if key in _REGISTRY:
                raise TypeError(f"two message classes for {key}")
            _REGISTRY[key] = cls

    @property
    def kind(self) -> str:
        return self.KIND

    @property
    def name(self) -> str:
        return self.NAME

    @property
    def is_request(self) -> bool:
        return self.kind in REQUEST_KINDS

    def _head(self) -> bytes:
        return f"{self.kind} {self.name}".encode("ascii")

    def encode_params(self, dialect: Dialect) -> bytes:
        w: BinWriter | AsciiWriter = BinWriter() if dialect is Dialect.B else AsciiWriter()
        for name, f in self.FIELDS:
            w.put(f, getattr(self, name))
        return w.getvalue()

    def encode(self, dialect: Dialect) -> bytes:
        """The unframed payload in ``dialect``."""
        dialect = Dialect(dialect)
        params = self.encode_params(dialect)
        if params:
            return self._head() + b" " + params
        if dialect is Dialect.B and self.kind in REPLY_KINDS:
            return self._head() + b" "  # devices keep the space on parameterless replies
        return self._head()

    @classmethod
    def decode_params(cls, buf: bytes, pos: int, dialect: Dialect) -> Message:
        r: BinReader | AsciiReader = BinReader(buf, pos) if dialect is Dialect.B else AsciiReader(buf, pos)
        values = [r.get(f) for _, f in cls.FIELDS]
        r.expect_end("parameters")
        return cls(*values)


_C = TypeVar("_C", bound="Message")


@dataclass_transform(frozen_default=True)
def _msg(kind: str, name: str, *layout: tuple[str, Field]) -> Callable[[type[_C]], type[_C]]:
    """Class decorator: make a frozen dataclass, set KIND/NAME/FIELDS and register it for decoding."""

    def wrap(cls: type[_C]) -> type[_C]:
        dc = dataclass(frozen=True)(cls)
        dc.KIND, dc.NAME, dc.FIELDS = kind, name, layout
        key = (kind, name)
        if key in _REGISTRY:
            raise TypeError(f"two message classes for {key}")
        _REGISTRY[key] = dc
        names = tuple(f.name for f in fields(dc))
        if names != tuple(n for n, _ in layout):
            raise TypeError(f"{cls.__name__}: dataclass fields {names} differ from the layout")
        return dc

    return wrap


T = TypeVar("T", bound=Message)

# ---------------------------------------------------------------------------------------------
# log in


@_msg("sMN", "SetAccessMode", ("level", Field("int", 1, True, "02X")), ("password_hash", U32))
class SetAccessMode(Message):
    """Log in: ``sMN SetAccessMode 03 F4724744``. Level 3 with the default hash by default."""

    level: int = AccessLevel.AUTHORIZED_CLIENT
    # a secret: left out of repr, so a logged request (the simulator logs what it turns down) never shows it
    password_hash: int = dataclasses.field(default=PASSWORD_HASHES[AccessLevel.AUTHORIZED_CLIENT], repr=False)

    @classmethod
    def default(cls, level: AccessLevel = AccessLevel.AUTHORIZED_CLIENT) -> SetAccessMode:
        return cls(int(level), PASSWORD_HASHES[level])


@_msg("sAN", "SetAccessMode", ("success", BOOL))
class SetAccessModeReply(Message):
    success: bool


# ---------------------------------------------------------------------------------------------
# scan configuration


class _ScanCfg:
    scan_frequency: int
    angular_resolution: int
    start_angle: int
    stop_angle: int

    @property
    def scan_frequency_hz(self) -> float:
        return self.scan_frequency / 100.0

    @property
    def angular_resolution_deg(self) -> float:
        return self.angular_resolution / 10000.0

    @property
    def start_angle_deg(self) -> float:
        return self.start_angle / 10000.0

    @property
    def stop_angle_deg(self) -> float:
        return self.stop_angle / 10000.0


_SCANCFG = (
    ("scan_frequency", U32),
    ("sectors", U16),
    ("angular_resolution", U32),
    ("start_angle", I32),
    ("stop_angle", I32),
)
_DEC: Style = "+d"
_SCANCFG_DEC = tuple((n, Field(f.kind, f.size, f.signed, _DEC)) for n, f in _SCANCFG)


@_msg("sRN", "LMPscancfg")
class ReadScanConfig(Message):
    pass


@_msg("sRA", "LMPscancfg", *_SCANCFG)
class ScanConfig(_ScanCfg, Message):
    """``sRA LMPscancfg``: frequency 1/100 Hz, sectors, resolution and angles 1/10000 deg."""

    scan_frequency: int
    sectors: int
    angular_resolution: int
    start_angle: int
    stop_angle: int


@_msg("sMN", "mLMPsetscancfg", *_SCANCFG_DEC)
class SetScanConfig(_ScanCfg, Message):
    """``sMN mLMPsetscancfg +5000 +1 +5000 -450000 +2250000`` (decimal with sign, as SICK's examples)."""

    scan_frequency: int = 5000
    sectors: int = 1
    angular_resolution: int = 5000
    start_angle: int = -450000
    stop_angle: int = 2250000

    @classmethod
    def from_hz_deg(
        cls, frequency_hz: float, resolution_deg: float, start_deg: float = -45.0, stop_deg: float = 225.0
    ) -> SetScanConfig:
        return cls(
            round(frequency_hz * 100),
            1,
            round(resolution_deg * 10000),
            round(start_deg * 10000),
            round(stop_deg * 10000),
        )


@_msg("sAN", "mLMPsetscancfg", ("status", U8), *_SCANCFG)
class SetScanConfigReply(_ScanCfg, Message):
    """Status (see :data:`SCAN_CONFIG_STATUS`) and the configuration actually applied."""

    status: int
    scan_frequency: int
    sectors: int
    angular_resolution: int
    start_angle: int
    stop_angle: int

    @property
    def ok(self) -> bool:
        return self.status == 0

    @property
    def status_text(self) -> str:
        return SCAN_CONFIG_STATUS.get(self.status, f"unknown status {self.status}")


_SCANDATACFG = (
    ("output_channel", PAIR02),
    ("remission", BOOL),
    ("resolution", U8),
    ("unit", U8),
    ("encoder", PAIR02),
    ("position", BOOL),
    ("device_name", BOOL),
    ("comment", BOOL),
    ("time", BOOL),
    ("output_rate", Field("int", 2, False, _DEC)),
)


class _ScanDataCfgFields:
    output_channel: tuple[int, int]
    remission: bool
    resolution: int
    unit: int
    encoder: tuple[int, int]
    position: bool
    device_name: bool
    comment: bool
    time: bool
    output_rate: int


@_msg("sWN", "LMDscandatacfg", *_SCANDATACFG)
class WriteScanDataConfig(_ScanDataCfgFields, Message):
    """What each LMDscandata carries: echo channel(s), RSSI (8 or 16 bit), blocks, output rate."""

    output_channel: tuple[int, int] = (1, 0)
    remission: bool = False
    resolution: int = 1
    unit: int = 0
    encoder: tuple[int, int] = (0, 0)
    position: bool = False
    device_name: bool = False
    comment: bool = False
    time: bool = False
    output_rate: int = 1


@_msg("sWA", "LMDscandatacfg")
class WriteScanDataConfigReply(Message):
    pass


@_msg("sRN", "LMDscandatacfg")
class ReadScanDataConfig(Message):
    pass


_SCANDATACFG_HEX = tuple((n, Field(f.kind, f.size, f.signed, "X")) for n, f in _SCANDATACFG)


@_msg("sRA", "LMDscandatacfg", *_SCANDATACFG_HEX)
class ScanDataConfig(_ScanDataCfgFields, Message):
    output_channel: tuple[int, int]
    remission: bool
    resolution: int
    unit: int
    encoder: tuple[int, int]
    position: bool
    device_name: bool
    comment: bool
    time: bool
    output_rate: int


_RANGE = (("sectors", U16), ("angular_resolution", U32), ("start_angle", I32), ("stop_angle", I32))


@_msg("sRN", "LMPoutputRange")
class ReadOutputRange(Message):
    pass


@_msg("sRA", "LMPoutputRange", *_RANGE)
class OutputRange(Message):
    sectors: int
    angular_resolution: int
    start_angle: int
    stop_angle: int


@_msg("sWN", "LMPoutputRange", *_RANGE)
class WriteOutputRange(Message):
    sectors: int = 1
    angular_resolution: int = 5000
    start_angle: int = -450000
    stop_angle: int = 2250000


@_msg("sWA", "LMPoutputRange")
class WriteOutputRangeReply(Message):
    pass


# ---------------------------------------------------------------------------------------------
# measurement and run level


@_msg("sMN", "LMCstartmeas")
class StartMeasurement(Message):
    pass


@_msg("sAN", "LMCstartmeas", ("status", U8))
class StartMeasurementReply(Message):
    status: int
    """0 ok, 1 not allowed."""


@_msg("sMN", "LMCstopmeas")
class StopMeasurement(Message):
    pass


@_msg("sAN", "LMCstopmeas", ("status", U8))
class StopMeasurementReply(Message):
    status: int


@_msg("sMN", "Run")
class Run(Message):
    pass


@_msg("sAN", "Run", ("success", BOOL))
class RunReply(Message):
    success: bool


@_msg("sMN", "mEEwriteall")
class SaveParameters(Message):
    pass


@_msg("sAN", "mEEwriteall", ("success", BOOL))
class SaveParametersReply(Message):
    success: bool


@_msg("sMN", "mSCreboot")
class Reboot(Message):
    pass


@_msg("sAN", "mSCreboot")
class RebootReply(Message):
    pass


@_msg("sWN", "EIHstCola", ("dialect", U8))
class SetHostDialect(Message):
    dialect: int
    """0 = CoLa A, 1 = CoLa B."""


@_msg("sWA", "EIHstCola")
class SetHostDialectReply(Message):
    pass


# ---------------------------------------------------------------------------------------------
# state and identity


@_msg("sRN", "STlms")
class ReadDeviceState(Message):
    pass


@_msg(
    "sRA",
    "STlms",
    ("status", U16),
    ("temperature_out_of_range", BOOL),
    ("time", STR),
    ("date", STR),
    ("led1", U16),
    ("led2", U16),
    ("led3", U16),
)
class DeviceState(Message):
    """``sRA STlms 7 0 8 00:34:19 A 01.01.1970 0 0 0``; status 7 = measuring (see :data:`DEVICE_STATES`)."""

    status: int
    temperature_out_of_range: bool
    time: str
    date: str
    led1: int = 0
    led2: int = 0
    led3: int = 0

    @property
    def status_text(self) -> str:
        return DEVICE_STATES.get(self.status, f"unknown state {self.status}")

    @property
    def measuring(self) -> bool:
        return self.status == 7


@_msg("sRN", "SCdevicestate")
class ReadDeviceReady(Message):
    pass


@_msg("sRA", "SCdevicestate", ("state", U8))
class DeviceReady(Message):
    state: int
    """0 busy, 1 ready, 2 error."""


@_msg("sRN", "DeviceIdent")
class ReadDeviceIdent(Message):
    pass


@_msg("sRA", "DeviceIdent", ("device_name", STR), ("version", STR))
class DeviceIdent(Message):
    device_name: str
    version: str


@_msg("sRN", "SerialNumber")
class ReadSerialNumber(Message):
    pass


@_msg("sRA", "SerialNumber", ("serial", STR))
class SerialNumber(Message):
    serial: str


@_msg("sRN", "FirmwareVersion")
class ReadFirmwareVersion(Message):
    pass


@_msg("sRA", "FirmwareVersion", ("version", STR))
class FirmwareVersion(Message):
    version: str


@_msg("sRN", "LocationName")
class ReadLocationName(Message):
    pass


@_msg("sRA", "LocationName", ("location", STR))
class LocationName(Message):
    location: str


@_msg("sRN", "ODoprh")
class ReadOperatingHours(Message):
    pass


@_msg("sRA", "ODoprh", ("tenth_hours", U32))
class OperatingHours(Message):
    tenth_hours: int


@_msg("sRN", "ODpwrc")
class ReadPowerOnCount(Message):
    pass


@_msg("sRA", "ODpwrc", ("count", U32))
class PowerOnCount(Message):
    count: int


# ---------------------------------------------------------------------------------------------
# scan data


@_msg("sRN", "LMDscandata")
class PollScan(Message):
    """Ask for the last scan once (``sRN LMDscandata``); the answer is :class:`ScanDataReply`."""


@_msg("sEN", "LMDscandata", ("enable", BOOL))
class SubscribeScanData(Message):
    """``sEN LMDscandata 1`` starts the scan stream, ``0`` stops it."""

    enable: bool = True


@_msg("sEA", "LMDscandata", ("enable", BOOL))
class SubscribeScanDataReply(Message):
    enable: bool


@dataclass(frozen=True)
class LMDScanData(Message):
    """A telegram carrying one :class:`Scan` (``sRA`` poll answer or ``sSN`` event)."""

    scan: Scan

    def encode_params(self, dialect: Dialect) -> bytes:
        return encode_scan(self.scan, dialect)

    @classmethod
    def decode_params(cls, buf: bytes, pos: int, dialect: Dialect) -> Message:
        return cls(decode_scan(buf, pos, dialect))


@dataclass(frozen=True)
class ScanDataReply(LMDScanData):
    KIND: ClassVar[str] = "sRA"
    NAME: ClassVar[str] = "LMDscandata"


@dataclass(frozen=True)
class ScanDataEvent(LMDScanData):
    KIND: ClassVar[str] = "sSN"
    NAME: ClassVar[str] = "LMDscandata"


# ---------------------------------------------------------------------------------------------
# errors and everything else


@dataclass(frozen=True)
class ErrorReply(Message):
    """``sFA <code>``: CoLa A ``sFA 3``; CoLa B ``sFA`` + uint16 code with no space."""

    code: int

    KIND: ClassVar[str] = "sFA"

    @property
    def name(self) -> str:
        return ""

    @property
    def message(self) -> str:
        return sfa_message(self.code)

    def to_exception(self, request: str | None = None) -> DeviceErrorReply:
        return DeviceErrorReply(self.code, request)

    def encode(self, dialect: Dialect) -> bytes:
        dialect = Dialect(dialect)
        if not 0 <= self.code <= 0xFFFF:
            raise TelegramError(f"sFA code {self.code} does not fit uint16")
        if dialect is Dialect.B:
            return b"sFA" + self.code.to_bytes(2, "big")
        return b"sFA %X" % self.code


@dataclass(frozen=True)
class RawTelegram(Message):
    """A telegram whose name this codec does not model; ``params`` are the raw parameter bytes.

    ``params`` is None when nothing follows the name, ``b""`` when only a space follows it.
    """

    command: str
    telegram_name: str
    params: bytes | None = None

    @property
    def kind(self) -> str:
        return self.command

    @property
    def name(self) -> str:
        return self.telegram_name

    def encode(self, dialect: Dialect) -> bytes:
        dialect = Dialect(dialect)
        if self.command.encode("ascii", "replace") not in _KIND_BYTES or self.command == "sFA":
            raise TelegramError(f"unknown CoLa command type {self.command!r}")
        if not _NAME_RE.match(self.telegram_name.encode("latin-1", "replace")):
            raise TelegramError(f"bad telegram name {self.telegram_name!r}")
        head = self._head()
        if self.params is None:
            return head
        if dialect is Dialect.A and (b"\x02" in self.params or b"\x03" in self.params):
            raise TelegramError("CoLa A parameters cannot contain STX/ETX")
        return head + b" " + self.params


_KIND_BYTES = frozenset(k.encode() for k in REQUEST_KINDS | REPLY_KINDS)


def decode_payload(payload: bytes, dialect: Dialect) -> Message:
    """Decode one unframed payload into its message (:class:`RawTelegram` for names not modelled).

    Raises :class:`TelegramError` for an unknown command type or unparseable parameters.
    """
    dialect = Dialect(dialect)
    payload = bytes(payload)
    kind_b = payload[:3]
    if kind_b not in _KIND_BYTES:
        raise TelegramError(f"unknown CoLa command type {kind_b!r}")
    kind = kind_b.decode("ascii")
    if kind == "sFA":
        return _decode_sfa(payload, dialect)
    if len(payload) < 5 or payload[3] != 0x20:
        raise TelegramError(f"{kind} must be followed by a space and a name: {payload[:40]!r}")
    sp = payload.find(b" ", 4)
    name_end = len(payload) if sp < 0 else sp
    name_b = payload[4:name_end]
    if not _NAME_RE.match(name_b):
        raise TelegramError(f"bad telegram name {name_b[:64]!r}")
    name = name_b.decode("ascii")
    pos = min(name_end + 1, len(payload))
    cls = _REGISTRY.get((kind, name))
    family = None if cls is not None else _family_decoder(kind, name)
    if cls is None and family is None:
        return RawTelegram(kind, name, None if sp < 0 else payload[pos:])
    try:
        if family is not None:
            return family(name, payload, pos, dialect)
        assert cls is not None
        return cls.decode_params(payload, pos, dialect)
    except TelegramError as exc:
        raise TelegramError(f"{kind} {name}: {exc}") from None
    except (ValueError, TypeError, IndexError, OverflowError) as exc:  # defensive: never leak other errors
        raise TelegramError(f"{kind} {name}: cannot decode parameters: {exc}") from None


def _decode_sfa(payload: bytes, dialect: Dialect) -> ErrorReply:
    if dialect is Dialect.B:
        if len(payload) != 5:
            raise TelegramError(f"CoLa B sFA must carry exactly a uint16 code, got {payload!r}")
        return ErrorReply(int.from_bytes(payload[3:5], "big"))
    r = AsciiReader(payload, 4)
    if len(payload) < 5 or payload[3] != 0x20:
        raise TelegramError(f"CoLa A sFA must be followed by a space and a hex code, got {payload!r}")
    code = r.num(2)
    r.expect_end("sFA")
    return ErrorReply(code)


def reply_kind(request: Message) -> str:
    """The command type of the reply to ``request`` (``sRN`` -> ``sRA``...)."""
    try:
        return _REPLY_OF[request.kind]
    except KeyError:
        raise TelegramError(f"{request.kind} is not a request") from None


def is_reply_to(reply: Message, request: Message) -> bool:
    """True if ``reply`` answers ``request``: same name and the matching type, or any ``sFA``.

    An ``sMA`` (method accepted, result later) also counts for an ``sMN``.
    """
    if isinstance(reply, ErrorReply):
        return True
    if reply.name != request.name:
        return False
    want = reply_kind(request)
    return reply.kind == want or (request.kind == "sMN" and reply.kind == "sMA")


def message_classes() -> dict[tuple[str, str], type[Message]]:
    """All modelled telegrams with a fixed name, keyed by (command type, name) (see also :func:`is_modelled`)."""
    return dict(_REGISTRY)


def register_family(kind: str, pattern: str, decoder: FamilyDecoder) -> None:
    """Model the telegrams ``kind`` + any name matching ``pattern`` (``field000``...); ``decoder`` builds them."""
    _FAMILIES.append((kind, re.compile(pattern), decoder))


def _family_decoder(kind: str, name: str) -> FamilyDecoder | None:
    for k, pattern, decoder in _FAMILIES:
        if k == kind and pattern.fullmatch(name):
            return decoder
    return None


def is_modelled(kind: str, name: str) -> bool:
    """True if ``kind name`` decodes to a typed message (a fixed name or a registered family)."""
    return (kind, name) in _REGISTRY or _family_decoder(kind, name) is not None


def cast(msg: Message, cls: type[T]) -> T:
    """``msg`` as ``cls`` or :class:`TelegramError` (an ``sFA`` becomes :class:`DeviceErrorReply`)."""
    if isinstance(msg, cls):
        return msg
    if isinstance(msg, ErrorReply):
        raise msg.to_exception(f"expected {cls.__name__}")
    raise TelegramError(f"expected {cls.__name__}, got {msg.kind} {msg.name}")
