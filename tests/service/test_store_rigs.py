"""Two rigs' services over HTTP sharing one result database (SQLite file or PostgreSQL): each runs its
own queue and schedules, the listing shows both rigs (``?rig=`` picks one), nothing is lost when
both take measurements at once; and ``lrms serve`` on PostgreSQL by ``[storage] url``."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.api import ServerThread, Service, create_app
from service.cli.serve import LISTENING
from service.config import TOKEN_ENV, parse_toml
from tests.conftest import REPO
from tests.service.pgserver import PostgresServer
from tests.service.test_api import GatedMeasure

TOKEN = "t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _config(tmp_path: Path, rig: str, url: str) -> Any:
    return parse_toml(
        f"[sim]\n[storage]\ndir = '{tmp_path / rig}'\nurl = '{url}'\nrig_id = '{rig}'\n"
        f"[schedules]\nmin_interval_s = 1\n[auth]\nread = 'open'\nadmin_token = '{TOKEN}'\n"
    )


@pytest.fixture
def two_rigs(
    tmp_path: Path, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> Iterator[list[tuple[httpx.Client, GatedMeasure, Service]]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    with ExitStack() as stack:
        out = []
        for rig in ("press-1", "press-2"):
            measure = GatedMeasure()
            svc = Service(_config(tmp_path, rig, db_url), measure)
            srv = stack.enter_context(ServerThread(create_app(svc)))
            client = stack.enter_context(httpx.Client(base_url=srv.url, timeout=30.0))
            out.append((client, measure, svc))
        yield out
        for _, measure, _ in out:
            for _ in range(50):
                measure.gate.release()


def _wait(client: httpx.Client, pred: Any, what: str, timeout: float = 60.0) -> list[dict[str, Any]]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        body: list[dict[str, Any]] = client.get("/api/v1/measurements", params={"limit": 1000}).json()
        if pred(body):
            return body
        time.sleep(0.05)
    raise AssertionError(f"never: {what}")


def test_two_rigs_share_one_database(two_rigs: list[tuple[httpx.Client, GatedMeasure, Service]]) -> None:
    (c1, m1, _), (c2, m2, s2) = two_rigs
    n = 8
    posted: dict[str, list[str]] = {"press-1": [], "press-2": []}
    refused: list[str] = []

    def post(client: httpx.Client, rig: str) -> None:
        for _ in range(n):
            r = client.post("/api/v1/measurements", json={"target": "cylinder"}, headers=AUTH)
            if r.status_code != 202:
                refused.append(r.text)
                return
            posted[rig].append(r.json()["id"])

    threads = [threading.Thread(target=post, args=a) for a in ((c1, "press-1"), (c2, "press-2"))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert refused == [] and all(len(ids) == n for ids in posted.values())
    for _ in range(n):  # both rigs measure at once
        m1.gate.release()
        m2.gate.release()
    body = _wait(c1, lambda b: len(b) == 2 * n and all(m["state"] == "done" for m in b), "all done")
    # every measurement of both rigs, each run by its own rig's service, in its own queue order
    assert {m["id"]: m["rig_id"] for m in body} == {i: r for r, ids in posted.items() for i in ids}
    assert m1.started == posted["press-1"] and m2.started == posted["press-2"]
    only2 = c1.get("/api/v1/measurements", params={"rig": "press-2", "limit": 1000}).json()
    assert sorted(m["id"] for m in only2) == sorted(posted["press-2"])
    assert c2.get("/api/v1/measurements", params={"rig": "bad rig"}).status_code == 422
    # one rig's service reads the other's measurement, and may not cancel it
    other = posted["press-2"][0]
    assert c1.get(f"/api/v1/measurements/{other}").json()["rig_id"] == "press-2"
    # a schedule of rig 1 fires on rig 1 only
    sched = c1.post(
        "/api/v1/schedules",
        json={"interval_s": 1, "name": "often", "measurement": {"target": "cylinder"}},
        headers=AUTH,
    )
    assert sched.status_code == 201 and sched.json()["rig_id"] == "press-1"
    sid = sched.json()["id"]
    body = _wait(c2, lambda b: sum(m["schedule_id"] == sid for m in b) >= 2, "two scheduled runs")
    assert {m["rig_id"] for m in body if m["schedule_id"] == sid} == {"press-1"}
    assert [s["id"] for s in c2.get("/api/v1/schedules", params={"rig": "press-1"}).json()] == [sid]
    assert c2.get("/api/v1/schedules", params={"rig": "press-2"}).json() == []
    assert s2.store.count_by_state()["queued"] == 0  # rig 2's queue never held rig 1's runs
    assert c2.delete(f"/api/v1/schedules/{sid}", headers=AUTH).status_code == 409
    assert c1.delete(f"/api/v1/schedules/{sid}", headers=AUTH).status_code == 204


def test_lrms_serve_on_postgresql(tmp_path: Path, postgres_server: PostgresServer) -> None:
    """``lrms serve`` with ``[storage] url`` on PostgreSQL: it migrates the empty database at start-up,
    says where its results go (without the password), and its measurements carry its rig id."""
    url = postgres_server.new_database().replace("postgresql://lrms@", "postgresql://lrms:s3cret-pw@")
    config = tmp_path / "rig.toml"
    config.write_text(
        f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\nurl = '{url}'\nrig_id = 'press-7'\n"
        f"[auth]\nread = 'open'\nadmin_token = '{TOKEN}'\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli.main", "serve", "--config", str(config), "--port", "0"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if line.startswith(LISTENING):
                break
        else:
            err = proc.stderr.read() if proc.stderr else ""
            raise AssertionError(f"lrms serve did not start: {''.join(lines)} {err}")
        base = lines[-1][len(LISTENING) :].strip()
        text = "".join(lines)
        assert "rig id press-7" in text and "postgresql://lrms:***@/" in text and "s3cret" not in text
        with httpx.Client(base_url=base, timeout=30) as client:
            r = client.post("/api/v1/measurements", json={"target": "cylinder"}, headers=AUTH)
            assert r.status_code == 202 and r.json()["rig_id"] == "press-7"
            assert client.post(f"/api/v1/measurements/{r.json()['id']}/cancel", headers=AUTH).status_code == 200
            listed = client.get("/api/v1/measurements", params={"rig": "press-7"}).json()
            assert [m["id"] for m in listed] == [r.json()["id"]]
    finally:
        proc.terminate()
        proc.wait(30)
