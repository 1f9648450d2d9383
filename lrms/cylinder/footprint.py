"""The line-of-sight fit under a finite beam footprint: the expected echo of a beam whose light
spot meets the model cylinder in whole or in part, with the receiver's edge behaviour estimated.

A real LMS1xx's spot is ``exit_diameter + divergence x range`` wide (8 mm + 15 mrad x r: 45 mm at
2.5 m), a Gaussian-like profile. A beam whose spot straddles the part's silhouette still returns
an echo of the covered part, and on a curved or inclined surface the range the receiver reports
is formed over the spot. The thin-beam fit reads those echoes as points on the beam's axis and
finds the part tens of millimetres too large (docs/sensor-model.md). Here the measured range of
beam i is modelled as the echo the model cylinder would return:

* the spot is a Gaussian of standard deviation ``sigma(t) = profile_sigma (exit + divergence t)``
  across the beam. Only the lateral coordinate ``xi`` across the cylinder's axis decides whether
  a sub-ray meets the part (``|x0 + xi sigma| < r``, ``x0`` the beam's signed closest approach to
  the axis); the covered share of the spot is ``c = Phi(xi_hi) - Phi(xi_lo)`` in closed form;
* the energy-weighted family's spot ends at ``BeamOptics.extent`` spot radii (a disc, as the
  optics' apertures cut a real one): its covered share and nodes follow the lateral marginal of
  the Gaussian cut to that disc (:func:`disc_marginal_cdf`) instead of ``Phi``; with an endless
  Gaussian, limb beams read 0.1-0.5 mm short and a noiseless fit came out +2 mm
  (docs/cylinder.md, section 7, round 5);
* the covered part of the profile is integrated by Gauss-Legendre nodes placed in probability
  (``xi_k = Phi^-1(Phi(xi_lo) + c u_k)``, weights ``c g_k``): each node a sub-ray cast exactly
  against the model (``_ray_cylinder``), so the integral follows the cylinder's true range
  profile and moves smoothly with the parameters (no sub-ray popping in or out);
* the range along the other direction across the beam varies linearly: it averages out of an
  energy-weighted range and widens the range distribution of a first-hit one;
* first hit (``mode="first"``): the range is in closed form (:func:`first_hit_range`, in
  :mod:`lrms.cylinder.footprint_first`, no sub-ray casts); the nodes below serve the energy-weighted family;
* edge behaviour, two families (what SICK publishes fixes neither): **energy-weighted** (the
  range is the energy-weighted mean over the covered spot, energy ~ cos(incidence) / t^2; it does
  not depend on the detection threshold, so the fit conditions on a beam being detected and
  needs no threshold) and **first hit** (the range at which the covered share of the spot, taken
  in range order, reaches the threshold ``tau``; ``tau`` is a fitted parameter, and a beam the
  model covers by less than ``tau`` adds the residual ``(tau - c) / 0.05``).

:func:`footprint_fit` fits both families from the thin-beam fit's solution and keeps the one of
lower Akaike criterion (the Gaussian ``-2 log L`` under the common range noise ``sigma_l``, range
residuals truncated at the gate, on the same beams for every family: the first-hit family's
widened sigmas of ``share_u`` weight its fit but are not compared); the thin-beam model itself
competes too (clouds without a footprint). What
is not estimated is carried as two budget rows (standard uncertainties of the diameter):
``fit.extra["edge_model_u_m"]``, the effective spot size (SICK's figures read as the 1/e^2
diameter of a Gaussian: our reading, with a relative standard uncertainty ``spot_scale_u``,
propagated by the fit's sensitivity to it), and ``fit.extra["edge_family_u_m"]``, the model
choice: the root-mean-square difference of each family's diameter (thin beam included) from the
reported one, weighted by the families' Akaike weights ``exp(-dAIC / 2)`` (normalised).

Where things live: this module holds :func:`footprint_fit` with the family choice (the
subsample's decision, the first hit's starts, the Akaike criteria, :func:`family_spread`, the
chosen family's beams taken anew, :func:`_regated`); :mod:`lrms.cylinder.footprint_echo` the
optics (:class:`BeamOptics`) and the echo model (:func:`expected_echo`, the disc marginal);
:mod:`lrms.cylinder.footprint_solve` one family's residuals, the first-hit Jacobian, the bounded
solve and the trim of the part's ends; :mod:`lrms.cylinder.footprint_profile` the radius's
profile (the energy-weighted variance, the first hit's profile-likelihood interval);
:mod:`lrms.cylinder.footprint_first` the first-hit range solver (:func:`first_hit_range`);
:mod:`lrms.cylinder.footprint_bias` the fit's second-order bias. The public names of the echo
module are re-exported here.
"""

