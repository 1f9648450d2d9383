"""Request bounds and the one 422 format, over real HTTP (uvicorn on 127.0.0.1), plus the rig
limits below the API: the planned duration, the sweep's own guard and the driver's.

The cases are the ones an outside fuzzer and a hand test found answered with 500 or accepted:
non-finite numbers, an offset beyond SQLite's integers, cron strings that never fire or fire every
second, a 1 MB cron string, sub-normal steps and speeds, and a sweep whose run-up drives the shaft
to -900.5 deg at a speed the drive refuses.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi import FastAPI, HTTPException

from drivers.servo.interface import TargetOutOfRange
from drivers.url import open_device
from service.api import ServerThread, Service, create_app
from service.api.errors import ValidationErrorBody, install_handlers
from service.config import TOKEN_ENV, parse_toml
from service.errors import ConfigError
from service.jobs import JobContext
from service.models import (
    ResolvedSweep,
    SweepSpec,
    planned_duration_s,
    resolve_sweep,
    run_up_deg,
    travel_deg,
)
from service.rig import motion_limits, plan_from
from service.sweep import SweepRecorder, TravelLimitError, run_sweep

TOKEN = "t0ken"
AUTH = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}


def _measure(ctx: JobContext) -> dict[str, Any]:
    raise AssertionError("no measurement may run in these tests")


def _config(tmp_path: Path, extra: str = "") -> Any:
    return parse_toml(
        f"[sim]\n[storage]\ndir = '{tmp_path / 'data'}'\n[auth]\nadmin_token = '{TOKEN}'\nread = 'open'\n{extra}"
    )


@pytest.fixture
def client(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[httpx.Client]:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    svc = Service(_config(tmp_path, "[schedules]\nmin_interval_s = 300\n"), _measure)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as c:
        yield c
        assert c.get("/api/v1/measurements").json() == []  # nothing refused was queued


def _refused(r: httpx.Response) -> ValidationErrorBody:
    """A 422 in the one documented format: exactly ``message`` and ``detail`` items of exactly
    ``loc``, ``msg`` and ``type``, as strict JSON (no NaN)."""
    assert r.status_code == 422, r.text
    raw = r.json()
    assert set(raw) == {"message", "detail"}
    assert raw["detail"] and all(set(item) == {"loc", "msg", "type"} for item in raw["detail"])
    return ValidationErrorBody.model_validate(raw)


def _locs(body: ValidationErrorBody) -> set[str]:
    return {".".join(str(x) for x in item.loc) for item in body.detail}


@pytest.mark.parametrize(
    ("raw", "loc"),
    [
        ('{"target": "cylinder", "sweep": {"speed_deg_s": NaN}}', "body.sweep.speed_deg_s"),
        ('{"target": "cylinder", "sweep": {"start_deg": Infinity}}', "body.sweep.start_deg"),
        ('{"target": "cylinder", "sweep": {"stop_deg": -Infinity}}', "body.sweep.stop_deg"),
        ('{"target": "cylinder", "sweep": {"step_deg": 1e999}}', "body.sweep.step_deg"),
        ('{"target": "cylinder", "options": {"k": NaN}}', "body.options.k"),
        ('{"target": "cylinder", "options": {"k": 1e999}}', "body.options.k"),
        ('{"target": "cylinder", "roi": {"min_m": [0, NaN, 0], "max_m": [1, 1, 1]}}', "body.roi.min_m.1"),
        ('{"target": "cylinder", "sweep": {"scans_per_step": 1e999}}', "body.sweep.scans_per_step"),
    ],
)
def test_non_finite_numbers_are_422_naming_the_field(client: httpx.Client, raw: str, loc: str) -> None:
    body = _refused(client.post("/api/v1/measurements", content=raw, headers=AUTH))
    assert loc in _locs(body), body


@pytest.mark.parametrize(
    ("sweep", "loc", "needle"),
    [
        ({"step_deg": 5e-324, "mode": "step"}, "body.sweep.step_deg", "greater than or equal to 0.01"),
        ({"speed_deg_s": 5e-324}, "body.sweep.speed_deg_s", "greater than or equal to 0.1"),
        ({"speed_deg_s": 0.001}, "body.sweep.speed_deg_s", "greater than or equal to 0.1"),
        # 90 deg at 0.1 deg/s: 913 s planned, beyond the default [sweep] max_duration_s = 600 s
        ({"speed_deg_s": 0.1}, "body.sweep.speed_deg_s", "more than [sweep] max_duration_s = 600 s"),
        ({"mode": "step", "step_deg": 0.01}, "body.sweep.step_deg", "more than [sweep] max_duration_s"),
        ({"mode": "step", "start_deg": 0, "stop_deg": 5, "step_deg": 10}, "body.sweep.step_deg", "wider than"),
        ({"start_deg": 10, "stop_deg": 10}, "body.sweep.stop_deg", "must differ"),
        # within the +-180 deg of a request, but the 20.5 deg run-up at 60 deg/s is beyond the travel
        ({"start_deg": -170, "stop_deg": 0, "speed_deg_s": 60}, "body.sweep.start_deg", "-190.5 deg"),
        ({"start_deg": 170, "stop_deg": 0, "speed_deg_s": 60}, "body.sweep.start_deg", "above the motor's travel"),
    ],
)
def test_sweeps_beyond_the_rig_are_422_naming_the_field(
    client: httpx.Client, sweep: dict[str, Any], loc: str, needle: str
) -> None:
    body = _refused(client.post("/api/v1/measurements", json={"target": "cylinder", "sweep": sweep}, headers=AUTH))
    assert loc in _locs(body) and needle in body.message, body.message


def test_the_full_turn_at_360_deg_s_is_refused_for_speed_and_travel(client: httpx.Client) -> None:
    """The case that drove the shaft to -900.5 deg and then failed on the drive's maximum speed."""
    sweep = {"start_deg": -180, "stop_deg": 180, "speed_deg_s": 360}
    body = _refused(client.post("/api/v1/measurements", json={"target": "cylinder", "sweep": sweep}, headers=AUTH))
    assert _locs(body) == {"body.sweep.speed_deg_s", "body.sweep.start_deg", "body.sweep.stop_deg"}
    assert "exceeds the motor's maximum speed 90 deg/s" in body.message
    assert "-900.5 deg" in body.message and "900.5 deg" in body.message
    # the same request inside a schedule is refused there, under body.measurement
    r = client.post(
        "/api/v1/schedules",
        json={"interval_s": 3600, "measurement": {"target": "cylinder", "sweep": sweep}},
        headers=AUTH,
    )
    assert "body.measurement.sweep.speed_deg_s" in _locs(_refused(r))


