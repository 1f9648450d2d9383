"""Issue 11: detection among walls and floors, a nominal diameter, the beam-footprint fit, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.special import ndtr

from lrms.cylinder import (
    BeamOptics,
    Cylinder,
    CylinderFit,
    Rays,
    dominant_planes,
    expected_echo,
    fit_cylinder,
    nominal_diameter_range,
    rays_from_points,
)
from lrms.cylinder.footprint import EdgeMode, disc_marginal_cdf
from lrms.errors import FitError
from lrms.kinematics import RigCalibration
from service.cli.main import main
from service.models import MeasurementRequest
from service.pointio import write_xyz
from sim.scene import SEED003_DIAMETER, Footprint, LMS1xxSensor, SensorModel, cast_beams, get_scene
from sim.scene.library import SEED003_AXIS_POINT

TRUTH = Cylinder(np.array([0.28, SEED003_AXIS_POINT[1], 0.0]), np.array([0.0, 0.0, 1.0]), SEED003_DIAMETER / 2)


def room_cloud(sensor: object, seed: int) -> np.ndarray:
    """The whole seed003-room cloud (no region of interest): walls, floor, ceiling, table, neighbours."""
    cal = RigCalibration()
    dev = np.deg2rad(np.arange(50.0, 130.0 + 1e-9, 0.25))
    mot = np.deg2rad(np.arange(-20.0, 70.0, 0.8))[:, None]
    samples = cast_beams(get_scene("seed003-room"), cal, sensor, dev, mot, np.random.default_rng(seed))  # type: ignore[arg-type]
    return samples.points(cal)


@pytest.fixture(scope="module")
def ideal_room() -> np.ndarray:
    return room_cloud(SensorModel(sigma_alpha=0.0, sigma_beta=0.0), 3)


@pytest.fixture(scope="module")
def lms_room() -> np.ndarray:
    sensor = LMS1xxSensor(footprint=Footprint(sub_rays=16), sigma_alpha=0.0, sigma_beta=0.0)
    return room_cloud(sensor, 4)


def test_walls_floor_and_ceiling_are_set_aside_and_the_part_kept(ideal_room: np.ndarray) -> None:
    off, planes = dominant_planes(ideal_room, rng=np.random.default_rng(0))
    assert 2 <= len(planes) <= 6
    normals = np.abs(np.array([n for n, _ in planes]))
    assert np.any(normals[:, 2] > 0.99) and np.any(normals[:, 1] > 0.99)  # floor and the back wall
    on_part = np.abs(TRUTH.surface_distance(ideal_room)) < 0.01
    on_part &= (ideal_room[:, 2] > -0.05) & (ideal_room[:, 2] < 1.05)
    kept = np.zeros(ideal_room.shape[0], dtype=bool)
    kept[off] = True
    assert np.count_nonzero(on_part) > 1000
    assert np.mean(kept[on_part]) > 0.97  # the part's surface is not a plane
    assert np.mean(kept) < 0.5  # most of the room is


def test_the_part_is_found_in_the_whole_room_with_the_ideal_sensor(ideal_room: np.ndarray) -> None:
    # with its nominal diameter (without one, a room corner can pass for a cylinder metres wide)
    fit = fit_cylinder(ideal_room, rng=np.random.default_rng(1), diameter_range=nominal_diameter_range(0.1375))
    assert abs(fit.diameter - SEED003_DIAMETER) < 3 * fit.std_diameter + 2e-4
    assert np.linalg.norm(TRUTH.radial(fit.cylinder.point)) < 2e-3


def test_the_part_is_found_in_the_whole_room_under_the_footprint_with_a_nominal_diameter(
    lms_room: np.ndarray,
) -> None:
    # thin-beam fit: the part is found (no gross failure), and too large by the footprint
    thin = fit_cylinder(lms_room, rng=np.random.default_rng(2), diameter_range=(0.1, 0.2))
    assert np.linalg.norm(TRUTH.radial(thin.cylinder.point)) < 0.03
    assert 0 < thin.diameter - SEED003_DIAMETER < 0.06


def test_expected_echo_of_a_half_covered_spot_and_of_a_spot_on_the_front() -> None:
    optics = BeamOptics()
    cyl = Cylinder(np.array([0.0, 2.5, 0.0]), np.array([0.0, 0.0, 1.0]), 0.1)
    sigma = float(optics.sigma(2.5))
    # beams parallel to +y, offset across the axis by x0: covered share Phi((r - x0) / sigma) (r >> sigma)
    x0 = np.array([0.0, 0.1, 0.1 + sigma, 0.1 - sigma])
    o = np.stack([x0, np.zeros(4), np.zeros(4)], axis=1)
    d = np.tile([0.0, 1.0, 0.0], (4, 1))
    rays = Rays(o, d, np.zeros(4), np.full(4, 0.012), np.full(4, 1e-3))
    t, c = expected_echo(cyl.point, cyl.direction, cyl.radius, rays, optics, "weighted")
    # the energy-weighted family's spot ends at 1.5 spot radii (3 sigma): its lateral marginal
    want = disc_marginal_cdf((cyl.radius - x0) / sigma, 3.0) - disc_marginal_cdf((-cyl.radius - x0) / sigma, 3.0)
    assert np.allclose(c, want, atol=2e-3)
    # that marginal: the Gaussian's far from the disc's end, a little short of it near the end
    assert disc_marginal_cdf(1.0, 3.0) == pytest.approx(ndtr(1.0), abs=5e-3)
    assert disc_marginal_cdf(-3.0, 3.0) == 0.0 and disc_marginal_cdf(3.0, 3.0) == 1.0
    assert 0 < disc_marginal_cdf(-2.5, 3.0) < ndtr(-2.5)
    wide = BeamOptics(extent=10.0)  # a disc of 20 sigmas: the untruncated Gaussian
    _, cw = expected_echo(cyl.point, cyl.direction, cyl.radius, rays, wide, "weighted")
    assert np.allclose(cw, ndtr((cyl.radius - x0) / sigma) - ndtr((-cyl.radius - x0) / sigma), atol=2e-3)
    assert c[1] == pytest.approx(0.5, abs=1e-3)
    # the spot on the front: the energy-weighted range lies behind the front by about sigma^2 / (2 r)
    assert t[0] - 2.4 == pytest.approx(sigma**2 / (2 * cyl.radius), rel=0.25)
    # a half-covered spot reads a range between the front and the axis' closest approach
    assert 2.4 < t[1] < 2.5
    # first hit at threshold 50 %: on the front, the median of 2.4 + x^2 / (2 r), x ~ N(0, sigma^2):
    # 0.455 sigma^2 / (2 r) (0.455: the median of chi-square with 1 dof)
    tf, _ = expected_echo(cyl.point, cyl.direction, cyl.radius, rays, optics, "first", tau=0.5)
    assert tf[0] - 2.4 == pytest.approx(0.455 * sigma**2 / (2 * cyl.radius), abs=2e-4)


def footprint_sweep(threshold: float, mode: EdgeMode, seed: int, spot: float = 1.0) -> np.ndarray:
    """A sweep of seed 003's bare part under the LMS1xx footprint; ``spot`` scales the device's spot."""
    fp = Footprint(sub_rays=32)
    fp = Footprint(sub_rays=32, exit_diameter_m=spot * fp.exit_diameter_m, divergence_rad=spot * fp.divergence_rad)
    sensor = LMS1xxSensor(footprint=fp, edge_threshold=threshold, range_mode=mode, sigma_alpha=0.0, sigma_beta=0.0)
    cal = RigCalibration()
    dev = np.deg2rad(np.arange(60.0, 120.0 + 1e-9, 0.25))
    mot = np.deg2rad(np.arange(-20.0, 70.0, 0.4))[:, None]
    samples = cast_beams(get_scene("seed003-bare"), cal, sensor, dev, mot, np.random.default_rng(seed))
    pts = samples.points(cal)
    c0 = np.asarray(SEED003_AXIS_POINT)
    lo, hi = c0 + np.array([-0.6, -0.4, -0.05]), c0 + np.array([0.6, 0.4, 0.9])
    return pts[np.all((pts >= lo) & (pts <= hi), axis=1)]


def test_the_footprint_fit_removes_most_of_the_thin_beams_bias() -> None:
    """Energy-weighted echoes at a 30 % threshold (the sensor model's default): the thin-beam fit is
    about +40 mm too large; the footprint fit, which is told neither the threshold nor the family,
    comes within a few mm and its uncertainty (fit + edge-model row) covers the truth."""
    pts = footprint_sweep(0.3, "weighted", 7)
    g = np.random.default_rng(0)
    thin = fit_cylinder(pts, rng=g)
    fit = fit_cylinder(pts, rng=np.random.default_rng(0), optics=BeamOptics())
    assert thin.diameter - SEED003_DIAMETER > 0.02
    err = fit.diameter - SEED003_DIAMETER
    assert abs(err) < 0.25 * (thin.diameter - SEED003_DIAMETER)
    assert fit.extra["edge_mode_first"] in (0.0, 1.0)
    u = float(np.sqrt(fit.std_diameter**2 + fit.extra["edge_model_u_m"] ** 2 + fit.extra["edge_family_u_m"] ** 2))
    assert abs(err) < 2 * u
    # the model choice's row: the Akaike weights of the thin beam and both families sum to 1
    weights = {k: v for k, v in fit.extra.items() if k.startswith("akaike_weight_")}
    # the first-hit family is left out here: its solution ends pinned on its radius bound (no minimum)
    assert {"akaike_weight_thin", "akaike_weight_weighted"} <= set(weights)
    assert sum(weights.values()) == pytest.approx(1.0)
    assert fit.extra["edge_family_u_m"] >= 0.0
    # the fit's (type A) u is the larger of the Gauss-Newton one and the cost profile's in the radius
    u_jtj, u_prof = fit.extra["footprint_u_jtj_m"], fit.extra["footprint_u_profile_m"]
    assert u_jtj > 0 and u_prof > 0
    assert fit.std_diameter == pytest.approx(max(u_jtj, u_prof), rel=1e-6)
    assert fit.extra["footprint_profile_scale"] == pytest.approx(max(1.0, (u_prof / u_jtj) ** 2), rel=1e-6)


def test_a_device_whose_spot_is_not_the_nominal_one_is_estimated_not_assumed() -> None:
    """A device whose spot is 1.2 x SICK's figure (energy-weighted, 30 %): the fit estimates the
    spot's scale (the nominal size a prior of 15 %) and its diameter is within 2 u of the truth with
    no spot row left in the budget; held at the nominal size, the spot's row is what has to cover it."""
    pts = footprint_sweep(0.3, "weighted", 8, spot=1.2)
    rng = np.random.default_rng(0)
    fit = fit_cylinder(pts, rng=rng, optics=BeamOptics(), diameter_range=nominal_diameter_range(SEED003_DIAMETER))
    assert fit.extra["edge_mode_first"] == 0.0
    s, us = fit.extra["edge_spot_scale"], fit.extra["edge_spot_scale_u"]
    assert 0.0 < us < 0.15  # the data pin the spot closer than the prior
    assert abs(s - 1.2) < 3 * us  # measured 1.117 +- 0.045 (the prior pulls toward 1)
    assert fit.extra["edge_model_u_m"] == 0.0
    assert abs(fit.diameter - SEED003_DIAMETER) < 2 * fit.std_diameter
    held = fit_cylinder(
        pts,
        rng=np.random.default_rng(0),
        optics=BeamOptics(fit_spot=False),
        diameter_range=nominal_diameter_range(SEED003_DIAMETER),
    )
    assert "edge_spot_scale" not in held.extra
    assert held.extra["edge_model_u_m"] > 0.0
    assert held.std_diameter < fit.std_diameter  # the spot's share moved from type A to its own row


def test_bad_optics_and_nominal_diameters_are_clear_errors() -> None:
    with pytest.raises(FitError, match="divergence_rad"):
        BeamOptics(divergence_rad=-0.001)
    with pytest.raises(FitError, match="fit_spot"):
        BeamOptics(fit_spot=1)  # type: ignore[arg-type]
    with pytest.raises(FitError, match="extent"):
        BeamOptics(extent=0.0)
    with pytest.raises(FitError, match="extent"):
        disc_marginal_cdf(0.0, -1.0)
    with pytest.raises(FitError, match="nominal diameter must be > 0"):
        nominal_diameter_range(0.0)
    with pytest.raises(FitError, match="nominal diameter must be > 0"):
        nominal_diameter_range(-0.1)
    with pytest.raises(FitError, match="tolerance"):
        nominal_diameter_range(0.1, 0.2)
    with pytest.raises(FitError, match="diameter range"):
        fit_cylinder(np.zeros((30, 3)), diameter_range=(0.2, 0.1))
    for bad in ({"nominal_diameter_m": 0.0}, {"nominal_diameter_m": -0.1}, {"diameter_tolerance_m": 0.01}):
        with pytest.raises(ValueError, match="nominal_diameter_m"):
            MeasurementRequest.model_validate({"target": "cylinder", "options": bad})
    with pytest.raises(ValueError, match="cylinder"):
        MeasurementRequest.model_validate({"target": "elbow", "options": {"nominal_diameter_m": 0.1}})
    ok = MeasurementRequest.model_validate(
        {"target": "cylinder", "options": {"nominal_diameter_m": 0.1375, "diameter_tolerance_m": 0.01}}
    )
    assert ok.options.nominal_diameter_m == 0.1375


def test_cli_nominal_diameter_and_optics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pts = footprint_sweep(0.5, "first", 8)
    f = tmp_path / "sweep.xyz"
    write_xyz(f, pts)
    for args, msg in (
        (["--nominal-diameter", "0"], "--nominal-diameter must be > 0"),
        (["--nominal-diameter", "-0.1"], "--nominal-diameter must be > 0"),
        (["--divergence-mrad", "-1"], "--divergence-mrad must be >= 0"),
        (["--spot-exit-mm", "-1"], "--spot-exit-mm must be >= 0"),
        (["--diameter-tolerance", "0.01"], "needs --nominal-diameter"),
    ):
        assert main(["fit", str(f), *args]) == 1
        assert msg in capsys.readouterr().err
    assert main(["fit", str(f), "--json", "--optics", "ideal", "--nominal-diameter", "0.1375"]) == 0
    thin = json.loads(capsys.readouterr().out)
    assert thin["footprint"] is None and thin["diameter_range_m"] == pytest.approx([0.12375, 0.15125])
    args = ["--optics", "lms1xx", "--nominal-diameter", "0.1375", "--diameter-tolerance", "0.03"]
    assert main(["fit", str(f), "--json", *args]) == 0
    fp = json.loads(capsys.readouterr().out)
    assert fp["footprint"]["edge_mode"] in ("first", "weighted", "thin")
    assert fp["footprint"]["thin_beam_diameter_m"] == pytest.approx(thin["diameter_m"], abs=2e-3)
    assert abs(fp["diameter_m"] - SEED003_DIAMETER) < 0.015
    # a footprint family won: the spot's scale was estimated, and its row is in the type A
    won = fp["footprint"]["edge_mode"] != "thin"
    assert (fp["footprint"]["spot_scale"] is not None) == won
    assert won or fp["footprint"]["spot_scale_u"] is None
    assert not won or (fp["footprint"]["spot_scale_u"] > 0 and fp["footprint"]["edge_model_u_m"] == 0.0)


@pytest.mark.parametrize(("threshold", "mode"), [(0.1, "first"), (0.3, "first"), (0.5, "first"), (0.3, "weighted")])
def test_the_forward_model_matches_the_simulators_echoes_beam_by_beam(threshold: float, mode: EdgeMode) -> None:
    """Noiseless LMS1xx echoes of seed 003's part (512 sub-rays over 3 spot radii: the simulator
    close to its continuous Gaussian profile) against :func:`expected_echo` at the true cylinder
    and threshold. Beams whose spot centre is on the part agree within 0.2 mm on average, and
    within 1 mm per beam (the sub-rays' own sampling) where covered by >= threshold + 10 %. The
    beams at the detection edge (first hit near the limb's range singularity) disagree by
    millimetres: not asserted, the remaining model error (docs/cylinder.md, section 7)."""
    from sim.scene import Scene
    from sim.scene.shapes import Cylinder as SceneCylinder

    scene = Scene("part")
    base = TRUTH.point - np.array([0.0, 0.0, 0.5])
    scene.add(SceneCylinder(base, TRUTH.direction, TRUTH.radius, 1.5), remission=0.35, name="cylinder")
    sensor = LMS1xxSensor(footprint=Footprint(sub_rays=512, extent=3.0), edge_threshold=threshold, range_mode=mode)
    cal = RigCalibration()
    dev, mot = np.meshgrid(np.deg2rad(np.arange(60.0, 120.0, 0.25)), np.deg2rad(np.arange(-20.0, 70.0, 6.0)))
    o, d = cal.world_rays(dev.ravel(), mot.ravel())
    e = sensor.echoes(scene, o, d, None)
    on = e.valid & (e.index == 0)
    pts = o[on] + e.range[on, None] * d[on]
    keep = (pts[:, 2] > -0.3) & (pts[:, 2] < 0.8)  # clear of the ends
    o, d, rng_ = o[on][keep], d[on][keep], e.range[on][keep]
    assert rng_.size > 100
    rays = Rays(o, d, rng_, np.full(rng_.size, 0.012), np.full(rng_.size, 1e-3))
    optics = BeamOptics(extent=3.0)  # the simulator's spot here: 3 spot radii
    pred, c = expected_echo(TRUTH.point, TRUTH.direction, TRUTH.radius, rays, optics, mode, tau=threshold)
    nvec = np.cross(d, TRUTH.direction)
    nvec /= np.linalg.norm(nvec, axis=1, keepdims=True)
    q = (np.abs(np.sum((o - TRUTH.point) * nvec, axis=1)) - TRUTH.radius) / optics.sigma(rng_)
    res = rng_ - pred
    centre_on = q < 0.0
    assert np.count_nonzero(centre_on) > 50 and np.count_nonzero(q > -1.0) > 10
    clear = centre_on & (c >= threshold + 0.1)  # clear of the detection edge
    assert np.max(np.abs(res[clear])) < 1e-3  # per beam: the 512 sub-rays' own sampling
    assert abs(float(np.mean(res[centre_on]))) < 2e-4
    assert np.all(np.abs(c[centre_on] - 0.5) <= 0.5)


@pytest.mark.parametrize("spot_free", [False, True])
def test_the_first_hit_jacobian_matches_differences_through_the_newton_solve(spot_free: bool) -> None:
    """The implicit-step Jacobian of the first-hit rows (share_u on: widened sigmas) against plain
    central differences of the residuals, each of which re-solves F(T) = target, on every beam of
    a noiseless first-hit cloud (table and part) near (not at) the solution; with the spot's scale
    a parameter too (its column and its prior row)."""
    from scipy.optimize._numdiff import approx_derivative
    from scipy.special import logit

    from lrms.cylinder.footprint_solve import _first_jacobian, _residuals
    from lrms.cylinder.refine import _Frame

    scene_pts = footprint_sweep(0.3, "first", 9)[::12]
    rays = rays_from_points(scene_pts)
    frame = _Frame.at(TRUTH.with_point_near(scene_pts.mean(axis=0)))
    optics = BeamOptics(share_u=0.03)
    # spot 1.1 x nominal: one beam of this cloud, on the front's centre, has its first hit just past
    # a node's tip (F's square-root onset); the linear implicit step made its radius row 47x too large
    # until such beams were re-solved per column
    theta = np.array([2e-4, -3e-4, 1e-3, -5e-4, 8e-4, float(logit(0.27))] + ([float(np.log(1.1))] if spot_free else []))
    jac = _first_jacobian(theta, frame, rays, optics)
    # absolute steps as the Jacobian's (a relative step of 1e-6 is 2e-10 on an angle of 2e-4: the
    # Newton tolerance of 1e-11 m then reads as a few units of noise in the rows)
    steps = np.array([1e-6] * 5 + [1e-4] * (theta.size - 5))
    ref = approx_derivative(
        lambda th: _residuals(th, frame, rays, optics, "first"), theta, method="3-point", abs_step=steps
    )
    assert jac.shape == ref.shape
    # the geometry and threshold columns agree to 0.3 % of their norm and per row to 2 % of the
    # column's largest entry (measured: 0.03 % / 0.7 %); the spot's column, a forward difference
    # of 1e-4 in its log, to 5 % (measured 1.5 %)
    for j in range(theta.size):
        tol = 0.003 if j < 6 else 0.05
        assert np.linalg.norm(jac[:, j] - ref[:, j]) <= tol * np.linalg.norm(ref[:, j]), j
        if j < 6:
            assert np.max(np.abs(jac[:, j] - ref[:, j])) <= 0.02 * np.max(np.abs(ref[:, j])), j


def test_the_first_hit_slope_includes_the_spots_growth_with_range() -> None:
    """``dF/dT`` of :func:`_first_share` (Newton's slope and the implicit step's divisor) against
    central differences of ``F`` in ``T``: the spot widens with ``T`` on the part's near side, a term
    once left out (3-7 % off on limb beams, more where F is nearly flat). Beams flagged near the
    front's tip (F's kink) are left out, as in the partials' test below."""
    from lrms.cylinder.footprint_first import _first_share, _first_share_grad

    rng = np.random.default_rng(0)
    n, r, s0, sd = 3000, 0.069, 0.25 * 0.008, 0.25 * 0.015
    t_ca = 2.5 + rng.normal(0.0, 0.01, n)
    x0 = rng.uniform(-0.11, 0.11, n)
    cos_axis = rng.uniform(-0.3, 0.3, n)
    big_t = t_ca - r / np.sqrt(1.0 - cos_axis**2) * rng.uniform(-0.2, 1.1, n)
    _, fp = _first_share(big_t, x0, t_ca, cos_axis, r, s0, sd)
    _, fp_grad, _, near = _first_share_grad(big_t, x0, t_ca, cos_axis, r, s0, sd)
    h = 1e-7
    num = (
        _first_share(big_t + h, x0, t_ca, cos_axis, r, s0, sd)[0]
        - _first_share(big_t - h, x0, t_ca, cos_axis, r, s0, sd)[0]
    ) / (2 * h)
    ok = ~near & (np.abs(num) > 1.0)
    assert np.count_nonzero(ok) > 500
    assert np.max(np.abs(fp[ok] - num[ok]) / np.abs(num[ok])) < 1e-5
    assert np.allclose(fp, fp_grad, rtol=1e-12, atol=1e-9)


def test_the_first_hit_shares_partials_match_its_differences_away_from_the_fronts_tip() -> None:
    """The partials of F(T) in the beam geometry (x0, t_ca, cos_axis, radius) that the first-hit
    Jacobian uses instead of one evaluation per column: against central differences of F on beams
    spread over the part's front, the limbs and behind the axis, except those flagged as having
    a node near the front's tip (the square root's infinite slope), which the Jacobian evaluates."""
    from lrms.cylinder.footprint_first import _first_share, _first_share_grad

    rng = np.random.default_rng(0)
    n, r, s0, sd = 3000, 0.069, 0.25 * 0.008, 0.25 * 0.015
    t_ca = 2.5 + rng.normal(0.0, 0.01, n)
    x0 = rng.uniform(-0.11, 0.11, n)
    cos_axis = rng.uniform(-0.3, 0.3, n)
    big_t = t_ca - r / np.sqrt(1.0 - cos_axis**2) * rng.uniform(-0.2, 1.1, n)
    f, fp, grad, near = _first_share_grad(big_t, x0, t_ca, cos_axis, r, s0, sd)
    f_ref, fp_ref = _first_share(big_t, x0, t_ca, cos_axis, r, s0, sd)
    assert np.allclose(f, f_ref, rtol=0, atol=1e-14) and np.allclose(fp, fp_ref, rtol=1e-12, atol=1e-9)
    assert 0 < np.count_nonzero(near) < n
    h = 1e-7
    args = [x0, t_ca, cos_axis, np.full(n, r)]
    for k in range(4):
        up = [a.copy() for a in args]
        dn = [a.copy() for a in args]
        up[k] += h
        dn[k] -= h
        f_up = _first_share(big_t, up[0], up[1], up[2], up[3], s0, sd)[0]
        f_dn = _first_share(big_t, dn[0], dn[1], dn[2], dn[3], s0, sd)[0]
        num = (f_up - f_dn) / (2 * h)
        ok = ~near
        scale = np.max(np.abs(num[ok]))
        assert scale > 0
        assert np.max(np.abs(grad[ok, k] - num[ok])) <= 1e-5 * scale, k


def test_an_ideal_cloud_keeps_the_thin_beam_with_share_u_on() -> None:
    """With share_u on, the first-hit family's down-weighted edge beams won the model choice on a
    thin-beam cloud when its chi-square under the widened sigmas was compared (-5.4 mm measured
    before): compared under the common range noise, the thin beam wins and the diameter is the thin
    fit's."""
    cal = RigCalibration()
    dev = np.deg2rad(np.arange(60.0, 120.0 + 1e-9, 0.25))
    mot = np.deg2rad(np.arange(-20.0, 70.0, 0.8))[:, None]
    sensor = SensorModel(sigma_alpha=0.0, sigma_beta=0.0)
    pts = cast_beams(get_scene("seed003-bare"), cal, sensor, dev, mot, np.random.default_rng(11)).points(cal)
    c0 = np.asarray(SEED003_AXIS_POINT)
    pts = pts[np.all((pts >= c0 + np.array([-0.6, -0.4, -0.05])) & (pts <= c0 + np.array([0.6, 0.4, 0.9])), axis=1)]
    fit = fit_cylinder(pts, rng=np.random.default_rng(1), optics=BeamOptics(share_u=0.03), diameter_range=(0.12, 0.16))
    assert fit.extra["edge_mode_first"] == -1.0
    assert fit.extra["aic_thin"] < fit.extra["aic_first"]
    assert abs(fit.diameter - SEED003_DIAMETER) < 3 * fit.std_diameter + 2e-4


def test_the_first_hit_memory_reuses_only_the_same_parameters_and_its_jacobian_matches() -> None:
    """The solver's memory (_Warm: the last solution reused at the same parameters) hands back the
    stored ranges at the same parameters, solves afresh at others (equal to a cold solve there and
    not the stored ranges), and the Jacobian through the memory matches central differences through
    cold Newton solves. (Newton is never warm-started: a start from the last solution moved 2 beams
    of this cloud to another root, 7-9 mm away.)"""
    from scipy.optimize._numdiff import approx_derivative
    from scipy.special import expit, logit

    from lrms.cylinder.footprint_echo import _geometry
    from lrms.cylinder.footprint_first import first_hit_range
    from lrms.cylinder.footprint_solve import _first_jacobian, _residuals, _Warm
    from lrms.cylinder.refine import _Frame

    scene_pts = footprint_sweep(0.1, "first", 5)[::12]
    rays = rays_from_points(scene_pts)
    frame = _Frame.at(TRUTH.with_point_near(scene_pts.mean(axis=0)))
    optics = BeamOptics()
    warm = _Warm()
    theta0 = np.array([0.0, 0.0, 0.0, 0.0, 0.0, float(logit(0.12))])
    _residuals(theta0, frame, rays, optics, "first", 1.0, warm)
    stored = warm.big_t
    assert stored is not None
    a0, w0, r0 = frame.unpack(theta0[:5])
    again, _ = warm.solve(theta0.copy(), _geometry(a0, w0, float(r0), rays, optics, 1.0), float(expit(theta0[5])))
    assert again is stored
    theta = theta0 + np.array([2e-4, -3e-4, 1e-3, -5e-4, 8e-4, 0.1])
    a, w, r = frame.unpack(theta[:5])
    g = _geometry(a, w, float(r), rays, optics, 1.0)
    tau = float(expit(theta[5]))
    got, _ = warm.solve(theta, g, tau)
    cold, _ = first_hit_range(g.x0, g.t_ca, g.cos_axis, g.radius, g.s0, g.sd, tau, g.c)
    assert np.max(np.abs(got - cold)) < 1e-9
    assert np.max(np.abs(got - stored)) > 1e-4
    jac = _first_jacobian(theta, frame, rays, optics, warm)
    steps = np.array([1e-6] * 5 + [1e-4])  # the Jacobian's own (absolute) steps
    ref = approx_derivative(
        lambda th: _residuals(th, frame, rays, optics, "first"), theta, method="3-point", abs_step=steps
    )
    for j in range(theta.size):
        assert np.linalg.norm(jac[:, j] - ref[:, j]) <= 0.003 * np.linalg.norm(ref[:, j]), j  # measured < 0.05 %


def test_the_thin_beams_criterion_on_a_subsample_counts_its_miss_rows_too() -> None:
    """The thin beam's criterion counts range and miss rows alike, on all beams and on a subsample
    (the subsample's families are scored with their coverage rows: leaving out the thin beam's miss
    rows there made it score too well)."""
    from lrms.cylinder.footprint import _thin_criterion

    ranges = np.array([1.0, 2.0, 3.0, 10.0])
    misses = np.array([0.5, 0.0, 6.0, 1.0])
    res = np.concatenate([ranges, misses])
    assert _thin_criterion(res, 4.0) == pytest.approx(1 + 4 + 9 + 16 + 0.25 + 0 + 16 + 1 + 10)
    pick = np.array([0, 2])
    assert _thin_criterion(res, 4.0, pick) == pytest.approx(1 + 9 + 0.25 + 16 + 10)
    assert _thin_criterion(res, 4.0, np.arange(4)) == _thin_criterion(res, 4.0)


def test_the_model_choice_u_is_the_akaike_weighted_spread_of_the_families() -> None:
    """family_spread: sqrt(sum w_i (d_i - chosen)^2), w_i = exp(-dAIC_i / 2) normalised."""
    from lrms.cylinder.footprint import family_spread

    u, w = family_spread({"thin": 0.150, "weighted": 0.138}, {"thin": 100.0, "weighted": 100.0}, 0.138)
    assert w == pytest.approx({"thin": 0.5, "weighted": 0.5})
    assert u == pytest.approx(0.012 / np.sqrt(2.0))
    # 10 apart (MODE_DECISIVE): the other family keeps e^-5 / (1 + e^-5) of the weight
    u, w = family_spread({"first": 0.140, "weighted": 0.137}, {"first": 110.0, "weighted": 100.0}, 0.137)
    w_first = np.exp(-5.0) / (1.0 + np.exp(-5.0))
    assert w["first"] == pytest.approx(w_first)
    assert u == pytest.approx(0.003 * np.sqrt(w_first))
    # one family alone: nothing to choose
    assert family_spread({"first": 0.14}, {"first": 5.0}, 0.14)[0] == 0.0
    with pytest.raises(FitError, match="one criterion per family"):
        family_spread({"first": 0.14}, {"weighted": 5.0}, 0.14)
    with pytest.raises(FitError, match="finite"):
        family_spread({"first": 0.14}, {"first": float("nan")}, 0.14)


def test_the_first_hit_multi_start_leaves_a_small_local_minimum_of_the_radius_tau_ridge() -> None:
    """The first-hit cost in (radius, tau) has local minima along a rough ridge: on 10 % first-hit
    sweeps of the bench (seed 2) one thin-beam start settled 8-15 mm small at tau 0.04-0.06 (one
    sweep then failed the nominal-diameter check), 14-24 criterion units above the basin near the
    truth. From such a start the family alone stays there; with the silhouette starts the family
    keeps the solution of the lowest criterion, near the truth."""
    from scipy.special import logit

    from lrms.cylinder.footprint import _aics, _first_starts, _fit_families
    from lrms.cylinder.refine import _Frame

    pts = footprint_sweep(0.1, "first", 5)
    thin = fit_cylinder(pts, rng=np.random.default_rng(0))
    rays = rays_from_points(pts).subset(thin.inliers)
    frame = _Frame.at(thin.cylinder.with_point_near(pts[thin.inliers].mean(axis=0)))
    optics = BeamOptics()
    bad = np.array([0.0, 0.0, 0.0, 0.0, -0.045, float(logit(0.03))])
    (single,) = _fit_families(frame, rays, optics, ("first",), {"first": bad}, 4.0)
    d_single = 2.0 * float(frame.unpack(single.theta[:5])[2])
    print(f"single start: {(d_single - SEED003_DIAMETER) * 1e3:+.2f} mm")
    # measured -8.3 mm (from -35 mm: -9.6, then -5.5 with k-d tree normals); -7.2 mm since round 8's
    # Jacobian fix (docs/cylinder.md, section 7)
    assert d_single - SEED003_DIAMETER < -0.006
    # the silhouette start of tau 0.5 (the cheapest of the three here) against the small minimum
    good = _first_starts(frame, optics, None)[-1]
    (multi,) = _fit_families(frame, rays, optics, ("first",), {"first": bad}, 4.0, [single.theta, good])
    d_multi = 2.0 * float(frame.unpack(multi.theta[:5])[2])
    assert abs(d_multi - SEED003_DIAMETER) < 0.004  # measured -3.0 mm
    crit_single = _aics([single], frame, rays, optics, 4.0)["first"]
    crit_multi = _aics([multi], frame, rays, optics, 4.0)["first"]
    # measured 14 lower; 3.6 since round 8 (the corrected Jacobian takes the single start further
    # down the ridge, to -7.2 mm from -24 mm on this tree before the fix)
    assert crit_multi < crit_single - 2.0


def test_the_energy_weighted_fit_models_the_spots_end_noiseless() -> None:
    """The cause of the energy-weighted family's +3 mm (issue 11): the simulator's spot, like a real
    one, ends (its sub-rays fill a disc of 1.5 spot radii), and a fit whose Gaussian has no end reads
    the edge beams' ranges 0.1-0.5 mm too short, which moves the weakly determined diameter by about
    +2 mm on a noiseless cloud. With the disc's lateral profile (BeamOptics.extent) the noiseless fit
    of energy-weighted 30 % echoes comes within 1 mm."""
    from sim.scene import Scene
    from sim.scene.shapes import Cylinder as SceneCylinder

    scene = Scene("part")
    scene.add(SceneCylinder(TRUTH.point - np.array([0.0, 0.0, 0.3]), TRUTH.direction, TRUTH.radius, 1.2), 0.35)
    sensor = LMS1xxSensor(edge_threshold=0.3, range_mode="weighted")  # the default footprint: 128 sub-rays
    cal = RigCalibration()
    dev, mot = np.meshgrid(np.deg2rad(np.arange(60.0, 120.0, 0.25)), np.deg2rad(np.arange(-20.0, 70.0, 1.2)))
    o, d = cal.world_rays(dev.ravel(), mot.ravel())
    near = TRUTH.ray_range(o, d)[1] < 0.05  # beams passing within 5 cm of the part (the cast's cost)
    e = sensor.echoes(scene, o[near], d[near], None)
    pts = o[near][e.valid] + e.range[e.valid, None] * d[near][e.valid]
    fit = fit_cylinder(pts, rng=np.random.default_rng(0), optics=BeamOptics(), diameter_range=(0.12, 0.16))
    assert fit.extra["edge_mode_first"] == 0.0  # the energy-weighted family
    assert abs(fit.diameter - SEED003_DIAMETER) < 1e-3


def test_the_first_hit_u_is_the_profile_likelihood_interval_and_covers_a_flat_valley() -> None:
    """On a 10 % first-hit cloud the cost in (radius, tau) is a flat, lopsided valley: with the
    radius held and tau refitted it rises steeply on one side and slowly on the other. The
    Jacobian's u sees only the curvature at the minimum; the profile-likelihood interval (its
    crossing of Delta = 4 x chi2/dof searched for on each side) reaches far out on the flat side,
    and its larger half-width over k is the fit's u. This cloud (seed 4) until round 8: error
    -3.5 mm, the truth on the flat side; J^T J's u 0.51 mm (U 1.1 mm with the edge rows: not
    covered), the interval -1.8 / +10.8 mm (U 10.8 mm: covered). Since round 8's Jacobian fix
    (docs/cylinder.md, section 7) the fit lands at +0.05 mm with an interval of -5.5 / +5.1 mm and
    J^T J's u no longer falls short on seeds 4-8, 10-13 of this cloud (none lopsided with the truth out of
    J^T J's reach), so the lopsided case is no longer asserted; the interval's mechanics and the
    coverage are."""
    pts = footprint_sweep(0.1, "first", 4)
    fit = fit_cylinder(
        pts, rng=np.random.default_rng(0), optics=BeamOptics(), diameter_range=nominal_diameter_range(SEED003_DIAMETER)
    )
    x = fit.extra
    assert x["edge_mode_first"] == 1.0
    lo, hi, lowest = x["footprint_profile_lo_m"], x["footprint_profile_hi_m"], x["footprint_profile_lowest_m"]
    err = fit.diameter - SEED003_DIAMETER
    print(f"error {err * 1e3:+.2f} mm, u {fit.std_diameter * 1e3:.2f} mm, interval {lo * 1e3:+.2f}, {hi * 1e3:+.2f}")
    assert lo < 0.0 < hi and lo <= lowest <= hi
    # the diameter's u: the interval's larger half-width over k = 2 (or J^T J's, were it wider)
    assert x["footprint_u_profile_m"] == pytest.approx(max(-lo, hi) / 2.0, rel=1e-9)
    assert fit.std_diameter == pytest.approx(max(x["footprint_u_jtj_m"], x["footprint_u_profile_m"]), rel=1e-6)
    edge = x["edge_model_u_m"] ** 2 + x["edge_family_u_m"] ** 2
    u = float(np.sqrt(fit.std_diameter**2 + edge))
    assert abs(err) <= 2.0 * u  # measured U = 5.5 mm for an error of +0.05 mm (round 8)


def test_the_energy_weighted_echo_stays_continuous_where_the_spot_leaves_the_part() -> None:
    """A beam whose cut spot no longer meets the part (covered share exactly 0 beyond extent
    radii) keeps the range of its spot's edge: the expected echo does not jump to 0 m there (a
    200-sigma cliff in the residuals for the solver's finite differences)."""
    a, w, r = np.array([0.0, 2.5, 0.0]), np.array([0.0, 0.0, 1.0]), 0.06875
    optics = BeamOptics()
    sig = optics.sigma(2.5)
    beyond = np.array([2.9, 2.99, 3.01, 3.5, 5.0])  # spot sigmas past the limb; the disc ends at 3
    x0 = r + sig * beyond
    n = x0.size
    rays = Rays(
        np.stack([x0, np.zeros(n), np.zeros(n)], 1), np.tile([0.0, 1.0, 0.0], (n, 1)),
        np.full(n, 2.43), np.full(n, 0.012), np.full(n, 1e-3),
    )  # fmt: skip
    t, c = expected_echo(a, w, r, rays, optics, "weighted")
    assert c[0] > 0 and np.all(c[2:] == 0.0)  # the cut spot: nothing of it on the part past 3 sigma
    np.testing.assert_allclose(t, 2.5, atol=0.01)  # every range near the limb's, none at 0 m
    assert abs(t[2] - t[1]) < 0.005  # no jump across the disc's edge


def test_the_energy_weighted_echo_weighs_each_sub_ray_at_its_own_hit_point() -> None:
    """The energy-weighted echo of a beam near the limb against a fine quadrature of its definition:
    the disc-cut Gaussian's lateral profile, each sub-ray leaving its own point of the exit spot
    (``s0 xi`` across the beam) and leaning out by the divergence, met exactly by the circle, its
    energy ``profile x cos(incidence) / t^2`` with the incidence at the sub-ray's own hit point. The
    forward model took the incidence at a point shifted by the sub-ray's exit offset (the beam's
    origin plus ``t`` along the sub-ray): near the limb, where the incidence changes fast, that
    read the echo 0.1-0.15 mm too deep, and the weakly determined diameter of a noiseless
    energy-weighted fit came out +0.45 mm (30 %), +0.74 mm (50 %) (docs/cylinder.md, section 7)."""
    from scipy.special import ndtr as phi_cdf

    a, w, r = np.array([0.0, 2.5, 0.0]), np.array([0.0, 0.0, 1.0]), 0.06875
    optics = BeamOptics()
    s0 = optics.profile_sigma * optics.exit_diameter_m
    lean = np.tan(optics.profile_sigma * optics.divergence_rad)
    sig = s0 + optics.profile_sigma * optics.divergence_rad * 2.5
    z = np.array([-4.0, -2.5, -1.8, -1.0, -0.5, 0.3, 1.0])  # beam offsets from the limb, spot sigmas
    x0 = -(r + z * sig)  # beams left of the axis, along +y from the x axis
    n = x0.size
    rays = Rays(
        np.stack([x0, np.zeros(n), np.zeros(n)], 1), np.tile([0.0, 1.0, 0.0], (n, 1)),
        np.full(n, 2.43), np.full(n, 0.012), np.full(n, 1e-3),
    )  # fmt: skip
    t_model, _ = expected_echo(a, w, r, rays, optics, "weighted")
    big_r = optics.extent / (2.0 * optics.profile_sigma)  # the disc's edge in sigmas (3)
    xi = np.linspace(-big_r, big_r, 200_001)
    pdf = np.exp(-0.5 * xi * xi) * (2.0 * phi_cdf(np.sqrt(np.maximum(big_r**2 - xi * xi, 0.0))) - 1.0)
    for i in range(n):
        ox = x0[i] + s0 * xi  # each sub-ray's start (x; y = 0) and direction (lean, 1) / norm
        norm = np.sqrt(1.0 + (lean * xi) ** 2)
        dx, dy = lean * xi / norm, 1.0 / norm
        # the circle (x^2 + (y - 2.5)^2 = r^2) met by the ray: t^2 + 2 b t + c = 0
        b = ox * dx - 2.5 * dy
        disc = b * b - (ox * ox + 6.25 - r * r)
        hit = disc > 0
        t = -b - np.sqrt(np.where(hit, disc, 0.0))
        qx, qy = ox + t * dx, t * dy - 2.5
        cos = np.abs(qx * dx + qy * dy) / r
        e = np.where(hit, pdf * cos / np.square(t), 0.0)
        t_ref = float(np.sum(e * t) / np.sum(e))
        assert abs(t_model[i] - t_ref) < 2e-5, (z[i], (t_model[i] - t_ref) * 1e3)


def test_the_first_hit_spot_scale_is_not_less_certain_than_its_prior() -> None:
    """The radius' profile factor (the first hit's flat (radius, tau) ridge) widens the radius and
    the axis, not the estimated spot scale: its u stays within the prior's (0.15 of the nominal).
    Seed 8's 30 % first-hit sweep: profile factor 10.3, spot 1.037 +- 0.126 (scaled by the factor
    it read 0.494 +- 3x its prior)."""
    pts = footprint_sweep(0.3, "first", 8)
    fit = fit_cylinder(
        pts,
        rng=np.random.default_rng(0),
        optics=BeamOptics(),
        diameter_range=nominal_diameter_range(SEED003_DIAMETER),
    )
    x = fit.extra
    assert x["edge_mode_first"] == 1.0 and x["footprint_profile_scale"] > 2.0, x
    assert 0.0 < x["edge_spot_scale_u"] <= BeamOptics().spot_scale_u * x["edge_spot_scale"], x


def test_the_footprint_fit_takes_its_beams_about_its_own_model_not_the_thin_beams_band(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 1.0 m part at 5 m (energy-weighted, 30 %, the simulator's noise growing with the range spread
    inside the spot): the thin fit is several cm too wide, and its inliers (a band about that wider
    surface) cut the noisy limb echoes on one side. Taken from there, the footprint fit came out
    about 5 u too large; with the chosen family's beams taken anew about its own model (a band of
    REGATE_BAND, then its gate) it is within 2 u of the truth."""
    import lrms.cylinder.footprint as fpmod
    from sim.scene.library import part_in_room
    from sim.scene.shapes import Cylinder as SceneCylinder

    d = 1.0
    scene = part_in_room(d, 5.0)
    sensor = LMS1xxSensor(footprint=Footprint(sub_rays=32))
    cal = RigCalibration()
    dev = np.deg2rad(np.arange(60.0, 120.0 + 1e-9, 0.25))
    mot = np.deg2rad(np.arange(-20.0, 70.0, 0.8))[:, None]
    pts = cast_beams(scene, cal, sensor, dev, mot, np.random.default_rng(11)).points(cal)
    part = scene.objects[scene.index_of("cylinder")].shape
    assert isinstance(part, SceneCylinder)
    c0 = part.point  # the part's axis at its foot
    lo, hi = c0 + np.array([-0.7, -0.7, -0.05]), c0 + np.array([0.7, 0.7, 0.9])
    pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]

    def fit() -> tuple[float, float]:
        rng = np.random.default_rng(0)
        f = fit_cylinder(pts, rng=rng, optics=BeamOptics(), diameter_range=nominal_diameter_range(d))
        assert f.extra["edge_mode_first"] == 0.0  # the energy-weighted family
        assert f.extra["footprint_beams"] > 1000
        return f.diameter - d, f.std_diameter

    err, u = fit()
    monkeypatch.setattr(fpmod, "REGATE_BAND", 0.0)
    err_band, u_band = fit()
    assert err_band > 3 * u_band  # the defect, still there with the thin fit's band (+8.9 mm, u 2.1)
    assert abs(err) < 2 * u  # +1.1 mm


def _fit_saved_sweep(path: Path) -> CylinderFit:
    """A saved coverage sweep (its "roi" cloud and the bench's fit seed) fitted as the bench fits it:
    the LMS1xx footprint, seed 003's nominal diameter range."""
    from lrms.covariance import NoiseModel

    z = np.load(path)
    return fit_cylinder(
        np.asarray(z["points"], dtype=np.float64),
        noise=NoiseModel(),
        rng=np.random.default_rng(int(z["fit_seed"])),
        optics=BeamOptics(),
        diameter_range=nominal_diameter_range(SEED003_DIAMETER),
    )


#: Sweep 8 (0-based) of the bench's seed-11 stream, 10 % energy-weighted echoes: ``PYTHONPATH=.
#: python -m bench.bench_sensor_model --only seed003 --clouds roi --fit footprint --no-offset
#: --no-ideal --edges 0.1:weighted --seed 11 --sweeps 9 --sweep-list 8 --dump DIR`` on the
#: 128-sub-ray ray cast of ``seed003-room`` (137.5 mm part at 2.53 m): the whole "roi" cloud (5197
#: points, stored as float32) and the bench's fit seed for that sweep.
SUBSAMPLE_BASIN = Path(__file__).resolve().parents[1] / "data" / "cylinder" / "room-sweep-seed11-w10-008-roi.npz"


def test_the_energy_weighted_family_is_refined_from_the_thin_beam_not_from_its_subsample(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On this sweep the energy-weighted family's solve on the 1000-beam subsample ends in another
    basin, 25 mm small; refined on all work beams from there (and gated about it) it stayed there
    (112.3 mm, u 3.2 mm, refused by the nominal check: 1 of 200 sweeps of the coverage run). Refined
    from the thin beam's solution the family finds the minimum of all beams: +7.0 mm, u 5.5 mm."""
    import lrms.cylinder.footprint as fpmod
    from lrms.cylinder import diameter_u
    from lrms.errors import NominalDiameterError

    def fit() -> CylinderFit:
        return _fit_saved_sweep(SUBSAMPLE_BASIN)

    f = fit()
    assert f.extra["edge_mode_first"] == 0.0  # the energy-weighted family
    assert abs(f.diameter - SEED003_DIAMETER) < 2 * diameter_u(f), (f.diameter, diameter_u(f))
    monkeypatch.setattr(fpmod, "WEIGHTED_FROM_THIN", False)
    with pytest.raises(NominalDiameterError, match=r"112\.\d mm"):
        fit()


#: Sweep 2 (0-based) of the bench's seed-11 stream, 10 % first-hit echoes: ``PYTHONPATH=. python -m
#: bench.bench_sensor_model --only seed003 --clouds roi --fit footprint --no-offset --no-ideal --edges
#: 0.1:first --seed 11 --sweeps 3 --sweep-list 2 --dump DIR`` on the 128-sub-ray ray cast of
#: ``seed003-room`` (137.5 mm part at 2.53 m): the whole "roi" cloud (5125 points, stored as float32)
#: and the bench's fit seed for that sweep.
PROFILE_LOWER = Path(__file__).resolve().parents[1] / "data" / "cylinder" / "room-sweep-seed11-f10-002-roi.npz"


def test_a_radius_profile_that_meets_a_lower_cost_restarts_the_first_hit_solve_from_there(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On this sweep the first hit's (radius, tau) ridge has another local minimum 6 mm smaller in
    the diameter, which the radius profile meets (a lower cost than the solution's); reported as it
    was, the diameter came out +5.3 mm (u 4.2 mm, the interval centred on the lower point). The fit
    now restarts the family's solve from the profile's lowest point and takes the profile again
    there: +3.3 mm, u 2.8 mm (measured)."""
    import lrms.cylinder.footprint as fpmod
    from lrms.cylinder import diameter_u

    def fit() -> CylinderFit:
        return _fit_saved_sweep(PROFILE_LOWER)

    f = fit()
    assert f.extra["edge_mode_first"] == 1.0 and f.extra["footprint_profile_restarts"] == 1.0
    assert -6e-3 < f.extra["footprint_profile_moved_m"] < -1e-3, f.extra["footprint_profile_moved_m"]
    err = f.diameter - SEED003_DIAMETER
    assert abs(err) < 2 * diameter_u(f), (err, diameter_u(f))
    from service.fitting import _footprint_json  # the result's JSON says so

    shown = _footprint_json(f.extra)
    assert shown["profile_restarts"] == 1 and shown["profile_moved_m"] == f.extra["footprint_profile_moved_m"]
    monkeypatch.setattr(fpmod, "PROFILE_RESTARTS", 0)
    before = fit()
    # the defect: the profile met a lower cost off the solution, and the solution was reported anyway
    assert before.extra["footprint_profile_lowest_m"] < -1e-3 and before.extra["footprint_profile_restarts"] == 0.0
    assert abs(err) < abs(before.diameter - SEED003_DIAMETER) - 1e-3