from __future__ import annotations

from contextlib import suppress
from dataclasses import replace

import numpy as np
from scipy.special import ndtri

from lrms.cylinder.footprint_echo import LMS1XX_DIVERGENCE as LMS1XX_DIVERGENCE
from lrms.cylinder.footprint_echo import LMS1XX_EXIT_DIAMETER as LMS1XX_EXIT_DIAMETER
from lrms.cylinder.footprint_echo import BeamOptics as BeamOptics
from lrms.cylinder.footprint_echo import EdgeMode as EdgeMode
from lrms.cylinder.footprint_echo import FloatArray, IntArray
from lrms.cylinder.footprint_echo import disc_marginal_cdf as disc_marginal_cdf
from lrms.cylinder.footprint_echo import disc_marginal_ppf as disc_marginal_ppf
from lrms.cylinder.footprint_echo import expected_echo as expected_echo
from lrms.cylinder.footprint_first import first_hit_range as first_hit_range
from lrms.cylinder.footprint_profile import _Profile, _profile_interval, _profile_variance
from lrms.cylinder.footprint_solve import (
    _end_trim,
    _fit_scale,
    _residuals,
    _solve,
    _Solved,
    _spot_index,
    _start,
    hit_heights,
)
from lrms.cylinder.model import Cylinder, Rays
from lrms.cylinder.refine import CylinderFit, _Frame, los_residuals
from lrms.errors import FitError

#: AIC difference above which one edge family is taken as decided by the data.
MODE_DECISIVE = 10.0
#: Threshold starts of the first-hit family (each with the radius its silhouette implies, see
#: :func:`_first_starts`): its cost in (radius, tau) has local minima along a rough ridge, and one
#: start from the thin beam settled up to 15 mm small on 10 % first-hit clouds.
FIRST_STARTS = (0.1, 0.3, 0.5)
#: The energy-weighted family's refinement on all work beams starts from the thin beam's solution,
#: not from its subsample's (False: from the subsample's, before session 12).
WEIGHTED_FROM_THIN = True
#: The energy-weighted family's radius u from the profile-likelihood interval searched outward (as
#: the first hit's), not from the profile's curvature at +-1 mm (False: the curvature, before
#: session 13).
WEIGHTED_PROFILE_INTERVAL = False
#: A radius profile that meets a cost (chi-square) lower than the solution's by more than
#: PROFILE_RESTART_DROP restarts the family's solve from that point, at most PROFILE_RESTARTS
#: times (0: the profile only reports it, before session 13).
PROFILE_RESTARTS = 1
PROFILE_RESTART_DROP = 1.0


