"""Recipes, part measurements, thermal correction, conformity decisions, history and SPC over HTTP.

A scripted measurement function (it returns a cylinder result with a chosen diameter and budget, as
the rig's does) makes the numbers hand-computable; the decisions on the simulated rig are in
``test_recipes_rig.py``.
"""

from __future__ import annotations

import csv
import io
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.api import ServerThread, Service, create_app
from service.config import TOKEN_ENV, parse_toml
from service.jobs import JobContext

TOKEN = "r3cipe"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
U_FIT = 2e-4  # the scripted result's one budget row (m)


def recipe(name: str = "FLANGE-SHAFT-320", **kw: Any) -> dict[str, Any]:
    body: dict[str, Any] = {
        "name": name,
        "target": "cylinder",
        "tolerances": {"diameter": {"nominal_m": 0.320, "lower_m": -0.0005, "upper_m": 0.0015}},
        "material": "carbon_steel",
        "sweep": {"speed_deg_s": 20.0},
    }
    body.update(kw)
    return body


class Scripted:
    """Returns the next diameter of ``values`` as a cylinder result with one budget row of U_FIT."""

    def __init__(self) -> None:
        self.values: list[float] = []
        self.lock = threading.Lock()

    def __call__(self, ctx: JobContext) -> dict[str, Any]:
        with self.lock:
            d = self.values.pop(0)
        row = {"source": "fit (type A)", "type": "A", "u_x": U_FIT, "unit": "m", "c": 1.0, "u_m": U_FIT}
        row |= {"distribution": "normal", "note": ""}
        unc = {"budget": [row], "combined_m": U_FIT, "expanded_m": 2 * U_FIT, "k": 2.0, "correlation": ""}
        return {"model": "cylinder", "diameter_m": d, "uncertainty": unc}


