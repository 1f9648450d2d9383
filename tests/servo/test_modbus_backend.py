"""Our Modbus RTU backend against our simulated Modbus drive over a real pseudo-terminal (and loopback TCP).

The simulated drive (sim.drive.model.SimDrive behind sim.drive.modbus_server) runs in a thread of the test
process and holds the master side of an ``os.openpty`` pair; the backend opens the slave device
(/dev/pts/N) with pyserial, exactly as it would open /dev/ttyUSB0.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import serial

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, DeviceURLError, DriverError
from drivers.servo import cia402
from drivers.servo.cia402 import State
from drivers.servo.interface import DriveConfig, HeartbeatLost, MotorFault, MotorStateError
from drivers.servo.modbus_backend import ModbusMotor, ModbusRtuClient, ModbusTimeoutError, open_url
from drivers.servo.modbus_map import ModbusMapError, default_map
from drivers.servo.modbus_rtu import (
    ExceptionCode,
    ModbusExceptionError,
    ReadHoldingRegisters,
    crc16,
    decode_response,
    encode_request,
)
from drivers.url import open_device
from sim.drive.modbus_server import ModbusDriveServer, start_from_url

CONFIG = DriveConfig(
    counts_per_rev=10_000,
    gear_ratio=50.0,
    velocity_rad_s=math.radians(60.0),
    acceleration_rad_s2=math.radians(600.0),
    max_velocity_rad_s=math.radians(120.0),
)


@pytest.fixture
def server() -> Iterator[ModbusDriveServer]:
    srv = start_from_url("modbus-rtu://")
    try:
        yield srv
    finally:
        srv.close()


@pytest.fixture
def motor(server: ModbusDriveServer) -> Iterator[ModbusMotor]:
    m = open_device("motor", server.url + "&timeout=0.2", config=CONFIG)
    assert isinstance(m, ModbusMotor)
    try:
        yield m
    finally:
        m.close()


def wait_for(predicate: object, timeout: float = 10.0) -> None:
    """Wait for a condition driven by other threads (a deadline against hangs, not a timing check)."""
    deadline = time.monotonic() + timeout
    while not predicate():  # type: ignore[operator]
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


# ------------------------------------------------------------------------------------ the basics
def test_server_serves_a_real_pty(server: ModbusDriveServer) -> None:
    path = server.url.removeprefix("modbus-rtu://").split("?")[0]
    assert path.startswith("/dev/pts/") and os.path.exists(path)
    assert os.isatty(os.open(path, os.O_RDWR | os.O_NOCTTY)) is True


def test_the_pty_can_be_opened_again_with_the_default_parity(server: ModbusDriveServer) -> None:
    for _ in range(2):  # a pty drops PARENB and refuses it on the next open; the backend opens it 8N1
        with open_url(server.url + "&parity=E&poll_hz=0", config=CONFIG) as m:
            assert m.client.timing.bits_per_char == 11  # 8E1 timing all the same
            assert m.state is State.SWITCH_ON_DISABLED


def test_enable_walks_the_state_machine(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    assert motor.state is State.SWITCH_ON_DISABLED
    motor.enable()
    assert motor.state is State.OPERATION_ENABLED
    assert server.drive.state is State.OPERATION_ENABLED
    # the controlword sequence really went over the wire
    assert server.drive.read(cia402.CONTROLWORD) == cia402.CMD_ENABLE_OPERATION
    motor.disable()
    assert motor.state is State.READY_TO_SWITCH_ON
    assert server.drive.state is State.READY_TO_SWITCH_ON


def test_move_reaches_the_target_and_samples_follow_it(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    t_start = motor.clock()
    motor.move_to(math.radians(12.0), wait=True)
    drive_counts = server.drive.read(cia402.POSITION_ACTUAL)
    window = CONFIG.position_window_rad
    assert abs(CONFIG.counts_to_rad(drive_counts) - math.radians(12.0)) <= window
    wait_for(lambda: motor.latest_sample() is not None and motor.latest_sample().t_host_s > motor.clock() - 0.05)
    assert abs(motor.position_rad() - math.radians(12.0)) <= window
    a = motor.sample_arrays_since(t_start)
    assert len(a.t_host_s) > 20
    assert np.all(np.diff(a.t_host_s) > 0)  # host stamps strictly increase
    # the axis moved forward monotonically (up to the servo loop's tiny ripple) from 0 to 12 deg
    assert a.position_rad[0] < math.radians(1.0)
    assert np.all(np.diff(a.position_rad) > -math.radians(0.01))
    # the host stamps agree with the drive's motion: between 1 and 11 deg the mean speed lies between half
    # the cruise speed and the cruise speed (each stamp is off by at most half its round trip, a few ms)
    inside = (a.position_rad > math.radians(1.0)) & (a.position_rad < math.radians(11.0))
    p, t = a.position_rad[inside], a.t_host_s[inside]
    mean_speed = (p[-1] - p[0]) / (t[-1] - t[0])
    assert 0.5 * CONFIG.velocity_rad_s < mean_speed < 1.1 * CONFIG.velocity_rad_s
    # and the drive's own velocity register (0x606C), polled in the same sample block, agrees
    assert a.velocity_rad_s.max() == pytest.approx(CONFIG.velocity_rad_s, rel=0.05)
    assert int(a.statusword[-1]) & cia402.SW_TARGET_REACHED


def test_move_to_a_negative_angle_and_back(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    motor.move_to(math.radians(-3.5), wait=True)
    assert server.drive.read(cia402.POSITION_ACTUAL) < 0  # i32 across two registers, sign intact
    assert CONFIG.counts_to_rad(server.drive.read(cia402.TARGET_POSITION)) == pytest.approx(
        math.radians(-3.5), abs=1e-5
    )
    motor.move_to(0.0, wait=True)
    assert abs(motor._read_object(cia402.POSITION_ACTUAL)) <= CONFIG.position_window_rad * CONFIG.counts_per_rad


def test_jog_then_stop(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    motor.jog(math.radians(-30.0))
    motor.wait_reached(timeout=10.0)  # PV: target velocity reached
    assert server.drive.read(cia402.MODES_OF_OPERATION_DISPLAY) == cia402.Mode.PROFILE_VELOCITY
    wait_for(lambda: abs(motor.velocity_rad_s() - math.radians(-30.0)) < math.radians(0.5))
    motor.stop()
    motor.wait_reached(timeout=10.0)
    wait_for(lambda: abs(motor.velocity_rad_s()) < math.radians(0.05))
    assert motor.state is State.OPERATION_ENABLED  # halt keeps the axis enabled
    assert motor.position_rad() < 0


def test_quick_stop_leaves_operation_enabled(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    motor.jog(math.radians(40.0))
    motor.wait_reached(timeout=10.0)
    motor.quick_stop()
    wait_for(lambda: server.drive.state is not State.OPERATION_ENABLED)
    wait_for(lambda: motor.state in (State.SWITCH_ON_DISABLED, State.QUICK_STOP_ACTIVE))
    with pytest.raises(MotorStateError):
        motor.move_to(0.0)


def test_home_sets_the_present_position_to_the_home_offset(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    motor.move_to(math.radians(5.0), wait=True)
    motor.home(method=37, timeout=10.0)
    assert abs(server.drive.read(cia402.POSITION_ACTUAL)) <= 1
    motor.move_to(math.radians(1.0), wait=True)
    assert motor.position_rad() == pytest.approx(math.radians(1.0), abs=CONFIG.position_window_rad)


# ------------------------------------------------------------------------------ faults and reset
def test_over_current_fault_is_decoded_and_reset(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    server.drive.inject_fault("over_current")
    wait_for(lambda: motor.state is State.FAULT)
    info = motor.fault()
    assert info is not None
    assert info.code == cia402.ERR_OVER_CURRENT == 0x2310
    assert info.reason == "continuous over-current"
    assert info.error_register == 0x03  # generic + current, read from 0x1001 through the map
    with pytest.raises(MotorFault, match="0x2310") as exc:
        motor.move_to(math.radians(1.0))
    assert exc.value.code == 0x2310
    motor.reset_fault()
    assert motor.state is State.SWITCH_ON_DISABLED
    assert motor.fault() is None
    motor.enable()
    motor.move_to(math.radians(2.0), wait=True)


def test_following_error_fault_during_a_move(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    server.drive.inject_fault("following_error")  # the axis stalls
    with pytest.raises(MotorFault) as exc:
        motor.move_to(math.radians(10.0), wait=True, timeout=10.0)
    assert exc.value.code == cia402.ERR_FOLLOWING_ERROR
    assert "following error" in str(exc.value)
    server.drive.clear_injected()
    wait_for(lambda: motor.state is State.FAULT)  # the fault reaction (quick-stop ramp) has ended
    motor.reset_fault()
    motor.enable()
    assert motor.state is State.OPERATION_ENABLED


def test_a_silent_drive_becomes_a_fault_and_recovers(motor: ModbusMotor, server: ModbusDriveServer) -> None:
    motor.enable()
    server.drive.inject_fault("heartbeat_loss")  # the model's "silent" condition: no more replies
    wait_for(lambda: motor.fault() is not None)
    info = motor.fault()
    assert info is not None and info.source == "heartbeat" and "stopped answering" in info.reason
    with pytest.raises(HeartbeatLost) as exc:
        motor.move_to(math.radians(1.0))
    assert isinstance(exc.value, DeviceConnectionError)
    assert server.stats.ignored_silent > 0
    with pytest.raises(ModbusTimeoutError):
        motor.reset_fault()  # still silent: the reset cannot clear the link fault
    server.drive.clear_injected()
    motor.reset_fault()
    wait_for(lambda: motor.fault() is None)
    assert motor.state is State.OPERATION_ENABLED  # the drive itself never faulted


# ------------------------------------------------------------------------ timeouts and retries
@pytest.fixture
def quiet_motor(server: ModbusDriveServer) -> Iterator[ModbusMotor]:
    """A motor without the poll thread, so that every transaction is the test's own. A generous response
    timeout: it bounds answers that must come (the test about timeouts lowers it itself)."""
    m = open_url(server.url + "&timeout=2&retries=2&poll_hz=0", config=CONFIG)
    try:
        yield m
    finally:
        m.close()


def test_silent_slave_times_out_after_the_retries(quiet_motor: ModbusMotor, server: ModbusDriveServer) -> None:
    server.silent = True
    before = server.stats.ignored_silent
    quiet_motor.client.timeout = 0.03
    with pytest.raises(ModbusTimeoutError, match="after 3 attempts") as exc:
        quiet_motor._read_object(cia402.STATUSWORD)
    assert isinstance(exc.value, DeviceTimeoutError) and isinstance(exc.value, DriverError)
    wait_for(lambda: server.stats.ignored_silent - before >= 3)
    assert server.stats.ignored_silent - before == 3  # the request really went out three times
    assert quiet_motor.client.stats.timeouts == 3
    assert quiet_motor.client.stats.failures == 1
    server.silent = False
    quiet_motor.client.timeout = 2.0  # an answer must come now: not within 30 ms on a busy machine
    assert cia402.decode_state(quiet_motor._read_object(cia402.STATUSWORD)) is State.SWITCH_ON_DISABLED


def test_corrupted_replies_are_retried(quiet_motor: ModbusMotor, server: ModbusDriveServer) -> None:
    stats = quiet_motor.client.stats
    attempts = stats.attempts
    server.corrupt_replies = 2
    assert quiet_motor._read_object(cia402.MODES_OF_OPERATION_DISPLAY) == 0
    assert stats.frame_errors == 2
    assert stats.attempts - attempts == 3
    server.corrupt_replies = 3
    with pytest.raises(DriverError, match="CRC"):
        quiet_motor._read_object(cia402.STATUSWORD)


def test_exception_responses_over_the_wire(quiet_motor: ModbusMotor, server: ModbusDriveServer) -> None:
    client = quiet_motor.client
    with pytest.raises(ModbusExceptionError) as exc:
        client.read_registers(0x6401, 1)  # unmapped
    assert exc.value.code == ExceptionCode.ILLEGAL_DATA_ADDRESS
    with pytest.raises(ModbusExceptionError) as exc:
        client.read_registers(0x6641, 1)  # second half of position actual
    assert exc.value.code == ExceptionCode.ILLEGAL_DATA_ADDRESS
    with pytest.raises(ModbusExceptionError) as exc:
        client.write_register(0x67A0, 5)  # half a 32-bit target: refused, nothing written
    assert exc.value.code == ExceptionCode.ILLEGAL_DATA_ADDRESS
    assert server.drive.read(cia402.TARGET_POSITION) == 0
    with pytest.raises(ModbusExceptionError) as exc:
        client.write_register(0x6410, 0)  # the statusword is read-only
    assert exc.value.code == ExceptionCode.ILLEGAL_DATA_ADDRESS
    with pytest.raises(ModbusExceptionError) as exc:
        client.write_register(0x6600, 5)  # mode 5 is not supported by the drive
    assert exc.value.code == ExceptionCode.ILLEGAL_DATA_VALUE
    with pytest.raises(ModbusExceptionError) as exc:
        client.write_register(0x6980, 200)  # 200 does not fit the i8 homing method
    assert exc.value.code == ExceptionCode.ILLEGAL_DATA_VALUE
    assert client.stats.failures == 0  # exceptions are answers, not link failures: no retries
    assert server.stats.exceptions == 6


def test_read_only_objects_are_refused_before_sending(quiet_motor: ModbusMotor) -> None:
    with pytest.raises(ModbusMapError, match="read-only"):
        quiet_motor._write_object(cia402.POSITION_ACTUAL, 0, 0)
    with pytest.raises(ModbusMapError, match="not in the register map"):
        quiet_motor._read_object(cia402.SUPPORTED_DRIVE_MODES)


def test_wrong_unit_gets_no_answer_and_broadcast_writes_apply(server: ModbusDriveServer) -> None:
    path = server.url.removeprefix("modbus-rtu://").split("?")[0]
    port = serial.serial_for_url(path, baudrate=115200, timeout=0.005)
    try:
        other = ModbusRtuClient(port, unit=2, timeout=0.03, retries=0)
        with pytest.raises(ModbusTimeoutError):
            other.read_registers(0x6410, 1)
        wait_for(lambda: server.stats.other_unit == 1)
        broadcast = ModbusRtuClient(port, unit=0, timeout=0.03, retries=0)
        broadcast.write_register(0x6400, cia402.CMD_SHUTDOWN)
        wait_for(lambda: server.stats.broadcasts == 1)
        assert server.drive.state is State.READY_TO_SWITCH_ON
    finally:
        port.close()


def test_raw_frames_on_the_pty(server: ModbusDriveServer) -> None:
    """Bytes written straight to the tty: an unknown function gets exception 01, garbage is ignored."""
    path = server.url.removeprefix("modbus-rtu://").split("?")[0]
    with serial.serial_for_url(path, baudrate=115200, timeout=10.0) as port:  # reads return once the bytes are in
        body = bytes([1, 0x2B, 0x0E, 0x01, 0x00])  # read device identification: not supported
        port.write(body + crc16(body).to_bytes(2, "little"))
        assert port.read(5) == bytes([1, 0xAB, 0x01]) + crc16(bytes([1, 0xAB, 0x01])).to_bytes(2, "little")
        port.write(b"\x01\x03\x64\x10\x00\x01\xff\xff")  # bad CRC: the slave stays silent
        wait_for(lambda: server.stats.crc_errors == 1)  # the slave has taken the frame in (and not answered)
        port.timeout = 0.1
        assert port.read(1) == b""
        request = ReadHoldingRegisters(0x6410, 1)
        port.timeout = 10.0
        port.write(encode_request(1, request))
        reply = decode_response(port.read(7), 1, request)
        assert cia402.decode_state(reply.values[0]) is State.SWITCH_ON_DISABLED  # type: ignore[union-attr]


# ------------------------------------------------------------------------------- other transports
def test_loopback_tcp_transport() -> None:
    with start_from_url("modbus-rtu+socket://127.0.0.1:0?unit=7") as srv:
        assert srv.url.startswith("modbus-rtu://127.0.0.1:") and srv.url.endswith("unit=7")
        # both spellings reach the TCP stream through drivers.url
        with open_device("motor", srv.url.replace("modbus-rtu://", "modbus-rtu+socket://"), config=CONFIG) as m:
            assert m.state is State.SWITCH_ON_DISABLED
        with open_device("motor", srv.url, config=CONFIG) as m:
            m.enable()
            m.move_to(math.radians(-2.0), wait=True)
            assert m.position_rad() == pytest.approx(math.radians(-2.0), abs=CONFIG.position_window_rad)
            assert srv.stats.replies > 10


def test_symlinked_pty_and_a_replacement_map_without_sample_block(tmp_path: Path) -> None:
    link = tmp_path / "servo"
    table = default_map().markdown_table()  # keep only the objects, drop the sample block, swap word order
    assert "sample." in table
    src = (Path(__file__).resolve().parents[2] / "drivers" / "servo" / "modbus_map.toml").read_text()
    text = src.split("\n[sample]\n")[0].replace('word_order = "high_first"', 'word_order = "low_first"')
    map_path = tmp_path / "map.toml"
    map_path.write_text(text)
    with start_from_url(f"modbus-rtu://{link}?map={map_path}") as srv:
        assert link.is_symlink() and os.readlink(link).startswith("/dev/pts/")
        with open_url(f"modbus-rtu://{link}?map={map_path}", config=CONFIG) as m:
            assert m.map.sample is None and m.map.word_order == "low_first"
            m.enable()
            m.move_to(math.radians(-1.5), wait=True)
            wait_for(lambda: m.latest_sample() is not None)
            assert m.position_rad() == pytest.approx(math.radians(-1.5), abs=CONFIG.position_window_rad)
            assert srv.drive.read(cia402.TARGET_POSITION) == CONFIG.rad_to_counts(math.radians(-1.5))
    assert not link.exists()


def test_a_map_without_the_error_register_reports_the_fault_with_register_0(
    server: ModbusDriveServer, tmp_path: Path
) -> None:
    src = (Path(__file__).resolve().parents[2] / "drivers" / "servo" / "modbus_map.toml").read_text()
    block = src[src.index('[[register]]\nname = "error_register"') : src.index('[[register]]\nname = "error_code"')]
    map_path = tmp_path / "map.toml"
    map_path.write_text(src.replace(block, ""))
    with open_url(server.url + f"&timeout=0.2&map={map_path}", config=CONFIG) as m:
        assert isinstance(m, ModbusMotor) and (cia402.ERROR_REGISTER, 0) not in m.map
        m.enable()
        server.drive.inject_fault("over_current")
        wait_for(lambda: m.state is State.FAULT)
        info = m.fault()
        assert info is not None and info.code == cia402.ERR_OVER_CURRENT
        assert info.error_register == 0  # not readable through this map; the drive's own register is 0x03
        assert server.drive.read(cia402.ERROR_REGISTER) == 0x03


# ------------------------------------------------------------------------------------ URL errors
@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("modbus-rtu:///dev/ttyUSB0?baud=115200&unti=1", "unknown option"),
        ("modbus-rtu:///dev/ttyUSB0?unit=0", "outside"),
        ("modbus-rtu:///dev/ttyUSB0?parity=X", "expected one of"),
        ("modbus-rtu://dev/ttyUSB0", "three slashes"),
        ("modbus-rtu://127.0.0.1:5020/x", "no path"),
        ("modbus-rtu://", "no serial device path"),
        ("modbus-rtu+socket://127.0.0.1", "host:port"),
        ("modbus-rtu+telnet://127.0.0.1:23", "unknown scheme"),
    ],
)
def test_bad_urls_are_typed_errors(url: str, message: str) -> None:
    with pytest.raises(DeviceURLError, match=message):
        open_url(url)


def test_missing_port_and_missing_map_are_typed_errors(tmp_path: Path) -> None:
    with pytest.raises(DeviceConnectionError, match="cannot open"):
        open_url(f"modbus-rtu://{tmp_path}/no-such-tty")
    with pytest.raises(ModbusMapError, match="not found"):
        open_url(f"modbus-rtu://{tmp_path}/no-such-tty?map={tmp_path}/none.toml")
    with pytest.raises(DeviceURLError, match="loopback"):
        start_from_url("modbus-rtu+socket://10.1.2.3:5020")