def footprint_fit(
    pts: FloatArray,
    rays: Rays,
    fit: CylinderFit,
    optics: BeamOptics,
    modes: tuple[EdgeMode, ...] = ("weighted", "first"),
    work_size: int = 4000,
    gate: float = 4.0,
    decide_size: int = 1000,
) -> CylinderFit:
    """Refit a thin-beam line-of-sight ``fit`` (its inliers; ``rays`` one per point of ``pts``)
    with the expected echo of each beam's footprint, the edge family chosen by the data.

    Returns a :class:`CylinderFit` whose covariance is that of the chosen family's fit (with the
    threshold's uncertainty for a first-hit fit), scaled by ``max(1, chi2/dof)`` (the range noise of
    a real receiver exceeds the noise model at weak and inclined echoes) and then to the radius's
    profile where that is wider (first hit: its profile-likelihood interval at k = 2,
    :func:`_profile_interval`, whose ends ``footprint_profile_lo_m`` / ``footprint_profile_hi_m``
    and lowest point ``footprint_profile_lowest_m``, diameter offsets, are in ``extra``; a profile
    that meets a cost lower than the solution's by more than :data:`PROFILE_RESTART_DROP` restarts
    the family's solve there, ``footprint_profile_restarts`` times, the diameter moved by
    ``footprint_profile_moved_m``; energy-weighted: the curvature at +-1 mm,
    :func:`_profile_variance`), and whose ``extra`` holds
    ``edge_model_u_m`` (the budget row of the spot size when it is held at its nominal size; 0 when
    the fit estimates it, ``BeamOptics.fit_spot``: then ``edge_spot_scale`` and its standard
    uncertainty ``edge_spot_scale_u``, in the covariance), ``edge_family_u_m`` (the
    budget row of the model choice, :func:`family_spread`; ``akaike_weight_*`` its weights),
    ``edge_mode_first`` (1 first hit, 0 energy-weighted, -1 the thin beam won), ``edge_threshold``
    (the fitted tau, first hit only), ``edge_spot_sensitivity_m`` (d diameter / d relative spot
    size), ``thin_beam_diameter_m``, ``aic_weighted`` / ``aic_first`` / ``aic_thin``,
    ``footprint_beams`` (the beams of the chosen family's last solve: after the model choice, its
    beams are taken anew about its own model, :func:`_regated`).
    """
    if not fit.line_of_sight:
        raise FitError("the footprint fit needs a line-of-sight fit")
    idx = fit.inliers
    sub = rays.subset(idx)
    keep = _end_trim(fit.cylinder, sub, optics)
    use = idx[keep]
    if use.size < 30:
        raise FitError(f"too few beams clear of the part's ends for the footprint fit ({use.size})")
    if use.size > work_size:
        use = np.sort(np.random.default_rng(4).choice(use, work_size, replace=False))
    work = rays.subset(use)
    frame = _Frame.at(fit.cylinder.with_point_near(pts[use].mean(axis=0)))
    thin_res = los_residuals(np.zeros(5), frame, work.origins, work.dirs, work.ranges, work.sigma_l, work.sigma_perp)
    aic_thin = _thin_criterion(thin_res, gate)
    # the families are first fitted on a subsample of the work beams; only those the subsample
    # leaves plausible (AIC within MODE_DECISIVE of the best, the thin beam included) are refined
    # on all of them, from the subsample's solution
    starts = {m: _start(m, optics) for m in modes}
    plausible = list(modes)
    dropped: list[_Solved] = []
    if work.ranges.size > 2 * decide_size and len(modes) > 1:
        pick = np.sort(np.random.default_rng(5).choice(work.ranges.size, decide_size, replace=False))
        # a family whose solution is pinned on a bound is left out as failed (no minimum: not
        # refined, and no diameter of it in the model choice's spread)
        sub_solved = _fit_families(frame, work.subset(pick), optics, modes, starts, gate)
        if sub_solved:
            aic_sub = _aics(sub_solved, frame, work.subset(pick), optics, gate)
            thin_sub = _thin_criterion(thin_res, gate, pick)
            floor = min(min(aic_sub.values()), thin_sub)
            plausible = [s.mode for s in sub_solved if aic_sub[s.mode] - floor < MODE_DECISIVE]
            # the subsample's solution starts the first hit's multi-start; the energy-weighted family
            # is refined from the thin beam again: its subsample solution can sit in another basin,
            # which the refinement on all beams (and its gate) kept (a 10 % energy-weighted sweep
            # ended 25 mm small; docs/cylinder.md, section 7, session 12)
            starts.update({s.mode: s.theta for s in sub_solved if s.mode == "first" or not WEIGHTED_FROM_THIN})
            if not plausible:  # the thin beam wins clearly: refine the best family for the record
                plausible = [min(sub_solved, key=lambda s: aic_sub[s.mode]).mode]
            dropped = [s for s in sub_solved if s.mode not in plausible]
    # the first hit's multi-start runs on all work beams: on a 1000-beam subsample the basins'
    # costs differ by less than their noise (10 % first-hit sweeps kept one 8-15 mm small)
    solved = _fit_families(
        frame,
        work,
        optics,
        tuple(plausible),
        starts,
        gate,
        _first_starts(frame, optics, starts.get("first")),
    )
    if not solved:
        raise FitError("the footprint fit failed in every edge family")
    aic = _aics(solved, frame, work, optics, gate)
    best = min(solved, key=lambda s: aic[s.mode])
    extra = {
        **fit.extra,
        "thin_beam_diameter_m": float(fit.diameter),
        "aic_thin": aic_thin,
        # a family dropped on the subsample: its criterion on all work beams at the subsample's solution
        **{f"aic_{m}": float(v) for m, v in _aics(dropped, frame, work, optics, gate).items()},
        **{f"aic_{m}": float(v) for m, v in aic.items()},
    }
    # the model choice's uncertainty: every family's diameter (a dropped one's at its subsample
    # solution) about the reported one, weighted by the Akaike weights of all families
    diam: dict[str, float] = {s.mode: float(2.0 * frame.unpack(s.theta[:5])[2]) for s in [*dropped, *solved]}
    diam["thin"] = float(fit.diameter)
    crit: dict[str, float] = {m: extra[f"aic_{m}"] for m in diam}
    chosen = diam["thin"] if aic_thin < aic[best.mode] else diam[best.mode]
    u_family, weights = family_spread(diam, crit, chosen)
    extra.update({"edge_family_u_m": u_family, **{f"akaike_weight_{m}": w for m, w in weights.items()}})
    if aic_thin < aic[best.mode]:
        return replace(fit, extra={**extra, "edge_mode_first": -1.0, "edge_model_u_m": 0.0})
    if REGATE_BAND > 0.0:
        best = _regated(best, frame, rays, fit.cylinder, use, optics, gate, work_size)
    extra["footprint_beams"] = float(best.rays.ranges.size)
    # the profile of the cost in the radius: the first hit's radius trades off against tau along a
    # flat, rough ridge that the Gauss-Newton curvature J^T J does not see (its u was 4-5x below
    # the spread of noise-only replicas); the variance is taken as the larger of the two, the whole
    # covariance scaled by their ratio (the axis point follows the radius along that ridge; see
    # docs/cylinder.md section 7). First hit: the profile-likelihood interval, its crossing searched
    # for (rounds 3-5); energy-weighted: the profile's curvature at +-1 mm. A profile that meets a
    # cost lower than the solution's by PROFILE_RESTART_DROP (another local minimum of the ridge)
    # restarts the family's solve from there, and the profile is taken again about the new solution
    restarts, moved = 0, 0.0
    while True:
        n_res = best.rays.ranges.size  # range rows (a first-hit fit adds coverage rows)
        range_rows = _residuals(best.theta, frame, best.rays, optics, best.mode)[:n_res]
        chi2 = float(np.sum(range_rows * range_rows))
        chi2_dof = chi2 / max(n_res - best.n_par, 1)
        prof: _Profile | None = None
        if best.mode == "first" or WEIGHTED_PROFILE_INTERVAL:
            prof = _profile_interval(best, frame, optics, chi2_dof)
            if (
                restarts < PROFILE_RESTARTS
                and prof.lowest_theta is not None
                and prof.lowest_cost < best.cost - PROFILE_RESTART_DROP
            ):
                restarts += 1
                again = _solve(frame, best.rays, optics, best.mode, prof.lowest_theta)
                if not again.pinned and again.cost < best.cost - PROFILE_RESTART_DROP:
                    moved += 2.0 * float(again.theta[4] - best.theta[4])
                    best = again
                    continue
            var_prof = prof.u**2
        else:
            var_prof = _profile_variance(best, frame, optics) * max(1.0, chi2_dof)
        break
    jac = best.jac
    jtj_inv = np.linalg.pinv(jac.T @ jac)
    cov_full = jtj_inv * max(1.0, chi2_dof)
    var_jtj = float(cov_full[4, 4])
    extra.update({"footprint_profile_restarts": float(restarts), "footprint_profile_moved_m": moved})
    prof_scale = max(1.0, var_prof / max(var_jtj, 1e-30))
    k_spot = _spot_index(best.mode)
    free = best.theta.size > k_spot
    # the spot's own variance before the radius' profile factor: that factor widens the radius (and
    # the axis point along the ridge), not the spot, whose posterior is held by its prior row
    var_spot = float(cov_full[k_spot, k_spot]) if free else 0.0
    cov_full = cov_full * prof_scale
    # sensitivity of the solution to the spot size: d theta / d scale = -(J^T J)^-1 J^T d res / d scale
    res_lo = _residuals(best.theta, frame, best.rays, optics, best.mode, scale=0.99)
    res_hi = _residuals(best.theta, frame, best.rays, optics, best.mode, scale=1.01)
    dtheta = -jtj_inv @ (jac.T @ ((res_hi - res_lo) / 0.02))
    spot_sens = float(2.0 * dtheta[4])
    # a spot held at its nominal size: its uncertainty carried by the sensitivity (the budget's
    # edge row); an estimated spot: in the covariance (type A), the row is 0
    u_spot = 0.0 if free else abs(spot_sens) * optics.spot_scale_u
    spot_extra = (
        {
            "edge_spot_scale": _fit_scale(best.theta, best.mode),
            "edge_spot_scale_u": float(np.sqrt(max(var_spot, 0.0))) * _fit_scale(best.theta, best.mode),
        }
        if free
        else {}
    )
    # Box's second-order bias of the chosen family's solution, subtracted (its own module)
    from lrms.cylinder.footprint_bias import corrected

    theta, bias_extra = corrected(
        best.mode,
        best.theta,
        lambda th: _residuals(th, frame, best.rays, optics, best.mode),
        jac,
        jtj_inv * max(1.0, chi2_dof),
    )
    cyl = frame.cylinder(theta[:5]).with_point_near(pts[idx].mean(axis=0))
    return replace(
        fit,
        cylinder=cyl,
        inliers=idx,
        rmse=float(np.sqrt(chi2 / n_res)) * float(np.median(best.rays.sigma_l)),
        covariance=np.asarray(cov_full[:5, :5], dtype=np.float64),
        frame=(frame.e1, frame.e2),
        chi2_dof=float(chi2_dof),
        sigma_scale=float(np.sqrt(max(1.0, chi2_dof))),
        extra={
            **extra,
            "edge_mode_first": 1.0 if best.mode == "first" else 0.0,
            "edge_threshold": best.tau if best.mode == "first" else float("nan"),
            "edge_spot_sensitivity_m": spot_sens,
            "edge_model_u_m": float(u_spot),
            **spot_extra,
            "footprint_beams": float(n_res),
            "footprint_u_jtj_m": float(2.0 * np.sqrt(max(var_jtj, 0.0))),
            "footprint_u_profile_m": float(2.0 * np.sqrt(max(var_prof, 0.0))),
            "footprint_profile_scale": float(prof_scale),
            **bias_extra,
            **(
                {}
                if prof is None
                else {
                    # the interval's ends and the lowest cost the profile met, as diameter offsets
                    "footprint_profile_lo_m": 2.0 * prof.lo,
                    "footprint_profile_hi_m": 2.0 * prof.hi,
                    "footprint_profile_lowest_m": 2.0 * prof.lowest,
                }
            ),
        },
    )


