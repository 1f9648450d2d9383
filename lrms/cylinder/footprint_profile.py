"""The footprint fit's radius profile: the cost with the radius held and the other parameters
refitted (:func:`_held`), the energy-weighted family's variance from the profile's curvature
(:func:`_profile_variance`) and the first-hit family's profile-likelihood interval
(:func:`_profile_interval`), used by :func:`lrms.cylinder.footprint.footprint_fit`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrms.cylinder.footprint_echo import BeamOptics, FloatArray
from lrms.cylinder.footprint_solve import _FTOL, _box, _first_jacobian, _residuals, _Solved, _Warm
from lrms.cylinder.refine import _Frame

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
    lowest_cost: float = float("nan")  # the lowest cost met (the solution's when ``lowest`` is 0)
    lowest_theta: FloatArray | None = None  # all parameters there (None when ``lowest`` is 0)

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
    params: dict[float, FloatArray] = {0.0: best.theta}
    floor = best.cost
    for side in (-1.0, 1.0):
        p = start
        for h in PROFILE_SEARCH:
            cost, p = _held(best, frame, optics, side * h, p, 6 * start.size)
            pts[side * h] = cost
            params[side * h] = np.insert(p, 4, best.theta[4] + side * h)
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
    return _Profile(
        lo=min(ends[0], 0.0),
        hi=max(ends[1], 0.0),
        lowest=lowest,
        evaluations=len(pts) - 1,
        lowest_cost=pts[lowest],
        lowest_theta=None if lowest == 0.0 else params[lowest],
    )
