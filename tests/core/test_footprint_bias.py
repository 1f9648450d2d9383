"""Box's second-order bias correction of the footprint fit (lrms/cylinder/footprint_bias.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lrms.budget import BEAM_SOURCES, BudgetRow, cylinder_budget
from lrms.cylinder import Cylinder, CylinderFit
from lrms.cylinder.footprint_bias import corrected, footprint_bias, second_order_bias
from lrms.errors import FitError


def _exp_problem(theta0: float, n: int, sigma: float) -> tuple[np.ndarray, object, np.ndarray, np.ndarray]:
    """``y_i = exp(theta) + e_i``: the least-squares estimate is ``log(mean y)``, whose bias to order
    ``sigma^2`` is ``-sigma^2 / (2 n exp(2 theta))`` (the delta method, in closed form)."""
    y = np.full(n, np.exp(theta0))  # noiseless data: the solution is theta0

    def res(th: np.ndarray) -> np.ndarray:
        return np.asarray((y - np.exp(th[0])) / sigma)

    jac = np.full((n, 1), -np.exp(theta0) / sigma)
    cov = np.array([[sigma**2 / (n * np.exp(2 * theta0))]])
    return np.array([theta0]), res, jac, cov


def test_box_bias_of_a_closed_form_estimate() -> None:
    theta, res, jac, cov = _exp_problem(0.3, 10, 0.1)
    b = second_order_bias(res, theta, jac, cov)  # type: ignore[arg-type]
    exact = -(0.1**2) / (2 * 10 * np.exp(0.6))
    assert b[0] == pytest.approx(exact, rel=1e-3)
    # and by Monte Carlo: the mean of log(mean y) - theta over noise draws, less its linear term
    # (mean zero: a control variate that leaves the second-order part)
    rng = np.random.default_rng(1)
    e = rng.normal(0.0, 0.1, (200_000, 10)).mean(axis=1)
    est = np.log(np.exp(0.3) + e) - 0.3 - e / np.exp(0.3)
    assert est.mean() == pytest.approx(exact, rel=0.03)


def test_the_footprint_bias_is_twice_the_radius_term_with_its_rectangular_u() -> None:
    # a 5-parameter problem whose radius (index 4) enters through exp(): the diameter's bias is 2 b_r
    n, sigma = 20, 0.05

    def res(th: np.ndarray) -> np.ndarray:
        return np.asarray(np.concatenate([-th[:4] / sigma, (np.exp(0.1) - np.exp(th[4])) * np.ones(n) / sigma]))

    jac = np.zeros((n + 4, 5))
    jac[:4, :4] = -np.eye(4) / sigma
    jac[4:, 4] = -np.exp(0.1) / sigma
    theta = np.array([0.0, 0.0, 0.0, 0.0, 0.1])
    cov = np.linalg.inv(jac.T @ jac)
    fb = footprint_bias(res, theta, jac, cov)
    exact = -(sigma**2) / (2 * n * np.exp(0.2))
    assert fb.theta[4] == pytest.approx(exact, rel=1e-3) and np.allclose(fb.theta[:4], 0.0, atol=1e-12)
    assert fb.diameter_m == pytest.approx(2 * exact, rel=1e-3)
    assert fb.u_m == pytest.approx(abs(fb.diameter_m) / np.sqrt(3.0))
    th, extra = corrected("weighted", theta, res, jac, cov)
    assert th[4] == pytest.approx(0.1 - fb.theta[4], rel=1e-12) and th[4] == pytest.approx(0.1 - exact, rel=1e-5)
    assert extra == {"bias_correction_diameter_m": fb.diameter_m, "footprint_bias_u_m": fb.u_m}
    same, none = corrected("thin", theta, res, jac, cov)
    assert np.array_equal(same, theta) and none == {}


def test_bad_shapes_are_clear_errors() -> None:
    theta, res, jac, cov = _exp_problem(0.0, 5, 0.1)
    with pytest.raises(FitError):
        second_order_bias(res, theta, jac, np.eye(2))  # type: ignore[arg-type]
    with pytest.raises(FitError):
        second_order_bias(res, theta, jac[:3], cov)  # type: ignore[arg-type]
    with pytest.raises(FitError):
        second_order_bias(res, theta, jac, np.full((1, 1), np.nan))  # type: ignore[arg-type]


def test_the_correction_has_its_own_budget_row_drawn_as_a_diameter_error() -> None:
    cyl = Cylinder(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.07)
    fit = CylinderFit(
        cylinder=cyl, inliers=np.arange(10), rmse=0.01, covariance=np.eye(5) * 1e-8,
        frame=(np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])), chi2_dof=1.0, sigma_scale=1.0,
        line_of_sight=False, extra={},
    )  # fmt: skip
    row = cylinder_budget(fit).row("footprint bias correction")
    assert row.u_m == 0.0 and row.distribution == "not evaluated"
    fp = dataclasses.replace(fit, extra={"bias_correction_diameter_m": 3e-4, "footprint_bias_u_m": 1.7e-4})
    b = cylinder_budget(fp)
    row = b.row("footprint bias correction")
    assert isinstance(row, BudgetRow) and row.u_m == pytest.approx(1.7e-4) and "+0.300 mm" in row.note
    u = np.array([r.u_m for r in b.rows])
    assert b.combined == pytest.approx(float(np.sqrt(np.sum(u * u))), rel=1e-12)
    assert "footprint bias correction" not in BEAM_SOURCES


def test_the_monte_carlo_of_a_footprint_fit_is_not_shifted_by_its_correction() -> None:
    """The Monte Carlo's replicas are thin-beam refits: they carry the thin beam's bias, not the
    footprint model's, so a footprint fit's correction (stored where the thin beam's is) must not
    move their interval (it moved it by -b, 0.2-0.26 mm on the service sweeps)."""
    from bench import seed003_reproduction as seed
    from lrms.covariance import NoiseModel
    from lrms.cylinder import refine_cylinder
    from lrms.uncertainty import monte_carlo_interval

    nm, r = NoiseModel(), 0.06875
    pts, rays = seed.noisy_scan(
        seed.sweep_points(radius=r, step_alpha_deg=1.0, step_beta_deg=1.0), nm, np.random.default_rng(2)
    )
    fit = refine_cylinder(pts, seed.seed_cylinder(r), rays=rays, gate=np.inf, max_rounds=1)
    extra = {"bias_correction_diameter_m": 3e-4, "footprint_bias_u_m": 1.7e-4, "edge_mode_first": 1.0}

    def mc(f: CylinderFit) -> tuple[float, float]:
        m = monte_carlo_interval(f, rays, noise=nm, n=50, rng=np.random.default_rng(3), p=seed.P)
        return m.low, m.high

    assert mc(dataclasses.replace(fit, extra=extra)) == pytest.approx(mc(fit), abs=1e-12)
    # a thin-beam correction under the same key still shifts them
    thin = mc(dataclasses.replace(fit, extra={"bias_correction_diameter_m": 3e-4}))
    assert thin == pytest.approx(tuple(v - 3e-4 for v in mc(fit)), abs=1e-12)
