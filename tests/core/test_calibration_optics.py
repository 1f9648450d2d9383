"""The spot size from reference spheres (issue 12, item 2): on a simulated LMS1xx with a spot of
known scale the estimator recovers it within its uncertainty from the spheres' limb beams; a
calibration with the LMS1xx optics stores it in its JSON and applies it to the footprint fit's
optics; without optics (the thin beam) there is none."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from lrms.calibration import CalibrationError, CalibrationOptions, CalibrationResult, calibrate
from lrms.calibration.optics import MIN_LIMB_BEAMS, estimate_spot_scale, fit_spot_scale, limb_echo
from lrms.calibration.result import ENDLESS_SCALE_U
from lrms.cylinder import BeamOptics
from lrms.kinematics import RigModel
from sim.scene import LMS1xxSensor, SensorModel
from sim.scene.lms1xx import Footprint
from sim.scene.spot_spheres import spheres_sweep, spheres_truth

TRUE_SCALE = 1.6


def lms1xx(scale: float) -> LMS1xxSensor:
    fp = Footprint(exit_diameter_m=0.008 * scale, divergence_rad=0.015 * scale, sub_rays=32)
    return LMS1xxSensor(footprint=fp)


@pytest.fixture(scope="module")
def scaled_spot() -> CalibrationResult:
    obs, art = spheres_sweep(lms1xx(TRUE_SCALE), step_deg=0.8)
    return calibrate([obs], art, options=CalibrationOptions(optics=BeamOptics()))


@pytest.mark.parametrize("scale", [TRUE_SCALE])
def test_the_spot_scale_is_recovered_from_the_spheres_within_its_uncertainty(scale: float) -> None:
    """The rig and the spheres' centres known (the calibration's job): the spot scale from the limb beams."""
    obs, _ = spheres_sweep(lms1xx(scale), seed=int(10 * scale))
    m = RigModel()
    o, d = m.rays(obs.alpha, obs.beta)
    got = estimate_spot_scale(
        o, d, m.geometric_range(obs.l), spheres_truth(), 0.008, 0.015, 0.25, 0.012,
        extent=1.5,
    )  # fmt: skip
    assert got is not None and got.beams > 500
    assert 0.0 < got.u < 0.1
    assert abs(got.scale - scale) <= 2 * got.u, got


def test_the_spot_scale_is_stored_and_applied_to_the_footprint_optics(scaled_spot: CalibrationResult) -> None:
    """Through ``calibrate`` (here three spheres and a wall seen over 50 deg: the rig itself is poorly
    determined, so only the presence and the plumbing are checked, not the value)."""
    assert scaled_spot.optics is not None
    assert scaled_spot.optics["spot_scale"] > 0.0 and scaled_spot.optics["spot_scale_u"] > 0.0
    back = CalibrationResult.from_json(scaled_spot.to_json())
    assert back.optics == scaled_spot.optics
    assert json.loads(scaled_spot.to_json())["optics"]["spot_scale"] == pytest.approx(back.optics["spot_scale"])  # type: ignore[index]
    s, u = back.optics["spot_scale"], back.optics["spot_scale_u"]  # type: ignore[index]
    applied = back.beam_optics(BeamOptics())
    assert applied.exit_diameter_m == pytest.approx(0.008 * s)
    assert applied.divergence_rad == pytest.approx(0.015 * s)
    assert applied.spot_scale_u == pytest.approx(u / s)
    assert back.beam_optics(None) is None  # the thin beam stays thin


def test_a_final_spot_scale_off_the_one_its_rig_assumed_is_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    """With optics ``calibrate`` adjusts the rig twice: with the nominal spot, then with the scale
    that gives; when the scale from the second rig is again more than 2 u off the one that rig
    assumed, it logs a warning. Here (true scale 1.3, seed 1, measured: 1.32 then 0.99, u 0.14)
    the stored ``assumed_scale`` and ``spot_scale`` differ by more than 2 u, so the warning must name both."""
    obs, art = spheres_sweep(lms1xx(1.3), seed=1, step_deg=0.8)
    with caplog.at_level(logging.WARNING, logger="lrms.calibration"):
        res = calibrate([obs], art, options=CalibrationOptions(optics=BeamOptics()))
    assert res.optics is not None
    s, u, assumed = res.optics["spot_scale"], res.optics["spot_scale_u"], res.optics["assumed_scale"]
    # the scenario's precondition (if the calibration's numerics change, pick another seed or scale)
    assert abs(s - assumed) > 2 * u, (s, u, assumed)
    want = (
        f"spot scale {s:.4g} (u {u:.2g}) differs from the {assumed:.4g} the final adjustment assumed by more than 2 u"
    )
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert want in warned, warned


def test_the_thin_beam_or_no_optics_gives_no_spot_scale() -> None:
    obs, art = spheres_sweep(SensorModel(), step_deg=0.8)
    res = calibrate([obs], art)  # no nominal optics given: nothing estimated
    assert res.optics is None and "optics" not in res.to_dict()
    bad = json.loads(res.to_json())
    bad["optics"] = {"spot_scale": -1.0, "spot_scale_u": 0.1}
    with pytest.raises(Exception, match="spot_scale"):
        CalibrationResult.from_dict(bad)


def test_limb_echo_reads_short_near_the_limb_and_thin_inside() -> None:
    r, t = 0.1, 3.0
    x0 = np.array([0.0, 0.05, 0.099, 0.105])
    thin = t - np.sqrt(np.maximum(r * r - x0 * x0, 0.0))
    rng, share = limb_echo(x0, np.full(4, t), np.full(4, r), np.full(4, 1e-4))
    np.testing.assert_allclose(rng[:2], thin[:2], atol=2e-4)
    assert share[0] == pytest.approx(1.0) and share[3] < 1e-6
    big, share_big = limb_echo(x0, np.full(4, t), np.full(4, r), np.full(4, 0.013))
    assert big[2] < thin[2] - 0.005  # a wide spot at the limb covers the sphere's nearer parts
    assert share_big[3] > 0.2  # and still meets the sphere beyond the thin-beam silhouette


def test_the_stored_spot_scale_carries_its_nominal_spot_and_refuses_another(
    scaled_spot: CalibrationResult, caplog: pytest.LogCaptureFixture
) -> None:
    """The scale multiplies the nominal spot it was estimated against, stored with it; a fit with
    another nominal spot is refused; an older file (no nominal stored) reads as the LMS1xx's."""
    d = json.loads(scaled_spot.to_json())
    o = d["optics"]
    assert o["exit_diameter_m"] == 0.008 and o["divergence_rad"] == 0.015 and o["profile_sigma"] == 0.25
    assert o["extent"] == 1.5
    assert o["assumed_scale"] > 0.0
    d["optics"] = {**o, "exit_diameter_m": 0.01, "divergence_rad": 0.02}
    other = CalibrationResult.from_dict(d)
    assert other.optics == d["optics"]
    applied = other.beam_optics(BeamOptics(exit_diameter_m=0.01, divergence_rad=0.02))
    assert applied.exit_diameter_m == pytest.approx(0.01 * o["spot_scale"])
    assert applied.divergence_rad == pytest.approx(0.02 * o["spot_scale"])
    with pytest.raises(CalibrationError, match="exit_diameter_m"):
        other.beam_optics(BeamOptics())  # 8 mm, 15 mrad: not the spot the scale refers to
    with pytest.raises(CalibrationError, match="divergence_rad"):
        other.beam_optics(BeamOptics(exit_diameter_m=0.01))
    with pytest.raises(CalibrationError, match="profile_sigma"):  # the same diameter read as another Gaussian
        other.beam_optics(BeamOptics(exit_diameter_m=0.01, divergence_rad=0.02, profile_sigma=0.3))
    with pytest.raises(CalibrationError, match="extent"):  # the same spot cut to another disc
        other.beam_optics(BeamOptics(exit_diameter_m=0.01, divergence_rad=0.02, extent=2.0))
    bad = {**d, "optics": {**o, "profile_sigma": 0.0}}
    with pytest.raises(CalibrationError, match="profile_sigma"):
        CalibrationResult.from_dict(bad)
    with pytest.raises(CalibrationError, match="extent"):
        CalibrationResult.from_dict({**d, "optics": {**o, "extent": -1.0}})
    d["optics"] = {"spot_scale": 1.5, "spot_scale_u": 0.1}  # an older file: the LMS1xx, an endless Gaussian
    old = CalibrationResult.from_dict(d)
    lms1xx = {"exit_diameter_m": 0.008, "divergence_rad": 0.015, "profile_sigma": 0.25}
    assert old.optics == {"spot_scale": 1.5, "spot_scale_u": 0.1, **lms1xx}
    assert CalibrationResult.from_json(old.to_json()).optics == old.optics
    with caplog.at_level(logging.WARNING, logger="lrms.calibration"):  # applied, its model shift as u
        applied_old = old.beam_optics(BeamOptics())
    assert "endless Gaussian" in caplog.text
    assert applied_old.exit_diameter_m == pytest.approx(0.008 * 1.5)
    assert applied_old.spot_scale_u == pytest.approx(np.hypot(0.1 / 1.5, ENDLESS_SCALE_U))
    d["optics"] = {**o, "assumed_scale": 0.0}
    with pytest.raises(CalibrationError, match="assumed_scale"):
        CalibrationResult.from_dict(d)


