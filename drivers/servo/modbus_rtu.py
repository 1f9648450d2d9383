"""Modbus RTU codec, sans I/O: CRC-16/MODBUS, RTU framing and the PDUs of function codes 03, 06 and 16.

Nothing here touches a port or a clock. The transport (:mod:`drivers.servo.modbus_backend` on the
master side, :mod:`sim.drive.modbus_server` on the slave side) moves bytes and applies the timing
that :class:`RtuTiming` computes; this module turns bytes into typed requests and responses and
back, and raises :class:`ModbusFrameError` for anything that is not a valid frame.

Frame layout (Modbus over Serial Line V1.02, section 2.5.1)::

    +-----------+----------+----------------------+-------------------+
    | address   | function | data                 | CRC               |
    | 1 byte    | 1 byte   | 0..252 bytes         | 2 bytes, LOW first|
    +-----------+----------+----------------------+-------------------+

Register values and addresses inside the PDU are big-endian (high byte first); only the CRC is sent
low byte first. Unit address 0 is broadcast (writes only, no reply), 1..247 are slaves.

PDUs (Modbus Application Protocol V1.1b3, section 6):

===========================  ==============================================  =====================================
function                     request data                                    normal response data
===========================  ==============================================  =====================================
0x03 read holding registers  address u16, quantity u16 (1..125)              byte count u8 (= 2 n), n values u16
0x06 write single register   address u16, value u16                          echo of the request
0x10 write multiple regs     address u16, quantity u16 (1..123),             address u16, quantity u16
                             byte count u8 (= 2 n), n values u16
===========================  ==============================================  =====================================

An exception response has the function code with bit 7 set and one byte exception code.

Silent intervals: a frame is delimited by at least 3.5 character times of silence, and characters
inside a frame may not be separated by more than 1.5 character times. Above 19200 baud the spec fixes
these at 750 µs and 1.75 ms. :class:`RtuTiming` gives both as timeouts for the transport.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Final

from drivers.errors import DriverError

__all__ = [
    "BROADCAST",
    "MAX_READ_COUNT",
    "MAX_WRITE_COUNT",
    "ExceptionCode",
    "FunctionCode",
    "ModbusError",
    "ModbusExceptionError",
    "ModbusFrameError",
    "ReadHoldingRegisters",
    "ReadHoldingRegistersResponse",
    "Request",
    "Response",
    "RtuTiming",
    "WriteMultipleRegisters",
    "WriteMultipleRegistersResponse",
    "WriteSingleRegister",
    "WriteSingleRegisterResponse",
    "crc16",
    "decode_request",
    "decode_response",
    "encode_exception",
    "encode_request",
    "encode_response",
    "request_frame_length",
    "response_frame_length",
]

BROADCAST: Final = 0
MAX_UNIT: Final = 247
MAX_READ_COUNT: Final = 125
MAX_WRITE_COUNT: Final = 123
MAX_FRAME: Final = 256


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------
class ModbusError(DriverError):
    """Base class of every Modbus error."""


class ModbusFrameError(ModbusError):
    """Bytes that are not a valid Modbus RTU frame (bad CRC, wrong length, unknown function, bad field)."""


class ExceptionCode(IntEnum):
    """Modbus exception codes (Application Protocol V1.1b3, section 7)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    ACKNOWLEDGE = 0x05
    SERVER_DEVICE_BUSY = 0x06
    MEMORY_PARITY_ERROR = 0x08
    GATEWAY_PATH_UNAVAILABLE = 0x0A
    GATEWAY_TARGET_FAILED_TO_RESPOND = 0x0B


