"""The REST API over real HTTP (uvicorn on 127.0.0.1, ephemeral port; httpx client).

These tests exercise the API, the queue, persistence and schedules with a measurement function
that writes a real MCAP log and PLY cloud and waits on a gate, so that queueing and cancellation
are deterministic. The full measurement through the simulated rig is in test_rig_sim.py.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service import mcaplog
from service.api import ServerThread, Service, create_app
from service.config import TOKEN_ENV, parse_toml
from service.jobs import JobContext
from service.store import Store

TOKEN = "t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
CYL = {"target": "cylinder"}


class GatedMeasure:
    """Runs one measurement per gate release; writes a small raw log and cloud like the rig does."""

    def __init__(self) -> None:
        self.gate = threading.Semaphore(0)
        self.started: list[str] = []

    def __call__(self, ctx: JobContext) -> dict[str, Any]:
        self.started.append(ctx.measurement.id)
        ctx.progress(0.1, "sweeping")
        with mcaplog.McapLog(ctx.raw_path) as log:
            log.log_json(mcaplog.TOPIC_MEASUREMENT, 1, {"id": ctx.measurement.id})
            while not self.gate.acquire(timeout=0.02):
                ctx.check_cancelled()
            ctx.progress(0.9, "fitting")
            log.log_json(mcaplog.TOPIC_RESULT, 2, {"n": len(self.started)})
        ctx.cloud_path.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
        return {"target": ctx.request.target, "order": len(self.started)}


def _config(tmp_path: Path, token: str | None = TOKEN) -> Any:
    """Reads open (the role checks are in test_security.py); ``token`` is the admin token (it may
    do everything). Schedules may fire every second here (the default minimum interval is 60 s)."""
    text = f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\n[schedules]\nmin_interval_s = 1\n[auth]\nread = 'open'\n"
    if token is not None:
        text += f"admin_token = '{token}'\n"
    return parse_toml(text)


@pytest.fixture
def served(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[httpx.Client, GatedMeasure, Service]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    measure = GatedMeasure()
    svc = Service(_config(tmp_path), measure, rig_info=lambda: {"scanner": {"connected": False}})
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as client:
        yield client, measure, svc
        for _ in range(20):
            measure.gate.release()


def _wait_state(client: httpx.Client, mid: str, states: set[str], timeout: float = 20.0) -> dict[str, Any]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        body: dict[str, Any] = client.get(f"/api/v1/measurements/{mid}").json()
        if body["state"] in states:
            return body
        time.sleep(0.02)
    raise AssertionError(f"measurement {mid} never reached {states}")


def test_health_rig_metrics_and_openapi(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, _, _ = served
    assert client.get("/healthz").json()["status"] == "ok"
    rig = client.get("/api/v1/rig").json()
    assert rig["simulated"] is True and rig["write_enabled"] is True and rig["scanner"] == {"connected": False}
    assert "token" not in json.dumps(rig)
    spec = client.get("/openapi.json").json()
    assert {"/api/v1/measurements", "/api/v1/schedules/{sid}", "/api/v1/measurements/{mid}/events"} <= set(
        spec["paths"]
    )
    assert client.get("/docs").status_code == 200
    metrics = client.get("/metrics")
    assert metrics.status_code == 200 and "lrms_measurements_queued" in metrics.text
    assert 'lrms_http_requests_total{method="GET",route="/healthz",status="200"}' in metrics.text


def test_write_endpoints_need_the_token(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, _, _ = served
    r = client.post("/api/v1/measurements", json=CYL)
    assert r.status_code == 401 and "missing bearer token" in r.json()["detail"]
    r = client.post("/api/v1/measurements", json=CYL, headers={"Authorization": "Bearer nope"})
    assert r.status_code == 401 and r.json()["detail"] == "invalid bearer token"
    r = client.post("/api/v1/schedules", json={"interval_s": 60, "measurement": CYL})
    assert r.status_code == 401
    assert client.get("/api/v1/measurements").status_code == 200  # reading is open


def test_no_token_configured_disables_writes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    svc = Service(_config(tmp_path, token=None), GatedMeasure())
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url) as client:
        r = client.post("/api/v1/measurements", json=CYL, headers=AUTH)
        assert r.status_code == 403 and "write endpoints are disabled" in r.json()["detail"]
        monkeypatch.setenv(TOKEN_ENV, TOKEN)  # the (deprecated) environment variable enables them
        r = client.post("/api/v1/measurements", json=CYL, headers=AUTH)
        assert r.status_code == 202


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ({"target": "sphere"}, "body.target"),
        ({}, "body: target: Field required"),
        ({"target": "cylinder", "sweep": {"speed_deg_s": -5}}, "body.sweep.speed_deg_s"),
        ({"target": "cylinder", "sweep": {"start_deg": 10, "stop_deg": 10}}, "must differ"),
        ({"target": "cylinder", "sweep": {"mode": "zigzag"}}, "body.sweep.mode"),
        ({"target": "cylinder", "roi": {"min_m": [0, 0, 0], "max_m": [1, -1, 1]}}, "below max_m"),
        ({"target": "cylinder", "options": {"kk": 3}}, "body.options.kk: Extra inputs are not permitted"),
        ({"target": "cylinder", "colour": "red"}, "body.colour"),
        ({"target": "cylinder", "options": {"monte_carlo": 20}}, "at least 40 replicas"),
    ],
)
def test_bad_measurement_requests_are_422_with_a_message(
    served: tuple[httpx.Client, GatedMeasure, Service], body: dict[str, Any], needle: str
) -> None:
    client, _, _ = served
    r = client.post("/api/v1/measurements", json=body, headers=AUTH)
    assert r.status_code == 422
    text = r.json().get("message") or r.json()["detail"]
    assert needle in text, text


def test_not_found_conflict_and_bad_query(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, _, _ = served
    r = client.get("/api/v1/measurements/doesnotexist")
    assert r.status_code == 404 and "no measurement" in r.json()["detail"]
    assert client.get("/api/v1/measurements", params={"state": "sleeping"}).status_code == 422
    assert client.post("/api/v1/measurements", content=b"{not json", headers=AUTH).status_code == 422
    mid = client.post("/api/v1/measurements", json=CYL, headers=AUTH).json()["id"]
    r = client.get(f"/api/v1/measurements/{mid}/raw")
    assert r.status_code == 409 and "not complete" in r.json()["detail"]
    assert client.delete("/api/v1/schedules/nope", headers=AUTH).status_code == 404


def test_one_sweep_at_a_time_in_order_with_cancel(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, measure, _ = served
    ids = []
    for _ in range(4):
        r = client.post("/api/v1/measurements", json=CYL, headers=AUTH)
        assert r.status_code == 202 and r.headers["location"] == f"/api/v1/measurements/{r.json()['id']}"
        ids.append(r.json()["id"])
    _wait_state(client, ids[0], {"running"})
    states = [client.get(f"/api/v1/measurements/{i}").json()["state"] for i in ids]
    assert states == ["running", "queued", "queued", "queued"]
    # cancel a queued one at once, and the running one
    assert client.post(f"/api/v1/measurements/{ids[2]}/cancel", headers=AUTH).json()["state"] == "cancelled"
    client.post(f"/api/v1/measurements/{ids[0]}/cancel", headers=AUTH)
    first = _wait_state(client, ids[0], {"cancelled"})
    assert first["error"] == "cancelled by request" and first["has_raw"]  # the partial log is kept
    assert client.post(f"/api/v1/measurements/{ids[0]}/cancel", headers=AUTH).status_code == 409
    _wait_state(client, ids[1], {"running"})
    measure.gate.release()
    second = _wait_state(client, ids[1], {"done"})
    _wait_state(client, ids[3], {"running"})
    measure.gate.release()
    fourth = _wait_state(client, ids[3], {"done"})
    assert measure.started == [ids[0], ids[1], ids[3]]
    assert second["result"] == {"target": "cylinder", "order": 2} and fourth["result"]["order"] == 3
    assert second["started_at"] >= first["finished_at"]
    # downloads
    raw = client.get(f"/api/v1/measurements/{ids[1]}/raw")
    assert raw.status_code == 200 and raw.headers["content-type"] == "application/x-mcap"
    assert raw.content[:8] == b"\x89MCAP0\r\n"
    cloud = client.get(f"/api/v1/measurements/{ids[1]}/cloud")
    assert cloud.status_code == 200 and cloud.text.startswith("ply")
    listed = client.get("/api/v1/measurements", params={"state": "done"}).json()
    assert [m["id"] for m in listed] == [ids[3], ids[1]]


def test_server_sent_events_follow_progress_to_the_end(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, measure, _ = served
    mid = client.post("/api/v1/measurements", json=CYL, headers=AUTH).json()["id"]
    events = []
    with client.stream("GET", f"/api/v1/measurements/{mid}/events") as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("data: "):
                ev = json.loads(line[6:])
                events.append(ev)
                if ev["state"] == "running" and ev["message"] == "sweeping":
                    measure.gate.release()
    assert events[-1]["state"] == "done" and events[-1]["progress"] == 1.0
    assert any(e["message"] == "sweeping" for e in events)
    assert client.get("/api/v1/measurements/nope/events").status_code == 404


def test_persistence_and_queued_work_resume_after_restart(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = _config(tmp_path)
    stuck = GatedMeasure()  # never released: the "process" dies during this sweep
    svc1 = Service(cfg, stuck)
    svc1.start()
    with ServerThread(create_app(svc1, manage_lifecycle=False)) as srv, httpx.Client(base_url=srv.url) as client:
        a = client.post("/api/v1/measurements", json=CYL, headers=AUTH).json()["id"]
        b = client.post("/api/v1/measurements", json={"target": "elbow"}, headers=AUTH).json()["id"]
        sched = client.post(
            "/api/v1/schedules", json={"cron": "0 3 * * *", "name": "nightly", "measurement": CYL}, headers=AUTH
        )
        assert sched.status_code == 201
        _wait_state(client, a, {"running"})
    # the HTTP server is gone and the worker never finished: a crash as far as the store knows
    svc1.scheduler.stop()
    fresh = GatedMeasure()
    svc2 = Service(cfg, fresh, store=Store(cfg.storage.db_path))
    with ServerThread(create_app(svc2)) as srv, httpx.Client(base_url=srv.url) as client:
        first = client.get(f"/api/v1/measurements/{a}").json()
        assert first["state"] == "failed" and "restart" in first["error"]
        _wait_state(client, b, {"running"})
        fresh.gate.release()
        done = _wait_state(client, b, {"done"})
        assert done["request"]["target"] == "elbow" and fresh.started == [b]
        scheds = client.get("/api/v1/schedules").json()
        assert [s["name"] for s in scheds] == ["nightly"] and scheds[0]["cron"] == "0 3 * * *"
        assert scheds[0]["next_run"] > time.time()


def test_schedules_fire_and_can_be_deleted(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, measure, _ = served
    r = client.post("/api/v1/schedules", json={"cron": "61 * * * *", "measurement": CYL}, headers=AUTH)
    assert r.status_code == 422 and "body.cron: not a valid cron" in r.json()["message"]
    r = client.post("/api/v1/schedules", json={"cron": "* * * * *", "interval_s": 5, "measurement": CYL}, headers=AUTH)
    assert r.status_code == 422 and "exactly one" in r.json()["message"]
    r = client.post("/api/v1/schedules", json={"interval_s": 0.5, "measurement": CYL}, headers=AUTH)
    assert r.status_code == 422 and "interval_s" in r.json()["message"]
    r = client.post(
        "/api/v1/schedules",
        json={"interval_s": 1, "name": "often", "measurement": {"target": "cylinder", "sweep": {"speed_deg_s": 5}}},
        headers=AUTH,
    )
    assert r.status_code == 201
    sid = r.json()["id"]
    assert client.get(f"/api/v1/schedules/{sid}").json()["interval_s"] == 1.0
    end = time.monotonic() + 20
    fired: list[dict[str, Any]] = []
    while time.monotonic() < end and not fired:
        fired = [m for m in client.get("/api/v1/measurements").json() if m["schedule_id"] == sid]
        time.sleep(0.05)
    assert fired and fired[0]["request"]["sweep"]["speed_deg_s"] == 5
    assert client.delete(f"/api/v1/schedules/{sid}", headers=AUTH).status_code == 204
    assert client.get(f"/api/v1/schedules/{sid}").status_code == 404
    for _ in range(10):
        measure.gate.release()


def test_measurement_function_failure_is_recorded_with_its_reason(tmp_path: Path) -> None:
    from service.sweep import SweepError

    def failing(ctx: JobContext) -> dict[str, Any]:
        ctx.progress(0.3, "sweeping")
        raise SweepError("motor fault 0x8611: following error")

    def crashing(ctx: JobContext) -> dict[str, Any]:
        values: list[float] = []
        return {"first": values[0]}  # a bug: IndexError

    for fn, needle in ((failing, "motor fault 0x8611: following error"), (crashing, "internal error: IndexError")):
        svc = Service(_config(tmp_path / fn.__name__), fn)
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url) as client:
            mid = client.post("/api/v1/measurements", json=CYL, headers=AUTH).json()["id"]
            body = _wait_state(client, mid, {"failed"})
            assert body["error"].startswith(needle)


def test_polled_reads_follow_every_change(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    """The read endpoints answer repeated polls from a cache; every change shows in the next poll,
    including a write by another connection to the same database."""
    client, measure, svc = served
    assert client.get("/api/v1/measurements").json() == []
    mid = client.post("/api/v1/measurements", headers=AUTH, json=CYL).json()["id"]
    polls = [client.get(f"/api/v1/measurements/{mid}").json() for _ in range(3)]
    assert [p["id"] for p in polls] == [mid] * 3
    listed = client.get("/api/v1/measurements?limit=20").json()
    assert [m["id"] for m in listed] == [mid]
    again = client.get("/api/v1/measurements?limit=20")
    assert again.json() == client.get("/api/v1/measurements?limit=20").json()
    assert svc.cache.hits > 0
    _wait_state(client, mid, {"running"})
    end = time.monotonic() + 20.0  # the progress the measurement reported reaches the poll
    while client.get(f"/api/v1/measurements/{mid}").json()["message"] != "sweeping":
        assert time.monotonic() < end, "progress never showed"
        time.sleep(0.02)
    assert client.get(f"/api/v1/measurements/{mid}").json()["progress"] == pytest.approx(0.1)
    assert client.get("/healthz").json()["running"] == mid
    measure.gate.release()
    done = _wait_state(client, mid, {"done"})
    assert done["result"]["order"] == 1 and done["has_raw"] and done["has_cloud"]
    assert client.get("/api/v1/measurements?limit=20").json()[0]["state"] == "done"
    assert client.get("/api/v1/measurements?state=done").json()[0]["id"] == mid
    assert client.get("/healthz").json()["running"] is None
    # another connection (another process, say) adds a schedule: the next poll has it
    assert client.get("/api/v1/schedules").json() == []
    other = Store(svc.config.storage.db_path)
    try:
        sid = other.add_schedule(CYL, interval_s=3600.0, next_run=time.time() + 3600.0).id
    finally:
        other.close()
    assert [s["id"] for s in client.get("/api/v1/schedules").json()] == [sid]


def test_responses_carry_the_app_time(served: tuple[httpx.Client, GatedMeasure, Service]) -> None:
    client, _, _ = served
    r = client.get("/api/v1/measurements")
    name, _, dur = r.headers["server-timing"].partition(";dur=")
    assert name == "app" and float(dur) >= 0.0
    spec = client.get("/openapi.json").json()  # the cached bytes keep their documented schema
    schema = spec["paths"]["/api/v1/measurements/{mid}"]["get"]["responses"]["200"]["content"]["application/json"]
    assert schema["schema"]["$ref"].endswith("/MeasurementOut")
    assert "lrms_http_request_seconds_bucket" in client.get("/metrics").text
    # the event loop's lag is watched while the app serves
    end = time.monotonic() + 10.0
    while "lrms_event_loop_lag_seconds_count 0.0" in client.get("/metrics").text:
        assert time.monotonic() < end, "the event-loop lag watcher never observed"
        time.sleep(0.05)
    assert "lrms_event_loop_lag_seconds_count" in client.get("/metrics").text


def test_rig_state_follows_the_devices(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """GET /rig re-reads the device state (at most every 0.25 s): a change shows in a later poll."""
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    state = {"scanner": {"connected": False}}
    calls = [0]

    def rig_info() -> dict[str, Any]:
        calls[0] += 1
        return {"scanner": dict(state["scanner"])}

    svc = Service(_config(tmp_path), GatedMeasure(), rig_info=rig_info)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as client:
        first = client.get("/api/v1/rig").json()
        assert first["scanner"] == {"connected": False} and first["name"] == svc.config.name
        state["scanner"] = {"connected": True}
        end = time.monotonic() + 10.0
        while client.get("/api/v1/rig").json()["scanner"] != {"connected": True}:
            assert time.monotonic() < end, "GET /rig never showed the new device state"
            time.sleep(0.05)
        assert calls[0] >= 2