def family_spread(
    diameters: dict[str, float], criteria: dict[str, float], chosen: float
) -> tuple[float, dict[str, float]]:
    """The model choice's standard uncertainty of the diameter: ``sqrt(sum_i w_i (d_i - chosen)^2)``
    with the Akaike weights ``w_i = exp(-(AIC_i - AIC_min) / 2) / sum`` of the families ``i``
    (``diameters`` and ``criteria`` keyed alike). Returns it and the weights."""
    if not diameters or set(diameters) != set(criteria):
        raise FitError("one criterion per family diameter is needed")
    names = sorted(diameters)
    a = np.array([criteria[m] for m in names])
    d = np.array([diameters[m] for m in names])
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(d))):
        raise FitError("family diameters and criteria must be finite")
    w = np.exp(-0.5 * (a - a.min()))
    w = w / w.sum()
    return float(np.sqrt(np.sum(w * (d - chosen) ** 2))), {m: float(x) for m, x in zip(names, w, strict=True)}


def _first_starts(frame: _Frame, optics: BeamOptics, own: FloatArray | None) -> list[FloatArray]:
    """Starts of the first-hit family: ``own`` (the subsample's solution or the plain start) and,
    for each threshold of :data:`FIRST_STARTS`, the radius whose first-hit silhouette (the beam
    covered by the share tau, ``sigma x z(1 - tau)`` outside the radius) is the thin beam's."""
    sigma = float(optics.sigma(float(np.linalg.norm(frame.a))))
    out = [] if own is None else [np.asarray(own, dtype=np.float64)]
    for tau in FIRST_STARTS:
        out.append(_start("first", optics, tau, -sigma * float(ndtri(1.0 - tau))))
    return out


