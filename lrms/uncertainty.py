"""Uncertainty of a fitted diameter, three ways.

a. :func:`critical_point_interval`: seed 003, Eq. 8-12. Every surface point carries its
   k-ellipsoid (Eq. 4, 7). Its *centripetal radius* ``r_ce`` is how far the ellipsoid reaches
   towards the axis: ``r_ce = r - min{distance to axis of x : x in the ellipsoid}`` (Eq. 12).
   The critical point is the point at the 25th percentile of ``r_ce``; the interval is
   ``[d - 2 r_ce, d + 2 r_ce]``.

   Eq. 12 is solved exactly in closed form up to one monotone 1-D root: the distance to the
   axis depends only on the projection onto the plane perpendicular to the axis, where the
   ellipsoid becomes the ellipse of ``S = P Sigma P^T`` (2 x 2) centred at ``c``. The nearest
   point to the axis is ``y = mu (S + mu I)^-1 c`` with ``mu > 0`` solving
   ``sum_i s_i c_i^2 / (s_i + mu)^2 = k^2`` (eigenbasis of ``S``); ``1/sqrt`` of the left side is
   concave and increasing in ``mu``, so Newton's method from ``mu = 0`` converges monotonically.
   :func:`centripetal_radius_eq12` solves the same problem with a general constrained optimiser
   (SLSQP) as the reference, and :func:`centripetal_radii_first_order` gives the tangent-plane
   approximation ``k sqrt(n^T Sigma n)``.
b. :func:`gum_interval`: ``u(d) = 2 sqrt(var r)`` from the fit's covariance (GUM, linearised),
   expanded with coverage factor 2.
c. :func:`monte_carlo_interval`: GUM Supplement 1. The scan is re-simulated from the fitted
   cylinder with the noise model (the same beams, Eq. 5 noise on ``(l, alpha, beta)``), every
   replica is refitted (batched Levenberg-Marquardt from the fit, same residuals as
   :func:`lrms.cylinder.refine_cylinder`, with the fit's multi-start), and the interval runs
   between the order statistics that hold a further replica with 95 % probability
   (:func:`coverage_order_statistics`; with M = 200 replicas: the 5th and the 196th, where
   plain 2.5 / 97.5 % quantiles would cover only ~94 %). Given
   :class:`lrms.budget.ReplicaSystematics`, the replicas also draw the budget's systematic effects
   (range offset and scale, angle zeros, per-scan motor errors, ...) from their distributions
   (:mod:`lrms.budget`). The replicas are thin-beam refits: a footprint fit's type A beyond
   their own spread (its estimated spot, the radius profile) is drawn as a normal error of each
   replica's diameter (:func:`footprint_type_a_excess`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms import kinematics
from lrms.budget import ReplicaSystematics
from lrms.covariance import NoiseModel
from lrms.cylinder import (
    MULTISTART,
    MULTISTART_SCREEN,
    SILHOUETTE_SIGMA,
    Cylinder,
    CylinderFit,
    Rays,
    _Frame,
    los_jacobian,
    los_residuals,
    orthogonal_jacobian,
    orthogonal_residuals,
    perpendicular_frame,
)
from lrms.errors import FitError, LrmsError

FloatArray = NDArray[np.float64]

#: Seed 003: the critical point sits at the 25th percentile of the centripetal radii.
CRITICAL_PERCENTILE = 25.0


def _check_k(k: float) -> float:
    kk = float(k)
    if not np.isfinite(kk) or kk <= 0:
        raise LrmsError(f"k must be > 0, got {k}")
    return kk


def _projected(cyl: Cylinder, points: FloatArray, covs: FloatArray) -> tuple[FloatArray, FloatArray]:
    e1, e2 = perpendicular_frame(cyl.direction)
    pm = np.stack([e1, e2])  # (2, 3)
    v = points - cyl.point
    c = v @ pm.T  # (N, 2)
    s = pm @ covs @ pm.T  # (N, 2, 2)
    return c, s


def min_axis_distance(cyl: Cylinder, points: ArrayLike, covs: ArrayLike, k: float) -> FloatArray:
    """Eq. 12, exactly: the smallest distance to the axis over each point's k-ellipsoid, ``(N,)``."""
    kk = _check_k(k)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cv = np.asarray(covs, dtype=np.float64).reshape(-1, 3, 3)
    c, s = _projected(cyl, pts, cv)
    return _min_distance_2d(c, s[:, 0, 0], s[:, 0, 1], s[:, 1, 1], kk)


