"""The scanner's spot size from reference spheres of known diameter (issue 12, item 2).

With a finite light spot (LMS1xx: ``exit + divergence x range``, :class:`lrms.cylinder.BeamOptics`)
a beam whose thin-beam ray passes near a sphere's limb still returns an echo formed over the part
of the spot that covers the sphere, and its range is the energy-weighted mean over that part: the
limb beams read *short* of the thin-beam surface (or hit where the thin ray misses), and the
sphere looks bigger. How much depends on the spot's size. With the sphere's centre and its
calibrated radius known from the adjustment, the range of each limb beam is predicted for a spot
``s`` times the nominal one, and ``s`` is fitted to the measured ranges (one parameter, least
squares, the range noise ``sigma_l``), with its standard uncertainty from the curvature of the
sum of squares (scaled by the variance factor when it exceeds 1).

The expected echo of a beam at closest approach ``x0`` from the centre, ``t_ca`` along the beam:
the spot is a Gaussian of standard deviation ``sigma = s profile_sigma (exit + divergence t_ca)``
whose light ends at ``BeamOptics.extent`` spot radii (a disc of ``R = extent / (2 profile_sigma)``
sigmas: 3 for the LMS1xx defaults, as the footprint fit's energy-weighted family and the simulator
model it). The limb is two-dimensional (the spot meets a sphere, not a cylinder): the coordinate
along the limb (``y``) is drawn from the disc's lateral marginal (Gauss-Legendre nodes placed in
its probability, :func:`lrms.cylinder.footprint.disc_marginal_ppf`), and given ``y`` the radial
one (``x``) is the Gaussian cut to the disc's chord ``|x| <= sqrt(R^2 - y^2)`` sigmas; the covered
radial interval, that chord intersected with ``|x| < sqrt(r^2 - y^2)``, is integrated by
Gauss-Legendre nodes placed in probability (as :func:`lrms.cylinder.footprint.expected_echo` does
for a cylinder, here with the curvature along the limb kept), each sub-ray meeting the sphere at
``t_ca - sqrt(r^2 - x^2 - y^2)`` with energy ``~ cos(incidence) / t^2``. This is the
"energy-weighted" edge family (the simulator's default and the footprint fit's "weighted" mode);
the sub-rays' divergence across the spot is left out (a path difference below 0.1 mm). With
``extent`` infinite the endless Gaussian (Gauss-Hermite nodes along the limb), as calibrations
before the disc cut were estimated: on a noiseless simulated sweep it read the scale 1.7 % lower
than the disc (docs/calibration.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import optimize
from scipy.special import ndtr, ndtri

from lrms.cylinder.footprint import disc_marginal_ppf

FloatArray = NDArray[np.float64]

_GL_X, _GL_W = np.polynomial.legendre.leggauss(12)
_GL_U, _GL_G = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W
_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(9)
_GH_W = _GH_W / np.sqrt(2.0 * np.pi)

#: Range of spot scales searched.
SCALE_BOUNDS = (0.05, 6.0)
#: Relative standard uncertainty of the limb-echo model itself, added to the fit's: on a simulated
#: LMS1xx (32 sub-rays, energy-weighted echoes) with the true spot, 3382 limb beams gave
#: s = 0.949 +- 0.017 (fit alone, endless Gaussian); this term covers that. With the disc cut, a
#: noiseless sweep of 128 sub-rays still reads 2.0-2.6 % low (docs/calibration.md).
MODEL_U = 0.03
#: Fewer limb beams than this: the spot scale is not estimated.
MIN_LIMB_BEAMS = 30


@dataclass(frozen=True)
class SpotScale:
    """The estimated spot scale (multiplies the nominal exit diameter and divergence), its standard
    uncertainty, the limb beams used and their rms range residual (m)."""

    scale: float
    u: float
    beams: int
    rms_m: float

    def to_dict(self) -> dict[str, Any]:
        return {"spot_scale": self.scale, "spot_scale_u": self.u, "beams": self.beams, "rms_m": self.rms_m}


def limb_echo(
    x0: FloatArray, t_ca: FloatArray, radius: FloatArray, spot_sigma: FloatArray, extent_sigmas: float = math.inf
) -> tuple[FloatArray, FloatArray]:
    """Energy-weighted echo range of beams passing ``x0`` (>= 0) from a sphere's centre at
    ``t_ca`` along the beam, spot standard deviation ``spot_sigma``, the spot's light cut to a disc
    of ``extent_sigmas`` sigmas (``inf``: the endless Gaussian); and the covered share (of the
    light within the disc). See the module notes."""
    x0, t_ca, r, sig = (np.asarray(v, dtype=np.float64)[:, None, None] for v in (x0, t_ca, radius, spot_sigma))
    if math.isinf(extent_sigmas) and extent_sigmas > 0:
        yk, wy = _GH_X, _GH_W
        lo_k, hi_k, norm = np.full(yk.size, -np.inf), np.full(yk.size, np.inf), np.ones(yk.size)
    else:
        # the disc: the along-limb coordinate from the disc's lateral marginal (nodes in its
        # probability, lrms.cylinder.footprint's table), the radial one given it a Gaussian cut to
        # the disc's chord |xi| <= sqrt(R^2 - y^2)
        yk, wy = disc_marginal_ppf(_GL_U, extent_sigmas), _GL_G
        hi_k = np.sqrt(np.maximum(extent_sigmas**2 - yk * yk, 0.0))
        lo_k, norm = -hi_k, np.maximum(2.0 * ndtr(hi_k) - 1.0, 1e-300)
    y = sig * yk[None, :, None]
    ry = np.sqrt(np.maximum(r * r - y * y, 0.0))
    a = np.maximum((-ry - x0) / sig, lo_k[None, :, None])
    b = np.minimum((ry - x0) / sig, hi_k[None, :, None])
    p_lo, p_hi = ndtr(a), ndtr(b)
    c = np.maximum(p_hi - p_lo, 0.0)  # (N, J, 1): the covered share of the chord's light
    p = np.clip(p_lo + np.maximum(c, 1e-12) * _GL_U[None, None, :], 1e-15, 1.0 - 1e-15)
    x = x0 + sig * ndtri(p)
    depth = np.sqrt(np.maximum(r * r - x * x - y * y, 0.0))
    t = t_ca - depth
    cos = np.maximum(depth / r, 1e-3)
    cw = wy[None, :, None] * c / norm[None, :, None]
    e = (cw * _GL_G[None, None, :]) * cos / np.square(np.maximum(t, 1e-3))
    rng = np.sum(e * t, axis=(1, 2)) / np.maximum(np.sum(e, axis=(1, 2)), 1e-300)
    share = np.sum(cw[:, :, 0], axis=1)
    return np.asarray(rng, dtype=np.float64), np.asarray(share, dtype=np.float64)


def limb_beams(
    origins: FloatArray,
    dirs: FloatArray,
    ranges: FloatArray,
    centre: FloatArray,
    radius: float,
    nominal_sigma: tuple[float, float],
    reach: float = 4.0,
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """Beams whose thin ray passes within ``reach`` nominal spot sigmas of the sphere's limb and
    whose geometric range lies on the sphere's near side (within 60 mm of it): their indices,
    closest approach ``x0`` and ``t_ca``. ``nominal_sigma``: the spot sigma's ``(s0, sd)``."""
    w = centre[None, :] - origins
    t_ca = np.einsum("ij,ij->i", w, dirs)
    x0 = np.linalg.norm(w - t_ca[:, None] * dirs, axis=1)
    sig = nominal_sigma[0] + nominal_sigma[1] * np.maximum(t_ca, 0.0)
    on = (
        (t_ca > radius)
        & (np.abs(x0 - radius) <= reach * sig)
        & (ranges >= t_ca - radius - 0.06)
        & (ranges <= t_ca + 0.06)
    )
    idx = np.flatnonzero(on)
    return idx, x0[idx], t_ca[idx]


