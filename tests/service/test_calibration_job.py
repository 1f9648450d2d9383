"""The calibration sweep in the service (issue 12, ``POST /api/v1/calibrations``), over real HTTP.

The whole loop on the simulated rig, in its own process as ``lrms serve`` runs it: a rig with
known errors (``[sim] rig_errors``) in the ``room-spheres-part`` scene runs a calibration sweep
queued by REST; the adjustment recovers the errors, the calibration is stored and activated, and
the next measurement of seed 003's part uses it. A sweep that sees no spheres fails with the
reason, keeps its raw log and stores nothing. Requests the route refuses (a bad artefact, a sweep
the rig cannot run, an operator's token, a calibration posted as a measurement or a schedule)
queue nothing and store nothing.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from lrms.kinematics import RigModel
from service.api import ServerThread, Service, create_app
from service.config import TOKEN_ENV, parse_toml
from service.jobs import JobContext
from sim.scene.library import SEED003_DIAMETER, room_spheres_artefact

ADMIN = "adm1n"
OPERATOR = "0perator"
AUTH = {"Authorization": f"Bearer {ADMIN}"}
OP = {"Authorization": f"Bearer {OPERATOR}"}
D = np.deg2rad
RIG_ERRORS = "{range_offset_m = 0.025, tilt_x_deg = 0.25, alpha_zero_deg = 0.12}"
TRUE_RIG = RigModel(k0=0.025, tilt_x=D(0.25), alpha_zero=D(0.12))


def _config(tmp_path: Path, extra: str = "") -> Any:
    return parse_toml(
        f"name = 'rig-a'\n[sim]\n{extra}\n[storage]\nrig_id = 'rig-a'\ndir = '{tmp_path / 'data'}'\n"
        f"[auth]\nread = 'open'\nadmin_token = '{ADMIN}'\noperator_token = '{OPERATOR}'\n"
    )


def _wait(client: httpx.Client, mid: str, timeout: float = 300.0) -> dict[str, Any]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        body: dict[str, Any] = client.get(f"/api/v1/measurements/{mid}").json()
        if body["state"] in ("done", "failed", "cancelled"):
            return body
        time.sleep(0.1)
    raise AssertionError(f"job {mid} did not finish")


def test_a_calibration_sweep_on_the_miscalibrated_rig_then_a_measurement_with_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from service.rig import build_service

    monkeypatch.delenv(TOKEN_ENV, raising=False)
    svc, rig = build_service(_config(tmp_path, f"scene = 'room-spheres-part'\nrig_errors = {RIG_ERRORS}"))
    body = {"artefact": room_spheres_artefact(), "name": "room", "comment": "after the move", "activate": True}
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as client:
            # a sweep that sees none of the spheres: failed with the reason, raw log kept, nothing stored
            narrow = client.post(
                "/api/v1/calibrations", json={**body, "sweep": {"start_deg": -3, "stop_deg": 3}}, headers=AUTH
            )
            assert narrow.status_code == 202, narrow.text
            failed = _wait(client, narrow.json()["id"])
            assert failed["state"] == "failed" and "no spheres found" in failed["error"], failed
            # the sweep's counters are kept, as for a failed fit
            assert failed["has_raw"] and failed["result"]["mapping"]["points"] > 0, failed
            assert client.get("/api/v1/calibrations").json() == []

            # the default sweep (-90..90 deg at 20 deg/s)
            r = client.post("/api/v1/calibrations", json=body, headers=AUTH)
            assert r.status_code == 202, r.text
            job = r.json()
            assert r.headers["Location"] == f"/api/v1/measurements/{job['id']}"
            assert job["request"]["target"] == "calibration" and job["request"]["sweep"]["start_deg"] == -90.0
            done = _wait(client, job["id"])
            assert done["state"] == "done", done
            res = done["result"]
            drift = res["clock"]["drift_ppm"] * 1e-6  # the simulated scanner's clock has none: all of it is error
            cid = res["calibration_id"]
            assert res["calibration_active"] and res["calibration"] is None  # swept with the nominal rig
            assert "calibration_result" not in res  # stored, not repeated in the job
            assert {"k0", "tilt_x", "alpha_zero"} <= set(res["calibration_summary"]["estimated"])
            assert "beta_zero" in res["identifiability"]["held"]
            assert done["has_raw"]
            stored = client.get(f"/api/v1/calibrations/{cid}").json()
            active = client.get("/api/v1/calibrations/active").json()
            assert active["id"] == cid and stored["name"] == "room" and stored["comment"] == "after the move"
            cal = stored["calibration"]
            assert cal["sources"] == [f"measurement {job['id']}"]
            report = client.get(f"/api/v1/measurements/{job['id']}/report.html")
            assert report.status_code == 409 and cid in report.json()["detail"]

            # the part, measured with the calibration just made (the rig's default sweep)
            m = client.post(
                "/api/v1/measurements",
                json={"target": "cylinder", "options": {"nominal_diameter_m": SEED003_DIAMETER}},
                headers=OP,
            ).json()
            part = _wait(client, m["id"])
            # the job's raw log through `lrms calibrate`: the same calibration, uploaded beside it
            from service.cli.main import main

            log = tmp_path / "cal.mcap"
            log.write_bytes(client.get(f"/api/v1/measurements/{job['id']}/raw").content)
            art = tmp_path / "artefact.json"
            art.write_text(json.dumps(room_spheres_artefact()))
            out = tmp_path / "cli.json"
            # its range noise: the recording rig's [noise], as the service adjusted with it (not NoiseModel()'s)
            argv = ["calibrate", str(log), "--artefact", str(art), "--out", str(out), "--upload", srv.url]
            assert main([*argv, "--token", ADMIN, "--name", "from the log"]) == 0
            listed = client.get("/api/v1/calibrations").json()
            from service.replay import replay

            replayed = replay(log)
    finally:
        svc.stop()
        rig.close()
    std = cal["std"]
    for name, true in (("k0", TRUE_RIG.k0), ("tilt_x", TRUE_RIG.tilt_x), ("alpha_zero", TRUE_RIG.alpha_zero)):
        err = cal["model"][name] - true
        print(f"calibration sweep: {name} off by {err / std[name]:+.2f} std")
        assert abs(err) <= 4 * std[name], (name, cal["model"][name], std[name])
    for name in ("k1", "p", "q", "beta_scale"):  # true 0 (the rig has no error there)
        if name in std:
            err = cal["model"][name] - RigModel().to_dict()[name]
            print(f"calibration sweep: {name} off by {err / std[name]:+.2f} std")
            if name == "beta_scale":
                # a rate error of the scanner clock's estimate (the time sync) scales the motor angles
                # like beta_scale, and the adjustment's std does not hold it (docs/calibration.md)
                print(f"calibration sweep: clock drift estimate {drift * 1e6:+.1f} ppm (true 0)")
                assert abs(err) <= 4 * std[name] + abs(drift), (name, cal["model"][name], std[name], drift)
                continue
            assert abs(cal["model"][name] - RigModel().to_dict()[name]) <= 4 * std[name], (name, cal["model"][name])
    assert part["state"] == "done", part
    result = part["result"]
    assert result["calibration"]["id"] == cid
    u_c = result["uncertainty"]["combined_m"]
    err = result["diameter_m"] - SEED003_DIAMETER
    print(f"part after the calibration sweep: {1e3 * err:+.3f} mm, u_c {1e3 * u_c:.3f} mm")
    assert abs(err) <= 3 * u_c, (result["diameter_m"], u_c)
    assert any(row["source"].startswith("calibration") for row in result["uncertainty"]["budget"])
    cli = json.loads(out.read_text())
    assert cli["sources"] == [str(log)] and cli["estimated"] == cal["estimated"]
    for name in cal["estimated"]:
        assert cli["model"][name] == pytest.approx(cal["model"][name], abs=1e-3 * std[name]), name
    assert [(c["name"], c["active"]) for c in listed] == [("from the log", False), ("room", True)]
    # the replay of the calibration sweep's log computes its calibration again, the same
    assert replayed["reproduced"], replayed["max_abs_diff"]


class _Refused:
    """A measurement function for the refusals: nothing may reach it."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, ctx: JobContext) -> dict[str, Any]:
        self.calls += 1
        return {}


