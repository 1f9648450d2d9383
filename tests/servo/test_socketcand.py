"""The socketcand-protocol CAN bus server: raw protocol, python-can's own socketcand clients, our
driver across it in-process, and across processes with ``lrms sim motor``."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.errors import DeviceConnectionError, DeviceURLError
from drivers.servo import cia402
from drivers.servo.cia402 import State
from drivers.servo.cia402_can import Cia402CanMotor
from drivers.servo.interface import ConnectionLost, HeartbeatLost
from drivers.url import open_device
from sim.drive.socketcand import SimulatedCanDrive, SocketcandError, SocketcandServer, format_frame, parse_send

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    with SocketcandServer() as s:
        yield s


class Raw:
    """A hand-driven socketcand client on a plain TCP socket."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10.0)  # for answers that must come
        self.buf = ""

    def send(self, text: str) -> None:
        self.sock.sendall(text.encode("ascii"))

    def expect(self) -> str:
        while ">" not in self.buf:
            chunk = self.sock.recv(4096).decode("ascii")
            if not chunk:
                raise ConnectionError("closed")
            self.buf += chunk
        end = self.buf.index(">") + 1
        msg, self.buf = self.buf[:end].strip(), self.buf[end:]
        return msg

    def close(self) -> None:
        self.sock.close()


def test_raw_protocol_handshake_and_frames(server: SocketcandServer) -> None:
    a, b = Raw(server.port), Raw(server.port)
    try:
        for c in (a, b):
            assert c.expect() == "< hi >"
            c.send("< send 123 1 11 >")
            assert c.expect() == "< error not in raw mode >"
            c.send("< open can9 >")
            assert c.expect() == "< error could not open bus >"
            c.send("< open can0 >")
            assert c.expect() == "< ok >"
            c.send("< rawmode >")
            assert c.expect() == "< ok >"
        a.send("< echo >")
        assert a.expect() == "< echo >"
        a.send("< send 601 8 40 0 10 0 0 0 0 0 >< send 1ABCDEF0 2 de ad >")
        f1, f2 = b.expect(), b.expect()
        parts = f1.split()
        assert parts[:3] == ["<", "frame", "601"] and parts[4] == "4000100000000000"
        assert float(parts[3]) > 1e9  # seconds.microseconds
        assert f2.split()[2] == "1ABCDEF0" and f2.split()[4] == "DEAD"
        a.send("< send 123 3 1 2 >")
        assert a.expect() == "< error malformed send >"
        a.send("< bcmmode >")
        assert a.expect() == "< error unknown command >"
        # the sender does not hear itself (like a CAN controller)
        a.sock.settimeout(0.2)
        with pytest.raises(TimeoutError):
            a.expect()
    finally:
        a.close()
        b.close()


def test_parse_and_format() -> None:
    assert parse_send("< send 7FF 0 >") == (0x7FF, False, b"")
    assert parse_send("< send 00000123 1 ff >") == (0x123, True, b"\xff")
    for bad in ("< send 800 0 >", "< send 12 9 1 2 3 4 5 6 7 8 9 >", "< send zz 1 1 >", "< frame 1 2 >"):
        with pytest.raises(SocketcandError):
            parse_send(bad)
    assert format_frame(0x80, False, b"", 1.5) == "< frame 080 1.500000  >"


def test_server_binds_loopback_only() -> None:
    with pytest.raises(ValueError, match=r"127\.0\.0\.1"):
        SocketcandServer(host="0.0.0.0")


def test_python_can_socketcand_clients_exchange_frames(server: SocketcandServer) -> None:
    buses = [can.Bus(interface="socketcand", host="127.0.0.1", port=server.port, channel="can0") for _ in range(3)]
    try:
        sent = [
            can.Message(arbitration_id=0x100 + k, data=bytes([k] * (k + 1)), is_extended_id=False) for k in range(5)
        ]
        for msg in sent:
            buses[0].send(msg)
        for bus in buses[1:]:
            got = [bus.recv(10.0) for _ in sent]
            assert [(m.arbitration_id, bytes(m.data)) for m in got if m is not None] == [
                (m.arbitration_id, bytes(m.data)) for m in sent
            ]
        assert buses[0].recv(0.1) is None
        assert server.client_count == 3
    finally:
        for bus in buses:
            bus.shutdown()


def test_driver_across_socketcand_in_process() -> None:
    with SimulatedCanDrive() as sim:
        motor = open_device("motor", sim.url + "&sync_hz=100")
        try:
            assert isinstance(motor, Cia402CanMotor)
            motor.enable()
            motor.move_to(math.radians(1.5), velocity=math.radians(30.0), wait=True)
            assert math.degrees(motor.position_rad()) == pytest.approx(1.5, abs=0.01)
            sim.drive.inject_fault("over_current")
            deadline = time.monotonic() + 10.0
            while motor.fault() is None:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            assert motor.emcy_history[-1][1].code == 0x2310
            motor.reset_fault()
            assert motor.state is State.SWITCH_ON_DISABLED
        finally:
            motor.close()


def test_bus_server_gone_is_a_connection_fault() -> None:
    sim = SimulatedCanDrive()
    # lost after 5 x 100 ms: a shorter period lets a busy test machine fake a loss before the server goes
    motor = open_device("motor", sim.url + "&heartbeat_ms=100")
    try:
        motor.enable()
        sim.close()
        deadline = time.monotonic() + 15.0
        while motor.fault() is None:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        fault = motor.fault()
        assert fault is not None and fault.source in ("heartbeat", "bus")
        with pytest.raises(ConnectionLost):
            motor.enable()
    finally:
        motor.close()


