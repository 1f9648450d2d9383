"""The LMDscandata body: a typed :class:`Scan` with numpy channels, decoded and encoded in both dialects.

Layout (offsets of the CoLa B payload after ``sRA LMDscandata `` / ``sSN LMDscandata ``): version,
device number, serial number, device status (2 x uint8), telegram counter, scan counter, time since
start-up (us), time of transmission (us), digital inputs and outputs (2 x uint8 each), layer angle
(int16, 1/100 deg), scan frequency (1/100 Hz), measurement frequency (100 Hz), encoder block, the
16-bit channels, the 8-bit channels, then the optional position, name, comment, time-info and event
blocks, each behind a uint16 flag. Each channel carries its content name (``DIST1``, ``RSSI1``...),
scale factor and offset (REAL), start angle (int32, 1/10000 deg), angular step (uint16, 1/10000
deg) and its values.

Channel values are decoded without per-point Python loops: ``np.frombuffer`` for CoLa B and a
vectorised hex parser for CoLa A (and the reverse for encoding).
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.lms100._values import AsciiReader, AsciiWriter, encode_text
from drivers.lms100.errors import TelegramError
from drivers.lms100.framing import Dialect

RAD_PER_UNIT = math.pi / 180.0 / 10000.0
"""Radians per 1/10000 degree (the unit of SICK angles)."""

_HDR = struct.Struct(">HHIBBHHIIBBBBhIIH")  # 38 bytes: version .. number of encoders
_ENC = struct.Struct(">IH")
_CH = struct.Struct(">5sffiHH")  # content, scale, offset, start angle, step, count
_U16 = struct.Struct(">H")
_POS = struct.Struct(">ffffffBB")
_TIME = struct.Struct(">HBBBBBI")
_EVENT = struct.Struct(">4sIIi")

_HEX_LUT = np.full(256, -1, dtype=np.int32)
for _i, _c in enumerate(b"0123456789ABCDEF"):
    _HEX_LUT[_c] = _i
for _i, _c in enumerate(b"abcdef"):
    _HEX_LUT[_c] = 10 + _i
_HEX_CHARS = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)


@dataclass(frozen=True, eq=False)
class Channel:
    """One output channel of a scan.

    ``values`` are the raw device numbers (uint16 for 16-bit channels, uint8 for 8-bit ones);
    a distance in mm is ``values * scale + offset``.
    """

    name: str
    scale: float
    offset: float
    start_angle_rad: float
    step_rad: float
    values: npt.NDArray[Any]

    @property
    def start_angle_raw(self) -> int:
        """Start angle in the device's unit, 1/10000 deg."""
        return round(self.start_angle_rad / RAD_PER_UNIT)

    @property
    def step_raw(self) -> int:
        """Angular step in 1/10000 deg."""
        return round(self.step_rad / RAD_PER_UNIT)

    @property
    def angles_rad(self) -> npt.NDArray[np.float64]:
        """Beam angle of every value, in the device's frame (90 deg = straight ahead)."""
        return (self.start_angle_raw + self.step_raw * np.arange(len(self.values), dtype=np.float64)) * RAD_PER_UNIT

    def scaled(self) -> npt.NDArray[np.float64]:
        """``values * scale + offset`` as float64 (mm for DIST channels)."""
        out = self.values.astype(np.float64)
        if self.scale != 1.0:
            out *= self.scale
        if self.offset != 0.0:
            out += self.offset
        return out

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Channel):
            return NotImplemented
        return (
            self.name == other.name
            and _same_float(self.scale, other.scale)
            and _same_float(self.offset, other.offset)
            and self.start_angle_raw == other.start_angle_raw
            and self.step_raw == other.step_raw
            and self.values.shape == other.values.shape
            and bool(np.array_equal(self.values, other.values))
        )

    __hash__ = None  # type: ignore[assignment]


