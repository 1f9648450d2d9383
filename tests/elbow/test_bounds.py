"""Precision floors (lrms.elbow.bounds) against repeated fits, and the curvature bias correction.

Statistics used by the tolerances (each test uses fixed seeds, so it is deterministic; the bounds
say how unlikely a failure would be if the claim tested were true):

* Whitened errors ``e = L^-1 (x_hat - x)`` with ``L L^T`` the floor: if the fit attains the floor
  and is unbiased, the ``K u`` numbers ``e`` are independent N(0, 1), so ``mean(e^2)`` has mean 1
  and standard deviation ``sqrt(2 / (K u))`` (0.079 for K = 40, u = 8), and each component's mean
  over the K fits times ``sqrt(K)`` is N(0, 1). The tests allow 4 standard deviations.
* A bias is tested with the t statistic of the K errors: ``|mean| < 4 sd / sqrt(K)``.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrms.elbow import ElbowParams, condition, fit_elbow, metric_floors, parameter_floor
from lrms.elbow.bounds import sample_metrics
from lrms.elbow.gauss_helmert import curvature_offset, noise_from_residual_sd, rice_excess
from lrms.elbow.model import rotation_matrix
from lrms.errors import FitError
from sim.scene.joints import make_joint, random_pose


def _perturbed(t: ElbowParams) -> ElbowParams:
    return replace(
        t, center=t.center + 0.002, rot=rotation_matrix(0.01, -0.01, 0.01) @ t.rot, A=t.A * 1.03, D=t.D * 0.98
    )


def _internal_error(p: ElbowParams, t: ElbowParams) -> np.ndarray:
    """Error in the internal unknowns: centre, small rotation w (R_hat = exp(-[w]x) R), A, D."""
    w = -Rotation.from_matrix(p.rot @ t.rot.T).as_rotvec()
    return np.concatenate([p.center - t.center, w, [p.A - t.A, p.D - t.D]])


def test_floor_matches_the_spread_of_repeated_fits() -> None:
    """40 fits of one 5,000-point cloud of joint a (1 mm noise): the floor is the fits' covariance."""
    rng = np.random.default_rng(5)
    c, rot = random_pose(rng)
    j = make_joint("a", center=c, rot=rot, n_along=50, step_deg=3.6)
    sigma = 0.001
    cov = parameter_floor(j.points, j.truth, sigma)
    assert cov.shape == (8, 8)
    chol = np.linalg.cholesky(cov)
    k = 40
    white = np.array(
        [
            np.linalg.solve(
                chol,
                _internal_error(
                    fit_elbow(j.points + rng.normal(0.0, sigma, j.points.shape), _perturbed(j.truth)).params, j.truth
                ),
            )
            for _ in range(k)
        ]
    )
    tol = 4 * math.sqrt(2 / white.size)
    assert abs(float(np.mean(white**2)) - 1.0) < tol, np.mean(white**2)
    assert np.all(np.abs(white.mean(axis=0)) * math.sqrt(k) < 4.0), white.mean(axis=0) * math.sqrt(k)
    # the metrics' expected RMSE follow from the same covariance
    m = metric_floors(cov, j.truth)
    assert m.d_t == pytest.approx(math.sqrt(np.trace(cov[:3, :3]) / 3))
    assert m.d_ad == pytest.approx(math.sqrt((cov[6, 6] + cov[7, 7]) / 2))
    # single fits drawn from N(0, cov): their mean squared metrics are the floors squared
    # (20,000 draws: relative standard error of a mean square of 2-3 normals below 1 %)
    d_t, d_r, d_ad = sample_metrics(cov, j.truth, None, 20_000, np.random.default_rng(0))
    assert float(np.mean(d_t**2)) == pytest.approx(m.d_t**2, rel=0.04)
    assert float(np.mean(d_r**2)) == pytest.approx(m.d_r**2, rel=0.05)
    assert float(np.mean(d_ad**2)) == pytest.approx(m.d_ad**2, rel=0.05)


def test_floor_inputs() -> None:
    j = make_joint("b", n_along=30, step_deg=6.0)
    n = j.points.shape[0]
    a = parameter_floor(j.points, j.truth, 0.002)
    b = parameter_floor(j.points, j.truth, cov=np.full(n, 0.002**2))
    c = parameter_floor(j.points, j.truth, cov=np.broadcast_to(np.eye(3) * 0.002**2, (n, 3, 3)))
    atol = 1e-12 * float(np.max(np.abs(a)))
    np.testing.assert_allclose(a, b, rtol=1e-10, atol=atol)
    np.testing.assert_allclose(a, c, rtol=1e-10, atol=atol)
    # the floor scales with the noise variance; fixing A/D removes one unknown and cannot raise it
    np.testing.assert_allclose(parameter_floor(j.points, j.truth, 0.004), 4 * a, rtol=1e-10, atol=4 * atol)
    fixed = parameter_floor(j.points, j.truth, 0.002, ratio=1.5)
    assert fixed.shape == (7, 7)
    assert np.trace(fixed[:3, :3]) < np.trace(a[:3, :3])
    with pytest.raises(FitError, match="either sigma or cov"):
        parameter_floor(j.points, j.truth)
    with pytest.raises(FitError, match="either sigma or cov"):
        parameter_floor(j.points, j.truth, 0.001, cov=np.full(n, 1e-6))
    with pytest.raises(FitError, match="sigma must be"):
        parameter_floor(j.points, j.truth, -1.0)
    with pytest.raises(FitError, match="fixed ratio"):
        parameter_floor(j.points, j.truth, 0.001, ratio=1.0)
    with pytest.raises(FitError, match="shape"):
        parameter_floor(j.points[:, :2], j.truth, 0.001)


