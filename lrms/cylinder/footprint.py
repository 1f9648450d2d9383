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

Where things live: this module holds :class:`BeamOptics`, the echo model (:func:`expected_echo`,
the disc marginal), the residuals, the first-hit Jacobian, the solve, :func:`footprint_fit` with the
family choice and the profile-likelihood interval of the radius (kept here: it refits through
``_solve``'s residuals); :mod:`lrms.cylinder.footprint_first` holds the first-hit range solver
(:func:`first_hit_range`, its Newton iteration and share ``F(T)``, re-imported here);
:mod:`lrms.cylinder.footprint_bias` the fit's second-order bias.
"""

from __future__ import annotations

from contextlib import suppress
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import expit, logit, ndtr, ndtri

from lrms.cylinder.footprint_first import _first_newton, _first_share, _first_share_grad, first_hit_range
from lrms.cylinder.model import Cylinder, Rays, _dot, _ray_cylinder
from lrms.cylinder.refine import CylinderFit, _Frame, los_residuals
from lrms.errors import FitError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
EdgeMode = Literal["weighted", "first"]

#: LMS1xx light spot at the front screen (m) and divergence (full angle, rad): SICK 8012471, 3.6.2.
LMS1XX_EXIT_DIAMETER = 0.008
LMS1XX_DIVERGENCE = 0.015
#: AIC difference above which one edge family is taken as decided by the data.
MODE_DECISIVE = 10.0
#: Threshold starts of the first-hit family (each with the radius its silhouette implies, see
#: :func:`_first_starts`): its cost in (radius, tau) has local minima along a rough ridge, and one
#: start from the thin beam settled up to 15 mm small on 10 % first-hit clouds.
FIRST_STARTS = (0.1, 0.3, 0.5)
#: Scale (share of the spot) of the penalty on a first-hit beam the model covers by less than tau.
COVERAGE_SCALE = 0.05
#: Gauss-Legendre nodes and weights on (0, 1).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)
_GL_U = 0.5 * (_GL_X + 1.0)
_GL_G = 0.5 * _GL_W


@dataclass(frozen=True)
class BeamOptics:
    """The scanner's light spot, as the fit models it.

    ``exit_diameter_m`` + ``divergence_rad`` x range: the nominal spot diameter (LMS1xx: 8 mm,
    15 mrad, SICK 8012471 section 3.6.2). ``profile_sigma``: the Gaussian's sigma over that
    diameter (0.25: the diameter read as the 1/e^2 intensity diameter; SICK does not define the
    spot's edge, so this is our reading). ``spot_scale_u``: relative standard uncertainty of the
    effective spot size carried into ``edge_model_u_m`` (0.15, ours). ``share_u``: standard
    uncertainty of a first-hit beam's share of the spot at the threshold (profile shape, a
    receiver's or the simulator's sampling of the spot), added to the range sigma through
    ``dT / d share``: it down-weights the beams at the detection edge, whose first hit sits on the
    limb's steep range profile; the model choice compares every family under ``sigma_l`` alone.
    Default 0 (off): 0.03 removes most of a noiseless cloud's edge bias, but on noisy room clouds
    the weighted fit lands where the common-noise likelihood loses to the thin beam (10 % / 30 %
    first hit: 4 / 5 of 6 sweeps failed; docs/cylinder.md, section 7). ``extent``: the spot's
    light ends at ``extent`` nominal spot radii (1.5: three sigmas at profile_sigma 0.25; a real
    spot is cut by the optics' apertures, and a Gaussian without an end is no better a reading of
    SICK's figures): the energy-weighted family integrates the profile of that disc
    (:func:`disc_marginal_cdf`; the first-hit family keeps the untruncated Gaussian). ``fit_spot``
    (default on, with ``spot_scale_u > 0``): the spot's scale is estimated by the fit, the nominal
    (or calibrated) size entering as a prior observation ``log(scale) / spot_scale_u`` (a residual
    row), so the fit's type A holds the spot's uncertainty and ``edge_model_u_m`` is 0; off (or
    ``spot_scale_u = 0``): the spot is held at its nominal size and ``spot_scale_u`` carried as the
    ``edge_model_u_m`` row. Bad values: :class:`FitError`.
    """

    exit_diameter_m: float = LMS1XX_EXIT_DIAMETER
    divergence_rad: float = LMS1XX_DIVERGENCE
    profile_sigma: float = 0.25
    spot_scale_u: float = 0.15
    share_u: float = 0.0
    extent: float = 1.5
    fit_spot: bool = True

    def __post_init__(self) -> None:
        for name, lo, hi in (
            ("exit_diameter_m", 0.0, 0.5),
            ("divergence_rad", 0.0, 0.5),
            ("profile_sigma", 1e-3, 10.0),
            ("spot_scale_u", 0.0, 1.0),
            ("share_u", 0.0, 0.5),
            ("extent", 0.1, 10.0),
        ):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and lo <= v <= hi):
                raise FitError(f"beam optics: {name} must be within [{lo}, {hi}], got {v!r}")
        if self.exit_diameter_m == 0.0 and self.divergence_rad == 0.0:
            raise FitError("beam optics: a spot of zero size is the thin beam (use no optics)")
        if not isinstance(self.fit_spot, bool):
            raise FitError(f"beam optics: fit_spot must be a bool, got {self.fit_spot!r}")

    @property
    def spot_free(self) -> bool:
        """Whether the footprint fit estimates the spot's scale (``fit_spot`` with a prior width)."""
        return self.fit_spot and self.spot_scale_u > 0.0

    def sigma(self, range_m: FloatArray | float) -> FloatArray:
        """The spot profile's standard deviation (m) at ``range_m``."""
        return np.asarray(
            self.profile_sigma * (self.exit_diameter_m + self.divergence_rad * np.asarray(range_m)), dtype=np.float64
        )


def expected_echo(
    cyl_a: FloatArray,
    cyl_w: FloatArray,
    radius: float,
    rays: Rays,
    optics: BeamOptics,
    mode: EdgeMode,
    tau: float = 0.3,
    scale: float = 1.0,
) -> tuple[FloatArray, FloatArray]:
    """Expected range of each beam's echo from the cylinder ``(cyl_a, cyl_w, radius)`` and the
    covered share ``c`` of its spot (see the module notes). ``scale`` multiplies the spot size."""
    rng_, c, _ = _echo(cyl_a, cyl_w, radius, rays, optics, mode, tau, scale)
    return rng_, c


def _geometry(
    cyl_a: FloatArray, cyl_w: FloatArray, radius: float, rays: Rays, optics: BeamOptics, scale: float
) -> _Geom:
    """Per-beam geometry of the spot against the cylinder (see the module notes)."""
    o, u = rays.origins, rays.dirs
    w = np.asarray(cyl_w, dtype=np.float64)
    a = np.asarray(cyl_a, dtype=np.float64)
    nvec = np.cross(u, w)
    nn = np.maximum(np.linalg.norm(nvec, axis=1, keepdims=True), 1e-12)
    nvec = nvec / nn
    x0 = _dot(o - a, nvec)
    t_ca, _ = _ray_cylinder(o, u, a, w, np.asarray(1e-9))  # closest approach to the axis
    s0 = scale * optics.profile_sigma * optics.exit_diameter_m
    sd = scale * optics.profile_sigma * optics.divergence_rad
    sig = s0 + sd * np.maximum(t_ca, 0.0)
    p_lo, p_hi = ndtr((-radius - x0) / sig), ndtr((radius - x0) / sig)
    c = np.maximum(p_hi - p_lo, 0.0)
    return _Geom(a, w, float(radius), nvec, x0, t_ca, _dot(u, w), s0, sd, p_lo, c)


@dataclass
class _Geom:
    a: FloatArray
    w: FloatArray
    radius: float
    nvec: FloatArray
    x0: FloatArray
    t_ca: FloatArray
    cos_axis: FloatArray
    s0: float
    sd: float
    p_lo: FloatArray
    c: FloatArray


def _echo(
    cyl_a: FloatArray,
    cyl_w: FloatArray,
    radius: float,
    rays: Rays,
    optics: BeamOptics,
    mode: EdgeMode,
    tau: float = 0.3,
    scale: float = 1.0,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`expected_echo`, and for a first hit the slope ``dT / d share`` of the range in the
    share of the spot at the threshold (0 for the energy-weighted family)."""
    g = _geometry(cyl_a, cyl_w, radius, rays, optics, scale)
    o, u, a, w, nvec, x0, s0, sd, p_lo, c = (rays.origins, rays.dirs, g.a, g.w, g.nvec, g.x0, g.s0, g.sd, g.p_lo, g.c)
    if mode == "first":
        big_t, slope = first_hit_range(x0, g.t_ca, g.cos_axis, radius, s0, sd, tau, c)
        return big_t, c, slope
    # the spot's light within its disc (BeamOptics.extent): the lateral marginal of the truncated
    # profile, its covered share and nodes in its probability (a spot that meets nothing keeps
    # nodes at the edge)
    grid, cum = _disc_table(optics.extent / (2.0 * optics.profile_sigma))
    sig = s0 + sd * np.maximum(g.t_ca, 0.0)
    p_lo = np.interp((-radius - x0) / sig, grid, cum)
    c = np.maximum(np.interp((radius - x0) / sig, grid, cum) - p_lo, 0.0)
    width = np.maximum(c, 1e-9)
    base = np.where(x0 > 0, np.minimum(p_lo, 1.0 - width), p_lo)
    p = np.clip(base[:, None] + width[:, None] * _GL_U[None, :], 0.0, 1.0)
    xi = np.interp(p, cum, grid)  # (N, K)
    # the light of each node; a beam's share c multiplies all its nodes alike and cancels in the
    # weighted range, so it is left out: a spot wholly off the disc (c = 0) keeps the range of its
    # edge nodes instead of 0 / 0 (a 200-sigma cliff for the solver's differences)
    wts = np.broadcast_to(_GL_G[None, :], xi.shape)
    k = xi.shape[1]

    def cast(lateral: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        off = lateral[..., None] * nvec[:, None, :]
        so = o[:, None, :] + s0 * off
        su = u[:, None, :] + np.tan(sd) * off
        su = su / np.linalg.norm(su, axis=2, keepdims=True)
        t, _ = _ray_cylinder(so.reshape(-1, 3), su.reshape(-1, 3), a, w, np.asarray(radius))
        return t.reshape(-1, k), so, su

    t, so, su = cast(xi)
    hit = so + t[..., None] * su  # each node's hit point, from its own start (the exit spot's offset)
    q = hit - a
    q = q - _dot(q, w)[..., None] * w
    cos = np.abs(_dot(q, su)) / np.maximum(np.linalg.norm(q, axis=2), 1e-300)
    e = wts * np.maximum(cos, 1e-3) / np.square(np.maximum(t, 1e-3))
    rng_ = np.sum(e * t, axis=1) / np.maximum(np.sum(e, axis=1), 1e-300)
    return np.asarray(rng_, dtype=np.float64), c, np.zeros_like(c)


@lru_cache(maxsize=8)
def _disc_table(extent_sigmas: float, size: int = 8001) -> tuple[FloatArray, FloatArray]:
    """The lateral marginal of a unit 2-D Gaussian cut to a disc of ``extent_sigmas`` sigmas:
    ``f(x) ~ phi(x) (2 Phi(sqrt(R^2 - x^2)) - 1)`` on ``[-R, R]``; returns a grid and its
    cumulative distribution (trapezoid rule, normalised; read by linear interpolation both ways)."""
    x = np.linspace(-extent_sigmas, extent_sigmas, size)
    pdf = np.exp(-0.5 * x * x) * (2.0 * ndtr(np.sqrt(np.maximum(extent_sigmas**2 - x * x, 0.0))) - 1.0)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (pdf[1:] + pdf[:-1]) * np.diff(x))])
    return x, cum / cum[-1]


def disc_marginal_cdf(z: FloatArray | float, extent_sigmas: float) -> FloatArray:
    """Share of a Gaussian spot cut to a disc of ``extent_sigmas`` sigmas whose lateral coordinate
    is ``<= z`` sigmas (0 below ``-extent_sigmas``, 1 above): the covered share of the spot for
    an edge across it, as the energy-weighted family models it (``BeamOptics.extent``)."""
    if not (np.isfinite(extent_sigmas) and extent_sigmas > 0):
        raise FitError(f"the disc's extent must be a positive number of sigmas, got {extent_sigmas!r}")
    grid, cum = _disc_table(float(extent_sigmas))
    return np.asarray(np.interp(np.asarray(z, dtype=np.float64), grid, cum), dtype=np.float64)


def disc_marginal_ppf(p: FloatArray | float, extent_sigmas: float) -> FloatArray:
    """The inverse of :func:`disc_marginal_cdf`: the lateral coordinate (sigmas) below which the
    share ``p`` (in [0, 1]) of a Gaussian spot cut to a disc of ``extent_sigmas`` sigmas lies."""
    if not (np.isfinite(extent_sigmas) and extent_sigmas > 0):
        raise FitError(f"the disc's extent must be a positive number of sigmas, got {extent_sigmas!r}")
    grid, cum = _disc_table(float(extent_sigmas))
    return np.asarray(np.interp(np.asarray(p, dtype=np.float64), cum, grid), dtype=np.float64)


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
    up to 7 % off, and one 47x where the linear step crossed a node's tip).
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
    jac = np.empty((r0.size, 6))
    cols = []
    redo: list[IntArray] = []  # per column: the beams whose range is re-solved by Newton
    for j in range(6):
        th = theta.copy()
        th[j] += _JAC_STEP[j]
        aj, wj, rj = frame.unpack(th[:5])
        tj = float(expit(th[5]))
        gj = _geometry(aj, wj, float(rj), rays, optics, spot) if j < 5 else g
        # F's change at T0 to first order in the geometry's (the steps are 1e-6)
        df = (
            grad[:, 0] * (gj.x0 - g.x0)
            + grad[:, 1] * (gj.t_ca - g.t_ca)
            + grad[:, 2] * (gj.cos_axis - g.cos_axis)
            + grad[:, 3] * (gj.radius - g.radius)
        )
        if near.size and j < 5:
            fn, _ = _first_share(big_t[near], gj.x0[near], gj.t_ca[near], gj.cos_axis[near], gj.radius, g.s0, g.sd)
            df[near] = fn - f0[near]
        target_j = np.minimum(tj, 0.999 * gj.c)
        tt = big_t - (df - (target_j - target0)) / fp0
        bad = flat
        if near.size and j < 5:
            # near the front's tip F has a node's square-root onset: the linear step from T0 can
            # miss (a radius row 47x off, spot 1.1 x nominal). Checked where it lands: a beam
            # whose F there misses the target by more than 1 % of its step is re-solved
            fl, _ = _first_share(tt[near], gj.x0[near], gj.t_ca[near], gj.cos_axis[near], gj.radius, g.s0, g.sd)
            miss = np.abs(fl - target_j[near]) / fp0[near] > 0.01 * np.abs(tt[near] - big_t[near]) + 1e-13
            bad = np.union1d(flat, near[miss])
        redo.append(bad)
        cols.append((gj, tj, tt))
    if sum(b.size for b in redo):  # every column's re-solved beams in one Newton solve
        tt_redo, _ = _first_newton(
            np.concatenate([gj.x0[b] for (gj, _, _), b in zip(cols, redo, strict=True)]),
            np.concatenate([gj.t_ca[b] for (gj, _, _), b in zip(cols, redo, strict=True)]),
            np.concatenate([gj.cos_axis[b] for (gj, _, _), b in zip(cols, redo, strict=True)]),
            np.concatenate([np.full(b.size, gj.radius) for (gj, _, _), b in zip(cols, redo, strict=True)]),
            g.s0,
            g.sd,
            np.concatenate([np.minimum(tj, 0.999 * gj.c[b]) for (gj, tj, _), b in zip(cols, redo, strict=True)]),
            np.concatenate([gj.c[b] for (gj, _, _), b in zip(cols, redo, strict=True)]),
        )
        at = 0
        for (_, _, tt), b in zip(cols, redo, strict=True):
            tt[b] = tt_redo[at : at + b.size]
            at += b.size
    for j, (gj, tj, tt) in enumerate(cols):
        sj = slope
        if optics.share_u > 0.0:
            _, fpj = _first_share(tt, gj.x0, gj.t_ca, gj.cos_axis, gj.radius, gj.s0, gj.sd)
            sj = 1.0 / np.maximum(fpj, 1.0)
        jac[:, j] = (_first_rows(gj, tt, sj, tj, rays, optics) - r0) / _JAC_STEP[j]
    if theta.size == 6:
        return jac
    # the spot's scale: a plain forward difference (one Newton solve), and the prior row
    th = theta.copy()
    th[6] += _JAC_STEP[6]
    full = np.zeros((r0.size + 1, 7))
    full[: r0.size, :6] = jac
    base = np.append(r0, theta[6] / optics.spot_scale_u)
    full[:, 6] = (_residuals(th, frame, rays, optics, "first") - base) / _JAC_STEP[6]
    return full


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


def _end_trim(cyl: Cylinder, rays: Rays, optics: BeamOptics) -> NDArray[np.bool_]:
    """Beams whose spot stays clear of the ends of the visible part (table, top): the model is an
    infinite cylinder, so a spot that straddles an end is not in it. The ends are the extreme hit
    heights of the inliers; the margin is 3 spot sigmas."""
    t, _ = cyl.ray_range(rays.origins, rays.dirs)
    h = (rays.origins + t[:, None] * rays.dirs - cyl.point) @ cyl.direction
    margin = 3.0 * optics.sigma(t)
    return np.asarray((h - margin >= np.min(h)) & (h + margin <= np.max(h)), dtype=np.bool_)


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
    and lowest point ``footprint_profile_lowest_m``, diameter offsets, are in ``extra``; energy-weighted:
    the curvature at +-1 mm, :func:`_profile_variance`), and whose ``extra`` holds
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
            starts.update({s.mode: s.theta for s in sub_solved})
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
        best = _regated(best, frame, rays, fit.cylinder, work, optics, gate, work_size)
    extra["footprint_beams"] = float(best.rays.ranges.size)
    jac = best.jac
    n_res = best.rays.ranges.size  # range rows (a first-hit fit adds coverage rows)
    jtj_inv = np.linalg.pinv(jac.T @ jac)
    dof = max(n_res - best.n_par, 1)
    range_rows = _residuals(best.theta, frame, best.rays, optics, best.mode)[:n_res]
    chi2 = float(np.sum(range_rows * range_rows))
    chi2_dof = chi2 / dof
    cov_full = jtj_inv * max(1.0, chi2_dof)
    # the profile of the cost in the radius: the first hit's radius trades off against tau along a
    # flat, rough ridge that the Gauss-Newton curvature J^T J does not see (its u was 4-5x below
    # the spread of noise-only replicas); the variance is taken as the larger of the two, the whole
    # covariance scaled by their ratio (the axis point follows the radius along that ridge; see
    # docs/cylinder.md section 7). First hit: the profile-likelihood interval, its crossing searched
    # for (rounds 3-5); energy-weighted: the profile's curvature at +-1 mm
    var_jtj = float(cov_full[4, 4])
    prof: _Profile | None = None
    if best.mode == "first":
        prof = _profile_interval(best, frame, optics, chi2_dof)
        var_prof = prof.u**2
    else:
        var_prof = _profile_variance(best, frame, optics) * max(1.0, chi2_dof)
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
    best: _Solved, frame: _Frame, rays: Rays, thin: Cylinder, work: Rays, optics: BeamOptics, gate: float, size: int
) -> _Solved:
    """``best`` solved again on the beams within ``gate`` of its own model, taken from every beam on
    the thin-beam cylinder's lines of sight within :data:`REGATE_BAND` of its range and between the
    work beams' extreme heights along the axis (their ends already trimmed); twice, each time from
    the last solution. A solution pinned on a bound, or fewer than 30 beams, keeps ``best``."""
    t, gap = thin.ray_range(rays.origins, rays.dirs)
    near = np.flatnonzero((gap <= 0.0) & (np.abs(rays.ranges - t) < REGATE_BAND))
    tw, _ = thin.ray_range(work.origins, work.dirs)
    hw = (work.origins + tw[:, None] * work.dirs - thin.point) @ thin.direction
    hn = (rays.origins[near] + t[near, None] * rays.dirs[near] - thin.point) @ thin.direction
    near = near[(hn >= hw.min()) & (hn <= hw.max())]
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


#: Radius step (m) of the cost's profile and the floor of its rise (a flat profile's u stays finite).
PROFILE_STEP = 1e-3
PROFILE_FLOOR = 0.05
#: Radius offsets (m) of the first-hit family's profile search, outward on each side of the
#: solution; the last is the widest interval half-width it can report.
PROFILE_SEARCH = (1e-3, 2e-3, 3e-3, 4.5e-3, 6.5e-3, 9e-3, 12e-3)
#: Coverage factor of the profile-likelihood interval (its crossing: a rise of k^2 x the residual
#: variance factor); the u reported is the half-width over k.
PROFILE_K = 2.0


def _held(
    best: _Solved, frame: _Frame, optics: BeamOptics, offset: float, start: FloatArray, max_nfev: int
) -> tuple[float, FloatArray]:
    """The cost (chi-square) with the radius held at ``best``'s + ``offset`` and the other
    parameters refitted from ``start`` (theirs, radius left out); returns it and the parameters."""
    from scipy.optimize import least_squares  # on first use (see _solve)

    idx = [i for i in range(best.theta.size) if i != 4]
    full = best.theta.copy()
    full[4] += offset

    warm = _Warm() if best.mode == "first" else None  # the Jacobian is asked where fun just was

    def fun(p: FloatArray) -> FloatArray:
        t = full.copy()
        t[idx] = p
        return _residuals(t, frame, best.rays, optics, best.mode, 1.0, warm)

    jac: object = "2-point"
    if best.mode == "first":

        def jac_fn(p: FloatArray) -> FloatArray:
            t = full.copy()
            t[idx] = p
            return _first_jacobian(t, frame, best.rays, optics, warm)[:, idx]

        jac = jac_fn
    out = least_squares(
        fun,
        start,
        jac=jac,
        method="trf",
        x_scale=np.delete(_box(best.mode, 1.0, best.theta.size)[2], 4),
        diff_step=np.full(len(idx), 1e-5),
        ftol=_FTOL,
        max_nfev=max_nfev,
    )
    return float(2.0 * out.cost), np.asarray(out.x, dtype=np.float64)


def _profile_variance(best: _Solved, frame: _Frame, optics: BeamOptics) -> float:
    """Variance of the radius from the profile of the cost: the other parameters refitted with the
    radius held at ``r +- PROFILE_STEP``; the mean rise ``dC`` of the cost (chi-square) over the
    lowest of the three gives ``var = step^2 / dC`` (a parabola: dC = 1 at one sigma). The rise is
    floored at ``PROFILE_FLOOR`` (u at most 4.5 steps). The energy-weighted family's u."""
    start = np.delete(best.theta, 4)
    costs = [_held(best, frame, optics, h, start, 4 * start.size)[0] for h in (-PROFILE_STEP, PROFILE_STEP)]
    rise = 0.5 * (costs[0] + costs[1]) - min(best.cost, *costs)
    return float(PROFILE_STEP**2 / max(rise, PROFILE_FLOOR))


@dataclass(frozen=True)
class _Profile:
    """The first-hit family's profile-likelihood interval of the radius (offsets from the solution, m)."""

    lo: float  # the interval's lower end (<= 0)
    hi: float  # its upper end (>= 0)
    lowest: float  # the offset of the lowest cost the profile met (0: the solution itself)
    evaluations: int  # held-radius solves

    @property
    def u(self) -> float:
        """The radius's standard uncertainty: the interval's larger half-width over ``PROFILE_K``."""
        return max(-self.lo, self.hi) / PROFILE_K


def _profile_interval(best: _Solved, frame: _Frame, optics: BeamOptics, variance_factor: float) -> _Profile:
    """The profile-likelihood interval of the radius: the radius held at the offsets
    :data:`PROFILE_SEARCH` outward on each side (each solve started from the last one's parameters:
    it follows the (radius, tau) ridge), the rest refitted; a side stops at the first offset whose
    cost rises above the lowest met by more than ``Delta = PROFILE_K^2 x variance_factor`` (the
    likelihood-ratio interval at k = 2, widened by the residual variance factor ``max(1,
    chi2/dof)``). Each end is the outermost offset still within ``Delta`` of the lowest cost, carried
    to the crossing by interpolating ``sqrt(rise)`` (linear in the offset for a parabola); a side
    that never crosses ends at the last offset searched. On the first hit's flat, rough ridge the
    cost's curvature at +-1 mm understated the spread of its radius (docs/cylinder.md, section 7,
    round 5): the crossing is searched for, not extrapolated."""
    delta = PROFILE_K**2 * max(1.0, variance_factor)
    start = np.delete(best.theta, 4)
    pts: dict[float, float] = {0.0: best.cost}
    floor = best.cost
    for side in (-1.0, 1.0):
        p = start
        for h in PROFILE_SEARCH:
            cost, p = _held(best, frame, optics, side * h, p, 6 * start.size)
            pts[side * h] = cost
            floor = min(floor, cost)
            if cost - floor > delta:
                break
    ends = []
    for side in (-1.0, 1.0):
        offs = [0.0, *[side * h for h in PROFILE_SEARCH if side * h in pts]]
        rise = [max(pts[o] - floor, 0.0) for o in offs]
        inside = [j for j, r in enumerate(rise) if r <= delta]
        j = max(inside) if inside else 0
        if j + 1 < len(offs):  # carried to the crossing with the next (outside) offset
            sa, sb = np.sqrt(rise[j]), np.sqrt(rise[j + 1])
            frac = (np.sqrt(delta) - sa) / max(sb - sa, 1e-12)
            ends.append(offs[j] + float(np.clip(frac, 0.0, 1.0)) * (offs[j + 1] - offs[j]))
        else:
            ends.append(offs[j])
    lowest = min(pts, key=lambda o: pts[o])
    return _Profile(lo=min(ends[0], 0.0), hi=max(ends[1], 0.0), lowest=lowest, evaluations=len(pts) - 1)
