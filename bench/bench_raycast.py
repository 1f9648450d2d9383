"""Ray-cast throughput of the simulated scene, and of the simulated LMS100 server, against the sensor.

Run: ``.venv/bin/python bench/bench_raycast.py``. Prints beams/s for one 1081-beam scan
(0.25 deg, 25 Hz: 27,025 reported beams/s) against the ``seed003`` scene, with and without the
sensor's noise, and for a sweep of 100 scans cast at once, as multiples of the sensor's rate; the
LMS1xx footprint model (16 / 32 / 64 / 128 sub-rays per beam) with its slowdown against the thin beam
measured in the same run;
then scans/s streamed by the simulated device in fast mode over loopback TCP (CoLa A and B; with
the streaming device's "lms1xx" sensor, 32 sub-rays, and with the model's default 128),
read by a plain-socket client with the codec, as multiples of 25 scans/s.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

import numpy as np

from drivers.lms100 import CoLaConnection, ScanDataEvent, SubscribeScanData
from lrms.kinematics import RigCalibration
from sim.scanner import ScannerServer, SimulatedLMS100
from sim.scene import (
    Footprint,
    LMS1xxSensor,
    Scene,
    Sensor,
    SensorModel,
    TorusSection,
    cast_beams,
    get_scene,
    lms1xx_device_angles,
    make_sensor,
)

SENSOR_BEAMS_PER_S = 1081 * 25.0


def _rate(fn: Callable[[], object], rays_per_call: int, min_time: float = 1.0) -> float:
    fn()  # warm-up
    calls = 0
    start = time.perf_counter()
    while True:
        fn()
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= min_time:
            return calls * rays_per_call / elapsed


def main() -> None:
    cal = RigCalibration()
    dev = lms1xx_device_angles(0.25)
    scene = get_scene("seed003")
    noisy, exact = SensorModel(), SensorModel.noiseless()
    rng = np.random.default_rng(0)
    sweep = np.deg2rad(np.linspace(-15, 60, 100))[:, None]
    elbow_scene = get_scene("seed003")
    elbow_scene.add(TorusSection((0.9, 2.6, 0.0), (0, 0, 1), 0.3, 0.08, np.pi / 2), name="elbow")
    cases: list[tuple[str, Callable[[], object], int]] = [
        ("seed003, 1 scan x 1081 beams, noiseless", lambda: cast_beams(scene, cal, exact, dev, 0.3), dev.size),
        ("seed003, 1 scan x 1081 beams, sensor noise", lambda: cast_beams(scene, cal, noisy, dev, 0.3, rng), dev.size),
        ("seed003, 100 scans at once (sweep)", lambda: cast_beams(scene, cal, noisy, dev, sweep, rng), 100 * dev.size),
        ("seed003 + torus elbow, 1 scan", lambda: cast_beams(elbow_scene, cal, noisy, dev, 0.0, rng), dev.size),
    ]
    # The LMS1xx footprint model: every beam is K sub-rays; slowdown against the thin beam in this run.
    room = get_scene("seed003-room")
    for k in (16, 32, 64, 128):
        lms = LMS1xxSensor(footprint=Footprint(sub_rays=k))
        cases.append(
            (f"seed003, 1 scan, LMS1xx {k} sub-rays", _cast(scene, cal, lms, dev, rng), dev.size),
        )
    cases.append(("seed003-room, 1 scan, thin beam", _cast(room, cal, noisy, dev, rng), dev.size))
    k_default = LMS1xxSensor().footprint.sub_rays
    cases.append(
        (f"seed003-room, 1 scan, LMS1xx {k_default} sub-rays", _cast(room, cal, LMS1xxSensor(), dev, rng), dev.size)
    )
    print(f"sensor rate (baseline): {SENSOR_BEAMS_PER_S:,.0f} beams/s (1081 beams x 25 Hz)")
    thin = 0.0
    for name, fn, n in cases:
        rate = _rate(fn, n)
        if name.endswith(("sensor noise", "thin beam")):
            thin = rate
        slower = f"  ({thin / rate:5.1f} x slower than the thin beam)" if "LMS1xx" in name and thin else ""
        print(f"{name:45s} {rate:12,.0f} beams/s = {rate / SENSOR_BEAMS_PER_S:7.1f} x real time{slower}")
    # the streaming device's "lms1xx" sensor (make_sensor: STREAM_SUB_RAYS) and the model's default
    for cola, sensor_model in (("a", None), ("b", None), ("b", make_sensor("lms1xx")), ("b", LMS1xxSensor())):
        rate = _server_rate(cola, scans=400 if sensor_model is None else 60, sensor=sensor_model)
        tag = f", LMS1xx {sensor_model.footprint.sub_rays}" if isinstance(sensor_model, LMS1xxSensor) else ""
        name = f"simulated LMS100 server, fast mode, CoLa {cola.upper()}{tag}"
        print(f"{name:45s} {rate:12,.1f} scans/s = {rate / 25:7.1f} x 25 Hz")


def _cast(
    scene: Scene, cal: RigCalibration, sensor: Sensor, dev: np.ndarray, rng: np.random.Generator
) -> Callable[[], object]:
    return lambda: cast_beams(scene, cal, sensor, dev, 0.3, rng)


def _server_rate(cola: str, scans: int, sensor: Sensor | None = None) -> float:
    """Scans per second a subscribed client receives from the fast (virtual-clock) device."""
    with ScannerServer(SimulatedLMS100("seed003", sensor=sensor, realtime=False), dialect=cola) as server:
        sock = socket.create_connection(server.address)
        conn = CoLaConnection(cola, role="client")
        sock.sendall(conn.send(SubscribeScanData(True)))
        received, start = 0, 0.0
        while received < scans:
            msg = conn.next_message()
            if msg is None:
                conn.receive_data(sock.recv(1 << 16))
            elif isinstance(msg, ScanDataEvent):
                received += 1
                if received == 20:  # start the clock after the first scans (thread start-up)
                    start = time.perf_counter()
        elapsed = time.perf_counter() - start
        sock.close()
        return (scans - 20) / elapsed


if __name__ == "__main__":
    main()
