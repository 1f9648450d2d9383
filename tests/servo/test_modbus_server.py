"""The simulated Modbus drive's slave logic: the sans-I/O frame handler, and its byte-stream framing on a pty."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.servo import cia402
from drivers.servo.cia402 import State
from drivers.servo.modbus_map import default_map, load_map
from drivers.servo.modbus_rtu import (
    ModbusExceptionError,
    ReadHoldingRegisters,
    ReadHoldingRegistersResponse,
    WriteMultipleRegisters,
    WriteSingleRegister,
    crc16,
    decode_response,
    encode_exception,
    encode_request,
    response_frame_length,
)
from sim.drive.modbus_server import ModbusDriveServer, exception_for_abort, start_from_url
from sim.drive.model import SimDrive

MAP = default_map()


def frozen_server(unit: int = 1) -> ModbusDriveServer:
    return ModbusDriveServer(SimDrive(clock=lambda: 0.0), MAP, unit=unit)


def ask(
    server: ModbusDriveServer, request: ReadHoldingRegisters | WriteSingleRegister | WriteMultipleRegisters
) -> object:
    reply = server.handle_frame(encode_request(server.unit, request))
    assert reply is not None
    return decode_response(reply, server.unit, request)


def test_read_and_write_through_the_map() -> None:
    srv = frozen_server()
    sw = ask(srv, ReadHoldingRegisters(MAP.entry(cia402.STATUSWORD).address, 1))
    assert isinstance(sw, ReadHoldingRegistersResponse)
    assert cia402.decode_state(sw.values[0]) is State.SWITCH_ON_DISABLED
    ask(srv, WriteSingleRegister(MAP.entry(cia402.CONTROLWORD).address, cia402.CMD_SHUTDOWN))
    assert srv.drive.state is State.READY_TO_SWITCH_ON
    ask(srv, WriteMultipleRegisters(MAP.entry(cia402.TARGET_POSITION).address, MAP.encode(MAP.entry(0x607A), -7)))
    assert srv.drive.read(cia402.TARGET_POSITION) == -7


def test_other_units_are_ignored_and_broadcasts_applied_silently() -> None:
    srv = frozen_server(unit=3)
    assert srv.handle_frame(encode_request(4, ReadHoldingRegisters(0x6410, 1))) is None
    assert srv.stats.other_unit == 1
    assert srv.handle_frame(encode_request(0, WriteSingleRegister(0x6400, cia402.CMD_SHUTDOWN))) is None
    assert srv.drive.state is State.READY_TO_SWITCH_ON
    # a refused broadcast stays silent too
    assert srv.handle_frame(encode_request(0, WriteSingleRegister(0x6410, 0))) is None


def test_multi_register_write_is_validated_as_a_whole(tmp_path: Path) -> None:
    path = tmp_path / "packed.toml"
    path.write_text(
        """
