"""Field-level readers and writers for CoLa parameters in both dialects (internal).

CoLa B: big-endian, packed, strings prefixed by a uint16 length.
CoLa A: space-separated tokens; numbers in upper-case hex (two's complement of the field width for
signed fields) or decimal with an explicit sign (``+5000``); REALs as the 8-hex-digit IEEE-754 bit
pattern; strings as a hex length token, a space, then exactly that many characters (which may
themselves contain spaces).
"""

from __future__ import annotations

import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from drivers.lms100.errors import TelegramError

Style = Literal["X", "02X", "+d"]

_HEX = frozenset(b"0123456789ABCDEFabcdef")
_DEC = frozenset(b"0123456789")
_INT_FMT = {
    (1, False): struct.Struct(">B"),
    (1, True): struct.Struct(">b"),
    (2, False): struct.Struct(">H"),
    (2, True): struct.Struct(">h"),
    (4, False): struct.Struct(">I"),
    (4, True): struct.Struct(">i"),
}
_REAL = struct.Struct(">f")
_U32 = struct.Struct(">I")
_U16 = struct.Struct(">H")


@dataclass(frozen=True)
class Field:
    """How one parameter is laid out: ``int`` (size, signed), ``bool`` (1 byte), ``real``, ``str``, ``pair``."""

    kind: Literal["int", "bool", "real", "str", "pair"]
    size: int = 0
    signed: bool = False
    style: Style = "X"


U8 = Field("int", 1)
U16 = Field("int", 2)
U32 = Field("int", 4)
I8 = Field("int", 1, True)
I16 = Field("int", 2, True)
I32 = Field("int", 4, True)
BOOL = Field("bool", 1)
REAL = Field("real", 4)
STR = Field("str")
PAIR = Field("pair", 1)  # "2 x uint8", a tuple of two ints
PAIR02 = Field("pair", 1, style="02X")


def int_range(size: int, signed: bool) -> tuple[int, int]:
    bits = 8 * size
    return (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)


def check_int(value: int, size: int, signed: bool) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TelegramError(f"expected an integer, got {value!r}")
    lo, hi = int_range(size, signed)
    if not lo <= value <= hi:
        raise TelegramError(f"value {value} does not fit a {'signed' if signed else 'unsigned'} {8 * size}-bit field")
    return value


def parse_ascii_int(tok: bytes, size: int, signed: bool) -> int:
    """Parse a CoLa A number token: hex (two's complement) or signed decimal."""
    if not tok:
        raise TelegramError("empty number")
    if tok[0] in b"+-":
        digits = tok[1:]
        if not digits or not _DEC.issuperset(digits):
            raise TelegramError(f"bad decimal number {tok!r}")
        value = int(tok)
        lo, hi = int_range(size, signed)
        if not lo <= value <= hi:
            raise TelegramError(f"decimal {tok!r} does not fit a {8 * size}-bit field")
        return value
    if len(tok) > 2 * size or not _HEX.issuperset(tok):
        raise TelegramError(f"bad hex number {tok!r} for a {8 * size}-bit field")
    value = int(tok, 16)
    if signed and value >= 1 << (8 * size - 1):
        value -= 1 << (8 * size)
    return value


def format_ascii_int(value: int, size: int, signed: bool, style: Style = "X") -> bytes:
    check_int(value, size, signed)
    if style == "+d":
        return b"%+d" % value
    if value < 0:
        value += 1 << (8 * size)
    return (b"%02X" if style == "02X" else b"%X") % value


class _Reader(ABC):
    """Sequential reader of one telegram's parameters; the dialects differ in how a value is read."""

    __slots__ = ("buf", "pos")

    def __init__(self, buf: bytes, pos: int = 0) -> None:
        self.buf = buf
        self.pos = pos

    @abstractmethod
    def num(self, size: int, signed: bool = False) -> int: ...

    @abstractmethod
    def real(self) -> float: ...

    @abstractmethod
    def string(self) -> str: ...

    def get(self, f: Field) -> Any:
        if f.kind == "int":
            return self.num(f.size, f.signed)
        if f.kind == "bool":
            return self.num(1) != 0
        if f.kind == "real":
            return self.real()
        if f.kind == "str":
            return self.string()
        return (self.num(1), self.num(1))

    def at_end(self) -> bool:
        return self.pos >= len(self.buf)


class BinReader(_Reader):
    """Sequential reader of CoLa B parameters."""

    __slots__ = ()

    def unpack(self, st: struct.Struct) -> tuple[Any, ...]:
        try:
            values = st.unpack_from(self.buf, self.pos)
        except struct.error:
            raise TelegramError(f"telegram too short: {st.size} more bytes needed at offset {self.pos}") from None
        self.pos += st.size
        return values

    def num(self, size: int, signed: bool = False) -> int:
        value: int = self.unpack(_INT_FMT[(size, signed)])[0]
        return value

    def real(self) -> float:
        value: float = self.unpack(_REAL)[0]
        return value

    def raw(self, n: int) -> bytes:
        end = self.pos + n
        if end > len(self.buf):
            raise TelegramError(f"telegram too short: {n} bytes needed at offset {self.pos}")
        data = self.buf[self.pos : end]
        self.pos = end
        return bytes(data)

    def string(self) -> str:
        n = self.num(2)
        return self.raw(n).decode("latin-1")

    def expect_end(self, what: str) -> None:
        if self.pos != len(self.buf):
            raise TelegramError(f"{what}: {len(self.buf) - self.pos} unexpected trailing bytes")