@pytest.fixture
def served(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[httpx.Client, Scripted]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = parse_toml(f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\n[auth]\nread = 'open'\nadmin_token = '{TOKEN}'\n")
    measure = Scripted()
    svc = Service(cfg, measure)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0, headers=AUTH) as client:
        yield client, measure


def wait_done(client: httpx.Client, mid: str, timeout: float = 20.0) -> dict[str, Any]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        body: dict[str, Any] = client.get(f"/api/v1/measurements/{mid}").json()
        if body["state"] in ("done", "failed", "cancelled"):
            assert body["state"] == "done", body["error"]
            return body
        time.sleep(0.02)
    raise AssertionError(f"measurement {mid} did not finish")


def measure_part(client: httpx.Client, measure: Scripted, d: float, **part: Any) -> dict[str, Any]:
    measure.values.append(d)
    r = client.post("/api/v1/measurements", json={"recipe": "FLANGE-SHAFT-320", "part_id": "4711", **part})
    assert r.status_code == 202, r.text
    return wait_done(client, r.json()["id"])


def loc_of(r: httpx.Response) -> list[list[str | int]]:
    assert r.status_code == 422, r.text
    return [d["loc"] for d in r.json()["detail"]]


def test_recipes_are_versioned_and_old_versions_stay_readable(served: tuple[httpx.Client, Scripted]) -> None:
    client, _ = served
    r = client.post("/api/v1/recipes", json=recipe())
    assert r.status_code == 201 and r.headers["location"] == "/api/v1/recipes/FLANGE-SHAFT-320"
    v1 = r.json()
    assert v1["version"] == 1 and v1["retired"] is False and v1["decision_rule"] == "iso14253-1"
    assert client.post("/api/v1/recipes", json=recipe()).status_code == 409
    changed = recipe(tolerances={"diameter": {"nominal_m": 0.320, "lower_m": -0.001, "upper_m": 0.001}})
    r = client.put("/api/v1/recipes/FLANGE-SHAFT-320", json=changed)
    assert r.status_code == 200 and r.json()["version"] == 2
    assert client.get("/api/v1/recipes/FLANGE-SHAFT-320").json()["tolerances"]["diameter"]["lower_m"] == -0.001
    old = client.get("/api/v1/recipes/FLANGE-SHAFT-320/versions/1").json()
    assert old["tolerances"]["diameter"]["lower_m"] == -0.0005 and old["version"] == 1
    assert [v["version"] for v in client.get("/api/v1/recipes/FLANGE-SHAFT-320/versions").json()] == [1, 2]
    assert client.get("/api/v1/recipes/FLANGE-SHAFT-320/versions/3").status_code == 404
    assert client.get("/api/v1/recipes/NOPE").status_code == 404
    # the body's name must be the path's; PUT of an unknown recipe is a 404
    assert loc_of(client.put("/api/v1/recipes/FLANGE-SHAFT-320", json=recipe("OTHER"))) == [["body", "name"]]
    assert client.put("/api/v1/recipes/OTHER", json=recipe("OTHER")).status_code == 404
    # writes need the admin token; reads are open here
    assert client.post("/api/v1/recipes", json=recipe("X"), headers={"Authorization": "Bearer no"}).status_code == 401
    # retire: readable, not listed, no new parts; a new version revives it
    r = client.delete("/api/v1/recipes/FLANGE-SHAFT-320")
    assert r.status_code == 200 and r.json()["retired"] is True
    assert client.get("/api/v1/recipes").json() == []
    assert [x["name"] for x in client.get("/api/v1/recipes?include_retired=true").json()] == ["FLANGE-SHAFT-320"]
    r = client.post("/api/v1/measurements", json={"recipe": "FLANGE-SHAFT-320", "part_id": "1"})
    assert loc_of(r) == [["body", "recipe"]] and "retired" in r.json()["message"]
    assert client.put("/api/v1/recipes/FLANGE-SHAFT-320", json=changed).json() == {
        **client.get("/api/v1/recipes/FLANGE-SHAFT-320").json(),
        "version": 3,
        "retired": False,
    }


def test_toml_export_and_import_round_trip(served: tuple[httpx.Client, Scripted]) -> None:
    client, _ = served
    body = recipe(roi={"min_m": [0.1, 2.3, -0.1], "max_m": [0.5, 2.8, 0.8]}, options={"k": 3.0, "seed": 7})
    assert client.post("/api/v1/recipes", json=body).status_code == 201
    r = client.get("/api/v1/recipes/FLANGE-SHAFT-320.toml")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/toml")
    text = r.text
    assert text.startswith("# lrms recipe FLANGE-SHAFT-320, version 1") and "[tolerances.diameter]" in text
    copy = text.replace('name = "FLANGE-SHAFT-320"', 'name = "COPY"')
    r = client.post("/api/v1/recipes", content=copy, headers={"Content-Type": "application/toml"})
    assert r.status_code == 201, r.text
    a = client.get("/api/v1/recipes/FLANGE-SHAFT-320").json()
    b = client.get("/api/v1/recipes/COPY").json()
    drop = {"name", "created_at"}
    assert {k: v for k, v in a.items() if k not in drop} == {k: v for k, v in b.items() if k not in drop}
    # a TOML syntax error and a schema error in TOML are 422s naming where
    r = client.post("/api/v1/recipes", content="name = ", headers={"Content-Type": "application/toml"})
    assert loc_of(r) == [["body", "toml"]]
    bad = copy.replace('name = "COPY"', 'name = "COPY2"').replace("upper_m = 0.0015", "upper_m = -0.002")
    r = client.post("/api/v1/recipes", content=bad, headers={"Content-Type": "application/toml"})
    assert loc_of(r) == [["body", "tolerances", "diameter"]] and "lower_m" in r.json()["message"]
    assert client.get("/api/v1/recipes/COPY2").status_code == 404


@pytest.mark.parametrize(
    ("change", "loc", "needle"),
    [
        ({"tolerances": {"diameter": {"nominal_m": 0.32, "lower_m": 0.001, "upper_m": -0.001}}}, "diameter", "lower_m"),
        ({"tolerances": {"diameter": {"nominal_m": 0.32}}}, "diameter", "lower_m, upper_m or both"),
        ({"material": "unobtainium"}, "material", "unknown material"),
        ({"decision_rule": "lenient"}, "decision_rule", "iso14253-1"),
        ({"name": "has.dot"}, "name", "pattern"),
        ({"target": "cone"}, "target", "cylinder"),
        ({"colour": "red"}, "colour", "Extra inputs"),
        ({"sweep": {"speed_deg_s": -1}}, "speed_deg_s", "greater than"),
        (
            {
                "tolerances": {
                    "diameter": {"nominal_m": 0.3, "upper_m": 0.1},
                    "bend_angle": {"nominal_deg": 90, "upper_deg": 1},
                }
            },
            "",
            "elbow",
        ),
        ({"options": {"degree_deg": 90}}, "", "elbow"),
    ],
)
def test_bad_recipes_are_422_naming_the_field_and_store_nothing(
    served: tuple[httpx.Client, Scripted], change: dict[str, Any], loc: str, needle: str
) -> None:
    client, _ = served
    r = client.post("/api/v1/recipes", json=recipe(**change))
    locs = loc_of(r)
    assert any(loc in [str(x) for x in at] for at in locs) if loc else locs, r.json()
    assert needle in r.json()["message"]
    assert client.get("/api/v1/recipes?include_retired=true").json() == []


def test_bad_part_requests_are_422_naming_the_field_and_store_nothing(served: tuple[httpx.Client, Scripted]) -> None:
    client, _ = served
    client.post("/api/v1/recipes", json=recipe()).raise_for_status()
    client.post("/api/v1/recipes", json=recipe("COLD", material=None)).raise_for_status()
    part = {"recipe": "FLANGE-SHAFT-320", "part_id": "4711"}
    cases: list[tuple[dict[str, Any], list[str | int], str]] = [
        ({**part, "recipe": "NO-SUCH"}, ["body", "recipe"], "no recipe 'NO-SUCH'"),
        ({**part, "recipe_version": 9}, ["body", "recipe_version"], "no version 9"),
        ({**part, "part_temperature_c": -300, "temperature_uncertainty_c": 1}, ["body", "part_temperature_c"], ""),
        ({**part, "part_temperature_c": 1300, "temperature_uncertainty_c": 1}, ["body", "part_temperature_c"], "1200"),
        ({**part, "part_temperature_c": 900}, ["body"], "temperature_uncertainty_c"),
        (
            {**part, "recipe": "COLD", "part_temperature_c": 900, "temperature_uncertainty_c": 5},
            ["body", "part_temperature_c"],
            "no material",
        ),
        ({**part, "target": "cylinder"}, ["body", "target"], "comes from recipe"),
        ({**part, "sweep": {"speed_deg_s": 5}}, ["body", "sweep"], "comes from recipe"),
        ({"recipe": "FLANGE-SHAFT-320"}, ["body"], "part_id"),
        ({"target": "cylinder", "part_id": "1"}, ["body"], "only with a recipe"),
        ({**part, "part_id": "bad id with spaces"}, ["body", "part_id"], "pattern"),
    ]
    for body, loc, needle in cases:
        r = client.post("/api/v1/measurements", json=body)
        assert loc in loc_of(r), (body, r.json())
        assert needle in r.json()["message"], (body, r.json())
    assert client.get("/api/v1/measurements").json() == []
    assert client.get("/api/v1/recipes/FLANGE-SHAFT-320/history").json() == []


def test_hot_part_is_corrected_to_20c_and_decided_with_the_thermal_rows(served: tuple[httpx.Client, Scripted]) -> None:
    client, measure = served
    client.post("/api/v1/recipes", json=recipe()).raise_for_status()
    d_t = 0.3245  # measured at 1000 °C
    m = measure_part(client, measure, d_t, part_temperature_c=1000.0, temperature_uncertainty_c=10.0, operator="kim")
    assert m["request"]["recipe_version"] == 1 and m["request"]["target"] == "cylinder"
    res = m["result"]
    assert res["part"] == {"recipe": "FLANGE-SHAFT-320", "recipe_version": 1, "part_id": "4711", "operator": "kim"}
    # by hand, EN 1993-1-2 above 860 °C: e = 2e-5 T - 6.2e-3 (0 at 20 °C already), de/dT = 2e-5
    e = 2e-5 * 1000 - 6.2e-3
    d20 = d_t / (1 + e)
    u_temp = d_t / (1 + e) ** 2 * 2e-5 * 10.0
    u_data = d_t / (1 + e) ** 2 * 0.05 * e
    th = res["thermal"]
    assert th["material"] == "carbon_steel" and th["part_temperature_c"] == 1000.0
    assert th["temperature_uncertainty_c"] == 10.0 and th["diameter_measured_m"] == d_t
    assert th["diameter_20c_m"] == pytest.approx(d20, rel=1e-12)
    rows = {r["source"]: r for r in th["budget"]}
    assert rows["part temperature"]["u_m"] == pytest.approx(u_temp, rel=1e-9)
    assert rows["thermal expansion data (carbon_steel)"]["u_m"] == pytest.approx(u_data, rel=1e-9)
    assert set(rows["part temperature"]) == {"source", "type", "u_x", "unit", "c", "u_m", "distribution", "note"}
    assert th["u_thermal_m"] == pytest.approx(math.hypot(u_temp, u_data), rel=1e-9)
    big_u = 2 * math.sqrt((U_FIT / (1 + e)) ** 2 + u_temp**2 + u_data**2)
    dec = res["decision"]
    assert dec["rule"] == "iso14253-1" and dec["k"] == 2.0
    assert dec["value_m"] == pytest.approx(d20, rel=1e-12) and dec["expanded_m"] == pytest.approx(big_u, rel=1e-9)
    assert dec["lsl_m"] == pytest.approx(0.3195) and dec["usl_m"] == pytest.approx(0.3215)
    lo, hi = dec["acceptance_zone_m"]
    assert lo == pytest.approx(0.3195 + big_u) and hi == pytest.approx(0.3215 - big_u)
    # D20 = 320.083 mm, U = 0.601 mm: inside the tolerance but within U of its lower limit
    assert d20 == pytest.approx(0.320083, abs=1e-6) and big_u == pytest.approx(0.000601, abs=1e-6)
    assert dec["outcome"] == "cannot_decide" and "diameter at 20 °C" in dec["note"]
    assert set(res) >= {"part", "thermal", "decision", "diameter_m", "uncertainty"}


def test_cold_part_decisions_and_simple_acceptance(served: tuple[httpx.Client, Scripted]) -> None:
    client, measure = served
    client.post("/api/v1/recipes", json=recipe()).raise_for_status()
    ok = measure_part(client, measure, 0.3205)["result"]  # U = 0.4 mm: acceptance zone 319.9 .. 321.1
    assert ok["thermal"] is None and ok["decision"]["outcome"] == "conforms" and ok["decision"]["value_m"] == 0.3205
    assert ok["decision"]["expanded_m"] == pytest.approx(2 * U_FIT)
    assert measure_part(client, measure, 0.3220)["result"]["decision"]["outcome"] == "does_not_conform"
    assert measure_part(client, measure, 0.3214)["result"]["decision"]["outcome"] == "cannot_decide"
    client.put("/api/v1/recipes/FLANGE-SHAFT-320", json=recipe(decision_rule="simple-acceptance")).raise_for_status()
    dec = measure_part(client, measure, 0.3214)["result"]["decision"]
    assert dec["rule"] == "simple-acceptance" and dec["outcome"] == "conforms"
    assert dec["acceptance_zone_m"] == [pytest.approx(0.3195), pytest.approx(0.3215)]
    assert "guard bands would say: cannot decide" in dec["note"]


def test_history_and_spc_against_hand_computed_numbers(served: tuple[httpx.Client, Scripted]) -> None:
    client, measure = served
    # tolerance 0.3002 .. 0.3014 and values 0.3000 + x 1e-4 for x = 5 7 6 9 8 (docs/conformity.md's example)
    tol = {"diameter": {"nominal_m": 0.3, "lower_m": 2e-4, "upper_m": 14e-4}}
    client.post("/api/v1/recipes", json=recipe(tolerances=tol, material=None)).raise_for_status()
    xs = [5, 7, 6, 9, 8]
    assert client.get("/api/v1/recipes/FLANGE-SHAFT-320/spc").status_code == 409
    ids = [measure_part(client, measure, 0.3 + x * 1e-4, part_id=f"P{i}")["id"] for i, x in enumerate(xs)]
    hist = client.get("/api/v1/recipes/FLANGE-SHAFT-320/history").json()
    assert [h["measurement_id"] for h in hist] == ids and [h["part_id"] for h in hist] == [f"P{i}" for i in range(5)]
    assert [h["value_m"] for h in hist] == pytest.approx([0.3 + x * 1e-4 for x in xs])
    # U = 0.4 mm: 300.5 mm is within U of the LSL 300.2 mm; 300.7, 300.9, 300.8 are inside the acceptance zone
    assert [hist[i]["outcome"] for i in (0, 1, 3, 4)] == ["cannot_decide", "conforms", "conforms", "conforms"]
    assert all(h["recipe_version"] == 1 for h in hist)
    for url in ("/api/v1/recipes/FLANGE-SHAFT-320/history.csv", "/api/v1/recipes/FLANGE-SHAFT-320/history?format=csv"):
        r = client.get(url)
        assert r.headers["content-type"].startswith("text/csv")
        table = list(csv.DictReader(io.StringIO(r.text)))
        assert [t["measurement_id"] for t in table] == ids and float(table[3]["value_m"]) == pytest.approx(0.3009)
        assert table[0]["diameter_20c_m"] == "" and table[1]["outcome"] == "conforms"
    s = client.get("/api/v1/recipes/FLANGE-SHAFT-320/spc").json()
    # by hand: mean 7, MR 2 1 3 1, MR-bar 1.75, sigma 1.75 / 1.128, s = sqrt(2.5) (units of 1e-4 m)
    sig = 1.75 / 1.128
    assert s["n"] == 5 and s["mean_m"] == pytest.approx(0.3007, rel=1e-12)
    assert s["mr_bar_m"] == pytest.approx(1.75e-4, rel=1e-9) and s["sigma_within_m"] == pytest.approx(sig * 1e-4)
    assert s["i_ucl_m"] == pytest.approx(0.3 + (7 + 3 * sig) * 1e-4) and s["mr_ucl_m"] == pytest.approx(3.267 * 1.75e-4)
    cap = s["capability"]
    assert cap["cp"] == pytest.approx(12 / (6 * sig), rel=1e-6) and cap["cp"] == pytest.approx(1.2891, abs=1e-4)
    assert cap["cpk"] == pytest.approx(5 / (3 * sig), rel=1e-6) and cap["cpk"] == pytest.approx(1.0743, abs=1e-4)
    assert cap["pp"] == pytest.approx(12 / (6 * math.sqrt(2.5)), rel=1e-6)
    assert cap["ppk"] == pytest.approx(5 / (3 * math.sqrt(2.5)), rel=1e-6)
    mrs = [p["moving_range_m"] for p in s["points"]]
    assert mrs[0] is None and mrs[1:] == pytest.approx([2e-4, 1e-4, 3e-4, 1e-4])
    assert not any(p["flagged"] for p in s["points"])
    # a sixth part far off is beyond the limits and flagged
    measure_part(client, measure, 0.3025, part_id="P5")
    s = client.get("/api/v1/recipes/FLANGE-SHAFT-320/spc").json()
    assert s["points"][-1]["beyond_limits"] is True and s["points"][-1]["flagged"] is True
    assert client.get("/api/v1/recipes/NOPE/history").status_code == 404


def test_cli_import_and_export_round_trip(tmp_path: Path) -> None:
    import subprocess
    import sys

    from tests.conftest import REPO

    lrms = [sys.executable, "-m", "service.cli.main"]
    data = ["--data", str(tmp_path / "data")]
    src = tmp_path / "in.toml"
    src.write_text(
        'name = "PIN-20"\ntarget = "cylinder"\nmaterial = "stainless_austenitic"\ndecision_rule = "simple-acceptance"\n'
        "[tolerances.diameter]\nnominal_m = 0.02\nlower_m = -0.0001\nupper_m = 0.0001\n"
    )

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*lrms, "recipe", *args], cwd=REPO, capture_output=True, text=True, timeout=60)

    r = cli("import", str(src), *data)
    assert r.returncode == 0 and r.stdout.strip() == "PIN-20: created, version 1", r.stderr
    assert cli("import", str(src), *data).stdout.strip() == "PIN-20: unchanged, version 1"
    src.write_text(src.read_text().replace("upper_m = 0.0001", "upper_m = 0.0002"))
    assert cli("import", str(src), *data).stdout.strip() == "PIN-20: version 2"
    out = tmp_path / "out.toml"
    r = cli("export", "PIN-20", str(out), "--version", "1", *data)
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert text.startswith("# lrms recipe PIN-20, version 1") and "upper_m = 0.0001" in text
    assert 'decision_rule = "simple-acceptance"' in text
    assert "upper_m = 0.0002" in cli("export", "PIN-20", *data).stdout
    src.write_text(src.read_text().replace("lower_m = -0.0001", "lower_m = 0.0005"))
    r = cli("import", str(src), *data)
    assert r.returncode == 1 and r.stderr.startswith("error: tolerances.diameter: lower_m"), r.stderr
    r = cli("export", "NOPE", *data)
    assert r.returncode == 1 and "no recipe 'NOPE'" in r.stderr


