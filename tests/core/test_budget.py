"""The GUM budget (lrms.budget): rows, quadrature, sensitivities against refits, the calibration
hook, Monte Carlo with the systematic effects drawn, and bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench import seed003_reproduction as seed
from lrms import kinematics
from lrms.budget import (
    BEAM_SOURCES,
    SOURCES,
    BeamGeometry,
    Budget,
    BudgetRow,
    CalibrationInput,
    SensorErrors,
    cylinder_budget,
    replica_systematics,
    scan_groups,
)
from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics, Cylinder, CylinderFit, Rays, _Frame, fit_cylinder
from lrms.errors import LrmsError
from lrms.uncertainty import _replica_fit, _replica_problem, ideal_points, monte_carlo_interval

NM = NoiseModel()
SPEED = float(np.deg2rad(15.0))


@pytest.fixture(scope="module")
def sweep_fit() -> tuple[CylinderFit, np.ndarray, Rays, BeamGeometry]:
    """A full sweep of seed 003's part (5942 beams), fitted from the truth as the bench does."""
    truth = seed.sweep_points(step_beta_deg=0.6)
    pts, rays = seed.noisy_scan(truth, NM, np.random.default_rng(1))
    fit = fit_cylinder(pts, rays=rays, noise=NM, initial=seed.seed_cylinder())
    _, a, b = kinematics.inverse(pts, seed.P)
    return fit, pts, rays, BeamGeometry(a, b, seed.P, SPEED)


def _budget(sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry], **kw: object) -> Budget:
    fit, _, rays, beams = sweep_fit
    return cylinder_budget(fit, rays.subset(fit.inliers), beams.subset(fit.inliers), noise=NM, **kw)  # type: ignore[arg-type]


