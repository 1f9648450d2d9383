"""The HTTP contract: the OpenAPI schema declares every status code and body the service answers.

An outside fuzzer, Schemathesis, reads our own ``/openapi.json`` and runs all its checks (server
errors, undeclared status codes, bodies and headers against the schema, refused valid data,
accepted invalid data, Allow headers of 405s, auth ignored, resources after deletion) against the
app served by uvicorn on 127.0.0.1, with the write token, in all its phases (examples, coverage,
fuzzing, stateful). Its size is bounded (``MAX_EXAMPLES`` per operation, one worker, a fixed seed so
a run is repeatable; ``LRMS_SCHEMATHESIS_SEED`` picks another).

The measurement function is a stub that writes a raw log and a cloud at once: this tests the HTTP
contract, and a fuzzer's hundreds of accepted requests would queue hours of real sweeps. Requests
are still checked against the rig's configuration (travel limits, maximum speed and duration), as
that happens in the routes, before anything is queued.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service import mcaplog
from service.api import ServerThread, Service, create_app
from service.config import TOKEN_ENV, parse_toml
from service.jobs import JobContext

TOKEN = "contract-t0ken"
HERE = Path(__file__).resolve().parent
MAX_EXAMPLES = 25
SEED = int(os.environ.get("LRMS_SCHEMATHESIS_SEED", "1"))


def _quick_measure(ctx: JobContext) -> dict[str, Any]:
    with mcaplog.McapLog(ctx.raw_path) as log:
        log.log_json(mcaplog.TOPIC_MEASUREMENT, 1, {"id": ctx.measurement.id})
    ctx.cloud_path.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    return {"target": ctx.request.target}


@pytest.fixture
def served(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = parse_toml(f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\n[auth]\ntoken = '{TOKEN}'\n")
    svc = Service(cfg, _quick_measure, rig_info=lambda: {"scanner": {"connected": False}, "motor": {"state": "X"}})
    with ServerThread(create_app(svc)) as srv:
        yield srv.url


def _ref(response: dict[str, Any]) -> str:
    return str(response["content"]["application/json"]["schema"]["$ref"]).rsplit("/", 1)[-1]


def test_the_schema_declares_every_error_with_its_body(served: str) -> None:
    spec = httpx.get(f"{served}/openapi.json").json()
    paths = spec["paths"]
    assert _ref(paths["/healthz"]["get"]["responses"]["200"]) == "HealthOut"
    assert _ref(paths["/healthz"]["get"]["responses"]["503"]) == "HealthOut"
    assert _ref(paths["/api/v1/rig"]["get"]["responses"]["200"]) == "RigOut"
    assert "HTTPValidationError" not in spec["components"]["schemas"]  # FastAPI's own 422 format is gone
    writes = 0
    for path, ops in paths.items():
        for method, op in ops.items():
            codes = set(op["responses"])
            for code, response in op["responses"].items():
                if code == "422":
                    assert _ref(response) == "ValidationErrorBody", (method, path)
                elif code[0] in "45" and path != "/healthz":
                    assert _ref(response) == "ErrorBody", (method, path, code)
            if op.get("security"):  # a token may be needed: reads when [auth] read = "token", every write
                assert {"401", "403"} <= codes, (method, path)
                assert "WWW-Authenticate" in op["responses"]["401"]["headers"]
            if method in {"post", "delete"}:
                writes += 1
                assert op.get("security") and {"401", "403", "413"} <= codes, (method, path)
                if path in {"/api/v1/measurements", "/api/v1/schedules", "/api/v1/calibrations"}:
                    assert "429" in codes and "Retry-After" in op["responses"]["429"]["headers"], path
            if "{" in path:
                assert "404" in codes, (method, path)
    # create and cancel a measurement, create and delete a schedule, reset the drive, create and retire a recipe
    assert writes == 10  # and run, upload and activate a calibration


def test_schemathesis_finds_no_contract_failure(served: str, tmp_path: Path) -> None:
    report = tmp_path / "schemathesis.json"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "schemathesis.cli",
            "--no-color",
            "--config-file",
            str(HERE / "schemathesis.toml"),
            "run",
            f"{served}/openapi.json",
            "--header",
            f"Authorization: Bearer {TOKEN}",
            "--checks",
            "all",
            "--max-examples",
            str(MAX_EXAMPLES),
            "--seed",
            str(SEED),
            "--workers",
            "1",
            "--request-timeout",
            "10",
            "--report",
            "json",
            "--report-json-path",
            str(report),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    tail = proc.stdout[-6000:] + proc.stderr[-2000:]
    assert report.is_file(), tail
    run = json.loads(report.read_text())
    cases, ops = run["test_cases"], run["operations"]
    print(
        f"schemathesis (seed {SEED}, {MAX_EXAMPLES} examples per operation): {ops['tested']} operations, "
        f"{cases['generated']} test cases, {cases['unique_failures']} failures, {len(run['errors'])} errors, "
        f"{run['running_time']:.1f} s"
    )
    assert proc.returncode == 0 and run["exit_code"] == 0, tail
    assert run["failures"] == [] and run["errors"] == [] and cases["with_failures"] == 0, tail
    assert ops["tested"] == ops["total"] == 34, ops
    assert {name: p["status"] for name, p in run["phases"].items()} == {
        "examples": "success",
        "coverage": "success",
        "fuzzing": "success",
        "stateful": "success",
    }, run["phases"]
    assert cases["generated"] >= 17 * 10, cases  # it did send requests to every operation
