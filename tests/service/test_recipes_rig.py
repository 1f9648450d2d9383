"""Parts of recipes measured on the simulated rig (seed 003's 137.5 mm cylinder) over HTTP: a
tolerance the part meets, one it misses, and one placed so that U straddles its lower limit."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from service.api import ServerThread, create_app
from service.config import parse_config, parse_toml
from service.rig import build_service
from tests.conftest import REPO
from tests.service.test_recipes import wait_done

TOKEN = "rig-recipes"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture
def sim_client(tmp_path: Any) -> Iterator[httpx.Client]:
    cfg = parse_toml((REPO / "service" / "default_rig.toml").read_text(), base_dir=tmp_path)
    data = cfg.model_dump(mode="json")  # the simulated devices in a process of their own, as `lrms serve` runs them
    cfg = parse_config({**data, "auth": {"admin_token": TOKEN, "read": "open"}}, base_dir=tmp_path)
    svc, rig = build_service(cfg)  # the rig in its own process, as `lrms serve` runs it
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30, headers=AUTH) as client:
            yield client
    finally:
        svc.stop()
        rig.close()


def _recipe(client: httpx.Client, name: str, nominal: float, lower: float | None, upper: float | None) -> None:
    tol = {"nominal_m": nominal, "lower_m": lower, "upper_m": upper}
    body = {
        "name": name,
        "target": "cylinder",
        "tolerances": {"diameter": {k: v for k, v in tol.items() if v is not None}},
        "material": "aluminium_alloy",
        "sweep": {"mode": "step", "step_deg": 3.0, "speed_deg_s": 30.0},
    }
    r = client.post("/api/v1/recipes", json=body)
    assert r.status_code == 201, r.text


def _part(client: httpx.Client, name: str, part_id: str, **extra: Any) -> dict[str, Any]:
    r = client.post("/api/v1/measurements", json={"recipe": name, "part_id": part_id, "operator": "sim", **extra})
    assert r.status_code == 202, r.text
    result: dict[str, Any] = wait_done(client, r.json()["id"], timeout=120)["result"]
    return result


def test_recipe_parts_on_the_simulated_rig_reach_each_decision(sim_client: httpx.Client) -> None:
    client = sim_client
    # meets: 137.5 +-10 mm (U is about 2.3 mm: the uncalibrated scanner's range offset and angular zero dominate;
    # step-and-scan, so no motor timing row and a repeatable diameter)
    _recipe(client, "SHAFT-OK", 0.1375, -0.010, 0.010)
    ok = _part(client, "SHAFT-OK", "A1")
    d, dec = ok["diameter_m"], ok["decision"]
    big_u = dec["expanded_m"]
    assert dec["outcome"] == "conforms" and dec["rule"] == "iso14253-1" and ok["thermal"] is None
    assert dec["value_m"] == d and abs(d - 0.1375) <= big_u
    assert big_u == pytest.approx(ok["uncertainty"]["expanded_m"], rel=1e-12) and dec["k"] == 2.0
    assert ok["part"] == {"recipe": "SHAFT-OK", "recipe_version": 1, "part_id": "A1", "operator": "sim"}
    # misses: 150 +-0.5 mm
    _recipe(client, "SHAFT-150", 0.150, -0.0005, 0.0005)
    miss = _part(client, "SHAFT-150", "B1")
    assert miss["decision"]["outcome"] == "does_not_conform"
    # U straddles the lower limit: LSL half a U below the measured value
    _recipe(client, "SHAFT-EDGE", round(d - big_u / 2, 6), 0.0, 0.020)
    edge = _part(client, "SHAFT-EDGE", "C1", part_temperature_c=20.0, temperature_uncertainty_c=1.0)
    assert abs(edge["diameter_m"] - d) < big_u / 2  # step-and-scan repeats within 0.3 mm here
    e = edge["decision"]
    assert e["outcome"] == "cannot_decide" and e["lsl_m"] < e["value_m"] < e["acceptance_zone_m"][0]
    # a part at 20 °C: D20 = D_T, the thermal rows are the temperature's (u = D alpha(20) u_T) and the data's (0)
    th = edge["thermal"]
    assert th["diameter_20c_m"] == th["diameter_measured_m"] == edge["diameter_m"]
    assert th["budget"][0]["source"] == "part temperature" and th["budget"][0]["u_m"] > 0
    assert th["budget"][1]["u_m"] == pytest.approx(0.0, abs=1e-15)
    hist = client.get("/api/v1/recipes/SHAFT-EDGE/history").json()
    assert [(h["part_id"], h["outcome"]) for h in hist] == [("C1", "cannot_decide")]