_EXCEPTION_TEXT: Final = {
    ExceptionCode.ILLEGAL_FUNCTION: "illegal function: the slave does not support this function code",
    ExceptionCode.ILLEGAL_DATA_ADDRESS: "illegal data address: the register range is not mapped (or splits a "
    "32-bit object)",
    ExceptionCode.ILLEGAL_DATA_VALUE: "illegal data value: the value or quantity is not allowed",
    ExceptionCode.SERVER_DEVICE_FAILURE: "server device failure: the slave failed while performing the action",
    ExceptionCode.ACKNOWLEDGE: "acknowledge: request accepted, processing takes long",
    ExceptionCode.SERVER_DEVICE_BUSY: "server device busy: retry later",
    ExceptionCode.MEMORY_PARITY_ERROR: "memory parity error",
    ExceptionCode.GATEWAY_PATH_UNAVAILABLE: "gateway path unavailable",
    ExceptionCode.GATEWAY_TARGET_FAILED_TO_RESPOND: "gateway target device failed to respond",
}


class ModbusExceptionError(ModbusError):
    """The slave answered with a Modbus exception response."""

    def __init__(self, unit: int, function: int, code: int) -> None:
        self.unit = unit
        self.function = function
        self.code = code
        try:
            text = _EXCEPTION_TEXT[ExceptionCode(code)]
        except ValueError:
            text = "unknown exception code"
        super().__init__(f"Modbus exception 0x{code:02X} from unit {unit} for function 0x{function:02X}: {text}")

    @property
    def exception_code(self) -> ExceptionCode | None:
        try:
            return ExceptionCode(self.code)
        except ValueError:
            return None


class FunctionCode(IntEnum):
    READ_HOLDING_REGISTERS = 0x03
    WRITE_SINGLE_REGISTER = 0x06
    WRITE_MULTIPLE_REGISTERS = 0x10