#: Ellipses per block of :func:`_min_distance_2d` (its temporaries stay in the CPU's cache).
_BLOCK = 8192


def _min_distance_2d(c: FloatArray, a: FloatArray, b: FloatArray, d: FloatArray, kk: float) -> FloatArray:
    """Distance from the origin to the filled ellipses ``(y - c)^T S^-1 (y - c) <= k^2``,
    ``S = [[a, b], [b, d]]``, for ``N`` ellipses at once (see the module notes), in blocks of
    :data:`_BLOCK`."""
    n = c.shape[0]
    if n <= _BLOCK:
        return _min_distance_block(c, a, b, d, kk)
    out = np.empty(n)
    for s in range(0, n, _BLOCK):
        e = s + _BLOCK
        out[s:e] = _min_distance_block(c[s:e], a[s:e], b[s:e], d[s:e], kk)
    return out


def _min_distance_block(c: FloatArray, a: FloatArray, b: FloatArray, d: FloatArray, kk: float) -> FloatArray:
    # eigen-decomposition of the symmetric 2x2 matrices, closed form, without trigonometry: the
    # eigenvector of the larger eigenvalue s1 is (s1 - d, b) or (b, s1 - a), whichever is longer
    mean = 0.5 * (a + d)
    half = 0.5 * (a - d)
    rad = np.sqrt(half * half + b * b)  # (np.hypot is many times slower)
    s1 = np.maximum(mean + rad, 1e-300)
    s2 = np.maximum(mean - rad, 1e-30 * s1)
    first = a >= d
    vx = rad + half  # s1 - d
    vy = b.copy()
    vx[~first] = b[~first]
    vy[~first] = rad[~first] - half[~first]  # s1 - a
    vn = np.sqrt(vx * vx + vy * vy)
    round_ = vn <= 0  # isotropic: any axes
    vn[round_] = 1.0
    vx[round_] = 1.0
    ca, sa = vx / vn, vy / vn
    c1 = ca * c[:, 0] + sa * c[:, 1]  # component along the s1 eigenvector
    c2 = -sa * c[:, 0] + ca * c[:, 1]
    q1, q2 = s1 * c1 * c1, s2 * c2 * c2
    inside = (c1 * c1 / s1 + c2 * c2 / s2) <= kk * kk
    target = 1.0 / kk
    # start from below: each single-term root sqrt(s_i) |c_i| / k - s_i is a lower bound of mu
    mu = np.maximum(np.maximum(np.sqrt(s1) * np.abs(c1) / kk - s1, np.sqrt(s2) * np.abs(c2) / kk - s2), 0.0)
    mu[inside] = 0.0
    todo = np.flatnonzero(~inside)
    # Newton on phi(mu) = |S^1/2 (S + mu)^-1 c|^-1 = 1 / k, on compacted arrays of the
    # unfinished ellipses (most finish in 2-3 steps)
    m_, s1_, s2_, q1_, q2_ = mu[todo], s1[todo], s2[todo], q1[todo], q2[todo]
    for _ in range(60):
        if todo.size == 0:
            break
        i1, i2 = 1.0 / (s1_ + m_), 1.0 / (s2_ + m_)
        t1, t2 = q1_ * i1 * i1, q2_ * i2 * i2
        m = t1 + t2
        phi = 1.0 / np.sqrt(m)
        dphi = (t1 * i1 + t2 * i2) * phi / m
        step = np.maximum((target - phi) / np.maximum(dphi, 1e-300), 0.0)
        m_ = m_ + step
        going = step > 1e-12 * np.maximum(m_, 1e-300)
        if not np.all(going):
            mu[todo] = m_
            todo, m_, s1_, s2_, q1_, q2_ = todo[going], m_[going], s1_[going], s2_[going], q1_[going], q2_[going]
    mu[todo] = m_
    y1 = mu * c1 / (s1 + mu)
    y2 = mu * c2 / (s2 + mu)
    dist = np.sqrt(y1 * y1 + y2 * y2)
    dist[inside] = 0.0
    return np.asarray(dist, dtype=np.float64)


def centripetal_radii(cyl: Cylinder, points: ArrayLike, covs: ArrayLike, k: float) -> FloatArray:
    """``r_ce = r - min distance to the axis over the k-ellipsoid`` for every point (exact Eq. 12)."""
    return np.asarray(cyl.radius - min_axis_distance(cyl, points, covs, k), dtype=np.float64)