def test_rows_sum_in_quadrature_and_u_is_k_times_u_c(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    b = _budget(sweep_fit)
    assert tuple(r.source for r in b.rows) == SOURCES
    u = np.array([r.u_m for r in b.rows])
    assert b.combined == pytest.approx(float(np.sqrt(np.sum(u * u))), rel=1e-12)
    assert b.k == 2.0 and b.expanded == pytest.approx(2.0 * b.combined, rel=1e-12)
    for r in b.rows:
        assert r.u_m == pytest.approx(abs(r.c) * r.u_x, rel=1e-12, abs=1e-18)
        assert r.type == ("A" if r.source == "fit (type A)" else "B")
    fit = sweep_fit[0]
    assert b.row("fit (type A)").u_m == pytest.approx(fit.std_diameter)
    # an uncalibrated LMS1xx: the +-30 mm systematic range error (rectangular, 17.3 mm) dominates
    off = b.row("range offset")
    assert off.u_x == pytest.approx(0.030 / np.sqrt(3)) and off.distribution == "rectangular"
    assert off.u_m > 3 * b.row("fit (type A)").u_m
    d = b.to_dict()
    assert set(d) == {"budget", "combined_m", "expanded_m", "k", "correlation"}
    assert set(d["budget"][0]) == {"source", "type", "u_x", "unit", "c", "u_m", "distribution", "note"}
    assert Budget(b.rows, k=3.0).expanded == pytest.approx(3 * b.combined)
    # no edge model in this fit: the row is there, marked not evaluated
    edge = b.row("footprint / edge model")
    assert edge.u_m == 0 and edge.distribution == "not evaluated" and "no edge model" in edge.note


def test_a_footprint_fit_carries_the_edge_family_row(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    """With a footprint fit (lrms.cylinder.footprint) the model choice among the edge families has
    its own row, fit.extra["edge_family_u_m"] (the families' diameters about the reported one,
    Akaike-weighted), beside the spot-size row; the rows still sum in quadrature and both are drawn
    as diameter contributions by the Monte Carlo replicas. Without it the row is "not evaluated"."""
    _, pts, rays, beams = sweep_fit
    thin_row = _budget(sweep_fit).row("edge family (model choice)")
    assert thin_row.u_m == 0 and thin_row.distribution == "not evaluated"
    fp = fit_cylinder(pts, rays=rays, noise=NM, initial=seed.seed_cylinder(), optics=BeamOptics())
    assert "edge_family_u_m" in fp.extra
    b = cylinder_budget(fp, rays.subset(fp.inliers), beams.subset(fp.inliers), noise=NM)
    assert tuple(r.source for r in b.rows) == SOURCES
    fam = b.row("edge family (model choice)")
    assert fam.u_m == pytest.approx(fp.extra["edge_family_u_m"], rel=1e-12, abs=1e-18)
    assert fam.distribution == "normal" and "Akaike" in fam.note
    u = np.array([r.u_m for r in b.rows])
    assert b.combined == pytest.approx(float(np.sqrt(np.sum(u * u))), rel=1e-12)
    assert "edge family (model choice)" not in BEAM_SOURCES
    # a non-zero model-choice u enters the combined value and the replicas' diameter-level draw
    wide = dataclasses.replace(fp, extra={**fp.extra, "edge_family_u_m": 3e-3})
    b2 = cylinder_budget(wide, rays.subset(fp.inliers), beams.subset(fp.inliers), noise=NM)
    assert b2.combined == pytest.approx(float(np.sqrt(b.combined**2 - fam.u_m**2 + 9e-6)), rel=1e-9)
    edge = b2.row("footprint / edge model").u_m
    assert b2.diameter_u_beyond(BEAM_SOURCES) == pytest.approx(float(np.hypot(edge, 3e-3)), rel=1e-9)


def _refit(fit: CylinderFit, rays: Rays) -> float:
    return fit_cylinder(rays.points(), rays=rays, noise=NM, initial=fit.cylinder).diameter


def test_range_offset_and_scale_sensitivities_match_finite_difference_refits(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    fit, _, rays, _ = sweep_fit
    b = _budget(sweep_fit)
    h = 0.01  # 10 mm on every range, the whole pipeline (multi-start, weights, bias correction) refitted
    up = _refit(fit, dataclasses.replace(rays, ranges=rays.ranges + h))
    down = _refit(fit, dataclasses.replace(rays, ranges=rays.ranges - h))
    c_fd = (up - down) / (2 * h)
    c = b.row("range offset").c
    assert c > 0.02  # a range offset scales the apparent size (divergence of the beams)
    assert c == pytest.approx(c_fd, rel=0.1)
    s = 2000e-6  # 2000 ppm
    up = _refit(fit, dataclasses.replace(rays, ranges=rays.ranges * (1 + s)))
    down = _refit(fit, dataclasses.replace(rays, ranges=rays.ranges * (1 - s)))
    assert b.row("range scale").c == pytest.approx((up - down) / (2 * s) * 1e-6, rel=0.1)


def test_angle_zero_sensitivities_match_refits_and_a_motor_zero_changes_nothing(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    fit, _, rays, beams = sweep_fit
    b = _budget(sweep_fit)
    l = rays.ranges

    def refit_angles(da: float, db: float) -> float:
        o, d = kinematics.beam_rays(beams.alpha + da, beams.beta + db, seed.P)
        c, s = np.cos(db), np.sin(db)
        turn = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])  # beta -> beta + db about the shaft (y)
        start = fit.cylinder
        # the start turns with the cloud: the multi-start's local minima (a few hundredths of a mm
        # apart) are then the same ones, and the diameter must agree to rounding
        start = Cylinder(turn @ start.point, turn @ start.direction, start.radius)
        rr = Rays(o, d, l, rays.sigma_l, rays.sigma_perp)
        return fit_cylinder(rr.points(), rays=rr, noise=NM, initial=start).diameter

    h = float(np.deg2rad(0.05))
    # the fit is told alpha + h where the echo came from alpha: an error of -h
    c_fd = -(refit_angles(h, 0) - refit_angles(-h, 0)) / (2 * h)
    assert abs(b.row("alpha zero").c) > 0.1
    assert b.row("alpha zero").c == pytest.approx(c_fd, rel=0.15)
    # a motor zero rotates the whole cloud about the shaft: the diameter does not move
    assert abs(refit_angles(0, h) - refit_angles(0, -h)) < 1e-9
    assert abs(b.row("beta zero").c) < 1e-4 * abs(b.row("alpha zero").c)


def test_scan_groups_recover_the_scans_of_a_sweep(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    truth = seed.sweep_points(step_beta_deg=0.6)
    _, _, b_true = kinematics.inverse(truth, seed.P)
    expected = np.unique(np.round(b_true, 9), return_inverse=True)[1]
    _, _, b_noisy = kinematics.inverse(seed.noisy_scan(truth, NM, np.random.default_rng(4))[0], seed.P)
    got = scan_groups(b_noisy)
    assert np.unique(got).size == np.unique(expected).size
    # the same partition (labels may differ)
    pairs = np.unique(np.stack([got, expected.reshape(-1)]), axis=1)
    assert pairs.shape[1] == np.unique(expected).size


def test_temperature_edge_model_and_extra_rows(sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry]) -> None:
    fit, _, rays, beams = sweep_fit
    err = SensorErrors(temperature_coeff_m_per_k=0.5e-3, temperature_u_k=4.0)
    edge_fit = dataclasses.replace(fit, extra={**fit.extra, "edge_model_u_m": 0.4e-3})
    extra = BudgetRow.of("ovality", "B", 0.3e-3, "m", 1.0, "rectangular", "form deviation")
    b = cylinder_budget(
        edge_fit, rays.subset(fit.inliers), beams.subset(fit.inliers), errors=err, noise=NM, extra_rows=[extra]
    )
    t = b.row("temperature drift")
    assert t.u_x == 4.0 and t.unit == "K"
    assert t.c == pytest.approx(0.5e-3 * b.row("range offset").c)
    assert b.row("footprint / edge model").u_m == pytest.approx(0.4e-3)
    assert "held at its nominal value" in b.row("footprint / edge model").note
    assert b.row("ovality").u_m == pytest.approx(0.3e-3)
    assert b.diameter_u_beyond(BEAM_SOURCES) == pytest.approx(float(np.hypot(0.4e-3, 0.3e-3)))
    # a spot size the footprint fit estimated: its uncertainty is in the fit's row, not carried again
    spot = {"edge_model_u_m": 0.0, "edge_spot_scale": 1.02, "edge_spot_scale_u": 0.04}
    spot_fit = dataclasses.replace(fit, extra={**fit.extra, **spot})
    row = cylinder_budget(spot_fit, rays.subset(fit.inliers), beams.subset(fit.inliers), noise=NM).row(
        "footprint / edge model"
    )
    assert row.u_m == 0.0 and "1.020 +- 0.040" in row.note and "type A" in row.note
    # the thin beam won the footprint fit's model choice: no spot in the fit, and the note says so
    won = dataclasses.replace(fit, extra={**fit.extra, "edge_model_u_m": 0.0, "edge_mode_first": -1.0})
    row = cylinder_budget(won, rays.subset(fit.inliers), beams.subset(fit.inliers), noise=NM).row(
        "footprint / edge model"
    )
    assert row.u_m == 0.0 and "thin beam won" in row.note and "nominal value" not in row.note


def test_calibration_row_keeps_correlations_and_replaces_the_uncalibrated_rows(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    b0 = _budget(sweep_fit)
    c = np.array([b0.row("range offset").c, b0.row("range scale").c])
    cov = np.array([[1e-6, -0.9 * 1e-3 * 50.0], [-0.9 * 1e-3 * 50.0, 50.0**2]])  # 1 mm, 50 ppm, rho -0.9
    cal = CalibrationInput(("k0", "k1"), cov, c, units=("m", "ppm"), replaces=("range offset", "range scale"))
    b = _budget(sweep_fit, calibration=cal)
    sources = [r.source for r in b.rows]
    assert "range offset" not in sources and "range scale" not in sources and sources[-1] == "calibration"
    assert b.row("calibration").u_m == pytest.approx(float(np.sqrt(c @ cov @ c)))
    assert b.row("calibration").u_m < float(np.sqrt((c**2) @ np.diag(cov)))  # the negative correlation helps
    with pytest.raises(LrmsError, match="positive semi-definite"):
        CalibrationInput(("k0", "k1"), np.array([[1.0, 2.0], [2.0, 1.0]]), c)
    with pytest.raises(LrmsError, match="2 x 2"):
        CalibrationInput(("k0", "k1"), np.eye(3), c)
    # the Monte Carlo replicas no longer draw what the calibration replaced
    fit, _, _, beams = sweep_fit
    sysm = replica_systematics(b, SensorErrors(), beams.subset(fit.inliers))
    assert sysm.errors.range_offset_u_m == 0 and sysm.errors.range_scale_u_ppm == 0
    assert sysm.diameter_u_m == pytest.approx(b.row("calibration").u_m)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"range_offset_u_m": -0.01}, "range_offset_u_m must be a finite standard uncertainty >= 0"),
        ({"timing_jitter_u_s": float("nan")}, "timing_jitter_u_s"),
        ({"range_offset_distribution": "triangular"}, "range_offset_distribution must be one of"),
        ({"temperature_coeff_m_per_k": float("inf")}, "temperature_coeff_m_per_k must be finite"),
    ],
)
def test_bad_inputs_are_clear_errors(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(LrmsError, match=message):
        SensorErrors(**kwargs)  # type: ignore[arg-type]


def test_bad_budget_arguments() -> None:
    with pytest.raises(LrmsError, match="coverage factor"):
        Budget((), k=0.0)
    with pytest.raises(LrmsError, match="u_x"):
        BudgetRow.of("x", "B", -1.0, "m", 1.0, "normal")
    with pytest.raises(LrmsError, match="one scan index per beam"):
        BeamGeometry(np.zeros(3), np.zeros(3), 0.1, 0.1, np.zeros(2, dtype=np.intp))
    with pytest.raises(LrmsError, match="motor speed"):
        BeamGeometry(np.zeros(3), np.zeros(3), 0.1, -1.0)


def test_monte_carlo_draws_the_systematic_effects_and_agrees_with_the_budget() -> None:
    """On the seed's 567 points: replicas that draw an uncalibrated LMS1xx's effects spread as the
    budget's u_c says (GUM and GUM-S1 agree where the model is nearly linear)."""
    truth = seed.visible_surface_points()
    pts, rays = seed.noisy_scan(truth, NM, np.random.default_rng(5))
    fit = fit_cylinder(pts, rays=rays, noise=NM, initial=seed.seed_cylinder())
    _, a, b = kinematics.inverse(pts[fit.inliers], seed.P)
    beams = BeamGeometry(a, b, seed.P, SPEED, scan_groups(b))
    inl = rays.subset(fit.inliers)
    err = SensorErrors()
    budget = cylinder_budget(fit, inl, beams, errors=err, noise=NM)
    assert budget.combined > 2 * fit.std_diameter  # the systematic rows dominate
    sysm = replica_systematics(budget, err, beams)
    mc = monte_carlo_interval(fit, inl, noise=NM, n=300, rng=np.random.default_rng(6), p=seed.P, systematics=sysm)
    # std of 300 draws: standard error ~4 %; the linearised budget within 15 %
    assert mc.std == pytest.approx(budget.combined, rel=0.15)
    plain = monte_carlo_interval(fit, inl, noise=NM, n=100, rng=np.random.default_rng(6), p=seed.P)
    assert plain.std < 0.5 * mc.std
    # the replicas' diameter-level rows (edge model) are drawn too
    edge_fit = dataclasses.replace(fit, extra={**fit.extra, "edge_model_u_m": 5e-3})
    b2 = cylinder_budget(edge_fit, inl, beams, errors=SensorErrors.none(), noise=NM)
    s2 = replica_systematics(b2, SensorErrors.none(), beams)
    assert s2.diameter_u_m == pytest.approx(5e-3)
    mc2 = monte_carlo_interval(edge_fit, inl, noise=NM, n=200, rng=np.random.default_rng(7), p=seed.P, systematics=s2)
    assert mc2.std == pytest.approx(b2.combined, rel=0.2)


def test_replica_multistart_keeps_the_lowest_cost(
    sweep_fit: tuple[CylinderFit, np.ndarray, Rays, BeamGeometry],
) -> None:
    """The replicas' multi-start (as the fit's) ends at a cost no higher than the one solve from
    the truth, and lower on some replicas of a full sweep (the likelihood's local minima)."""
    fit, _, rays, _ = sweep_fit
    inl = rays.subset(fit.inliers)
    l0, a0, b0 = kinematics.inverse(ideal_points(fit.cylinder, inl), seed.P)
    rep = 24
    ln, an, bn = NM.perturb(*(np.broadcast_to(v, (rep, v.size)) for v in (l0, a0, b0)), np.random.default_rng(11))
    fun, jfun = _replica_problem(_Frame.at(fit.cylinder), kinematics.forward(ln, an, bn, seed.P), True, NM, seed.P)
    idx = np.arange(rep)

    def cost(th: np.ndarray) -> np.ndarray:
        r = fun(th, idx)
        return np.asarray(np.sum(r * r, axis=-1))

    one = _replica_fit(fun, jfun, rep, NM.sigma_l, 15, multistart=False)
    ms = _replica_fit(fun, jfun, rep, NM.sigma_l, 15, multistart=True)
    c1, c5 = cost(one), cost(ms)
    assert np.all(c5 <= c1 * (1 + 1e-12))
    assert np.count_nonzero(c5 < c1 - 1e-6) >= 1, c1 - c5