def test_offsets_page_sizes_and_ids_are_bounded(client: httpx.Client) -> None:
    for params, loc in [
        ({"offset": "9223372036854775808"}, "query.offset"),
        ({"offset": "-1"}, "query.offset"),
        ({"limit": "0"}, "query.limit"),
        ({"limit": "1001"}, "query.limit"),
        ({"state": "sleeping"}, "query.state"),
    ]:
        assert loc in _locs(_refused(client.get("/api/v1/measurements", params=params)))
    assert client.get("/api/v1/measurements", params={"offset": 1_000_000_000, "limit": 1000}).json() == []
    assert "path.mid" in _locs(_refused(client.get("/api/v1/measurements/" + "a" * 65)))
    assert client.get("/api/v1/measurements/" + "a" * 64).status_code == 404


@pytest.mark.parametrize(
    ("schedule", "loc", "needle"),
    [
        ({"cron": "0 0 30 2 *"}, "body.cron", "never fires"),
        ({"cron": "0 0 31 4 *"}, "body.cron", "never fires"),
        ({"cron": "* * * * * *"}, "body.cron", "exactly 5 fields"),
        ({"cron": "* * * * * * *"}, "body.cron", "exactly 5 fields"),
        ({"cron": "@hourly"}, "body.cron", "at least 9 characters"),
        ({"cron": "61 * * * *"}, "body.cron", "not a valid cron"),
        ({"cron": "* " * 500_000 + "*"}, "body.cron", "at most 120 characters"),
        # [schedules] min_interval_s = 300 in this fixture
        ({"cron": "*/2 * * * *"}, "body.cron", "fires 120 s apart"),
        ({"cron": "0,1 3 * * *"}, "body.cron", "fires 60 s apart"),
        ({"interval_s": 60}, "body.interval_s", "shorter than [schedules] min_interval_s = 300 s"),
        ({"interval_s": math.inf}, "body.interval_s", "finite"),
    ],
)
def test_bad_cron_and_intervals_are_422(client: httpx.Client, schedule: dict[str, Any], loc: str, needle: str) -> None:
    raw = json.dumps({**schedule, "measurement": {"target": "cylinder"}})  # inf is written as Infinity
    refused = _refused(client.post("/api/v1/schedules", content=raw, headers=AUTH))
    assert loc in _locs(refused) and needle in refused.message, refused.message
    assert client.get("/api/v1/schedules").json() == []