def centripetal_radii_first_order(cyl: Cylinder, points: ArrayLike, covs: ArrayLike, k: float) -> FloatArray:
    """Tangent-plane approximation ``k sqrt(n^T Sigma n)`` (``n``: radial direction at the point).

    It neglects the curvature of the cylinder across the ellipsoid, so it over-estimates ``r_ce``
    by about ``h^2 / (2 r)`` where ``h`` is the ellipsoid's extent along the surface.
    """
    kk = _check_k(k)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cv = np.asarray(covs, dtype=np.float64).reshape(-1, 3, 3)
    rad = cyl.radial(pts)
    n = rad / np.linalg.norm(rad, axis=1, keepdims=True)
    return np.asarray(kk * np.sqrt(np.einsum("ni,nij,nj->n", n, cv, n)), dtype=np.float64)


def centripetal_radius_eq12(cyl: Cylinder, point: ArrayLike, cov: ArrayLike, k: float) -> float:
    """Eq. 12 for one point with a general constrained optimiser (SLSQP): the reference solution.

    ``min |TA|`` (distance of ``T`` to the axis) subject to ``(T - E)^T Sigma^-1 (T - E) <= k^2``.
    Solved in whitened coordinates ``T = E + L u`` (``Sigma = L L^T``) for conditioning.
    """
    kk = _check_k(k)
    e = np.asarray(point, dtype=np.float64).reshape(3)
    cv = np.asarray(cov, dtype=np.float64).reshape(3, 3)
    w, v = np.linalg.eigh(cv)
    lmat = v * np.sqrt(np.clip(w, 1e-300, None))
    scale = float(np.sqrt(np.max(w)))

    def dist2(u: FloatArray) -> float:
        rad = cyl.radial(e + lmat @ u)
        return float(rad @ rad) / scale**2

    def grad(u: FloatArray) -> FloatArray:
        rad = cyl.radial(e + lmat @ u)
        return np.asarray(2.0 * (lmat.T @ rad) / scale**2, dtype=np.float64)

    rad0 = cyl.radial(e)
    u0 = -kk * 0.5 * (lmat.T @ rad0) / max(float(np.linalg.norm(lmat.T @ rad0)), 1e-300)
    from scipy.optimize import minimize  # imported on first use, not when the module loads

    res = minimize(
        dist2,
        u0,
        jac=grad,
        method="SLSQP",
        constraints=[{"type": "ineq", "fun": lambda u: kk * kk - float(u @ u), "jac": lambda u: -2.0 * u}],
        options={"ftol": 1e-16, "maxiter": 500},
    )
    r_min = float(np.sqrt(max(res.fun, 0.0))) * scale
    return cyl.radius - r_min


def _rig_centripetal_radii(cyl: Cylinder, pts: FloatArray, nm: NoiseModel, p: float, k: float) -> FloatArray:
    """:func:`_rig_centripetal_radii_block` in blocks of :data:`_BLOCK` points."""
    n = pts.shape[0]
    if n <= _BLOCK:
        return _rig_centripetal_radii_block(cyl, pts, nm, p, k)
    out = np.empty(n)
    for s in range(0, n, _BLOCK):
        out[s : s + _BLOCK] = _rig_centripetal_radii_block(cyl, pts[s : s + _BLOCK], nm, p, k)
    return out


