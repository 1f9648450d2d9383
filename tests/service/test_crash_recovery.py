"""``lrms serve`` killed with SIGKILL mid-sweep and started again on the same data folder.

The real thing, nothing simulated but the rig: ``lrms serve`` (its own process, on the default
simulated rig; the rig process and the simulated rig run in child processes) is killed while a
sweep runs. Killed alone, the API process leaves the rig process to stop the sweep and close the
raw log (:func:`test_killed_api_process_leaves_a_closed_raw_log`). Killed together with the rig
process (power loss), the log is cut short. Then:

* the rig's child process does not outlive the service (it ends when its stdin closes);
* the raw log on disk has no summary (indexed readers refuse it);
* after the restart the measurement is ``failed`` with the reason (the process died, where the log
  ends, how many messages were kept), ``has_raw`` and ``raw_truncated`` are true, and the raw log
  served over HTTP opens with mcap's indexed reader and holds the sweep up to the kill;
* no JSON message of the log carries an integer above 2^53 (JavaScript readers round those);
* neither the API token nor the scanner's login password hash is in the log or on the service's stderr.
"""

from __future__ import annotations

import io
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
from mcap.reader import make_reader

from drivers.lms100 import PASSWORD_HASHES, AccessLevel
from service import mcaplog, mcaprecovery
from service.cli.serve import LISTENING
from service.replay import replay
from tests.conftest import REPO
from tests.service.logcheck import assert_json_is_javascript_safe
from tests.service.test_rig_sim import _wait, _wait_sweeping

TOKEN = "crash-test-token-7f3a9c"
PASSWORD_HASH = PASSWORD_HASHES[AccessLevel.AUTHORIZED_CLIENT]  # the one the simulated scanner accepts
SECRETS = (TOKEN, str(PASSWORD_HASH), f"{PASSWORD_HASH:08X}", f"{PASSWORD_HASH:08x}")


def _config(tmp_path: Path) -> Path:
    text = (REPO / "service" / "default_rig.toml").read_text()
    text = text.replace('operator_token = ""', f'operator_token = "{TOKEN}"')
    text = text.replace("resolution_deg = 0.25\n", f"resolution_deg = 0.25\nlogin_password_hash = {PASSWORD_HASH}\n")
    text = text.replace('dir = "lrms-data"', f'dir = "{tmp_path / "data"}"')
    assert TOKEN in text and str(PASSWORD_HASH) in text
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def _serve(config: Path, stderr: Path) -> tuple[subprocess.Popen[str], str]:
    with open(stderr, "a") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli.main", "serve", "--config", str(config), "--port", "0"],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith(LISTENING):
            return proc, line[len(LISTENING) :].strip()
    proc.wait(30)
    raise AssertionError(f"lrms serve exited ({proc.returncode}) without listening: {stderr.read_text()}")


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie (a zombie has ended; only its exit status is left)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_killed_service_leaves_a_recoverable_raw_log_served_as_truncated(tmp_path: Path) -> None:
    config = _config(tmp_path)
    stderr = tmp_path / "serve.stderr"
    auth = {"Authorization": f"Bearer {TOKEN}"}
    proc, url = _serve(config, stderr)
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            rig = client.get("/api/v1/rig").json()
            sim_pid = int(rig["sim"]["pid"])
            rig_pid = int(client.get("/healthz").json()["rig_process"]["pid"])
            assert _alive(sim_pid) and _alive(rig_pid) and not any(s in str(rig) for s in SECRETS)
            mid = client.post("/api/v1/measurements", json={"target": "cylinder"}, headers=auth).json()["id"]
            _wait_sweeping(client, mid, 20.0)  # 4 s into the sweep: several chunks closed
            killed_at_ns = time.time_ns()
            # the whole service dies at once (power loss, OOM killer): the API process and the rig
            # process that writes the raw log, so nothing is left to close the log
            os.kill(rig_pid, signal.SIGKILL)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    # the simulated rig's process sees its stdin close and ends: not leaked
    end = time.monotonic() + 20
    while _alive(sim_pid) and time.monotonic() < end:
        time.sleep(0.1)
    assert not _alive(sim_pid), f"the simulated rig (pid {sim_pid}) outlived the killed service"
    # what the kill left: a raw log without summary, which the indexed reader refuses
    raw = tmp_path / "data" / "raw" / f"{mid}.mcap"
    assert raw.stat().st_size > 0 and not mcaprecovery.has_summary(raw)
    on_disk, status = mcaplog.read_log(raw)
    assert status.truncated and on_disk

    proc, url = _serve(config, stderr)  # the same data folder
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            body = _wait(client, mid, {"failed"}, timeout=30)
            assert body["has_raw"] is True and body["raw_truncated"] is True, body
            error = body["error"]
            assert "process died" in error and "truncated at" in error, error
            found = re.search(r"(\d+) messages recovered", error)
            assert found, error
            n = int(found.group(1))
            download = client.get(f"/api/v1/measurements/{mid}/raw")
            assert download.status_code == 200 and download.headers["content-type"] == "application/x-mcap"
            assert not any(s in str(client.get("/api/v1/rig").json()) for s in SECRETS)
    finally:
        proc.terminate()
        proc.wait(30)
    data = download.content
    reader = make_reader(io.BytesIO(data))
    assert reader.get_summary() is not None  # indexed: summary, chunk indexes, statistics
    indexed = list(reader.iter_messages())
    assert len(indexed) == n == len(on_disk)
    topics = {ch.topic for _, ch, _ in indexed}
    assert {mcaplog.TOPIC_MEASUREMENT, mcaplog.TOPIC_TELEGRAM, mcaplog.TOPIC_MOTOR, mcaplog.TOPIC_EVENT} <= topics
    assert mcaplog.TOPIC_RESULT not in topics  # the process died before it could say how the sweep ended
    # the messages reach the kill: the writer closes a chunk about once a second (3 s of slack for a loaded machine)
    last = max(m.log_time for _, _, m in indexed)
    assert killed_at_ns - 3 * 10**9 < last < killed_at_ns, (killed_at_ns - last) / 1e9
    telegrams = sum(ch.topic == mcaplog.TOPIC_TELEGRAM for _, ch, _ in indexed)
    assert telegrams > 75  # the approach and 4 s of sweep at 25 scans/s
    got = tmp_path / "recovered.mcap"
    got.write_bytes(data)
    msgs, status = mcaplog.read_log(got)
    assert not status.truncated and len(msgs) == n
    assert_json_is_javascript_safe(msgs)
    events = [m.decode() for m in msgs if m.topic == mcaplog.TOPIC_EVENT]
    assert [e["kind"] for e in events if e["kind"].startswith("sweep_")] == ["sweep_start"]
    info = mcaprecovery.recovery_info(got)
    assert info is not None and info["messages"] == str(n)
    # secrets: not in the file (summary and uncompressed records) nor in any message, nor on stderr
    plain = data + b"".join(m.data for m in msgs)
    for secret in SECRETS:
        assert secret.encode() not in plain, secret
        assert secret not in stderr.read_text(), secret
    meta = next(m.decode() for m in msgs if m.topic == mcaplog.TOPIC_MEASUREMENT)
    assert "auth" not in meta["config"] and "login_password_hash" not in meta["config"]["scanner"]
    # lrms replay reads the recovered log (the sweep ends at the kill: mapped up to there)
    out = replay(got)
    assert out["truncated"] is True and out["recovered"]["messages"] == str(n) and out["stored"] is None
    assert out["result"]["sweep"]["scans_received"] == telegrams


