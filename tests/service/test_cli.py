"""The command line end to end: ``lrms measure`` on the default simulated rig, ``lrms replay``, ``lrms serve``."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from service import mcaplog
from service.cli.serve import LISTENING
from tests.conftest import REPO
from tests.service.logcheck import assert_json_is_javascript_safe

LRMS = [sys.executable, "-m", "service.cli.main"]


def test_measure_starts_the_rig_process_before_the_rig_code_api_and_store_load() -> None:
    """``lrms measure`` starts the rig process (:func:`service.isolated.isolated_service`) with only
    the config and request models loaded: the rig code, the web stack and the store load in this
    process while the rig process boots (bench/bench_cli_start.py: the sweep's start). The rig
    process's code loads no store (SQLAlchemy, Alembic), no web stack, no simulator device code
    (a process = true rig opens the simulated rig's tcp:// and socketcand:// URLs) and no
    calibration store (only when a calibration is applied); the service (``from service.api import
    Service``, what the command uses) loads no ``lrms.calibration`` (scipy.spatial, scipy.special)
    until a calibration is read, and none of what a measurement does not need: FastAPI and the
    routes (``create_app``, ``lrms serve``), uvicorn (``lrms serve``), Alembic (a store not at the
    newest schema), croniter (a cron schedule), jinja2 (a report)."""
    code = (
        "import sys\n"
        "import service.cli.measure, service.config, service.models, service.isolated\n"
        "late = ('service.rig', 'service.api', 'service.store', 'service.jobs', 'fastapi', 'sqlalchemy', 'alembic',\n"
        "        'scipy', 'service.calstore', 'lrms.calibration', 'scipy.optimize', 'sim.scanner', 'sim.scene',\n"
        "        'service.api.core', 'service.api.app', 'uvicorn', 'croniter', 'jinja2', 'service.report')\n"
        "print('LOADED:', *[m for m in late if m in sys.modules])\n"
        "import service.rig\n"
        "print('LOADED:', *[m for m in late if m in sys.modules])\n"
        "from service.api import Service\n"
        "print('LOADED:', *[m for m in late if m in sys.modules])\n"
        "from service.api import create_app, ServerThread\n"
        "print('LOADED:', *[m for m in late if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    before, rig, api, app = (line.split() for line in out.stdout.strip().splitlines()[-4:])
    assert before == ["LOADED:"], out.stdout
    assert "service.rig" in rig and "service.jobs" in rig  # the probe can see them
    assert rig == ["LOADED:", "service.rig", "service.jobs"], rig
    assert {"service.api", "service.api.core", "service.store", "sqlalchemy", "service.calstore"} <= set(api), api
    assert not {"lrms.calibration", "scipy", "scipy.optimize"} & set(api), api
    assert not {"fastapi", "service.api.app", "uvicorn", "alembic", "croniter", "jinja2"} & set(api), api
    # the probe sees them when they do load: the app (its routes: the reports), and the server
    assert {"fastapi", "service.api.app", "uvicorn", "service.report"} <= set(app), app
    assert not {"jinja2", "croniter", "alembic"} & set(app), app


def test_a_store_at_the_newest_schema_opens_without_alembic(tmp_path: Path) -> None:
    """Opening a store migrates it with Alembic only when it is not at the newest revision: the
    embedded ``lrms measure`` opens one already migrated without loading Alembic."""
    code = (
        "import sys\n"
        "from service.store import Store\n"
        f"Store({str(tmp_path / 'r.sqlite')!r}, 'rig')\n"
        "print('LOADED:', *[m for m in ('alembic', 'sqlalchemy') if m in sys.modules])\n"
    )
    first, again = (
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True
        ).stdout.split()
        for _ in range(2)
    )
    assert first == ["LOADED:", "alembic", "sqlalchemy"], first  # a new file is migrated
    assert again == ["LOADED:", "sqlalchemy"], again


def test_measure_then_replay(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    plot = tmp_path / "run.png"
    proc = subprocess.run(
        [
            *LRMS,
            "measure",
            "--target",
            "cylinder",
            "--speed",
            "20",
            "--out",
            str(out),
            "--plot",
            str(plot),
            "--data",
            str(tmp_path / "data"),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    (tmp_path / "result.json").write_text(proc.stdout)  # kept with the MCAP by pytest's tmp_path retention
    u = result["uncertainty"]
    assert u["d_min_m"] <= 0.1375 <= u["d_max_m"] and abs(result["diameter_m"] - 0.1375) <= 4 * u["std_m"], (
        accuracy_report(result, tmp_path)
    )
    assert "%" in proc.stderr  # the progress bar
    assert out.stat().st_size > 100_000 and plot.read_bytes()[:4] == b"\x89PNG"
    msgs, _ = mcaplog.read_log(out)
    assert_json_is_javascript_safe(msgs)  # no integer above 2^53 in any JSON message
    rep = subprocess.run([*LRMS, "replay", str(out)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stderr
    replayed = json.loads(rep.stdout)
    assert replayed["reproduced"] is True and replayed["max_abs_diff"] <= 1e-9
    assert replayed["result"]["diameter_m"] == result["diameter_m"]


def accuracy_report(result: dict[str, Any], kept: Path) -> str:
    """What a failed accuracy check needs to be judged: the error against the fit's type A
    ``std_m``, the sweep's scan and timing figures, and where the result, MCAP and cloud are kept."""
    u, sweep, clock = result["uncertainty"], result["sweep"], result["clock"]
    err = result["diameter_m"] - 0.1375
    return (
        f"diameter {result['diameter_m'] * 1e3:.3f} mm, error {err * 1e3:+.3f} mm = {err / u['std_m']:+.2f} std_m "
        f"(std_m {u['std_m'] * 1e3:.3f} mm, interval [{u['d_min_m'] * 1e3:.2f}, {u['d_max_m'] * 1e3:.2f}] mm); "
        f"{result['n_inliers']} inliers, chi2/dof {result['chi2_dof']:.3f}; scans in sweep {sweep['scans_in_sweep']}, "
        f"missing {sweep['scans_missing']}; clock drift {clock['drift_ppm']:.1f} ppm, receive jitter "
        f"{clock['residual_jitter_s'] * 1e3:.1f} ms, resets {clock['resets']}; motor timing jitter "
        f"{sweep['motor_timing_jitter_s']} s ({sweep['motor_time_source']}); kept in {kept} "
        f"(result.json, run.mcap, {result.get('cloud_path')})"
    )


def test_bad_config_and_bad_replay_file_are_one_line_errors(tmp_path: Path) -> None:
    bad = tmp_path / "rig.toml"
    bad.write_text("[sim]\n[sweep]\nspeed_deg_s = -1\n")
    proc = subprocess.run(
        [*LRMS, "measure", "--config", str(bad), "--target", "cylinder"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1 and proc.stderr.startswith("error: ") and "sweep.speed_deg_s" in proc.stderr
    # a sweep beyond the rig's [motor] limits is refused before the rig is opened
    proc = subprocess.run(
        [*LRMS, "measure", "--target", "cylinder", "--speed", "100", "--data", str(tmp_path / "data")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1 and proc.stderr.strip() == (
        "error: sweep.speed_deg_s: 100 deg/s exceeds the motor's maximum speed 90 deg/s ([motor] max_velocity_deg_s)"
    )
    assert not (tmp_path / "data").exists()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"nope")
    proc = subprocess.run([*LRMS, "replay", str(junk)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "not an MCAP file" in proc.stderr


def announced_url(proc: subprocess.Popen[str]) -> str:
    """The URL of ``lrms serve``'s listening line on stdout (read until it comes or the process ends)."""
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith(LISTENING):
            return line[len(LISTENING) :].strip()
    proc.wait(30)
    raise AssertionError(f"lrms serve exited ({proc.returncode}) without listening: {proc.communicate()[1]}")


def test_serve_answers_on_loopback(tmp_path: Path) -> None:
    env = {**os.environ, "LRMS_API_TOKEN": "x"}
    proc = subprocess.Popen(
        [*LRMS, "serve", "--port", "0", "--data", str(tmp_path), "--log-level", "info"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out, err = "", ""
    try:
        url = announced_url(proc)  # --port 0: the port the service bound, from its stdout
        assert url.startswith("http://127.0.0.1:") and int(url.rsplit(":", 1)[1]) > 0, url
        end = time.monotonic() + 60
        body = None
        while time.monotonic() < end and body is None:
            try:
                body = httpx.get(f"{url}/api/v1/rig", timeout=10).json()
            except httpx.HTTPError:
                assert proc.poll() is None, proc.communicate()
                time.sleep(0.2)
        assert body is not None and body["simulated"] is True and body["write_enabled"] is True
        assert body["sim"]["alive"] is True and body["scanner"]["connected"] is True
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    # the access log is on stderr: nothing after the listening line on stdout (a caller that stops
    # reading it after that line cannot block the server)
    assert "GET /api/v1/rig" in err and out == "", out


def test_serve_on_a_port_in_use_is_a_one_line_error(tmp_path: Path) -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:  # listening: nobody else can bind it
        port = taken.getsockname()[1]
        proc = subprocess.run(
            [*LRMS, "serve", "--port", str(port), "--data", str(tmp_path), "--log-level", "warning"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert proc.stderr.startswith("error: cannot listen on 127.0.0.1 port ") and str(port) in proc.stderr, proc.stderr
    assert LISTENING not in proc.stdout