def test_schedules_at_the_minimum_interval_are_accepted(client: httpx.Client) -> None:
    for trigger in ({"cron": "*/5 * * * *"}, {"cron": "0 0 29 2 *"}, {"interval_s": 300}):
        r = client.post("/api/v1/schedules", json={**trigger, "measurement": {"target": "cylinder"}}, headers=AUTH)
        assert r.status_code == 201, r.text
        assert client.delete(f"/api/v1/schedules/{r.json()['id']}", headers=AUTH).status_code == 204


def test_an_http_exception_422_has_the_same_format(tmp_path: Path) -> None:
    """A route raising HTTPException(422) (none of ours does any more) still answers the one format."""
    app = FastAPI()
    install_handlers(app)

    @app.get("/boom")
    def boom() -> None:
        raise HTTPException(422, "refused by hand")

    with ServerThread(app) as srv, httpx.Client(base_url=srv.url) as c:
        body = _refused(c.get("/boom"))
        assert body.message == "refused by hand" and body.detail[0].loc == []


def test_405_names_every_method_of_the_path(client: httpx.Client) -> None:
    # with a token: without one, a method with a body is refused (401) before the router sees it
    for method, path, allow in [
        ("PUT", "/api/v1/measurements", "GET, POST"),
        ("DELETE", "/api/v1/measurements/abc", "GET"),
        ("POST", "/api/v1/schedules/abc", "DELETE, GET"),
        ("PATCH", "/api/v1/schedules", "GET, POST"),
    ]:
        r = client.request(method, path, headers=AUTH)
        assert r.status_code == 405 and r.headers["allow"] == allow and r.json() == {"detail": "Method Not Allowed"}


# -- below the API -----------------------------------------------------------------------------


def _sweep(**kw: Any) -> ResolvedSweep:
    base: dict[str, Any] = {
        "start_deg": -20.0,
        "stop_deg": 70.0,
        "speed_deg_s": 10.0,
        "mode": "constant",
        "step_deg": 1.0,
        "scans_per_step": 1,
        "acceleration_deg_s2": 90.0,
    }
    return ResolvedSweep(**{**base, **kw})


def test_planned_duration_counts_approach_sweep_ramps_and_dwell() -> None:
    s = _sweep()
    travel = 90.0 + 2 * run_up_deg(10.0, 90.0)  # 92.11 deg
    # approach at 30 deg/s and sweep at 10 deg/s, each with a ramp of v/a
    assert planned_duration_s(s) == pytest.approx(travel / 30 + 30 / 90 + travel / 10 + 10 / 90)
    # a short move is a triangle: 2 sqrt(d / a)
    step = _sweep(mode="step", start_deg=0.0, stop_deg=1.0, step_deg=0.5, speed_deg_s=20.0, scans_per_step=3)
    dwell = 0.05 + 4 / 25
    expected = 2 * math.sqrt(1.0 / 90) + 2 * 2 * math.sqrt(0.5 / 90) + 3 * dwell
    assert planned_duration_s(step) == pytest.approx(expected)
    assert planned_duration_s(s, approach_speed_deg_s=10.0) > planned_duration_s(s)


@pytest.mark.parametrize(
    "sweep",
    [_sweep(), _sweep(start_deg=70.0, stop_deg=-20.0, speed_deg_s=45.0), _sweep(mode="step", step_deg=7.0)],
)
def test_the_request_check_and_the_sweep_plan_agree_on_the_travel(sweep: ResolvedSweep) -> None:
    """The request is checked with the travel the plan moves over: exactly (constant speed: the
    run-up on both sides), or the whole window (step mode, whose last step may fall short of it)."""
    betas = [math.degrees(b) for b, _ in plan_from(sweep).targets()]
    lo, hi = travel_deg(sweep)
    assert min(betas) == pytest.approx(lo)
    if sweep.mode == "constant":
        assert max(betas) == pytest.approx(hi)
    else:
        assert hi - sweep.step_deg < max(betas) <= hi


