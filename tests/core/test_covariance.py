"""Single-point error ellipsoids (seed 003, Eq. 2-7)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from lrms import kinematics
from lrms.covariance import (
    NoiseModel,
    chi2_share,
    covariances_of_points,
    ellipsoid_axes,
    mahalanobis_sq,
    monte_carlo_share,
    point_covariances,
)
from lrms.errors import LrmsError


def test_seed_noise_figures() -> None:
    nm = NoiseModel()
    assert nm.sigma_l**2 == pytest.approx(136.11e-6)
    np.testing.assert_allclose(
        np.diag(nm.raw_covariance()), [136.11e-6, np.deg2rad(1.74e-3) ** 2, np.deg2rad(3.6e-5) ** 2]
    )


def test_eq7_matches_empirical_covariance_of_eq1() -> None:
    """J Sigma J^T against the sample covariance of Eq. 1 applied to perturbed raw readings."""
    nm = NoiseModel(sigma_l=0.01, sigma_alpha=np.deg2rad(0.2), sigma_beta=np.deg2rad(0.3))
    l, a, b = 2.5, np.deg2rad(12.0), np.deg2rad(40.0)
    rng = np.random.default_rng(11)
    n = 200_000
    obs = kinematics.forward(*nm.perturb(np.full(n, l), np.full(n, a), np.full(n, b), rng), p=0.1)
    emp = np.cov(obs.T)
    lin = point_covariances(l, a, b, nm, 0.1)
    np.testing.assert_allclose(emp, lin, rtol=0.03, atol=2e-3 * np.abs(lin).max())


def test_covariances_of_points_vectorized_and_along_the_beam() -> None:
    pts = np.array([[0.28, 2.4, 0.5], [0.2, 2.5, -0.1], [0.35, 2.6, 1.0]])
    covs = covariances_of_points(pts)
    assert covs.shape == (3, 3, 3)
    for c, x in zip(covs, pts, strict=True):
        lengths, axes = ellipsoid_axes(c, k=1.0)
        # the long axis is the beam: from the optical centre through the point
        _, a, b = kinematics.inverse(x)
        _, d = kinematics.beam_rays(a, b)
        assert abs(float(axes[:, 2] @ d)) > 0.9999
        assert lengths[2] == pytest.approx(NoiseModel().sigma_l, rel=1e-6)
        assert lengths[0] < 1e-3 * lengths[2]


def test_ellipsoid_axes_scale_with_k() -> None:
    c = np.diag([4.0, 1.0, 9.0])
    l1, _ = ellipsoid_axes(c, 1.0)
    l3, v3 = ellipsoid_axes(c, 3.0)
    np.testing.assert_allclose(l1, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(l3, 3 * l1)
    # a point on the k = 3 ellipsoid along each axis has Mahalanobis distance 3
    pts = (v3 * l3).T
    np.testing.assert_allclose(mahalanobis_sq(pts, np.broadcast_to(c, (3, 3, 3))), 9.0)
    with pytest.raises(LrmsError):
        ellipsoid_axes(c, 0.0)
    with pytest.raises(LrmsError):
        ellipsoid_axes(np.eye(2), 1.0)


def test_chi2_law_values() -> None:
    np.testing.assert_allclose(chi2_share([1, 2, 3]), [0.198748, 0.738536, 0.970709], atol=1e-6)


def test_monte_carlo_share_inside_ellipsoids_follows_chi2_3dof() -> None:
    """Fig. 3 of the seed with many more draws: the shares inside k = 1, 2, 3 follow chi2(3)."""
    n = 100_000
    share = monte_carlo_share(2.53, np.deg2rad(10.0), np.deg2rad(60.0), n_draws=n, rng=np.random.default_rng(3))
    expect = stats.chi2.cdf(np.array([1.0, 4.0, 9.0]), 3)
    tol = 4.5 * np.sqrt(expect * (1 - expect) / n)  # binomial, ~4.5 sigma
    assert np.all(np.abs(share - expect) < tol), (share, expect)
    # the seed's 97.75 % at k = 3 (2000 draws) is 1.8 binomial sigma above the law's 97.07 %
    z = (0.9775 - expect[2]) / np.sqrt(expect[2] * (1 - expect[2]) / 2000)
    assert 1.0 < z < 2.5


def test_bad_noise_model() -> None:
    with pytest.raises(LrmsError):
        NoiseModel(sigma_l=0.0)
    with pytest.raises(LrmsError):
        NoiseModel(sigma_alpha=-1.0)