def test_no_server_is_a_connection_error() -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(DeviceConnectionError, match="no socketcand server"):
        open_device("motor", f"canopen+socketcand://127.0.0.1:{port}/can0?node=1")


def test_lrms_motor_against_lrms_sim_motor_subprocess() -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    sim = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli.main",
            "sim",
            "motor",
            "--motor",
            "canopen+socketcand://127.0.0.1:0/can0?node=3",
        ],
        cwd=REPO,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )

    def command(text: str) -> str:
        assert sim.stdin is not None and sim.stdout is not None
        sim.stdin.write(text + "\n")
        sim.stdin.flush()
        return sim.stdout.readline().strip()

    try:
        assert sim.stdout is not None
        line = sim.stdout.readline()
        assert line.startswith("serving canopen+socketcand://127.0.0.1:"), line
        url = line.split()[1]
        # our driver in this process, the simulated drive in the other one
        motor = open_device("motor", url)
        try:
            t0 = motor.clock()
            motor.enable()
            motor.move_to(math.radians(2.0), velocity=math.radians(40.0), wait=True)
            a = motor.sample_arrays_since(t0)
            assert len(a.t_host_s) >= 5 and np.all(np.diff(a.t_host_s) > 0)
            assert math.degrees(a.position_rad[-1]) == pytest.approx(2.0, abs=0.01)
            assert a.statusword[-1] & cia402.SW_TARGET_REACHED
            # the drive in the other process goes silent: a fault here
            assert command("inject heartbeat_loss") == "ok injected heartbeat_loss"
            deadline = time.monotonic() + 15.0
            while motor.fault() is None:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            fault = motor.fault()
            assert fault is not None
            with pytest.raises(HeartbeatLost):
                motor.move_to(0.0)
            assert command("clear") == "ok cleared"
            # the reset clears the fault once a heartbeat came after it (it waits only a few periods for one):
            # wait for the other process's next heartbeat to arrive here rather than race it
            deadline = time.monotonic() + 15.0
            while motor._last_heartbeat is None or motor._last_heartbeat <= fault.t_host_s:
                assert time.monotonic() < deadline, "the drive's heartbeat never came back"
                time.sleep(0.01)
            motor.reset_fault()
            assert motor.fault() is None
            # the driver's quick stop after the loss (sent from its own thread, then the drive's ramp): wait
            # for the drive to get there rather than read its state at once
            deadline = time.monotonic() + 15.0
            while not (status := command("status")).startswith("ok Switch on disabled"):
                assert time.monotonic() < deadline, status
                time.sleep(0.02)
            assert command("inject gremlins").startswith("error unknown fault kind")
        finally:
            motor.close()
        # and the command line, a third process
        out = subprocess.run(
            [sys.executable, "-m", "service.cli.main", "motor", "--motor", url, "move", "-1.0"],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert out.returncode == 0, out.stderr
        assert "Operation enabled" in out.stdout
        position = float(next(x for x in out.stdout.splitlines() if x.startswith("position_deg:")).split()[1])
        assert position == pytest.approx(-1.0, abs=0.01)
        bad = subprocess.run(
            [sys.executable, "-m", "service.cli.main", "motor", "--motor", url + "&colour=red", "status"],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert bad.returncode == 1 and bad.stderr.startswith("error:") and "colour" in bad.stderr
    finally:
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(timeout=10)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
    assert sim.returncode == 0


def test_sim_motor_refuses_other_hosts() -> None:
    from service.cli.main import main

    with pytest.raises(DeviceURLError):
        from argparse import Namespace

        from service.cli import sim_motor

        sim_motor.run(Namespace(motor="canopen+socketcand://10.1.2.3:0/can0?node=1"))
    assert main(["sim", "motor", "--motor", "sim://?node=1"]) == 1


CRASHING_HOST = """
import math, os, sys
from drivers.url import open_device
motor = open_device("motor", sys.argv[1])
motor.enable()
motor.jog(math.radians(20.0))
print("jogging", flush=True)
sys.stdin.readline()
os._exit(0)  # the host process dies: no close(), no stop
"""


def test_a_dead_host_stops_the_drive_but_a_closed_one_does_not() -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    with SimulatedCanDrive() as sim:
        drive = sim.drive
        host = subprocess.Popen(
            [sys.executable, "-c", CRASHING_HOST, sim.url],
            cwd=REPO,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert host.stdout is not None and host.stdin is not None
            assert host.stdout.readline().strip() == "jogging"
            assert drive.state is State.OPERATION_ENABLED
            host.stdin.write("\n")
            host.stdin.flush()
            assert host.wait(timeout=10) == 0
        finally:
            if host.poll() is None:
                host.kill()
                host.wait()
        deadline = time.monotonic() + 15.0
        while drive.state is not State.FAULT:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert drive.read(cia402.ERROR_CODE) == cia402.ERR_HEARTBEAT
        assert drive.read(cia402.VELOCITY_ACTUAL) == 0

        # a deliberate close keeps the drive turning (lrms motor jog; ...; lrms motor stop)
        drive.write(cia402.CONTROLWORD, 0, 0x00)
        drive.write(cia402.CONTROLWORD, 0, 0x80)
        motor = open_device("motor", sim.url)
        motor.enable()
        motor.jog(math.radians(20.0))
        motor.close()
        consumer_s = 5 * 0.1  # heartbeat_lost x heartbeat_ms
        time.sleep(consumer_s + 0.3)
        assert drive.state is State.OPERATION_ENABLED
        assert drive.read(cia402.VELOCITY_ACTUAL) != 0