def _rig_centripetal_radii_block(cyl: Cylinder, pts: FloatArray, nm: NoiseModel, p: float, k: float) -> FloatArray:
    """:func:`centripetal_radii` with Eq. 7 covariances, projected without forming them:
    ``S = (P J) diag(var) (P J)^T`` for the 2 x 3 projection ``P`` onto the cross-section.

    The columns of Eq. 6's ``J`` follow from the point itself (the branch of
    :func:`lrms.kinematics.inverse`, ``l sin(alpha) + p = hypot(x, z) >= 0``): with
    ``rho = hypot(x, z)`` and ``s = rho - p = l sin(alpha)``, ``d/dl = (s x / rho, y, s z / rho) / l``,
    ``d/dalpha = (y x / rho, -s, y z / rho)`` and ``d/dbeta = (-z, 0, x)``; no trigonometry and
    no ``(N, 3, 3)`` array."""
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    rho = np.maximum(np.sqrt(x * x + z * z), 1e-300)
    s = rho - p
    l = np.maximum(np.sqrt(s * s + y * y), 1e-300)
    cx, cz = x / rho, z / rho
    e1, e2 = perpendicular_frame(cyl.direction)
    var_l, var_a, var_b = nm.sigma_l**2, nm.sigma_alpha**2, nm.sigma_beta**2
    sl = s / l
    proj = []
    for e in (e1, e2):
        dl = (sl * cx) * e[0] + (y / l) * e[1] + (sl * cz) * e[2]
        da = (y * cx) * e[0] - s * e[1] + (y * cz) * e[2]
        db = x * e[2] - z * e[0]
        proj.append((dl, da, db))
    (l0, a0, b0), (l1, a1, b1) = proj
    s00 = var_l * l0 * l0 + var_a * a0 * a0 + var_b * b0 * b0
    s01 = var_l * l0 * l1 + var_a * a0 * a1 + var_b * b0 * b1
    s11 = var_l * l1 * l1 + var_a * a1 * a1 + var_b * b1 * b1
    a = cyl.point
    c0 = (x - a[0]) * e1[0] + (y - a[1]) * e1[1] + (z - a[2]) * e1[2]
    c1 = (x - a[0]) * e2[0] + (y - a[1]) * e2[1] + (z - a[2]) * e2[2]
    return np.asarray(cyl.radius - _min_distance_2d(np.column_stack([c0, c1]), s00, s01, s11, k), dtype=np.float64)


def ideal_points(cyl: Cylinder, rays: Rays) -> FloatArray:
    """Where each beam meets the cylinder (for a miss: its closest approach moved onto the surface)."""
    t, gap = cyl.ray_range(rays.origins, rays.dirs)
    pts = rays.origins + t[:, None] * rays.dirs
    miss = gap > 0
    if np.any(miss):
        rad = cyl.radial(pts[miss])
        pts[miss] -= rad * (gap[miss] / np.linalg.norm(rad, axis=1))[:, None]
    return np.asarray(pts, dtype=np.float64)


@dataclass(frozen=True)
class CriticalPointInterval:
    """Seed 003's interval: ``d_min = d - 2 r_ce``, ``d_max = d + 2 r_ce`` at the critical point."""

    diameter: float
    k: float
    percentile: float
    r_ce: float
    d_min: float
    d_max: float
    critical_index: int
    radii: FloatArray  # centripetal radius of every point (input order)
    points: FloatArray  # the surface points whose ellipsoids were used

    @property
    def half_width(self) -> float:
        return 0.5 * (self.d_max - self.d_min)

    def cdf(self) -> tuple[FloatArray, FloatArray]:
        """Empirical CDF of the centripetal radii (Fig. 7): sorted radii and cumulative shares."""
        x = np.sort(self.radii)
        return x, np.arange(1, x.size + 1, dtype=np.float64) / x.size

    def histogram(self, bins: int = 30) -> tuple[FloatArray, FloatArray]:
        counts, edges = np.histogram(self.radii, bins=bins)
        return counts.astype(np.float64), edges.astype(np.float64)


def critical_point_interval(
    cyl: Cylinder,
    surface_points: ArrayLike | None = None,
    *,
    rays: Rays | None = None,
    noise: NoiseModel | None = None,
    k: float = 1.0,
    p: float = kinematics.DEFAULT_P,
    percentile: float = CRITICAL_PERCENTILE,
    isotropic_sigma: float | None = None,
) -> CriticalPointInterval:
    """Eq. 8-12 with the seed's 25th-percentile critical point.

    The ellipsoids sit on ``surface_points`` (points on ``cyl``, as in the seed's simulation), or,
    given ``rays`` (the inliers' beams of a measurement), on the points where those beams meet the
    fitted cylinder. Covariances come from Eq. 7 with the rig at the origin (inner parameter ``p``),
    or are ``isotropic_sigma^2 I`` when given (clouds whose beams are unknown).
    """
    kk = _check_k(k)
    if not 0 <= percentile <= 100:
        raise LrmsError(f"percentile must be in [0, 100], got {percentile}")
    if surface_points is not None:
        pts = np.asarray(surface_points, dtype=np.float64).reshape(-1, 3)
    elif rays is not None:
        pts = ideal_points(cyl, rays)
    else:
        raise LrmsError("give surface_points or rays")
    if pts.shape[0] == 0:
        raise FitError("no points for the critical-point interval")
    if isotropic_sigma is not None:
        if not np.isfinite(isotropic_sigma) or isotropic_sigma <= 0:
            raise LrmsError(f"isotropic_sigma must be > 0, got {isotropic_sigma}")
        covs = np.broadcast_to(np.eye(3) * isotropic_sigma**2, (pts.shape[0], 3, 3))
        radii = centripetal_radii(cyl, pts, covs, kk)
    else:
        radii = _rig_centripetal_radii(cyl, pts, noise if noise is not None else NoiseModel(), p, kk)
    pos = int(np.floor(percentile / 100.0 * (radii.size - 1)))
    crit = int(np.argpartition(radii, pos)[pos])
    r_ce = float(radii[crit])
    d = cyl.diameter
    return CriticalPointInterval(
        diameter=d,
        k=kk,
        percentile=float(percentile),
        r_ce=r_ce,
        d_min=d - 2.0 * r_ce,
        d_max=d + 2.0 * r_ce,
        critical_index=crit,
        radii=radii,
        points=pts,
    )


