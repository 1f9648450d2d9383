"""Gauss-Helmert adjustment of the elbow model (seed 000, Eq. 10).

The linearized model is ``A d + B v + w = 0`` with one condition per point (the geometric form of
Eq. 8, see :mod:`lrms.elbow.model`). ``B`` is block diagonal: row ``i`` touches only point ``i``'s
three coordinates, so ``M = B Q B^T`` is diagonal (``M_i = B_i Q_i B_i^T``) and the normal
equations ``N = A^T M^-1 A`` are built with a few vectorized passes over the points.

Unknowns (internal): the centre ``c`` (3), a small rotation ``w`` (3) applied to the current
rotation as ``R <- exp(-[w]x) R`` (so no Euler-angle singularity can stall the adjustment; the
reported ``omega, psi, kappa`` and their standard deviations are derived afterwards), then the
dimensions: ``A`` and ``D`` (ratio free) or ``D`` alone with ``A = ratio D``, and ``Df`` for a
flanged joint.

Iteration: each step linearizes at the current parameters and at the adjusted observations
``l0 = l + v`` (the rigorous Gauss-Helmert iteration, misclosure ``w = f(x0, l0) + B (l - l0)``).
A step that raises the weighted sum of squared orthogonal distances is halved (up to 12 times);
then the next linearization restarts at ``l0 = l``. The first iterations are Huber-weighted
(a robust start: a flange point assigned to the bend by a start a few degrees off has a residual
of ``(Df - D)/2`` and would otherwise drag the solution into a wrong minimum); once those settle,
plain least-squares iterations follow, so the reported solution and statistics are those of the
Gauss-Helmert least-squares adjustment. Converged when the parameter update is below
``tol`` (relative to ``D`` for lengths, in rad for the rotation). The a posteriori variance factor
is ``s0^2 = v^T P v / (n - u)`` and the parameter covariance ``s0^2 N^-1``. When the
Gauss-Newton steps stall (no shortened step lowers the cost, or the iteration limit is reached)
the same weighted residuals are handed to :func:`scipy.optimize.least_squares` (trust region,
analytic Jacobian) to finish; the statistics are then computed as above and ``solver`` says so. Besides that absolute
test, the adjustment has converged when every update is below 1 % of the parameter's current
standard deviation (the cost of a sharp 0.5D elbow is not smooth where the horn torus pinches
to its axis, and the last digits can otherwise oscillate far below the precision).

Curvature correction (default on): the misclosures are the orthogonal distances minus their
expected value under the noise (:func:`curvature_offset`), which removes the second-order bias of
orthogonal-distance fitting on a curved surface (a tube fitted ``sigma^2/(2R)`` too fat, and the
bend radius and centre shifted); docs/elbow-accuracy.md has the derivation and the measurements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.special import i0e, i1e

from lrms.elbow.model import BEND, ElbowParams, Evaluation, as_points, euler_jacobian, evaluate_model
from lrms.errors import FitError

FloatArray = NDArray[np.float64]

#: A solution with A below this multiple of D is degenerate (a torus with A < D/2 cuts itself).
MIN_RATIO = 0.45
#: Fewest points accepted for a fit.
MIN_POINTS = 30
#: Huber threshold of the robust start, in robust standard deviations of the residuals.
HUBER_K = 2.0
#: Points nearer the torus axis than this many residual standard deviations (at most
#: AXIS_GATE_MAX tube radii) are not used; only sharp elbows have surface there.
AXIS_GATE = 3.0
AXIS_GATE_MAX = 0.5
#: A step the cost refuses even when shortened 4096-fold is taken as convergence when below this
#: fraction of each parameter's standard deviation: the cost is only piecewise smooth (portion
#: boundaries, the pinch of a sharp elbow's horn torus), so no descent along the Gauss-Newton
#: direction means a minimum along it, and a remaining step within the precision is no error.
STALL_FRACTION = 1.0
#: Converged once every parameter update is below this fraction of its standard deviation.
PRECISION_FRACTION = 0.01


def param_names(ratio: float | None, flange: bool) -> list[str]:
    """Names of the internal unknowns in order."""
    names = ["Xc", "Yc", "Zc", "wx", "wy", "wz"]
    names += ["D"] if ratio is not None else ["A", "D"]
    if flange:
        names.append("Df")
    return names


def design_matrices(
    points: ArrayLike, params: ElbowParams, ratio: float | None = None, flange: bool | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Condition values ``f`` (n,), design matrix ``A`` (n, u) and ``B`` rows (n, 3), analytic.

    ``A`` is taken with respect to the internal unknowns of :func:`param_names` at ``w = 0``.
    """
    pts = as_points(points)
    has_flange = params.Df is not None if flange is None else flange
    if has_flange and params.Df is None:
        raise FitError("a flanged fit needs an initial flange diameter Df")
    m = (pts - params.center) @ params.rot.T
    ev = evaluate_model(m, params.A, params.D, params.degree, params.Df if has_flange else None)
    return _design(ev, params, ratio, has_flange)