#: The chosen family's last solve takes its beams anew (:func:`_regated`): every beam on the
#: thin-beam cylinder's lines of sight within this band (m) of its range, then those within the
#: gate of the family's own model. The thin fit's inliers are a band of twice the detection
#: threshold about the thin beam's surface, which a footprint cloud's limbs leave by up to 1.5 spot
#: radii: that band cut the noisy limb echoes on one side (a 1.0 m part at 5 m came out +10 mm with
#: u 2 mm, its spot scale 0.88; docs/cylinder.md, section 7, session 11). 0: the thin fit's inliers.
REGATE_BAND = 0.25


def _regated(
    best: _Solved,
    frame: _Frame,
    rays: Rays,
    thin: Cylinder,
    work: IntArray,
    optics: BeamOptics,
    gate: float,
    size: int,
) -> _Solved:
    """``best`` solved again on the beams within ``gate`` of its own model, taken from every beam on
    the thin-beam cylinder's lines of sight within :data:`REGATE_BAND` of its range and between the
    work beams' (indices ``work`` into ``rays``) extreme heights along the axis (their ends already
    trimmed); twice, each time from the last solution. A solution pinned on a bound, or fewer than
    30 beams, keeps ``best``."""
    t, gap = thin.ray_range(rays.origins, rays.dirs)
    h = hit_heights(thin, rays, t)
    lo, hi = h[work].min(), h[work].max()
    near = np.flatnonzero((gap <= 0.0) & (np.abs(rays.ranges - t) < REGATE_BAND) & (h >= lo) & (h <= hi))
    if near.size > size:
        near = np.sort(np.random.default_rng(4).choice(near, size, replace=False))
    pool = rays.subset(near)
    for _ in range(2):
        res = _residuals(best.theta, frame, pool, optics, best.mode)[: pool.ranges.size]
        ok = np.flatnonzero(np.abs(res) < gate)
        if ok.size < 30:
            return best
        again = _solve(frame, pool.subset(ok), optics, best.mode, best.theta)
        if again.pinned:
            return best
        best = again
    return best


