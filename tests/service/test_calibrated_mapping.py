"""Issue 12: the service maps a sweep with every term of the rig model in ``[kinematics]``.

The simulated rig casts its beams through its *true* geometry (``[sim] rig_errors``); the
service measures seed 003's 137.5 mm cylinder over HTTP, once mapping with the nominal Eq. 1
(``[kinematics]`` without the errors) and once with the true parameters given as ``[kinematics]``
(as a stored calibration will give them). Low range noise (0.5 mm) and a short sweep (-6..20 deg
at 20 deg/s, about 400 beams on the part) keep the test quick and the biases clear of the noise
(the fit's std is about 0.09 mm).

The expected bias of a range offset, from the geometry: a beam reporting ``l = L - k0`` puts its
point ``k0`` closer to the scanner along the line of sight. On the visible half of a circle of
radius ``r`` seen from ``R`` (beams uniform in scan angle, so weight ``cos theta`` at the angle
``theta`` from the front), the shift normal to the surface is ``k0 cos(incidence)``, with
``incidence = theta + (r / R) sin theta``: ``k0 cos theta`` is a shift of the centre, the rest
``-k0 (r / R) sin^2 theta``. Fitting ``a + b cos theta`` to ``sin^2 theta`` with that weight on
[-90, 90] deg gives ``a = 1.365``: the radius changes by ``-1.365 k0 r / R``, the diameter by
``-2.73 k0 r / R`` = -1.11 mm for k0 = 15 mm, r = 68.75 mm, R = 2.54 m (issue 12's simulation:
1.0 mm in size).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service.api import ServerThread, create_app
from service.config import parse_config, parse_toml
from service.rig import build_service
from tests.conftest import REPO

TRUTH_D = 0.1375
TOKEN = "cal-map-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SHORT = {"target": "cylinder", "sweep": {"speed_deg_s": 20.0, "start_deg": -6.0, "stop_deg": 20.0}}
#: distance from the optical centre (0.1, 0, 0) to the part's axis (0.28, 2.53) in the seed003 scene
R_AXIS = math.hypot(0.28 - 0.1, 2.53)

#: every [kinematics] term of the rig model, at magnitudes within a machine shop's and SICK's tolerances
ALL_TERMS: dict[str, float] = {
    "p_m": 0.103,
    "range_offset_m": 0.015,
    "range_scale_ppm": 800.0,
    "q_m": -0.004,
    "tilt_x_deg": 0.2,
    "tilt_y_deg": -0.15,
    "alpha_zero_deg": 0.1,
    "beta_zero_deg": 0.25,
    "motor_scale_ppm": -700.0,
    "backlash_deg": 0.08,
    "time_offset_s": 0.004,
}


def _measure(tmp_path: Path, kinematics: dict[str, float], rig_errors: dict[str, float]) -> dict[str, Any]:
    """One cylinder measurement on the in-process simulated rig with the true errors ``rig_errors``,
    mapped with ``[kinematics]`` = the default table updated by ``kinematics``."""
    cfg = parse_toml((REPO / "service" / "default_rig.toml").read_text(), base_dir=tmp_path)
    data = cfg.model_dump(mode="json")
    data["sim"].update(process=False, rig_errors=rig_errors)
    data["kinematics"].update(kinematics)
    data["noise"]["sigma_l_m"] = 0.0005
    cfg = parse_config({**data, "auth": {"token": TOKEN, "read": "open"}}, base_dir=tmp_path)
    svc, rig = build_service(cfg)
    try:
        with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=30) as client:
            req = {**SHORT, "options": {"seed": 0}}
            mid = client.post("/api/v1/measurements", json=req, headers=AUTH).json()["id"]
            end = time.monotonic() + 90
            while time.monotonic() < end:
                body: dict[str, Any] = client.get(f"/api/v1/measurements/{mid}").json()
                if body["state"] in ("done", "failed"):
                    break
                time.sleep(0.05)
    finally:
        svc.stop()
        rig.close()
    assert body["state"] == "done", (body["error"], body["message"])
    result: dict[str, Any] = body["result"]
    return result


def _axis_tilt_deg(result: dict[str, Any]) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(result["axis_direction"][2])))))


def test_a_range_offset_biases_the_nominal_mapping_as_the_geometry_says_and_kinematics_removes_it(
    tmp_path: Path,
) -> None:
    errors = {"range_offset_m": 0.015}
    nominal = _measure(tmp_path / "nominal", {}, errors)
    calibrated = _measure(tmp_path / "calibrated", errors, errors)
    expected = -2.73 * 0.015 * (TRUTH_D / 2) / R_AXIS  # -1.11 mm (module docstring)
    bias = nominal["diameter_m"] - TRUTH_D
    # the model to 10 %, plus the noise of the short sweep (the fit's std, ~0.09 mm)
    assert abs(bias - expected) < 0.1 * abs(expected) + 4 * nominal["uncertainty"]["std_m"], (bias, expected)
    std = calibrated["uncertainty"]["std_m"]
    assert std < 0.2e-3  # the test's premise: the noise is well below the bias
    assert abs(calibrated["diameter_m"] - TRUTH_D) < 3 * std, calibrated


def test_every_term_of_the_rig_model_is_applied_to_the_sweep_and_the_fit(tmp_path: Path) -> None:
    """All eleven terms at once (backlash and time offset act through the motor speed): the nominal
    mapping misses the diameter by about 2 mm and tilts the axis by more than 1 deg; with the
    true rig as ``[kinematics]`` both are gone to within the noise."""
    nominal = _measure(tmp_path / "nominal", {}, ALL_TERMS)
    calibrated = _measure(tmp_path / "calibrated", ALL_TERMS, ALL_TERMS)
    assert abs(nominal["diameter_m"] - TRUTH_D) > 1.0e-3, nominal
    assert _axis_tilt_deg(nominal) > 0.5, nominal["axis_direction"]
    std = calibrated["uncertainty"]["std_m"]
    assert abs(calibrated["diameter_m"] - TRUTH_D) < 3 * std, calibrated
    # the axis of a 0.84 m tall part from ~400 points with 0.5 mm noise: std ~0.02 deg; 0.03 deg seen on an
    # idle machine, 0.13 deg once at load 4-5 with the SYNC time's smear; still 0.12 and 0.07 deg at load 7-8 with
    # the drive's latch time (docs/service.md known limits), so the bound stays;
    # uncalibrated: 1.3 deg
    print(f"calibrated: axis tilt {_axis_tilt_deg(calibrated):.3f} deg ({calibrated['sweep']['motor_time_source']})")
    assert _axis_tilt_deg(calibrated) < 0.3, calibrated["axis_direction"]
