"""Modbus RTU servo path across processes: transaction round trip, polled samples per second, sample age.

Run: ``.venv/bin/python bench/bench_modbus.py``. A child process serves the simulated drive on a
pseudo-terminal (``sim.drive.modbus_server``); this process opens it with the Modbus backend.

Printed:

* the round trip of an FC 03 read of 2 registers (position actual) through :class:`ModbusRtuClient`,
  against a baseline measured in the same run: a child process that answers every 8-byte request with a
  fixed 9-byte reply on a pty (no codec, no drive), i.e. what the pty and the two processes cost alone;
* the same against the wire-time floor of a real 115200-baud line (computed: 17 bytes of 11 bits plus
  two t3.5 gaps), to show where a real RS-485 link would put the limit;
* samples/s of :class:`ModbusMotor`'s poll thread (default 200 Hz) while a move runs, against the 100
  samples/s the rig needs, and the age of the newest sample when a consumer looks at a random instant.
"""

from __future__ import annotations

import math
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

import serial

from drivers.servo.interface import DriveConfig
from drivers.servo.modbus_backend import ModbusRtuClient, open_url
from drivers.servo.modbus_rtu import RtuTiming

REPO = Path(__file__).resolve().parent.parent

ECHO_CHILD = r"""
import os, select, sys, tty
master, slave = os.openpty()
tty.setraw(slave)
print(os.ttyname(slave), flush=True)
reply = bytes(9)
buf = b""
while True:
    r, _, _ = select.select([master, sys.stdin], [], [])
    if sys.stdin in r:
        break
    buf += os.read(master, 256)
    while len(buf) >= 8:
        buf = buf[8:]
        os.write(master, reply)
"""

DRIVE_CHILD = r"""
import sys
from sim.drive.modbus_server import start_from_url
server = start_from_url("modbus-rtu://")
print(server.url, flush=True)
sys.stdin.read()
server.close()
"""


def _child(code: str) -> tuple[subprocess.Popen[str], str]:
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO
    )
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    if not line:
        proc.kill()
        raise RuntimeError("child process did not start")
    return proc, line


def _stop(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    proc.wait(timeout=5)


def _percentiles(values: list[float]) -> tuple[float, float, float]:
    v = sorted(values)
    return statistics.median(v), v[int(0.99 * (len(v) - 1))], v[-1]


def baseline_round_trip(n: int) -> list[float]:
    proc, path = _child(ECHO_CHILD)
    try:
        with serial.serial_for_url(path, baudrate=115200, timeout=1.0) as port:
            times = []
            request = bytes(8)
            for _ in range(n):
                t0 = time.perf_counter()
                port.write(request)
                if len(port.read(9)) != 9:
                    raise RuntimeError("echo child did not answer")
                times.append(time.perf_counter() - t0)
            return times
    finally:
        _stop(proc)


def modbus_round_trip(url: str, n: int) -> list[float]:
    path = url.removeprefix("modbus-rtu://").split("?")[0]
    with serial.serial_for_url(path, baudrate=115200, timeout=0.005) as port:
        client = ModbusRtuClient(port, unit=1, timeout=0.5, retries=0, clock=time.perf_counter)
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            client.read_registers(0x6640, 2)
            times.append(time.perf_counter() - t0)
        return times


def sampling(url: str, seconds: float) -> tuple[float, list[float]]:
    config = DriveConfig(velocity_rad_s=math.radians(30.0), max_velocity_rad_s=math.radians(90.0))
    with open_url(url, config=config) as motor:
        motor.enable()
        motor.jog(math.radians(30.0))
        time.sleep(0.2)
        n0, t0 = motor.sample_count, time.monotonic()
        ages = []
        rng = random.Random(1)
        while time.monotonic() - t0 < seconds:
            time.sleep(rng.uniform(0.0, 0.01))
            latest = motor.latest_sample()
            assert latest is not None
            ages.append(motor.clock() - latest.t_host_s)
        rate = (motor.sample_count - n0) / (time.monotonic() - t0)
        motor.stop()
        return rate, ages


def main() -> None:
    n = 2000
    base = baseline_round_trip(n)
    proc, url = _child(DRIVE_CHILD)
    try:
        rtt = modbus_round_trip(url, n)
        rate, ages = sampling(url, 3.0)
    finally:
        _stop(proc)
    b50, b99, _ = _percentiles(base)
    m50, m99, mmax = _percentiles(rtt)
    timing = RtuTiming(115200)
    wire = timing.frame_time(8 + 9) + 2 * timing.t3_5
    print(f"baseline: raw pty round trip, child process, 8 B out / 9 B back: median {b50 * 1e3:.3f} ms, "
          f"p99 {b99 * 1e3:.3f} ms  (n={n})")  # fmt: skip
    print(f"Modbus FC 03 (2 registers) via ModbusRtuClient to the simulated drive in a child process: "
          f"median {m50 * 1e3:.3f} ms, p99 {m99 * 1e3:.3f} ms, max {mmax * 1e3:.3f} ms  (n={n})")  # fmt: skip
    print(f"  = {m50 / b50:.1f} x the raw pty round trip; {timing.t3_5 * 1e3:.2f} ms of it is the t3.5 silence the "
          f"client keeps before each request, the rest is codec, framing, register map and drive model")  # fmt: skip
    print(f"  real 115200-baud line floor (17 B x 11 bit + 2 x t3.5): {wire * 1e3:.2f} ms; "
          f"the pty path is {wire / m50:.1f} x faster than that floor")  # fmt: skip
    a50, a99, amax = _percentiles(ages)
    print(f"ModbusMotor poll thread (poll_hz=200) during a jog: {rate:.1f} samples/s = {rate / 100:.2f} x the "
          f"100 samples/s the rig needs")  # fmt: skip
    print(f"age of the newest sample at random instants: median {a50 * 1e3:.2f} ms, p99 {a99 * 1e3:.2f} ms, "
          f"max {amax * 1e3:.2f} ms  (n={len(ages)})")  # fmt: skip


if __name__ == "__main__":
    main()