def test_the_config_sets_the_limits_and_its_defaults_must_fit(tmp_path: Path) -> None:
    cfg = _config(tmp_path, "[motor]\nmin_angle_deg = -30\nmax_angle_deg = 80\nmax_velocity_deg_s = 20\n")
    assert resolve_sweep(SweepSpec(), cfg).start_deg == -20.0  # the defaults fit: -21.1 .. 71.1 deg
    with pytest.raises(ValueError, match="exceeds the motor's maximum speed 20"):
        resolve_sweep(SweepSpec(speed_deg_s=30.0), cfg)
    # the limits are shaft angles: with the motor's zero at 15 deg, beta 71.06 deg is 86.06 deg, and
    # a config whose own default sweep does not fit is refused when it is loaded
    with pytest.raises(ConfigError, match=r"\[sweep\] defaults: sweep\.stop_deg: the sweep needs the shaft at 86\.05"):
        _config(tmp_path, "[motor]\nmin_angle_deg = -30\nmax_angle_deg = 80\n[kinematics]\nmotor_zero_deg = 15\n")
    for extra, needle in [
        ("[motor]\nmin_angle_deg = 0\n", r"\[sweep\] defaults: sweep\.start_deg"),
        ("[motor]\nmin_angle_deg = 10\nmax_angle_deg = 10\n", "must be below max_angle_deg"),
        ("[sweep]\nacceleration_deg_s2 = 1000\n", "exceeds the motor's maximum 720"),
        ("[sweep]\nspeed_deg_s = 0.1\n", "max_duration_s"),
        ("[sweep]\nmax_duration_s = 0\n", "sweep.max_duration_s"),
        ("[fit]\nroi_min_m = [0, nan, 0]\n", "finite"),
        ("[schedules]\nmin_interval_s = 0.5\n", "schedules.min_interval_s"),
    ]:
        with pytest.raises(ConfigError, match=needle):
            _config(tmp_path, extra)


def test_the_sweep_refuses_a_plan_beyond_the_limits_before_any_device_is_touched(tmp_path: Path) -> None:
    """Defence in depth: a plan that got past the request check (a changed config, a replayed
    template) stops in run_sweep before the scanner or the motor is used (both are None here)."""
    cfg = _config(tmp_path)
    bad = _sweep(start_deg=-180.0, stop_deg=180.0, speed_deg_s=60.0)
    with pytest.raises(TravelLimitError, match=r"refusing to move the shaft to -200\.500 deg"):
        run_sweep(
            None,
            None,
            SweepRecorder(cfg.calibration),
            plan_from(bad),
            clock_ns=lambda t: 0,
            read_scan=lambda timeout: (None, 0.0, None),
            limits=motion_limits(cfg),
        )
    fast = _sweep(speed_deg_s=120.0, start_deg=-10.0, stop_deg=10.0)
    with pytest.raises(TravelLimitError, match="refusing to move at 120 deg/s"):
        motion_limits(cfg).check_plan(plan_from(fast), cfg.calibration)
    motion_limits(cfg).check_plan(plan_from(_sweep()), cfg.calibration)  # the default sweep passes


def test_the_driver_gets_the_motor_limits(tmp_path: Path) -> None:
    """The [motor] limits reach the CiA 402 driver (a simulated drive over a python-can virtual
    bus): it refuses targets and speeds beyond them before sending anything."""
    cfg = _config(tmp_path, "[motor]\nmin_angle_deg = -30\nmax_angle_deg = 80\nmax_velocity_deg_s = 45\n")
    motor = open_device("motor", "sim://", config=cfg.motor.drive_config())
    try:
        assert motor.config.min_angle_rad == pytest.approx(math.radians(-30.0))
        assert motor.config.max_velocity_rad_s == pytest.approx(math.radians(45.0))
        motor.enable()
        with pytest.raises(TargetOutOfRange, match="below the software limit"):
            motor.move_to(math.radians(-31.0))
        with pytest.raises(TargetOutOfRange, match="exceeds the configured maximum"):
            motor.move_to(math.radians(10.0), velocity=math.radians(50.0))
        motor.move_to(math.radians(2.0), velocity=math.radians(45.0), wait=True)
        assert math.degrees(motor.position_rad()) == pytest.approx(2.0, abs=0.05)
    finally:
        motor.close()
