"""``lrms scan`` end to end: a subprocess against the simulated LMS100 served over TCP by this test."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from collections.abc import Iterator

import pytest

from sim.scanner import ScannerServer, SimulatedLMS100
from tests.conftest import REPO

REQUIRED = {
    "telegram_counter",
    "scan_counter",
    "time_since_startup_us",
    "time_of_transmission_us",
    "scan_frequency_hz",
    "start_angle_deg",
    "angular_step_deg",
    "ranges_m",
    "rssi",
    "device_status",
    "serial_number",
}


def lrms(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli.main", *args], cwd=REPO, capture_output=True, text=True, timeout=60
    )


@pytest.fixture(params=["a", "b"])
def server(request: pytest.FixtureRequest) -> Iterator[ScannerServer]:
    with ScannerServer(SimulatedLMS100("wall", realtime=False), dialect=request.param) as s:
        yield s


def test_scan_streams_jsonl(server: ScannerServer) -> None:
    proc = lrms("scan", "--scanner", server.url, "--count", "4", "--format", "jsonl", "--stats")
    assert proc.returncode == 0, proc.stderr
    records = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(records) == 4
    for r in records:
        assert set(r) >= REQUIRED
        assert len(r["ranges_m"]) == 1081 and r["rssi"] is None
        assert (r["scan_frequency_hz"], r["start_angle_deg"], r["angular_step_deg"]) == (25.0, -45.0, 0.25)
        assert r["serial_number"] == 19060042 and len(r["device_status"]) == 2
        assert r["ranges_m"][540] == pytest.approx(3.0, abs=0.1)  # beam 540 is 90 deg: the wall, 3 m ahead
    counters = [r["scan_counter"] for r in records]
    assert counters == list(range(counters[0], counters[0] + 4))
    times = [r["time_since_startup_us"] for r in records]
    assert all(b - a == 40_000 for a, b in itertools.pairwise(times))
    stats = json.loads(proc.stderr.strip().splitlines()[-1])
    assert stats["received"] >= 4 and stats["lost"] == 0


def test_scan_poll_starts_a_stopped_device() -> None:
    device = SimulatedLMS100("wall", realtime=False)
    device.measuring = False  # switched off: the command logs in, starts it and sends Run
    with ScannerServer(device, dialect="b") as server:
        proc = lrms("scan", "--scanner", server.url, "--count", "2", "--poll")
        assert proc.returncode == 0, proc.stderr
        records = [json.loads(line) for line in proc.stdout.splitlines()]
        assert len(records) == 2 and records[0]["scan_counter"] != records[1]["scan_counter"]
        assert device.measuring


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("tcp://127.0.0.1:1?cola=a", "error: cannot connect to 127.0.0.1:1"),
        ("tcp://127.0.0.1:2111?cola=x", "error: option cola='x'"),
        ("tcp://127.0.0.1:2111?speed=9", "error: unknown option(s) speed"),
    ],
)
def test_scan_errors_are_one_line_and_exit_1(url: str, message: str) -> None:
    proc = lrms("scan", "--scanner", url, "--count", "1")
    assert proc.returncode == 1
    assert proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert proc.stderr.startswith(message)