class AsciiReader(_Reader):
    """Sequential reader of CoLa A parameters (tokens separated by single spaces)."""

    __slots__ = ()

    def token(self) -> bytes:
        buf = self.buf
        pos = self.pos
        if pos >= len(buf):
            raise TelegramError("telegram too short: a parameter is missing")
        end = buf.find(b" ", pos)
        if end < 0:
            end = len(buf)
        if end == pos:
            raise TelegramError(f"empty parameter (two spaces) at offset {pos}")
        self.pos = end + 1
        return buf[pos:end]

    def num(self, size: int, signed: bool = False) -> int:
        return parse_ascii_int(self.token(), size, signed)

    def real(self) -> float:
        tok = self.token()
        if len(tok) > 8 or not _HEX.issuperset(tok):
            raise TelegramError(f"bad REAL {tok!r} (expected up to 8 hex digits of the IEEE-754 pattern)")
        value: float = _REAL.unpack(_U32.pack(int(tok, 16)))[0]
        return value

    def raw(self, n: int) -> bytes:
        """Exactly ``n`` characters (spaces included), then the separating space if any."""
        buf = self.buf
        end = self.pos + n
        if end > len(buf):
            raise TelegramError(f"telegram too short: a {n}-character string is cut")
        if end < len(buf) and buf[end] != 0x20:
            raise TelegramError(f"a {n}-character string is not followed by a space")
        data = buf[self.pos : end]
        self.pos = end + 1
        return bytes(data)

    def string(self) -> str:
        tok = self.token()
        if len(tok) > 4 or not _HEX.issuperset(tok):
            raise TelegramError(f"bad string length {tok!r}")
        n = int(tok, 16)
        if n == 0:
            return ""
        return self.raw(n).decode("latin-1")

    def expect_end(self, what: str) -> None:
        if self.pos < len(self.buf):
            raise TelegramError(f"{what}: unexpected trailing parameters {self.buf[self.pos : self.pos + 40]!r}")


def _pack_real(value: float) -> bytes:
    """The 4 big-endian bytes of an IEEE-754 single (both dialects carry this bit pattern)."""
    try:
        return _REAL.pack(value)
    except (struct.error, OverflowError, TypeError) as exc:
        raise TelegramError(f"bad REAL {value!r}: {exc}") from None


class _Writer(ABC):
    """Collects one telegram's parameters; the dialects differ in how a value is written and joined."""

    __slots__ = ("parts",)
    SEPARATOR: ClassVar[bytes]

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    @abstractmethod
    def num(self, value: int, size: int, signed: bool = False, style: Style = "X") -> None: ...

    @abstractmethod
    def real(self, value: float) -> None: ...

    @abstractmethod
    def string(self, value: str) -> None: ...

    def raw(self, data: bytes) -> None:
        self.parts.append(data)

    def put(self, f: Field, value: Any) -> None:
        if f.kind == "int":
            self.num(value, f.size, f.signed, f.style)
        elif f.kind == "bool":
            self.num(int(bool(value)), 1, False, f.style)
        elif f.kind == "real":
            self.real(value)
        elif f.kind == "str":
            self.string(value)
        else:
            a, b = value
            self.num(a, 1, False, f.style)
            self.num(b, 1, False, f.style)

    def getvalue(self) -> bytes:
        return self.SEPARATOR.join(self.parts)


class BinWriter(_Writer):
    """CoLa B: packed big-endian values (``style`` is a CoLa A matter and ignored)."""

    __slots__ = ()
    SEPARATOR = b""

    def num(self, value: int, size: int, signed: bool = False, style: Style = "X") -> None:
        self.parts.append(_INT_FMT[(size, signed)].pack(check_int(value, size, signed)))

    def real(self, value: float) -> None:
        self.parts.append(_pack_real(value))

    def string(self, value: str) -> None:
        data = encode_text(value)
        if len(data) > 0xFFFF:
            raise TelegramError("string longer than 65535 characters")
        self.parts.append(_U16.pack(len(data)) + data)


class AsciiWriter(_Writer):
    """CoLa A: space-separated tokens."""

    __slots__ = ()
    SEPARATOR = b" "

    def num(self, value: int, size: int, signed: bool = False, style: Style = "X") -> None:
        self.parts.append(format_ascii_int(value, size, signed, style))

    def real(self, value: float) -> None:
        self.parts.append(b"%08X" % _U32.unpack(_pack_real(value))[0])

    def string(self, value: str) -> None:
        data = encode_text(value, ascii_frame=True)
        if len(data) > 0xFFFF:
            raise TelegramError("string longer than 65535 characters")
        self.parts.append(b"%X" % len(data))
        if data:
            self.parts.append(data)


def encode_text(value: str, ascii_frame: bool = False) -> bytes:
    """Strings go on the wire as single bytes (latin-1); in CoLa A they cannot contain STX/ETX."""
    try:
        data = value.encode("latin-1")
    except (UnicodeEncodeError, AttributeError):
        raise TelegramError(f"string {value!r} is not representable in latin-1") from None
    if ascii_frame and (b"\x02" in data or b"\x03" in data):
        raise TelegramError(f"string {value!r} contains STX/ETX, which a CoLa A frame cannot carry")
    return data


Reader = BinReader | AsciiReader
Writer = BinWriter | AsciiWriter