def test_too_few_limb_beams_after_the_second_outlier_cut_give_no_scale() -> None:
    """20 central beams and 8 limb beams of scale 1, 2 limb beams of scale 1.6 and a gross one of
    2.5: the first fit (pulled by the gross beam) keeps 30 beams (MIN_LIMB_BEAMS), the second drops
    the two scale-1.6 beams: 28 left, too few for the final u."""
    assert MIN_LIMB_BEAMS == 30
    sig = (0.002, 0.004)
    x0 = np.r_[np.zeros(20), np.linspace(0.085, 0.098, 8), np.linspace(0.09, 0.097, 2), [0.099]]
    scale = np.r_[np.ones(28), [1.6, 1.6], [2.5]]
    t, r = np.full(x0.size, 2.0), np.full(x0.size, 0.1)
    ranges = limb_echo(x0, t, r, scale * (sig[0] + sig[1] * t))[0]
    assert fit_spot_scale(x0, t, r, ranges, 0.001, sig) is None
    ok = np.r_[np.arange(28), np.arange(28)[-8:]]  # 36 beams of scale 1: estimable
    got = fit_spot_scale(x0[ok], t[ok], r[ok], ranges[ok], 0.001, sig)
    assert got is not None and got.scale == pytest.approx(1.0, abs=1e-3)


