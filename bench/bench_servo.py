"""CANopen servo link: SDO round trip, position samples per second, age of the newest sample.

Run: ``.venv/bin/python -m bench.bench_servo [--seconds S] [--sync-hz HZ]``.

The measured case is the cross-process bus of the rig: ``lrms sim motor`` serves a socketcand
bus on 127.0.0.1 with the simulated drive in a subprocess, and our driver opens
``canopen+socketcand://127.0.0.1:PORT/can0?node=1`` here. The baseline, measured in the same run,
is the same driver against the same simulated drive on an in-process python-can ``virtual`` bus
(``sim://``); the ratio column is cross-process / in-process.

* SDO round trip: expedited uploads of the statusword 0x6041 (one request, one response frame).
* samples/s: samples whose SYNC stamps fall in the measuring window, counted, divided by the
  window; the rig needs >= 100/s (each 50 Hz scan gets its beta by interpolation).
* age of the newest sample: ``clock() - latest_sample().t_host_s`` read at random instants,
  i.e. SYNC period / 2 on average plus the SYNC -> TPDO -> host latency.
* stamp jitter: during the constant-velocity jog, positions against their SYNC stamps are fitted
  with a line; the residuals divided by the velocity are the timing error of the stamps (how
  far the instant the drive latched its position strays from the stamp), rms and max, in ms.

The axis jogs at 20 deg/s during the sample measurements, so the TPDOs carry changing values.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import service.simdevices  # noqa: F401  (registers the sim:// device URLs)
from drivers.servo import cia402
from drivers.servo.cia402_can import Cia402CanMotor
from drivers.url import open_device

REPO = Path(__file__).resolve().parent.parent


@dataclass
class Result:
    sdo_ms: np.ndarray
    samples_per_s: float
    age_ms: np.ndarray
    gaps_ms: np.ndarray
    jitter_ms: np.ndarray


def measure(motor: Cia402CanMotor, seconds: float, sdo_count: int) -> Result:
    # SDO round trips (axis at rest, SYNC running as always)
    for _ in range(20):  # warm-up
        motor.sdo_upload(cia402.STATUSWORD)
    rtt = np.empty(sdo_count)
    for k in range(sdo_count):
        t0 = time.perf_counter()
        motor.sdo_upload(cia402.STATUSWORD)
        rtt[k] = time.perf_counter() - t0
    motor.enable()
    motor.jog(math.radians(20.0))
    try:
        time.sleep(0.2)
        t_start = motor.clock()
        ages = []
        rng = random.Random(1)
        while motor.clock() - t_start < seconds:
            time.sleep(rng.uniform(0.0, 0.02))
            latest = motor.latest_sample()
            if latest is not None:
                ages.append(motor.clock() - latest.t_host_s)
        t_end = motor.clock()
        a = motor.sample_arrays_since(t_start)
        keep = a.t_host_s <= t_end
        stamps = a.t_host_s[keep]
        steady = keep & ((a.statusword & cia402.SW_TARGET_REACHED) != 0)  # at the jog velocity
        t, p = a.t_host_s[steady], a.position_rad[steady]
        slope, intercept = np.polyfit(t - t[0], p, 1)
        jitter = (p - (slope * (t - t[0]) + intercept)) / slope
    finally:
        motor.stop()
        motor.disable()
    return Result(
        sdo_ms=rtt * 1e3,
        samples_per_s=len(stamps) / (t_end - t_start),
        age_ms=np.asarray(ages) * 1e3,
        gaps_ms=np.diff(stamps) * 1e3,
        jitter_ms=jitter * 1e3,
    )


def start_sim_process(sync_hz: float) -> tuple[subprocess.Popen[str], str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli.main",
            "sim",
            "motor",
            "--motor",
            "canopen+socketcand://127.0.0.1:0/can0?node=1",
        ],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("serving "):
        proc.kill()
        raise SystemExit(f"lrms sim motor did not start: {line!r}")
    return proc, f"{line.split()[1]}&sync_hz={sync_hz:g}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="length of the sample measurement")
    parser.add_argument("--sync-hz", type=float, default=200.0, help="SYNC rate the driver produces")
    parser.add_argument("--sdo", type=int, default=500, help="number of SDO round trips")
    args = parser.parse_args()

    print(f"servo link benchmark: SYNC {args.sync_hz:g} Hz, {args.seconds:g} s of samples, {args.sdo} SDO reads")
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")

    with open_device("motor", f"sim://?node=1&sync_hz={args.sync_hz:g}") as base_motor:
        assert isinstance(base_motor, Cia402CanMotor)
        base = measure(base_motor, args.seconds, args.sdo)

    proc, url = start_sim_process(args.sync_hz)
    try:
        with open_device("motor", url) as motor:
            assert isinstance(motor, Cia402CanMotor)
            cross = measure(motor, args.seconds, args.sdo)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)

    def row(name: str, x: float, b: float, unit: str) -> None:
        print(f"  {name:<34} {x:10.3f} {b:12.3f}  {x / b:7.2f}  {unit}")

    print(f"\n  {'':<34} {'socketcand':>10} {'virtual(in)':>12}  {'ratio':>7}")
    print("  (cross-process)")
    for q in (50, 95, 99):
        row(f"SDO round trip p{q}", np.percentile(cross.sdo_ms, q), np.percentile(base.sdo_ms, q), "ms")
    row("SDO round trips per second", 1e3 / cross.sdo_ms.mean(), 1e3 / base.sdo_ms.mean(), "1/s")
    row("position samples per second", cross.samples_per_s, base.samples_per_s, "1/s")
    row("largest gap between samples", cross.gaps_ms.max(), base.gaps_ms.max(), "ms")
    for q in (50, 95, 99):
        row(f"age of newest sample p{q}", np.percentile(cross.age_ms, q), np.percentile(base.age_ms, q), "ms")
    row(
        "stamp jitter rms",
        float(np.sqrt(np.mean(cross.jitter_ms**2))),
        float(np.sqrt(np.mean(base.jitter_ms**2))),
        "ms",
    )
    row("stamp jitter max", float(np.max(np.abs(cross.jitter_ms))), float(np.max(np.abs(base.jitter_ms))), "ms")
    print(
        f"\n  samples/s vs the rig's need (100/s): {cross.samples_per_s / 100.0:.2f}x cross-process;"
        f" vs the SYNC rate: {cross.samples_per_s / args.sync_hz:.3f}"
    )


if __name__ == "__main__":
    main()
