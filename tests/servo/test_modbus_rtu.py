"""Modbus RTU codec: golden frames from the Modbus specifications, CRC vectors, round trips, fuzzing.

Golden PDUs are the worked examples of the Modbus Application Protocol Specification V1.1b3
(section 6.3 read holding registers 108..110, 6.6 write single register 1 = 3, 6.12 write multiple
registers 1..2 = 0x000A 0x0102, section 7 exception responses); the RTU frames add the unit address and
the CRC, low byte first. The CRC of ``11 03 00 6B 00 03`` = ``76 87`` is the classic example of the
serial-line guide; ``123456789`` -> 0x4B37 is the CRC-16/MODBUS check value of the CRC catalogue.
pymodbus's own framer gives an independent second opinion on every CRC.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.framer.rtu import FramerRTU

from drivers.errors import DriverError
from drivers.servo.modbus_rtu import (
    ExceptionCode,
    ModbusError,
    ModbusExceptionError,
    ModbusFrameError,
    ReadHoldingRegisters,
    ReadHoldingRegistersResponse,
    Request,
    RtuTiming,
    WriteMultipleRegisters,
    WriteMultipleRegistersResponse,
    WriteSingleRegister,
    WriteSingleRegisterResponse,
    crc16,
    decode_request,
    decode_response,
    encode_exception,
    encode_request,
    encode_response,
    request_frame_length,
    response_frame_length,
)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# ------------------------------------------------------------------------------------------- CRC
def test_crc_check_value_of_the_catalogue() -> None:
    assert crc16(b"123456789") == 0x4B37


def test_crc_of_empty_input_is_the_initial_value() -> None:
    assert crc16(b"") == 0xFFFF


def test_crc_classic_serial_line_examples_low_byte_first() -> None:
    # request: slave 0x11 reads 3 holding registers from 0x006B
    assert encode_request(0x11, ReadHoldingRegisters(0x006B, 3)) == h("11 03 00 6B 00 03 76 87")
    # its classic reply: 0xAE41 0x5652 0x4340
    frame = encode_response(0x11, ReadHoldingRegistersResponse((0xAE41, 0x5652, 0x4340)))
    assert frame == h("11 03 06 AE 41 56 52 43 40 49 AD")


@given(st.binary(max_size=256))
def test_crc_agrees_with_pymodbus(data: bytes) -> None:
    # pymodbus returns the CRC byte-swapped so that packing it big-endian gives the wire order
    assert struct.pack("<H", crc16(data)) == FramerRTU.compute_CRC(data).to_bytes(2, "big")


# ------------------------------------------------------------------------ golden request frames
GOLDEN_REQUESTS = [
    # spec 6.3: read registers 108..110 (address 0x006B, quantity 3), unit 1
    (1, ReadHoldingRegisters(0x006B, 3), "01 03 00 6B 00 03 74 17"),
    # spec 6.6: write register 2 (address 0x0001) = 0x0003, unit 1
    (1, WriteSingleRegister(0x0001, 0x0003), "01 06 00 01 00 03 98 0B"),
    # spec 6.12: write registers 2..3 (address 0x0001) = 0x000A 0x0102, unit 1
    (1, WriteMultipleRegisters(0x0001, (0x000A, 0x0102)), "01 10 00 01 00 02 04 00 0A 01 02 92 30"),
    # broadcast write of the controlword (CRC bytes taken from pymodbus's framer, an independent implementation)
    (0, WriteSingleRegister(0x6400, 0x0006), "00 06 64 00 00 06 17 29"),
]


@pytest.mark.parametrize(("unit", "request_", "wire"), GOLDEN_REQUESTS)
def test_golden_request_frames(unit: int, request_: ReadHoldingRegisters, wire: str) -> None:
    frame = encode_request(unit, request_)
    assert frame == h(wire)
    assert FramerRTU.compute_CRC(frame[:-2]).to_bytes(2, "big") == frame[-2:]
    assert decode_request(frame) == (unit, request_)
    assert request_frame_length(frame[:7]) == len(frame)


GOLDEN_RESPONSES = [
    (1, ReadHoldingRegisters(0x006B, 3), ReadHoldingRegistersResponse((0x022B, 0x0000, 0x0064)),
     "01 03 06 02 2B 00 00 00 64 05 7A"),
    (1, WriteSingleRegister(0x0001, 0x0003), WriteSingleRegisterResponse(0x0001, 0x0003), "01 06 00 01 00 03 98 0B"),
    (1, WriteMultipleRegisters(0x0001, (0x000A, 0x0102)), WriteMultipleRegistersResponse(0x0001, 2),
     "01 10 00 01 00 02 10 08"),
]  # fmt: skip


@pytest.mark.parametrize(("unit", "request_", "response", "wire"), GOLDEN_RESPONSES)
def test_golden_response_frames(unit: int, request_: ReadHoldingRegisters, response: object, wire: str) -> None:
    frame = encode_response(unit, response)  # type: ignore[arg-type]
    assert frame == h(wire)
    assert FramerRTU.compute_CRC(frame[:-2]).to_bytes(2, "big") == frame[-2:]
    assert decode_response(frame, unit, request_) == response
    assert response_frame_length(frame[:3]) == len(frame)


@pytest.mark.parametrize(
    ("function", "code", "wire"),
    [
        (0x03, ExceptionCode.ILLEGAL_DATA_ADDRESS, "01 83 02 C0 F1"),
        (0x06, ExceptionCode.ILLEGAL_DATA_VALUE, "01 86 03 02 61"),
        (0x10, ExceptionCode.SERVER_DEVICE_FAILURE, "01 90 04 4D C3"),
        (0x03, ExceptionCode.SERVER_DEVICE_BUSY, "01 83 06 C1 32"),
    ],
)
def test_golden_exception_responses_decode_to_typed_errors(function: int, code: int, wire: str) -> None:
    frame = encode_exception(1, function, code)
    assert frame == h(wire)
    assert FramerRTU.compute_CRC(frame[:-2]).to_bytes(2, "big") == frame[-2:]
    request = {
        0x03: ReadHoldingRegisters(0x6410, 1),
        0x06: WriteSingleRegister(0x6400, 6),
        0x10: WriteMultipleRegisters(0x67A0, (0, 1)),
    }[function]
    with pytest.raises(ModbusExceptionError) as info:
        decode_response(frame, 1, request)
    assert info.value.code == code
    assert info.value.exception_code == code
    assert info.value.function == function
    assert isinstance(info.value, DriverError)
    assert f"0x{code:02X}" in str(info.value)
    assert response_frame_length(frame[:2]) == 5


def test_exception_messages_say_what_went_wrong() -> None:
    err = ModbusExceptionError(3, 0x06, ExceptionCode.ILLEGAL_DATA_ADDRESS)
    assert "illegal data address" in str(err) and "unit 3" in str(err)
    unknown = ModbusExceptionError(3, 0x06, 0x42)
    assert unknown.exception_code is None and "unknown exception code" in str(unknown)


# ---------------------------------------------------------------------------- master-side checks
def test_reply_with_bad_crc_is_a_frame_error() -> None:
    frame = bytearray(h("01 03 06 02 2B 00 00 00 64 05 7A"))
    frame[-1] ^= 0x01
    with pytest.raises(ModbusFrameError, match="CRC"):
        decode_response(bytes(frame), 1, ReadHoldingRegisters(0x006B, 3))


def test_crc_sent_high_byte_first_is_rejected() -> None:
    frame = h("01 03 00 6B 00 03 17 74")  # the right CRC in the wrong byte order
    with pytest.raises(ModbusFrameError, match="CRC"):
        decode_request(frame)


def test_reply_from_another_unit_or_for_another_request_is_rejected() -> None:
    frame = encode_response(2, WriteSingleRegisterResponse(0x0001, 0x0003))
    with pytest.raises(ModbusFrameError, match="unit 2"):
        decode_response(frame, 1, WriteSingleRegister(0x0001, 0x0003))
    with pytest.raises(ModbusFrameError, match="echo"):
        decode_response(frame, 2, WriteSingleRegister(0x0001, 0x0004))
    with pytest.raises(ModbusFrameError, match="function"):
        decode_response(frame, 2, ReadHoldingRegisters(0x0001, 1))
    read = encode_response(1, ReadHoldingRegistersResponse((1, 2)))
    with pytest.raises(ModbusFrameError, match="expected 6"):
        decode_response(read, 1, ReadHoldingRegisters(0, 3))
    multi = encode_response(1, WriteMultipleRegistersResponse(0x10, 2))
    with pytest.raises(ModbusFrameError, match="differs"):
        decode_response(multi, 1, WriteMultipleRegisters(0x10, (1, 2, 3)))


# ----------------------------------------------------------------------------- slave-side checks
def test_unknown_function_is_an_illegal_function_exception_for_the_slave() -> None:
    frame = bytes([1, 0x2B, 0x0E, 0x01, 0x00])
    frame += struct.pack("<H", crc16(frame))
    with pytest.raises(ModbusExceptionError) as info:
        decode_request(frame)
    assert info.value.code == ExceptionCode.ILLEGAL_FUNCTION and info.value.function == 0x2B
    with pytest.raises(ModbusFrameError, match="unsupported function"):
        request_frame_length(frame[:2])


def test_read_quantity_out_of_range_is_illegal_data_value() -> None:
    body = h("01 03 00 00 00 7E")  # 126 registers
    with pytest.raises(ModbusExceptionError) as info:
        decode_request(body + struct.pack("<H", crc16(body)))
    assert info.value.code == ExceptionCode.ILLEGAL_DATA_VALUE


def test_write_multiple_with_inconsistent_byte_count_is_rejected() -> None:
    body = h("01 10 00 01 00 02 06 00 0A 01 02 00 00")  # byte count 6 for 2 registers
    with pytest.raises(ModbusExceptionError) as info:
        decode_request(body + struct.pack("<H", crc16(body)))
    assert info.value.code == ExceptionCode.ILLEGAL_DATA_VALUE
    body = h("01 10 00 01 00 02 04 00 0A 01")  # byte count 4, only 3 bytes
    with pytest.raises(ModbusFrameError, match="byte count"):
        decode_request(body + struct.pack("<H", crc16(body)))


def test_frame_length_needs_enough_head() -> None:
    assert request_frame_length(b"\x01") is None
    assert request_frame_length(h("01 10 00 01 00")) is None
    assert request_frame_length(h("01 10 00 01 00 02 04")) == 13
    assert response_frame_length(h("01 03")) is None
    assert response_frame_length(h("01 03 04")) == 9
    assert response_frame_length(h("01 10")) == 8


# ------------------------------------------------------------------------- argument validation
@pytest.mark.parametrize(
    "make",
    [
        lambda: ReadHoldingRegisters(0, 0),
        lambda: ReadHoldingRegisters(0, 126),
        lambda: ReadHoldingRegisters(0xFFFF, 2),
        lambda: ReadHoldingRegisters(-1, 1),
        lambda: WriteSingleRegister(0, 0x10000),
        lambda: WriteSingleRegister(0x10000, 0),
        lambda: WriteMultipleRegisters(0, ()),
        lambda: WriteMultipleRegisters(0, tuple(range(124))),
        lambda: WriteMultipleRegisters(0, (-1,)),
        lambda: encode_request(248, ReadHoldingRegisters(0, 1)),
        lambda: encode_request(0, ReadHoldingRegisters(0, 1)),
        lambda: encode_response(0, WriteSingleRegisterResponse(0, 0)),
        lambda: encode_exception(1, 0x83, 2),
        lambda: RtuTiming(0),
    ],
)
def test_bad_arguments_raise_typed_errors(make: object) -> None:
    with pytest.raises(ModbusError):
        make()  # type: ignore[operator]


def test_silent_intervals() -> None:
    slow = RtuTiming(9600)  # 11-bit characters: 1.1458 ms each
    assert slow.char_time == pytest.approx(11 / 9600)
    assert slow.t3_5 == pytest.approx(3.5 * 11 / 9600)
    assert slow.t1_5 == pytest.approx(1.5 * 11 / 9600)
    fast = RtuTiming.for_line(115200, parity="N")
    assert fast.bits_per_char == 10
    assert fast.t3_5 == pytest.approx(1.75e-3) and fast.t1_5 == pytest.approx(750e-6)
    assert fast.frame_time(8) == pytest.approx(80 / 115200)


# --------------------------------------------------------------------------- round trips, fuzz
units = st.integers(1, 247)
addresses = st.integers(0, 0xFFFF)
values = st.integers(0, 0xFFFF)


@st.composite
def requests(draw: st.DrawFn) -> Request:
    kind = draw(st.sampled_from(["read", "single", "multi"]))
    if kind == "read":
        count = draw(st.integers(1, 125))
        return ReadHoldingRegisters(draw(st.integers(0, 0x10000 - count)), count)
    if kind == "single":
        return WriteSingleRegister(draw(addresses), draw(values))
    vals = tuple(draw(st.lists(values, min_size=1, max_size=123)))
    return WriteMultipleRegisters(draw(st.integers(0, 0x10000 - len(vals))), vals)


@given(units, requests())
def test_request_round_trip(unit: int, request: ReadHoldingRegisters) -> None:
    frame = encode_request(unit, request)
    assert decode_request(frame) == (unit, request)
    assert request_frame_length(frame[: min(len(frame), 7)]) == len(frame)


@given(units, requests(), st.data())
def test_response_round_trip(unit: int, request: object, data: st.DataObject) -> None:
    response: ReadHoldingRegistersResponse | WriteSingleRegisterResponse | WriteMultipleRegistersResponse
    if isinstance(request, ReadHoldingRegisters):
        response = ReadHoldingRegistersResponse(
            tuple(data.draw(st.lists(values, min_size=request.count, max_size=request.count)))
        )
    elif isinstance(request, WriteSingleRegister):
        response = WriteSingleRegisterResponse(request.address, request.value)
    else:
        assert isinstance(request, WriteMultipleRegisters)
        response = WriteMultipleRegistersResponse(request.address, len(request.values))
    frame = encode_response(unit, response)
    assert decode_response(frame, unit, request) == response  # type: ignore[arg-type]
    assert response_frame_length(frame[:3]) == len(frame)


def _decodes_exactly_or_raises_typed_error(frame: bytes, request: Request) -> None:
    """Whatever ``frame`` is, decoding either gives a message that encodes back to the same bytes or
    raises the codec's :class:`ModbusError`; any other exception fails the test."""
    try:
        unit, decoded = decode_request(frame)
    except ModbusError:
        pass
    else:
        assert encode_request(unit, decoded) == frame
    try:
        response = decode_response(frame, frame[0] if frame else 1, request)
    except ModbusError:
        pass
    else:
        assert encode_response(frame[0], response) == frame
    for length in (request_frame_length, response_frame_length):
        try:
            n = length(frame)
        except ModbusFrameError:
            pass
        else:
            assert n is None or 4 <= n <= 256


@settings(max_examples=300)
@given(st.binary(max_size=300), requests())
def test_garbage_only_raises_the_codec_error(garbage: bytes, request: Request) -> None:
    _decodes_exactly_or_raises_typed_error(garbage, request)


@settings(max_examples=300)
@given(units, requests(), st.integers(0, 10_000), st.integers(1, 255))
def test_flipped_bytes_never_pass_silently(unit: int, request: Request, pos: int, xor: int) -> None:
    frame = bytearray(encode_request(unit, request))
    frame[pos % len(frame)] ^= xor
    # CRC-16 detects every error burst of up to 16 bits, so one corrupted byte is always caught
    with pytest.raises(ModbusFrameError):
        decode_request(bytes(frame))


@settings(max_examples=300)
@given(st.binary(min_size=1, max_size=250), units, requests())
def test_garbage_with_a_valid_crc_still_only_raises_typed_errors(body: bytes, unit: int, request: Request) -> None:
    frame = bytes([unit]) + body
    frame += struct.pack("<H", crc16(frame))
    _decodes_exactly_or_raises_typed_error(frame, request)