def estimate_spot_scale(
    origins: FloatArray,
    dirs: FloatArray,
    ranges: FloatArray,
    spheres: list[tuple[FloatArray, float]],
    exit_diameter_m: float,
    divergence_rad: float,
    profile_sigma: float,
    sigma_l: float,
    extent: float = math.inf,
) -> SpotScale | None:
    """The spot scale from every beam (world ``origins``, unit ``dirs``, geometric ``ranges``) near
    the limbs of ``spheres`` (``(centre, calibrated radius)``), the nominal spot ``exit_diameter_m``
    + ``divergence_rad`` x range with ``profile_sigma`` and its light cut to ``extent`` nominal spot
    radii (:class:`lrms.cylinder.BeamOptics`; ``inf``: the endless Gaussian)."""
    nominal = (profile_sigma * exit_diameter_m, profile_sigma * divergence_rad)
    parts: list[tuple[FloatArray, ...]] = []
    for centre, radius in spheres:
        i, x0, t_ca = limb_beams(origins, dirs, ranges, np.asarray(centre, dtype=np.float64), radius, nominal)
        parts.append((x0, t_ca, np.full(i.size, radius), ranges[i]))
    if not parts:
        return None
    x0, t_ca, rad, rng = (np.concatenate(z) for z in zip(*parts, strict=True))
    return fit_spot_scale(x0, t_ca, rad, rng, sigma_l, nominal, extent_sigmas=extent / (2.0 * profile_sigma))


