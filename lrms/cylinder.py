"""Cylinder detection and fitting that honours the rig's noise model.

Pipeline (:func:`fit_cylinder`; the details and measured numbers are in ``docs/cylinder.md``):

1. **Normals** on a random subsample by PCA of k-nearest-neighbour patches (scipy ``cKDTree``),
   as PCL's ``SACMODEL_CYLINDER`` expects them. The subsample keeps the neighbourhoods wider
   than the range noise (about 12 mm on the LMS100), so the normals mean something.
2. **Cylinder RANSAC** on minimal samples of 2 points + normals (:class:`CylinderModel`): the
   axis direction is ``n1 x n2``, the axis passes through the closest points of the two normal
   lines, the radius is the distance of the first point from that axis. Residual: distance to
   the surface plus a penalty for the angle between the point's normal and the radial direction.
3. **Support plane** (:func:`support_plane`): the populated slab perpendicular to the axis (the
   table); its points are set aside and the axis meets it at the base point.
4. **Refinement** with ``scipy.optimize.least_squares`` (analytic Jacobians):

   * *line of sight* (default): every point keeps its beam (origin and direction recovered by
     inverting Eq. 1) and the residual is the measured range minus the range at which that beam
     meets the model cylinder, divided by ``sigma_l``. This is the maximum-likelihood fit for the
     rig's noise, which lies almost entirely along the beam (Eq. 7). A beam that misses the model
     gets a second residual, its miss distance over a lateral sigma floored at
     :data:`SILHOUETTE_SIGMA`, so the objective stays continuous at the silhouette. Inliers are
     re-selected on the candidates (range residual below :data:`INLIER_GATE` sigma, miss below
     :data:`MISS_GATE` lateral sigmas, with hysteresis), then the fit is restarted from nearby
     radii (:data:`MULTISTART`) because the silhouette makes the likelihood multi-modal.
   * *orthogonal distance* (``line_of_sight=False``): ``(|distance to axis| - r) / sigma``, the
     right fit for isotropic noise. On a one-sided view with range noise it is biased low.

5. Up to ``DetectOptions.attempts`` RANSAC runs (more while no fit is explained by the noise
   model); the best fit by :func:`_better` is kept.
6. **Selection by the scene model** (:func:`table_height`, :func:`_select_above_table`): the
   table is the plane perpendicular to the fitted axis under the part; the part's beams are
   those whose predicted first hit on the fitted part lies at least :data:`BASE_CLEARANCE` above
   it and not above the part's top (:func:`_top_height`); refit on them.
7. **Grazing weights** (:func:`grazing_weighted_fit`): the inliers are refitted with per-beam
   variances ``sigma_l^2 + (tan(incidence) sigma_lat)^2``, which moderates the leverage of the
   near-tangent limb beams (a trade of spread for a small bias, measured in docs/cylinder.md).
8. **Second-order bias correction** (:func:`second_order_bias`, Box 1971): the range of a beam
   near the silhouette is strongly curved in the parameters, which biases the nonlinear fit by
   about +0.07 mm in diameter on the seed's set-up; the bias is estimated at the solution and
   subtracted.

The parameters' covariance is expressed in a local frame at the solution: ``theta = (t1, t2,
s1, s2, r)``, the axis direction ``normalize(w + t1 e1 + t2 e2)``, the axis point ``a + s1 e1 +
s2 e2`` and the radius ``r``, where ``e1, e2`` (:attr:`CylinderFit.frame`) are perpendicular to the
fitted direction ``w`` and ``a`` is the fitted axis point.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from lrms import kinematics
from lrms.covariance import NoiseModel
from lrms.errors import FitError
from lrms.ransac import PlaneModel, ransac

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Inlier gate on the whitened residual during refinement.
INLIER_GATE = 4.0
#: Largest miss distance of an inlier's beam, in lateral standard deviations.
MISS_GATE = 2.0
#: Floor (m) of the lateral standard deviation that scales a beam's miss distance. The
#: angular noise alone (``l sigma_alpha``, 0.08 mm at 2.5 m) would make the fit hostage to the
#: last fraction of a millimetre at the silhouette, where real returns are mixed pixels of a
#: spot tens of mm wide; 1 mm keeps the objective continuous without trusting that edge.
SILHOUETTE_SIGMA = 1e-3
#: Parameter steps for the central-difference Jacobian: tilt (rad), shift (m), radius (m).
_STEPS = np.array([1e-6, 1e-6, 1e-6, 1e-6, 1e-6])


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    """Inner products over the last axis (broadcasting); faster than ``np.sum(a * b, -1)``."""
    return np.asarray(np.einsum("...i,...i->...", a, b), dtype=np.float64)


def _unit(v: ArrayLike) -> FloatArray:
    a = np.asarray(v, dtype=np.float64)
    return np.asarray(a / np.linalg.norm(a, axis=-1, keepdims=True), dtype=np.float64)


def perpendicular_frame(w: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors ``e1, e2`` with ``(e1, e2, w)`` right-handed and orthonormal."""
    wu = _unit(w)
    helper = np.array([1.0, 0.0, 0.0]) if abs(wu[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _unit(np.cross(helper, wu))
    e2 = np.cross(wu, e1)
    return e1, np.asarray(e2, dtype=np.float64)


@dataclass(frozen=True)
class Cylinder:
    """An infinite circular cylinder: a point on the axis, the unit axis direction, the radius."""

    point: FloatArray
    direction: FloatArray
    radius: float

    def __post_init__(self) -> None:
        p = np.asarray(self.point, dtype=np.float64).reshape(3)
        d = np.asarray(self.direction, dtype=np.float64).reshape(3)
        nd = float(np.linalg.norm(d))
        if not (np.all(np.isfinite(p)) and np.isfinite(nd) and nd > 0 and np.isfinite(self.radius)):
            raise FitError("cylinder parameters must be finite with a non-zero axis direction")
        if self.radius <= 0:
            raise FitError(f"cylinder radius must be > 0, got {self.radius}")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "direction", d / nd)
        object.__setattr__(self, "radius", float(self.radius))

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius

    def radial(self, points: ArrayLike) -> FloatArray:
        """Component of ``points - point`` perpendicular to the axis, ``(N, 3)``."""
        v = np.asarray(points, dtype=np.float64) - self.point
        return np.asarray(v - (v @ self.direction)[..., None] * self.direction, dtype=np.float64)

    def axis_distance(self, points: ArrayLike) -> FloatArray:
        return np.asarray(np.linalg.norm(self.radial(points), axis=-1), dtype=np.float64)

    def surface_distance(self, points: ArrayLike) -> FloatArray:
        """Signed orthogonal distance to the surface (positive outside)."""
        return self.axis_distance(points) - self.radius

    def ray_range(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Range at which unit rays first meet the surface, and the miss distance.

        Returns ``(t, gap)``: for a hit, ``t`` is the near intersection and ``gap`` is 0; for a
        miss, ``t`` is the range of closest approach to the axis and ``gap`` (> 0) how far the
        ray passes outside the surface there.
        """
        t, gap = _ray_cylinder(
            np.asarray(origins, dtype=np.float64),
            np.asarray(dirs, dtype=np.float64),
            self.point,
            self.direction,
            np.asarray(self.radius),
        )
        return t, gap

    def with_point_near(self, reference: ArrayLike) -> Cylinder:
        """Same cylinder with its axis point moved to the foot of ``reference`` on the axis."""
        ref = np.asarray(reference, dtype=np.float64)
        a = self.point + float((ref - self.point) @ self.direction) * self.direction
        return Cylinder(a, self.direction, self.radius)


def _ray_cylinder(
    o: FloatArray, u: FloatArray, a: FloatArray, w: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Broadcasting core of :meth:`Cylinder.ray_range`.

    ``o, u``: ``(..., N, 3)``; ``a, w``: ``(..., 3)`` (one axis per leading index); ``r``: ``(...)``.
    """
    a_ = a[..., None, :]
    w_ = w[..., None, :]
    v = o - a_
    vp = v - _dot(v, w_)[..., None] * w_
    up = u - _dot(u, w_)[..., None] * w_
    aa = np.maximum(_dot(up, up), 1e-300)
    bb = _dot(vp, up)
    cc = _dot(vp, vp)
    t_ca = -bb / aa
    d_ca2 = np.maximum(cc - bb * bb / aa, 0.0)
    rr = np.asarray(r, dtype=np.float64)[..., None]
    disc = aa * (rr * rr - d_ca2)
    hit = disc >= 0
    t = np.where(hit, t_ca - np.sqrt(np.where(hit, disc, 0.0)) / aa, t_ca)
    gap = np.where(hit, 0.0, np.sqrt(d_ca2) - rr)
    return np.asarray(t, dtype=np.float64), np.asarray(gap, dtype=np.float64)


# --------------------------------------------------------------------------- rays & normals


@dataclass(frozen=True)
class Rays:
    """Beams of the measured points: origins ``(N, 3)``, unit directions ``(N, 3)``, ranges ``(N,)``,
    and per-point standard deviations along (``sigma_l``) and across (``sigma_perp``) the beam."""

    origins: FloatArray
    dirs: FloatArray
    ranges: FloatArray
    sigma_l: FloatArray
    sigma_perp: FloatArray

    def subset(self, idx: ArrayLike) -> Rays:
        i = np.asarray(idx)
        return Rays(self.origins[i], self.dirs[i], self.ranges[i], self.sigma_l[i], self.sigma_perp[i])

    def points(self) -> FloatArray:
        return np.asarray(self.origins + self.ranges[:, None] * self.dirs, dtype=np.float64)


def rays_from_points(points: ArrayLike, p: float = kinematics.DEFAULT_P, noise: NoiseModel | None = None) -> Rays:
    """Recover each rig-frame point's beam by inverting Eq. 1 (the rig at the origin)."""
    nm = noise if noise is not None else NoiseModel()
    pts = np.asarray(points, dtype=np.float64)
    l, alpha, beta = kinematics.inverse(pts, p)
    origins, dirs = kinematics.beam_rays(alpha, beta, p)
    lat = np.hypot(l * nm.sigma_alpha, (l * np.sin(alpha) + p) * nm.sigma_beta)
    return Rays(
        origins=origins,
        dirs=dirs,
        ranges=l,
        sigma_l=np.full(l.shape, nm.sigma_l),
        sigma_perp=np.maximum(lat, SILHOUETTE_SIGMA),
    )


def estimate_normals(points: ArrayLike, k: int = 24, chunk: int = 50_000) -> FloatArray:
    """Unit normals by PCA of each point's ``k`` nearest neighbours (smallest-eigenvalue axis)."""
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if n < 3:
        raise FitError(f"need at least 3 points for normals, got {n}")
    kk = int(min(max(k, 3), n))
    tree = cKDTree(pts)
    out = np.empty_like(pts)
    for s in range(0, n, chunk):
        _, idx = tree.query(pts[s : s + chunk], k=kk)
        nb = pts[idx]
        nb = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb)
        _, vecs = np.linalg.eigh(cov)
        out[s : s + chunk] = vecs[:, :, 0]
    return out


# --------------------------------------------------------------------------- RANSAC models


class CylinderModel:
    """RANSAC model on rows ``(x, y, z, nx, ny, nz)``: a cylinder from 2 points with normals.

    ``normal_weight`` (m per rad) converts the angle between a point's normal and the model's
    radial direction into distance in the residual.
    """

    normal_weight = 0.02
    radius_range: tuple[float, float] = (0.005, 2.0)

    def __init__(self) -> None:
        self.cylinder: Cylinder | None = None

    def estimate(self, data: FloatArray) -> bool:
        d = np.asarray(data, dtype=np.float64)
        if d.shape[0] < 2 or d.shape[1] < 6:
            return False
        if d.shape[0] > 2:
            return self._estimate_many(d)
        p1, n1, p2, n2 = d[0, :3], d[0, 3:6], d[1, :3], d[1, 3:6]
        w = np.cross(n1, n2)
        sw = float(np.linalg.norm(w))
        if sw < 0.05:  # normals nearly parallel: axis undefined
            return False
        w = w / sw
        # closest points of the lines p1 + s n1 and p2 + t n2
        r12 = p1 - p2
        b = float(n1 @ n2)
        denom = 1.0 - b * b
        e, f = float(n1 @ r12), float(n2 @ r12)
        s = (b * f - e) / denom
        t = (f - b * e) / denom
        c = 0.5 * ((p1 + s * n1) + (p2 + t * n2))
        cyl_r = float(np.linalg.norm(Cylinder(c, w, 1.0).radial(p1)))
        lo, hi = self.radius_range
        if not (lo <= cyl_r <= hi):
            return False
        self.cylinder = Cylinder(c, w, cyl_r)
        return True

    def _estimate_many(self, d: FloatArray) -> bool:
        """Least-squares polish on many inliers (orthogonal distance), from a 2-point start."""
        if self.cylinder is None:
            # start from the best pair among a few
            best: Cylinder | None = None
            for i in range(1, min(d.shape[0], 8)):
                m = CylinderModel()
                if m.estimate(d[[0, i]]):
                    best = m.cylinder
                    break
            if best is None:
                return False
            self.cylinder = best
        try:
            fit = refine_cylinder(d[:, :3], self.cylinder, rays=None, sigma=1.0, max_rounds=1)
        except FitError:
            return False
        self.cylinder = fit.cylinder
        return True

    def residuals(self, data: FloatArray) -> FloatArray:
        if self.cylinder is None:
            raise FitError("model not estimated")
        d = np.asarray(data, dtype=np.float64)
        rad = self.cylinder.radial(d[:, :3])
        dist = np.linalg.norm(rad, axis=1)
        res = np.abs(dist - self.cylinder.radius)
        if d.shape[1] >= 6:
            cosang = np.abs(np.sum(rad * d[:, 3:6], axis=1)) / np.maximum(dist, 1e-12)
            res = res + self.normal_weight * np.arccos(np.clip(cosang, 0.0, 1.0))
        return np.asarray(res, dtype=np.float64)


# --------------------------------------------------------------------------- refinement


@dataclass(frozen=True)
class _Frame:
    a: FloatArray
    w: FloatArray
    e1: FloatArray
    e2: FloatArray
    r0: float

    @classmethod
    def at(cls, cyl: Cylinder) -> _Frame:
        e1, e2 = perpendicular_frame(cyl.direction)
        return cls(cyl.point, cyl.direction, e1, e2, cyl.radius)

    def unpack(self, theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        th = np.asarray(theta, dtype=np.float64)
        w = self.w + th[..., 0:1] * self.e1 + th[..., 1:2] * self.e2
        w = w / np.linalg.norm(w, axis=-1, keepdims=True)
        a = self.a + th[..., 2:3] * self.e1 + th[..., 3:4] * self.e2
        return a, w, self.r0 + th[..., 4]

    def cylinder(self, theta: FloatArray) -> Cylinder:
        a, w, r = self.unpack(theta)
        return Cylinder(a, w, float(r))


def _param_derivatives(frame: _Frame, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``d w / d theta`` and ``d a / d theta`` as ``(..., 5, 3)`` arrays."""
    th = np.asarray(theta, dtype=np.float64)
    raw = frame.w + th[..., 0:1] * frame.e1 + th[..., 1:2] * frame.e2
    nrm = np.linalg.norm(raw, axis=-1, keepdims=True)
    w = raw / nrm
    dw = np.zeros((*th.shape[:-1], 5, 3))
    da = np.zeros((*th.shape[:-1], 5, 3))
    for j, e in enumerate((frame.e1, frame.e2)):
        dw[..., j, :] = (e - np.sum(w * e, axis=-1, keepdims=True) * w) / nrm
        da[..., j + 2, :] = e
    return dw, da


def los_residuals(
    theta: FloatArray,
    frame: _Frame,
    origins: FloatArray,
    dirs: FloatArray,
    ranges: FloatArray,
    sigma_l: FloatArray,
    sigma_perp: FloatArray,
) -> FloatArray:
    """Whitened line-of-sight residuals ``(..., 2N)``: range part then miss part.

    ``theta``: ``(..., 5)``; beams ``(..., N, 3)`` broadcast against it.
    """
    a, w, r = frame.unpack(theta)
    t, gap = _ray_cylinder(origins, dirs, a, w, r)
    return np.concatenate([(ranges - t) / sigma_l, gap / sigma_perp], axis=-1)


def los_jacobian(
    theta: FloatArray,
    frame: _Frame,
    origins: FloatArray,
    dirs: FloatArray,
    sigma_l: FloatArray,
    sigma_perp: FloatArray,
) -> FloatArray:
    """Analytic Jacobian ``(..., 2N, 5)`` of :func:`los_residuals`.

    Hit: implicit differentiation of ``|P(X - a)|^2 = r^2`` at ``X = o + t u`` gives
    ``dt = (q.da + h v.dw + r dr) / (q.u)`` (``v = X - a``, ``h = v.w``, ``q = v - h w``).
    Miss: ``t`` is the closest approach (``d(q.u) = 0``) and the gap's derivative follows from
    the envelope theorem: ``d gap = -(q.da + h v.dw) / |q| - dr``.
    """
    a, w, r = frame.unpack(theta)
    t, gap = _ray_cylinder(origins, dirs, a, w, r)
    dw, da = _param_derivatives(frame, theta)
    x = origins + t[..., None] * dirs
    v = x - a[..., None, :]
    h = _dot(v, w[..., None, :])
    q = v - h[..., None] * w[..., None, :]
    # (..., N, 5) pieces: q.da_j and v.dw_j
    da_t = np.swapaxes(da, -1, -2)  # (..., 3, 5)
    dw_t = np.swapaxes(dw, -1, -2)
    q_da = q @ da_t
    v_dw = v @ dw_t
    dr = np.zeros(5)
    dr[4] = 1.0
    qu = _dot(q, dirs)
    safe_qu = np.where(np.abs(qu) > 1e-300, qu, 1e-300)
    sig_l = np.broadcast_to(np.asarray(sigma_l, dtype=np.float64), t.shape)
    jr = -(q_da + h[..., None] * v_dw + r[..., None, None] * dr) / (safe_qu * sig_l)[..., None]
    jg = np.zeros_like(jr)
    miss = gap > 0
    if np.any(miss):
        # miss rows only (few): the closest approach H = q.u = 0 -> dt = -(dH/dtheta) / A
        lead = t.shape
        d_m = dirs if dirs.shape[:-1] == lead else np.broadcast_to(dirs, (*lead, 3))
        w_m = np.broadcast_to(w[..., None, :], (*lead, 3))[miss]
        da_m = np.broadcast_to(da_t[..., None, :, :], (*lead, 3, 5))[miss]
        dw_m = np.broadcast_to(dw_t[..., None, :, :], (*lead, 3, 5))[miss]
        u = d_m[miss]
        qm, hm = q[miss], h[miss]
        uw = _dot(u, w_m)
        big_a = np.maximum(1.0 - uw * uw, 1e-300)
        u_da = np.einsum("ki,kij->kj", u, da_m)
        w_da = np.einsum("ki,kij->kj", w_m, da_m)
        u_dw = np.einsum("ki,kij->kj", u, dw_m)
        v_dw_m = v_dw[miss]
        dh = -u_da + uw[:, None] * w_da - v_dw_m * uw[:, None] - hm[:, None] * u_dw
        dt_miss = -dh / big_a[:, None]
        qn = np.maximum(np.linalg.norm(qm, axis=-1), 1e-300)
        dgap = -(q_da[miss] + hm[:, None] * v_dw_m) / qn[:, None] - dr
        jr[miss] = -dt_miss / sig_l[miss][:, None]
        sig_p = np.broadcast_to(np.asarray(sigma_perp, dtype=np.float64), lead)
        jg[miss] = dgap / sig_p[miss][:, None]
    return np.asarray(np.concatenate([jr, jg], axis=-2), dtype=np.float64)


def orthogonal_residuals(theta: FloatArray, frame: _Frame, points: FloatArray, sigma: FloatArray) -> FloatArray:
    """Whitened orthogonal-distance residuals ``(..., N)``."""
    a, w, r = frame.unpack(theta)
    v = points - a[..., None, :]
    vw = _dot(v, w[..., None, :])
    dist = np.sqrt(np.maximum(_dot(v, v) - vw * vw, 0.0))
    return np.asarray((dist - r[..., None]) / sigma, dtype=np.float64)


def orthogonal_jacobian(theta: FloatArray, frame: _Frame, points: FloatArray, sigma: FloatArray) -> FloatArray:
    """Analytic Jacobian ``(..., N, 5)`` of :func:`orthogonal_residuals`."""
    a, w, _ = frame.unpack(theta)
    dw, da = _param_derivatives(frame, theta)
    v = points - a[..., None, :]
    h = _dot(v, w[..., None, :])
    q = v - h[..., None] * w[..., None, :]
    qn = np.maximum(np.linalg.norm(q, axis=-1), 1e-300)
    q_da = q @ np.swapaxes(da, -1, -2)
    v_dw = v @ np.swapaxes(dw, -1, -2)
    dr = np.zeros(5)
    dr[4] = 1.0
    jac = (-(q_da + h[..., None] * v_dw) / qn[..., None] - dr) / np.asarray(sigma)[..., None]
    return np.asarray(jac, dtype=np.float64)


def central_jacobian(fun: Callable[[FloatArray], FloatArray], theta: FloatArray) -> FloatArray:
    """Central-difference Jacobian of a residual function that broadcasts over leading axes
    (a check on the analytic ones). ``theta``: ``(..., 5)``; returns ``(..., m, 5)``."""
    th = np.asarray(theta, dtype=np.float64)
    n = th.shape[-1]
    eye = np.eye(n) * _STEPS[:n]
    pert = np.concatenate([th[..., None, :] + eye, th[..., None, :] - eye], axis=-2)  # (..., 2n, n)
    f = fun(pert)  # (..., 2n, m)
    diff = (f[..., :n, :] - f[..., n:, :]) / (2.0 * _STEPS[:n, None])
    return np.asarray(np.swapaxes(diff, -1, -2), dtype=np.float64)


@dataclass(frozen=True)
class CylinderFit:
    """Result of a cylinder fit.

    ``rmse``: rms of the range residuals (m) for a line-of-sight fit, of the orthogonal distances
    otherwise. ``covariance``: ``(5, 5)`` covariance of ``theta = (t1, t2, s1, s2, r)`` in
    :attr:`frame` (see the module docstring). ``chi2_dof``: sum of squared whitened residuals over
    the degrees of freedom (about 1 when the noise model is right).
    """

    cylinder: Cylinder
    inliers: IntArray
    rmse: float
    covariance: FloatArray
    frame: tuple[FloatArray, FloatArray]
    line_of_sight: bool
    chi2_dof: float
    sigma_scale: float
    plane: tuple[FloatArray, float] | None = None
    base_point: FloatArray | None = None
    n_points: int = 0
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def diameter(self) -> float:
        return self.cylinder.diameter

    @property
    def std_diameter(self) -> float:
        """GUM standard uncertainty of the diameter from the fit covariance: ``2 sqrt(var r)``."""
        return float(2.0 * np.sqrt(max(self.covariance[4, 4], 0.0)))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.size)


Residuals = Callable[[FloatArray], FloatArray]


def _solve(fun: Residuals, jac: Residuals, max_nfev: int) -> FloatArray:
    res = least_squares(
        fun,
        np.zeros(5),
        jac=jac,
        method="lm",
        x_scale=np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3]),
        max_nfev=max_nfev,
    )
    if not np.all(np.isfinite(res.x)):
        raise FitError("cylinder refinement diverged")
    return np.asarray(res.x, dtype=np.float64)


def _covariance(jac: FloatArray) -> FloatArray:
    jtj = jac.T @ jac
    try:
        return np.asarray(np.linalg.inv(jtj), dtype=np.float64)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - degenerate geometry
        raise FitError("cylinder fit is degenerate (singular normal matrix)") from exc


def refine_cylinder(
    points: ArrayLike,
    initial: Cylinder,
    *,
    rays: Rays | None = None,
    sigma: float | None = None,
    max_rounds: int = 3,
    gate: float = INLIER_GATE,
    max_nfev: int = 200,
    work_size: int = 20_000,
    final_full: bool = True,
) -> CylinderFit:
    """Least-squares refinement from ``initial`` with inlier re-selection on ``points``.

    Rounds before the last work on at most ``work_size`` random inliers; the final solve always
    uses every inlier (unless ``final_full`` is false: then the result may come from the subset,
    as a start for further work).

    With ``rays`` (one per point): the line-of-sight fit, covariance from the a priori noise
    model. Without: the orthogonal-distance fit with isotropic ``sigma`` (m); ``sigma=None``
    estimates it from the residuals (the covariance is then scaled by the posterior variance).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FitError(f"points must have shape (N, 3), got {pts.shape}")
    if pts.shape[0] < 6:
        raise FitError(f"a cylinder fit needs at least 6 points, got {pts.shape[0]}")
    if rays is not None and rays.ranges.shape[0] != pts.shape[0]:
        raise FitError("rays and points differ in length")
    cyl = initial.with_point_near(pts.mean(axis=0))
    use_los = rays is not None
    sig = 1.0 if sigma is None else float(sigma)

    def make_fun(frame: _Frame, sel: IntArray) -> tuple[Residuals, Residuals]:
        if rays is not None:
            rs = rays.subset(sel)
            return (
                lambda th: los_residuals(th, frame, rs.origins, rs.dirs, rs.ranges, rs.sigma_l, rs.sigma_perp),
                lambda th: los_jacobian(th, frame, rs.origins, rs.dirs, rs.sigma_l, rs.sigma_perp),
            )
        ps = pts[sel]
        sg = np.asarray(sig)
        return (
            lambda th: orthogonal_residuals(th, frame, ps, sg),
            lambda th: orthogonal_jacobian(th, frame, ps, sg),
        )

    def whitened_all(c: Cylinder) -> FloatArray:
        if rays is not None:
            t, gap = c.ray_range(rays.origins, rays.dirs)
            # a beam may miss the model by at most MISS_GATE lateral sigmas: limb beams of the part
            # miss by a fraction of a millimetre, clutter beside the silhouette by more
            miss = gap / rays.sigma_perp * (gate / MISS_GATE) if np.isfinite(gate) else np.zeros_like(gap)
            return np.asarray(np.maximum(np.abs(rays.ranges - t) / rays.sigma_l, miss), dtype=np.float64)
        return np.asarray(np.abs(c.surface_distance(pts)) / sig, dtype=np.float64)

    idx = np.flatnonzero(whitened_all(cyl) < gate) if use_los else np.arange(pts.shape[0])
    pick = np.random.default_rng(0)

    def solve_on(sel: IntArray, c: Cylinder) -> Cylinder:
        if sel.size < 6:
            raise FitError(f"too few inliers left for a cylinder fit ({sel.size})")
        fr = _Frame.at(c)
        out = fr.cylinder(_solve(*make_fun(fr, sel), max_nfev)).with_point_near(pts[sel].mean(axis=0))
        if out.radius <= 0:
            raise FitError("cylinder refinement gave a non-positive radius")
        return out

    partial_solve = False
    for round_ in range(max_rounds):
        if idx.size < 6:
            raise FitError(f"too few inliers left for a cylinder fit ({idx.size})")
        partial_solve = idx.size > work_size and (round_ < max_rounds - 1 or not final_full)
        sel = np.sort(pick.choice(idx, work_size, replace=False)) if partial_solve else idx
        cyl = solve_on(sel, cyl)
        if not use_los and sigma is None:
            sig = max(float(np.sqrt(np.mean(np.square(cyl.surface_distance(pts[idx]))))), 1e-9)
        if round_ == max_rounds - 1:
            break
        # hysteresis: a point joins below ``gate`` and leaves only above 1.5 ``gate``, so the
        # few limb beams that carry most of the information on the radius are not dropped by a
        # model that is still moving
        wa = whitened_all(cyl)
        member = np.zeros(pts.shape[0], dtype=bool)
        member[idx] = True
        new_idx = np.flatnonzero((wa < gate) | (member & (wa < 1.5 * gate)))
        if np.array_equal(new_idx, idx):
            break
        idx = new_idx
    if partial_solve and final_full:
        cyl = solve_on(idx, cyl)

    frame = _Frame.at(cyl)
    fun, jfun = make_fun(frame, idx)
    r0 = fun(np.zeros(5))
    jac = jfun(np.zeros(5))
    dof = max(idx.size - 5, 1)
    chi2_dof = float(np.sum(r0 * r0) / dof)
    cov = _covariance(jac)
    scale = 1.0
    if use_los:
        assert rays is not None
        t, _ = cyl.ray_range(rays.origins[idx], rays.dirs[idx])
        rmse = float(np.sqrt(np.mean(np.square(rays.ranges[idx] - t))))
    else:
        rmse = float(np.sqrt(np.mean(np.square(cyl.surface_distance(pts[idx])))))
        if sigma is None:
            scale = chi2_dof  # posterior variance factor (sigma estimated from the data)
            cov = cov * scale
    return CylinderFit(
        cylinder=cyl,
        inliers=idx,
        rmse=rmse,
        covariance=cov,
        frame=(frame.e1, frame.e2),
        line_of_sight=use_los,
        chi2_dof=chi2_dof,
        sigma_scale=float(np.sqrt(scale)),
        n_points=int(pts.shape[0]),
    )


# --------------------------------------------------------------------------- detection


@dataclass(frozen=True)
class DetectOptions:
    """Tuning of :func:`detect_cylinder` and :func:`fit_cylinder`; distances in metres.

    ``attempts``: independent RANSAC runs (stopping early at a plausible fit); while no fit is
    plausible (see :func:`_plausible`) up to ``max_attempts``. The best fit by :func:`_better` wins.
    ``grazing_sigma``: the lateral term of the line-of-sight fit's weights (m; negative: the
    default :data:`GRAZING_SIGMA`; 0: the plain maximum-likelihood fit), see
    :func:`grazing_weighted_fit`. ``bias_correction``: subtract the fit's second-order bias
    (:func:`second_order_bias`) from a line-of-sight fit.
    """

    sample_size: int = 3000
    normal_k: int = 32
    threshold: float = 0.03
    normal_weight: float = 0.02
    radius_range: tuple[float, float] = (0.01, 2.0)
    plane_threshold: float = 0.02
    plane_normal_weight: float = 0.02
    plane_min_share: float = 0.05
    max_trials: int = 2000
    min_trials: int = 200
    min_inliers: int = 20
    attempts: int = 3
    max_attempts: int = 10
    grazing_sigma: float = -1.0
    bias_correction: bool = True


def detect_plane(
    points: ArrayLike,
    threshold: float,
    rng: np.random.Generator,
    min_share: float = 0.05,
    normals: ArrayLike | None = None,
    normal_weight: float = 0.02,
) -> tuple[FloatArray, float, NDArray[np.bool_]] | None:
    """Dominant plane ``(normal, offset, inlier mask)`` of a cloud, or ``None`` if it holds less
    than ``min_share`` of the points. With ``normals``, a point counts only if its normal agrees
    with the plane's (see :class:`lrms.ransac.PlaneModel`)."""
    pts = np.asarray(points, dtype=np.float64)
    data = pts if normals is None else np.hstack([pts, np.asarray(normals, dtype=np.float64)])

    class _Plane(PlaneModel):
        pass

    _Plane.normal_weight = normal_weight if normals is not None else 0.0
    try:
        model, mask = ransac(data, _Plane, 3, threshold, max_trials=1500, min_trials=400, rng=rng, score_size=5000)
    except FitError:
        return None
    if np.count_nonzero(mask) < min_share * pts.shape[0]:
        return None
    return model.normal, model.offset, mask


def detect_cylinder(
    points: ArrayLike, options: DetectOptions | None = None, rng: np.random.Generator | None = None
) -> tuple[Cylinder, tuple[FloatArray, float] | None]:
    """Rough cylinder (RANSAC, 2 points + normals) and the table plane if one was found."""
    opt = options if options is not None else DetectOptions()
    g = rng if rng is not None else np.random.default_rng(0)
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if n < opt.min_inliers:
        raise FitError(f"too few points to detect a cylinder: {n} (need {opt.min_inliers})")
    sub = pts[g.choice(n, size=opt.sample_size, replace=False)] if n > opt.sample_size else pts
    normals = estimate_normals(sub, opt.normal_k)
    data = np.hstack([sub, normals])

    class _Model(CylinderModel):
        normal_weight = opt.normal_weight
        radius_range = opt.radius_range

    min_inl = max(opt.min_inliers // 2, int(0.02 * data.shape[0]), 6)
    model, _ = ransac(
        data,
        _Model,
        2,
        opt.threshold,
        max_trials=opt.max_trials,
        min_trials=opt.min_trials,
        min_inliers=min_inl,
        refine=False,
        rng=g,
    )
    assert model.cylinder is not None
    return model.cylinder, support_plane(pts, model.cylinder, opt)


def support_plane(pts: FloatArray, cyl: Cylinder, opt: DetectOptions) -> tuple[FloatArray, float] | None:
    """The plane the part stands on: perpendicular to the axis (within 10 deg), the most
    populated such slab among the points off the cylinder, refined by total least squares.

    (A free plane RANSAC is unreliable here: at the rig's grazing view of a table the points
    come in sparse scan lines, so their neighbourhood normals are ill-defined, and the front of
    the part is as flat as the table within the range noise.)
    """
    dist = np.abs(cyl.surface_distance(pts))
    off = pts[dist > opt.threshold]
    if off.shape[0] < max(opt.min_inliers, opt.plane_min_share * pts.shape[0]):
        return None
    s = off @ cyl.direction
    width = opt.plane_threshold
    edges = np.arange(s.min(), s.max() + 2 * width, width)
    if edges.size < 2:
        return None
    counts, edges = np.histogram(s, bins=edges)
    # the part stands on the plane: a slab through the middle of the points on the candidate is
    # not its support (a dense band of the part's own points, left off a wrong candidate, can
    # outnumber the table), so only slabs beyond the 5th / 95th percentile of the candidate's
    # points along the axis, less two slab widths, are eligible
    s_on = pts[dist <= opt.threshold] @ cyl.direction
    if s_on.size >= opt.min_inliers:
        lo, hi = np.percentile(s_on, [5.0, 95.0])
        mid = 0.5 * (edges[:-1] + edges[1:])
        counts = np.where((mid <= lo + 2 * width) | (mid >= hi - 2 * width), counts, 0)
    pair = counts[:-1] + counts[1:] if counts.size > 1 else counts
    if not np.any(pair > 0):
        return None
    i = int(np.argmax(pair))
    centre = edges[i + 1] if counts.size > 1 else 0.5 * (edges[0] + edges[1])
    near = off[np.abs(s - centre) < width]
    if near.shape[0] < max(opt.min_inliers, opt.plane_min_share * pts.shape[0]):
        return None
    model = PlaneModel()
    for _ in range(2):
        if not model.estimate(near):
            return None
        near = off[model.residuals(off) < width]
        if near.shape[0] < 3:
            return None
    if abs(float(model.normal @ cyl.direction)) < np.cos(np.deg2rad(10.0)):
        return None
    return model.normal, model.offset


#: Radius offsets (in units of sigma_l) of the extra starts of the line-of-sight fit.
MULTISTART = (-0.2, -0.1, 0.1, 0.2)


def _multistart(pts: FloatArray, rays: Rays, fit: CylinderFit, opt: DetectOptions) -> CylinderFit:
    """Restart the line-of-sight fit from radii around the solution and keep the lowest cost.

    The range residual of a beam near the silhouette has a kink where the beam becomes tangent
    (the hit range varies like a square root of the radius there), so the likelihood has
    several local minima a few tenths of sigma_l apart; one LM run from the orthogonal fit's
    (biased) start does not always reach the best. The starts are compared on the same inliers
    (a random subset of at most 5000 of them for large clouds), the winner is refined on all.
    """
    idx = fit.inliers
    work = 5_000
    sel = idx if idx.size <= work else np.sort(np.random.default_rng(2).choice(idx, work, replace=False))
    sub_pts, sub_rays = pts[sel], rays.subset(sel)
    sig = float(np.median(rays.sigma_l))
    best_cyl, best_cost = fit.cylinder, np.inf
    for dr in (0.0, *MULTISTART):
        start = Cylinder(fit.cylinder.point, fit.cylinder.direction, fit.cylinder.radius + dr * sig)
        try:
            trial = refine_cylinder(sub_pts, start, rays=sub_rays, gate=np.inf, max_rounds=1)
        except FitError:
            continue
        if trial.chi2_dof < best_cost:
            best_cyl, best_cost = trial.cylinder, trial.chi2_dof
    return refine_cylinder(pts, best_cyl, rays=rays, max_rounds=1)


def _los_fit(pts: FloatArray, rays: Rays, start: Cylinder, opt: DetectOptions) -> CylinderFit:
    """The line-of-sight fit from ``start`` on candidate points (their beams ``rays``): inlier
    selection from ``start``, then :func:`_multistart` around its solution."""
    fit = refine_cylinder(pts, start, rays=rays, max_rounds=4, final_full=False, work_size=5000)
    return _multistart(pts, rays, fit, opt)


def _refine_from(
    pts: FloatArray,
    initial: Cylinder,
    line_of_sight: bool,
    rays: Rays | None,
    opt: DetectOptions,
) -> CylinderFit:
    """Orthogonal polish near ``initial``, then the final fit on the whole cloud's candidates."""
    band = np.flatnonzero(np.abs(initial.surface_distance(pts)) < 1.5 * opt.threshold)
    if band.size < opt.min_inliers:
        raise FitError(f"no cylinder found: only {band.size} points near the best candidate")
    if band.size > 5000:  # a rough start needs no more
        band = np.sort(np.random.default_rng(1).choice(band, 5000, replace=False))
    rough = refine_cylinder(pts[band], initial, sigma=None, max_rounds=2, gate=3.0)
    lo, hi = opt.radius_range
    if not lo <= rough.cylinder.radius <= hi:
        raise FitError(f"no cylinder found: radius {rough.cylinder.radius:.4g} m outside [{lo}, {hi}] m")
    if line_of_sight:
        assert rays is not None
        t, gap = rough.cylinder.ray_range(rays.origins, rays.dirs)
        cand = np.flatnonzero((np.abs(rays.ranges - t) < 2.0 * opt.threshold) & (gap < 2.0 * opt.threshold))
        if cand.size < opt.min_inliers:
            raise FitError(f"no cylinder found: only {cand.size} points on the candidate's lines of sight")
        fit = _los_fit(pts[cand], rays.subset(cand), rough.cylinder, opt)
    else:
        cand = np.flatnonzero(np.abs(rough.cylinder.surface_distance(pts)) < 2.0 * opt.threshold)
        if cand.size < opt.min_inliers:
            raise FitError(f"no cylinder found: only {cand.size} points near the candidate")
        fit = refine_cylinder(pts[cand], rough.cylinder, sigma=None, max_rounds=4, gate=3.0)
    if not lo <= fit.cylinder.radius <= hi:
        raise FitError(f"no cylinder found: radius {fit.cylinder.radius:.4g} m outside [{lo}, {hi}] m")
    inl = cand[fit.inliers]
    if inl.size < opt.min_inliers:
        raise FitError(f"no cylinder found: only {inl.size} inliers after refinement")
    return CylinderFit(
        cylinder=fit.cylinder,
        inliers=inl,
        rmse=fit.rmse,
        covariance=fit.covariance,
        frame=fit.frame,
        line_of_sight=fit.line_of_sight,
        chi2_dof=fit.chi2_dof,
        sigma_scale=fit.sigma_scale,
        n_points=int(pts.shape[0]),
    )


def _off_support(
    pts: FloatArray, cyl: Cylinder, plane: tuple[FloatArray, float] | None, opt: DetectOptions
) -> IntArray:
    """Indices of the points not on the support plane (a plane nearly perpendicular to the axis:
    the table the part stands on, whose points in front of the base would pass for the part)."""
    if plane is None or abs(float(plane[0] @ cyl.direction)) < 0.9:
        return np.arange(pts.shape[0])
    return np.flatnonzero(np.abs(pts @ plane[0] - plane[1]) > opt.plane_threshold)


def _reindex(fit: CylinderFit, use: IntArray, n_points: int) -> CylinderFit:
    return CylinderFit(
        cylinder=fit.cylinder,
        inliers=use[fit.inliers],
        rmse=fit.rmse,
        covariance=fit.covariance,
        frame=fit.frame,
        line_of_sight=fit.line_of_sight,
        chi2_dof=fit.chi2_dof,
        sigma_scale=fit.sigma_scale,
        n_points=n_points,
    )


#: A line-of-sight fit whose chi2/dof exceeds this is not explained by the range noise alone.
CHI2_PLAUSIBLE = 1.3


def _better(a: CylinderFit, b: CylinderFit) -> bool:
    """Is fit ``a`` preferable to ``b``? Fits the noise model explains (chi2/dof below
    CHI2_PLAUSIBLE) beat those it does not; among equals, more inliers win (a wrong, larger
    cylinder through the part and its surroundings can collect more points, at a worse chi2)."""
    if a.line_of_sight and b.line_of_sight:
        ok_a, ok_b = a.chi2_dof < CHI2_PLAUSIBLE, b.chi2_dof < CHI2_PLAUSIBLE
        if ok_a != ok_b:
            return ok_a
        if not ok_a:
            return a.chi2_dof < b.chi2_dof
    return a.n_inliers > b.n_inliers


def _noise_explains(fit: CylinderFit) -> bool:
    return fit.chi2_dof < CHI2_PLAUSIBLE or not fit.line_of_sight


def _plausible(fit: CylinderFit, pts: FloatArray, start: Cylinder, opt: DetectOptions) -> bool:
    """Accept a fit without further RANSAC attempts: the noise model explains it and it keeps
    most of the points that lay near the RANSAC candidate."""
    near = int(np.count_nonzero(np.abs(start.surface_distance(pts)) < opt.threshold))
    chi_ok = fit.chi2_dof < CHI2_PLAUSIBLE or not fit.line_of_sight
    return chi_ok and fit.n_inliers >= 0.7 * near


#: Lateral standard deviation (m) of a beam's footprint in the estimator's weights
#: (:func:`grazing_weighted_fit`): a beam meeting the surface at incidence ``i`` is weighted by
#: ``1 / (sigma_l^2 + (tan(i) GRAZING_SIGMA)^2)``. 0 gives the plain maximum-likelihood fit.
GRAZING_SIGMA = 2e-4
#: Smallest cosine of incidence in those weights (a beam that misses the model counts as this).
_COS_FLOOR = 0.01


def incidence_cosines(cyl: Cylinder, rays: Rays) -> FloatArray:
    """|cos| of the angle between each beam and the surface normal where it meets ``cyl``
    (0 for a beam that misses)."""
    t, gap = cyl.ray_range(rays.origins, rays.dirs)
    q = cyl.radial(rays.origins + t[:, None] * rays.dirs)
    c = np.abs(_dot(q, rays.dirs)) / np.maximum(np.linalg.norm(q, axis=1), 1e-300)
    return np.asarray(np.where(gap > 0, 0.0, c), dtype=np.float64)


def grazing_sigmas(cyl: Cylinder, rays: Rays, sigma_lat: float) -> FloatArray:
    """Per-beam ``sqrt(sigma_l^2 + (tan(incidence) sigma_lat)^2)`` at the model ``cyl``."""
    c = np.maximum(incidence_cosines(cyl, rays), _COS_FLOOR)
    tan = np.sqrt(1.0 - c * c) / c
    return np.asarray(np.sqrt(rays.sigma_l**2 + (tan * sigma_lat) ** 2), dtype=np.float64)


def grazing_weighted_fit(
    pts: FloatArray,
    rays: Rays,
    fit: CylinderFit,
    sigma_lat: float = GRAZING_SIGMA,
    rounds: int = 3,
    radius_range: tuple[float, float] | None = None,
) -> CylinderFit:
    """Refit ``fit``'s inliers with the near-grazing beams' leverage moderated.

    The hit range of a beam near the silhouette varies like the square root of the radius, so
    the few beams at cos(incidence) of 0.03-0.1 carry much of the Fisher information while the
    linearised model fails there, and a clutter point in front of the part on such a beam pulls
    the fit hardest. The weights ``1 / (sigma_l^2 + (tan(i) sigma_lat)^2)`` (a lateral term of
    the order of the beam's pointing / footprint) are recomputed at the current solution for
    ``rounds`` rounds. An estimator choice: the Cramer-Rao bound is unchanged. The covariance
    is the sandwich ``A^-1 J^T V J A^-1`` of this weighted fit under the rig's noise
    (``V = sigma_l^2 / s_i^2``), ``chi2_dof`` the plain one with ``sigma_l``. Keeps ``fit`` if a
    refit fails or leaves ``radius_range`` (the detection's; default ``DetectOptions()``'s).
    """
    if sigma_lat <= 0 or not fit.line_of_sight:
        return fit
    idx = fit.inliers
    sub_pts, sub = pts[idx], rays.subset(idx)
    cyl = fit.cylinder
    work = np.arange(idx.size)
    if idx.size > 10_000:  # all rounds but the last on a subset (large clouds)
        work = np.sort(np.random.default_rng(3).choice(idx.size, 5_000, replace=False))
    try:
        for k in range(rounds):
            use = work if k < rounds - 1 else np.arange(idx.size)
            part = sub.subset(use)
            sig = grazing_sigmas(cyl, part, sigma_lat)
            weighted = Rays(part.origins, part.dirs, part.ranges, sig, part.sigma_perp)
            # a large cloud's last round starts next to its optimum: a few LM steps suffice
            nfev = 200 if use.size <= 10_000 or k < rounds - 1 else 4
            cyl = refine_cylinder(sub_pts[use], cyl, rays=weighted, gate=np.inf, max_rounds=1, max_nfev=nfev).cylinder
    except FitError:
        return fit
    lo, hi = DetectOptions().radius_range if radius_range is None else radius_range
    if not lo <= cyl.radius <= hi:
        return fit
    sig = grazing_sigmas(cyl, sub, sigma_lat)
    frame = _Frame.at(cyl)
    jac = los_jacobian(np.zeros(5), frame, sub.origins, sub.dirs, sig, sub.sigma_perp)
    var = np.concatenate([np.square(sub.sigma_l / sig), np.ones(idx.size)])
    a_inv = _covariance(jac)
    cov = a_inv @ (jac.T @ (var[:, None] * jac)) @ a_inv
    res = los_residuals(np.zeros(5), frame, sub.origins, sub.dirs, sub.ranges, sub.sigma_l, sub.sigma_perp)
    t, _ = cyl.ray_range(sub.origins, sub.dirs)
    return replace(
        fit,
        cylinder=cyl,
        rmse=float(np.sqrt(np.mean(np.square(sub.ranges - t)))),
        covariance=np.asarray(cov, dtype=np.float64),
        frame=(frame.e1, frame.e2),
        chi2_dof=float(np.sum(res * res) / max(idx.size - 5, 1)),
        sigma_scale=1.0,
        extra={**fit.extra, "grazing_sigma_m": float(sigma_lat)},
    )


def second_order_bias(fit: CylinderFit, rays: Rays) -> FloatArray:
    """Second-order bias ``E[theta_hat] - theta`` (Box 1971) of a line-of-sight fit, in its frame.

    ``rays``: the fit's inlier beams (one per inlier, as :func:`fit_cylinder` builds them). For the
    fit ``min sum ((l_i - t_i(theta)) / s_i)^2`` the bias to order ``sigma^2`` is
    ``-1/2 A^-1 sum J_i tr(H_i C) / s_i^2``, with ``J_i, H_i`` the gradient and Hessian of the
    predicted range ``t_i``, ``A = sum J_i J_i^T / s_i^2`` and ``C`` the parameters' covariance
    (:attr:`CylinderFit.covariance`). The local Hessian of a near-tangent beam's range is
    singular (the range goes like a square root at the silhouette), so ``tr(H_i C)`` is replaced
    by what it stands for, ``2 (E[t_i(theta + delta)] - t_i(theta))`` for ``delta ~ N(0, C)``,
    taken with the 3-point Gauss-Hermite rule along each principal axis of ``C``: nodes ``0`` and
    ``+-sqrt(3 lambda_k) v_k`` (the unscented transform's points for ``kappa = 3 - n``), exact for
    polynomials up to degree 5. ``s_i``: the grazing weights' sigmas when the fit carries them
    (``extra["grazing_sigma_m"]``), else ``sigma_l``; for weights computed at the solution this is
    the leading term only. Miss rows (beams passing the model) take part through their whitened
    miss distance. Checked by Monte Carlo in tests/core/test_cylinder.py and docs/cylinder.md.
    """
    if not fit.line_of_sight:
        raise FitError("the second-order bias is defined for a line-of-sight fit")
    if rays.ranges.shape[0] != fit.inliers.size:
        raise FitError("one beam per inlier is needed for the bias")
    frame = _fit_frame(fit)
    lat = fit.extra.get("grazing_sigma_m", 0.0)
    sig = grazing_sigmas(fit.cylinder, rays, lat) if lat > 0 else np.broadcast_to(rays.sigma_l, rays.ranges.shape)
    lam, vec = np.linalg.eigh(0.5 * (fit.covariance + fit.covariance.T))
    steps = (np.sqrt(3.0 * np.maximum(lam, 0.0)) * vec).T  # rows: the Gauss-Hermite nodes' offsets

    def res(th: FloatArray) -> FloatArray:
        return los_residuals(th, frame, rays.origins, rays.dirs, rays.ranges, sig, rays.sigma_perp)

    centre = res(np.zeros(5))
    second = np.zeros_like(centre)
    for step in steps:  # 5 directions, each a vectorized pass over the beams
        second += (res(step) + res(-step) - 2.0 * centre) / 3.0
    jac = los_jacobian(np.zeros(5), frame, rays.origins, rays.dirs, sig, rays.sigma_perp)
    # whitened residuals r_i = (l_i - t_i) / s_i: J_r = -J_t / s_i and second = -"tr(H_i C)" / s_i
    return np.asarray(-0.5 * (_covariance(jac) @ (jac.T @ second)), dtype=np.float64)


def _fit_frame(fit: CylinderFit) -> _Frame:
    """The local frame of ``fit``'s covariance (theta = 0 at its solution)."""
    cyl = fit.cylinder
    return _Frame(cyl.point, cyl.direction, fit.frame[0], fit.frame[1], cyl.radius)


def bias_corrected(fit: CylinderFit, rays: Rays) -> CylinderFit:
    """``fit`` with its :func:`second_order_bias` subtracted (``rays``: its inlier beams). The
    covariance is kept (the correction is of second order); ``extra["bias_correction_diameter_m"]``
    records what was subtracted from the diameter."""
    b = second_order_bias(fit, rays)
    new = _fit_frame(fit).cylinder(-b)
    if not new.radius > 0:
        raise FitError("the bias correction gave a non-positive radius")
    return replace(fit, cylinder=new, extra={**fit.extra, "bias_correction_diameter_m": float(2.0 * b[4])})


#: Clearance (m) above the table, along the axis, of a beam's predicted first hit on the fitted
#: part for the beam to count as a part echo (:func:`_select_above_table`). The selection is by
#: the model, not by the measured range, so it does not bias the fit; the clearance covers the
#: beam's pointing noise (``l sigma_alpha`` = 0.08 mm at 2.5 m) and the error of the table height
#: and axis (< 0.1 mm) many times over. (0.5 mm let table echoes in front of the base in, +0.04 mm
#: mean diameter error on 100 sweeps; 1 and 3 mm did not, docs/cylinder.md section 4.)
BASE_CLEARANCE = 2e-3


def table_height(
    pts: FloatArray, fit: CylinderFit, plane: tuple[FloatArray, float], opt: DetectOptions
) -> tuple[FloatArray, float, FloatArray] | None:
    """The table under the fitted part as a plane perpendicular to the fitted axis.

    Returns ``(up, height, origin)``: the axis direction pointing from the table to the part and
    the table's height along it, measured from ``origin`` (the fitted axis point), or ``None``
    when the support plane is not under the part or too few table points lie near the part. The
    height is the mode (2 mm bins, then the mean within 3 mm) of the axial coordinates of the
    points off the part within 0.3 m of its surface and 50 mm of the support plane: the part
    stands on the table, so the table's normal is the axis, and the few points near the part
    fix its height better than the plane fitted to the whole grazing table (tilted by 1-4 deg
    in some sweeps).
    """
    cyl = fit.cylinder
    pn, po = plane
    up = cyl.direction
    denom = float(pn @ up)
    if abs(denom) < 0.9:
        return None
    s = (pts - cyl.point) @ up
    s0 = (po - float(pn @ cyl.point)) / denom
    if s0 > float(np.median(s[fit.inliers])):
        up, s, s0 = -up, -s, -s0
    dist = cyl.axis_distance(pts)
    near = (dist > cyl.radius + opt.threshold) & (dist < cyl.radius + 0.3) & (np.abs(s - s0) < 0.05)
    if np.count_nonzero(near) < opt.min_inliers:
        return None
    counts, edges = np.histogram(s[near], bins=np.arange(s0 - 0.05, s0 + 0.0501, 0.002))
    mode = 0.5 * (edges[int(np.argmax(counts))] + edges[int(np.argmax(counts)) + 1])
    for _ in range(2):
        sel = near & (np.abs(s - mode) < 0.003)
        if np.count_nonzero(sel) < opt.min_inliers:
            return None
        mode = float(np.median(s[sel]))
    return np.asarray(up, dtype=np.float64), float(np.mean(s[sel])), cyl.point


#: Bin width (m) along the axis of the inlier density that locates the part's top.
TOP_BIN = 0.02


def _top_height(h_cand: FloatArray, h_inl: FloatArray) -> float:
    """Height of the part's top end above the table, from the predicted hit heights of its
    beams: the upper edge (plus one bin) of the last :data:`TOP_BIN` bin holding at least a fifth
    of the median count of the fit's inliers per bin. Above it the candidates are beams that
    pass over the part and meet the model's infinite extension: clutter, never the part. A part
    whose top is not in view keeps its dense bins to the end, and nothing is cut."""
    top = float(np.max(h_cand))
    edges = np.arange(0.0, top + TOP_BIN, TOP_BIN)
    if edges.size < 4:
        return top
    counts, _ = np.histogram(h_inl, bins=edges)
    filled = counts[counts > 0]
    if filled.size == 0:
        return top
    dense = np.flatnonzero(counts >= 0.2 * float(np.median(filled)))
    return min(top, float(edges[dense[-1] + 1]) + TOP_BIN)


def _select_above_table(
    pts: FloatArray, rays: Rays, fit: CylinderFit, table: tuple[FloatArray, float, FloatArray], opt: DetectOptions
) -> CylinderFit:
    """Refit on the beams whose predicted first hit on the fitted part lies at least
    :data:`BASE_CLEARANCE` above the table (instead of cutting a slab of the support plane's
    width, which drops the part's bottom 20 mm) and not above the part's top
    (:func:`_top_height`), within the candidate gate of the detection. Keeps ``fit`` if the refit
    fails."""
    up, height, origin = table
    t, gap = fit.cylinder.ray_range(rays.origins, rays.dirs)
    h = (rays.origins + t[:, None] * rays.dirs - origin) @ up - height
    gate = 2.0 * opt.threshold
    ok = (h >= BASE_CLEARANCE) & (np.abs(rays.ranges - t) < gate) & (gap < gate)
    if np.count_nonzero(ok) < opt.min_inliers:
        return fit
    ok &= h <= _top_height(h[ok], h[fit.inliers])
    cand = np.flatnonzero(ok)
    if cand.size < opt.min_inliers:
        return fit
    try:
        new = _los_fit(pts[cand], rays.subset(cand), fit.cylinder, opt)
    except FitError:
        return fit
    lo, hi = opt.radius_range
    if not lo <= new.cylinder.radius <= hi or new.n_inliers < opt.min_inliers:
        return fit
    return _reindex(new, cand, pts.shape[0])


def fit_cylinder(
    points: ArrayLike,
    *,
    line_of_sight: bool = True,
    p: float = kinematics.DEFAULT_P,
    noise: NoiseModel | None = None,
    rays: Rays | None = None,
    options: DetectOptions | None = None,
    initial: Cylinder | None = None,
    rng: np.random.Generator | None = None,
) -> CylinderFit:
    """Detect and fit the cylinder in a rig-frame cloud.

    ``line_of_sight``: refine with the range residual along each point's beam; the beams come from
    ``rays`` if given, else from inverting Eq. 1 with the rig at the origin and inner parameter
    ``p``. Otherwise the orthogonal-distance fit with isotropic noise (``sigma`` estimated from
    the residuals). ``initial`` skips detection. Raises :class:`FitError` when no cylinder is found.
    """
    nm = noise if noise is not None else NoiseModel()
    opt = options if options is not None else DetectOptions(threshold=max(0.03, 2.5 * nm.sigma_l))
    g = rng if rng is not None else np.random.default_rng(0)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FitError(f"points must have shape (N, 3), got {pts.shape}")
    finite = np.all(np.isfinite(pts), axis=1)
    if not np.all(finite):
        raise FitError(f"{int(np.count_nonzero(~finite))} point(s) are not finite")
    if pts.shape[0] < opt.min_inliers:
        raise FitError(f"too few points for a cylinder: {pts.shape[0]} (need {opt.min_inliers})")
    if rays is not None and rays.ranges.shape[0] != pts.shape[0]:
        raise FitError("rays and points differ in length")
    rr = (rays if rays is not None else rays_from_points(pts, p, nm)) if line_of_sight else None
    best: CylinderFit | None = None
    plane: tuple[FloatArray, float] | None = None
    errors: list[str] = []
    n_try = 1 if initial is not None else max(opt.attempts, opt.max_attempts, 1)
    for attempt in range(n_try):
        if attempt >= max(opt.attempts, 1) and best is not None and _noise_explains(best):
            break
        try:
            if initial is not None:
                start, pl = initial, None
            else:
                start, pl = detect_cylinder(pts, opt, g)
            use = _off_support(pts, start, pl, opt)
            fit = _refine_from(pts[use], start, line_of_sight, None if rr is None else rr.subset(use), opt)
            fit = _reindex(fit, use, pts.shape[0])
        except FitError as exc:
            errors.append(str(exc))
            continue
        if best is None or _better(fit, best):
            best, plane = fit, pl
        if initial is None and _plausible(fit, pts, start, opt):
            break
    if best is None:
        last = errors[-1] if errors else "no candidate"
        raise FitError(last if last.startswith("no cylinder found") else f"no cylinder found: {last}")
    base = None
    if plane is not None:
        pn, po = plane
        denom = float(pn @ best.cylinder.direction)
        if abs(denom) > 0.9:  # the support plane: nearly perpendicular to the axis
            s = (po - float(pn @ best.cylinder.point)) / denom
            base = best.cylinder.point + s * best.cylinder.direction
        if rr is not None and initial is None:
            table = table_height(pts, best, plane, opt)
            if table is not None:
                best = _select_above_table(pts, rr, best, table, opt)
                up, height, origin = table
                base = best.cylinder.point + (height - float((best.cylinder.point - origin) @ up)) * up
    if rr is not None:
        lat = GRAZING_SIGMA if opt.grazing_sigma < 0 else opt.grazing_sigma
        best = grazing_weighted_fit(pts, rr, best, lat, radius_range=opt.radius_range)
        if opt.bias_correction:
            best = bias_corrected(best, rr.subset(best.inliers))
    return replace(best, plane=plane, base_point=base, n_points=int(pts.shape[0]))
