"""Independent peer: pymodbus's serial client (its own framer, CRC and PDUs) drives our simulated Modbus drive.

It talks to the simulated drive over a real pseudo-terminal and over pyserial's ``socket://`` on loopback,
reads the statusword, writes the controlword and sees the CiA 402 state change, runs a profile-position
move, and gets Modbus exception responses for unmapped or half 32-bit registers. 32-bit values are
packed with pymodbus's own ``convert_to/from_registers`` (word order "big" = high word first, the default
map's order), so the word order is checked by an implementation that is not ours.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from pymodbus.client import ModbusSerialClient

from drivers.servo import cia402
from drivers.servo.cia402 import State
from drivers.servo.modbus_map import default_map
from sim.drive.modbus_server import ModbusDriveServer, start_from_url

MAP = default_map()
CW = MAP.entry(cia402.CONTROLWORD).address
SW = MAP.entry(cia402.STATUSWORD).address
UNIT = 5
I32 = ModbusSerialClient.DATATYPE.INT32
U32 = ModbusSerialClient.DATATYPE.UINT32


@pytest.fixture(params=["pty", "socket"])
def peer(request: pytest.FixtureRequest) -> Iterator[tuple[ModbusSerialClient, ModbusDriveServer]]:
    if request.param == "pty":
        server = start_from_url(f"modbus-rtu://?unit={UNIT}")
        port = server.url.removeprefix("modbus-rtu://").split("?")[0]
    else:
        server = start_from_url(f"modbus-rtu+socket://127.0.0.1:0?unit={UNIT}")
        port = "socket://" + server.url.removeprefix("modbus-rtu://").split("?")[0]
    # parity N: a pty cannot change parity after opening, and pymodbus reconfigures the port once. The timeout
    # bounds answers that must come (no test waits one out): generous for a busy machine
    client = ModbusSerialClient(port, baudrate=115200, parity="N", timeout=5.0, retries=1)
    try:
        assert client.connect(), f"pymodbus could not open {port}"
        yield client, server
    finally:
        client.close()
        server.close()


def read_u16(client: ModbusSerialClient, address: int) -> int:
    rr = client.read_holding_registers(address, count=1, device_id=UNIT)
    assert not rr.isError(), rr
    value: int = rr.registers[0]
    return value


def read_i32(client: ModbusSerialClient, address: int) -> int:
    rr = client.read_holding_registers(address, count=2, device_id=UNIT)
    assert not rr.isError(), rr
    value = client.convert_from_registers(rr.registers, I32)
    assert isinstance(value, int)
    return value


def write_32(client: ModbusSerialClient, index: int, value: int, dtype: object) -> None:
    regs = client.convert_to_registers(value, dtype)  # type: ignore[arg-type]
    wr = client.write_registers(MAP.entry(index).address, regs, device_id=UNIT)
    assert not wr.isError(), wr


def write_cw(client: ModbusSerialClient, value: int) -> None:
    wr = client.write_register(CW, value, device_id=UNIT)
    assert not wr.isError(), wr
    assert wr.registers == [value]  # the echo


def wait_sw(client: ModbusSerialClient, predicate: object, timeout: float = 10.0) -> int:
    deadline = time.monotonic() + timeout
    while True:
        sw = read_u16(client, SW)
        if predicate(sw):  # type: ignore[operator]
            return sw
        assert time.monotonic() < deadline, f"statusword stuck at 0x{sw:04X}"
        time.sleep(0.005)


def test_pymodbus_walks_the_state_machine(peer: tuple[ModbusSerialClient, ModbusDriveServer]) -> None:
    client, server = peer
    assert cia402.decode_state(read_u16(client, SW)) is State.SWITCH_ON_DISABLED
    for command, state in (
        (0x06, State.READY_TO_SWITCH_ON),
        (0x07, State.SWITCHED_ON),
        (0x0F, State.OPERATION_ENABLED),
    ):
        write_cw(client, command)
        assert cia402.decode_state(read_u16(client, SW)) is state
        assert server.drive.state is state
    write_cw(client, 0x0000)  # disable voltage
    assert cia402.decode_state(read_u16(client, SW)) is State.SWITCH_ON_DISABLED


def test_pymodbus_runs_a_profile_position_move(peer: tuple[ModbusSerialClient, ModbusDriveServer]) -> None:
    client, server = peer
    for command in (0x06, 0x07, 0x0F):
        write_cw(client, command)
    assert client.write_register(MAP.entry(cia402.MODES_OF_OPERATION).address, 1, device_id=UNIT).registers == [1]
    assert read_u16(client, MAP.entry(cia402.MODES_OF_OPERATION_DISPLAY).address) == 1
    write_32(client, cia402.PROFILE_VELOCITY, 400_000, U32)
    write_32(client, cia402.PROFILE_ACCELERATION, 4_000_000, U32)
    write_32(client, cia402.PROFILE_DECELERATION, 4_000_000, U32)
    write_32(client, cia402.TARGET_POSITION, -120_000, I32)
    assert server.drive.read(cia402.TARGET_POSITION) == -120_000  # pymodbus's high-word-first packing agrees
    write_cw(client, 0x1F)  # new set-point
    wait_sw(client, lambda sw: sw & cia402.SW_SET_POINT_ACK)
    write_cw(client, 0x0F)
    sw = wait_sw(client, lambda sw: sw & cia402.SW_TARGET_REACHED)
    assert cia402.decode_state(sw) is State.OPERATION_ENABLED
    position = read_i32(client, MAP.entry(cia402.POSITION_ACTUAL).address)
    window = server.drive.read(cia402.POSITION_WINDOW)
    assert abs(position + 120_000) <= window
    # the sample block: statusword, error code, position, velocity in one read
    assert MAP.sample is not None
    rr = client.read_holding_registers(MAP.sample.address, count=MAP.sample.count, device_id=UNIT)
    assert not rr.isError()
    assert rr.registers[0] & cia402.SW_TARGET_REACHED and rr.registers[1] == 0
    assert abs(client.convert_from_registers(rr.registers[2:4], I32) + 120_000) <= window


def test_pymodbus_sees_fault_code_and_resets(peer: tuple[ModbusSerialClient, ModbusDriveServer]) -> None:
    client, server = peer
    for command in (0x06, 0x07, 0x0F):
        write_cw(client, command)
    server.drive.inject_fault("over_current")
    wait_sw(client, lambda sw: cia402.decode_state(sw) is State.FAULT)
    assert read_u16(client, MAP.entry(cia402.ERROR_CODE).address) == cia402.ERR_OVER_CURRENT
    write_cw(client, 0x0000)
    write_cw(client, 0x0080)  # rising edge of fault reset
    assert cia402.decode_state(read_u16(client, SW)) is State.SWITCH_ON_DISABLED
    assert read_u16(client, MAP.entry(cia402.ERROR_CODE).address) == 0


def test_pymodbus_gets_exception_responses(peer: tuple[ModbusSerialClient, ModbusDriveServer]) -> None:
    client, server = peer
    rr = client.read_holding_registers(0x0000, count=1, device_id=UNIT)
    assert rr.isError() and rr.exception_code == 2  # unmapped
    rr = client.read_holding_registers(MAP.entry(cia402.POSITION_ACTUAL).address + 1, count=1, device_id=UNIT)
    assert rr.isError() and rr.exception_code == 2  # half of a 32-bit object
    wr = client.write_register(SW, 0, device_id=UNIT)
    assert wr.isError() and wr.exception_code == 2  # read-only
    wr = client.write_register(MAP.entry(cia402.MODES_OF_OPERATION).address, 2, device_id=UNIT)
    assert wr.isError() and wr.exception_code == 3  # mode 2 (vl) not supported by the drive
    assert server.stats.exceptions == 4