@dataclass(frozen=True)
class Interval:
    diameter: float
    std: float
    low: float
    high: float
    coverage: float


def gum_interval(fit: CylinderFit, coverage_factor: float = 2.0) -> Interval:
    """GUM: ``d +- k u(d)`` with ``u(d) = 2 sqrt(var r)`` from the fit's covariance."""
    u = fit.std_diameter
    d = fit.diameter
    cov = math.erf(coverage_factor / math.sqrt(2.0))  # 2 Phi(k) - 1, without scipy.special
    return Interval(diameter=d, std=u, low=d - coverage_factor * u, high=d + coverage_factor * u, coverage=cov)


@dataclass(frozen=True)
class MonteCarloResult(Interval):
    diameters: FloatArray
    n_failed: int
    #: a footprint fit's type A beyond the thin-beam replicas' own spread, drawn as a normal error
    #: of each replica's diameter (m; 0 for a thin-beam fit): :func:`footprint_type_a_excess`
    footprint_type_a_u: float = 0.0


BatchResiduals = Callable[[FloatArray, NDArray[np.intp]], FloatArray]


def batched_levenberg_marquardt(
    fun: BatchResiduals, jfun: BatchResiduals, theta0: FloatArray, max_iter: int = 30, tol: float = 1e-7
) -> FloatArray:
    """Levenberg-Marquardt on many independent least-squares problems at once.

    ``fun(theta, idx)``: ``(len(idx), m)`` residuals of problems ``idx`` at ``theta``
    ``(len(idx), n)``; ``jfun(theta, idx)``: ``(len(idx), m, n)``. Each problem keeps its own
    damping, a step is taken only where it lowers that problem's cost, and finished problems drop
    out of the batch. A problem stops when its step is below ``tol`` (rad / m) or its cost
    stalls. Problems whose normal matrix is singular end as nan.
    """
    theta = np.array(theta0, dtype=np.float64)
    n_prob = theta.shape[0]
    idx = np.arange(n_prob)
    r = fun(theta, idx)
    cost = np.sum(r * r, axis=-1)
    lam = np.full(n_prob, 1e-4)
    eye = np.eye(theta.shape[-1])
    active = idx
    for _ in range(max_iter):
        if active.size == 0:
            break
        th, ra = theta[active], r[active]
        jac = jfun(th, active)
        jac_t = np.swapaxes(jac, -1, -2)
        jtj = jac_t @ jac
        g = (jac_t @ ra[..., None])[..., 0]
        diag = np.einsum("rii->ri", jtj)
        damped = jtj + lam[active, None, None] * (diag[:, :, None] * eye)
        ok = np.abs(np.linalg.det(damped)) > 0
        delta = np.zeros_like(th)
        delta[ok] = -np.linalg.solve(damped[ok], g[ok][..., None])[..., 0]
        theta[active[~ok]] = np.nan
        new = th + delta
        rn = fun(new, active)
        cn = np.sum(rn * rn, axis=-1)
        acc = (cn <= cost[active]) & ok
        flat = acc & (cost[active] - cn <= 1e-10 * cost[active])
        theta[active[acc]] = new[acc]
        r[active[acc]] = rn[acc]
        cost[active[acc]] = cn[acc]
        lam[active] = np.where(acc, lam[active] * 0.3, lam[active] * 10.0)
        small = np.max(np.abs(delta), axis=-1) < tol
        finished = ~ok | (acc & (small | flat)) | (lam[active] > 1e12)
        active = active[~finished]
    return theta


