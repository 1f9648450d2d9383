"""Security of the REST API over real HTTP: token roles, reads behind a token, the body guard (token
and size decided before the body is read), /docs from local assets; ``lrms serve`` with TLS, its
warning beyond loopback, and no secret in its output.

The measurement function is the gated fake of test_api.py (the real rig is test_rig_sim.py's); the
``lrms serve`` tests run the default simulated rig in a subprocess.
"""

from __future__ import annotations

import json
import os
import re
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.api import ServerThread, Service, create_app
from service.cli.serve import LISTENING, WARNING, exposure_warnings, is_loopback
from service.config import DEFAULT_RIG, TOKEN_ENV, TOKEN_ENVS, load_config, parse_toml
from tests.conftest import REPO
from tests.service.test_api import GatedMeasure

READER, OPERATOR, ADMIN = "r3ad-token-4a1f", "0perator-token-9c2e", "adm1n-token-77d0"
CYL = {"target": "cylinder"}
LIMIT = 1 << 20
LRMS = [sys.executable, "-m", "service.cli.main"]


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(autouse=True)
def _no_token_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for var in (TOKEN_ENV, *TOKEN_ENVS.values()):
        monkeypatch.delenv(var, raising=False)


def _config(tmp_path: Path, auth: str) -> Any:
    return parse_toml(
        f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\n[auth]\n{auth}\n[api]\nmax_body_bytes = {LIMIT}\n"
    )


ALL_ROLES = f"read = 'token'\nread_token = '{READER}'\noperator_token = '{OPERATOR}'\nadmin_token = '{ADMIN}'"


@pytest.fixture
def locked(tmp_path: Path) -> Iterator[tuple[httpx.Client, ServerThread, GatedMeasure]]:
    """A service with all three tokens and ``read = "token"``."""
    measure = GatedMeasure()
    svc = Service(_config(tmp_path, ALL_ROLES), measure, rig_info=lambda: {"scanner": {"connected": False}})
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as client:
        yield client, srv, measure
        for _ in range(20):
            measure.gate.release()


# -- roles --------------------------------------------------------------------------------


def test_every_read_needs_a_token_of_any_role(locked: tuple[httpx.Client, ServerThread, GatedMeasure]) -> None:
    client, _, _ = locked
    mid = client.post("/api/v1/measurements", json=CYL, headers=bearer(OPERATOR)).json()["id"]
    sid = client.post("/api/v1/schedules", json={"interval_s": 3600, "measurement": CYL}, headers=bearer(ADMIN))
    reads = [
        "/api/v1/rig",
        "/api/v1/measurements",
        f"/api/v1/measurements/{mid}",
        f"/api/v1/measurements/{mid}/raw",
        f"/api/v1/measurements/{mid}/cloud",
        f"/api/v1/measurements/{mid}/events",
        "/api/v1/schedules",
        f"/api/v1/schedules/{sid.json()['id']}",
        "/metrics",
    ]
    for path in reads:
        r = client.get(path)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer", (path, r.text)
        assert client.get(path, headers=bearer("wrong")).status_code == 401, path
        for token in (READER, OPERATOR, ADMIN):
            # raw and cloud: 409 while the gated measurement runs; the events stream is left at once
            with client.stream("GET", path, headers=bearer(token)) as r:
                assert r.status_code in (200, 409), (path, r.status_code)
    # probes and the API's description stay open
    assert client.get("/healthz").json()["status"] == "ok"
    assert client.get("/openapi.json").status_code == 200 and client.get("/docs").status_code == 200


def test_operator_starts_and_cancels_admin_does_everything(
    locked: tuple[httpx.Client, ServerThread, GatedMeasure],
) -> None:
    client, _, _ = locked
    r = client.post("/api/v1/measurements", json=CYL, headers=bearer(READER))
    assert r.status_code == 403 and "needs the operator or admin token" in r.json()["detail"]
    assert r.json()["detail"].endswith("a read token")
    a = client.post("/api/v1/measurements", json=CYL, headers=bearer(OPERATOR))
    b = client.post("/api/v1/measurements", json=CYL, headers=bearer(ADMIN))
    assert a.status_code == b.status_code == 202
    assert client.post(f"/api/v1/measurements/{b.json()['id']}/cancel", headers=bearer(READER)).status_code == 403
    assert client.post(f"/api/v1/measurements/{b.json()['id']}/cancel", headers=bearer(OPERATOR)).status_code == 200
    assert client.post(f"/api/v1/measurements/{a.json()['id']}/cancel", headers=bearer(ADMIN)).status_code == 200

    sched = {"interval_s": 3600, "measurement": CYL}
    r = client.post("/api/v1/schedules", json=sched, headers=bearer(OPERATOR))
    assert r.status_code == 403 and "needs the admin token" in r.json()["detail"]
    sid = client.post("/api/v1/schedules", json=sched, headers=bearer(ADMIN)).json()["id"]
    assert client.delete(f"/api/v1/schedules/{sid}", headers=bearer(OPERATOR)).status_code == 403
    assert client.delete(f"/api/v1/schedules/{sid}").status_code == 401
    assert client.delete(f"/api/v1/schedules/{sid}", headers=bearer(ADMIN)).status_code == 204
    # a scheme other than Bearer is no token
    assert (
        client.post("/api/v1/measurements", json=CYL, headers={"Authorization": f"Basic {OPERATOR}"}).status_code == 401
    )


