"""``lrms measure --server URL``: the command as a client of a running ``lrms serve`` (default
simulated rig, on 127.0.0.1), over real HTTP."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import ClassVar

import httpx
import pytest

from service import mcaplog
from tests.conftest import REPO
from tests.service.test_cli import LRMS, announced_url

TOKEN = "0perator-remote-5e1a"
#: What the client must not load: its start is the interpreter's plus the standard library's.
HEAVY = ("numpy", "pydantic", "fastapi", "httpx", "scipy", "sqlalchemy", "service.config", "service.rig")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("LRMS_")}
    return {**env, "PYTHONPATH": str(REPO), **extra}


@contextlib.contextmanager
def _running(args: list[str], env: dict[str, str], stderr: int = subprocess.PIPE) -> Iterator[subprocess.Popen[str]]:
    """``lrms ARGS`` started in the background (stdout piped; stderr piped unless told), stopped
    on leaving if it still runs: SIGTERM, then SIGKILL past 30 s."""
    proc = subprocess.Popen([*LRMS, *args], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=stderr, text=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``lrms serve`` on a free loopback port with an operator token; its base URL once it answers."""
    data = tmp_path_factory.mktemp("serve")
    serve = ["serve", "--port", "0", "--data", str(data), "--log-level", "warning"]
    with _running(serve, _env(LRMS_OPERATOR_TOKEN=TOKEN), stderr=subprocess.DEVNULL) as proc:
        url = announced_url(proc)
        end = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/api/v1/rig", timeout=10).json()["scanner"]["connected"]:
                    break
            except httpx.HTTPError:
                pass
            assert proc.poll() is None and time.monotonic() < end, "lrms serve did not come up"
            time.sleep(0.2)
        yield url


def _measure(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*LRMS, "measure", *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=180)


