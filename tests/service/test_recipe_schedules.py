"""Schedules that measure parts of a recipe, over HTTP: the part id pattern filled in per run, the
recipe's latest version when a run fires (or a pinned one), a retired recipe's runs skipped, and
the refusals of a bad template. The scheduler is ticked with chosen times (``Scheduler.tick``);
the measurement is scripted (``test_recipes.Scripted``)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.api import ServerThread, Service, create_app
from service.config import TOKEN_ENV, parse_toml
from service.schedulemodels import render_part_id
from tests.service.test_recipes import AUTH, TOKEN, Scripted, loc_of, recipe, wait_done

HOUR = 3600.0


@pytest.fixture
def served(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[httpx.Client, Scripted, Service]]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = parse_toml(f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\n[auth]\nread = 'open'\nadmin_token = '{TOKEN}'\n")
    measure = Scripted()
    svc = Service(cfg, measure)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0, headers=AUTH) as client:
        yield client, measure, svc


def _fire(client: httpx.Client, svc: Service, sid: str, when: float) -> str | None:
    """Tick the scheduler at ``when`` (the schedule due by then) and return what it queued."""
    due = client.get(f"/api/v1/schedules/{sid}").json()["next_run"]
    assert due <= when
    svc.scheduler.tick(now=when)
    mid: str | None = client.get(f"/api/v1/schedules/{sid}").json()["last_measurement_id"]
    return mid


def test_a_schedule_measures_parts_of_a_recipe_with_a_part_id_pattern(
    served: tuple[httpx.Client, Scripted, Service],
) -> None:
    client, measure, svc = served
    assert client.post("/api/v1/recipes", json=recipe()).status_code == 201
    body = {
        "name": "hourly sample",
        "interval_s": HOUR,
        "measurement": {"recipe": "FLANGE-SHAFT-320", "part_id": "{date}-{n:03d}", "operator": "schedule"},
    }
    r = client.post("/api/v1/schedules", json=body)
    assert r.status_code == 201, r.text
    s = r.json()
    # the template is what was given: the recipe supplies target, sweep, roi and options at each run
    assert s["measurement"] == body["measurement"]
    sid = s["id"]

    t1 = s["next_run"] + 1.0
    measure.values.append(0.3201)
    m1 = _fire(client, svc, sid, t1)
    assert m1 is not None
    done = wait_done(client, m1)
    date1 = dt.datetime.fromtimestamp(t1, dt.UTC).strftime("%Y%m%d")
    assert done["result"]["part"] == {
        "recipe": "FLANGE-SHAFT-320",
        "recipe_version": 1,
        "part_id": f"{date1}-001",
        "operator": "schedule",
    }
    assert done["result"]["decision"]["outcome"] == "conforms"
    assert done["schedule_id"] == sid and done["request"]["sweep"]["speed_deg_s"] == 20.0  # the recipe's sweep

    # a new version: the next run measures with it (the schedule follows the recipe)
    v2 = recipe(tolerances={"diameter": {"nominal_m": 0.320, "lower_m": -0.0002, "upper_m": 0.0002}})
    assert client.put("/api/v1/recipes/FLANGE-SHAFT-320", json=v2).json()["version"] == 2
    t2 = t1 + HOUR + 1.0
    measure.values.append(0.3210)  # beyond USL 320.2 mm + U 0.4 mm
    m2 = _fire(client, svc, sid, t2)
    assert m2 is not None and m2 != m1
    res2 = wait_done(client, m2)["result"]
    date2 = dt.datetime.fromtimestamp(t2, dt.UTC).strftime("%Y%m%d")
    assert (res2["part"]["part_id"], res2["part"]["recipe_version"]) == (f"{date2}-002", 2)
    assert res2["decision"]["outcome"] == "does_not_conform"
    hist = client.get("/api/v1/recipes/FLANGE-SHAFT-320/history").json()
    assert [(h["measurement_id"], h["part_id"], h["outcome"]) for h in hist] == [
        (m1, f"{date1}-001", "conforms"),
        (m2, f"{date2}-002", "does_not_conform"),
    ]

    # retired: the run is skipped (nothing queued), the schedule moves on
    assert client.delete("/api/v1/recipes/FLANGE-SHAFT-320").status_code == 200
    skipped = svc.scheduler.skipped
    t3 = t2 + HOUR + 1.0
    assert _fire(client, svc, sid, t3) is None
    assert svc.scheduler.skipped == skipped + 1
    after = client.get(f"/api/v1/schedules/{sid}").json()
    assert after["last_run"] == t3 and after["next_run"] == t3 + HOUR
    assert len(client.get("/api/v1/recipes/FLANGE-SHAFT-320/history").json()) == 2
    assert 'lrms_schedule_runs_skipped_total{reason="refused"} 1.0' in client.get("/metrics").text


def test_a_schedule_can_pin_a_recipe_version(served: tuple[httpx.Client, Scripted, Service]) -> None:
    client, measure, svc = served
    assert client.post("/api/v1/recipes", json=recipe()).status_code == 201
    assert client.put("/api/v1/recipes/FLANGE-SHAFT-320", json=recipe(material="stainless_austenitic")).is_success
    m = {"recipe": "FLANGE-SHAFT-320", "recipe_version": 1, "part_id": "LOT7-{time}"}
    s = client.post("/api/v1/schedules", json={"interval_s": HOUR, "measurement": m}).json()
    when = s["next_run"] + 1.0
    measure.values.append(0.3200)
    mid = _fire(client, svc, s["id"], when)
    assert mid is not None
    part = wait_done(client, mid)["result"]["part"]
    stamp = dt.datetime.fromtimestamp(when, dt.UTC).strftime("%H%M%S")
    assert part["recipe_version"] == 1 and part["part_id"] == f"LOT7-{stamp}"


def test_a_bad_recipe_schedule_is_refused_and_nothing_stored(served: tuple[httpx.Client, Scripted, Service]) -> None:
    client, _, _ = served
    assert client.post("/api/v1/recipes", json=recipe()).status_code == 201

    def post(measurement: dict[str, Any]) -> httpx.Response:
        return client.post("/api/v1/schedules", json={"interval_s": HOUR, "measurement": measurement})

    part = {"recipe": "FLANGE-SHAFT-320"}
    r = post({**part, "part_id": "{lot}-{n}"})
    assert loc_of(r) == [["body", "measurement", "part_id"]] and "unknown placeholder {lot}" in r.json()["message"]
    assert loc_of(post({**part, "part_id": "{n:.<3}"})) == [["body", "measurement", "part_id"]]  # '..1': no part id
    assert loc_of(post({**part, "part_id": "{date!r}"})) == [["body", "measurement", "part_id"]]
    assert loc_of(post(part)) == [["body", "measurement"]]  # a part needs its id
    r = post({"recipe": "NOPE", "part_id": "{n}"})
    assert loc_of(r) == [["body", "measurement", "recipe"]] and "no recipe 'NOPE'" in r.json()["message"]
    r = post({**part, "part_id": "{n}", "recipe_version": 9})
    assert loc_of(r) == [["body", "measurement", "recipe_version"]]
    r = post({**part, "part_id": "{n}", "sweep": {"speed_deg_s": 10.0}})
    assert loc_of(r) == [["body", "measurement", "sweep"]] and "comes from recipe" in r.json()["message"]
    assert client.get("/api/v1/schedules").json() == []


def test_part_id_patterns() -> None:
    t = dt.datetime(2026, 3, 9, 7, 5, 2, tzinfo=dt.UTC).timestamp()
    assert render_part_id("{date}-{n}", t, 12) == "20260309-12"
    assert render_part_id("P{n:05d}/{date}T{time}", t, 3) == "P00003/20260309T070502"
    assert render_part_id("FIXED-1", t, 99) == "FIXED-1"
    for bad in ("{}", "{0}", "{n.real}", "{n:q}", "{date", "{n:>200}"):
        with pytest.raises(ValueError, match="part id pattern"):
            render_part_id(bad, t, 1)
