"""The footprint model's optics and echo: :class:`BeamOptics` (the LMS1xx's spot), the expected
echo of a beam whose Gaussian spot meets a model cylinder in whole or in part
(:func:`expected_echo`, :func:`_echo` on a beam geometry :func:`_geometry`), and the lateral
marginal of a Gaussian cut to a disc (:func:`disc_marginal_cdf`, :func:`disc_marginal_ppf`).
The model is described in :mod:`lrms.cylinder.footprint`; the fit's residuals and solve are in
:mod:`lrms.cylinder.footprint_solve`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from lrms.cylinder.footprint_first import first_hit_range
from lrms.cylinder.model import Rays, _dot, _ray_cylinder
from lrms.errors import FitError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
EdgeMode = Literal["weighted", "first"]

#: LMS1xx light spot at the front screen (m) and divergence (full angle, rad): SICK 8012471, 3.6.2.
LMS1XX_EXIT_DIAMETER = 0.008
LMS1XX_DIVERGENCE = 0.015
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
