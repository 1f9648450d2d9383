"""Precision floors of an elbow fit: the Gauss-Helmert covariance at the true parameters.

For points ``l_i`` on the true surface observed with noise ``e_i`` of covariance ``Q_i`` (``sigma^2 I``
by default: the same noise on x, y and z), the linearised Gauss-Helmert model at the truth gives the
parameter covariance ``(A^T M^-1 A)^-1`` with ``M_i = B_i Q_i B_i^T``. For Gaussian noise this is the
Cramer-Rao bound of the functional model (unknown foot points as nuisance parameters): no unbiased
estimator of the elbow from that cloud has a smaller covariance, to first order in the noise. For
other noise distributions of the same covariance (the uniform reading of the seed's "+-N mm") it is
the covariance of the linearised least-squares estimator (Gauss-Markov), which is what orthogonal
distance fitting reaches.

:func:`parameter_floor` returns that covariance in the order of
:func:`lrms.elbow.gauss_helmert.param_names`; :func:`metric_floors` turns it into the expected
RMSEs of the seed's metrics (delta_T over the three centre coordinates, delta_R over omega and psi,
delta_AD over A and D); :func:`sample_metrics` draws the metrics of single fits from the Gaussian
linear model, for the probability that one fit lands at or below a given value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.elbow.gauss_helmert import _check_cov, _weights_denominator, design_matrices, param_names
from lrms.elbow.model import ElbowParams, as_points, euler_jacobian
from lrms.errors import FitError

FloatArray = NDArray[np.float64]


def parameter_floor(
    points: ArrayLike,
    truth: ElbowParams,
    sigma: float | None = None,
    ratio: float | None = None,
    flange: bool | None = None,
    *,
    cov: ArrayLike | None = None,
) -> FloatArray:
    """Covariance floor of the internal unknowns (``param_names(ratio, flange)`` order).

    ``points``: the noise-free points (on the true surface; points off it are used as given, which
    is a first-order approximation). ``sigma``: the standard deviation of the noise on each
    coordinate (m), or ``cov``: per-point variances ``(n,)`` or covariances ``(n, 3, 3)`` (m^2);
    exactly one of the two. ``ratio``: A/D fixed at that value (then ``truth.A`` must equal
    ``ratio * truth.D``) or ``None`` for A and D free. ``flange``: whether ``Df`` is estimated
    (default: whether ``truth.Df`` is set). Raises :class:`FitError` for bad input or geometry that
    does not determine the parameters.
    """
    pts = as_points(points)
    n = pts.shape[0]
    if not np.all(np.isfinite(pts)):
        raise FitError("points contain NaN or infinite coordinates")
    if (sigma is None) == (cov is None):
        raise FitError("give either sigma or cov (not both, not neither)")
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
        raise FitError(f"sigma must be a positive number of metres, got {sigma}")
    if ratio is not None and not math.isclose(truth.A, ratio * truth.D, rel_tol=1e-9):
        raise FitError(f"truth has A/D = {truth.A / truth.D:.6g}, not the fixed ratio {ratio}")
    has_flange = truth.Df is not None if flange is None else bool(flange)
    u = len(param_names(ratio, has_flange))
    if n < u:
        raise FitError(f"too few points for a covariance floor: {n} (need at least {u})")
    q = _check_cov(cov, n)
    _, amat, b = design_matrices(pts, truth, ratio, has_flange)
    mm = _weights_denominator(b, q)
    if sigma is not None:
        mm = mm * sigma**2
    normal = amat.T @ (amat / mm[:, None])
    if not np.isfinite(np.linalg.cond(normal)) or np.linalg.cond(normal) > 1e15:
        raise FitError("singular normal equations: the points do not determine the elbow")
    return np.asarray(np.linalg.inv(normal), dtype=np.float64)


@dataclass(frozen=True)
class MetricFloors:
    """Expected RMSEs of one fit at the floor: delta_T (m), delta_R (rad), delta_AD (m), and kappa (rad)."""

    d_t: float
    d_r: float
    d_ad: float
    d_kappa: float


def _metric_blocks(
    cov: FloatArray, truth: ElbowParams, ratio: float | None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Covariances of (Xc, Yc, Zc), of (omega, psi, kappa) and of (A, D)."""
    c_t = cov[:3, :3]
    jac = euler_jacobian(*truth.angles)
    c_e = jac @ cov[3:6, 3:6] @ jac.T
    if ratio is None:
        c_ad = cov[6:8, 6:8]
    else:
        g = np.array([[ratio], [1.0]])
        c_ad = g @ cov[6:7, 6:7] @ g.T
    return np.asarray(c_t), np.asarray(c_e), np.asarray(c_ad)


def metric_floors(cov: ArrayLike, truth: ElbowParams, ratio: float | None = None) -> MetricFloors:
    """Expected root mean square of the seed's metrics for an estimator with covariance ``cov``.

    delta_T^2 = mean of the three centre variances, delta_R^2 = mean of the omega and psi variances
    (through the Euler angles' Jacobian at the truth), delta_AD^2 = mean of the A and D variances.
    """
    c = np.asarray(cov, dtype=np.float64)
    c_t, c_e, c_ad = _metric_blocks(c, truth, ratio)
    return MetricFloors(
        d_t=math.sqrt(float(np.trace(c_t)) / 3),
        d_r=math.sqrt(float(c_e[0, 0] + c_e[1, 1]) / 2),
        d_ad=math.sqrt(float(np.trace(c_ad)) / 2),
        d_kappa=math.sqrt(float(c_e[2, 2])),
    )


def sample_metrics(
    cov: ArrayLike, truth: ElbowParams, ratio: float | None, size: int, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """delta_T (m), delta_R (rad) and delta_AD (m) of ``size`` single fits drawn from N(0, cov)."""
    c = np.asarray(cov, dtype=np.float64)
    c_t, c_e, c_ad = _metric_blocks(c, truth, ratio)

    def draw(block: FloatArray, k: int) -> FloatArray:
        e = rng.multivariate_normal(np.zeros(block.shape[0]), block, size=size, method="eigh")
        return np.asarray(np.sqrt(np.mean(e[:, :k] ** 2, axis=1)))

    return draw(c_t, 3), draw(c_e[:2, :2], 2), draw(c_ad, 2)
