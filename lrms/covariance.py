"""Single-point error ellipsoids: seed 003, Eq. 2-7.

The raw readings ``(l, alpha, beta)`` are independent with variances ``sigma_l^2``,
``sigma_alpha^2`` and ``sigma_beta^2`` (Eq. 5); their covariance propagates to the rig frame
through the Jacobian of Eq. 1 (Eq. 6): ``Sigma_xyz = J Sigma_(l,alpha,beta) J^T`` (Eq. 7).
The k-ellipsoid of a point is ``r^T Sigma^-1 r = k^2`` (Eq. 4); for a Gaussian the squared
Mahalanobis distance follows the chi-square law with 3 degrees of freedom, so the share of
draws inside the k-ellipsoid is ``chi2.cdf(k^2, 3)`` (19.9 %, 73.9 %, 97.1 % for k = 1, 2, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms import kinematics
from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]

#: Seed 003: the range variance of a single LMS100 reading at about 2.4 m is 136.11 mm^2.
SEED_SIGMA_L = float(np.sqrt(136.11e-6))
#: Seed 003: sigma_alpha = 1.74e-3 deg (LMS100 angular uncertainty).
SEED_SIGMA_ALPHA = float(np.deg2rad(1.74e-3))
#: Seed 003: sigma_beta = 3.6e-5 deg (servo + reducer).
SEED_SIGMA_BETA = float(np.deg2rad(3.6e-5))


@dataclass(frozen=True)
class NoiseModel:
    """Standard deviations of the raw readings (Eq. 5): range (m), scan and motor angle (rad)."""

    sigma_l: float = SEED_SIGMA_L
    sigma_alpha: float = SEED_SIGMA_ALPHA
    sigma_beta: float = SEED_SIGMA_BETA

    def __post_init__(self) -> None:
        for name in ("sigma_l", "sigma_alpha", "sigma_beta"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v < 0:
                raise LrmsError(f"{name} must be a finite standard deviation >= 0, got {v}")
        if self.sigma_l <= 0:
            raise LrmsError("sigma_l must be > 0")

    def raw_covariance(self) -> FloatArray:
        """Eq. 5: the diagonal covariance of ``(l, alpha, beta)``."""
        return np.diag([self.sigma_l**2, self.sigma_alpha**2, self.sigma_beta**2])

    def perturb(
        self, l: ArrayLike, alpha: ArrayLike, beta: ArrayLike, rng: np.random.Generator
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Noisy copies of raw readings (independent Gaussian errors, Eq. 5)."""
        l_, a, b = np.broadcast_arrays(np.asarray(l, float), np.asarray(alpha, float), np.asarray(beta, float))
        return (
            l_ + rng.normal(0.0, self.sigma_l, l_.shape),
            a + rng.normal(0.0, self.sigma_alpha, a.shape),
            b + rng.normal(0.0, self.sigma_beta, b.shape),
        )


def point_covariances(
    l: ArrayLike, alpha: ArrayLike, beta: ArrayLike, noise: NoiseModel | None = None, p: float = kinematics.DEFAULT_P
) -> FloatArray:
    """Eq. 7 for every reading: ``Sigma_xyz = J Sigma_(l,alpha,beta) J^T``, shape ``(..., 3, 3)``."""
    nm = noise if noise is not None else NoiseModel()
    j = kinematics.jacobian(l, alpha, beta, p)
    var = np.array([nm.sigma_l**2, nm.sigma_alpha**2, nm.sigma_beta**2])
    return np.asarray((j * var) @ np.swapaxes(j, -1, -2), dtype=np.float64)


def covariances_of_points(
    xyz: ArrayLike, noise: NoiseModel | None = None, p: float = kinematics.DEFAULT_P
) -> FloatArray:
    """Eq. 7 for rig-frame points: recovers ``(l, alpha, beta)`` by inverting Eq. 1 first."""
    l, a, b = kinematics.inverse(xyz, p)
    return point_covariances(l, a, b, noise, p)


def _check_cov(cov: ArrayLike) -> FloatArray:
    c = np.asarray(cov, dtype=np.float64)
    if c.ndim < 2 or c.shape[-2:] != (3, 3):
        raise LrmsError(f"covariances must have shape (..., 3, 3), got {c.shape}")
    return c


def ellipsoid_axes(cov: ArrayLike, k: float = 1.0) -> tuple[FloatArray, FloatArray]:
    """Semi-axes of the k-ellipsoids ``r^T Sigma^-1 r = k^2`` (Eq. 4).

    Returns ``(lengths, directions)``: lengths ``(..., 3)`` in ascending order (``k sqrt(eig)``)
    and the matching unit axes as the columns of ``directions`` ``(..., 3, 3)``.
    """
    if not np.isfinite(k) or k <= 0:
        raise LrmsError(f"k must be > 0, got {k}")
    c = _check_cov(cov)
    w, v = np.linalg.eigh(c)
    return k * np.sqrt(np.clip(w, 0.0, None)), v


def mahalanobis_sq(residuals: ArrayLike, cov: ArrayLike) -> FloatArray:
    """``r^T Sigma^-1 r`` for residuals ``(..., 3)`` and covariances ``(..., 3, 3)``."""
    r = np.asarray(residuals, dtype=np.float64)
    c = _check_cov(cov)
    sol = np.linalg.solve(c, r[..., None])[..., 0]
    return np.asarray(np.einsum("...i,...i->...", r, sol), dtype=np.float64)


def chi2_share(k: ArrayLike, dof: int = 3) -> FloatArray:
    """Probability mass of a ``dof``-dimensional Gaussian inside its k-ellipsoid: ``chi2.cdf(k^2, dof)``."""
    from scipy.special import chdtr  # the chi-square CDF itself (scipy.stats costs ~0.5 s to import)

    return np.asarray(chdtr(dof, np.square(np.asarray(k, dtype=np.float64))), dtype=np.float64)


def monte_carlo_share(
    l: float,
    alpha: float,
    beta: float,
    ks: ArrayLike = (1.0, 2.0, 3.0),
    n_draws: int = 100_000,
    noise: NoiseModel | None = None,
    p: float = kinematics.DEFAULT_P,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """Share of noisy observations of one point that fall inside its k-ellipsoids (Fig. 3 check).

    The readings are perturbed in raw space and mapped by the full non-linear Eq. 1; the
    ellipsoids come from the linearised Eq. 7 at the true reading.
    """
    nm = noise if noise is not None else NoiseModel()
    g = rng if rng is not None else np.random.default_rng()
    truth = kinematics.forward(l, alpha, beta, p)
    cov = point_covariances(l, alpha, beta, nm, p)
    ln, an, bn = nm.perturb(np.full(n_draws, l), np.full(n_draws, alpha), np.full(n_draws, beta), g)
    obs = kinematics.forward(ln, an, bn, p)
    m2 = mahalanobis_sq(obs - truth, np.broadcast_to(cov, (n_draws, 3, 3)))
    kk = np.asarray(ks, dtype=np.float64)
    return np.asarray((m2[None, :] <= np.square(kk)[:, None]).mean(axis=1), dtype=np.float64)
