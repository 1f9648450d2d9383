"""Rig calibration under the LMS1xx beam footprint (issue 12): with the nominal optics given, the
adjustment censors the beams whose spot is not wholly on their surface, corrects the sphere beams'
expected range for the spot's curvature average, and estimates the spot scale with the calibrated
rig; on a simulated room with spheres swept by a miscalibrated rig with the footprint sensor, k0
and the scan-plane tilt come out within 3 of their reported standard deviations and the spot scale
within 2 of its u."""

from __future__ import annotations

import numpy as np
import pytest

from lrms.calibration import AdjustOptions, Artefact, CalibrationOptions, CalibrationResult, Observations, calibrate
from lrms.calibration.adjust import sphere_spot_bias
from lrms.calibration.optics import limb_echo
from lrms.cylinder import BeamOptics
from lrms.kinematics import RigCalibration, RigModel
from sim.scene import LMS1xxSensor, continuous_sweep_cloud, get_scene
from sim.scene.library import ROOM_SPHERES, ROOM_SPHERES_LARGE_FACTOR, room_spheres_artefact
from sim.scene.lms1xx import Footprint

D = np.deg2rad
TRUTH = RigModel(k0=0.021, k1=-4e-4, p=0.103, q=-0.002, tilt_x=D(0.2), alpha_zero=D(-0.15), beta_scale=3e-4)


@pytest.fixture(scope="module")
def footprint_calibration() -> CalibrationResult:
    """A two-face sweep (-170..170 deg at 80 deg/s: ~115,000 beams) of ``room-spheres-large`` with
    the LMS1xx footprint (32 sub-rays, energy-weighted echoes), the sphere network's distances known."""
    cal = RigCalibration(model=TRUTH)
    sensor = LMS1xxSensor(footprint=Footprint(sub_rays=32))
    _, s = continuous_sweep_cloud(
        get_scene("room-spheres-large"), cal, sensor, -D(170), D(170), D(80), rng=np.random.default_rng(3)
    )
    v = s.valid
    obs = Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))
    art = room_spheres_artefact(ROOM_SPHERES_LARGE_FACTOR)
    c = [np.asarray(x, dtype=np.float64) for x, _ in ROOM_SPHERES]
    art["distances_m"] = [
        {"a": i, "b": j, "distance_m": float(np.linalg.norm(c[j] - c[i])), "u_distance_m": 3e-5}
        for i in range(len(c))
        for j in range(i + 1, len(c))
    ]
    opts = CalibrationOptions(adjust=AdjustOptions(max_plane_points=2000), optics=BeamOptics())
    return calibrate([obs], Artefact.from_dict(art), options=opts)


def test_k0_tilt_and_spot_scale_are_recovered_under_the_footprint(footprint_calibration: CalibrationResult) -> None:
    res = footprint_calibration
    truth = TRUTH.canonical()
    std = dict(zip(RigModel.NAMES, np.sqrt(np.diag(res.covariance)), strict=True))
    for name in ("k0", "tilt_x"):
        assert name in res.estimated
        err = getattr(res.model, name) - getattr(truth, name)
        assert abs(err) <= 3 * std[name], (name, err, std[name])
    assert res.optics is not None
    s, u = res.optics["spot_scale"], res.optics["spot_scale_u"]
    assert 0.0 < u < 0.1
    assert abs(s - 1.0) <= 2 * u, (s, u)


def test_the_censored_beams_are_counted_per_artefact(footprint_calibration: CalibrationResult) -> None:
    res = footprint_calibration
    assert res.censored is not None
    spheres = [k for k in res.censored if k.startswith("sphere")]
    planes = [k for k in res.censored if k.startswith("plane")]
    assert spheres and planes
    assert sum(res.censored[k] for k in spheres) > 0 and sum(res.censored[k] for k in planes) > 0
    back = CalibrationResult.from_json(res.to_json())
    assert back.censored == res.censored


def test_the_sphere_spot_bias_matches_the_quadrature_of_the_echo() -> None:
    """The second-order closed form against the numerical energy-weighted echo (``limb_echo``, which
    the adjustment uses) for spots wholly on the sphere, the axis up to half the radius off centre
    (further out, toward R - 3 sigma, the higher orders grow: there only the quadrature is used)."""
    r, t, sig = 0.2, 3.0, 0.013
    x0 = np.linspace(0.0, r / 2, 9)
    depth = np.sqrt(r * r - x0 * x0)
    thin = t - depth
    echo, share = limb_echo(x0, np.full(x0.size, t), np.full(x0.size, r), np.full(x0.size, sig))
    assert np.all(share > 0.998)
    bias = sphere_spot_bias(depth, r, np.full(x0.size, sig), np.full(x0.size, t))
    assert bias[0] == pytest.approx(sig**2 / r, rel=1e-12)
    np.testing.assert_allclose(echo - thin, bias, atol=0.02e-3)  # the shift itself is ~0.8 mm: within 2.5 %
    assert np.max(np.abs(echo - thin)) > 0.5e-3