def _replica_problem(
    frame: _Frame, pts: FloatArray, line_of_sight: bool, nm: NoiseModel, p: float
) -> tuple[BatchResiduals, BatchResiduals]:
    """Residual and Jacobian functions of replicas ``pts`` ``(R, M, 3)`` for the batched solver."""
    if line_of_sight:
        l_, al, be = kinematics.inverse(pts, p)
        o, d = kinematics.beam_rays(al, be, p)
        sig_l = np.full(pts.shape[1], nm.sigma_l)
        sig_p = np.maximum(np.hypot(l_ * nm.sigma_alpha, (l_ * np.sin(al) + p) * nm.sigma_beta), SILHOUETTE_SIGMA)

        def fun(th: FloatArray, i: NDArray[np.intp]) -> FloatArray:
            return los_residuals(th, frame, o[i], d[i], l_[i], sig_l, sig_p[i])

        def jfun(th: FloatArray, i: NDArray[np.intp]) -> FloatArray:
            return los_jacobian(th, frame, o[i], d[i], sig_l, sig_p[i])

        return fun, jfun
    one = np.asarray(1.0)

    def ofun(th: FloatArray, i: NDArray[np.intp]) -> FloatArray:
        return orthogonal_residuals(th, frame, pts[i], one)

    def ojfun(th: FloatArray, i: NDArray[np.intp]) -> FloatArray:
        return orthogonal_jacobian(th, frame, pts[i], one)

    return ofun, ojfun


def coverage_order_statistics(samples: ArrayLike, coverage: float) -> tuple[float, float]:
    """Shortest symmetric pair of order statistics ``(x_(r), x_(M+1-r))`` that holds a further
    draw with probability ``(M + 1 - 2 r) / (M + 1) >= coverage``.

    Plain 2.5 / 97.5 % sample quantiles of ``M`` replicas hold a further draw only with
    probability ``~ (0.95 M - 1) / (M + 1)`` (94.0 % for M = 200), and that shortfall shows up
    as under-coverage; choosing ``r = floor((M + 1)(1 - coverage) / 2)`` removes it.
    """
    x = np.sort(np.asarray(samples, dtype=np.float64).ravel())
    m = x.size
    r = int(np.floor((m + 1) * (1.0 - coverage) / 2.0))
    if r < 1:
        raise LrmsError(f"{m} replicas are too few for a {100 * coverage:g} % interval")
    return float(x[r - 1]), float(x[m - r])


def _subset_problem(fn: BatchResiduals, rows: NDArray[np.intp]) -> BatchResiduals:
    """``fn`` on the problems ``rows`` only (their local indices mapped back)."""

    def sub(th: FloatArray, i: NDArray[np.intp]) -> FloatArray:
        return fn(th, rows[i])

    return sub


def _replica_fit(
    fun: BatchResiduals, jfun: BatchResiduals, rep: int, sigma_l: float, iterations: int, multistart: bool
) -> FloatArray:
    """Refit ``rep`` replicas: one batched solve from the truth (``theta = 0``), then, with
    ``multistart``, the fit's multi-start (:func:`lrms.cylinder._multistart`): restarts at radii
    :data:`lrms.cylinder.MULTISTART` sigma_l around that solution, each given
    :data:`lrms.cylinder.MULTISTART_SCREEN` (20) steps, about a full solve, and continued by a
    fresh solve where they beat the best cost so far, as in the fit; the lowest cost wins."""
    idx = np.arange(rep)
    theta = batched_levenberg_marquardt(fun, jfun, np.zeros((rep, 5)), max_iter=iterations)
    if not multistart:
        return theta

    def cost(th: FloatArray, rows: NDArray[np.intp] = idx) -> FloatArray:
        c = np.full(rows.size, np.inf)
        ok = np.all(np.isfinite(th), axis=1)
        if np.any(ok):
            r = fun(th[ok], rows[ok])
            c[ok] = np.sum(r * r, axis=-1)
        return c

    best, best_cost = theta, cost(theta)
    for dr in MULTISTART:
        start = np.where(np.isfinite(theta), theta, 0.0)
        start[:, 4] += dr * sigma_l
        # as in the fit: MULTISTART_SCREEN steps, continued where they beat the best so far
        trial = batched_levenberg_marquardt(fun, jfun, start, max_iter=MULTISTART_SCREEN)
        c = cost(trial)
        go = np.flatnonzero(c < best_cost)
        if go.size:
            sub = _subset_problem(fun, go)
            trial[go] = batched_levenberg_marquardt(sub, _subset_problem(jfun, go), trial[go], max_iter=iterations)
            c[go] = cost(trial[go], go)
        better = c < best_cost
        best = np.where(better[:, None], trial, best)
        best_cost = np.where(better, c, best_cost)
    return best