# --------------------------------------------------------------------------------------------
# CRC-16/MODBUS: reflected polynomial 0xA001 (0x8005), initial value 0xFFFF, no final XOR
# --------------------------------------------------------------------------------------------
def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _make_table()


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS of ``data``; sent on the wire low byte first."""
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in bytes(data):
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def _with_crc(body: bytes) -> bytes:
    return body + struct.pack("<H", crc16(body))


def _check_crc(frame: bytes) -> None:
    if len(frame) < 4:
        raise ModbusFrameError(f"frame of {len(frame)} bytes is too short (minimum 4: address, function, CRC)")
    if len(frame) > MAX_FRAME:
        raise ModbusFrameError(f"frame of {len(frame)} bytes is longer than the RTU maximum of {MAX_FRAME}")
    (received,) = struct.unpack_from("<H", frame, len(frame) - 2)
    computed = crc16(frame[:-2])
    if received != computed:
        raise ModbusFrameError(f"CRC mismatch: frame carries 0x{received:04X}, computed 0x{computed:04X}")


# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RtuTiming:
    """Character time and the RTU silent intervals for a serial line setting.

    One RTU character is start bit + 8 data bits + parity bit (or a second stop bit) + stop bit =
    11 bits, the default (8E1 is the Modbus default line setting). :meth:`for_line` counts the bits
    of another setting (8N1 = 10). Above 19200 baud the spec fixes t1.5 and t3.5 instead.
    """

    baudrate: int
    bits_per_char: int = 11

    def __post_init__(self) -> None:
        if self.baudrate <= 0:
            raise ModbusError(f"baud rate must be positive, got {self.baudrate}")
        if not 10 <= self.bits_per_char <= 12:
            raise ModbusError(f"bits per character must be 10..12, got {self.bits_per_char}")

    @classmethod
    def for_line(cls, baudrate: int, parity: str = "E", stopbits: float = 1) -> RtuTiming:
        bits = 1 + 8 + (0 if parity.upper() == "N" else 1) + (2 if stopbits == 2 else 1)
        return cls(baudrate=baudrate, bits_per_char=bits)

    @property
    def char_time(self) -> float:
        """Seconds per character on the wire."""
        return self.bits_per_char / self.baudrate

    @property
    def t1_5(self) -> float:
        """Longest allowed gap between two characters of one frame (seconds)."""
        return 750e-6 if self.baudrate > 19200 else 1.5 * self.char_time

    @property
    def t3_5(self) -> float:
        """Silent interval that ends a frame and must precede the next one (seconds)."""
        return 1.75e-3 if self.baudrate > 19200 else 3.5 * self.char_time

    def frame_time(self, n_bytes: int) -> float:
        """Wire time of a frame of ``n_bytes`` (seconds), without the silent intervals."""
        return n_bytes * self.char_time


# --------------------------------------------------------------------------------------------
# PDUs
# --------------------------------------------------------------------------------------------
def _check_u16(name: str, value: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= 0xFFFF:
        raise ModbusError(f"{name} must be an integer 0..65535, got {value!r}")


def _check_unit(unit: int, *, allow_broadcast: bool) -> None:
    lo = BROADCAST if allow_broadcast else 1
    if not isinstance(unit, int) or isinstance(unit, bool) or not lo <= unit <= MAX_UNIT:
        raise ModbusError(f"unit address must be {lo}..{MAX_UNIT}, got {unit!r}")


def _check_quantity(kind: str, count: int, maximum: int) -> None:
    if not isinstance(count, int) or not 1 <= count <= maximum:
        raise ModbusError(f"{kind} quantity must be 1..{maximum}, got {count!r}")


def _check_span(address: int, count: int) -> None:
    if address + count > 0x10000:
        raise ModbusError(f"register range 0x{address:04X} + {count} runs past 0xFFFF")


@dataclass(frozen=True)
class ReadHoldingRegisters:
    address: int
    count: int
    function: int = FunctionCode.READ_HOLDING_REGISTERS

    def __post_init__(self) -> None:
        _check_u16("address", self.address)
        _check_quantity("read", self.count, MAX_READ_COUNT)
        _check_span(self.address, self.count)

    def pdu(self) -> bytes:
        return struct.pack(">BHH", self.function, self.address, self.count)


@dataclass(frozen=True)
class _SingleRegister:
    """FC 06 layout: one register address and its value (the response echoes the request)."""

    address: int
    value: int
    function: int = FunctionCode.WRITE_SINGLE_REGISTER

    def __post_init__(self) -> None:
        _check_u16("address", self.address)
        _check_u16("value", self.value)

    def pdu(self) -> bytes:
        return struct.pack(">BHH", self.function, self.address, self.value)


@dataclass(frozen=True)
class WriteSingleRegister(_SingleRegister):
    """FC 06 request: write ``value`` to the register at ``address``."""


@dataclass(frozen=True)
class WriteMultipleRegisters:
    address: int
    values: tuple[int, ...]
    function: int = FunctionCode.WRITE_MULTIPLE_REGISTERS

    def __post_init__(self) -> None:
        _check_u16("address", self.address)
        object.__setattr__(self, "values", tuple(self.values))
        _check_quantity("write", len(self.values), MAX_WRITE_COUNT)
        for v in self.values:
            _check_u16("register value", v)
        _check_span(self.address, len(self.values))

    def pdu(self) -> bytes:
        n = len(self.values)
        return struct.pack(f">BHHB{n}H", self.function, self.address, n, 2 * n, *self.values)


@dataclass(frozen=True)
class ReadHoldingRegistersResponse:
    values: tuple[int, ...]
    function: int = FunctionCode.READ_HOLDING_REGISTERS

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", tuple(self.values))
        if not 1 <= len(self.values) <= MAX_READ_COUNT:
            raise ModbusError(f"read response must carry 1..{MAX_READ_COUNT} registers, got {len(self.values)}")
        for v in self.values:
            _check_u16("register value", v)

    def pdu(self) -> bytes:
        n = len(self.values)
        return struct.pack(f">BB{n}H", self.function, 2 * n, *self.values)


@dataclass(frozen=True)
class WriteSingleRegisterResponse(_SingleRegister):
    """FC 06 response: the request echoed."""


@dataclass(frozen=True)
class WriteMultipleRegistersResponse:
    address: int
    count: int
    function: int = FunctionCode.WRITE_MULTIPLE_REGISTERS

    def __post_init__(self) -> None:
        _check_u16("address", self.address)
        _check_quantity("write", self.count, MAX_WRITE_COUNT)
        _check_span(self.address, self.count)

    def pdu(self) -> bytes:
        return struct.pack(">BHH", self.function, self.address, self.count)


Request = ReadHoldingRegisters | WriteSingleRegister | WriteMultipleRegisters
Response = ReadHoldingRegistersResponse | WriteSingleRegisterResponse | WriteMultipleRegistersResponse


# --------------------------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------------------------
def encode_request(unit: int, request: Request) -> bytes:
    """The complete RTU frame (address, PDU, CRC) of a request. ``unit`` 0 broadcasts (writes only)."""
    _check_unit(unit, allow_broadcast=True)
    if unit == BROADCAST and isinstance(request, ReadHoldingRegisters):
        raise ModbusError("a read cannot be broadcast (unit 0): nobody would answer")
    return _with_crc(bytes([unit]) + request.pdu())


def encode_response(unit: int, response: Response) -> bytes:
    """The complete RTU frame of a normal response from slave ``unit``."""
    _check_unit(unit, allow_broadcast=False)
    return _with_crc(bytes([unit]) + response.pdu())


def encode_exception(unit: int, function: int, code: int) -> bytes:
    """The complete RTU frame of an exception response (function | 0x80, exception code)."""
    _check_unit(unit, allow_broadcast=False)
    if not 1 <= function <= 0x7F:
        raise ModbusError(f"function code must be 1..127, got {function}")
    if not 1 <= code <= 0xFF:
        raise ModbusError(f"exception code must be 1..255, got {code}")
    return _with_crc(bytes([unit, function | 0x80, code]))


# --------------------------------------------------------------------------------------------
# Frame lengths (so that a transport can read exactly one frame without waiting for silence)
# --------------------------------------------------------------------------------------------
def request_frame_length(head: bytes) -> int | None:
    """Total length of the request frame that starts with ``head``, or None if more bytes are needed.

    Raises :class:`ModbusFrameError` for a function code this codec does not know; the transport
    then falls back to the 3.5-character silent interval to find the end of the frame.
    """
    if len(head) < 2:
        return None
    function = head[1]
    if function in (FunctionCode.READ_HOLDING_REGISTERS, FunctionCode.WRITE_SINGLE_REGISTER):
        return 8
    if function == FunctionCode.WRITE_MULTIPLE_REGISTERS:
        if len(head) < 7:
            return None
        return 9 + head[6]
    raise ModbusFrameError(f"unsupported function code 0x{function:02X} in request")


def response_frame_length(head: bytes) -> int | None:
    """Total length of the response frame that starts with ``head``, or None if more bytes are needed."""
    if len(head) < 2:
        return None
    function = head[1]
    if function & 0x80:
        return 5
    if function == FunctionCode.READ_HOLDING_REGISTERS:
        if len(head) < 3:
            return None
        return 5 + head[2]
    if function in (FunctionCode.WRITE_SINGLE_REGISTER, FunctionCode.WRITE_MULTIPLE_REGISTERS):
        return 8
    raise ModbusFrameError(f"unsupported function code 0x{function:02X} in response")


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------
def decode_request(frame: bytes) -> tuple[int, Request]:
    """Parse a request frame (slave side): ``(unit, request)``.

    Raises :class:`ModbusFrameError` for a bad CRC or malformed frame, and :class:`ModbusExceptionError`
    (with the code the slave should answer) for a well-formed frame it cannot serve: an unknown
    function code (01) or a quantity out of range (03).
    """
    frame = bytes(frame)
    _check_crc(frame)
    unit, function = frame[0], frame[1]
    if unit > MAX_UNIT:
        raise ModbusFrameError(f"unit address {unit} is reserved (valid 0..{MAX_UNIT})")
    data = frame[2:-2]
    if function == FunctionCode.READ_HOLDING_REGISTERS:
        if len(data) != 4:
            raise ModbusFrameError(f"read request carries {len(data)} data bytes, expected 4")
        address, count = struct.unpack(">HH", data)
        if not 1 <= count <= MAX_READ_COUNT or address + count > 0x10000:
            raise ModbusExceptionError(unit, function, ExceptionCode.ILLEGAL_DATA_VALUE)
        return unit, ReadHoldingRegisters(address, count)
    if function == FunctionCode.WRITE_SINGLE_REGISTER:
        if len(data) != 4:
            raise ModbusFrameError(f"write-single request carries {len(data)} data bytes, expected 4")
        address, value = struct.unpack(">HH", data)
        return unit, WriteSingleRegister(address, value)
    if function == FunctionCode.WRITE_MULTIPLE_REGISTERS:
        if len(data) < 5:
            raise ModbusFrameError(f"write-multiple request carries {len(data)} data bytes, expected >= 5")
        address, count, nbytes = struct.unpack_from(">HHB", data)
        if len(data) != 5 + nbytes:
            raise ModbusFrameError(f"write-multiple byte count {nbytes} does not match {len(data) - 5} data bytes")
        if not 1 <= count <= MAX_WRITE_COUNT or nbytes != 2 * count or address + count > 0x10000:
            raise ModbusExceptionError(unit, function, ExceptionCode.ILLEGAL_DATA_VALUE)
        values = struct.unpack_from(f">{count}H", data, 5)
        return unit, WriteMultipleRegisters(address, values)
    raise ModbusExceptionError(unit, function & 0x7F, ExceptionCode.ILLEGAL_FUNCTION)


def decode_response(frame: bytes, unit: int, request: Request) -> Response:
    """Parse the reply to ``request`` sent to ``unit`` (master side) and check that it matches.

    Raises :class:`ModbusExceptionError` for an exception response and :class:`ModbusFrameError`
    for a bad CRC, a reply from another unit, or a reply that does not answer ``request``.
    """
    _check_unit(unit, allow_broadcast=False)
    frame = bytes(frame)
    _check_crc(frame)
    if frame[0] != unit:
        raise ModbusFrameError(f"reply from unit {frame[0]}, expected unit {unit}")
    function = frame[1]
    data = frame[2:-2]
    if function == request.function | 0x80:
        if len(data) != 1:
            raise ModbusFrameError(f"exception response carries {len(data)} data bytes, expected 1")
        raise ModbusExceptionError(unit, request.function, data[0])
    if function != request.function:
        raise ModbusFrameError(f"reply has function 0x{function:02X}, request had 0x{request.function:02X}")
    if isinstance(request, ReadHoldingRegisters):
        if len(data) < 1 or data[0] != len(data) - 1:
            raise ModbusFrameError("read response byte count does not match its length")
        if data[0] != 2 * request.count:
            raise ModbusFrameError(f"read response carries {data[0]} bytes, expected {2 * request.count}")
        return ReadHoldingRegistersResponse(struct.unpack_from(f">{request.count}H", data, 1))
    if len(data) != 4:
        raise ModbusFrameError(f"write response carries {len(data)} data bytes, expected 4")
    address, second = struct.unpack(">HH", data)
    if isinstance(request, WriteSingleRegister):
        if (address, second) != (request.address, request.value):
            raise ModbusFrameError(
                f"write-single echo 0x{address:04X}=0x{second:04X} differs from request "
                f"0x{request.address:04X}=0x{request.value:04X}"
            )
        return WriteSingleRegisterResponse(address, second)
    if (address, second) != (request.address, len(request.values)):
        raise ModbusFrameError(
            f"write-multiple reply 0x{address:04X}+{second} differs from request "
            f"0x{request.address:04X}+{len(request.values)}"
        )
    return WriteMultipleRegistersResponse(address, second)