def test_an_elbow_part_is_decided_on_its_diameter_with_the_fit_sigma(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = parse_toml(f"[sim]\n[storage]\ndir = '{tmp_path}'\n[auth]\nread = 'open'\nadmin_token = '{TOKEN}'\n")

    def elbow(ctx: JobContext) -> dict[str, Any]:
        assert ctx.request.target == "elbow" and ctx.request.options.degree_deg == 90.0
        sigma = {"D_m": 3e-4, "A_m": 5e-4}
        return {"model": "elbow", "diameter_m": 0.2190, "bend_radius_m": 0.305, "degree": 90.0, "sigma": sigma}

    body = {
        "name": "ELBOW-219",
        "target": "elbow",
        "tolerances": {
            "diameter": {"nominal_m": 0.2191, "lower_m": -0.002, "upper_m": 0.002},
            "bend_radius": {"nominal_m": 0.305, "lower_m": -0.003, "upper_m": 0.003},
            "bend_angle": {"nominal_deg": 90.0, "lower_deg": -1.0, "upper_deg": 1.0},
        },
        "options": {"degree_deg": 90.0},
    }
    svc = Service(cfg, elbow)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0, headers=AUTH) as client:
        assert client.post("/api/v1/recipes", json=body).status_code == 201
        r = client.post("/api/v1/measurements", json={"recipe": "ELBOW-219", "part_id": "E1"})
        assert r.status_code == 202, r.text
        dec = wait_done(client, r.json()["id"])["result"]["decision"]
    # D is decided with U = 2 sigma_D; the bend angle is not estimated by the fit: the part cannot be decided
    # (tests/service/test_recipe_elbows.py decides A and the angle)
    outcomes = [(c["characteristic"], c["outcome"]) for c in dec["characteristics"]]
    assert outcomes == [("diameter", "conforms"), ("bend_radius", "conforms"), ("bend_angle", "cannot_decide")]
    assert dec["value_m"] == 0.2190
    assert dec["expanded_m"] == pytest.approx(6e-4) and dec["lsl_m"] == pytest.approx(0.2171)
    assert dec["outcome"] == "cannot_decide"
