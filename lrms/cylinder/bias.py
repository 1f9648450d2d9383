"""The line-of-sight fit's estimator refinements: grazing weights and the second-order (Box)
bias correction."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from lrms.cylinder.lm import LosProblem, levenberg_marquardt
from lrms.cylinder.model import Cylinder, Rays, _dot, perpendicular_frame
from lrms.cylinder.options import DetectOptions
from lrms.cylinder.refine import CylinderFit, _covariance, _Frame
from lrms.errors import FitError

FloatArray = NDArray[np.float64]

#: Lateral standard deviation (m) of a beam's footprint in the estimator's weights
#: (:func:`grazing_weighted_fit`): a beam meeting the surface at incidence ``i`` is weighted by
#: ``1 / (sigma_l^2 + (tan(i) GRAZING_SIGMA)^2)``. 0 gives the plain maximum-likelihood fit.
GRAZING_SIGMA = 2e-4
#: Smallest cosine of incidence in those weights (a beam that misses the model counts as this).
_COS_FLOOR = 0.01
#: Beams (at most; a fixed random subset of more) on which :func:`second_order_bias` is evaluated.
#: The bias is a ratio of two sums over the beams (``A^-1 sum J_i tr(H_i C)``, ``C`` the whole
#: fit's covariance), so a subset estimates it with a relative scatter of about ``1/sqrt(n)``:
#: about 2 % of a diameter bias of about 10 um at 3000 (0.2 um), where its eleven passes over
#: every beam of a 1M-point cloud took a second (20 000 until issue 15's sixth round).
BIAS_WORK = 3_000
#: LM steps of each round of :func:`grazing_weighted_fit` before the last, on a small cloud's
#: beams (all of them): the weights of the next round are all they feed, and those move little
#: with the last steps (200 until issue 15's sixth round; docs/cylinder.md section 6).
GRAZING_EARLY_STEPS = 4
#: Beams (at most) on which :func:`smoothed_covariance` takes its nodes' change: kept at 20 000,
#: not :data:`BIAS_WORK`, since one grazing beam can carry most of the information a subset would miss.
SMOOTH_WORK = 20_000
#: Share of the radius a node of :func:`smoothed_covariance` may move it by at most (its step along
#: the radius is shortened to this, the pair's second difference scaled back accordingly).
SMOOTH_MIN_RADIUS = 0.5
#: ``kappa`` of the unscented points over which :func:`smoothed_covariance` averages (1: the nodes
#: at ``sqrt(6)`` standard deviations, the centre weighted 1/6).
SMOOTH_KAPPA = 1.0


def incidence_cosines(cyl: Cylinder, rays: Rays) -> FloatArray:
    """|cos| of the angle between each beam and the surface normal where it meets ``cyl``
    (0 for a beam that misses)."""
    t, gap = cyl.ray_range(rays.origins, rays.dirs)
    o, u = rays.origins, rays.dirs
    if o.ndim != 2 or u.shape != o.shape:
        q = cyl.radial(o + t[:, None] * u)
        c = np.abs(_dot(q, u)) / np.maximum(np.linalg.norm(q, axis=1), 1e-300)
        return np.asarray(np.where(gap > 0, 0.0, c), dtype=np.float64)
    # by coordinate (no (N, 3) temporaries): q = the hit point's component across the axis
    a, w = cyl.point, cyl.direction
    x = o[:, 0] - a[0] + t * u[:, 0]
    y = o[:, 1] - a[1] + t * u[:, 1]
    z = o[:, 2] - a[2] + t * u[:, 2]
    h = x * w[0] + y * w[1] + z * w[2]
    x -= h * w[0]
    y -= h * w[1]
    z -= h * w[2]
    c = np.abs(x * u[:, 0] + y * u[:, 1] + z * u[:, 2]) / np.maximum(np.sqrt(x * x + y * y + z * z), 1e-300)
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
    beams = LosProblem(sub)
    cyl = fit.cylinder
    work = np.arange(idx.size)
    if idx.size > 10_000:  # all rounds but the last on a subset (large clouds)
        work = np.sort(np.random.default_rng(3).choice(idx.size, 5_000, replace=False))
    try:
        for k in range(rounds):
            # each round one solve of the LM (with the axis point at the beams' centroid, as
            # :func:`refine_cylinder` with no gate): no inlier selection, no summary of the fit
            whole = k == rounds - 1 or work.size == idx.size
            part = sub if whole else sub.subset(work)
            prob = beams if whole else LosProblem(part)
            centre = (sub_pts if whole else sub_pts[work]).mean(axis=0)
            # a large cloud's last round starts next to its optimum: a few LM steps suffice
            # (the rounds before it: all beams of a small cloud, GRAZING_EARLY_STEPS steps; a
            # subset of a large one, solved to the end, since its last round's steps are few)
            if k < rounds - 1:
                nfev = GRAZING_EARLY_STEPS if whole else 200
            else:
                nfev = 200 if part.ranges.size <= 10_000 else 4
            weighted = prob.reweighted(grazing_sigmas(cyl, part, sigma_lat))
            cyl, _ = levenberg_marquardt(weighted, cyl.with_point_near(centre), max_iter=nfev)
            cyl = cyl.with_point_near(centre)
    except FitError:
        return fit
    lo, hi = DetectOptions().radius_range if radius_range is None else radius_range
    if not lo <= cyl.radius <= hi:
        return fit
    frame = perpendicular_frame(cyl.direction)
    cov = smoothed_covariance(beams, sub, cyl, sigma_lat, frame)
    plain = beams.linearise(cyl, jacobian=False, frame=frame)
    m = idx.size
    return replace(
        fit,
        cylinder=cyl,
        rmse=float(np.sqrt(np.mean(np.square(plain.residuals[:m] / plain_isl(sub))))),
        covariance=np.asarray(cov, dtype=np.float64),
        frame=(plain.e1, plain.e2),
        chi2_dof=float(plain.cost / max(m - 5, 1)),
        sigma_scale=1.0,
        extra={**fit.extra, "grazing_sigma_m": float(sigma_lat)},
    )


def weighted_sandwich(
    beams: LosProblem, rays: Rays, cyl: Cylinder, sigma_lat: float, frame: tuple[FloatArray, FloatArray]
) -> FloatArray:
    """The sandwich covariance ``A^-1 J^T V J A^-1`` of the grazing-weighted fit at ``cyl`` (in
    ``frame``): ``beams`` the problem of ``rays``, the weights at ``cyl``, ``V`` the rig's range noise."""
    # the two normal matrices from the beams' range rows at unit weight (one pass; no 2N x 5
    # Jacobian): the weighted fit's ``A = J^T J`` (range rows over ``s_i``) weighs them by
    # ``1 / s_i^2``; ``J^T V J`` with ``V = sigma_l^2 / s_i^2`` on the range rows (the range rows
    # over ``s_i^2 / sigma_l``) by ``sigma_l^2 / s_i^4``; both without the miss rows' information
    # (:func:`~lrms.cylinder.refine.hit_information`). The weights' incidences from the exact
    # geometry (:func:`grazing_sigmas`), not from ``frame``, which is the centre's at a node of
    # :func:`smoothed_covariance`.
    rows = beams.reweighted(np.ones(beams.size)).range_rows(cyl, frame=frame)
    sl2 = np.square(np.broadcast_to(rays.sigma_l, rays.ranges.shape))
    w = 1.0 / np.square(grazing_sigmas(cyl, rays, sigma_lat))  # 1 / s_i^2
    try:
        a_inv = np.linalg.inv((rows * w) @ rows.T)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - degenerate geometry
        raise FitError("cylinder fit is degenerate (singular normal matrix)") from exc
    meat = (rows * (sl2 * w * w)) @ rows.T
    return np.asarray(a_inv @ meat @ a_inv, dtype=np.float64)


