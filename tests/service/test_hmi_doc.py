"""docs/hmi.md's ``sh`` blocks, run in order by bash against a live service on the simulated rig:
the integrator's walk-through cannot drift from the API."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from service.api import ServerThread, create_app
from service.config import parse_config, parse_toml
from service.rig import build_service
from tests.conftest import REPO

DOC = REPO / "docs" / "hmi.md"
OPERATOR, ADMIN = "hmi-operator", "hmi-admin"


def sh_blocks(text: str) -> list[str]:
    """The fenced ``sh`` blocks of a Markdown text, in order."""
    return re.findall(r"^```sh\n(.*?)^```", text, flags=re.S | re.M)


def test_the_doc_has_the_workflow() -> None:
    blocks = sh_blocks(DOC.read_text())
    joined = "\n".join(blocks)
    assert len(blocks) >= 9
    for call in (
        "/api/v1/recipes",
        "/api/v1/measurements",
        "/events",
        "/report.pdf",
        "/report.html",
        "/history.csv",
        "/spc",
    ):
        assert call in joined


@pytest.mark.skipif(shutil.which("curl") is None or shutil.which("jq") is None, reason="needs curl and jq")
def test_the_hmi_doc_runs_against_a_live_service(tmp_path: Path) -> None:
    cfg = parse_toml((REPO / "service" / "default_rig.toml").read_text(), base_dir=tmp_path)
    data = cfg.model_dump(mode="json")
    auth = {"operator_token": OPERATOR, "admin_token": ADMIN, "read": "token"}
    cfg = parse_config({**data, "auth": auth}, base_dir=tmp_path)
    svc, rig = build_service(cfg)
    script = "set -euo pipefail\n" + "\n".join(sh_blocks(DOC.read_text()))
    try:
        with ServerThread(create_app(svc)) as srv:
            env = {"PATH": "/usr/bin:/bin", "LRMS": srv.url, "TOKEN": OPERATOR, "ADMIN_TOKEN": ADMIN}
            proc = subprocess.run(
                ["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
            )
    finally:
        svc.stop()
        rig.close()
    out = proc.stdout
    assert proc.returncode == 0, (out, proc.stderr)
    assert '"name": "SHAFT-137"' in out and '"version": 1' in out
    assert '"outcome": "conforms"' in out and '"recipe_version": 1' in out and '"part_id": "4711"' in out
    assert re.search(r'^data: \{"id": "[0-9a-f]{16}", "state": "done"', out, flags=re.M), out  # the last event
    assert re.search(r"^[0-9a-f]{16},done,4711,conforms$", out, flags=re.M), out  # the history's CSV row
    assert "a control chart needs 2" in out
    assert re.search(r'^%PDF-\nclass="outcome conforms">conforms<\nSHA-256 [0-9a-f]{64}$', out, flags=re.M), out
    spc = re.search(r'^\{"n":2,"mean_mm":([\d.]+),"limits_mm":\[([\d.]+),([\d.]+)\],.*"flagged":\[\]\}$', out, re.M)
    assert spc and float(spc[2]) < float(spc[1]) < float(spc[3]), out  # LCL < mean < UCL
    assert re.search(r"^[0-9a-f]{16},done,4712,conforms$", out, flags=re.M) is None  # the CSV came before part 2
    assert '422\n["body","recipe"]\n' in out and "no recipe 'NO-SUCH-PART'" in out