def _fit_one(frame: _Frame, work: Rays, optics: BeamOptics, mode: EdgeMode, start: FloatArray, gate: float) -> _Solved:
    if mode == "first" and optics.share_u > 0.0:
        # from the thin beam's solution, down-weighted edge beams let the fit settle on a
        # wrong (large) radius with a high threshold: fit unweighted first, then weighted
        start = _solve(frame, work, replace(optics, share_u=0.0), mode, start).theta
    first = _solve(frame, work, optics, mode, start)
    res = _residuals(first.theta, frame, work, optics, mode)[: work.ranges.size]
    ok = np.abs(res) < gate
    if np.count_nonzero(ok) < 30:
        raise FitError("too few beams within the gate")
    return _solve(frame, work.subset(np.flatnonzero(ok)), optics, mode, first.theta) if not np.all(ok) else first


def _fit_families(
    frame: _Frame,
    work: Rays,
    optics: BeamOptics,
    modes: tuple[EdgeMode, ...],
    starts: dict[EdgeMode, FloatArray],
    gate: float,
    first_multi: list[FloatArray] | None = None,
) -> list[_Solved]:
    """Each edge family fitted from ``starts``, gross outliers (beyond ``gate`` sigmas under the
    footprint model) dropped and refitted once; a family that fails is left out, and so is a
    solution pinned on a bound (:attr:`_Solved.pinned`). With
    ``first_multi``, the first-hit family is fitted from each of those starts instead and the
    solution of the lowest criterion (:func:`_aics`, on ``work``) is kept."""
    solved: list[_Solved] = []
    for mode in modes:
        tries = first_multi if mode == "first" and first_multi else [starts[mode]]
        found: list[_Solved] = []
        for start in tries:
            with suppress(FitError):
                one = _fit_one(frame, work, optics, mode, start, gate)
                if not one.pinned:
                    found.append(one)
        if len(found) > 1:
            crit = [_aics([f], frame, work, optics, gate)[mode] for f in found]
            found = [found[int(np.argmin(crit))]]
        solved.extend(found)
    return solved


