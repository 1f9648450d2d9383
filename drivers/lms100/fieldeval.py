"""Field-evaluation and I/O telegrams of the LMS1xx: field definitions, input and output states.

Layouts come from the LMS111 and LMS511 recordings (``tests/data/sick-recordings/``), where every
telegram below occurs and decodes, and re-encodes, byte for byte; SICK's public material does not
list them. CoLa A uses the same fields as tokens (hex numbers, REALs as bit patterns, strings with a
hex length), as for every other telegram; no CoLa A recording of these exists.

* ``sRN fieldNNN`` -> ``sRA fieldNNN``: :class:`ReadFieldDefinition` / :class:`FieldDefinition`. An
  LMS1xx has 30 (field000..field029; an LMS5xx answers ``sFA 3`` from field030 on). A definition is
  either a :class:`FieldGeometry` or, for indices the device keeps no definition for, the single byte
  ``00`` (the LMS111 answers field010..field029 so): ``geometry=None``.
* ``sRN LIDinputstate`` -> ``sRA LIDinputstate`` (:class:`InputState`); the same body comes as
  ``sSN LIDinputstate`` (:class:`InputStateEvent`) after ``sEN LIDinputstate 1`` when an input changes.
* ``sSN LIDoutputstate`` (:class:`OutputStateEvent`) after ``sEN LIDoutputstate 1``: at once, then on
  every change.
* ``sEN`` / ``sEA`` for ``LIDoutputstate``, ``LIDinputstate`` and ``LFErec`` (the subscriptions).
  ``sSN LFErec`` (field evaluation results) stays a :class:`~drivers.lms100.messages.RawTelegram`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from drivers.lms100._values import BOOL, AsciiReader, AsciiWriter, BinReader, BinWriter, check_int
from drivers.lms100.errors import TelegramError
from drivers.lms100.framing import Dialect
from drivers.lms100.messages import Message, RawTelegram, _msg, register_family
from drivers.lms100.scan import ScanTime

_Reader = BinReader | AsciiReader
_Writer = BinWriter | AsciiWriter

FIELD_TYPES: dict[int, str] = {0: "radial", 1: "rectangle", 2: "segmented", 3: "dynamic"}
"""``FieldGeometry.field_type`` as sick_scan_xd names it (radial: no recording, not decodable)."""


def _reader(buf: bytes, pos: int, dialect: Dialect) -> _Reader:
    return BinReader(buf, pos) if dialect is Dialect.B else AsciiReader(buf, pos)


def _writer(dialect: Dialect) -> _Writer:
    return BinWriter() if Dialect(dialect) is Dialect.B else AsciiWriter()


def _flag(r: _Reader, what: str) -> bool:
    value = r.num(2)
    if value not in (0, 1):
        raise TelegramError(f"{what} flag must be 0 or 1, got {value}")
    return value == 1


def _put_time(w: _Writer, t: ScanTime | None) -> None:
    """The optional date/time block as in LMDscandata: uint16 flag, then year, 5 x uint8, uint32 us."""
    if t is None:
        w.num(0, 2)
        return
    w.num(1, 2)
    w.num(t.year, 2)
    for x in (t.month, t.day, t.hour, t.minute, t.second):
        w.num(x, 1)
    w.num(t.microsecond, 4)


def _get_time(r: _Reader) -> ScanTime | None:
    if not _flag(r, "time"):
        return None
    return ScanTime(r.num(2), r.num(1), r.num(1), r.num(1), r.num(1), r.num(1), r.num(4))


# ---------------------------------------------------------------------------------------------
# field definitions


def _field_index(name: str) -> int:
    return int(name[5:])


def _check_index(index: int) -> None:
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index <= 999:
        raise TelegramError(f"field index must be 0..999 (fieldNNN), got {index!r}")


@dataclass(frozen=True)
class SegmentPoint:
    """One point of a segmented field: beam index on the field's angle grid, distances (mm before scaling)."""

    angle_index: int
    start_distance: int
    stop_distance: int


@dataclass(frozen=True)
class RectangularField:
    """A rectangle placed by a reference point (angle 1/10000 deg, distance) and turned by ``rotation``."""

    angle_ref: int
    distance_ref: int
    rotation: int
    """1/10000 deg."""
    width: int
    """mm."""
    length: int
    """mm."""


@dataclass(frozen=True)
class DynamicField(RectangularField):
    """A rectangle that grows with speed: ``length`` at standstill, ``max_length`` at ``max_speed``."""

    max_speed: int
    """mm/s (int16)."""
    max_length: int
    """mm."""


def _put_rectangle(w: _Writer, rect: RectangularField | None) -> None:
    """Flag, then reference angle, reference distance, rotation, width, length (a dynamic field adds two)."""
    if rect is None:
        w.num(0, 2)
        return
    w.num(1, 2)
    w.num(rect.angle_ref, 4, True)
    w.num(rect.distance_ref, 2)
    w.num(rect.rotation, 4, True)
    w.num(rect.width, 4)
    w.num(rect.length, 4)


