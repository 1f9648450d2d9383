"""Diameter uncertainty: critical point (Eq. 8-12), GUM, Monte Carlo; coverage and the CRB."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench import seed003_reproduction as seed
from lrms.covariance import NoiseModel, covariances_of_points
from lrms.crb import cylinder_crb
from lrms.cylinder import Cylinder, _Frame, bias_corrected, fit_cylinder, rays_from_points, refine_cylinder
from lrms.errors import LrmsError
from lrms.uncertainty import (
    _replica_problem,
    batched_levenberg_marquardt,
    centripetal_radii,
    centripetal_radii_first_order,
    centripetal_radius_eq12,
    critical_point_interval,
    gum_interval,
    min_axis_distance,
    monte_carlo_interval,
)

NM = NoiseModel()
CYL = seed.seed_cylinder()


@pytest.mark.parametrize("k", [1.0, 2.0, 3.0])
def test_closed_form_matches_constrained_minimisation_of_eq12(k: float) -> None:
    pts = seed.visible_surface_points(9, 5)
    covs = covariances_of_points(pts, NM)
    exact = centripetal_radii(CYL, pts, covs, k)
    ref = np.array([centripetal_radius_eq12(CYL, x, c, k) for x, c in zip(pts, covs, strict=True)])
    np.testing.assert_allclose(exact, ref, atol=1e-9)
    # the tangent-plane formula over-estimates by at most ~ h^2 / (2 r), h = the ellipsoid's reach
    first = centripetal_radii_first_order(CYL, pts, covs, k)
    h = k * NM.sigma_l
    assert np.all(first >= exact - 1e-12)
    assert np.all(first - exact <= h * h / (2 * CYL.radius) + 1e-9)


def test_closed_form_on_a_tilted_axis_with_general_covariances() -> None:
    rng = np.random.default_rng(9)
    cyl = Cylinder(np.array([0.1, -0.2, 0.3]), np.array([0.2, -0.4, 1.0]), 0.2)
    e = cyl.point + rng.normal(size=(12, 3))
    e = cyl.point + cyl.radial(e) / cyl.axis_distance(e)[:, None] * 0.2 + 0.3 * rng.normal(size=(12, 1)) * cyl.direction
    a = rng.normal(size=(12, 3, 3)) * 0.01
    covs = a @ np.swapaxes(a, 1, 2) + 1e-6 * np.eye(3)
    for k in (0.5, 2.0):
        exact = centripetal_radii(cyl, e, covs, k)
        ref = np.array([centripetal_radius_eq12(cyl, x, c, k) for x, c in zip(e, covs, strict=True)])
        np.testing.assert_allclose(exact, ref, atol=1e-8)


def test_ellipsoid_containing_the_axis_reaches_it() -> None:
    cyl = Cylinder(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.01)
    x = np.array([[0.01, 0.0, 0.0]])
    cov = np.eye(3)[None] * 0.02**2
    assert min_axis_distance(cyl, x, cov, 1.0)[0] == 0.0
    assert centripetal_radii(cyl, x, cov, 1.0)[0] == pytest.approx(0.01)


def test_critical_point_interval_structure_and_fig7_data() -> None:
    pts = seed.visible_surface_points()
    assert pts.shape == (567, 3)
    ci = critical_point_interval(CYL, pts, noise=NM, k=1.0)
    radii = centripetal_radii(CYL, pts, covariances_of_points(pts, NM), 1.0)
    np.testing.assert_allclose(ci.radii, radii)
    assert ci.r_ce == pytest.approx(np.percentile(radii, 25, method="lower"))
    assert ci.radii[ci.critical_index] == ci.r_ce
    assert ci.d_min == pytest.approx(CYL.diameter - 2 * ci.r_ce) and ci.d_max == pytest.approx(
        CYL.diameter + 2 * ci.r_ce
    )
    # the centre beam sees the whole range noise: r_ce up to k sigma_l; the limbs almost none
    assert radii.max() == pytest.approx(NM.sigma_l, rel=0.01) and radii.min() < 0.15 * NM.sigma_l
    x, cdf = ci.cdf()
    assert np.all(np.diff(x) >= 0) and cdf[-1] == 1.0
    counts, edges = ci.histogram(20)
    assert counts.sum() == 567 and edges.size == 21
    # larger k reaches further, but less than proportionally: the surface curves away
    ci3 = critical_point_interval(CYL, pts, noise=NM, k=3.0)
    assert 2.0 * ci.half_width < ci3.half_width < 3.0 * ci.half_width
    with pytest.raises(LrmsError):
        critical_point_interval(CYL, pts, k=0.0)
    with pytest.raises(LrmsError):
        critical_point_interval(CYL)


def test_batched_solver_agrees_with_scipy_least_squares() -> None:
    truth = seed.visible_surface_points()
    rng = np.random.default_rng(12)
    reps = np.stack([seed.noisy_scan(truth, NM, rng)[0] for _ in range(4)])
    frame = _Frame.at(CYL)
    for los in (True, False):
        fun, jfun = _replica_problem(frame, reps, los, NM, seed.P)
        theta = batched_levenberg_marquardt(fun, jfun, np.zeros((4, 5)))
        for i in range(4):
            from lrms.cylinder import rays_from_points

            rays = rays_from_points(reps[i], seed.P, NM) if los else None
            ref = refine_cylinder(reps[i], CYL, rays=rays, sigma=1.0, gate=np.inf, max_rounds=1)
            assert 2 * (CYL.radius + theta[i, 4]) == pytest.approx(ref.diameter, abs=2e-6)


def test_coverage_of_the_three_intervals_on_the_seed_simulation() -> None:
    """Share of simulated scans whose interval holds the true diameter (binomial tolerance)."""
    truth = seed.visible_surface_points()
    rng = np.random.default_rng(2016)
    n_scans, n_mc = 200, 40
    in_a = in_b = in_c = 0
    d_fit = []
    for s in range(n_scans):
        pts, rays = seed.noisy_scan(truth, NM, rng)
        fit = fit_cylinder(pts, rays=rays, noise=NM, initial=CYL)
        d_fit.append(fit.diameter)
        own = critical_point_interval(fit.cylinder, rays=rays.subset(fit.inliers), noise=NM, k=1.0)
        in_a += own.d_min <= CYL.diameter <= own.d_max
        g = gum_interval(fit)
        in_b += g.low <= CYL.diameter <= g.high
        if s < n_mc:
            mc = monte_carlo_interval(fit, rays.subset(fit.inliers), noise=NM, n=100, rng=rng)
            in_c += mc.low <= CYL.diameter <= mc.high
    # (a) claims "almost all": it is ~14 fit standard deviations wide on this set-up
    assert in_a / n_scans >= 0.99
    # (b) and (c) claim 95 %: within 3.5 binomial sigma (c: 100 replicas add quantile noise)
    assert abs(in_b / n_scans - 0.9545) < 3.5 * np.sqrt(0.95 * 0.05 / n_scans)
    assert in_c / n_mc > 0.95 - 3.5 * np.sqrt(0.95 * 0.05 / n_mc)
    # the fit's spread agrees with its GUM uncertainty and with the Cramer-Rao bound
    spread = float(np.std(d_fit, ddof=1))
    rays = rays_from_points(truth, seed.P, NM)
    crb = cylinder_crb(CYL, rays.origins, rays.dirs, NM.sigma_l).std_diameter
    assert 0.85 * crb < spread < 1.25 * crb, (spread, crb)


def test_monte_carlo_interval_checks_its_arguments() -> None:
    truth = seed.visible_surface_points()
    pts, rays = seed.noisy_scan(truth, NM, np.random.default_rng(1))
    fit = fit_cylinder(pts, rays=rays, noise=NM, initial=CYL)
    with pytest.raises(LrmsError):
        monte_carlo_interval(fit, rays.subset(fit.inliers), n=5)
    with pytest.raises(LrmsError):
        monte_carlo_interval(fit, rays.subset(fit.inliers), coverage=1.5)
    mc = monte_carlo_interval(fit, rays.subset(fit.inliers), noise=NM, n=50, rng=np.random.default_rng(2))
    assert mc.low < fit.diameter < mc.high and mc.n_failed == 0
    assert mc.std == pytest.approx(fit.std_diameter, rel=0.4)


def test_monte_carlo_order_statistics_hold_a_further_draw_at_the_claimed_rate() -> None:
    from lrms.uncertainty import coverage_order_statistics

    rng = np.random.default_rng(5)
    draws = rng.normal(size=(20_000, 201))
    lo_hi = np.array([coverage_order_statistics(row[:200], 0.95) for row in draws])
    inside = np.mean((draws[:, 200] >= lo_hi[:, 0]) & (draws[:, 200] <= lo_hi[:, 1]))
    assert abs(inside - 191 / 201) < 4 * np.sqrt(0.95 * 0.05 / 20_000)  # 5th..196th of 200
    # plain 2.5 / 97.5 % quantiles fall short of 95 %
    q = np.quantile(draws[:, :200], [0.025, 0.975], axis=1)
    plain = np.mean((draws[:, 200] >= q[0]) & (draws[:, 200] <= q[1]))
    assert plain < 0.95 - 3 * np.sqrt(0.95 * 0.05 / 20_000)
    with pytest.raises(LrmsError):
        coverage_order_statistics(np.arange(20.0), 0.95)


def test_angular_noise_changes_the_bound_of_a_ray_cast_sweep_by_well_under_one_percent() -> None:
    """docs/cylinder.md section 4: the range-only Cramer-Rao bound is not what makes the fit look
    inefficient. Adding each beam's angular terms (dt/dalpha sigma_alpha, dt/dbeta sigma_beta, by
    finite differences of the hit range) as per-beam range sigmas raises the bound, but by < 1 %."""
    from lrms import kinematics

    rng = np.random.default_rng(5)
    _, part, pr = seed.lrms_sweep(rng, clutter=0.0, scene_name="seed003-bare", crop=False)
    _, a, b = kinematics.inverse(pr.points(), seed.P)
    t0, gap = part.ray_range(*kinematics.beam_rays(a, b, seed.P))
    assert np.count_nonzero(gap > 0) <= 2  # the recovered nominal beams meet the true part
    eps = 1e-6
    ta, _ = part.ray_range(*kinematics.beam_rays(a + eps, b, seed.P))
    tb, _ = part.ray_range(*kinematics.beam_rays(a, b + eps, seed.P))
    ang = np.hypot((ta - t0) / eps * NM.sigma_alpha, (tb - t0) / eps * NM.sigma_beta)
    hit = gap <= 0
    ang = np.where(hit, ang, 0.0)
    assert 1e-4 < float(ang.max()) < 0.5 * NM.sigma_l  # grazing beams: mm, not negligible per beam
    plain = cylinder_crb(part, pr.origins, pr.dirs, NM.sigma_l).std_diameter
    full = cylinder_crb(part, pr.origins, pr.dirs, np.sqrt(NM.sigma_l**2 + ang**2)).std_diameter
    assert plain < full < 1.01 * plain


def test_monte_carlo_replicas_of_a_bias_corrected_fit_are_centred_on_it() -> None:
    """The replicas are plain fits from the fitted cylinder, so they carry the silhouette's upward
    bias; for a corrected fit they take the same correction and centre on the fit again. A coarse
    grid (1 deg, 438 beams) makes the bias large against the replicas' standard error."""
    r = 0.06875
    truth = seed.sweep_points(radius=r, step_alpha_deg=1.0, step_beta_deg=1.0)
    pts, rays = seed.noisy_scan(truth, NM, np.random.default_rng(2))
    fit = bias_corrected(refine_cylinder(pts, seed.seed_cylinder(r), rays=rays, gate=np.inf, max_rounds=1), rays)
    shift = fit.extra["bias_correction_diameter_m"]
    mc = monte_carlo_interval(fit, rays, noise=NM, n=400, rng=np.random.default_rng(3), p=seed.P)
    raw = monte_carlo_interval(
        dataclasses.replace(fit, extra={}), rays, noise=NM, n=400, rng=np.random.default_rng(3), p=seed.P
    )
    se = mc.std / np.sqrt(mc.diameters.size)
    assert shift > 4 * se  # large enough that a missing or doubled shift would show
    assert abs(float(np.mean(mc.diameters)) - fit.diameter) < 3 * se
    assert mc.low == pytest.approx(raw.low - shift) and mc.high == pytest.approx(raw.high - shift)