def _same_float(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


@dataclass(frozen=True)
class Encoder:
    position: int
    """Encoder position in ticks (uint32)."""
    speed: int
    """Encoder speed in ticks/mm (uint16)."""


@dataclass(frozen=True)
class Position:
    """Optional position block: X/Y/Z position and rotation (REALs) and the rotation type."""

    x: float
    y: float
    z: float
    rot_x: float
    rot_y: float
    rot_z: float
    rotation_type: int
    """0 none, 1 pitch, 2 roll, 3 free."""
    transmit_name: int = 0
    """The enum8 that follows the rotation type in SICK's listing and Wireshark's dissector
    ("transmits the name of device"); no recording has a position block to confirm it."""


@dataclass(frozen=True)
class ScanTime:
    """Optional date/time block (the device clock; usually unset, i.e. 1970-01-01 + uptime)."""

    year: int
    month: int
    day: int
    hour: int
    minute: int
    second: int
    microsecond: int


@dataclass(frozen=True)
class ScanEvent:
    """Optional event block."""

    kind: str
    """4 characters, e.g. ``FDIN``."""
    encoder_position: int
    time_us: int
    angle: int
    """1/10000 deg."""


@dataclass(frozen=True)
class Scan:
    """One LMDscandata body with every header field and all channels."""

    version: int = 1
    device_number: int = 1
    serial_number: int = 0
    device_status: tuple[int, int] = (0, 0)
    """Second byte: 0 ok, 1 error, 2 contamination warning, 4/5 contamination error."""
    telegram_counter: int = 0
    scan_counter: int = 0
    time_since_startup_us: int = 0
    time_of_transmission_us: int = 0
    digital_inputs: tuple[int, int] = (0, 0)
    digital_outputs: tuple[int, int] = (0, 0)
    layer_angle: int = 0
    """int16, 1/100 deg (0 on single-layer scanners, -500 on the MRS1000's lowest layer)."""
    scan_frequency: int = 5000
    """1/100 Hz."""
    measurement_frequency: int = 360
    """Units of 100 Hz (360 = 36 kHz)."""
    encoders: tuple[Encoder, ...] = ()
    channels_16: list[Channel] = field(default_factory=list)
    channels_8: list[Channel] = field(default_factory=list)
    position: Position | None = None
    name: str | None = None
    comment: str | None = None
    time_info: ScanTime | None = None
    event: ScanEvent | None = None

    __hash__ = None  # type: ignore[assignment]

    # -- derived values -----------------------------------------------------------------
    @property
    def scan_frequency_hz(self) -> float:
        return self.scan_frequency / 100.0

    @property
    def measurement_frequency_hz(self) -> float:
        return self.measurement_frequency * 100.0

    @property
    def layer_angle_deg(self) -> float:
        return self.layer_angle / 100.0

    def channel(self, name: str) -> Channel | None:
        """The first channel (16-bit first, then 8-bit) with this content name, or None."""
        for ch in self.channels_16:
            if ch.name == name:
                return ch
        for ch in self.channels_8:
            if ch.name == name:
                return ch
        return None

    @property
    def dist1(self) -> Channel:
        ch = self.channel("DIST1")
        if ch is None:
            raise TelegramError("scan has no DIST1 channel")
        return ch

    @property
    def ranges_m(self) -> npt.NDArray[np.float64]:
        """DIST1 in metres (``values * scale + offset`` mm / 1000), float64. 0 means no echo."""
        return self.dist1.scaled() / 1000.0

    @property
    def angles_rad(self) -> npt.NDArray[np.float64]:
        """Beam angles of DIST1 in radians, device frame (-45..225 deg on an LMS1xx)."""
        return self.dist1.angles_rad

    @property
    def rssi(self) -> npt.NDArray[np.float64] | None:
        """RSSI1 (16- or 8-bit channel) scaled to float64, or None if the scan has none."""
        ch = self.channel("RSSI1")
        return None if ch is None else ch.scaled()

    @property
    def start_angle_deg(self) -> float:
        return self.dist1.start_angle_raw / 10000.0

    @property
    def angular_step_deg(self) -> float:
        return self.dist1.step_raw / 10000.0


def make_channel(
    name: str, values: npt.ArrayLike, start_angle_deg: float, step_deg: float, scale: float = 1.0, offset: float = 0.0
) -> Channel:
    """Convenience constructor from degrees (angles rounded to the device's 1/10000 deg)."""
    return Channel(
        name=name,
        scale=scale,
        offset=offset,
        start_angle_rad=round(start_angle_deg * 10000) * RAD_PER_UNIT,
        step_rad=round(step_deg * 10000) * RAD_PER_UNIT,
        values=np.asarray(values),
    )


# ---------------------------------------------------------------------------------------------
# CoLa B


def _unpack(st: struct.Struct, buf: bytes, pos: int) -> tuple[Any, ...]:
    try:
        return st.unpack_from(buf, pos)
    except struct.error:
        raise TelegramError(f"LMDscandata too short: {st.size} bytes needed at offset {pos}") from None


def _flag(value: int, what: str) -> bool:
    if value > 1:
        raise TelegramError(f"LMDscandata {what} flag is {value}, expected 0 or 1")
    return value == 1


def _channels_b(
    buf: bytes, pos: int, dtype: str, out_dtype: type[np.unsignedinteger[Any]]
) -> tuple[list[Channel], int]:
    (count,) = _unpack(_U16, buf, pos)
    pos += 2
    width = np.dtype(dtype).itemsize
    channels: list[Channel] = []
    for _ in range(count):
        name, scale, offset, start, step, n = _unpack(_CH, buf, pos)
        pos += 21
        end = pos + width * n
        if end > len(buf):
            raise TelegramError(f"LMDscandata channel {name!r} announces {n} values but the telegram is too short")
        values = np.frombuffer(buf, dtype=dtype, count=n, offset=pos).astype(out_dtype)
        pos = end
        channels.append(
            Channel(name.decode("latin-1"), scale, offset, start * RAD_PER_UNIT, step * RAD_PER_UNIT, values)
        )
    return channels, pos


def _string_b(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = _unpack(_U16, buf, pos)
    pos += 2
    if pos + n > len(buf):
        raise TelegramError("LMDscandata string cut short")
    return buf[pos : pos + n].decode("latin-1"), pos + n


def decode_scan_b(buf: bytes, pos: int) -> Scan:
    """Decode a CoLa B LMDscandata body starting at ``buf[pos]`` (to the end of ``buf``)."""
    h = _unpack(_HDR, buf, pos)
    pos += _HDR.size
    encoders = []
    for _ in range(h[16]):
        p, s = _unpack(_ENC, buf, pos)
        pos += 6
        encoders.append(Encoder(p, s))
    ch16, pos = _channels_b(buf, pos, ">u2", np.uint16)
    ch8, pos = _channels_b(buf, pos, "u1", np.uint8)
    position = name = comment = time_info = event = None
    (f,) = _unpack(_U16, buf, pos)
    pos += 2
    if _flag(f, "position"):
        position = Position(*_unpack(_POS, buf, pos))
        pos += _POS.size
    (f,) = _unpack(_U16, buf, pos)
    pos += 2
    if _flag(f, "name"):
        name, pos = _string_b(buf, pos)
    (f,) = _unpack(_U16, buf, pos)
    pos += 2
    if _flag(f, "comment"):
        comment, pos = _string_b(buf, pos)
    (f,) = _unpack(_U16, buf, pos)
    pos += 2
    if _flag(f, "time"):
        time_info = ScanTime(*_unpack(_TIME, buf, pos))
        pos += _TIME.size
    (f,) = _unpack(_U16, buf, pos)
    pos += 2
    if _flag(f, "event"):
        kind, enc, t, ang = _unpack(_EVENT, buf, pos)
        event = ScanEvent(kind.decode("latin-1"), enc, t, ang)
        pos += _EVENT.size
    if pos != len(buf):
        raise TelegramError(f"LMDscandata: {len(buf) - pos} unexpected trailing bytes")
    return Scan(
        version=h[0],
        device_number=h[1],
        serial_number=h[2],
        device_status=(h[3], h[4]),
        telegram_counter=h[5],
        scan_counter=h[6],
        time_since_startup_us=h[7],
        time_of_transmission_us=h[8],
        digital_inputs=(h[9], h[10]),
        digital_outputs=(h[11], h[12]),
        layer_angle=h[13],
        scan_frequency=h[14],
        measurement_frequency=h[15],
        encoders=tuple(encoders),
        channels_16=ch16,
        channels_8=ch8,
        position=position,
        name=name,
        comment=comment,
        time_info=time_info,
        event=event,
    )


def _check_values(ch: Channel, bits: int) -> npt.NDArray[Any]:
    v = np.asarray(ch.values)
    if v.ndim != 1:
        raise TelegramError(f"channel {ch.name} values must be one-dimensional")
    target = np.uint16 if bits == 16 else np.uint8
    if v.dtype != target:
        if v.size and (not np.issubdtype(v.dtype, np.integer) or int(v.min()) < 0 or int(v.max()) >= 1 << bits):
            raise TelegramError(f"channel {ch.name} values do not fit {bits}-bit unsigned integers")
        v = v.astype(target)
    if len(v) > 0xFFFF:
        raise TelegramError(f"channel {ch.name} has more than 65535 values")
    return v


def _channel_name(ch: Channel) -> bytes:
    name = encode_text(ch.name, ascii_frame=True)
    if len(name) != 5 or b" " in name:
        raise TelegramError(f"channel content name must be 5 characters without spaces, got {ch.name!r}")
    return name


def _angles(ch: Channel) -> tuple[int, int]:
    start, step = ch.start_angle_raw, ch.step_raw
    if not -(1 << 31) <= start < 1 << 31 or not 0 <= step <= 0xFFFF:
        raise TelegramError(f"channel {ch.name} angles out of range: start {start}, step {step} (1/10000 deg)")
    return start, step


def encode_scan_b(scan: Scan) -> bytes:
    """CoLa B body of a scan (what follows ``sSN LMDscandata ``)."""
    try:
        parts = [
            _HDR.pack(
                scan.version,
                scan.device_number,
                scan.serial_number,
                *scan.device_status,
                scan.telegram_counter,
                scan.scan_counter,
                scan.time_since_startup_us,
                scan.time_of_transmission_us,
                *scan.digital_inputs,
                *scan.digital_outputs,
                scan.layer_angle,
                scan.scan_frequency,
                scan.measurement_frequency,
                len(scan.encoders),
            )
        ]
        parts.extend(_ENC.pack(e.position, e.speed) for e in scan.encoders)
        for channels, bits, dtype in ((scan.channels_16, 16, ">u2"), (scan.channels_8, 8, "u1")):
            parts.append(_U16.pack(len(channels)))
            for ch in channels:
                v = _check_values(ch, bits)
                start, step = _angles(ch)
                parts.append(_CH.pack(_channel_name(ch), ch.scale, ch.offset, start, step, len(v)))
                parts.append(v.astype(dtype, copy=False).tobytes())
        if scan.position is None:
            parts.append(b"\x00\x00")
        else:
            p = scan.position
            parts.append(
                b"\x00\x01" + _POS.pack(p.x, p.y, p.z, p.rot_x, p.rot_y, p.rot_z, p.rotation_type, p.transmit_name)
            )
        for text in (scan.name, scan.comment):
            if text is None:
                parts.append(b"\x00\x00")
            else:
                data = encode_text(text)
                parts.append(b"\x00\x01" + _U16.pack(len(data)) + data)
        if scan.time_info is None:
            parts.append(b"\x00\x00")
        else:
            t = scan.time_info
            parts.append(b"\x00\x01" + _TIME.pack(t.year, t.month, t.day, t.hour, t.minute, t.second, t.microsecond))
        if scan.event is None:
            parts.append(b"\x00\x00")
        else:
            e = scan.event
            kind = encode_text(e.kind)
            if len(kind) != 4:
                raise TelegramError(f"event type must be 4 characters, got {e.kind!r}")
            parts.append(b"\x00\x01" + _EVENT.pack(kind, e.encoder_position, e.time_us, e.angle))
    except (struct.error, TypeError, ValueError) as exc:
        raise TelegramError(f"cannot encode scan: {exc}") from None
    return b"".join(parts)


# ---------------------------------------------------------------------------------------------
# CoLa A


def parse_hex_tokens(buf: bytes, pos: int, n: int, max_digits: int) -> tuple[npt.NDArray[np.int64], int]:
    """Parse ``n`` space-separated hex tokens (1..max_digits digits each) starting at ``buf[pos]``.

    Returns the values and the position after the last token's separating space. Vectorised.
    """
    if n == 0:
        return np.empty(0, dtype=np.int64), pos
    seg = np.frombuffer(buf, dtype=np.uint8, count=min(len(buf) - pos, n * (max_digits + 1)), offset=pos)
    spaces = np.flatnonzero(seg == 0x20)
    if len(spaces) >= n:
        end = int(spaces[n - 1])
        new_pos = pos + end + 1
    elif len(spaces) == n - 1 and pos + len(seg) == len(buf):
        end = len(seg)
        new_pos = len(buf)
    else:
        raise TelegramError(f"expected {n} values of up to {max_digits} hex digits")
    ends = np.empty(n, dtype=np.int64)
    ends[: n - 1] = spaces[: n - 1]
    ends[n - 1] = end
    starts = np.empty(n, dtype=np.int64)
    starts[0] = 0
    starts[1:] = ends[: n - 1] + 1
    lengths = ends - starts
    if int(lengths.min()) < 1 or int(lengths.max()) > max_digits:
        raise TelegramError(f"value tokens must have 1..{max_digits} hex digits")
    idx = ends[:, None] + np.arange(-max_digits, 0, dtype=np.int64)[None, :]
    valid = idx >= starts[:, None]
    digits = _HEX_LUT[seg[np.maximum(idx, 0)]]
    if bool(((digits < 0) & valid).any()):
        raise TelegramError("invalid character in a hex value")
    digits[~valid] = 0
    weights = np.left_shift(1, 4 * np.arange(max_digits - 1, -1, -1, dtype=np.int64))
    return digits @ weights, new_pos


def format_hex_tokens(values: npt.NDArray[Any], max_digits: int) -> bytes:
    """Upper-case hex without leading zeros, space-separated (inverse of :func:`parse_hex_tokens`)."""
    n = len(values)
    if n == 0:
        return b""
    v = values.astype(np.int64)
    shifts = 4 * np.arange(max_digits - 1, -1, -1, dtype=np.int64)
    d = (v[:, None] >> shifts[None, :]) & 0xF
    nz = d != 0
    first = np.where(nz.any(axis=1), nz.argmax(axis=1), max_digits - 1)
    out = np.empty((n, max_digits + 1), dtype=np.uint8)
    out[:, :max_digits] = _HEX_CHARS[d]
    out[:, max_digits] = 0x20
    mask = np.ones((n, max_digits + 1), dtype=bool)
    mask[:, :max_digits] = np.arange(max_digits)[None, :] >= first[:, None]
    return out[mask].tobytes()[:-1]


def _hex_re(*digits: int) -> re.Pattern[bytes]:
    return re.compile(b" ".join(b"([0-9A-Fa-f]{1,%d})" % d for d in digits) + b" ")


# version .. measurement frequency (16 tokens), each followed by a space
_HDR_A = _hex_re(4, 4, 8, 2, 2, 4, 4, 8, 8, 2, 2, 2, 2, 4, 8, 8)
# content name, scale, offset, start angle, step, count; the count may end the text (0 values, then nothing)
_CH_A = re.compile(
    rb"([^ ]+) ([0-9A-Fa-f]{1,8}) ([0-9A-Fa-f]{1,8}) ([0-9A-Fa-f]{1,8}) ([0-9A-Fa-f]{1,4}) ([0-9A-Fa-f]{1,4}) "
)
_REALS = struct.Struct(">ff")
_U32X2 = struct.Struct(">II")


def _channels_a(r: AsciiReader, max_digits: int, out_dtype: type[np.unsignedinteger[Any]]) -> list[Channel]:
    count = r.num(2)
    channels: list[Channel] = []
    for _ in range(count):
        m = _CH_A.match(r.buf, r.pos)
        if m is not None:  # fast path: the device's own hex notation
            name = m[1].decode("latin-1")
            scale, offset = _REALS.unpack(_U32X2.pack(int(m[2], 16), int(m[3], 16)))
            start = int(m[4], 16)
            if start >= 1 << 31:
                start -= 1 << 32
            step, n = int(m[5], 16), int(m[6], 16)
            r.pos = m.end()
        else:  # general path: signed decimals etc., with precise errors
            name = r.token().decode("latin-1")
            scale = r.real()
            offset = r.real()
            start = r.num(4, True)
            step = r.num(2)
            n = r.num(2)
        values, r.pos = parse_hex_tokens(r.buf, r.pos, n, max_digits)
        channels.append(
            Channel(name, scale, offset, start * RAD_PER_UNIT, step * RAD_PER_UNIT, values.astype(out_dtype))
        )
    return channels


def _flag_a(r: AsciiReader, what: str) -> bool:
    return _flag(r.num(2), what)


def decode_scan_a(buf: bytes, pos: int) -> Scan:
    """Decode a CoLa A LMDscandata body starting at ``buf[pos]``."""
    r = AsciiReader(buf, pos)
    m = _HDR_A.match(buf, pos)
    if m is not None:  # fast path: the device's own hex notation
        h = [int(g, 16) for g in m.groups()]
        version, device_number, serial = h[0], h[1], h[2]
        status, tcount, scount, t_start, t_tx = (h[3], h[4]), h[5], h[6], h[7], h[8]
        inputs, outputs = (h[9], h[10]), (h[11], h[12])
        layer = h[13] - (1 << 16) if h[13] >= 1 << 15 else h[13]
        freq, mfreq = h[14], h[15]
        r.pos = m.end()
    else:  # general path: signed decimals etc., with precise errors
        version = r.num(2)
        device_number = r.num(2)
        serial = r.num(4)
        status = (r.num(1), r.num(1))
        tcount = r.num(2)
        scount = r.num(2)
        t_start = r.num(4)
        t_tx = r.num(4)
        inputs = (r.num(1), r.num(1))
        outputs = (r.num(1), r.num(1))
        layer = r.num(2, True)
        freq = r.num(4)
        mfreq = r.num(4)
    encoders = tuple(Encoder(r.num(4), r.num(2)) for _ in range(r.num(2)))
    ch16 = _channels_a(r, 4, np.uint16)
    ch8 = _channels_a(r, 2, np.uint8)
    position = name = comment = time_info = event = None
    if _flag_a(r, "position"):
        position = Position(r.real(), r.real(), r.real(), r.real(), r.real(), r.real(), r.num(1), r.num(1))
    if _flag_a(r, "name"):
        name = r.string()
    if _flag_a(r, "comment"):
        comment = r.string()
    if _flag_a(r, "time"):
        time_info = ScanTime(r.num(2), r.num(1), r.num(1), r.num(1), r.num(1), r.num(1), r.num(4))
    if _flag_a(r, "event"):
        event = ScanEvent(r.token().decode("latin-1"), r.num(4), r.num(4), r.num(4, True))
    r.expect_end("LMDscandata")
    return Scan(
        version=version,
        device_number=device_number,
        serial_number=serial,
        device_status=status,
        telegram_counter=tcount,
        scan_counter=scount,
        time_since_startup_us=t_start,
        time_of_transmission_us=t_tx,
        digital_inputs=inputs,
        digital_outputs=outputs,
        layer_angle=layer,
        scan_frequency=freq,
        measurement_frequency=mfreq,
        encoders=encoders,
        channels_16=ch16,
        channels_8=ch8,
        position=position,
        name=name,
        comment=comment,
        time_info=time_info,
        event=event,
    )


def encode_scan_a(scan: Scan) -> bytes:
    """CoLa A body of a scan (what follows ``sSN LMDscandata ``)."""
    w = AsciiWriter()
    w.num(scan.version, 2)
    w.num(scan.device_number, 2)
    w.num(scan.serial_number, 4)
    for b in scan.device_status:
        w.num(b, 1)
    w.num(scan.telegram_counter, 2)
    w.num(scan.scan_counter, 2)
    w.num(scan.time_since_startup_us, 4)
    w.num(scan.time_of_transmission_us, 4)
    for b in (*scan.digital_inputs, *scan.digital_outputs):
        w.num(b, 1)
    w.num(scan.layer_angle, 2, True)
    w.num(scan.scan_frequency, 4)
    w.num(scan.measurement_frequency, 4)
    w.num(len(scan.encoders), 2)
    for e in scan.encoders:
        w.num(e.position, 4)
        w.num(e.speed, 2)
    for channels, bits, digits in ((scan.channels_16, 16, 4), (scan.channels_8, 8, 2)):
        w.num(len(channels), 2)
        for ch in channels:
            v = _check_values(ch, bits)
            start, step = _angles(ch)
            w.raw(_channel_name(ch))
            w.real(ch.scale)
            w.real(ch.offset)
            w.num(start, 4, True)
            w.num(step, 2)
            w.num(len(v), 2)
            if len(v):
                w.raw(format_hex_tokens(v, digits))
    if scan.position is None:
        w.num(0, 2)
    else:
        p = scan.position
        w.num(1, 2)
        for x in (p.x, p.y, p.z, p.rot_x, p.rot_y, p.rot_z):
            w.real(x)
        w.num(p.rotation_type, 1)
        w.num(p.transmit_name, 1)
    for text in (scan.name, scan.comment):
        if text is None:
            w.num(0, 2)
        else:
            w.num(1, 2)
            w.string(text)
    if scan.time_info is None:
        w.num(0, 2)
    else:
        t = scan.time_info
        w.num(1, 2)
        w.num(t.year, 2)
        for x in (t.month, t.day, t.hour, t.minute, t.second):
            w.num(x, 1)
        w.num(t.microsecond, 4)
    if scan.event is None:
        w.num(0, 2)
    else:
        ev = scan.event
        kind = encode_text(ev.kind, ascii_frame=True)
        if len(kind) != 4 or b" " in kind:
            raise TelegramError(f"event type must be 4 characters without spaces, got {ev.kind!r}")
        w.num(1, 2)
        w.raw(kind)
        w.num(ev.encoder_position, 4)
        w.num(ev.time_us, 4)
        w.num(ev.angle, 4, True)
    return w.getvalue()


def decode_scan(buf: bytes, pos: int, dialect: Dialect) -> Scan:
    return decode_scan_b(buf, pos) if dialect is Dialect.B else decode_scan_a(buf, pos)


def encode_scan(scan: Scan, dialect: Dialect) -> bytes:
    return encode_scan_b(scan) if dialect is Dialect.B else encode_scan_a(scan)