@dataclass(frozen=True)
class FieldGeometry:
    """The body of ``sRA fieldNNN`` when a definition exists.

    Distances are ``value x distance_scale + distance_offset`` mm; angles of segment points are
    ``angle_index x angular_scale + angular_offset`` (1/10000 deg). ``name`` and ``comment`` follow as
    flag-prefixed strings as in LMDscandata; every recorded definition has a name (possibly empty) and
    no comment.
    """

    distance_scale: float = 1.0
    distance_offset: float = 0.0
    angular_scale: int = 5000
    angular_offset: int = -450000
    field_type: int = 2
    """See :data:`FIELD_TYPES`."""
    field_number: int = 0
    segments: tuple[SegmentPoint, ...] | None = None
    rectangle: RectangularField | None = None
    dynamic: DynamicField | None = None
    name: str | None = ""
    comment: str | None = None

    def write(self, w: _Writer) -> None:
        w.real(self.distance_scale)
        w.real(self.distance_offset)
        w.num(self.angular_scale, 4)
        w.num(self.angular_offset, 4, True)
        w.num(self.field_type, 1)
        w.num(self.field_number, 1)
        if self.segments is None:
            w.num(0, 2)
        else:
            w.num(1, 2)
            w.num(check_int(len(self.segments), 2, False), 2)
            for p in self.segments:
                w.num(p.angle_index, 2)
                w.num(p.start_distance, 2)
                w.num(p.stop_distance, 2)
        _put_rectangle(w, self.rectangle)
        w.num(0, 2)  # no radial field (its layout is in no source we have)
        _put_rectangle(w, self.dynamic)
        if self.dynamic is not None:
            w.num(self.dynamic.max_speed, 2, True)
            w.num(self.dynamic.max_length, 4)
        for text in (self.name, self.comment):
            if text is None:
                w.num(0, 2)
            else:
                w.num(1, 2)
                w.string(text)

    @classmethod
    def read(cls, r: _Reader) -> FieldGeometry | None:
        """The geometry, or None for a radial field (its layout is in no source we have)."""
        scale, offset = r.real(), r.real()
        ang_scale, ang_offset = r.num(4), r.num(4, True)
        field_type, field_number = r.num(1), r.num(1)
        segments = None
        if _flag(r, "segmented field"):
            segments = tuple(SegmentPoint(r.num(2), r.num(2), r.num(2)) for _ in range(r.num(2)))
        rectangle = None
        if _flag(r, "rectangular field"):
            rectangle = RectangularField(r.num(4, True), r.num(2), r.num(4, True), r.num(4), r.num(4))
        if _flag(r, "radial field"):
            return None
        dynamic = None
        if _flag(r, "dynamic field"):
            rect = (r.num(4, True), r.num(2), r.num(4, True), r.num(4), r.num(4))
            dynamic = DynamicField(*rect, max_speed=r.num(2, True), max_length=r.num(4))
        name = r.string() if _flag(r, "name") else None
        comment = r.string() if _flag(r, "comment") else None
        return cls(
            scale, offset, ang_scale, ang_offset, field_type, field_number, segments, rectangle, dynamic, name, comment
        )


@dataclass(frozen=True)
class ReadFieldDefinition(Message):
    """``sRN fieldNNN``: read field definition ``index`` (0..29 on an LMS1xx)."""

    index: int
    KIND: ClassVar[str] = "sRN"

    def __post_init__(self) -> None:
        _check_index(self.index)

    @property
    def name(self) -> str:
        return f"field{self.index:03d}"


@dataclass(frozen=True)
class FieldDefinition(Message):
    """``sRA fieldNNN``: the definition, or ``geometry=None`` for the device's one-byte ``00`` answer."""

    index: int
    geometry: FieldGeometry | None
    KIND: ClassVar[str] = "sRA"

    def __post_init__(self) -> None:
        _check_index(self.index)

    @property
    def name(self) -> str:
        return f"field{self.index:03d}"

    def encode_params(self, dialect: Dialect) -> bytes:
        w = _writer(dialect)
        if self.geometry is None:
            w.num(0, 1)
        else:
            self.geometry.write(w)
        return w.getvalue()


def _decode_read_field(name: str, buf: bytes, pos: int, dialect: Dialect) -> Message:
    if pos < len(buf):
        raise TelegramError(f"sRN {name} takes no parameters")
    return ReadFieldDefinition(_field_index(name))


def _decode_field(name: str, buf: bytes, pos: int, dialect: Dialect) -> Message:
    r = _reader(buf, pos, dialect)
    index = _field_index(name)
    if len(buf) - pos <= 2:  # the one-byte "no definition" answer (CoLa A: one short token)
        if r.num(1) != 0:
            raise TelegramError(f"sRA {name}: a one-byte field answer must be 0")
        r.expect_end("field")
        return FieldDefinition(index, None)
    geometry = FieldGeometry.read(r)
    if geometry is None:  # a radial field: kept as raw bytes
        return RawTelegram("sRA", name, buf[pos:])
    r.expect_end("field definition")
    return FieldDefinition(index, geometry)