@pytest.fixture
def served(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[httpx.Client, Service, _Refused]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    fn = _Refused()
    svc = Service(_config(tmp_path), fn)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as client:
        yield client, svc, fn


@pytest.mark.parametrize(
    ("body", "loc", "words"),
    [
        (
            {"artefact": {"spheres": [{"diameter_m": -0.2}]}},
            ["body", "artefact", "spheres", 0, "diameter_m"],
            "greater",
        ),
        (
            {"artefact": {"spheres": [{"diameter_m": 0.2}], "distances_m": [{"a": 0, "b": 1, "distance_m": 1.0}]}},
            ["body", "artefact"],
            "two different of the 1 spheres",
        ),
        ({"artefact": {"planes": False}}, ["body", "artefact"], "needs planes or spheres"),
        ({"artefact": {"planes": True, "cones": []}}, ["body", "artefact", "cones"], "Extra inputs"),
        ({"artefact": {}, "optics": "laser"}, ["body", "optics"], "'ideal' or 'lms1xx'"),
        ({"artefact": {}, "sweep": {"start_deg": -179.0, "stop_deg": 179.0}}, ["body", "sweep"], "travel"),
        ({}, ["body", "artefact"], "Field required"),
        (  # a calibration file (lrms calibrate --out) posted here, as an old client would upload it
            {"schema": "lrms.calibration/1", "model": {}, "artefact": {"planes": True}},
            ["body"],
            "POST /api/v1/calibrations/upload",
        ),
    ],
)
def test_bad_calibration_requests_are_422_and_nothing_is_queued(
    served: tuple[httpx.Client, Service, _Refused], body: dict[str, Any], loc: list[Any], words: str
) -> None:
    client, _, fn = served
    r = client.post("/api/v1/calibrations", json=body, headers=AUTH)
    assert r.status_code == 422, r.text
    errors = r.json()["detail"]
    assert any(e["loc"][: len(loc)] == loc and words in e["msg"] for e in errors), errors
    assert client.get("/api/v1/measurements").json() == []
    assert client.get("/api/v1/calibrations").json() == []
    assert fn.calls == 0


def test_a_calibration_sweep_needs_the_admin_and_its_own_route(served: tuple[httpx.Client, Service, _Refused]) -> None:
    client, _, fn = served
    body = {"artefact": room_spheres_artefact()}
    assert client.post("/api/v1/calibrations", json=body, headers=OP).status_code == 403
    assert client.post("/api/v1/calibrations", json=body).status_code == 401
    as_measurement = {"target": "calibration", "calibration": body}
    r = client.post("/api/v1/measurements", json=as_measurement, headers=OP)
    assert r.status_code == 422 and "'cylinder' or 'elbow'" in r.text, r.text
    r = client.post("/api/v1/schedules", json={"interval_s": 3600, "measurement": as_measurement}, headers=AUTH)
    assert r.status_code == 422 and "'cylinder' or 'elbow'" in r.text, r.text
    # the public schemas do not offer it either
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    assert schemas["MeasurementRequest"]["properties"]["target"]["anyOf"][0]["enum"] == ["cylinder", "elbow"]
    assert "calibration" not in schemas["MeasurementRequest"]["properties"]
    assert client.get("/api/v1/measurements").json() == [] and client.get("/api/v1/schedules").json() == []
    assert fn.calls == 0


def test_a_job_without_a_calibration_in_its_result_fails_and_stores_nothing(
    served: tuple[httpx.Client, Service, _Refused],
) -> None:
    """The service process stores only a valid calibration: a result without one (a rig process of
    another version) fails the job with the reason."""
    client, _, fn = served
    r = client.post("/api/v1/calibrations", json={"artefact": room_spheres_artefact()}, headers=AUTH)
    assert r.status_code == 202
    job = _wait(client, r.json()["id"], 30.0)
    assert job["state"] == "failed" and "returned no calibration" in job["error"], job
    assert fn.calls == 1 and client.get("/api/v1/calibrations").json() == []


class _AdjustsUntilCancelled:
    """The rig's side of a calibration sweep cancelled during its adjustment: the sweep is over,
    the adjustment (here: a valid calibration) finishes after the cancel arrived."""

    def __call__(self, ctx: JobContext) -> dict[str, Any]:
        from tests.service.test_calibrations import CAL

        ctx.progress(0.86, "mapping")
        end = time.monotonic() + 20.0
        while not ctx.cancelled and time.monotonic() < end:
            time.sleep(0.02)
        return {"calibration_result": CAL.to_dict()}


def test_a_calibration_sweep_cancelled_during_its_adjustment_stores_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    svc = Service(_config(tmp_path), _AdjustsUntilCancelled())
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as client:
        body = {"artefact": room_spheres_artefact(), "activate": True}
        job = client.post("/api/v1/calibrations", json=body, headers=AUTH).json()
        end = time.monotonic() + 10.0
        while client.get(f"/api/v1/measurements/{job['id']}").json()["message"] != "mapping":
            assert time.monotonic() < end
            time.sleep(0.02)
        assert client.post(f"/api/v1/measurements/{job['id']}/cancel", headers=AUTH).status_code == 200
        done = _wait(client, job["id"], 30.0)
        assert done["state"] == "cancelled", done
        assert client.get("/api/v1/calibrations").json() == []
        assert client.get("/api/v1/calibrations/active").status_code == 404