def test_killed_api_process_leaves_a_closed_raw_log(tmp_path: Path) -> None:
    """Only the API process dies: the rig process sees its command socket close, stops the sweep
    and closes the raw log (summary and all), then exits with the simulated rig. After the restart
    the measurement is failed as interrupted, with its complete log (not truncated)."""
    config = _config(tmp_path)
    stderr = tmp_path / "serve.stderr"
    auth = {"Authorization": f"Bearer {TOKEN}"}
    proc, url = _serve(config, stderr)
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            sim_pid = int(client.get("/api/v1/rig").json()["sim"]["pid"])
            rig_pid = int(client.get("/healthz").json()["rig_process"]["pid"])
            mid = client.post("/api/v1/measurements", json={"target": "cylinder"}, headers=auth).json()["id"]
            _wait_sweeping(client, mid, 10.0)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    end = time.monotonic() + 30
    while (_alive(rig_pid) or _alive(sim_pid)) and time.monotonic() < end:
        time.sleep(0.1)
    assert not _alive(rig_pid) and not _alive(sim_pid), "the rig process or the simulated rig outlived the service"
    raw = tmp_path / "data" / "raw" / f"{mid}.mcap"
    assert mcaprecovery.has_summary(raw)  # closed by the rig process
    msgs, status = mcaplog.read_log(raw)
    assert not status.truncated
    results = [m.decode() for m in msgs if m.topic == mcaplog.TOPIC_RESULT]
    assert len(results) == 1 and results[0]["state"] in {"cancelled", "failed"}, results

    proc, url = _serve(config, stderr)
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            body = _wait(client, mid, {"failed"}, timeout=30)
            assert body["has_raw"] is True and body["raw_truncated"] is False, body
            assert "process died" in body["error"] and "truncated" not in body["error"], body["error"]
            assert client.get(f"/api/v1/measurements/{mid}/raw").content == raw.read_bytes()
    finally:
        proc.terminate()
        proc.wait(30)