def thin_beam_replica_u(fit: CylinderFit, rays: Rays, noise: NoiseModel, p: float = kinematics.DEFAULT_P) -> float:
    """The diameter's standard uncertainty that :func:`monte_carlo_interval`'s thin-beam replicas
    reproduce from the beams' noise alone (m): ``2 sqrt((J^T J)^-1)_rr`` of the thin-beam
    line-of-sight problem on the inliers' beams (``rays``) at their ideal points on the fitted
    cylinder, the replicas' own linearisation."""
    truth = ideal_points(fit.cylinder, rays)
    _, jfun = _replica_problem(_Frame.at(fit.cylinder), truth[None], True, noise, p)
    jac = jfun(np.zeros((1, 5)), np.arange(1))[0]
    try:
        var = float(np.linalg.inv(jac.T @ jac)[4, 4])
    except np.linalg.LinAlgError as exc:  # pragma: no cover - degenerate geometry
        raise FitError("the replicas' thin-beam problem is degenerate (singular normal matrix)") from exc
    return float(2.0 * np.sqrt(max(var, 0.0)))


def footprint_type_a_excess(fit: CylinderFit, rays: Rays, noise: NoiseModel, p: float = kinematics.DEFAULT_P) -> float:
    """A footprint fit's type A (``fit.std_diameter``) that thin-beam replicas do not reproduce (m):
    ``sqrt(max(u_fit^2 - u_thin^2, 0))``, ``u_thin`` from :func:`thin_beam_replica_u`; 0 for a
    fit with no footprint model chosen (``fit.extra["edge_mode_first"]`` absent or -1).

    The replicas are thin-beam refits of the beams' noise; a footprint fit's type A is wider: its
    estimated spot size (a prior row) and the radius profile's ridge (docs/cylinder.md). That
    share is not re-simulated beam by beam; it is drawn as a normal error of each replica's
    diameter, as the budget's diameter-level rows are, so the replicas' spread carries it."""
    if fit.extra.get("edge_mode_first", -1.0) < 0:
        return 0.0
    u_fit = fit.std_diameter
    u_thin = thin_beam_replica_u(fit, rays, noise, p)
    return float(np.sqrt(max(u_fit * u_fit - u_thin * u_thin, 0.0)))


