"""CoLa A / CoLa B framing: build frames and cut a byte stream back into payloads.

CoLa A: ``STX`` + ASCII text + ``ETX``; no length, no checksum.
CoLa B: ``02 02 02 02`` + payload length (uint32, big-endian) + payload + XOR of the payload bytes.

:class:`Framer` is incremental and sans-I/O: :meth:`Framer.feed` any chunk of bytes (one byte at a
time is fine), then call :meth:`Framer.next_payload` until it returns ``None``. Bytes that cannot
start a frame are skipped (counted in :attr:`Framer.skipped_bytes`). Something that started like a
frame but turns out broken (bad checksum, absurd length, a payload not starting with a CoLa command
type, a CoLa A frame cut by a new STX) is dropped first and then reported as :class:`FramingError`;
the next call continues with the bytes after the offending frame start, so a real telegram that
follows garbage is still found.
"""

from __future__ import annotations

import struct
from enum import Enum

import numpy as np

from drivers.lms100.errors import FramingError

STX = 0x02
ETX = 0x03
MAGIC = b"\x02\x02\x02\x02"
DEFAULT_MAX_PAYLOAD = 256 * 1024
"""Largest payload accepted (bytes). Real LMS/MRS telegrams stay below ~30 KB even in CoLa A."""

# The three letters every CoLa payload starts with (requests, replies, events, errors).
COMMAND_TYPES = frozenset(
    {b"sRN", b"sRA", b"sWN", b"sWA", b"sMN", b"sMA", b"sAN", b"sEN", b"sEA", b"sSN", b"sFA", b"sRI", b"sWI"}
)

_LEN = struct.Struct(">I")


class Dialect(str, Enum):  # noqa: UP042  (str mix-in kept on purpose: Dialect("a"), == "a")
    """CoLa dialect: A = ASCII (port 2111), B = binary (port 2112)."""

    A = "a"
    B = "b"


def xor_checksum(payload: bytes | bytearray | memoryview) -> int:
    """XOR of all bytes (the CoLa B checksum)."""
    n = len(payload)
    if n == 0:
        return 0
    arr = np.frombuffer(payload, dtype=np.uint8)
    head = n - n % 8
    acc = 0
    if head:
        word = int(np.bitwise_xor.reduce(arr[:head].view(np.uint64)))
        word ^= word >> 32
        word ^= word >> 16
        word ^= word >> 8
        acc = word & 0xFF
    for b in arr[head:].tolist():
        acc ^= b
    return acc


def frame(payload: bytes, dialect: Dialect) -> bytes:
    """Wrap one payload (``b"sRN LMDscandata"``...) in the dialect's frame."""
    if dialect is Dialect.A:
        if STX in payload or ETX in payload:
            raise FramingError("a CoLa A payload must not contain STX (0x02) or ETX (0x03)")
        return b"\x02" + payload + b"\x03"
    return MAGIC + _LEN.pack(len(payload)) + payload + bytes((xor_checksum(payload),))


class Framer:
    """Incremental frame parser for one dialect (see the module docstring)."""

    def __init__(self, dialect: Dialect, max_payload: int = DEFAULT_MAX_PAYLOAD) -> None:
        if max_payload < 4:
            raise ValueError("max_payload must be at least 4 bytes")
        self.dialect = Dialect(dialect)
        self.max_payload = max_payload
        self._buf = bytearray()
        self._pos = 0  # start of unconsumed data in _buf
        self._etx_from = -1  # CoLa A: where to continue looking for ETX in the current frame
        self.skipped_bytes = 0
        """Bytes dropped because they could not start a frame (garbage between telegrams)."""
        self.frames = 0
        """Payloads returned so far."""
        self.errors = 0
        """FramingErrors raised so far."""

    @property
    def buffered(self) -> int:
        """Bytes received but not yet returned or dropped."""
        return len(self._buf) - self._pos

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Add received bytes."""
        if self._pos and self._pos >= len(self._buf) // 2:
            del self._buf[: self._pos]
            if self._etx_from >= 0:
                self._etx_from -= self._pos
            self._pos = 0
        self._buf += data

    def next_payload(self) -> bytes | None:
        """The next complete payload, or ``None`` if more bytes are needed.

        Raises :class:`FramingError` for a broken frame, after dropping it.
        """
        if self.dialect is Dialect.B:
            return self._next_b()
        return self._next_a()

    # -- internals --------------------------------------------------------------------------
    def _fail(self, new_pos: int, message: str) -> FramingError:
        self._pos = new_pos
        self._etx_from = -1
        self.errors += 1
        return FramingError(message)

    def _skip_to(self, new_pos: int) -> None:
        self.skipped_bytes += new_pos - self._pos
        self._pos = new_pos

    def _next_b(self) -> bytes | None:
        buf = self._buf
        while True:
            start = buf.find(MAGIC, self._pos)
            if start < 0:
                # keep a possible partial magic at the end
                keep = len(buf)
                while keep > self._pos and keep > len(buf) - 3 and buf[keep - 1] == STX:
                    keep -= 1
                self._skip_to(keep)
                return None
            if start > self._pos:
                self._skip_to(start)
            avail = len(buf) - start
            if avail < 8:
                return None
            (length,) = _LEN.unpack_from(buf, start + 4)
            if length > self.max_payload or length < 3:
                raise self._fail(start + 1, f"CoLa B frame with absurd payload length {length}")
            if avail >= 11 and bytes(buf[start + 8 : start + 11]) not in COMMAND_TYPES:
                raise self._fail(
                    start + 1,
                    f"CoLa B payload does not start with a CoLa command type: {bytes(buf[start + 8 : start + 11])!r}",
                )
            end = start + 8 + length
            if len(buf) < end + 1:
                return None
            payload = bytes(buf[start + 8 : end])
            got = buf[end]
            want = xor_checksum(payload)
            if got != want:
                raise self._fail(
                    start + 1, f"CoLa B checksum mismatch: frame says 0x{got:02X}, payload XOR is 0x{want:02X}"
                )
            self._pos = end + 1
            self.frames += 1
            return payload

    def _next_a(self) -> bytes | None:
        buf = self._buf
        if self._etx_from < 0:
            start = buf.find(b"\x02", self._pos)
            if start < 0:
                self._skip_to(len(buf))
                return None
            if start > self._pos:
                self._skip_to(start)
            self._etx_from = start + 1
        start = self._pos
        if len(buf) - start >= 4 and bytes(buf[start + 1 : start + 4]) not in COMMAND_TYPES:
            raise self._fail(
                start + 1,
                f"CoLa A frame does not start with a CoLa command type: {bytes(buf[start + 1 : start + 4])!r}",
            )
        limit = min(len(buf), start + 2 + self.max_payload)
        etx = buf.find(b"\x03", self._etx_from, limit)
        stx = buf.find(b"\x02", self._etx_from, etx if etx >= 0 else limit)
        if stx >= 0:
            raise self._fail(stx, "CoLa A frame interrupted by a new STX before its ETX")
        if etx < 0:
            if limit < len(buf) or limit - start >= self.max_payload + 2:
                raise self._fail(limit, f"CoLa A frame longer than {self.max_payload} bytes without ETX")
            self._etx_from = limit
            return None
        payload = bytes(buf[start + 1 : etx])
        self._pos = etx + 1
        self._etx_from = -1
        self.frames += 1
        return payload