def smoothed_covariance(
    beams: LosProblem, rays: Rays, cyl: Cylinder, sigma_lat: float, frame: tuple[FloatArray, FloatArray]
) -> FloatArray:
    """:func:`weighted_sandwich` averaged over the parameters' own uncertainty: at ``cyl`` and at
    the unscented transform's points ``+-sqrt(n + kappa) sqrt(lambda_k) v_k`` of its covariance
    (``n = 5``, ``kappa =`` :data:`SMOOTH_KAPPA`; weights ``kappa / (n + kappa)`` and
    ``1 / (2 (n + kappa))``, all positive).

    A beam next to the model's silhouette carries a Fisher information that goes like
    ``1 / cos(incidence)^2`` even under the grazing weights: whichever beam the solution happens
    to put there sets the covariance, and a move of the model by a fraction of its standard error
    takes that information away. The covariance at the solution alone then ranged 0.17-0.82 mm
    on the diameter between replicas of one scene whose scatter was 0.46 mm, the smallest values
    on the fits that were most off (docs/cylinder.md, "the covariance near the silhouette").
    More than :data:`SMOOTH_WORK` beams: the nodes' change is taken on a fixed random subset of
    that many and scaled by the subset's share (the covariance goes like 1 / N). A node pair that
    would move the radius by more than :data:`SMOOTH_MIN_RADIUS` of it (to r <= 0 on a very
    uncertain fit, which raised a FitError) is shortened to that, the same weights kept: the
    average is over a narrower interval along that direction.
    """
    centre = weighted_sandwich(beams, rays, cyl, sigma_lat, frame)
    n = rays.ranges.shape[0]
    part, prob, scale = rays, beams, 1.0
    if n > SMOOTH_WORK:
        part = rays.subset(np.sort(np.random.default_rng(5).choice(n, SMOOTH_WORK, replace=False)))
        prob, scale = LosProblem(part), SMOOTH_WORK / n
    here = centre if part is rays else weighted_sandwich(prob, part, cyl, sigma_lat, frame)
    lam, vec = np.linalg.eigh(0.5 * (centre + centre.T))
    steps = (np.sqrt((5.0 + SMOOTH_KAPPA) * np.maximum(lam, 0.0)) * vec).T
    fr = _Frame(cyl.point, cyl.direction, frame[0], frame[1], cyl.radius)
    change = np.zeros_like(here)
    for step in steps:
        # a node pair that would reach r <= 0 (a fit whose radius is uncertain by more than
        # r / sqrt(6)) is moved in to change the radius by half of it: the average is then over a
        # shorter interval along that direction (scaling its second difference back by
        # 1 / shrink^2 amplified the nonlinearity near r = 0 a hundredfold)
        shrink = min(1.0, SMOOTH_MIN_RADIUS * cyl.radius / abs(float(step[4]))) if step[4] != 0 else 1.0
        pair = sum(
            weighted_sandwich(prob, part, fr.cylinder(sign * shrink * step), sigma_lat, frame) for sign in (1.0, -1.0)
        )
        change = change + (pair - 2.0 * here) / (2.0 * (5.0 + SMOOTH_KAPPA))
    return np.asarray(centre + scale * change, dtype=np.float64)