def test_measure_on_a_running_service_prints_its_result_and_fetches_the_raw_log(server: str, tmp_path: Path) -> None:
    """The command posts the measurement, follows it to the end and prints the service's result
    (with the measurement's id and the URLs of its raw log and cloud); ``--out`` / ``--cloud``
    fetch those. A probe runs the command in a process that then lists what it loaded: no numpy,
    pydantic, web stack or HTTP library (the rig and the fit are the service's)."""
    out, cloud = tmp_path / "run.mcap", tmp_path / "run.ply"
    argv = ["measure", "--server", server, "--target", "cylinder", "--speed", "45", "--quiet"]
    argv += ["--out", str(out), "--cloud", str(cloud)]
    code = (
        "import sys, io, contextlib\n"
        "from service.cli import main\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        f"    status = main.main({argv!r})\n"
        "print(buf.getvalue())\n"
        f"print('STATUS', status, 'HEAVY:', *[m for m in {HEAVY!r} if m in sys.modules])\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, env=_env(LRMS_OPERATOR_TOKEN=TOKEN), capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    body, last = proc.stdout.rstrip().rsplit("\n", 1)
    assert last == "STATUS 0 HEAVY:", (last, proc.stderr[-2000:])
    printed = json.loads(body)
    mid = printed["measurement_id"]  # the service's result carries it
    assert printed.pop("raw_url") == f"{server}/api/v1/measurements/{mid}/raw"
    assert printed.pop("cloud_url") == f"{server}/api/v1/measurements/{mid}/cloud"
    stored = httpx.get(f"{server}/api/v1/measurements/{mid}", timeout=10).json()
    assert stored["state"] == "done" and stored["request"]["sweep"]["speed_deg_s"] == 45
    assert printed == stored["result"]
    assert printed["model"] == "cylinder" and 0.1 < printed["diameter_m"] < 0.4
    assert out.read_bytes() == httpx.get(f"{server}/api/v1/measurements/{mid}/raw", timeout=30).content
    msgs, _ = mcaplog.read_log(out)
    assert any(m.topic == mcaplog.TOPIC_MEASUREMENT for m in msgs)
    assert cloud.read_bytes().startswith(b"ply")


def test_refusals_are_one_line_errors(server: str) -> None:
    base = ["--server", server, "--target", "cylinder", "--quiet"]
    no_token = _measure(base, _env())
    assert no_token.returncode == 1 and "answered 401" in no_token.stderr and "bearer token" in no_token.stderr
    too_fast = _measure([*base, "--speed", "4500"], _env(LRMS_OPERATOR_TOKEN=TOKEN))
    assert too_fast.returncode == 1 and "answered 422" in too_fast.stderr, too_fast.stderr
    assert "speed_deg_s" in too_fast.stderr and too_fast.stderr.count("\n") == 1
    local = _measure([*base, "--token", TOKEN, "--plot", "x.png", "--data", "d"], _env())
    assert local.returncode == 1 and "not with --server: --data, --plot" in local.stderr, local.stderr
    gone = _measure(["--server", "http://127.0.0.1:9", "--target", "cylinder", "--token", TOKEN], _env())
    assert gone.returncode == 1 and "cannot reach the service at http://127.0.0.1:9" in gone.stderr, gone.stderr
    # nothing was queued by the refused requests
    listed = httpx.get(f"{server}/api/v1/measurements", timeout=10).json()
    assert all(m["request"]["sweep"].get("speed_deg_s") != 4500 for m in listed)


def test_ctrl_c_cancels_the_measurement_on_the_service(server: str) -> None:
    measure = ["measure", "--server", server, "--target", "cylinder", "--speed", "5", "--quiet"]
    with _running(measure, _env(LRMS_OPERATOR_TOKEN=TOKEN)) as proc:
        end = time.monotonic() + 60
        running = None
        while running is None:  # the newest measurement of the 5 deg/s sweep, once it runs
            listed = httpx.get(f"{server}/api/v1/measurements", params={"limit": 1}, timeout=10).json()
            if listed and listed[0]["request"]["sweep"].get("speed_deg_s") == 5 and listed[0]["state"] == "running":
                running = listed[0]["id"]
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err, err
    end = time.monotonic() + 60
    while (state := httpx.get(f"{server}/api/v1/measurements/{running}", timeout=10).json()["state"]) == "running":
        assert time.monotonic() < end, "the cancelled measurement still runs"
        time.sleep(0.2)
    assert state == "cancelled", state


def test_wait_gives_up_cancels_and_fails(server: str) -> None:
    """``--wait`` bounds the whole wait: past it the command says so, cancels the measurement on
    the service and exits 1."""
    cmd = ["--server", server, "--target", "cylinder", "--speed", "5", "--quiet", "--wait", "1.5"]
    p = _measure(cmd, _env(LRMS_OPERATOR_TOKEN=TOKEN))
    assert p.returncode == 1 and "did not end within --wait 1.5 s" in p.stderr, p.stderr
    assert "cancelled on the service" in p.stderr and p.stderr.count("\n") == 1, p.stderr
    found = re.search(r"measurement (\w+) did not end", p.stderr)
    assert found is not None, p.stderr
    end = time.monotonic() + 60
    url = f"{server}/api/v1/measurements/{found.group(1)}"
    while (state := httpx.get(url, timeout=10).json()["state"]) in ("queued", "running"):
        assert time.monotonic() < end, "the measurement past --wait still runs"
        time.sleep(0.2)
    assert state == "cancelled", state


def test_client_only_options_are_refused_without_server() -> None:
    for extra, named in (
        (["--token", TOKEN], "--token"),
        (["--timeout", "5", "--wait", "3"], "--timeout, --wait"),
    ):
        p = _measure(["--target", "cylinder", "--quiet", *extra], _env())
        assert p.returncode == 1 and f"error: only with --server: {named}" in p.stderr, p.stderr
        assert p.stderr.count("\n") == 1, p.stderr


class _FakeService(BaseHTTPRequestHandler):
    """Not an lrms service: each test sets ``mode`` and reads ``seen`` (the requests' lines)."""

    mode = ""
    seen: ClassVar[list[str]] = []
    posted = threading.Event()

    def log_message(self, format: str, *args: object) -> None:  # quiet
        pass

    def _send(self, body: bytes, ctype: str = "application/json", length: int | None = None) -> None:
        self.send_response(200)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body) if length is None else length))
        self.end_headers()
        self.wfile.write(body)
        self.wfile.flush()

    def do_POST(self) -> None:
        self.seen.append(f"POST {self.path}")
        self.rfile.read(int(self.headers.get("Content-Length") or 0))
        if self.path.endswith("/cancel"):
            self._send(json.dumps({"id": "m7", "state": "cancelled"}).encode())
        elif self.mode == "html":
            self._send(b"<html><body>a proxy's login page</body></html>", "text/html")
        elif self.mode == "cut":
            done = {"id": "m7", "state": "done", "has_raw": True, "has_cloud": False, "result": {"model": "x"}}
            self._send(json.dumps(done).encode())
        elif self.mode == "slow":
            type(self).posted.set()
            time.sleep(1.5)
            self._send(json.dumps({"id": "m7", "state": "queued"}).encode())

    def do_GET(self) -> None:
        self.seen.append(f"GET {self.path}")
        if self.path.endswith("/raw"):  # a tenth of the promised body, then silence
            self._send(b"\x89MCAP0\r\n" * 100, "application/octet-stream", length=9000)
            time.sleep(3)
        else:
            self._send(json.dumps({"id": "m7", "state": "running", "progress": 0.1}).encode())