def monte_carlo_interval(
    fit: CylinderFit,
    rays: Rays | None = None,
    *,
    points: ArrayLike | None = None,
    isotropic_sigma: float | None = None,
    noise: NoiseModel | None = None,
    n: int = 200,
    coverage: float = 0.95,
    p: float = kinematics.DEFAULT_P,
    rng: np.random.Generator | None = None,
    iterations: int = 15,
    systematics: ReplicaSystematics | None = None,
    multistart: bool = True,
) -> MonteCarloResult:
    """GUM-S1 interval: re-simulate the inliers' beams from the fitted cylinder, refit, quantiles.

    ``rays`` are the beams of the fit's inliers (``rays.subset(fit.inliers)``); the replicas get
    the rig's noise (Eq. 5) on every beam and, given ``systematics``
    (:func:`lrms.budget.replica_systematics`), the systematic effects of the budget drawn from
    their distributions: one range offset, scale, temperature drift and angle zeros per replica,
    one motor-angle error per scan, and the diameter-level rows (edge model, calibration) as a
    normal error of the replica's diameter. Each replica is refitted with the fit's multi-start
    (``multistart``; :func:`_replica_fit`). For an orthogonal-distance fit the replicas are
    refitted with orthogonal distances too, so the interval describes that estimator. Without
    rays (clouds from elsewhere), give the inlier ``points`` of an orthogonal fit: their radial
    projections on the cylinder get isotropic Gaussian noise of ``isotropic_sigma`` (default:
    the fit's rms residual); ``systematics`` do not apply there. The replicas are refitted
    without the grazing weights; when the fit was bias-corrected
    (``fit.extra["bias_correction_diameter_m"]``) they are shifted by the same correction, a thin
    beam's only: a footprint fit's (``fit.extra["edge_mode_first"] >= 0``) corrects the footprint
    model's bias, which the thin-beam replicas do not carry, and leaves them as they are. A
    footprint fit's type A beyond the thin-beam replicas' own spread (its estimated spot size and
    the radius profile, :func:`footprint_type_a_excess`) is drawn as a normal error of each
    replica's diameter (``footprint_type_a_u`` of the result): not re-simulated, a Gaussian.
    """
    if n < 10:
        raise LrmsError(f"Monte Carlo needs at least 10 replicas, got {n}")
    if not 0 < coverage < 1:
        raise LrmsError(f"coverage must be in (0, 1), got {coverage}")
    nm = noise if noise is not None else NoiseModel()
    g = rng if rng is not None else np.random.default_rng()
    cyl = fit.cylinder
    frame = _Frame.at(cyl)
    iso: float | None = None
    if rays is not None:
        truth = ideal_points(cyl, rays)
    elif points is not None and not fit.line_of_sight:
        pp = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        rad = cyl.radial(pp)
        truth = pp - rad * (1.0 - cyl.radius / np.linalg.norm(rad, axis=1))[:, None]
        iso = float(isotropic_sigma) if isotropic_sigma is not None else fit.rmse
        if not np.isfinite(iso) or iso <= 0:
            raise LrmsError(f"isotropic sigma must be > 0, got {iso}")
    else:
        raise LrmsError("Monte Carlo needs the inliers' rays (or, for an orthogonal fit, their points)")
    if systematics is not None and iso is not None:
        raise LrmsError("systematic effects need the inliers' rays (a cloud from elsewhere has no beams)")
    l0, a0, b0 = kinematics.inverse(truth, p)
    m_pts = truth.shape[0]
    chunk = max(1, int(1_500_000 // (10 * max(m_pts, 1))))
    sig_l = nm.sigma_l if iso is None else iso
    out = np.empty(n)
    for s in range(0, n, chunk):
        rep = min(chunk, n - s)
        if iso is None:
            if systematics is not None:
                lt, at, bt = systematics.perturb(l0, a0, b0, rep, g)
            else:
                lt, at, bt = (np.broadcast_to(v, (rep, m_pts)) for v in (l0, a0, b0))
            ln, an, bn = nm.perturb(lt, at, bt, g)
            pts = kinematics.forward(ln, an, bn, p)  # (rep, M, 3)
        else:
            pts = truth + g.normal(0.0, iso, (rep, m_pts, 3))
        fun, jfun = _replica_problem(frame, pts, fit.line_of_sight, nm, p)
        theta = _replica_fit(fun, jfun, rep, sig_l, iterations, multistart and fit.line_of_sight)
        out[s : s + rep] = 2.0 * theta[:, 4] + 2.0 * cyl.radius
    # a bias-corrected fit: the replicas are plain fits, so they take the fit's correction too (its
    # spread from scan to scan, 0.006 mm on the seed's 567 points and 0.013 mm on the ray-cast sweeps
    # of docs/cylinder.md, is small against theirs); a footprint fit's correction is of the
    # footprint model's bias, which the thin-beam replicas do not carry
    if fit.extra.get("edge_mode_first", -1.0) < 0:
        out -= fit.extra.get("bias_correction_diameter_m", 0.0)
    if systematics is not None and systematics.diameter_u_m > 0:
        out += g.normal(0.0, systematics.diameter_u_m, n)
    u_fp = footprint_type_a_excess(fit, rays, nm, p) if rays is not None else 0.0
    if u_fp > 0:
        out += g.normal(0.0, u_fp, n)
    ok = np.isfinite(out)
    if np.count_nonzero(ok) < 10:
        raise FitError("Monte Carlo refits failed")
    good = out[ok]
    lo, hi = coverage_order_statistics(good, coverage)
    return MonteCarloResult(
        diameter=fit.diameter,
        std=float(np.std(good, ddof=1)),
        low=float(lo),
        high=float(hi),
        coverage=coverage,
        diameters=good,
        n_failed=int(np.count_nonzero(~ok)),
        footprint_type_a_u=u_fp,
    )