def test_rice_excess_and_its_inversion() -> None:
    rng = np.random.default_rng(0)
    r = 0.1
    for sigma in (0.001, 0.02, 0.08, 0.3):
        x = rng.normal(0.0, sigma, (2, 400_000))
        s = np.hypot(r + x[0], x[1])
        # Monte Carlo standard error of the mean of s is about sigma / sqrt(400000)
        assert float(rice_excess(r, sigma)) == pytest.approx(float(s.mean()) - r, abs=5 * sigma / math.sqrt(4e5))
        assert noise_from_residual_sd(float(s.std()), r) == pytest.approx(sigma, rel=0.01)
    assert float(rice_excess(r, 1e-6)) == pytest.approx(1e-12 / (2 * r), rel=1e-9)


@pytest.mark.parametrize("name", ["b", "d"])
def test_curvature_offset_is_the_mean_distance_of_noisy_points(name: str) -> None:
    """At the true parameters the orthogonal distances of noisy points average to the offset."""
    rng = np.random.default_rng(1)
    j = make_joint(name, D=0.2, n_along=60, step_deg=3.0)
    sigma = 0.01
    off = curvature_offset(j.points, j.truth, sigma**2)
    reps = 40
    f = np.mean([condition(j.points + rng.normal(0.0, sigma, j.points.shape), j.truth) for _ in range(reps)], axis=0)
    # per point: mean of 40 distances, standard error sigma / sqrt(40); pooled by portion
    for part in (0, 1, 2):
        sel = j.portion == part
        se = sigma / math.sqrt(reps * np.count_nonzero(sel))
        assert abs(float(np.mean(f[sel] - off[sel]))) < 5 * se
        assert float(np.mean(off[sel])) > 5 * se  # the offset itself is far from zero
    # with a full covariance the second-order form agrees with the isotropic one to O(sigma^4)
    n = j.points.shape[0]
    off3 = curvature_offset(j.points, j.truth, cov=np.broadcast_to(np.eye(3) * sigma**2, (n, 3, 3)))
    np.testing.assert_allclose(off3, off, atol=sigma**4 / (j.truth.D / 2) ** 3)


def test_curvature_correction_removes_the_bias_at_high_noise() -> None:
    """Joint b (D = 0.2 m) with 20 mm noise, 30 fits of a 5,000-point cloud: without the correction
    D comes out about sigma^2 / R = 4 mm large; with it the mean errors of A, D and the centre are
    within 4 standard errors of zero."""
    rng = np.random.default_rng(7)
    c, rot = random_pose(rng)
    j = make_joint("b", D=0.2, center=c, rot=rot, n_along=50, step_deg=3.6)
    sigma = 0.02
    errs: dict[bool, list[np.ndarray]] = {True: [], False: []}
    k = 30
    for _ in range(k):
        pts = j.points + rng.normal(0.0, sigma, j.points.shape)
        for cc in errs:
            fit = fit_elbow(pts, _perturbed(j.truth), curvature_correction=cc)
            err = _internal_error(fit.params, j.truth)
            errs[cc].append(np.concatenate([j.truth.rot @ err[:3], err[6:]]))  # centre in the model frame
    on, off = np.array(errs[True]), np.array(errs[False])
    se_on = on.std(axis=0, ddof=1) / math.sqrt(k)
    assert np.all(np.abs(on.mean(axis=0)) < 4 * se_on), (on.mean(axis=0), se_on)
    se_off = off.std(axis=0, ddof=1) / math.sqrt(k)
    assert off[:, 4].mean() > 10 * se_off[4]  # D: the uncorrected fit is biased
    assert off[:, 4].mean() == pytest.approx(sigma**2 / (j.truth.D / 2), rel=0.25)


def test_gate_on_the_legs_leaves_out_only_points_near_the_torus_axis() -> None:
    """Sharp joint c: with gate_legs the axis gate also takes the legs' points whose foot point is
    within the gate radius of the torus axis, and nothing farther."""
    from lrms.elbow.gauss_helmert import AXIS_GATE_MAX, _usable

    j = make_joint("c", n_along=80, step_deg=2.0)
    t = j.truth
    sigma = 0.002
    radius = min(3.0 * sigma, AXIS_GATE_MAX * t.D / 2)
    m = t.to_model(j.points)
    rho = np.hypot(m[:, 0], m[:, 2])  # noise-free points are their own foot points
    bend_only = _usable(j.points, t, sigma, 3.0)
    legs_too = _usable(j.points, t, sigma, 3.0, legs=True)
    assert np.all(bend_only[j.portion != 1])  # the default keeps every leg point
    dropped = ~legs_too
    assert np.count_nonzero(dropped & (j.portion != 1)) > 0
    assert np.all(rho[dropped] <= radius * (1 + 1e-9))
    assert np.all(legs_too[rho > radius * 1.01])
    noisy = j.points + np.random.default_rng(2).normal(0.0, sigma, j.points.shape)
    f0 = fit_elbow(noisy, _perturbed(t))
    f1 = fit_elbow(noisy, _perturbed(t), gate_legs=True)
    assert f1.n < f0.n
    assert abs(f1.params.A - t.A) < 5 * f1.sigmas["A_m"]
