"""The request's nominal diameter range as a plausibility check on the final fit
(:func:`lrms.cylinder.nominal_check`), through the service's interfaces: ``lrms fit`` (its JSON keys,
its warning line, its error and exit status) and a measurement over HTTP on the simulated rig (the
result's keys, a recipe part's decision, a failed measurement's reason).

The fits are the footprint fit (``--optics lms1xx`` / ``[scanner.optics] model = "lms1xx"``) of
thin-beam clouds of seed 003's 137.5 mm part: only with the footprint model do the detection
stages let a candidate somewhat wider than the range through (the spot's allowance,
``lrms.cylinder.pipeline._radius_ok``), so that the final fit can land outside the range and meet
the check; a thin-beam fit outside the range is refused earlier ("no cylinder found: radius ...").
"""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from lrms.kinematics import RigCalibration
from service.api import ServerThread, create_app
from service.cli.fit import EXIT_NOMINAL_DIAMETER
from service.config import parse_config, parse_toml
from service.pointio import write_xyz
from service.rig import build_service
from sim.scene import SensorModel, cast_beams, get_scene
from sim.scene.library import SEED003_AXIS_POINT
from tests.conftest import REPO

LRMS = [sys.executable, "-m", "service.cli.main"]
TOKEN = "nominal-range"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _lrms(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([*LRMS, *args], capture_output=True, text=True, timeout=120, env=env, cwd=REPO)


@pytest.fixture(scope="module")
def thin_cloud(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A thin-beam sweep of seed 003's bare part (1094 points round the part, 0.5 x 1 deg), as .xyz."""
    cal = RigCalibration()
    dev = np.deg2rad(np.arange(60.0, 120.0 + 1e-9, 0.5))
    mot = np.deg2rad(np.arange(-20.0, 70.0, 1.0))[:, None]
    samples = cast_beams(get_scene("seed003-bare"), cal, SensorModel(), dev, mot, np.random.default_rng(3))
    pts = samples.points(cal)
    c0 = np.asarray(SEED003_AXIS_POINT)
    lo, hi = c0 + np.array([-0.6, -0.4, -0.05]), c0 + np.array([0.6, 0.4, 0.9])
    f = tmp_path_factory.mktemp("nominal") / "part.xyz"
    write_xyz(f, pts[np.all((pts >= lo) & (pts <= hi), axis=1)])
    return f


def test_lrms_fit_flags_a_fit_just_outside_the_range_and_refuses_one_far_outside(thin_cloud: Path) -> None:
    # the range's upper end 1-2 u below the fit's diameter (about 136.5 mm with a u of about 1.1 mm)
    near = ["--optics", "lms1xx", "--nominal-diameter", "0.130", "--diameter-tolerance", "0.005"]
    p = _lrms("fit", str(thin_cloud), "--json", *near)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r["diameter_range_m"] == pytest.approx([0.125, 0.135])
    d, excess, in_u = r["diameter_m"], r["diameter_range_excess_m"], r["diameter_range_excess_u"]
    assert d > 0.135 and excess == pytest.approx(d - 0.135, abs=1e-12)
    assert 0.0 < in_u <= 3.0
    # the same fit as text: one warning line with the range, the excess and its u
    p = _lrms("fit", str(thin_cloud), *near)
    assert p.returncode == 0, p.stderr
    warn = [line for line in p.stdout.splitlines() if line.startswith("warning:")]
    assert warn == [
        f"warning: the diameter is outside the nominal range [125.0, 135.0] mm by {excess * 1e3:+.2f} mm"
        f" ({in_u:.2f} u of the fit)"
    ]
    # inside the range: no flag, no warning
    p = _lrms("fit", str(thin_cloud), "--json", "--optics", "lms1xx", "--nominal-diameter", "0.1375")
    assert p.returncode == 0, p.stderr
    inside = json.loads(p.stdout)
    assert inside["diameter_range_excess_m"] is None and inside["diameter_range_excess_u"] is None
    # the range 5 mm below (more than 3 u): NominalDiameterError, one error line, its own exit status
    far = ["--optics", "lms1xx", "--nominal-diameter", "0.125", "--diameter-tolerance", "0.005"]
    for extra in ([], ["--json"]):
        p = _lrms("fit", str(thin_cloud), *far, *extra)
        assert p.returncode == EXIT_NOMINAL_DIAMETER == 3, (p.returncode, p.stderr)
        assert p.stdout == ""
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: no cylinder of the nominal diameter found: "), lines
        assert "is outside [120.0, 130.0] mm by" in lines[0] and "(more than 3 u)" in lines[0]
    # other fit errors keep exit status 1
    p = _lrms("fit", str(thin_cloud), "--nominal-diameter", "0.3")
    assert p.returncode == 1 and p.stderr.startswith("error: no cylinder found"), (p.returncode, p.stderr)


@pytest.fixture
def footprint_rig(tmp_path: Path) -> Iterator[httpx.Client]:
    """The default simulated rig (thin-beam sensor) whose service fits with the LMS1xx footprint model."""
    cfg = parse_toml((REPO / "service" / "default_rig.toml").read_text(), base_dir=tmp_path)
    data = cfg.model_dump(mode="json")
    data["scanner"]["optics"]["model"] = "lms1xx"
    cfg = parse_config({**data, "auth": {"admin_token": TOKEN, "read": "open"}}, base_dir=tmp_path)
    svc, rig = build_service(cfg)
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30, headers=AUTH) as client:
            yield client
    finally:
        svc.stop()
        rig.close()


STEP = {"mode": "step", "step_deg": 3.0, "speed_deg_s": 30.0}


def _finished(client: httpx.Client, body: dict[str, Any], timeout: float = 180.0) -> dict[str, Any]:
    import time

    r = client.post("/api/v1/measurements", json=body)
    assert r.status_code == 202, r.text
    mid = r.json()["id"]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        m: dict[str, Any] = client.get(f"/api/v1/measurements/{mid}").json()
        if m["state"] in ("done", "failed", "cancelled"):
            return m
        time.sleep(0.05)
    raise AssertionError(f"measurement {mid} did not finish")


def test_a_measurement_just_outside_its_range_is_flagged_in_its_result_and_decision(
    footprint_rig: httpx.Client,
) -> None:
    client = footprint_rig
    # the part measures 137.5 +- 0.3 mm (one sweep's scatter), a range ending 0.5 mm below it. One
    # sweep lands inside the range or beyond 3 u now and then; and on these thin-beam clouds (a
    # sensor the footprint model does not describe) the footprint fit's first-hit family wins on
    # about 1 sweep in 3 (the (radius, threshold) ridge), with the diameter up to 10 mm off and
    # u_c 3-8 mm, so that the guard-banded acceptance zone may no longer hold the value (measured:
    # 15 sweeps of this recipe, 5 first-hit, 2 of them outside their zone, 1 inside the range). So
    # each measurement is checked against its own diameter and zone, and the flagged case inside
    # the zone is required of at least one of up to six recipe parts (all six missing it, at about
    # 1 in 5 each: about 1e-4)
    near = {"nominal_diameter_m": 0.132, "diameter_tolerance_m": 0.005}
    recipe = {
        "name": "SHAFT-NARROW-RANGE",
        "target": "cylinder",
        "tolerances": {"diameter": {"nominal_m": 0.1375, "lower_m": -0.010, "upper_m": 0.010}},
        "sweep": STEP,
        "options": near,
    }
    assert client.post("/api/v1/recipes", json=recipe).status_code == 201
    flagged: list[dict[str, Any]] = []
    outcomes: list[tuple[str, str]] = []  # the recipe parts done: (part_id, outcome)
    for k in range(7):
        # a free-form measurement first, then parts of a recipe whose tolerance the part meets but
        # whose options' range ends below it
        body = (
            {"target": "cylinder", "sweep": STEP, "options": near}
            if k == 0
            else {"recipe": recipe["name"], "part_id": f"N{k}"}
        )
        m = _finished(client, body)
        if m["state"] == "failed":  # more than 3 u above the range: the typed check's reason
            assert "no cylinder of the nominal diameter found" in m["error"] and "(more than 3 u)" in m["error"], m[
                "error"
            ]
            continue
        assert m["state"] == "done", m["error"]
        r = m["result"]
        assert r["footprint"] is not None and r["diameter_range_m"] == pytest.approx([0.127, 0.137])
        if r["diameter_m"] <= 0.137:  # inside: no flag
            assert r["diameter_range_excess_m"] is None and r["diameter_range_excess_u"] is None
        else:
            assert r["diameter_range_excess_m"] == pytest.approx(r["diameter_m"] - 0.137, abs=1e-12)
            assert 0.0 < r["diameter_range_excess_u"] <= 3.0, (r["diameter_m"], r["diameter_range_excess_u"])
        if k == 0:
            continue
        dec = r["decision"]
        outcomes.append((f"N{k}", dec["outcome"]))
        lsl, usl = dec["acceptance_zone_m"]
        if not lsl < dec["value_m"] < usl:  # a wide u (the zone shrunk past the value): never "conforms"
            assert dec["outcome"] != "conforms", dec
            continue
        # inside the acceptance zone: conforms but for the flag
        if r["diameter_range_excess_m"] is None:
            assert dec["outcome"] == "conforms" and dec.get("nominal_range_excess_m") is None
            continue
        # the decision does not say "conforms" on a fit the plausibility check flagged
        assert dec["outcome"] == "cannot_decide"
        assert dec["nominal_range_excess_m"] == r["diameter_range_excess_m"]
        assert "outside the nominal diameter range [127.0, 137.0] mm" in dec["note"]
        flagged.append({"part_id": f"N{k}", "excess": r["diameter_range_excess_m"]})
        break
    assert flagged, "no recipe part of six landed just outside the range and inside its acceptance zone"
    hist = client.get("/api/v1/recipes/SHAFT-NARROW-RANGE/history").json()
    assert sorted((h["part_id"], h["outcome"]) for h in hist if h["state"] == "done") == sorted(outcomes)
    (row,) = [h for h in hist if h["part_id"] == flagged[0]["part_id"]]
    assert row["outcome"] == "cannot_decide" and row["nominal_range_excess_m"] == flagged[0]["excess"]
    text = client.get("/api/v1/recipes/SHAFT-NARROW-RANGE/history.csv").text
    assert text.splitlines()[0].endswith(",usl_m,nominal_range_excess_m")
    (line,) = [x for x in csv.DictReader(io.StringIO(text)) if x["part_id"] == flagged[0]["part_id"]]
    assert float(line["nominal_range_excess_m"]) == pytest.approx(flagged[0]["excess"], rel=1e-12)
    # far outside (the range ends 12.5 mm below, about 30 u): the measurement fails with the reason
    far = _finished(
        client,
        {"target": "cylinder", "sweep": STEP, "options": {"nominal_diameter_m": 0.12, "diameter_tolerance_m": 0.005}},
    )
    assert far["state"] == "failed" and "diameter_m" not in (far["result"] or {})  # the sweep's partial result
    assert "no cylinder of the nominal diameter found" in far["error"]
    assert "is outside [115.0, 125.0] mm by" in far["error"]