def _thin_criterion(thin_res: FloatArray, gate: float, pick: IntArray | None = None) -> float:
    """The thin beam's model-choice criterion from its line-of-sight residuals ``thin_res`` (the
    range rows then the miss rows of the same beams, :func:`los_residuals`): every row truncated at
    the gate, + 2 per parameter. ``pick``: the beams of a subsample, both rows of each counted."""
    if pick is not None:
        n = thin_res.size // 2
        thin_res = thin_res[np.concatenate([pick, pick + n])]
    return float(np.sum(np.minimum(thin_res * thin_res, gate * gate))) + 2 * 5


def _aics(solved: list[_Solved], frame: _Frame, work: Rays, optics: BeamOptics, gate: float) -> dict[str, float]:
    """The model-choice criterion of each solved family: ``-2 log L`` under the common range noise
    ``sigma_l`` (the first hit's widened sigmas are the fit's weights, not part of the compared
    likelihood), on the same beams for every family, range rows truncated at the gate, plus the
    first hit's coverage rows, + 2 per parameter."""
    n_work = work.ranges.size
    common = replace(optics, share_u=0.0)
    aic: dict[str, float] = {}
    for s in solved:
        rows = _residuals(s.theta, frame, work, common, s.mode)
        rr = rows[:n_work]
        aic[s.mode] = float(np.sum(np.minimum(rr * rr, gate * gate)) + np.sum(rows[n_work:] ** 2)) + 2 * s.n_par
    return aic
