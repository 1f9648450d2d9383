"""From a cloud to an elbow fit: initial values, adjustment, labelling of the legs, trimming."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.cylinder import Cylinder, refine_cylinder
from lrms.elbow.gauss_helmert import ElbowFit, fit_elbow
from lrms.elbow.initial import initial_candidates
from lrms.elbow.model import BEND, END, START, ElbowParams, Evaluation, as_points, evaluate_model
from lrms.errors import FitError

FloatArray = NDArray[np.float64]

#: Fits whose a posteriori sigma exceeds this fraction of D are not elbows (the default of
#: ``fit_auto``'s ``max_spread``): noise of up to 20-25 % of D passes.
MAX_SIGMA0_FRACTION = 0.3
#: The points on the bend must cover at least this fraction of the fitted bend angle.
MIN_BEND_SPAN = 0.3
#: The straight-cylinder comparison fits the cylinder to at most this many random points.
CYLINDER_SAMPLE = 5000
#: Rounds of trimming at most.
TRIM_ROUNDS = 8
#: The end leg must be this much longer than the start leg before the two are swapped.
LEG_MARGIN = 1.05


def leg_extents(points: ArrayLike, params: ElbowParams, ev: Evaluation | None = None) -> tuple[float, float, int]:
    """How far the points reach along the start and end legs (m) and how many lie on the bend.

    ``ev``: the model already evaluated at ``points`` for ``params``."""
    if ev is None:
        ev = evaluate_model(params.to_model(points), params.A, params.D, params.degree, params.Df)
    m = ev.m
    theta0 = math.pi / 2 + params.degree
    start = m[ev.portion == START, 0]
    end_dir = np.array([-math.sin(theta0), 0.0, math.cos(theta0)])
    end = m[ev.portion == END] @ end_dir
    return (
        float(start.max()) if start.size else 0.0,
        float(end.max()) if end.size else 0.0,
        int(np.count_nonzero(ev.portion == BEND)),
    )


def bend_span(points: ArrayLike, params: ElbowParams, ev: Evaluation | None = None) -> float:
    """Angle (rad) along the bend covered by the points on it: the 2 %-98 % range of their Phi."""
    if ev is None:
        ev = evaluate_model(params.to_model(points), params.A, params.D, params.degree, params.Df)
    phi = ev.phi[ev.portion == BEND]
    if phi.size < 10:
        return 0.0
    lo, hi = np.quantile(phi, [0.02, 0.98])
    return float(hi - lo)


def canonical(points: ArrayLike, params: ElbowParams, ev: Evaluation | None = None) -> ElbowParams:
    """The labelling of the two legs with the longer visible leg as the start leg.

    The model cannot tell its legs apart (a half turn about the bend's bisector maps it onto
    itself); registration needs both clouds labelled alike, so we label by visible leg length.
    ``ev``: the model already evaluated at ``points`` for ``params``.
    """
    s, e, _ = leg_extents(points, params, ev)
    return params.flipped() if e > LEG_MARGIN * s else params


def fit_auto(
    points: ArrayLike,
    *,
    degree: float | None = None,
    ratio: float | None = None,
    flange: bool = False,
    cov: ArrayLike | None = None,
    init: ElbowParams | None = None,
    trim: float | None = None,
    max_iter: int = 60,
    rng: np.random.Generator | None = None,
    max_spread: float = MAX_SIGMA0_FRACTION,
    straight_check: bool = True,
) -> ElbowFit:
    """Fit an elbow to ``points`` without manual start values.

    ``degree`` (rad): the joint degree (``None``: estimated from the two pipe ends, snapped to 45
    or 90 deg when close); ``ratio``: ``A/D`` fixed, or ``None`` (free); ``flange``: fit ``Df``.
    ``trim``: drop points farther than ``trim`` robust standard deviations (1.4826 times the
    median absolute residual of the points kept so far) from the fitted surface and refit, until
    the kept set settles (at most ``TRIM_ROUNDS`` rounds; the kept rows are in ``fit.inliers``).
    Starts: ``init``, or the candidates of :func:`lrms.elbow.initial.initial_candidates` (one
    when the slice start fits the points closely; else up to three distinct starts of the global
    search): the adjustment runs from each and the fit with the lowest ``sigma0`` is returned.
    Raises :class:`FitError` when no elbow is found or the adjustment fails from every start; a
    fit whose residual spread ``sigma0`` exceeds ``max_spread`` times ``D`` (default
    ``MAX_SIGMA0_FRACTION``) is rejected as "not an elbow"; raise it for clouds known to be
    that noisy (seed 000's Table 6: noise of 40 % of D gives ``sigma0`` of 30-40 % of the fitted
    ``D``). Last, a fit that a straight cylinder explains as well (by BIC on the orthogonal
    residuals, :func:`straight_cylinder_bic`) is rejected as "no elbow" too, unless
    ``straight_check`` is false: for a cloud known to be an elbow at noise of 30 % of ``D`` and
    more, where the orthogonal residuals of the true elbow itself are no smaller than those of a
    fat straight cylinder, so that the comparison can no longer tell (docs/elbow-model.md).
    """
    pts = as_points(points)
    if trim is not None and trim <= 0:
        raise FitError(f"trim must be > 0 (in sigma0), got {trim}")
    if init is not None:
        starts = [replace(init, degree=degree) if degree is not None else init]
    else:
        starts = initial_candidates(pts, degree=degree, ratio=ratio, flange=flange, rng=rng)
    errors: list[str] = []
    best: ElbowFit | None = None
    for start in starts:
        try:
            fit = _fit_from(pts, start, ratio, flange, cov, trim, max_iter, max_spread)
        except FitError as exc:
            errors.append(str(exc))
            continue
        # several starts (different basins found by the global search): the lowest final cost wins
        if best is None or fit.sigma0 < best.sigma0:
            best = fit
    if best is not None:
        if straight_check:
            _refuse_straight_cylinder(pts, best, degree is None)
        return best
    if len(errors) == 1:
        raise FitError(errors[0])
    raise FitError(f"{errors[0]} (best start; the {len(errors) - 1} other starts: " + "; ".join(errors[1:]) + ")")


def _fit_from(
    pts: FloatArray,
    start: ElbowParams,
    ratio: float | None,
    flange: bool,
    cov: ArrayLike | None,
    trim: float | None,
    max_iter: int,
    max_spread: float,
) -> ElbowFit:
    """Adjustment, trimming, labelling and the sanity checks of :func:`fit_auto` from one start."""
    cv = None if cov is None else np.asarray(cov, dtype=np.float64)
    keep = np.ones(pts.shape[0], dtype=bool)
    # label the legs on the start already: the adjustment from the flipped start ends on the
    # flipped solution (the same surface), so the refit below is needed only when the fit itself
    # changes which visible leg is the longer
    start = canonical(pts, start)
    if trim is None:
        fit = fit_elbow(pts, start, ratio=ratio, flange=flange, cov=cv, max_iter=max_iter)
    else:
        # trimmed least squares from the start values: the points near the starting surface,
        # then (after each fit) the points within trim * sigma0 of the fitted surface
        params = start
        res = np.abs(_residuals(pts, params))
        sig = 1.4826 * float(np.median(res))
        for rnd in range(TRIM_ROUNDS):
            new_keep = res < trim * sig
            if np.count_nonzero(new_keep) < 30:
                raise FitError("no elbow: too few points lie near the fitted surface")
            if np.array_equal(new_keep, keep) and rnd > 0:
                break
            keep = new_keep
            fit = fit_elbow(
                pts[keep], params, ratio=ratio, flange=flange, cov=None if cv is None else cv[keep], max_iter=max_iter
            )
            params = fit.params
            res = np.abs(_residuals(pts, params))
            # robust spread of the kept points' residuals (sigma0 itself is inflated by any
            # outliers still kept), in units of the point standard deviation when cov is given
            sig = 1.4826 * float(np.median(res[keep]))
    sub = pts[keep]
    ev = _evaluate(sub, fit.params)
    can = canonical(sub, fit.params, ev)
    if can is not fit.params:
        fit = fit_elbow(sub, can, ratio=ratio, flange=flange, cov=None if cv is None else cv[keep], max_iter=max_iter)
        ev = _evaluate(sub, fit.params)
    if cv is None and fit.sigma0 > max_spread * fit.params.D:
        raise FitError(
            f"no elbow: residual spread {fit.sigma0 * 1e3:.1f} mm is {fit.sigma0 / fit.params.D:.0%} of "
            f"the fitted diameter {fit.params.D * 1e3:.1f} mm"
        )
    _, _, nb = leg_extents(sub, fit.params, ev)
    if nb < 10:
        raise FitError("no elbow: hardly any points lie on the bend of the fitted model")
    span = bend_span(sub, fit.params, ev)
    if span < MIN_BEND_SPAN * fit.params.degree:
        raise FitError(
            f"no elbow: the points cover {math.degrees(span):.1f} deg of the fitted bend's "
            f"{math.degrees(fit.params.degree):.0f} deg (a straight pipe fits a leg and a sliver of bend)"
        )
    return replace(
        fit,
        inliers=keep if trim is not None else None,
        residuals=_residuals(pts, fit.params) if trim is not None else fit.residuals,
    )


def straight_cylinder_bic(
    points: ArrayLike, fit: ElbowFit, degree_estimated: bool, residuals: ArrayLike | None = None
) -> tuple[float, float]:
    """BIC of the elbow ``fit`` and of a straight cylinder fitted to the same ``points``.

    Both on the plain orthogonal residuals: ``n ln(RSS / n) + k ln n`` with ``k`` the free
    parameters (the elbow's adjusted unknowns, plus one when its degree was estimated from the
    data; the cylinder's 5: axis direction 2, axis point 2, radius 1). The cylinder is the
    orthogonal-distance fit of :func:`lrms.cylinder.refine_cylinder` (isotropic, one round, no
    inlier selection) from the principal axis of the points, on ``CYLINDER_SAMPLE`` random
    points of larger clouds (its RSS is then taken over all points, so it can only come out a
    little high: the doubt goes to the elbow). Returns ``(bic_elbow,
    bic_cylinder)``; ``bic_cylinder`` is ``inf`` when the cylinder fit fails. ``residuals``: the
    elbow's orthogonal distances of ``points`` when the caller has them (else computed).
    """
    pts = as_points(points)
    n = pts.shape[0]
    res = _residuals(pts, fit.params) if residuals is None else np.asarray(residuals, dtype=np.float64)
    rss_e = float(np.sum(np.square(res)))
    k_e = len(fit.names) + (1 if degree_estimated else 0)
    sub = pts
    if n > CYLINDER_SAMPLE:
        sub = pts[np.random.default_rng(0).choice(n, CYLINDER_SAMPLE, replace=False)]
    centroid = sub.mean(axis=0)
    axis = np.linalg.eigh(np.cov(sub.T))[1][:, -1]
    v = sub - centroid
    r0 = float(np.median(np.linalg.norm(v - np.outer(v @ axis, axis), axis=1)))
    try:
        cyl = refine_cylinder(sub, Cylinder(centroid, axis, max(r0, 1e-6)), sigma=None, max_rounds=1).cylinder
    except FitError:
        return _bic(rss_e, n, k_e), math.inf
    rss_c = float(np.sum(np.square(cyl.surface_distance(pts))))
    return _bic(rss_e, n, k_e), _bic(rss_c, n, 5)


def _bic(rss: float, n: int, k: int) -> float:
    return n * math.log(max(rss, 1e-300) / n) + k * math.log(n)


def _refuse_straight_cylinder(pts: FloatArray, fit: ElbowFit, degree_estimated: bool) -> None:
    """Raise :class:`FitError` when a straight cylinder explains ``fit``'s points (``pts``, or its
    ``inliers`` of them) as well as the elbow."""
    keep = slice(None) if fit.inliers is None else fit.inliers
    bic_e, bic_c = straight_cylinder_bic(pts[keep], fit, degree_estimated, fit.residuals[keep])
    if bic_c <= bic_e:
        raise FitError(
            f"no elbow: a straight cylinder fits the points as well (BIC {bic_c:.1f} for the cylinder, "
            f"{bic_e:.1f} for the {math.degrees(fit.params.degree):.0f} deg elbow with sigma0 "
            f"{fit.sigma0 * 1e3:.1f} mm, n = {pts.shape[0]})"
        )


def _residuals(pts: FloatArray, p: ElbowParams) -> FloatArray:
    return _evaluate(pts, p).f


def _evaluate(pts: FloatArray, p: ElbowParams) -> Evaluation:
    return evaluate_model(p.to_model(pts), p.A, p.D, p.degree, p.Df)