def test_role_tokens_from_the_environment_and_unconfigured_roles(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    svc = Service(_config(tmp_path, "read = 'token'"), GatedMeasure())
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as client:
        r = client.get("/api/v1/measurements", headers=bearer(READER))
        assert r.status_code == 403 and "none is configured" in r.json()["detail"]
        assert "LRMS_READ_TOKEN" in r.json()["detail"]
        r = client.post("/api/v1/measurements", json=CYL, headers=bearer(OPERATOR))
        assert r.status_code == 403 and "write endpoints are disabled" in r.json()["detail"]
        monkeypatch.setenv("LRMS_READ_TOKEN", READER)
        monkeypatch.setenv("LRMS_OPERATOR_TOKEN", OPERATOR)
        assert client.get("/api/v1/measurements", headers=bearer(READER)).status_code == 200
        assert client.post("/api/v1/measurements", json=CYL, headers=bearer(OPERATOR)).status_code == 202
        r = client.post("/api/v1/schedules", json={"interval_s": 60, "measurement": CYL}, headers=bearer(OPERATOR))
        assert r.status_code == 403 and "admin endpoints are disabled" in r.json()["detail"]
        monkeypatch.setenv("LRMS_ADMIN_TOKEN", ADMIN)
        r = client.post("/api/v1/schedules", json={"interval_s": 60, "measurement": CYL}, headers=bearer(ADMIN))
        assert r.status_code == 201


def test_auth_config_keys(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from service.errors import ConfigError

    real = "[scanner]\nurl = 'tcp://10.0.0.5:2112'\n[motor]\nurl = 'sim://'\n"
    cfg = parse_toml(real)
    assert cfg.auth.read == "token"  # a rig file's default: reads need a token
    assert all(cfg.role_token(r) is None for r in ("read", "operator", "admin"))
    monkeypatch.setenv("LRMS_DATA", str(tmp_path))
    assert load_config().auth.read == "open"  # the built-in simulated rig (on loopback)
    # the deprecated [auth] token and LRMS_API_TOKEN are the operator token
    assert parse_toml(real + "[auth]\ntoken = 'x1'\n").role_token("operator") == "x1"
    monkeypatch.setenv(TOKEN_ENV, "x2")
    assert cfg.role_token("operator") == "x2" and cfg.role_token("admin") is None
    monkeypatch.setenv("LRMS_OPERATOR_TOKEN", "x3")  # the new name wins
    assert cfg.role_token("operator") == "x3"
    with pytest.raises(ConfigError, match="deprecated name of operator_token"):
        parse_toml(real + "[auth]\ntoken = 'a'\noperator_token = 'b'\n")
    with pytest.raises(ConfigError, match="operator_token and admin_token are the same token") as same:
        parse_toml(real + "[auth]\noperator_token = 'samesame'\nadmin_token = 'samesame'\n")
    assert "samesame" not in str(same.value)
    with pytest.raises(ConfigError, match=r"auth\.read"):
        parse_toml(real + "[auth]\nread = 'sometimes'\n")
    with pytest.raises(ConfigError, match="tls_cert and tls_key go together"):
        parse_toml(real + "[api]\ntls_cert = 'c.pem'\n")
    with pytest.raises(ConfigError, match=r"api\.max_body_bytes"):
        parse_toml(real + "[api]\nmax_body_bytes = 10\n")
    f = tmp_path / "rig.toml"
    f.write_text(real + "[api]\ntls_cert = 'c.pem'\ntls_key = 'k.pem'\n")
    api = load_config(f).api
    assert api.tls_cert == tmp_path / "c.pem" and api.tls_key == tmp_path / "k.pem"  # relative to the file
    assert api.max_body_bytes == 1 << 20
    # secrets stay out of the config's repr (tracebacks, debug logs)
    secret = parse_toml(
        real.replace("[scanner]\n", "[scanner]\nlogin_password_hash = 4101130052\n")
        + ALL_ROLES.join(("[auth]\n", "\n"))
    )
    text = repr(secret)
    assert not any(s in text for s in (READER, OPERATOR, ADMIN, "4101130052")), text
    with pytest.raises(ConfigError, match="login_password_hash") as big:
        parse_toml(real.replace("[scanner]\n", "[scanner]\nlogin_password_hash = 99999999999\n"))
    assert "99999999999" not in str(big.value)
    assert DEFAULT_RIG.endswith(".toml")


# -- the body guard -----------------------------------------------------------------------


def _send_head(srv: ServerThread, head: str) -> socket.socket:
    sock = socket.create_connection((srv.host, srv.port), timeout=10)
    sock.sendall(head.replace("\n", "\r\n").encode() + b"\r\n")
    return sock


def _send(sock: socket.socket, data: bytes) -> bool:
    """Send like an HTTP client: False once the server has closed (it answered without reading the rest)."""
    try:
        sock.sendall(data)
    except (BrokenPipeError, ConnectionResetError):
        return False
    return True


def _read_response(sock: socket.socket) -> tuple[int, dict[str, str], dict[str, Any]]:
    """Status, headers and JSON body of one HTTP/1.1 response with a Content-Length."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"connection closed before a response: {data!r}"
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    n = int(headers["content-length"])
    while len(rest) < n:
        chunk = sock.recv(65536)
        assert chunk
        rest += chunk
    return int(lines[0].split()[1]), headers, json.loads(rest[:n])


def _guard_answers(client: httpx.Client, status: int) -> float:
    """``lrms_http_requests_total`` of POSTs answered ``status`` without reaching a route (the guard's)."""
    text = client.get("/metrics", headers=bearer(READER)).text
    m = re.search(rf'lrms_http_requests_total{{method="POST",route="unmatched",status="{status}"}} (\S+)', text)
    return float(m.group(1)) if m else 0.0


def test_unauthenticated_40_mb_post_is_refused_before_its_body_is_read(
    locked: tuple[httpx.Client, ServerThread, GatedMeasure],
) -> None:
    client, srv, measure = locked
    size = 40 * 1024 * 1024
    for auth in ("", f"Authorization: Bearer {OPERATOR}x\n", f"Authorization: Bearer {READER}\n"):
        t0 = time.perf_counter()
        sock = _send_head(
            srv,
            f"POST /api/v1/measurements HTTP/1.1\nHost: t\n{auth}Content-Type: application/json\n"
            f"Content-Length: {size}\n",
        )
        with sock:
            _send(sock, b'{"target": "cylinder", "pad": "' + b"x" * 65536)  # 64 KiB of the 40 MiB
            status, headers, body = _read_response(sock)  # answered without the other 39.9 MiB
            dt = time.perf_counter() - t0
            assert status == (403 if READER in auth else 401), body
            assert headers["connection"] == "close"
            print(f"40 MiB POST ({auth.strip() or 'no token'}): {status} after 64 KiB sent, in {dt * 1e3:.1f} ms")
    assert _guard_answers(client, 401) == 2 and _guard_answers(client, 403) == 1  # never routed
    assert measure.started == []

    # an ordinary client sending the whole 40 MiB gets the same answer
    payload = b'{"target": "cylinder", "pad": "' + b"x" * size + b'"}'
    t0 = time.perf_counter()
    r = httpx.post(f"{srv.url}/api/v1/measurements", content=payload, headers={"Content-Type": "application/json"})
    print(f"httpx, 40 MiB unauthenticated POST: {r.status_code} in {time.perf_counter() - t0:.3f} s")
    assert r.status_code == 401 and r.json()["detail"].startswith("missing bearer token")
    assert _guard_answers(client, 401) == 3


def test_body_size_limit_by_content_length_and_while_streaming(
    locked: tuple[httpx.Client, ServerThread, GatedMeasure],
) -> None:
    client, srv, _ = locked
    # Content-Length over the limit: 413 from the header, before any body byte is sent
    sock = _send_head(
        srv,
        f"POST /api/v1/measurements HTTP/1.1\nHost: t\nAuthorization: Bearer {OPERATOR}\n"
        f"Content-Type: application/json\nContent-Length: {2 * LIMIT}\n",
    )
    with sock:
        status, headers, body = _read_response(sock)
    assert status == 413 and f"limit of {LIMIT} bytes" in body["detail"] and headers["connection"] == "close"
    r = client.post("/api/v1/measurements", content=b" " * (2 * LIMIT), headers=bearer(ADMIN))
    assert r.status_code == 413

    # chunked: answered 413 once the limit is passed, while the body is still open (the last
    # chunk is never sent), so the server never waited for nor held the whole body
    sock = _send_head(
        srv,
        f"POST /api/v1/measurements HTTP/1.1\nHost: t\nAuthorization: Bearer {OPERATOR}\n"
        "Content-Type: application/json\nTransfer-Encoding: chunked\n",
    )
    with sock:
        piece = b"x" * 65536
        for _ in range(3 * LIMIT // 2 // len(piece)):  # 1.5 MiB in 64 KiB chunks
            if not _send(sock, b"%x\r\n%s\r\n" % (len(piece), piece)):
                break
        status, headers, body = _read_response(sock)
    assert status == 413 and "exceeds the limit" in body["detail"]

    # a chunked body within the limit reaches the app intact
    def chunks() -> Iterator[bytes]:
        text = json.dumps({"target": "cylinder", "sweep": {"speed_deg_s": 20.0}}).encode()
        yield from (text[i : i + 7] for i in range(0, len(text), 7))

    r = client.post(
        "/api/v1/measurements", content=chunks(), headers={**bearer(OPERATOR), "Content-Type": "application/json"}
    )
    assert r.status_code == 202 and r.json()["request"]["sweep"]["speed_deg_s"] == 20.0
    # a read is not limited by the guard beyond its body: GETs still work on the same server
    assert client.get("/api/v1/measurements", headers=bearer(READER)).status_code == 200
    assert _guard_answers(client, 413) == 3


# -- /docs --------------------------------------------------------------------------------


def test_docs_pages_load_only_local_assets(locked: tuple[httpx.Client, ServerThread, GatedMeasure]) -> None:
    client, _, _ = locked  # reads need a token there; the docs do not
    for page in ("/docs", "/redoc"):
        html = client.get(page)
        assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
        assert (
            "http://" not in html.text and "https://" not in html.text and "//" not in html.text.replace("://", "")
        ), page
        refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", html.text)
        refs += re.findall(r"""url: ?['"]([^'"]+)['"]""", html.text)  # Swagger UI's openapi.json
        refs += re.findall(r"""spec-url=["']([^"']+)["']""", html.text)  # ReDoc's
        assert any(r.endswith(".js") for r in refs) and any(r.endswith("openapi.json") for r in refs), refs
        for ref in refs:
            assert ref.startswith("/"), ref
            asset = client.get(ref)
            assert asset.status_code == 200 and len(asset.content) > 1000, (ref, asset.status_code)


# -- lrms serve: warning, TLS, no secret in the output ------------------------------------


def test_exposure_warnings_name_what_is_missing(tmp_path: Path) -> None:
    rig = parse_toml("[sim]\n[auth]\nread = 'open'\n")
    locked_rig = parse_toml("[sim]\n[auth]\nread = 'token'\n")
    for host in ("127.0.0.1", "127.5.5.5", "::1", "[::1]", "localhost"):
        assert is_loopback(host) and exposure_warnings(host, rig, tls=False) == [], host
    for host in ("0.0.0.0", "::", "192.168.0.10", "10.1.2.3"):
        assert not is_loopback(host)
        both = exposure_warnings(host, rig, tls=False)
        assert len(both) == 2 and "without TLS" in both[0] and "without a token for reads" in both[1], both
        assert exposure_warnings(host, rig, tls=True) == [both[1]]
        assert exposure_warnings(host, locked_rig, tls=False) == [both[0]]
        assert exposure_warnings(host, locked_rig, tls=True) == []


def test_serve_beyond_loopback_warns_on_stderr(tmp_path: Path) -> None:
    # 192.0.2.1 (TEST-NET-1) is on no interface: the bind fails after the warnings (house rule: tests
    # listen on loopback only)
    nonlocal_bind = Path("/proc/sys/net/ipv4/ip_nonlocal_bind")
    if nonlocal_bind.exists() and nonlocal_bind.read_text().strip() != "0":
        pytest.skip("this machine allows binding addresses it does not have")
    proc = subprocess.run(
        [*LRMS, "serve", "--host", "192.0.2.1", "--port", "0", "--data", str(tmp_path), "--log-level", "warning"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1 and "cannot listen on 192.0.2.1" in proc.stderr, proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if line.startswith(WARNING)]
    assert len(warnings) == 2, proc.stderr
    assert "without TLS" in warnings[0] and "without a token for reads" in warnings[1]
    # and in the log (same stream by default)
    assert sum("WARNING lrms.serve: listening on 192.0.2.1" in line for line in proc.stderr.splitlines()) == 2


def test_serve_over_tls_writes_no_secret(tmp_path: Path) -> None:
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1", "localhost")
    cert_pem, key_pem, ca_pem = tmp_path / "cert.pem", tmp_path / "key.pem", tmp_path / "ca.pem"
    cert.private_key_and_cert_chain_pem.write_to_path(str(cert_pem))
    cert.private_key_pem.write_to_path(str(key_pem))
    ca.cert_pem.write_to_path(str(ca_pem))
    password_hash = 0xF4724744  # the factory hash of level 3, as the simulated scanner expects: still a secret
    rig_toml = (REPO / "service" / DEFAULT_RIG).read_text()
    rig_toml = rig_toml.replace("\n[scanner]", f"\n[scanner]\nlogin_password_hash = {password_hash}", 1)
    rig_toml = re.sub(r"\[auth\].*?\n\n", "[auth]\nread = 'token'\n\n", rig_toml, flags=re.S)
    config = tmp_path / "rig.toml"
    config.write_text(rig_toml)
    env = {**os.environ, "LRMS_READ_TOKEN": READER, "LRMS_OPERATOR_TOKEN": OPERATOR, "LRMS_ADMIN_TOKEN": ADMIN}
    env.pop(TOKEN_ENV, None)
    bad = [OPERATOR[:-1], OPERATOR + "0", ADMIN.upper(), "guess-" + READER]
    secrets = [READER, OPERATOR, ADMIN, *bad, str(password_hash), f"{password_hash:X}", f"{password_hash:x}"]
    log_file = tmp_path / "serve.log"  # a file, not a pipe: the debug log must not fill a pipe nobody reads
    proc = subprocess.Popen(
        [*LRMS, "serve", "--config", str(config), "--port", "0", "--data", str(tmp_path / "data"),
         "--log-level", "debug", "--tls-cert", str(cert_pem), "--tls-key", str(key_pem)],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=log_file.open("w"), text=True,
    )  # fmt: skip
    out_lines: list[str] = []
    try:
        assert proc.stdout is not None
        url = ""
        for line in proc.stdout:
            out_lines.append(line)
            if line.startswith(LISTENING):
                url = line[len(LISTENING) :].strip()
                break
        if not url:
            proc.wait(30)
            raise AssertionError(f"lrms serve exited ({proc.returncode}): {out_lines} {log_file.read_text()}")
        assert url.startswith("https://127.0.0.1:"), url
        trusted = ssl.create_default_context(cafile=str(ca_pem))
        with httpx.Client(base_url=url, verify=trusted, timeout=30) as client:
            end = time.monotonic() + 60
            while True:
                try:
                    rig = client.get("/api/v1/rig", headers=bearer(READER))
                    break
                except httpx.TransportError:
                    assert proc.poll() is None and time.monotonic() < end
                    time.sleep(0.2)
            assert rig.status_code == 200 and rig.json()["scanner"]["connected"] is True
            assert not any(s in rig.text for s in secrets), rig.text  # no token, no password hash
            with pytest.raises(httpx.ConnectError):  # a client that does not trust the CA refuses the server
                httpx.get(f"{url}/healthz", timeout=10)
            for token in bad:
                assert client.get("/api/v1/measurements", headers=bearer(token)).status_code == 401
                assert client.post("/api/v1/measurements", json=CYL, headers=bearer(token)).status_code == 401
            r = client.post("/api/v1/schedules", json={"interval_s": 60, "measurement": CYL}, headers=bearer(OPERATOR))
            assert r.status_code == 403 and not any(s in r.text for s in secrets)
            # one short measurement, so the run's own log lines are in the output too
            sweep = {"start_deg": 0.0, "stop_deg": 4.0, "speed_deg_s": 20.0}
            r = client.post("/api/v1/measurements", json={**CYL, "sweep": sweep}, headers=bearer(ADMIN))
            assert r.status_code == 202, r.text
            mid = r.json()["id"]
            end = time.monotonic() + 90
            state = ""
            while state not in ("done", "failed", "cancelled") and time.monotonic() < end:
                time.sleep(0.3)
                state = client.get(f"/api/v1/measurements/{mid}", headers=bearer(OPERATOR)).json()["state"]
            assert state in ("done", "failed"), state
            assert client.get("/metrics", headers=bearer(READER)).status_code == 200
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=60)
    err = log_file.read_text()
    output = "".join(out_lines) + out + err
    assert "GET /api/v1/measurements" in err  # the access log is there, and it was looked at
    assert "lrms serve: auth: reads need a token; tokens configured: operator, admin, read" in output
    leaked = [s for s in secrets if s in output]
    assert leaked == [], leaked
