"""Rig calibrations in the service (issue 12), over real HTTP: the store and ``/api/v1/calibrations``
(upload, list, read, activate, bad input stores nothing), measurements on the simulated rig
using the active calibration (its rig model, its budget row, the result naming it, the replay
reproducing it), and ``lrms calibrate --upload`` refused. ``lrms calibrate`` on the raw log of a
calibration sweep the service ran is in test_calibration_job.py."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from lrms.calibration import CalibrationResult, Identifiability
from lrms.kinematics import RigModel
from service.api import ServerThread, Service, create_app
from service.config import TOKEN_ENV, parse_toml
from service.jobs import JobContext

ADMIN = "adm1n"
UPLOAD = "/api/v1/calibrations/upload"
OPERATOR = "0perator"
AUTH = {"Authorization": f"Bearer {ADMIN}", "Content-Type": "application/json"}
OP = {"Authorization": f"Bearer {OPERATOR}", "Content-Type": "application/json"}
D = np.deg2rad
#: The simulated rig's true errors (``[sim] rig_errors``) and the same as a rig model.
RIG_ERRORS = "{range_offset_m = 0.025, tilt_x_deg = 0.25, alpha_zero_deg = 0.12}"
TRUE_RIG = RigModel(k0=0.025, tilt_x=D(0.25), alpha_zero=D(0.12))


def handmade(model: RigModel, std: dict[str, float], created: str = "2026-01-01T00:00:00+00:00") -> CalibrationResult:
    """A calibration of ``model`` with independent standard deviations ``std`` (SI)."""
    cov = np.zeros((len(RigModel.NAMES), len(RigModel.NAMES)))
    for n, s in std.items():
        i = RigModel.NAMES.index(n)
        cov[i, i] = s * s
    return CalibrationResult(
        model=model,
        nominal=RigModel(),
        covariance=cov,
        estimated=tuple(std),
        identifiability=Identifiability(held={"beta_zero": "a rotation about the shaft"}, rank=len(std), condition=1.0),
        surfaces=(),
        residuals={"variance_factor": 1.0},
        artefact={"planes": True, "spheres": [], "distances_m": []},
        sources=("test",),
        created=created,
        software_version="test",
    )


CAL = handmade(TRUE_RIG, {"k0": 3e-4, "tilt_x": D(0.003), "alpha_zero": D(0.0015)})


def _config(tmp_path: Path, extra: str = "") -> Any:
    return parse_toml(
        f"name = 'rig-a'\n[sim]\n{extra}\n[storage]\nrig_id = 'rig-a'\ndir = '{tmp_path / 'data'}'\n"
        f"[auth]\nread = 'open'\nadmin_token = '{ADMIN}'\noperator_token = '{OPERATOR}'\n"
    )


class Recording:
    """A measurement function that returns the calibration the service handed it."""

    def __call__(self, ctx: JobContext) -> dict[str, Any]:
        return {"calibration_id": None if ctx.calibration is None else ctx.calibration["id"]}


@pytest.fixture
def served(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[httpx.Client, Service]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    svc = Service(_config(tmp_path), Recording())
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as client:
        yield client, svc


def _wait(client: httpx.Client, mid: str, timeout: float = 120.0) -> dict[str, Any]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        body: dict[str, Any] = client.get(f"/api/v1/measurements/{mid}").json()
        if body["state"] in ("done", "failed", "cancelled"):
            return body
        time.sleep(0.05)
    raise AssertionError(f"measurement {mid} did not finish")


def test_upload_list_read_activate_round_trip(served: tuple[httpx.Client, Service]) -> None:
    client, _ = served
    assert client.get("/api/v1/calibrations").json() == []
    assert client.get("/api/v1/calibrations/active").status_code == 404
    r = client.post(UPLOAD, params={"name": "room 1"}, content=CAL.to_json(), headers=AUTH)
    assert r.status_code == 201, r.text
    first = r.json()
    assert r.headers["Location"] == f"/api/v1/calibrations/{first['id']}"
    assert first["name"] == "room 1" and first["rig_id"] == "rig-a" and not first["active"]
    assert first["calibrated"] == CAL.created and first["estimated"] == ["k0", "tilt_x", "alpha_zero"]
    assert first["model"]["k0_mm"] == pytest.approx(25.0)
    # the stored calibration is the uploaded one, bit for bit
    got = client.get(f"/api/v1/calibrations/{first['id']}").json()
    back = CalibrationResult.from_dict(got["calibration"])
    assert back.model == CAL.model and np.array_equal(back.covariance, CAL.covariance)
    second = client.post(UPLOAD, params={"name": "room 2"}, content=CAL.to_json(), headers=AUTH).json()
    assert [c["id"] for c in client.get("/api/v1/calibrations").json()] == [second["id"], first["id"]]
    # one active per rig: activating the second deactivates the first
    assert client.post(f"/api/v1/calibrations/{first['id']}/activate", headers=AUTH).json()["active"]
    assert client.get("/api/v1/calibrations/active").json()["id"] == first["id"]
    client.post(f"/api/v1/calibrations/{second['id']}/activate", headers=AUTH)
    listed = {c["id"]: c["active"] for c in client.get("/api/v1/calibrations").json()}
    assert listed == {first["id"]: False, second["id"]: True}
    # another rig's calibrations are apart
    other = client.post(
        UPLOAD, params={"rig_id": "rig-b", "activate": "true"}, content=CAL.to_json(), headers=AUTH
    ).json()
    assert other["active"] and client.get("/api/v1/calibrations/active").json()["id"] == second["id"]
    assert [c["id"] for c in client.get("/api/v1/calibrations", params={"rig_id": "rig-b"}).json()] == [other["id"]]
    assert client.get("/api/v1/calibrations/0123456789abcdef").status_code == 404
    assert client.post("/api/v1/calibrations/0123456789abcdef/activate", headers=AUTH).status_code == 404


def test_writes_need_the_admin_token(served: tuple[httpx.Client, Service]) -> None:
    client, _ = served
    assert client.post(UPLOAD, content=CAL.to_json()).status_code == 401
    assert client.post(UPLOAD, content=CAL.to_json(), headers=OP).status_code == 403
    cid = client.post(UPLOAD, content=CAL.to_json(), headers=AUTH).json()["id"]
    assert client.post(f"/api/v1/calibrations/{cid}/activate", headers=OP).status_code == 403
    assert client.get("/api/v1/calibrations/active").status_code == 404


def _bad(d: dict[str, Any], *path: Any, value: Any) -> str:
    cur: Any = d
    for key in path[:-1]:
        cur = cur[key]
    cur[path[-1]] = value
    return json.dumps(d)


@pytest.mark.parametrize(
    ("make", "says"),
    [
        (lambda d: json.dumps({"hello": 1}), "not a calibration"),
        (lambda d: json.dumps([1, 2]), "valid dictionary"),
        (lambda d: _bad(d, "model", "k0", value="far"), "malformed"),
        (lambda d: _bad(d, "model", "warp", value=1.0), "unknown rig parameter"),
        (lambda d: d_text(d).replace('"k0": 0.025', '"k0": NaN', 1), "finite"),
        (lambda d: _bad(d, "covariance", value=[[1.0]]), "11x11"),
        (lambda d: _bad(d, "covariance", 0, 1, value=1e-6), "symmetric"),
        (lambda d: _bad(d, "covariance", 0, 0, value=-1e-6), "positive semi-definite"),
        (lambda d: _bad(d, "covariance", 3, 3, value=1e-6), "not estimated must be zero"),
        (lambda d: _bad(d, "estimated", value=["k0", "k0"]), "twice"),
        (lambda d: _bad(d, "estimated", value=["k0", "warp"]), "unknown rig parameter"),
        (lambda d: _bad(d, "residuals", value={"x": "y"}), "malformed"),
    ],
)
def test_bad_calibrations_are_422_and_nothing_is_stored(
    served: tuple[httpx.Client, Service], make: Any, says: str
) -> None:
    client, _ = served
    r = client.post(
        "/api/v1/calibrations/upload", content=make(CAL.to_dict()), headers={**AUTH, "Content-Type": "application/json"}
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["detail"][0]["loc"] == ["body"] and says in body["message"], body
    assert client.get("/api/v1/calibrations").json() == []


def d_text(d: dict[str, Any]) -> str:
    return json.dumps(d)


def test_not_json_is_a_clear_error_not_500(served: tuple[httpx.Client, Service]) -> None:
    client, _ = served
    r = client.post(UPLOAD, content=b"{not json", headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code in (400, 422), r.text
    r = client.post(
        UPLOAD, params={"name": "x" * 300}, content=CAL.to_json(), headers=AUTH
    )  # a name past 200 characters
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "name"]


def test_the_job_gets_the_active_calibration_when_it_starts(served: tuple[httpx.Client, Service]) -> None:
    client, svc = served
    m0 = client.post("/api/v1/measurements", json={"target": "cylinder"}, headers=OP).json()["id"]
    assert _wait(client, m0)["result"] == {"calibration_id": None}
    cid = client.post(UPLOAD, params={"activate": "true"}, content=CAL.to_json(), headers=AUTH).json()
    m1 = client.post("/api/v1/measurements", json={"target": "cylinder"}, headers=OP).json()["id"]
    assert _wait(client, m1)["result"] == {"calibration_id": cid["id"]}
    # the store survives a restart of the service (same database file)
    svc2 = Service(svc.config, Recording())
    assert svc2.calibrations.active("rig-a") is not None
    assert svc2.calibrations.active("rig-a").id == cid["id"]  # type: ignore[union-attr]


# -- the simulated rig -----------------------------------------------------------------------------


def test_measurements_on_a_miscalibrated_rig_use_the_active_calibration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The simulated rig has true errors; without a calibration the part's diameter is off and its
    budget carries the uncalibrated range offset; with the truth's calibration active the fit uses
    the calibrated beams, names the calibration, and its budget has the calibration's row instead
    of the rows it covers. The replay of the raw log reproduces the calibrated result."""
    from service.replay import replay
    from service.rig import build_service

    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = _config(tmp_path, f"rig_errors = {RIG_ERRORS}")
    svc, rig = build_service(cfg)  # the rig in its own process, as `lrms serve` runs it
    req = {"target": "cylinder", "sweep": {"speed_deg_s": 20.0}}
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as client:
            # two sweeps each way: one sweep's uncalibrated diameter scatters by 0.7 mm about its -2.7 mm
            # (six runs: -1.7..-3.7 mm; twice in about 15 fresh-clone CI runs a single one came out at
            # -0.43 / -0.63 mm), the calibrated one by 0.4 mm: the means are compared
            befores = [
                _wait(client, client.post("/api/v1/measurements", json=req, headers=OP).json()["id"]) for _ in range(2)
            ]
            cal = client.post(
                "/api/v1/calibrations/upload",
                params={"name": "truth", "activate": "true"},
                content=CAL.to_json(),
                headers=AUTH,
            ).json()
            afters = [
                _wait(client, client.post("/api/v1/measurements", json=req, headers=OP).json()["id"]) for _ in range(2)
            ]
    finally:
        svc.stop()
        rig.close()
    for m in (*befores, *afters):
        assert m["state"] == "done", m["error"]
    before, after = befores[0], afters[0]
    b, a = before["result"], after["result"]
    assert b["calibration"] is None
    assert a["calibration"] == {"id": cal["id"], "name": "truth", "created": cal["created"]}
    truth = 0.1375
    # 25 mm of range offset and a tilted plane: -2.5 mm seen on an idle machine; -2.5 and -3.6 mm at load 8
    # now that the motor samples carry the drive's latch time (-0.9 mm once before, with the SYNC time's
    # smear, docs/service.md known limits): the calibrated result must be the closer
    assert b["sweep"]["motor_time_source"] == "drive"
    # what the next failure needs to be traced (fresh-clone runs, 2026-11-24: before -0.63 mm, after
    # +0.97 mm; before -0.43, after -0.16 mm; 13 runs on this machine: before -1.7..-4.5, after -0.78..+1.17 mm)
    why = {
        f"{k}{i}": {
            "error_mm": 1e3 * (m["result"]["diameter_m"] - truth),
            "u_c_mm": 1e3 * m["result"]["uncertainty"]["combined_m"],
            "inliers": m["result"].get("n_inliers"),
            "chi2_dof": m["result"].get("chi2_dof"),
            "scans_missing": m["result"]["sweep"].get("scans_missing"),
            "scan_gaps": m["result"]["sweep"].get("scan_gaps"),
            "motor_timing_jitter_s": m["result"]["sweep"].get("motor_timing_jitter_s"),
        }
        for k, ms in (("before", befores), ("after", afters))
        for i, m in enumerate(ms)
    }
    err_b = float(np.mean([m["result"]["diameter_m"] for m in befores])) - truth
    err_a = float(np.mean([m["result"]["diameter_m"] for m in afters])) - truth
    assert err_b < -0.5e-3, why  # about 4 std of a mean of two from its -2.7 mm
    assert abs(err_a) < abs(err_b), why
    # the fit's own noise (u ~ 0.5 mm at 20 deg/s) dominates the calibrated result: within 3 u_c
    assert abs(a["diameter_m"] - truth) <= 3 * a["uncertainty"]["combined_m"], why
    tilt = [np.rad2deg(np.arccos(abs(r["axis_direction"][2]))) for r in (b, a)]
    assert tilt[0] > 1.0 and tilt[1] < 0.4, tilt  # 1.4 deg before; after: the fit's noise (0.015, 0.12 deg seen)
    rows_b = {r["source"]: r for r in b["uncertainty"]["budget"]}
    rows_a = {r["source"]: r for r in a["uncertainty"]["budget"]}
    assert "calibration" not in rows_b and "range offset" in rows_b and "alpha zero" in rows_b
    assert "range offset" not in rows_a and "alpha zero" not in rows_a and "range scale" in rows_a
    row = rows_a["calibration"]
    # k0's std alone (0.3 mm) moves the diameter by |sum of range gains| x 0.3 mm: a part of a mm
    assert 1e-6 < row["u_m"] < 1e-3 and "k0, tilt_x, alpha_zero" in row["note"]
    # the calibration row is smaller than the uncalibrated rows it replaces (the type-A rows of the two
    # sweeps are each their own noise, which load on the machine inflates: not compared)
    replaced = float(np.hypot(rows_b["range offset"]["u_m"], rows_b["alpha zero"]["u_m"]))
    assert row["u_m"] < replaced, (row, replaced)
    raw = Path(cfg.storage.dir) / "raw" / f"{after['id']}.mcap"
    if not raw.exists():
        raw = next(Path(cfg.storage.dir).rglob(f"{after['id']}.mcap"))
    rep = replay(raw)
    assert rep["reproduced"], rep["max_abs_diff"]
    assert rep["result"]["calibration"] == a["calibration"]


def test_calibrate_upload_refused_is_a_clear_error(served: tuple[httpx.Client, Service], tmp_path: Path) -> None:
    from service.cli.calibrate import upload
    from service.errors import ServiceError

    client, _ = served
    with pytest.raises(ServiceError, match=r"refused the calibration \(403\)"):
        upload(CAL.to_json(), str(client.base_url), OPERATOR, "x", "", False)
    with pytest.raises(ServiceError, match=r"refused the calibration \(422\).*not a calibration"):
        upload("{}", str(client.base_url), ADMIN, "x", "", False)
    stored = upload(CAL.to_json(), f"{client.base_url}/api/v1/calibrations", ADMIN, "x", "", True)
    assert stored["active"] and client.get("/api/v1/calibrations").json()[0]["id"] == stored["id"]
