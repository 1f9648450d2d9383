"""Hardware in the loop with faults: the simulated rig in its own process (``python -m sim.rig``),
faults injected through its stdin control channel, the service driven over HTTP.

* scanner connection cut mid-sweep: reconnect, the hole reported (and logged as gap events);
* motor fault mid-sweep: sweep aborted, motor stopped, log readable up to the fault, failed with the reason;
* dead scanner: failed with the reason, motor stopped;
* the rig process killed mid-sweep: the motor stop cannot be confirmed and the failure says so;
* restart with queued work: the queued measurement runs to done after a restart on the same SQLite file;
* step-and-scan mode, and cancelling a running sweep (the motor comes to rest).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service import mcaplog
from service.api import ServerThread, create_app
from service.config import RigConfig, parse_toml
from service.rig import build_service
from tests.conftest import REPO
from tests.service.test_cli import announced_url
from tests.service.test_rig_sim import AUTH, FAST, RigProcess, _check_cylinder, _wait, _wait_sweeping, hil_config_text


@pytest.fixture
def rig_process() -> Iterator[RigProcess]:
    rig = RigProcess()
    try:
        yield rig
    finally:
        if rig.proc.poll() is None:
            rig.close()


def _config(urls: dict[str, str], data_dir: Path) -> RigConfig:
    return parse_toml(hil_config_text(urls, data_dir))


@pytest.fixture
def hil(rig_process: RigProcess, tmp_path: Path) -> Iterator[tuple[RigProcess, httpx.Client]]:
    svc, rig = build_service(_config(rig_process.urls, tmp_path))
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
            yield rig_process, client
    finally:
        svc.stop()
        rig.close()


def _events(client: httpx.Client, mid: str, path: Path) -> tuple[list[mcaplog.LoggedMessage], list[dict[str, Any]]]:
    path.write_bytes(client.get(f"/api/v1/measurements/{mid}/raw").content)
    msgs, _ = mcaplog.read_log(path)
    return msgs, [m.decode() for m in msgs if m.topic == mcaplog.TOPIC_EVENT]


def test_scanner_connection_dropped_mid_sweep_reconnects_and_reports_the_gap(
    hil: tuple[RigProcess, httpx.Client], tmp_path: Path
) -> None:
    sim, client = hil
    # The reconnect (0.2 s back-off, then the session restore) has to finish, and a scan has to come
    # after it, while the sweep still runs, or nothing shows the hole. The service itself gives a
    # silent scanner 3 s (run_sweep's scan_silence_s) before it fails the sweep; so the cable is
    # pulled right after the sweep starts, with 85 deg at 10 deg/s (8.5 s) still to go: any reconnect
    # the service accepts ends well inside the sweep, however slow the machine (measured: 0.55 s
    # from the drop to the reconnect with two CPU hogs on two cores).
    req = {"target": "cylinder", "sweep": {"start_deg": -20.0, "stop_deg": 70.0, "speed_deg_s": 10.0}}
    mid = client.post("/api/v1/measurements", json=req, headers=AUTH).json()["id"]
    _wait_sweeping(client, mid, -15.0)
    assert sim.command("drop_scanner") == {"ok": True, "dropped": 1}
    body = _wait(client, mid, {"done", "failed"})
    assert body["state"] == "done", body["error"]
    res = body["result"]
    assert res["scanner_stats"]["connection_losses"] >= 1 and res["scanner_stats"]["reconnects"] >= 1
    assert res["sweep"]["scans_missing"] > 0 and res["sweep"]["scan_gaps"]  # the hole is reported, not hidden
    # the metrology goal and the reported interval; not 4 GUM u: on a loaded machine a reconnect
    # run was 0.5 mm off with u = 0.10 mm (timing errors are not in the noise model)
    _check_cylinder(res, gum=False)
    # the log has the gap events, and they add up to the scans the result reports missing
    _, events = _events(client, mid, tmp_path / "gap.mcap")
    gaps = [e for e in events if e["kind"] == "scan_gap"]
    assert gaps and sum(int(e["missing"]) for e in gaps) == res["sweep"]["scans_missing"], gaps


def test_motor_fault_mid_sweep_stops_the_motor_and_fails_with_the_reason(
    hil: tuple[RigProcess, httpx.Client], tmp_path: Path
) -> None:
    sim, client = hil
    mid = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    _wait_sweeping(client, mid, 10.0)
    assert sim.command("motor_fault over_current") == {"ok": True}
    body = _wait(client, mid, {"done", "failed"})
    assert body["state"] == "failed"
    assert "motor fault 0x2310" in body["error"], body["error"]
    # the motor is stopped: the drive came to rest and stays faulted (power stage off)
    state = sim.wait_motor_at_rest()
    assert state["velocity_actual"] == 0 and state["state"] == "FAULT", state
    # the raw log is readable up to the fault and says why it ends
    msgs, events = _events(client, mid, tmp_path / "fault.mcap")
    assert sum(m.topic == mcaplog.TOPIC_TELEGRAM for m in msgs) > 10
    aborted = [e for e in events if e["kind"] == "sweep_aborted"]
    assert aborted and "0x2310" in aborted[0]["reason"] and "motor_stop_error" not in aborted[0]
    final = [m.decode() for m in msgs if m.topic == mcaplog.TOPIC_RESULT]
    assert final[-1]["state"] == "failed" and "0x2310" in final[-1]["reason"]
    # the next measurement refuses to start on a faulted drive, with the reason
    nxt = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    body = _wait(client, nxt, {"done", "failed"})
    assert body["state"] == "failed" and "faulted" in body["error"]


def test_dead_scanner_fails_the_measurement_with_the_reason_and_stops_the_motor(
    hil: tuple[RigProcess, httpx.Client], tmp_path: Path
) -> None:
    sim, client = hil
    mid = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    _wait_sweeping(client, mid, 10.0)
    assert sim.command("kill_scanner") == {"ok": True}
    body = _wait(client, mid, {"done", "failed"})
    assert body["state"] == "failed", body
    assert "scan" in body["error"].lower(), body["error"]
    state = sim.wait_motor_at_rest()
    assert state["velocity_actual"] == 0 and state["state"] != "OPERATION_ENABLED", state
    _, events = _events(client, mid, tmp_path / "dead.mcap")
    aborted = [e for e in events if e["kind"] == "sweep_aborted"]
    assert aborted and aborted[0]["reason"] in body["error"] and "motor_stop_error" not in aborted[0]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # python-can's reader thread
def test_rig_process_killed_mid_sweep_reports_that_the_motor_stop_failed(
    hil: tuple[RigProcess, httpx.Client], tmp_path: Path
) -> None:
    sim, client = hil
    mid = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    _wait_sweeping(client, mid, 10.0)
    sim.proc.kill()  # the drive (and the scanner) gone: a stop command cannot be confirmed
    sim.proc.wait(10)
    body = _wait(client, mid, {"done", "failed"})
    assert body["state"] == "failed", body
    assert "motor" in body["error"] and "stop" in body["error"], body["error"]
    _, events = _events(client, mid, tmp_path / "killed.mcap")
    aborted = [e for e in events if e["kind"] == "sweep_aborted"]
    assert aborted and aborted[0]["motor_stop_error"] in body["error"], aborted


LRMS_SERVE = [sys.executable, "-m", "service.cli.main", "serve"]


def _serve(config: Path) -> tuple[subprocess.Popen[str], str]:
    """``lrms serve`` on a port of its own choosing (``--port 0``) and the URL it announces."""
    proc = subprocess.Popen(
        [*LRMS_SERVE, "--config", str(config), "--port", "0", "--log-level", "warning"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        return proc, announced_url(proc)
    except BaseException:
        proc.kill()
        proc.wait(30)
        raise


def _client_of(proc: subprocess.Popen[str], url: str) -> httpx.Client:
    """A client once ``lrms serve`` answers (the process must stay alive meanwhile)."""
    end = time.monotonic() + 60
    while time.monotonic() < end:
        try:
            httpx.get(f"{url}/healthz", timeout=5)
            return httpx.Client(base_url=url, timeout=30)
        except httpx.HTTPError:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.2)
    raise AssertionError("lrms serve did not answer")


def test_restart_with_queued_work_runs_the_queued_measurement(rig_process: RigProcess, tmp_path: Path) -> None:
    """``lrms serve`` (its own process) on the rig process; stopped (SIGTERM) mid-sweep with a
    measurement queued, started again on the same SQLite file: the queued one runs to done."""
    config = tmp_path / "rig.toml"
    config.write_text(hil_config_text(rig_process.urls, tmp_path))
    slow = {"target": "cylinder", "sweep": {"speed_deg_s": 5.0}}
    proc, url = _serve(config)
    try:
        with _client_of(proc, url) as client:
            first = client.post("/api/v1/measurements", json=slow, headers=AUTH).json()["id"]
            queued = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
            _wait_sweeping(client, first, 0.0)
            assert client.get(f"/api/v1/measurements/{queued}").json()["state"] == "queued"
    finally:
        proc.terminate()  # the service stops mid-sweep with work queued
        proc.wait(30)
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr.read() if proc.stderr else None  # closed, not killed
    state = rig_process.wait_motor_at_rest()  # the sweep was cancelled: quick stop
    assert state["velocity_actual"] == 0 and state["state"] != "FAULT", state  # the rig closed cleanly
    proc, url = _serve(config)  # the same SQLite file
    try:
        with _client_of(proc, url) as client:
            body = _wait(client, queued, {"done", "failed"})
            assert body["state"] == "done", body["error"]
            res = body["result"]
            assert res["model"] == "cylinder" and abs(res["diameter_m"] - 0.1375) < 2e-3, res
            assert res["uncertainty"]["d_min_m"] <= 0.1375 <= res["uncertainty"]["d_max_m"], res
            interrupted = client.get(f"/api/v1/measurements/{first}").json()
            assert interrupted["state"] == "cancelled" and interrupted["error"], interrupted
    finally:
        proc.terminate()
        proc.wait(30)


def test_step_and_scan_mode(hil: tuple[RigProcess, httpx.Client]) -> None:
    _, client = hil
    req = {
        "target": "cylinder",
        "sweep": {
            "mode": "step",
            "start_deg": -10,
            "stop_deg": 50,
            "step_deg": 4,
            "speed_deg_s": 30,
            "scans_per_step": 2,
        },
    }
    mid = client.post("/api/v1/measurements", json=req, headers=AUTH).json()["id"]
    body = _wait(client, mid, {"done", "failed"})
    assert body["state"] == "done", body["error"]
    res = body["result"]
    assert res["sweep"]["mode"] == "step" and res["sweep"]["scans_in_sweep"] >= 16 * 2
    _check_cylinder(res)


def test_cancel_a_running_sweep_stops_the_motor(hil: tuple[RigProcess, httpx.Client]) -> None:
    sim, client = hil
    mid = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    _wait_sweeping(client, mid, 5.0)
    assert client.post(f"/api/v1/measurements/{mid}/cancel", headers=AUTH).status_code == 200
    body = _wait(client, mid, {"done", "failed", "cancelled"})
    assert body["state"] == "cancelled" and body["error"] == "cancelled by request"
    assert sim.wait_motor_at_rest()["velocity_actual"] == 0
    assert body["has_raw"]
