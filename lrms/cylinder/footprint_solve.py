"""The footprint fit's residuals and solve: one edge family's parameters (the axis, the radius's
change, the first hit's logit(tau), the spot's log scale), its residual rows (:func:`_residuals`),
the first-hit family's implicit Jacobian (:func:`_first_jacobian`), the bounded solve
(:func:`_solve`, :class:`_Solved`) and the trim of beams near the part's ends (:func:`_end_trim`).
:mod:`lrms.cylinder.footprint` chooses among the families; the echo model is in
:mod:`lrms.cylinder.footprint_echo`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import expit, logit

from lrms.cylinder.footprint_echo import BeamOptics, EdgeMode, FloatArray, IntArray, _echo, _Geom, _geometry
from lrms.cylinder.footprint_first import _first_newton, _first_share, _first_share_grad, first_hit_range
from lrms.cylinder.model import Cylinder, Rays
from lrms.cylinder.refine import _Frame
from lrms.errors import FitError

#: Scale (share of the spot) of the penalty on a first-hit beam the model covers by less than tau.
COVERAGE_SCALE = 0.05


@dataclass
class _Solved:
    mode: EdgeMode
    theta: FloatArray
    tau: float
    cost: float
    jac: FloatArray
    n_par: int
    rays: Rays
    nfev: int = 0
    #: the radius, the threshold or the spot scale ended on its bound: not a minimum of the likelihood
    #: (the first hit's (radius, tau) ridge runs on beyond it), so no solution of the family
    pinned: bool = False


def _spot_index(mode: EdgeMode) -> int:
    """Index of the spot's log scale in a family's parameters (after the threshold's logit)."""
    return 5 if mode == "weighted" else 6


def _fit_scale(theta: FloatArray, mode: EdgeMode) -> float:
    """The spot scale ``theta`` holds (1 when the spot is held at its nominal size)."""
    k = _spot_index(mode)
    return float(np.exp(theta[k])) if theta.size > k else 1.0


def _start(mode: EdgeMode, optics: BeamOptics, tau: float = 0.3, radius: float = 0.0) -> FloatArray:
    """A family's start: the thin beam's cylinder (``radius`` added), ``logit(tau)`` for a first
    hit, the nominal spot (log scale 0) when the fit estimates it."""
    head = [0.0, 0.0, 0.0, 0.0, radius] + ([float(logit(tau))] if mode == "first" else [])
    return np.array(head + ([0.0] if optics.spot_free else []), dtype=np.float64)


def _first_rows(
    g: _Geom, big_t: FloatArray, slope: FloatArray, tau: float, rays: Rays, optics: BeamOptics
) -> FloatArray:
    """Residual rows of the first-hit family: the ranges whitened by ``hypot(sigma_l, share_u
    dT/dshare)``, then the coverage penalty. The widened sigmas are weights: the fit's objective
    leaves out their log-determinant (with it, a noiseless 10 % first-hit cloud came out +15 mm:
    the fit moves toward geometries whose edge beams have flat slopes)."""
    sigma = np.hypot(rays.sigma_l, optics.share_u * slope)
    rows = [(rays.ranges - big_t) / sigma, np.maximum(tau - g.c, 0.0) / COVERAGE_SCALE]
    return np.asarray(np.concatenate(rows), dtype=np.float64)


@dataclass
class _Warm:
    """One solve's memory of the first-hit ranges: the last parameters and their solution, reused
    when the same parameters come again (the Jacobian is asked at the point just evaluated). Other
    parameters get a cold Newton solve: no warm start (see :func:`first_hit_range`)."""

    theta: FloatArray | None = None
    big_t: FloatArray | None = None
    slope: FloatArray | None = None

    def solve(self, theta: FloatArray, g: _Geom, tau: float) -> tuple[FloatArray, FloatArray]:
        same = self.theta is not None and self.theta.shape == theta.shape and np.array_equal(self.theta, theta)
        if same and self.big_t is not None and self.slope is not None:
            return self.big_t, self.slope
        big_t, slope = first_hit_range(g.x0, g.t_ca, g.cos_axis, g.radius, g.s0, g.sd, tau, g.c)
        self.theta, self.big_t, self.slope = theta.copy(), big_t, slope
        return big_t, slope


def _residuals(
    theta: FloatArray,
    frame: _Frame,
    rays: Rays,
    optics: BeamOptics,
    mode: EdgeMode,
    scale: float = 1.0,
    warm: _Warm | None = None,
) -> FloatArray:
    a, w, r = frame.unpack(theta[:5])
    k = _spot_index(mode)
    # the spot's estimated scale and its prior row (the nominal size, u = spot_scale_u in log)
    prior = [np.array([theta[k] / optics.spot_scale_u])] if theta.size > k else []
    spot = scale * _fit_scale(theta, mode)
    if mode == "weighted":
        pred, _, _ = _echo(a, w, float(r), rays, optics, mode, 0.0, spot)
        return np.asarray(np.concatenate([(rays.ranges - pred) / rays.sigma_l, *prior]), dtype=np.float64)
    tau = float(expit(theta[5]))
    g = _geometry(a, w, float(r), rays, optics, spot)
    if warm is not None and scale == 1.0:
        big_t, slope = warm.solve(theta, g, tau)
    else:
        big_t, slope = first_hit_range(g.x0, g.t_ca, g.cos_axis, g.radius, g.s0, g.sd, tau, g.c)
    return np.asarray(np.concatenate([_first_rows(g, big_t, slope, tau, rays, optics), *prior]), dtype=np.float64)


#: Steps of the first-hit Jacobian's differences: the geometry (m, rad), logit(tau), log(spot scale).
_JAC_STEP = np.array([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-4, 1e-4])


def _first_jacobian(
    theta: FloatArray, frame: _Frame, rays: Rays, optics: BeamOptics, warm: _Warm | None = None
) -> FloatArray:
    """Jacobian of the first-hit rows without re-solving ``F(T) = target`` per column.

    Each parameter is stepped in the cheap closed forms (the beam geometry, the covered share
    ``c``, ``tau``); the first-hit range then moves by the implicit-function step
    ``dT = -(dF_j - target_j + target_0) / F'(T0)``, ``dF_j`` the change of ``F`` at ``T0`` to first
    order in the geometry's change (the partials of :func:`_first_share_grad`: one evaluation of
    ``F`` for all columns; before, one per column). Forward differences of the rows follow: first
    order in the step like a plain finite difference. With ``share_u`` the slope ``dT/dF`` is read
    at ``T0 + dT`` (one evaluation per column). Beams where ``F`` is flat at ``T0`` (``F' < 1`` per
    metre: a spot that barely meets the part) are re-solved per column, as a plain difference would;
    so are the beams with a node near the front's tip (``F``'s square-root onset) whose linear step
    lands off the target (``F`` evaluated there misses it by more than 1 % of the step). ``F'`` is
    the full slope, the spot's growth with ``T`` included (:func:`_first_share`; without it rows were
    up to 7 % off, and one 47x where the linear step crossed a node's tip). The spot scale's column
    (when the fit estimates it) takes the same step, its ``dF`` evaluated at ``T0`` under the scaled
    spot (until session 13 a plain forward difference through a Newton solve: a third of the
    Jacobian's cost).
    """
    a, w, r = frame.unpack(theta[:5])
    tau = float(expit(theta[5]))
    spot = _fit_scale(theta, "first")
    g = _geometry(a, w, float(r), rays, optics, spot)
    big_t, slope = (warm or _Warm()).solve(theta, g, tau)
    f0, fp0, grad, near_mask = _first_share_grad(big_t, g.x0, g.t_ca, g.cos_axis, g.radius, g.s0, g.sd)
    target0 = np.minimum(tau, 0.999 * g.c)
    near = np.flatnonzero(near_mask)
    flat = np.flatnonzero(fp0 < 1.0)  # F flat at T (a spot that barely meets the part): re-solved
    fp0 = np.maximum(fp0, 1.0)
    r0 = _first_rows(g, big_t, slope, tau, rays, optics)
    ncol = theta.size  # 6, or 7 with the spot's scale (and its prior row)
    jac = np.zeros((r0.size + (ncol > 6), ncol))
    cols = []
    redo: list[IntArray] = []  # per column: the beams whose range is re-solved by Newton
    for j in range(ncol):
        th = theta.copy()
        th[j] += _JAC_STEP[j]
        aj, wj, rj = frame.unpack(th[:5])
        tj = float(expit(th[5]))
        if j < 5:
            gj = _geometry(aj, wj, float(rj), rays, optics, spot)
            # F's change at T0 to first order in the geometry's (the steps are 1e-6)
            df = (
                grad[:, 0] * (gj.x0 - g.x0)
                + grad[:, 1] * (gj.t_ca - g.t_ca)
                + grad[:, 2] * (gj.cos_axis - g.cos_axis)
                + grad[:, 3] * (gj.radius - g.radius)
            )
            if near.size:
                fn, _ = _first_share(big_t[near], gj.x0[near], gj.t_ca[near], gj.cos_axis[near], gj.radius, g.s0, g.sd)
                df[near] = fn - f0[near]
        elif j == 5:  # the threshold: F unchanged, only the target moves
            gj, df = g, np.zeros_like(f0)
        else:
            # the spot's scale: F at T0 under the scaled spot, evaluated (one F for all beams, no
            # Newton solve); the implicit step as for the other columns
            gj = _geometry(a, w, float(r), rays, optics, _fit_scale(th, "first"))
            df = _first_share(big_t, gj.x0, gj.t_ca, gj.cos_axis, gj.radius, gj.s0, gj.sd)[0] - f0
        target_j = np.minimum(tj, 0.999 * gj.c)
        tt = big_t - (df - (target_j - target0)) / fp0
        bad = flat
        if near.size and j != 5:
            # near the front's tip F has a node's square-root onset: the linear step from T0 can
            # miss (a radius row 47x off, spot 1.1 x nominal). Checked where it lands: a beam
            # whose F there misses the target by more than 1 % of its step is re-solved
            fl, _ = _first_share(tt[near], gj.x0[near], gj.t_ca[near], gj.cos_axis[near], gj.radius, gj.s0, gj.sd)
            miss = np.abs(fl - target_j[near]) / fp0[near] > 0.01 * np.abs(tt[near] - big_t[near]) + 1e-13
            bad = np.union1d(flat, near[miss])
        redo.append(bad)
        cols.append((gj, tj, tt))
    # every column's re-solved beams in one Newton solve per spot size (the geometry and threshold
    # columns share the spot; the spot's own column has its own)
    for group in (range(min(ncol, 6)), range(6, ncol)):
        if not sum(redo[j].size for j in group):
            continue
        gs = cols[group[0]][0]
        tt_redo, _ = _first_newton(
            np.concatenate([cols[j][0].x0[redo[j]] for j in group]),
            np.concatenate([cols[j][0].t_ca[redo[j]] for j in group]),
            np.concatenate([cols[j][0].cos_axis[redo[j]] for j in group]),
            np.concatenate([np.full(redo[j].size, cols[j][0].radius) for j in group]),
            gs.s0,
            gs.sd,
            np.concatenate([np.minimum(cols[j][1], 0.999 * cols[j][0].c[redo[j]]) for j in group]),
            np.concatenate([cols[j][0].c[redo[j]] for j in group]),
        )
        at = 0
        for j in group:
            b = redo[j]
            cols[j][2][b] = tt_redo[at : at + b.size]
            at += b.size
    for j, (gj, tj, tt) in enumerate(cols):
        sj = slope
        if optics.share_u > 0.0:
            _, fpj = _first_share(tt, gj.x0, gj.t_ca, gj.cos_axis, gj.radius, gj.s0, gj.sd)
            sj = 1.0 / np.maximum(fpj, 1.0)
        jac[: r0.size, j] = (_first_rows(gj, tt, sj, tj, rays, optics) - r0) / _JAC_STEP[j]
    if ncol > 6:  # the spot scale's prior row (log(scale) / spot_scale_u)
        jac[r0.size, 6] = 1.0 / optics.spot_scale_u
    return jac


def _solve(frame: _Frame, rays: Rays, optics: BeamOptics, mode: EdgeMode, start: FloatArray) -> _Solved:
    from scipy.optimize import least_squares  # on first use: ~0.4 s of a command's start-up otherwise

    # the footprint makes the thin-beam fit too large by up to a spot diameter, never smaller by
    # more than a fraction of one: bounds keep a flat likelihood from wandering off
    spot = float(2.0 / optics.profile_sigma * optics.sigma(float(np.linalg.norm(frame.a))))
    lo, hi, x_scale = _box(mode, spot, start.size)
    jac: object = "2-point"
    warm = _Warm() if mode == "first" else None
    if mode == "first" and _JACOBIAN == "implicit":
        jac = lambda th: _first_jacobian(th, frame, rays, optics, warm)  # noqa: E731
    out = least_squares(
        lambda th: _residuals(th, frame, rays, optics, mode, 1.0, warm),
        np.clip(start, lo + 1e-12, hi - 1e-12),
        jac=jac,
        bounds=(lo, hi),
        method="trf",
        x_scale=x_scale,
        diff_step=np.full(start.size, 1e-5),
        ftol=_FTOL,
        max_nfev=60 * start.size,
    )
    if not np.all(np.isfinite(out.x)):
        raise FitError("footprint fit diverged")
    tau = float(expit(out.x[5])) if mode == "first" else float("nan")
    watched = [i for i in (4, 5 if mode == "first" else -1, _spot_index(mode)) if 0 <= i < start.size]
    x, width = np.asarray(out.x)[watched], (hi - lo)[watched]
    # trf keeps its iterates strictly inside the box: "on the bound" is within PIN_TOL of the box's width
    pinned = bool(np.any(np.minimum(x - lo[watched], hi[watched] - x) < PIN_TOL * width))
    return _Solved(
        mode, np.asarray(out.x), tau, float(2.0 * out.cost), np.asarray(out.jac), start.size, rays, out.nfev, pinned
    )


#: Bounds of the spot's log scale: half to twice the nominal size.
SPOT_LOG_BOUND = float(np.log(2.0))


def _box(mode: EdgeMode, spot: float, size: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Bounds and ``x_scale`` of a family's ``size`` parameters (``spot``: the nominal spot
    diameter at the part): the axis (rad, m), the radius's change, logit(tau), log(spot scale)."""
    tau = [(-8.0, 8.0, 0.3)] if mode == "first" else []
    cols = [
        (-0.05, 0.05, 1e-3),
        (-0.05, 0.05, 1e-3),
        (-spot, spot, 1e-3),
        (-spot, spot, 1e-3),
        (-spot, 0.25 * spot, 1e-3),
        *tau,
        (-SPOT_LOG_BOUND, SPOT_LOG_BOUND, 0.05),
    ][:size]
    lo, hi, xs = (np.array(c, dtype=np.float64) for c in zip(*cols, strict=True))
    return lo, hi, xs


#: The first-hit family's Jacobian: "implicit" (:func:`_first_jacobian`) or "2-point" (plain
#: forward differences through the Newton solve; kept as the benchmark's baseline).
_JACOBIAN = "implicit"
#: A family's solution within this share of its box's width from a bound (radius, threshold, spot
#: scale) is pinned there (:attr:`_Solved.pinned`): the first hit's (radius, tau) ridge ran into the
#: radius's upper bound at tau 0.8 on 1 sweep in 400 (issue 11's coverage run, 0.3:weighted sweep 367).
PIN_TOL = 2e-3
#: least_squares' relative tolerance on the cost.
_FTOL = 1e-8


def hit_heights(cyl: Cylinder, rays: Rays, t: FloatArray) -> FloatArray:
    """Heights along ``cyl``'s axis (from its point) of the points at ranges ``t`` on ``rays``."""
    return np.asarray((rays.origins + t[:, None] * rays.dirs - cyl.point) @ cyl.direction, dtype=np.float64)


def _end_trim(cyl: Cylinder, rays: Rays, optics: BeamOptics) -> NDArray[np.bool_]:
    """Beams whose spot stays clear of the ends of the visible part (table, top): the model is an
    infinite cylinder, so a spot that straddles an end is not in it. The ends are the extreme hit
    heights of the inliers; the margin is 3 spot sigmas."""
    t, _ = cyl.ray_range(rays.origins, rays.dirs)
    h = hit_heights(cyl, rays, t)
    margin = 3.0 * optics.sigma(t)
    return np.asarray((h - margin >= np.min(h)) & (h + margin <= np.max(h)), dtype=np.bool_)
