"""Cylinder detection and the line-of-sight fit (seed 003 geometry)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bench import seed003_reproduction as seed
from lrms.covariance import NoiseModel
from lrms.cylinder import (
    TOP_BIN,
    Cylinder,
    DetectOptions,
    _Frame,
    _top_height,
    bias_corrected,
    central_jacobian,
    estimate_normals,
    fit_cylinder,
    grazing_sigmas,
    grazing_weighted_fit,
    incidence_cosines,
    los_jacobian,
    los_residuals,
    orthogonal_jacobian,
    orthogonal_residuals,
    rays_from_points,
    refine_cylinder,
    second_order_bias,
    support_plane,
)
from lrms.errors import FitError

NM = NoiseModel()


def test_ray_range_hits_misses_and_gap() -> None:
    cyl = Cylinder(np.array([0.0, 2.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.1)
    o = np.zeros((3, 3))
    d = np.array([[0.0, 1.0, 0.0], [np.sin(0.2), np.cos(0.2), 0.0], [0.05, 1.0, 0.3]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, gap = cyl.ray_range(o, d)
    assert t[0] == pytest.approx(1.9) and gap[0] == 0
    # beam at 0.2 rad passes 2 sin(0.2) = 0.397 m from the axis: a miss by 0.297 m
    assert gap[1] == pytest.approx(2.0 * np.sin(0.2) - 0.1)
    assert t[1] == pytest.approx(2.0 * np.cos(0.2))
    x = o[2] + t[2] * d[2]
    assert cyl.axis_distance(x[None])[0] == pytest.approx(0.1) and gap[2] == 0


def test_analytic_jacobians_match_central_differences() -> None:
    truth = seed.sweep_points(radius=0.06875, step_beta_deg=1.0)
    pts, rays = seed.noisy_scan(truth, NM, np.random.default_rng(4))
    start = seed.seed_cylinder(0.06875)
    frame = _Frame.at(Cylinder(start.point + np.array([0.002, -0.003, 0.0]), np.array([0.01, 0.02, 1.0]), 0.066))
    th = np.array([0.003, -0.002, 0.001, 0.0005, 0.001])
    args = (rays.origins, rays.dirs, rays.ranges, rays.sigma_l, rays.sigma_perp)
    res = los_residuals(th, frame, *args)
    n = res.size // 2
    ja = los_jacobian(th, frame, rays.origins, rays.dirs, rays.sigma_l, rays.sigma_perp)
    jn = central_jacobian(lambda t: los_residuals(t, frame, *args), th)
    assert ja.shape == jn.shape == (2 * n, 5)
    # away from the silhouette (where dt/dtheta is unbounded) central differences are accurate
    t, gap = frame.cylinder(th).ray_range(rays.origins, rays.dirs)
    x = rays.origins + t[:, None] * rays.dirs
    rad = frame.cylinder(th).radial(x)
    cos_inc = np.abs(np.sum(rad * rays.dirs, axis=1)) / np.linalg.norm(rad, axis=1)
    rows = np.flatnonzero((gap == 0) & (cos_inc > 0.2))
    assert rows.size > 0.8 * n
    np.testing.assert_allclose(ja[rows], jn[rows], rtol=1e-4, atol=1e-3)
    miss = np.flatnonzero(gap > 0)
    assert miss.size > 0
    np.testing.assert_allclose(ja[n + miss], jn[n + miss], rtol=1e-4, atol=1e-3)
    jo = orthogonal_jacobian(th, frame, pts, np.asarray(0.01))
    jc = central_jacobian(lambda t: orthogonal_residuals(t, frame, pts, np.asarray(0.01)), th)
    np.testing.assert_allclose(np.asarray(jo, dtype=float), np.asarray(jc, dtype=float), atol=1e-4)


def test_normals_of_a_clean_cylinder_are_radial() -> None:
    cyl = seed.seed_cylinder()
    pts = seed.visible_surface_points(41, 41)
    n = estimate_normals(pts, k=12)
    rad = cyl.radial(pts)
    cosang = np.abs(np.sum(n * rad, axis=1)) / np.linalg.norm(rad, axis=1)
    assert np.median(cosang) > 0.999


def test_line_of_sight_fit_is_unbiased_orthogonal_fit_is_not() -> None:
    """The issue's numbers: on the seed's set-up with a 137.5 mm part (full sweep), the
    orthogonal-distance fit is biased by about -9.6 mm, the line-of-sight fit by < 0.1 mm."""
    r = 0.1375 / 2
    truth = seed.sweep_points(radius=r, step_beta_deg=0.6)
    cyl = seed.seed_cylinder(r)
    rng = np.random.default_rng(2024)
    d_los, d_orth, sd = [], [], []
    for _ in range(25):
        pts, rays = seed.noisy_scan(truth, NM, rng)
        f = fit_cylinder(pts, rays=rays, noise=NM, initial=cyl)
        o = fit_cylinder(pts, line_of_sight=False, noise=NM, initial=cyl)
        d_los.append(f.diameter)
        d_orth.append(o.diameter)
        sd.append(f.std_diameter)
    err_los = np.mean(d_los) - 2 * r
    err_orth = np.mean(d_orth) - 2 * r
    se = np.std(d_los, ddof=1) / np.sqrt(len(d_los))
    assert abs(err_los) < max(4 * se, 1e-4), (err_los, se)
    assert -0.0115 < err_orth < -0.0075, err_orth


def test_detects_part_on_table_with_clutter_from_a_ray_cast_sweep() -> None:
    rng = np.random.default_rng(8)
    pts, truth, _ = seed.lrms_sweep(rng, clutter=0.1)
    fit = fit_cylinder(pts, noise=NM, rng=rng)
    assert abs(fit.diameter - truth.diameter) < 4 * fit.std_diameter + 2e-4
    assert abs(float(fit.cylinder.direction @ truth.direction)) > np.cos(np.deg2rad(1.0))
    assert truth.axis_distance(fit.cylinder.point[None])[0] < 0.005
    assert fit.plane is not None and fit.base_point is not None
    np.testing.assert_allclose(fit.base_point, truth.point, atol=0.01)  # C0 on the table top
    on = np.abs(truth.surface_distance(pts)) < 0.05
    assert on[fit.inliers].mean() > 0.98
    assert 0.8 < fit.chi2_dof < 1.3
    assert fit.covariance.shape == (5, 5) and np.all(np.linalg.eigvalsh(fit.covariance) > 0)


def test_isotropic_mode_on_isotropic_noise_is_unbiased() -> None:
    rng = np.random.default_rng(5)
    cyl = Cylinder(np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.1, 1.0]), 0.25)
    e1 = np.cross(cyl.direction, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(cyl.direction, e1)
    th = rng.uniform(0, 2 * np.pi, 3000)
    h = rng.uniform(-0.5, 0.5, 3000)
    pts = cyl.point + h[:, None] * cyl.direction + 0.25 * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
    pts += rng.normal(0, 0.002, pts.shape)
    fit = fit_cylinder(pts, line_of_sight=False, rng=rng)
    assert fit.diameter == pytest.approx(0.5, abs=4 * fit.std_diameter)
    assert fit.rmse == pytest.approx(0.002, rel=0.1)
    assert abs(float(fit.cylinder.direction @ cyl.direction)) > 0.9999


def test_bad_input_raises_fit_error() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(FitError):
        fit_cylinder(np.zeros((5, 3)))
    with pytest.raises(FitError):
        fit_cylinder(np.zeros((100, 2)))
    bad = rng.normal(size=(100, 3))
    bad[3, 1] = np.nan
    with pytest.raises(FitError):
        fit_cylinder(bad)
    # a flat wall: no cylinder in the allowed radius range
    wall = np.column_stack([rng.uniform(-1, 1, 3000), np.full(3000, 3.0), rng.uniform(-1, 1, 3000)])
    wall[:, 1] += rng.normal(0, 0.002, 3000)
    with pytest.raises(FitError):
        fit_cylinder(wall, rng=rng)
    # rays that do not match the points
    with pytest.raises(FitError):
        fit_cylinder(wall, rays=rays_from_points(wall[:10]))


def test_support_plane_is_at_the_end_of_the_part_not_through_a_dense_band_of_it() -> None:
    """A rough candidate (axis 60 mm off, radius 128 mm) leaves the sides of the part off its
    surface; a dense band of those at mid-height (the rig samples its own height densely) must
    not pass for the table the part stands on."""
    rng = np.random.default_rng(4)
    part = Cylinder(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.07)
    phi = rng.uniform(-np.pi, 0.0, 11000)  # the half facing the rig (-y)
    z = np.concatenate([rng.uniform(0.0, 0.8, 3000), rng.uniform(0.39, 0.41, 8000)])
    side = np.column_stack([0.07 * np.cos(phi), 0.07 * np.sin(phi), z])
    rad, ang = np.sqrt(rng.uniform(0.1**2, 0.5**2, 500)), rng.uniform(-np.pi, 0.0, 500)
    table = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), rng.normal(0.0, 5e-4, 500)])
    pts = np.vstack([side, table])
    rough = Cylinder(np.array([0.0, 0.06, 0.4]), part.direction, 0.128)
    opt = DetectOptions(plane_min_share=0.02)
    # the band outnumbers the table among the points off the rough candidate
    off = np.abs(rough.surface_distance(pts)) > opt.threshold
    assert np.count_nonzero(off & (np.abs(pts[:, 2] - 0.4) < 0.02)) > np.count_nonzero(off & (pts[:, 2] < 0.02))
    plane = support_plane(pts, rough, opt)
    assert plane is not None
    normal, offset = plane
    assert abs(normal[2]) > 0.999 and abs(offset) < 0.002


def test_fit_keeps_the_parts_bottom_and_drops_the_table_and_what_lies_above_the_top() -> None:
    """The part's beams are selected by the fitted scene model (table under the part, part's top
    from the inlier density), not by cutting a 20 mm slab at the table."""
    rng = np.random.default_rng(12)
    pts, truth, part_rays = seed.lrms_sweep(rng, clutter=0.1, scene_name="seed003-bare")
    fit = fit_cylinder(pts, noise=NM, rng=rng)
    assert fit.base_point is not None
    np.testing.assert_allclose(fit.base_point, truth.point, atol=1e-3)  # C0 on the table top
    inl = pts[fit.inliers]
    height = inl[:, 2] - truth.point[2]
    echoes = part_rays.points()
    low = echoes[:, 2] - truth.point[2] < 0.02
    assert np.count_nonzero(low) > 50
    kept_low = np.count_nonzero((height < 0.02) & (np.abs(truth.surface_distance(inl)) < 0.05))
    assert kept_low > 0.9 * np.count_nonzero(low)  # the old slab cut kept none of them
    not_part = cKDTree(echoes).query(inl)[0] > 1e-9
    assert not np.any(not_part & (np.abs(height) < 3e-3))  # no table echo in front of the base
    assert height.max() < 0.8 + 0.05  # the part is 0.8 m high: nothing far above its top


def test_top_height_from_the_inlier_density() -> None:
    rng = np.random.default_rng(0)
    dense = rng.uniform(0.0, 0.6, 3000)
    sparse = rng.uniform(0.0, 1.0, 10)
    h = np.concatenate([dense, sparse])
    top = _top_height(h, h)
    assert 0.6 <= top <= 0.6 + 3 * TOP_BIN
    assert _top_height(dense, dense) == pytest.approx(dense.max())  # top not in view: nothing cut


def test_grazing_weights_and_the_weighted_fit_on_exact_data() -> None:
    """The weights grow with tan(incidence); on noise-free beams the weighted fit is exact, and
    its (sandwich) covariance is no smaller than the plain maximum-likelihood one (Gauss-Markov)."""
    cyl = seed.seed_cylinder(0.06875)
    truth = seed.sweep_points(radius=0.06875, step_beta_deg=1.0)
    rays = rays_from_points(truth, seed.P, NM)
    cos_i = incidence_cosines(cyl, rays)
    sig = grazing_sigmas(cyl, rays, 5e-4)
    head_on = int(np.argmax(cos_i))
    grazing = int(np.argmin(cos_i))
    assert cos_i[head_on] > 0.99 and cos_i[grazing] < 0.05
    assert sig[head_on] == pytest.approx(NM.sigma_l, rel=1e-3)
    tan = np.sqrt(1 - cos_i[grazing] ** 2) / cos_i[grazing]
    assert sig[grazing] == pytest.approx(np.hypot(NM.sigma_l, 5e-4 * tan), rel=1e-9)
    order = np.argsort(cos_i)
    assert np.all(np.diff(sig[order]) <= 1e-12)  # more grazing, larger sigma
    plain = fit_cylinder(truth, rays=rays, noise=NM, initial=cyl, options=DetectOptions(grazing_sigma=0.0))
    assert grazing_weighted_fit(truth, rays, plain, sigma_lat=0.0) is plain
    weighted = grazing_weighted_fit(truth, rays, plain, sigma_lat=5e-4)
    assert weighted.diameter == pytest.approx(cyl.diameter, abs=1e-7)
    assert weighted.chi2_dof < 1e-6
    assert weighted.std_diameter >= plain.std_diameter * (1 - 1e-6)
    assert weighted.std_diameter < 1.5 * plain.std_diameter


def test_second_order_bias_predicts_the_fits_monte_carlo_bias() -> None:
    """The line-of-sight ML fit is biased upward by the silhouette beams' curvature; the predicted
    second-order bias matches a Monte Carlo of the fit, and subtracting it leaves no bias. A coarse
    beam grid (1 deg, 438 beams) makes the bias large against its standard error."""
    r = 0.06875
    truth = seed.sweep_points(radius=r, step_alpha_deg=1.0, step_beta_deg=1.0)
    cyl = seed.seed_cylinder(r)
    rng = np.random.default_rng(11)
    raw, pred, corrected = [], [], []
    for _ in range(250):
        pts, rays = seed.noisy_scan(truth, NM, rng)
        fit = refine_cylinder(pts, cyl, rays=rays, gate=np.inf, max_rounds=1)
        b = second_order_bias(fit, rays)
        raw.append(fit.diameter - cyl.diameter)
        pred.append(2 * b[4])
        corrected.append(bias_corrected(fit, rays).diameter - cyl.diameter)
    se = np.std(raw, ddof=1) / np.sqrt(len(raw))
    assert np.mean(raw) > 3 * se  # the bias is real
    assert abs(np.mean(pred) - np.mean(raw)) < 3 * se  # and predicted
    se_c = np.std(corrected, ddof=1) / np.sqrt(len(corrected))
    assert abs(np.mean(corrected)) < 3 * se_c  # and removed
    np.testing.assert_allclose(np.asarray(raw) - np.asarray(corrected), pred, rtol=1e-9)


def test_fit_cylinder_subtracts_and_records_the_bias_correction() -> None:
    pts, truth, _ = seed.lrms_sweep(np.random.default_rng(21), clutter=0.1)
    on = fit_cylinder(pts, noise=NM, rng=np.random.default_rng(5))
    off = fit_cylinder(pts, noise=NM, rng=np.random.default_rng(5), options=DetectOptions(bias_correction=False))
    np.testing.assert_array_equal(on.inliers, off.inliers)
    shift = on.extra["bias_correction_diameter_m"]
    assert "bias_correction_diameter_m" not in off.extra
    assert on.diameter == pytest.approx(off.diameter - shift, abs=1e-12)
    assert 0 < shift < 0.5 * on.std_diameter  # upward, and small against the uncertainty
    assert on.extra["grazing_sigma_m"] > 0  # the default fit is the weighted one
    assert abs(on.diameter - truth.diameter) < 4 * on.std_diameter
    iso = fit_cylinder(pts, line_of_sight=False, noise=NM, rng=np.random.default_rng(5))
    with pytest.raises(FitError, match="line-of-sight"):
        second_order_bias(iso, rays_from_points(pts[iso.inliers], seed.P, NM))
    with pytest.raises(FitError, match="one beam per inlier"):
        second_order_bias(on, rays_from_points(pts, seed.P, NM))