@pytest.fixture()
def fake() -> Iterator[tuple[str, type[_FakeService]]]:
    _FakeService.seen = []
    _FakeService.posted = threading.Event()
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _FakeService)
    httpd.daemon_threads = True
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", _FakeService
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_a_reply_that_is_not_the_api_is_a_one_line_error(fake: tuple[str, type[_FakeService]]) -> None:
    url, svc = fake
    svc.mode = "html"
    p = _measure(["--server", url, "--target", "cylinder", "--quiet", "--token", TOKEN], _env())
    assert p.returncode == 1 and p.stderr.count("\n") == 1, p.stderr
    assert f"error: the reply to POST /api/v1/measurements from {url} is not an lrms API answer" in p.stderr


def test_a_download_cut_short_leaves_the_out_file_as_it_was(
    fake: tuple[str, type[_FakeService]], tmp_path: Path
) -> None:
    """The raw log stops after 900 of 9,000 bytes: the read times out (``--timeout 0.5``), the
    command fails on one line, and ``--out`` keeps its old content (no half-written file, no
    temporary file left beside it)."""
    url, svc = fake
    svc.mode = "cut"
    out = tmp_path / "run.mcap"
    out.write_bytes(b"an older run")
    argv = ["--server", url, "--target", "cylinder", "--quiet", "--token", TOKEN, "--timeout", "0.5"]
    p = _measure([*argv, "--out", str(out)], _env())
    assert p.returncode == 1 and p.stderr.count("\n") == 1, p.stderr
    assert "the reply to GET /api/v1/measurements/m7/raw" in p.stderr and "not an lrms API answer" in p.stderr
    assert out.read_bytes() == b"an older run"
    assert sorted(f.name for f in tmp_path.iterdir()) == ["run.mcap"]


def test_ctrl_c_during_the_request_cancels_once_the_id_is_known(fake: tuple[str, type[_FakeService]]) -> None:
    """Ctrl-C while the POST waits for its answer: the command holds it, takes the answered id,
    cancels that measurement and exits 130."""
    url, svc = fake
    svc.mode = "slow"
    with _running(["measure", "--server", url, "--target", "cylinder", "--quiet", "--token", TOKEN], _env()) as proc:
        assert svc.posted.wait(60), proc.communicate()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err, err
    assert svc.seen == ["POST /api/v1/measurements", "POST /api/v1/measurements/m7/cancel"], svc.seen