def _design(
    ev: Evaluation, params: ElbowParams, ratio: float | None, has_flange: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`design_matrices` from the model evaluated at the points (``ev``)."""
    m = ev.m
    n = m.shape[0]
    u = len(param_names(ratio, has_flange))
    x, y, z = m[:, 0], m[:, 1], m[:, 2]
    s = np.maximum(ev.s, 1e-12 * max(params.D, 1e-9))
    dz = (ev.zp - params.A) / s  # d s / d Zp
    # d f / d m, one contiguous row per component
    g = np.empty((3, n))
    np.multiply(dz, np.cos(ev.phi), out=g[0])
    np.divide(y, s, out=g[1])
    np.multiply(dz, np.sin(ev.phi), out=g[2])
    b = (params.rot.T @ g).T  # rows g_i^T R
    # the design matrix is filled column by column: (u, n) rows, handed out transposed
    at = np.empty((u, n))
    np.negative(b.T, out=at[:3])
    # g x m, written out (np.cross is slow on (n, 3) rows)
    at[3] = g[1] * z - g[2] * y
    at[4] = g[2] * x - g[0] * z
    at[5] = g[0] * y - g[1] * x
    if ratio is None:
        np.negative(dz, out=at[6])
        at[7] = -(1.0 - ev.q) / 2
        k = 8
    else:
        at[6] = -ratio * dz - (1.0 - ev.q) / 2
        k = 7
    if has_flange:
        at[k] = -ev.q / 2
    amat = at.T
    return ev.f, amat, b


def rice_excess(radius: FloatArray | float, sigma: FloatArray | float) -> FloatArray:
    """``E[sqrt((R + x)^2 + y^2)] - R`` for ``x, y ~ N(0, sigma^2)``: the mean excess distance from
    a circle's centre of a noisy point on it (the Rice distribution's mean minus ``R``).

    ``sigma sqrt(pi/2) L_1/2(-R^2 / (2 sigma^2)) - R``, with the Laguerre function written through
    the exponentially scaled Bessel functions; ``sigma^2/(2R) + sigma^4/(8R^3)`` where that is exact
    to round-off (``sigma < 1e-3 R``). Zero where ``sigma`` is zero.
    """
    r = np.asarray(radius, dtype=np.float64)
    sg = np.asarray(sigma, dtype=np.float64)
    r, sg = np.broadcast_arrays(r, sg)
    small = sg < 1e-3 * r
    out = np.asarray(sg**2 / (2 * r) + sg**4 / (8 * r**3), dtype=np.float64)
    big = ~small
    if np.any(big):
        rb, sb = r[big], sg[big]
        z = rb**2 / (4 * sb**2)
        out[big] = sb * math.sqrt(math.pi / 2) * ((1 + 2 * z) * i0e(z) + 2 * z * i1e(z)) - rb
    return out


def curvature_offset(
    points: ArrayLike, params: ElbowParams, var: FloatArray | float | None = None, cov: FloatArray | None = None
) -> FloatArray:
    """Expected orthogonal distance ``E[f]`` of a noisy observation of each point's foot point.

    A point on a curved surface observed with zero-mean noise lies on average outside a convex
    surface: ``E[f] = 1/2 tr(H Q)`` to second order, ``H`` the Hessian of the signed distance (the
    principal curvatures ``k1 = 1/Rq`` around the tube and ``k2 = cos(phi)/rho`` along the bend,
    ``rho`` the foot point's distance from the torus axis; ``k2 = 0`` on the legs) and ``Q`` the
    point's covariance. For isotropic noise (``var``: a variance per point or one for all) the term
    around the tube is the exact Rice mean (:func:`rice_excess`, exact on a cylinder for Gaussian
    noise of any size) and the term along the bend ``var k2 / 2``; for ``cov`` ``(n, 3, 3)`` both are
    second order. ``rho`` is kept >= 2 standard deviations (only sharp elbows come nearer the axis,
    and the axis gate leaves those points out of the fit).
    """
    pts = as_points(points)
    m = (pts - params.center) @ params.rot.T
    return _curvature_offset(evaluate_model(m, params.A, params.D, params.degree, params.Df), params, var, cov)


def _curvature_offset(
    ev: Evaluation, params: ElbowParams, var: FloatArray | float | None = None, cov: FloatArray | None = None
) -> FloatArray:
    """:func:`curvature_offset` from the model evaluated at the points (``ev``)."""
    m = ev.m
    s = np.maximum(ev.s, 1e-300)
    dz = (ev.zp - params.A) / s
    if cov is not None:
        t2 = np.stack([-np.sin(ev.phi), np.zeros_like(ev.phi), np.cos(ev.phi)], axis=1)
        g = np.stack([dz * np.cos(ev.phi), m[:, 1] / s, dz * np.sin(ev.phi)], axis=1)
        t1 = np.cross(g, t2)
        t1w, t2w = t1 @ params.rot, t2 @ params.rot
        v1 = np.einsum("ni,nij,nj->n", t1w, cov, t1w)
        v2 = np.einsum("ni,nij,nj->n", t2w, cov, t2w)
    else:
        v = np.broadcast_to(np.asarray(0.0 if var is None else var, dtype=np.float64), ev.f.shape)
        v1 = v2 = v
    sd = np.sqrt(np.maximum(v2, 0.0))
    rho = np.maximum(params.A + ev.radius * dz, 2.0 * sd)
    k2 = np.where(ev.portion == BEND, dz / np.maximum(rho, 1e-300), 0.0)
    if cov is not None:
        tube = v1 / (2 * ev.radius)
    elif var is None or np.ndim(var) == 0:
        # one variance for all points: the Rice mean of the (at most two) radii, not of every point
        sg = math.sqrt(max(float(0.0 if var is None else var), 0.0))
        radii = np.array([params.D / 2, (params.Df if params.Df is not None else params.D) / 2])
        ex = rice_excess(radii, sg)
        tube = np.where(ev.q > 0.5, ex[1], ex[0])  # q: 0 on the tube radius D/2, 1 on Df/2
    else:
        tube = rice_excess(ev.radius, np.sqrt(np.maximum(v1, 0.0)))
    return np.asarray(tube + 0.5 * k2 * v2)


def noise_from_residual_sd(sd: float, radius: float) -> float:
    """The coordinate noise ``sigma`` whose orthogonal distances to a tube of radius ``radius`` have
    standard deviation ``sd``.

    The distance of a noisy point from a cylinder's axis is Rice distributed; its variance is
    ``R^2 + 2 sigma^2 - E[s]^2`` (``sigma^2 - sigma^4/(4R^2)`` for small noise, down to
    ``(2 - pi/2) sigma^2`` for noise far above ``R``), which this inverts. ``sd`` itself when the
    relation cannot be inverted (``sd`` beyond what any noise gives).
    """
    if not (sd > 0 and math.isfinite(sd)) or radius <= 0:
        return max(sd, 0.0) if math.isfinite(sd) else 0.0

    def var_f(sg: float) -> float:
        es = radius + float(rice_excess(radius, sg))
        return radius**2 + 2 * sg**2 - es**2

    lo, hi = sd, 4.0 * sd
    if var_f(lo) > sd**2 or var_f(hi) < sd**2:
        return sd
    from scipy.optimize import brentq

    return float(brentq(lambda sg: var_f(sg) - sd**2, lo, hi, xtol=1e-6 * sd))


def apply_update(params: ElbowParams, delta: ArrayLike, ratio: float | None, flange: bool) -> ElbowParams:
    """Parameters after adding the internal update ``delta``."""
    d = np.asarray(delta, dtype=np.float64)
    rot = Rotation.from_rotvec(-d[3:6]).as_matrix() @ params.rot
    # re-orthonormalize against round-off accumulated over iterations
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt
    if ratio is None:
        a, dd = params.A + d[6], params.D + d[7]
        k = 8
    else:
        dd = params.D + d[6]
        a = ratio * dd
        k = 7
    df = params.Df + d[k] if flange and params.Df is not None else params.Df
    return replace(
        params, center=params.center + d[:3], rot=rot, A=float(a), D=float(dd), Df=None if df is None else float(df)
    )


@dataclass(frozen=True)
class ElbowFit:
    """Result of :func:`fit_elbow`."""

    params: ElbowParams
    cov: FloatArray  # covariance of the internal unknowns (param_names order)
    names: list[str]
    sigma0: float  # a posteriori standard deviation of unit weight
    iterations: int
    converged: bool
    n: int
    redundancy: int
    residuals: FloatArray  # signed orthogonal distance of each observed point to the fitted surface (m)
    # n: the points used (all but those within the axis gate of a sharp elbow)
    ratio: float | None
    sigmas: dict[str, float] = field(default_factory=dict)
    solver: str = "gauss-helmert"
    inliers: NDArray[np.bool_] | None = None  # set by trimmed fits (lrms.elbow.pipeline): rows of the input used

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (SI units, angles in degrees where named ``*_deg``)."""
        p = self.params
        om, ps, ka = p.angles
        out: dict[str, Any] = {
            "model": "elbow",
            "center_m": [float(x) for x in p.center],
            "axis": [float(x) for x in p.axis],
            "bend_radius_m": p.A,
            "diameter_m": p.D,
            "ratio": p.A / p.D,
            "ratio_fixed": self.ratio is not None,
            "degree": math.degrees(p.degree),
            "omega_deg": math.degrees(om),
            "psi_deg": math.degrees(ps),
            "kappa_deg": math.degrees(ka),
            "rotation_world_to_model": [[float(x) for x in row] for row in p.rot],
            "sigma": dict(self.sigmas),
            "sigma0_m": self.sigma0,
            "iterations": self.iterations,
            "converged": self.converged,
            "solver": self.solver,
            "n_points": self.n,
            "redundancy": self.redundancy,
            "rmse_m": self.rmse,
        }
        if p.Df is not None:
            out["flange_diameter_m"] = p.Df
        if self.inliers is not None:
            out["n_outliers"] = int(self.inliers.size - np.count_nonzero(self.inliers))
        return out


def _weights_denominator(b: FloatArray, cov: FloatArray | None) -> FloatArray:
    if cov is None:
        return np.asarray(np.einsum("ij,ij->i", b, b))
    if cov.ndim == 1:
        return np.asarray(cov * np.einsum("ij,ij->i", b, b))
    return np.asarray(np.einsum("ni,nij,nj->n", b, cov, b))


def _qbt(b: FloatArray, cov: FloatArray | None) -> FloatArray:
    if cov is None:
        return b
    if cov.ndim == 1:
        return np.asarray(cov[:, None] * b)
    return np.asarray(np.einsum("nij,nj->ni", cov, b))


def _check_cov(cov: ArrayLike | None, n: int) -> FloatArray | None:
    if cov is None:
        return None
    c = np.asarray(cov, dtype=np.float64)
    if c.shape not in ((n,), (n, 3, 3)):
        raise FitError(f"point covariance must have shape ({n},) or ({n}, 3, 3), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise FitError("point covariance contains non-finite values")
    if c.ndim == 1 and np.any(c <= 0):
        raise FitError("point variances must be positive")
    if c.ndim == 3 and np.any(np.linalg.eigvalsh(c)[:, 0] <= 0):
        raise FitError("point covariance matrices must be positive definite")
    return c


def fit_elbow(
    points: ArrayLike,
    init: ElbowParams,
    *,
    ratio: float | None = None,
    flange: bool | None = None,
    cov: ArrayLike | None = None,
    max_iter: int = 60,
    tol: float = 1e-9,
    robust_start: bool = True,
    robust_only: bool = False,
    fallback: bool = True,
    axis_gate: float = AXIS_GATE,
    curvature_correction: bool = True,
    gate_legs: bool = False,
) -> ElbowFit:
    """Adjust the elbow model to ``points`` (n, 3) from the initial values ``init``.

    ``ratio``: fix ``A = ratio * D`` (e.g. 0.5, 1, 1.5) or ``None`` to estimate ``A`` and ``D``.
    ``flange``: estimate a flange diameter ``Df`` for the legs (default: whether ``init.Df`` is set).
    ``cov``: per-point covariance, ``(n,)`` variances or ``(n, 3, 3)`` matrices (m^2); without it
    all points have unit cofactor and ``sigma0`` is the residual standard deviation in metres.
    ``robust_start``: begin with Huber-weighted iterations (points far from the current model, e.g.
    flange points handed to the bend by a slightly wrong start, count less) and finish with plain
    least squares; the result is the least-squares solution either way. ``robust_only`` stops
    after the Huber iterations (an M-estimate, for trimming outliers before the real fit; its
    statistics are computed as for least squares and are only indicative). ``fallback``: finish
    with the trust-region solver when the Gauss-Newton steps stall (else raise).
    ``axis_gate``: points closer to the torus axis than ``axis_gate`` robust residual standard
    deviations (but at most ``AXIS_GATE_MAX`` tube radii) are left out; 0 keeps all. Only sharp
    elbows (``A`` near ``D/2``) have surface there: the horn torus pinches to its axis, the
    surface's curvature radius along the bend is the distance ``rho`` from the axis, and the
    orthogonal distance of a noisy point is biased by about ``sigma^2 / (2 rho)``, all with one
    sign (measured on joint f of Table 1: a bend radius 1 mm short at 1 mm noise without the
    gate). The set of points used is fixed when the least-squares iterations start.
    ``curvature_correction``: subtract from each orthogonal distance its expected value under the
    noise (:func:`curvature_offset`: a noisy point on a curved surface lies on average outside a
    convex one, which inflates ``D`` by about ``sigma^2 / R`` and shifts ``A`` and the centre);
    the noise is ``cov`` when given, else the one that explains the current residual spread
    (:func:`noise_from_residual_sd`, re-estimated every iteration).
    ``gate_legs``: apply the axis gate to the legs' points too (their inner side reaches the torus
    axis where a sharp elbow's legs meet the bend); off by default: it removes joint c's remaining
    bias but raises joint f's error (docs/elbow-accuracy.md).
    Raises :class:`FitError` for too few points, singular normal equations, no convergence, or a
    degenerate solution (``A < 0.45 D``).
    """
    pts = as_points(points)
    n = pts.shape[0]
    if not np.all(np.isfinite(pts)):
        raise FitError("points contain NaN or infinite coordinates")
    has_flange = init.Df is not None if flange is None else bool(flange)
    if has_flange and init.Df is None:
        init = replace(init, Df=init.D)
    if not has_flange:
        init = replace(init, Df=None)
    if ratio is not None:
        init = replace(init, A=ratio * init.D)
    names = param_names(ratio, has_flange)
    u = len(names)
    if n < max(MIN_POINTS, 3 * u):
        raise FitError(f"too few points for an elbow fit: {n} (need at least {max(MIN_POINTS, 3 * u)})")
    q = _check_cov(cov, n)
    scale = max(init.D, 1e-6)

    params = init
    l0 = pts
    converged = False
    robust = robust_start
    it = 0
    vpv = 0.0
    use = np.ones(n, dtype=bool)
    hub_scale = math.inf
    stalled = False
    sig_r = 0.0
    # the model at the observations for the current parameters (shared by the misclosures, the
    # curvature correction and the axis gate; the accepted trial step's evaluation is reused)
    ev_obs = _eval_obs(pts, params)
    ev_trial = ev_obs
    corr: FloatArray | float = 0.0  # expected orthogonal distance of the noisy points (curvature_correction)
    var_hat: float | None = None
    for it in range(1, max_iter + 1):
        f_cache = ev_obs.f
        if l0 is pts:
            f0, amat, b = _design(ev_obs, params, ratio, has_flange)
        else:
            f0, amat, b = design_matrices(l0, params, ratio, has_flange)
        if curvature_correction:
            if q is None:
                if var_hat is None or robust:
                    sd_f = 1.4826 * float(np.median(np.abs(f_cache - corr)))
                else:
                    sd_f = math.sqrt(var_hat)
                var_hat = noise_from_residual_sd(sd_f, params.D / 2) ** 2
                corr = _curvature_offset(ev_obs, params, var_hat)
            else:
                corr = _curvature_offset(ev_obs, params, q if q.ndim == 1 else None, q if q.ndim == 3 else None)
        w = f0 + np.einsum("ij,ij->i", b, pts - l0) - corr
        mm = _weights_denominator(b, q)
        if np.any(mm <= 0) or not np.all(np.isfinite(mm)):
            raise FitError("degenerate linearization (zero gradient of the condition)")
        sqm = np.sqrt(mm)
        fo = f_cache - corr
        z = np.abs(fo) / sqm
        if robust or it == 1:  # the set of points used is frozen once the least-squares phase starts
            sig_r = 1.4826 * float(np.median(z))
            use = _usable(pts, params, sig_r * np.sqrt(np.median(mm)), axis_gate, gate_legs, ev_obs)
        if np.count_nonzero(use) < max(MIN_POINTS, 3 * u):
            raise FitError("too few points away from the torus axis for an elbow fit")
        hub = math.inf
        wt = np.where(use, 1.0 / mm, 0.0)
        if robust:
            # the scale may shrink but never grow: outliers must not inflate their own threshold
            hub_scale = min(hub_scale, HUBER_K * max(sig_r, 1e-12))
            hub = hub_scale
            wt = wt * np.minimum(1.0, hub / np.maximum(z, 1e-300))
        normal = amat.T @ (amat * wt[:, None])
        rhs = amat.T @ (wt * w)
        try:
            cond = np.linalg.cond(normal)
            if not np.isfinite(cond) or cond > 1e15:
                raise np.linalg.LinAlgError("ill-conditioned")
            delta = -np.linalg.solve(normal, rhs)
        except np.linalg.LinAlgError as exc:
            raise FitError(
                "singular normal equations: the points do not determine the elbow (too little coverage or not an elbow)"
            ) from exc
        cost0 = _cost((fo / sqm)[use], hub)
        floor = n * (1e-12 * scale) ** 2  # round-off level of the cost
        step = 1.0
        rigorous = not robust
        for _ in range(13):
            trial = apply_update(params, step * delta, ratio, has_flange)
            if _valid(trial):
                ev_trial = _eval_obs(pts, trial)
                if _cost(((ev_trial.f - corr) / sqm)[use], hub) <= cost0 * (1 + 1e-9) + floor:
                    break
            step *= 0.5
            rigorous = False
        else:
            n_use = int(np.count_nonzero(use))
            sd = np.sqrt(np.clip(np.diag(np.linalg.inv(normal)), 0.0, None) * cost0 / max(n_use - u, 1))
            if np.all(np.abs(delta) <= STALL_FRACTION * sd):
                # the cost is piecewise smooth (see STALL_FRACTION)
                vpv = float(np.sum((fo / sqm)[use] ** 2))
                if robust and not robust_only:
                    robust, l0 = False, pts
                    continue
                converged = True
                break
            if robust:  # the robust start is stuck: carry on with plain least squares
                robust, l0 = False, pts
                continue
            stalled = True
            break
        params = trial
        ev_obs = ev_trial
        kk = np.where(use, -(1.0 / mm) * (amat @ (step * delta) + w), 0.0)
        v = kk[:, None] * _qbt(b, q)
        vpv = float(np.sum(kk * kk * mm))
        if curvature_correction and q is None:
            var_hat = vpv / max(int(np.count_nonzero(use)) - u, 1)
        l0 = pts + v if rigorous else pts
        d = step * np.abs(delta)
        lin = np.concatenate([d[:3], d[6:]])
        done = bool(np.max(lin) < tol * scale and np.max(d[3:6]) < tol)
        # precision criterion: every update below 1 % of its standard deviation
        n_use = int(np.count_nonzero(use))
        sd = np.sqrt(np.clip(np.diag(np.linalg.inv(normal)), 0.0, None) * cost0 / max(n_use - u, 1))
        done = done or bool(it > 1 and np.all(d <= PRECISION_FRACTION * sd))
        if done and robust and robust_only:
            converged = True
            break
        if done and robust:
            robust, l0 = False, pts  # robust start finished: polish with plain least squares
        elif done:
            converged = True
            break
    solver = "gauss-helmert"
    if not converged and not robust_only and fallback:
        # the Gauss-Newton steps stall on the piecewise-smooth cost: finish with a trust-region
        # least-squares solver on the same residuals (orthogonal distances over sqrt(M))
        params, vpv = _trust_region_polish(pts, params, ratio, has_flange, q, use, max_iter, corr)
        converged = True
        solver = "gauss-helmert+trf"
        it += 1
    if not converged:
        what = "stalled (no step reduces the residuals)" if stalled else f"did not converge in {max_iter} iterations"
        raise FitError(f"the elbow adjustment {what}")
    if params.A < MIN_RATIO * params.D:
        raise FitError(
            f"degenerate solution: bend radius A = {params.A * 1e3:.1f} mm is below half the diameter "
            f"D = {params.D * 1e3:.1f} mm (the torus would cut itself); the points do not determine an elbow"
        )
    # final residuals and statistics at the solution (points used in the last iteration)
    f_fin, amat, b = _design(ev_obs if solver == "gauss-helmert" else _eval_obs(pts, params), params, ratio, has_flange)
    mm = _weights_denominator(b, q)
    normal = amat[use].T @ (amat[use] / mm[use, None])
    n_use = int(np.count_nonzero(use))
    redundancy = n_use - u
    s0sq = vpv / redundancy
    try:
        qxx = np.linalg.inv(normal)
    except np.linalg.LinAlgError as exc:
        raise FitError("singular normal matrix at the solution") from exc
    covx = np.asarray(s0sq * qxx, dtype=np.float64)
    fit = ElbowFit(
        params=params,
        cov=covx,
        names=names,
        sigma0=math.sqrt(s0sq),
        iterations=it,
        converged=True,
        n=n_use,
        redundancy=redundancy,
        residuals=np.asarray(f_fin),
        ratio=ratio,
        solver=solver,
    )
    return replace(fit, sigmas=derived_sigmas(fit))


def _usable(
    pts: FloatArray, p: ElbowParams, sigma: float, gate: float, legs: bool = False, ev: Evaluation | None = None
) -> NDArray[np.bool_]:
    """Points used: all but bend points (``legs``: all points) whose foot point lies within the axis gate.

    The gate radius is ``min(gate sigma, AXIS_GATE_MAX D/2)``; the foot point's distance from the
    torus axis is ``A + (D/2) cos(phi)`` (``phi`` around the tube), which noise along the surface
    normal does not change, so the selection does not favour one sign of the noise. All points
    when ``gate`` is 0. ``ev``: the model already evaluated at ``pts`` for ``p``.
    """
    if gate <= 0:
        return np.ones(pts.shape[0], dtype=bool)
    if ev is None:
        ev = evaluate_model((pts - p.center) @ p.rot.T, p.A, p.D, p.degree, p.Df)
    m = ev.m
    radius = min(gate * sigma, AXIS_GATE_MAX * p.D / 2)
    foot = p.A + (p.D / 2) * (ev.zp - p.A) / np.maximum(ev.s, 1e-300)
    if legs:
        # the foot point's distance from the axis: radial part and the part along the leg
        along = -m[:, 0] * np.sin(ev.phi) + m[:, 2] * np.cos(ev.phi)
        return np.asarray(np.hypot(foot, along) > radius)
    return np.asarray((ev.portion != BEND) | (foot > radius))


def _trust_region_polish(
    pts: FloatArray,
    params: ElbowParams,
    ratio: float | None,
    flange: bool,
    q: FloatArray | None,
    use: NDArray[np.bool_],
    max_iter: int,
    offset: FloatArray | float = 0.0,
) -> tuple[ElbowParams, float]:
    """Minimize the same weighted orthogonal distances with :func:`scipy.optimize.least_squares`
    (trust region reflective, analytic Jacobian); returns the parameters and ``v^T P v``."""
    from scipy.optimize import least_squares

    sel = pts[use]
    qs = None if q is None else q[use]
    off = np.broadcast_to(np.asarray(offset, dtype=np.float64), (pts.shape[0],))[use]
    _, _, b0 = design_matrices(sel, params, ratio, flange)
    sqm = np.sqrt(_weights_denominator(b0, qs))
    scale = max(params.D, 1e-6)

    def fun(x: FloatArray) -> FloatArray:
        p = apply_update(params, x, ratio, flange)
        if not _valid(p):
            return np.full(sel.shape[0], 1e3 * scale)
        return np.asarray((_f_obs(sel, p) - off) / sqm)

    def jac(x: FloatArray) -> FloatArray:
        p = apply_update(params, x, ratio, flange)
        _, amat, _ = design_matrices(sel, p, ratio, flange)
        return np.asarray(amat / sqm[:, None])

    u = len(param_names(ratio, flange))
    res = least_squares(fun, np.zeros(u), jac=jac, method="trf", x_scale="jac", max_nfev=10 * max_iter)
    if not res.success or not np.all(np.isfinite(res.x)):
        raise FitError(f"the elbow adjustment did not converge ({res.message})")
    p = apply_update(params, res.x, ratio, flange)
    if not _valid(p):
        raise FitError("the elbow adjustment diverged (non-positive dimensions)")
    r = fun(res.x)
    return p, float(r @ r)


def _f_obs(pts: FloatArray, p: ElbowParams) -> FloatArray:
    return _eval_obs(pts, p).f


def _eval_obs(pts: FloatArray, p: ElbowParams) -> Evaluation:
    return evaluate_model((pts - p.center) @ p.rot.T, p.A, p.D, p.degree, p.Df)


def _cost(z: FloatArray, hub: float) -> float:
    """Sum of squares, or Huber's cost (times 2) with threshold ``hub``."""
    if not math.isfinite(hub):
        return float(np.sum(z * z))
    a = np.abs(z)
    return float(np.sum(np.where(a <= hub, a * a, 2 * hub * a - hub * hub)))


def _valid(p: ElbowParams) -> bool:
    vals = [*p.center, p.A, p.D] + ([p.Df] if p.Df is not None else [])
    if not all(math.isfinite(x) for x in vals):
        return False
    return p.D > 0 and p.A > 0 and (p.Df is None or p.Df > 0)


def derived_sigmas(fit: ElbowFit) -> dict[str, float]:
    """Standard deviations of the reported parameters (m, and deg for the angles)."""
    cov = fit.cov
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {"Xc_m": float(sd[0]), "Yc_m": float(sd[1]), "Zc_m": float(sd[2])}
    om, ps, ka = fit.params.angles
    jac = euler_jacobian(om, ps, ka)
    ce = jac @ cov[3:6, 3:6] @ jac.T
    se = np.degrees(np.sqrt(np.clip(np.diag(ce), 0.0, None)))
    out.update({"omega_deg": float(se[0]), "psi_deg": float(se[1]), "kappa_deg": float(se[2])})
    # axis direction uncertainty: the model Y axis turns by the w components about model X and Z
    out["axis_deg"] = float(np.degrees(math.sqrt(max(cov[3, 3] + cov[5, 5], 0.0))))
    if fit.ratio is None:
        out["A_m"], out["D_m"] = float(sd[6]), float(sd[7])
        k = 8
    else:
        out["D_m"] = float(sd[6])
        out["A_m"] = float(fit.ratio * sd[6])
        k = 7
    if fit.params.Df is not None:
        out["Df_m"] = float(sd[k])
    return out