register_family("sRN", r"field[0-9]{3}", _decode_read_field)
register_family("sRA", r"field[0-9]{3}", _decode_field)


# ---------------------------------------------------------------------------------------------
# input and output states


@_msg("sRN", "LIDinputstate")
class ReadInputState(Message):
    pass


@dataclass(frozen=True)
class _InputStateBody(Message):
    """Version, a system counter (us), the four digital inputs, the optional date/time block.

    Inputs as recorded: the LMS111 answers ``02 02 02 02``, the LMS511 ``00 00 00 00``; sick_scan_xd
    reads 1 as "active" (and picks the active field set from them).
    """

    version: int
    system_counter: int
    inputs: tuple[int, int, int, int]
    time: ScanTime | None = None

    def encode_params(self, dialect: Dialect) -> bytes:
        if len(self.inputs) != 4:
            raise TelegramError(f"LIDinputstate carries 4 inputs, got {len(self.inputs)}")
        w = _writer(dialect)
        w.num(self.version, 2)
        w.num(self.system_counter, 4)
        for x in self.inputs:
            w.num(x, 1)
        _put_time(w, self.time)
        return w.getvalue()

    @classmethod
    def decode_params(cls, buf: bytes, pos: int, dialect: Dialect) -> Message:
        r = _reader(buf, pos, dialect)
        version, counter = r.num(2), r.num(4)
        inputs = (r.num(1), r.num(1), r.num(1), r.num(1))
        time = _get_time(r)
        r.expect_end("LIDinputstate")
        return cls(version, counter, inputs, time)


@dataclass(frozen=True)
class InputState(_InputStateBody):
    """``sRA LIDinputstate``."""

    KIND: ClassVar[str] = "sRA"
    NAME: ClassVar[str] = "LIDinputstate"


@dataclass(frozen=True)
class InputStateEvent(_InputStateBody):
    """``sSN LIDinputstate``."""

    KIND: ClassVar[str] = "sSN"
    NAME: ClassVar[str] = "LIDinputstate"


@dataclass(frozen=True)
class OutputStateEvent(Message):
    """``sSN LIDoutputstate``: version, system counter (us), per output (state, count), optional date/time.

    State 0 inactive, 1 active, 2 not used (sick_scan_xd's reading). The count is not prefixed: it
    follows from the length (5 bytes per output; CoLa A: 2 tokens). The LMS111 sends 11 outputs
    (3 switching outputs, then 8 "not used"), the LMS511 14.
    """

    version: int
    system_counter: int
    outputs: tuple[tuple[int, int], ...]
    time: ScanTime | None = None

    KIND: ClassVar[str] = "sSN"
    NAME: ClassVar[str] = "LIDoutputstate"

    def encode_params(self, dialect: Dialect) -> bytes:
        w = _writer(dialect)
        w.num(self.version, 2)
        w.num(self.system_counter, 4)
        for state, count in self.outputs:
            w.num(state, 1)
            w.num(count, 4)
        _put_time(w, self.time)
        return w.getvalue()

    @classmethod
    def decode_params(cls, buf: bytes, pos: int, dialect: Dialect) -> Message:
        r = _reader(buf, pos, dialect)
        version, counter = r.num(2), r.num(4)
        if dialect is Dialect.B:  # 5 bytes per output, then 2 (no time) or 13 (time) bytes
            rest = len(buf) - r.pos
            n, tail = divmod(rest - 2, 5)
            if tail == 1:
                n = (rest - 13) // 5
            elif tail != 0:
                raise TelegramError(f"LIDoutputstate: {rest} bytes after the counter fit no layout")
        else:  # 2 tokens per output, then 1 (no time) or 8 (time) tokens
            rest_tokens = len(buf[r.pos :].split(b" ")) if r.pos < len(buf) else 0
            n = (rest_tokens - 1) // 2 if rest_tokens % 2 else (rest_tokens - 8) // 2
        if n < 0:
            raise TelegramError("LIDoutputstate is too short")
        outputs = tuple((r.num(1), r.num(4)) for _ in range(n))
        time = _get_time(r)
        r.expect_end("LIDoutputstate")
        return cls(version, counter, outputs, time)


# ---------------------------------------------------------------------------------------------
# subscriptions


@_msg("sEN", "LIDoutputstate", ("enable", BOOL))
class SubscribeOutputState(Message):
    enable: bool = True


@_msg("sEA", "LIDoutputstate", ("enable", BOOL))
class SubscribeOutputStateReply(Message):
    enable: bool


@_msg("sEN", "LIDinputstate", ("enable", BOOL))
class SubscribeInputState(Message):
    enable: bool = True


@_msg("sEA", "LIDinputstate", ("enable", BOOL))
class SubscribeInputStateReply(Message):
    enable: bool


@_msg("sEN", "LFErec", ("enable", BOOL))
class SubscribeFieldResults(Message):
    """``sEN LFErec 1``: field evaluation results as ``sSN LFErec`` (a RawTelegram here)."""

    enable: bool = True


@_msg("sEA", "LFErec", ("enable", BOOL))
class SubscribeFieldResultsReply(Message):
    enable: bool