def plain_isl(rays: Rays) -> FloatArray:
    """``1 / sigma_l`` of each beam (undoes the whitening of the range residuals)."""
    return np.asarray(1.0 / np.broadcast_to(rays.sigma_l, rays.ranges.shape), dtype=np.float64)


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
    the leading term only. More than :data:`BIAS_WORK` beams: evaluated on a fixed random subset
    of that many. Checked by Monte Carlo in tests/core/test_cylinder.py and docs/cylinder.md.

    Miss rows (beams passing the model, whitened miss distance ``gap / sigma_perp``) are in ``A``,
    the normal matrix of the rows the estimator minimises, but not in the sum: a miss distance is
    a kink at the silhouette, its second difference over the nodes (``sqrt(3 lambda)`` of the
    radius, many ``sigma_perp``) is of the fit's uncertainty over ``sigma_perp`` whatever the miss,
    and the row vanishes once the model meets the beam. Summed, one limb beam left tangent
    (missing by 0.001-0.03 ``sigma_perp``) gave 0.7 mm of a short sweep's correction and none a
    hair further out, where it hits; and over 2280 simulated short sweeps the corrected diameter
    came out 0.50 +- 0.05 mm small (0.16 +- 0.04 mm without the miss rows' terms; 320 full
    sweeps: -0.10 +- 0.03 and +0.06 +- 0.03 mm; docs/cylinder.md, "Another local minimum,
    another bias correction").
    """
    if not fit.line_of_sight:
        raise FitError("the second-order bias is defined for a line-of-sight fit")
    if rays.ranges.shape[0] != fit.inliers.size:
        raise FitError("one beam per inlier is needed for the bias")
    frame = _fit_frame(fit)
    if rays.ranges.shape[0] > BIAS_WORK:
        rays = rays.subset(np.sort(np.random.default_rng(4).choice(rays.ranges.shape[0], BIAS_WORK, replace=False)))
    lat = fit.extra.get("grazing_sigma_m", 0.0)
    sig = grazing_sigmas(fit.cylinder, rays, lat) if lat > 0 else np.broadcast_to(rays.sigma_l, rays.ranges.shape)
    lam, vec = np.linalg.eigh(0.5 * (fit.covariance + fit.covariance.T))
    steps = (np.sqrt(3.0 * np.maximum(lam, 0.0)) * vec).T  # rows: the Gauss-Hermite nodes' offsets

    problem = LosProblem(Rays(rays.origins, rays.dirs, rays.ranges, np.asarray(sig), rays.sigma_perp))

    def res(th: FloatArray) -> FloatArray:
        return problem.linearise(frame.cylinder(th), jacobian=False).residuals

    centre = res(np.zeros(5))
    second = np.zeros_like(centre)
    for step in steps:  # 5 directions, each a vectorized pass over the beams
        second += (res(step) + res(-step) - 2.0 * centre) / 3.0
    jac = problem.jacobian(fit.cylinder, frame=(frame.e1, frame.e2))
    # whitened residuals r_i = (l_i - t_i) / s_i: J_r = -J_t / s_i and second = -"tr(H_i C)" / s_i;
    # the sum over the range rows only (the miss rows, the last n, are in A alone: see above)
    n = rays.ranges.shape[0]
    return np.asarray(-0.5 * (_covariance(jac) @ (jac[:n].T @ second[:n])), dtype=np.float64)


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