[[register]]
name = "target_position"
index = 0x607A
address = 0x0010
type = "i32"
[[register]]
name = "homing_method"
index = 0x6098
address = 0x0012
type = "i8"
"""
    )
    srv = ModbusDriveServer(SimDrive(clock=lambda: 0.0), load_map(path))
    with pytest.raises(ModbusExceptionError) as exc:
        ask(srv, WriteMultipleRegisters(0x0010, (0, 1000, 0x0100)))  # 256 does not fit the i8
    assert exc.value.code == 3
    assert srv.drive.read(cia402.TARGET_POSITION) == 0  # nothing was written
    ask(srv, WriteMultipleRegisters(0x0010, (0, 1000, 35)))
    assert srv.drive.read(cia402.TARGET_POSITION) == 1000
    assert srv.drive.read(cia402.HOMING_METHOD) == 35


def test_abort_codes_map_to_exception_codes() -> None:
    assert exception_for_abort(cia402.ABORT_NO_OBJECT) == 2
    assert exception_for_abort(cia402.ABORT_READ_ONLY) == 2
    assert exception_for_abort(cia402.ABORT_VALUE_TOO_HIGH) == 3
    assert exception_for_abort(cia402.ABORT_DEVICE_STATE) == 4


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=40))
def test_garbage_never_crashes_the_slave(data: bytes) -> None:
    srv = frozen_server()
    reply = srv.handle_frame(data)
    assert reply is None or response_frame_length(reply) == len(reply)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from([e.address for e in MAP.entries] + [0x5000, 0x0000, 0x6401]),
    st.integers(1, 8),
    st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=6),
    st.sampled_from(["read", "single", "multi"]),
)
def test_any_well_formed_request_gets_a_reply_or_an_exception(address: int, count: int, values: list[int],
                                                               kind: str) -> None:  # fmt: skip
    srv = frozen_server()
    request: ReadHoldingRegisters | WriteSingleRegister | WriteMultipleRegisters
    if kind == "read":
        request = ReadHoldingRegisters(address, count)
    elif kind == "single":
        request = WriteSingleRegister(address, values[0])
    else:
        request = WriteMultipleRegisters(address, tuple(values))
    try:
        ask(srv, request)
    except ModbusExceptionError as exc:
        assert exc.code in (2, 3, 4)
    assert srv.stats.replies + srv.stats.exceptions == 1


# ------------------------------------------------------------------------------ stream framing
@pytest.fixture
def pty_port() -> Iterator[tuple[serial.SerialBase, ModbusDriveServer]]:
    srv = start_from_url("modbus-rtu://")
    path = srv.url.removeprefix("modbus-rtu://").split("?")[0]
    port = serial.serial_for_url(path, baudrate=115200, timeout=10.0)  # reads return once the bytes are in
    try:
        yield port, srv
    finally:
        port.close()
        srv.close()


def read_status(port: serial.SerialBase) -> int:
    request = ReadHoldingRegisters(0x6410, 1)
    port.write(encode_request(1, request))
    reply = decode_response(port.read(7), 1, request)
    assert isinstance(reply, ReadHoldingRegistersResponse)
    return reply.values[0]


def test_a_request_trickling_in_byte_by_byte_is_served(pty_port: tuple[serial.SerialBase, ModbusDriveServer]) -> None:
    port, srv = pty_port
    srv._frame_gap = 1.0  # a loaded machine may stall this writer longer than the default 20 ms
    frame = encode_request(1, WriteSingleRegister(0x6400, cia402.CMD_SHUTDOWN))
    for b in frame:
        port.write(bytes([b]))
        port.flush()
        time.sleep(0.001)
    assert port.read(8) == frame  # the echo of a write-single
    assert srv.drive.state is State.READY_TO_SWITCH_ON


def test_back_to_back_requests_and_an_abandoned_frame(pty_port: tuple[serial.SerialBase, ModbusDriveServer]) -> None:
    port, srv = pty_port
    a = encode_request(1, WriteSingleRegister(0x6400, cia402.CMD_SHUTDOWN))
    b = encode_request(1, WriteSingleRegister(0x6400, cia402.CMD_SWITCH_ON))
    port.write(a + b)
    assert port.read(16) == a + b
    assert srv.drive.state is State.SWITCHED_ON
    port.write(b[:5])  # the master gives up half-way
    # the slave closes the abandoned frame after its silent interval: wait for that before the next request
    # (a slave thread stalled on a busy machine would otherwise read both in one go, with no silence between)
    deadline = time.monotonic() + 10.0
    while srv.stats.incomplete < 1:
        assert time.monotonic() < deadline, "the abandoned frame was never closed"
        time.sleep(0.005)
    port.timeout = 0.1
    assert port.read(1) == b""
    port.timeout = 10.0
    assert cia402.decode_state(read_status(port)) is State.SWITCHED_ON
    assert srv.stats.incomplete == 1


def test_a_corrupted_frame_does_not_swallow_the_next(pty_port: tuple[serial.SerialBase, ModbusDriveServer]) -> None:
    port, srv = pty_port
    good = encode_request(1, WriteSingleRegister(0x6400, cia402.CMD_SHUTDOWN))
    bad = good[:-1] + bytes([good[-1] ^ 0x55])
    port.write(bad + good)  # in one write: the slave drops the first and answers the second
    assert port.read(8) == good
    assert srv.stats.crc_errors == 1 and srv.stats.replies == 1


def test_unknown_function_is_closed_by_the_silent_interval(
    pty_port: tuple[serial.SerialBase, ModbusDriveServer],
) -> None:
    port, srv = pty_port
    body = bytes([1, 0x41, 1, 2, 3, 4, 5, 6, 7, 8, 9])  # a function the codec cannot size
    port.write(body + crc16(body).to_bytes(2, "little"))
    assert port.read(5) == encode_exception(1, 0x41, 1)  # exception 01, illegal function
    assert srv.stats.exceptions == 1


def test_serve_forever_returns_when_closed() -> None:
    srv = start_from_url("modbus-rtu+socket://127.0.0.1:0")
    done = threading.Event()

    def run() -> None:
        srv.serve_forever()
        done.set()

    threading.Thread(target=run, daemon=True).start()
    srv.close()
    assert done.wait(10.0)