def fit_spot_scale(
    x0: FloatArray,
    t_ca: FloatArray,
    radius: FloatArray,
    ranges: FloatArray,
    sigma_l: float,
    nominal_sigma: tuple[float, float],
    outlier_sigma: float = 5.0,
    extent_sigmas: float = math.inf,
) -> SpotScale | None:
    """Fit the spot scale to limb beams (see the module notes), the spot's light cut to a disc of
    ``extent_sigmas`` sigmas (:func:`limb_echo`); ``None`` with too few beams."""
    ext = extent_sigmas
    keep = np.ones(x0.size, dtype=bool)
    best = 1.0
    for _ in range(2):
        if int(keep.sum()) < MIN_LIMB_BEAMS:
            return None
        xs, ts, rs, ls = x0[keep], t_ca[keep], radius[keep], ranges[keep]
        base = nominal_sigma[0] + nominal_sigma[1] * ts

        def ssr(s: float, xs: FloatArray = xs, ts: FloatArray = ts, rs: FloatArray = rs, ls: FloatArray = ls,
                base: FloatArray = base) -> float:  # fmt: skip
            return float(np.sum(np.square(ls - limb_echo(xs, ts, rs, s * base, ext)[0])))

        grid = np.geomspace(*SCALE_BOUNDS, 25)
        costs = [ssr(float(g)) for g in grid]
        k = int(np.argmin(costs))
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
        best = float(optimize.minimize_scalar(ssr, bounds=(lo, hi), method="bounded", options={"xatol": 1e-5}).x)
        res = ranges - limb_echo(x0, t_ca, radius, best * (nominal_sigma[0] + nominal_sigma[1] * t_ca), ext)[0]
        keep = np.abs(res) <= outlier_sigma * sigma_l
    if int(keep.sum()) < MIN_LIMB_BEAMS:  # the last cut left too few for the final u
        return None
    xs, ts, rs, ls = x0[keep], t_ca[keep], radius[keep], ranges[keep]
    base = nominal_sigma[0] + nominal_sigma[1] * ts
    h = 1e-3 * best
    up, dn = limb_echo(xs, ts, rs, (best + h) * base, ext)[0], limb_echo(xs, ts, rs, (best - h) * base, ext)[0]
    jac = (up - dn) / (2 * h)
    res = ls - limb_echo(xs, ts, rs, best * base, ext)[0]
    n = res.size
    s0sq = float(np.sum(np.square(res / sigma_l))) / max(n - 1, 1)
    info = float(np.sum(np.square(jac / sigma_l)))
    if info <= 0:
        return None
    u = float(np.sqrt(max(1.0, s0sq) / info + (MODEL_U * best) ** 2))
    return SpotScale(best, u, n, float(np.sqrt(np.mean(res**2))))