def test_the_disc_cut_limb_echo_recovers_a_noiseless_spot_scale_closer_than_the_endless_gaussian() -> None:
    """The simulator's spot ends at 1.5 radii: on a noiseless sweep (128 sub-rays, rig and spheres
    known) the disc-cut echo reads the scale about 1.7 % closer to the truth than the endless
    Gaussian (measured: -2.0 % against -3.7 %; what is left is other model error, docs/calibration.md)."""
    fp = Footprint(sub_rays=128)
    quiet = LMS1xxSensor(footprint=fp, sigma_typical=0.0, sigma_max=0.0, spread_noise=0.0, sigma_alpha=0.0,
                         sigma_beta=0.0)  # fmt: skip
    obs, _ = spheres_sweep(quiet, step_deg=0.5)
    m = RigModel()
    o, d = m.rays(obs.alpha, obs.beta)
    args = (o, d, m.geometric_range(obs.l), spheres_truth(), 0.008, 0.015, 0.25, 0.012)
    disc, endless = estimate_spot_scale(*args, extent=1.5), estimate_spot_scale(*args)
    assert disc is not None and endless is not None and disc.beams == endless.beams > 500
    assert endless.scale < disc.scale < 1.0
    assert abs(disc.scale - 1.0) < 0.025 < abs(endless.scale - 1.0)
    assert disc.rms_m < endless.rms_m


def test_limb_echo_with_a_wide_disc_is_the_endless_gaussian_and_a_tight_one_meets_less() -> None:
    r, t = 0.1, 3.0
    x0 = np.array([0.0, 0.05, 0.09, 0.099, 0.105, 0.12])
    n, sig = x0.size, np.full(x0.size, 0.013)
    endless, s_endless = limb_echo(x0, np.full(n, t), np.full(n, r), sig)
    wide, s_wide = limb_echo(x0, np.full(n, t), np.full(n, r), sig, 8.0)
    np.testing.assert_allclose(wide, endless, atol=2e-5)
    np.testing.assert_allclose(s_wide, s_endless, atol=1e-3)
    tight, s_tight = limb_echo(x0, np.full(n, t), np.full(n, r), sig, 1.0)
    assert s_tight[-1] == 0.0  # the disc of 13 mm ends 7 mm short of the sphere
    assert s_tight[0] == pytest.approx(1.0)
    assert tight[0] < endless[0]  # less light far off the centre ray: less of the sphere's curvature average
