"""ModbusRtuClient against a scripted slave on a real pty: replies in chunks, late replies, garbage, busy.

The slave side is the test itself holding the pty master: it reads the request bytes the client wrote and
answers with frames built by the codec (or deliberately broken ones), so the client's framing, timeouts
and retries are exercised byte for byte.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator

import pytest
import serial

from drivers.servo.modbus_backend import ModbusRtuClient, ModbusTimeoutError
from drivers.servo.modbus_rtu import (
    ExceptionCode,
    ModbusExceptionError,
    ModbusFrameError,
    ReadHoldingRegisters,
    ReadHoldingRegistersResponse,
    RtuTiming,
    decode_request,
    encode_exception,
    encode_response,
)

# script: request frame -> list of (delay before chunk in s, chunk bytes)
Script = Callable[[bytes, int], list[tuple[float, bytes]]]


class ScriptedSlave:
    def __init__(self, script: Script) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.script = script
        self.requests: list[bytes] = []
        self.answered = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            buf += os.read(self.master, 256)
            if len(buf) < 8:  # the tests only send 8-byte requests (FC 03 / FC 06)
                continue
            frame, buf = buf[:8], buf[8:]
            self.requests.append(frame)
            for delay, chunk in self.script(frame, len(self.requests)):
                time.sleep(delay)
                os.write(self.master, chunk)
            self.answered += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def make_client() -> Iterator[Callable[[Script], tuple[ModbusRtuClient, ScriptedSlave]]]:
    made: list[tuple[serial.SerialBase, ScriptedSlave]] = []

    def make(script: Script) -> tuple[ModbusRtuClient, ScriptedSlave]:
        slave = ScriptedSlave(script)
        port = serial.serial_for_url(slave.path, baudrate=115200, timeout=0.005)
        made.append((port, slave))
        # a generous response timeout: only the tests about timeouts wait for one (they lower it themselves)
        return ModbusRtuClient(port, unit=1, timeout=2.0, retries=2, timing=RtuTiming(115200)), slave

    yield make
    for port, slave in made:
        port.close()
        slave.close()


def reply_for(frame: bytes, values: tuple[int, ...] = (0x1234, 0x5678)) -> bytes:
    unit, request = decode_request(frame)
    assert isinstance(request, ReadHoldingRegisters)
    return encode_response(unit, ReadHoldingRegistersResponse(values[: request.count]))


def test_a_reply_in_chunks_a_few_ms_apart_is_one_frame(make_client) -> None:  # type: ignore[no-untyped-def]
    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        r = reply_for(frame)
        return [(0.0, r[:1]), (0.004, r[1:3]), (0.004, r[3:])]  # like a USB adapter's latency timer

    client, _slave = make_client(script)
    # the chunks are a few ms apart, but the slave thread's sleeps can stretch on a busy machine: a generous
    # slack for the rest of the frame (what is tested is that the chunks make one frame, not the slack)
    client.frame_slack = 2.0
    assert client.read_registers(0x6640, 2) == (0x1234, 0x5678)
    assert client.stats.attempts == 1


def test_a_late_reply_to_a_timed_out_request_is_not_taken_for_the_next(make_client) -> None:  # type: ignore[no-untyped-def]
    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        if n == 1:  # first answer arrives after the client gave up
            return [(0.3, reply_for(frame, (1, 1)))]
        return [(0.0, reply_for(frame, (2, 2)))]

    client, slave = make_client(script)
    client.retries = 0
    client.timeout = 0.1
    with pytest.raises(ModbusTimeoutError, match="no reply"):
        client.read_registers(0x6640, 2)
    deadline = time.monotonic() + 10.0
    while slave.answered < 1:  # wait until the stale reply is waiting in the input buffer
        assert time.monotonic() < deadline
        time.sleep(0.01)
    client.timeout = 2.0  # this answer must come: not within 100 ms on a busy machine
    assert client.read_registers(0x6640, 2) == (2, 2)


def test_a_reply_that_stops_half_way_times_out_and_is_retried(make_client) -> None:  # type: ignore[no-untyped-def]
    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        r = reply_for(frame)
        return [(0.0, r[:4])] if n == 1 else [(0.0, r)]

    client, slave = make_client(script)
    assert client.read_registers(0x6640, 2) == (0x1234, 0x5678)
    assert client.stats.timeouts == 1 and client.stats.attempts == 2
    assert len(slave.requests) == 2


def test_noise_with_an_unknown_function_is_drained_and_retried(make_client) -> None:  # type: ignore[no-untyped-def]
    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        if n == 1:
            return [(0.0, b"\x01\x41garbage-garbage")]
        return [(0.0, reply_for(frame))]

    client, _slave = make_client(script)
    assert client.read_registers(0x6640, 2) == (0x1234, 0x5678)
    assert client.stats.frame_errors == 1


def test_busy_is_retried_other_exceptions_are_not(make_client) -> None:  # type: ignore[no-untyped-def]
    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        if n == 1:
            return [(0.0, encode_exception(1, 0x03, ExceptionCode.SERVER_DEVICE_BUSY))]
        if n == 2:
            return [(0.0, reply_for(frame))]
        return [(0.0, encode_exception(1, 0x03, ExceptionCode.ILLEGAL_DATA_ADDRESS))]

    client, slave = make_client(script)
    assert client.read_registers(0x6640, 2) == (0x1234, 0x5678)
    assert client.stats.busy == 1
    with pytest.raises(ModbusExceptionError, match="illegal data address") as exc:
        client.read_registers(0x6640, 2)
    assert exc.value.code == 2
    assert len(slave.requests) == 3  # no retry of a definite answer


def test_wrong_unit_in_the_reply_is_a_frame_error_after_retries(make_client) -> None:  # type: ignore[no-untyped-def]
    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        return [(0.0, encode_response(9, ReadHoldingRegistersResponse((0, 0))))]

    client, slave = make_client(script)
    with pytest.raises(ModbusFrameError, match="after 3 attempts"):
        client.read_registers(0x6640, 2)
    assert len(slave.requests) == 3


def test_the_client_keeps_the_silent_interval_between_requests(make_client) -> None:  # type: ignore[no-untyped-def]
    arrivals: list[float] = []

    def script(frame: bytes, n: int) -> list[tuple[float, bytes]]:
        arrivals.append(time.monotonic())
        return [(0.0, reply_for(frame))]

    client, _slave = make_client(script)
    client.timing = RtuTiming(1200)  # t3.5 = 32 ms: large enough to see across threads
    for _ in range(3):
        client.read_registers(0x6640, 2)
    # a request arrives after the previous reply was sent (which is after that request arrived) plus t3.5
    assert len(arrivals) == 3
    assert all(arrivals[i + 1] - arrivals[i] >= client.timing.t3_5 for i in range(2))
