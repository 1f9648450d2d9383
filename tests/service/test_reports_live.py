"""Reports and the engineer's page against the simulated rig (the built-in seed 003 rig, its own
rig process; the service on 127.0.0.1 over real HTTP):

* a real measurement's report over HTTP, HTML and PDF: the budget rows, the fit plot, the raw
  log's SHA-256 (checked against the bytes of ``GET .../raw``); 409 before the end and for a
  cancelled measurement, 404 for an unknown id; ``lrms report`` against the same service;
* the page at ``/`` in Debian's headless Chromium (Playwright's client, never a downloaded
  browser): start a measurement by clicking, watch the progress bar move, wait for the result,
  open its report. Screenshots go to the test's temporary folder.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.api import ServerThread, create_app
from service.config import parse_config, parse_toml
from service.rig import build_service
from tests.conftest import REPO

TOKEN = "report-op-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
FAST = {"target": "cylinder", "sweep": {"speed_deg_s": 20.0}}
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, httpx.Client]]:
    tmp = tmp_path_factory.mktemp("reports-live")
    cfg = parse_toml((REPO / "service" / "default_rig.toml").read_text(), base_dir=tmp)
    data = cfg.model_dump(mode="json")
    cfg = parse_config({**data, "auth": {"operator_token": TOKEN, "read": "open"}}, base_dir=tmp)
    svc, rig = build_service(cfg)
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=60) as client:
            yield srv.url, client
    finally:
        svc.stop()
        rig.close()


def _wait(client: httpx.Client, mid: str, states: set[str], timeout: float = 120.0) -> dict[str, Any]:
    end = time.monotonic() + timeout
    body: dict[str, Any] = {}
    while time.monotonic() < end:
        body = client.get(f"/api/v1/measurements/{mid}").json()
        if body["state"] in states:
            return body
        time.sleep(0.1)
    raise AssertionError(f"measurement {mid} did not reach {states}: {body}")


def test_report_of_a_simulated_measurement(live: tuple[str, httpx.Client], tmp_path: Path) -> None:
    import pypdf

    url, client = live
    mid = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    early = client.get(f"/api/v1/measurements/{mid}/report.html")
    assert early.status_code == 409 and "no report yet (wait until it is done)" in early.json()["detail"]
    other = client.post("/api/v1/measurements", json=FAST, headers=AUTH).json()["id"]
    assert client.post(f"/api/v1/measurements/{other}/cancel", headers=AUTH).status_code == 200
    r = client.get(f"/api/v1/measurements/{other}/report.pdf")
    assert r.status_code == 409 and "cancelled and has no result" in r.json()["detail"]
    assert client.get("/api/v1/measurements/ffffffffffffffff/report.html").status_code == 404

    body = _wait(client, mid, {"done", "failed"})
    assert body["state"] == "done", body["error"]
    result = body["result"]
    digest = hashlib.sha256(client.get(f"/api/v1/measurements/{mid}/raw").content).hexdigest()

    r = client.get(f"/api/v1/measurements/{mid}/report.html")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    html = r.text
    assert f"{mid}.mcap" in html and f"SHA-256 {digest}" in html
    assert f"{result['diameter_m'] * 1e3:.3f} mm" in html
    budget = html.split('id="budget"')[1].split("</table>")[0]
    for row in result["uncertainty"]["budget"]:
        assert f"<td>{row['source']}</td>" in budget
        assert f"{row['u_m'] * 1e6:.1f}" in budget
    assert '<img id="fit-plot" src="data:image/png;base64,' in html
    assert re.search(r'src="(https?:)?//', html) is None  # nothing from outside

    r = client.get(f"/api/v1/measurements/{mid}/report.pdf")
    assert r.status_code == 200 and r.headers["content-type"] == "application/pdf"
    reader = pypdf.PdfReader(io.BytesIO(r.content))
    flat = re.sub(r"\s+", "", "".join(p.extract_text() for p in reader.pages))
    assert mid in flat and digest in flat and "Uncertaintybudget" in flat
    assert any(len(p.images) > 0 for p in reader.pages)  # the fit plot

    # lrms report, against the same service
    env = {**os.environ, "LRMS_READ_TOKEN": ""}
    out = tmp_path / "r.pdf"
    cmd = [sys.executable, "-m", "service.cli.main", "report", mid, "--pdf", "--url", url, "--out", str(out)]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == str(out) and out.read_bytes().startswith(b"%PDF-")
    cmd = [sys.executable, "-m", "service.cli.main", "report", mid, "--url", url, "--out", "-"]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0 and f"SHA-256 {digest}" in p.stdout
    cmd = [sys.executable, "-m", "service.cli.main", "report", other, "--url", url]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path)
    assert p.returncode == 1 and "error: the service answered 409" in p.stderr and "cancelled" in p.stderr


@pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"{CHROMIUM} is absent (apt-get install chromium)")
def test_web_page_starts_a_measurement_and_opens_its_report(live: tuple[str, httpx.Client], tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    url, client = live
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            context = browser.new_context()
            page = context.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            # script errors; a refused request (the 401 below) is logged as a "Failed to load resource"
            page.on(
                "console",
                lambda m: errors.append(m.text) if m.type == "error" and "Failed to load" not in m.text else None,
            )
            page.goto(url + "/")
            # the rig's state from /healthz (ok, or degraded with reasons on a loaded machine)
            page.wait_for_function("() => /^rig: (ok|degraded)/.test(document.getElementById('health').textContent)")
            page.screenshot(path=str(tmp_path / "1-page.png"))
            # without the token the start is refused, and the page says so
            page.click("#start")
            page.wait_for_selector("#start-error:not([hidden])")
            assert "missing bearer token" in page.inner_text("#start-error")
            page.fill("#token", TOKEN)
            page.fill("#speed", "20")
            page.click("#start")
            page.wait_for_selector("#detail-section:not([hidden])")
            mid = page.inner_text("#detail-id")
            assert re.fullmatch(r"[0-9a-f]{16}", mid)
            # the progress bar moves while the sweep runs (events read by fetch streaming)
            page.wait_for_function(
                "() => { const p = document.getElementById('progress'); return p.value > 0.05 && p.value < 1; }",
                timeout=60_000,
            )
            page.screenshot(path=str(tmp_path / "2-running.png"))
            page.wait_for_function(
                "() => document.getElementById('detail-state').textContent === 'done'", timeout=120_000
            )
            assert page.eval_on_selector("#progress", "p => p.value") == 1
            page.wait_for_selector(f'#measurements tr[data-id="{mid}"] td.state-done')
            diameter = client.get(f"/api/v1/measurements/{mid}").json()["result"]["diameter_m"]
            assert f"{diameter * 1e3:.3f} mm" in page.inner_text("#detail-values")
            assert "fit (type A)" in page.inner_text("#detail-budget")
            page.screenshot(path=str(tmp_path / "3-done.png"), full_page=True)
            # its report opens from the detail panel (a token is typed in: the page fetches the
            # report with it and opens it from memory)
            with context.expect_page() as new_page:
                page.click("text=report (HTML)")
            report = new_page.value
            report.wait_for_load_state()
            assert report.url.startswith("blob:")
            assert report.inner_text("#measurement-id") == mid
            assert "SHA-256" in report.inner_text("#raw-log")
            report.screenshot(path=str(tmp_path / "4-report.png"), full_page=True)
            assert errors == []
        finally:
            browser.close()
