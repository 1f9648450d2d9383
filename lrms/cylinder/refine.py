"""Refinement: the line-of-sight and orthogonal residuals with their analytic Jacobians, the
fit result, and :func:`refine_cylinder` (least squares with inlier re-selection)."""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.cylinder.lm import LosProblem, OrthogonalProblem, levenberg_marquardt
from lrms.cylinder.lm import covariance as lm_covariance
from lrms.cylinder.model import Cylinder, Rays, _dot, _ray_cylinder, perpendicular_frame
from lrms.errors import FitError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Inlier gate on the whitened residual during refinement.
INLIER_GATE = 4.0
#: Largest miss distance of an inlier's beam, in lateral standard deviations.
MISS_GATE = 2.0
#: Parameter steps for the central-difference Jacobian: tilt (rad), shift (m), radius (m).
_STEPS = np.array([1e-6, 1e-6, 1e-6, 1e-6, 1e-6])


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
    from scipy.optimize import least_squares  # lazy: only the fallback path needs it

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


def hit_information(problem: LosProblem) -> LosProblem:
    """``problem`` with its miss rows (``gap / sigma_perp``) weighted zero: the problem whose normal
    matrix is the fit's information for its covariance.

    A beam that misses the model by a fraction of ``sigma_perp`` (an inlier may miss by up to
    :data:`MISS_GATE` of them) has a miss distance that is a kink in the parameters: it is a row
    of weight ``1 / sigma_perp^2`` (``sigma_perp`` of the pointing noise, 0.07 mm at 2 m) on the
    miss side and none once the model meets the beam, a fraction of the radius' standard error
    away. Counted as information, one or two such beams took the diameter's ``u`` from 0.51 to
    0.24 mm and ten to 0.05 mm while the scatter over sweeps was 0.3-0.4 mm (docs/cylinder.md,
    "miss rows in the covariance"). The estimator keeps them (they hold the silhouette); its
    covariance counts the beam's range row only, continuous with the grazing hit it turns into.
    """
    out = copy.copy(problem)
    out.isp = np.zeros_like(problem.isp)
    return out


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
    covariance: bool = True,
) -> CylinderFit:
    """Least-squares refinement from ``initial`` with inlier re-selection on ``points``.

    Rounds before the last work on at most ``work_size`` random inliers (those of the lowest rank
    in one random order of the points, so consecutive rounds share most of them); the final solve always
    uses every inlier (unless ``final_full`` is false: then the result may come from the subset,
    as a start for further work).

    With ``rays`` (one per point): the line-of-sight fit, covariance from the a priori noise
    model. Without: the orthogonal-distance fit with isotropic ``sigma`` (m); ``sigma=None``
    estimates it from the residuals (the covariance is then scaled by the posterior variance).
    Each solve is :func:`lrms.cylinder.lm.levenberg_marquardt` with at most ``max_nfev`` steps.
    ``covariance=False``: the fit's covariance is not computed (all NaN; no Jacobian on the
    inliers) for a fit that only starts further work (the multi-start's start and inliers).
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

    def whitened_all(c: Cylinder) -> FloatArray:
        if rays is not None:
            t, gap = c.ray_range(rays.origins, rays.dirs)
            # a beam may miss the model by at most MISS_GATE lateral sigmas: limb beams of the part
            # miss by a fraction of a millimetre, clutter beside the silhouette by more
            miss = gap / rays.sigma_perp * (gate / MISS_GATE) if np.isfinite(gate) else np.zeros_like(gap)
            return np.asarray(np.maximum(np.abs(rays.ranges - t) / rays.sigma_l, miss), dtype=np.float64)
        return np.asarray(np.abs(c.surface_distance(pts)) / sig, dtype=np.float64)

    idx = np.flatnonzero(whitened_all(cyl) < gate) if use_los else np.arange(pts.shape[0])
    # the subsets of the rounds: the ``work_size`` inliers of the lowest rank in one random order
    # of the points, so a round whose inliers changed little solves on nearly the same subset and
    # starts next to its optimum (a fresh draw per round moved it by the subset's noise: a full
    # solve of 20-25 steps each round)
    rank: list[IntArray] = []

    def subset_of(sel: IntArray) -> IntArray:
        if not rank:
            rank.append(np.random.default_rng(0).permutation(pts.shape[0]))
        r = rank[0][sel]
        # the ranks below a cut that keeps about ``work_size`` of them (a pass, no partition of
        # the whole set), then exactly the lowest ``work_size`` of those
        below = np.flatnonzero(r < int(1.2 * work_size * pts.shape[0] / sel.size) + 1)
        if below.size < work_size:
            below = np.argpartition(r, work_size)[:work_size]
        elif below.size > work_size:
            below = below[np.argpartition(r[below], work_size)[:work_size]]
        return np.sort(sel[below])

    last: list[tuple[IntArray, LosProblem]] = []  # the last line-of-sight problem and its rows

    def problem(sel: IntArray) -> LosProblem | OrthogonalProblem:
        if rays is not None:
            if last and last[0][0] is sel:
                return last[0][1]
            # ``sel`` is sorted and unique: as many rows as the beams are all of them, in order
            los = LosProblem(rays) if sel.size == rays.ranges.shape[0] else LosProblem.of_rows(rays, sel)
            last[:] = [(sel, los)]
            return los
        return OrthogonalProblem(pts[sel], sig)

    def solve_on(sel: IntArray, c: Cylinder) -> Cylinder:
        if sel.size < 6:
            raise FitError(f"too few inliers left for a cylinder fit ({sel.size})")
        out = levenberg_marquardt(problem(sel), c, max_iter=max_nfev)[0] if max_nfev > 0 else c
        out = out.with_point_near((pts if sel.size == pts.shape[0] else pts[sel]).mean(axis=0))
        if out.radius <= 0:
            raise FitError("cylinder refinement gave a non-positive radius")
        return out

    partial_solve = False
    for round_ in range(max_rounds):
        if idx.size < 6:
            raise FitError(f"too few inliers left for a cylinder fit ({idx.size})")
        partial_solve = idx.size > work_size and (round_ < max_rounds - 1 or not final_full)
        sel = subset_of(idx) if partial_solve else idx
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

    prob = problem(idx)
    lin = prob.linearise(cyl, jacobian=covariance)
    dof = max(idx.size - 5, 1)
    chi2_dof = float(lin.cost / dof)
    info = lin
    if isinstance(prob, LosProblem) and np.any(lin.residuals[idx.size :] != 0):
        # a line-of-sight fit with beams that miss the model: its information without their miss
        # rows (:func:`hit_information`)
        info = hit_information(prob).linearise(cyl, frame=(lin.e1, lin.e2)) if covariance else lin
    cov = lm_covariance(info) if covariance else np.full((5, 5), np.nan)
    scale = 1.0
    if use_los:
        assert rays is not None
        # the range residuals (l - t) / sigma_l of the linearisation, unwhitened
        sig_l = np.broadcast_to(np.asarray(rays.sigma_l, dtype=np.float64), rays.ranges.shape)[idx]
        rmse = float(np.sqrt(np.mean(np.square(lin.residuals[: idx.size] * sig_l))))
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
        frame=(lin.e1, lin.e2),
        line_of_sight=use_los,
        chi2_dof=chi2_dof,
        sigma_scale=float(np.sqrt(scale)),
        n_points=int(pts.shape[0]),
    )
