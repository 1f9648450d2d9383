"""The cylinder fits' own Levenberg-Marquardt: analytic normal equations on the 5 parameters.

Every iteration re-linearises in the local frame of the current cylinder (``theta = 0``: tilts
``t1, t2`` of the axis along ``e1, e2``, shifts ``s1, s2`` of the axis point, radius change), where
the Jacobians of :func:`lrms.cylinder.refine.los_jacobian` and
:func:`~lrms.cylinder.refine.orthogonal_jacobian` reduce to a few products with the beams'
coordinates: with ``v = X - a`` (``X`` the point, or where the beam meets the model), ``h = v.w``,
``q_k = v.e_k``, ``qu = q.u``, a hit beam's range moves by ``(h q1, h q2, q1, q2, r) / qu``.
The arrays are held by coordinate (``(3, N)``), so each evaluation is some forty passes over
``N`` contiguous numbers and one ``(5, N) x (N, 5)`` product; no per-call set-up as in
``scipy.optimize.least_squares``, whose MINPACK QR of the full ``2N x 5`` Jacobian dominated the
pipeline's time on small clouds. Results equal scipy's LM at its tolerances (tests).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from lrms.cylinder.model import Cylinder, Rays, perpendicular_frame
from lrms.errors import FitError

FloatArray = NDArray[np.float64]
#: What a cost-only :meth:`LosProblem.linearise` keeps: radius, the beams in the cylinder's frame,
#: their ranges to the model, which hit, the range and miss residuals.
_State = tuple[
    float, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray,
    NDArray[np.bool_], FloatArray, FloatArray,
]  # fmt: skip

#: Convergence (see :func:`levenberg_marquardt`): the Newton decrement over ``cost / dof``, or
#: ``STALL`` steps in a row that change the cost by less than ``FTOL`` relative (kinks of the cost).
DECREMENT_TOL = 1e-8
FTOL = 1e-7
STALL = 2
#: ... or when the damped step ``delta`` is below ``sqrt(STEP_TOL)`` of the parameters' standard
#: errors (``delta^T J^T J delta < STEP_TOL cost / dof``): at a kink of the cost the Newton step
#: does not shrink, the damping does, and the last thousandths of a standard error are not worth
#: the dozen creeping steps they took. (1e-4 saved another fifth of the evaluations but moved a
#: 567-point fit by 2.6 um against the replicas' batched solver, tests/core/test_uncertainty.py.)
STEP_TOL = 1e-6


@dataclass(frozen=True)
class Linearised:
    """Cost ``sum r^2``, normal matrix ``J^T J`` and gradient ``J^T r`` at a cylinder (its local
    frame ``e1, e2``); ``residuals`` the whitened residuals (range part, then miss part)."""

    cost: float
    normal: FloatArray
    gradient: FloatArray
    e1: FloatArray
    e2: FloatArray
    residuals: FloatArray
    #: what :meth:`LosProblem.complete` / :meth:`OrthogonalProblem.complete` need to add the
    #: normal matrix and gradient to a cost-only linearisation without evaluating again
    state: object = field(default=None, repr=False, compare=False)


class LosProblem:
    """Line-of-sight residuals ``(l - t) / sigma_l`` and miss distances ``gap / sigma_perp``."""

    def __init__(self, rays: Rays) -> None:
        self.o = np.ascontiguousarray(rays.origins.T)
        self.u = np.ascontiguousarray(rays.dirs.T)
        self.l = np.ascontiguousarray(rays.ranges)
        n = self.l.shape[0]
        self.isl = 1.0 / np.broadcast_to(np.asarray(rays.sigma_l, dtype=np.float64), (n,))
        self.isp = 1.0 / np.broadcast_to(np.asarray(rays.sigma_perp, dtype=np.float64), (n,))

    @classmethod
    def of_rows(cls, rays: Rays, rows: NDArray[np.intp]) -> LosProblem:
        """The problem of the beams ``rows`` of ``rays``, gathered straight into the by-coordinate
        layout (one copy of each array instead of :meth:`Rays.subset`'s and then this one's)."""
        new = cls.__new__(cls)
        new.o = rays.origins.T[:, rows]
        new.u = rays.dirs.T[:, rows]
        new.l = rays.ranges[rows]
        new.isl = 1.0 / np.broadcast_to(np.asarray(rays.sigma_l, dtype=np.float64), rays.ranges.shape)[rows]
        new.isp = 1.0 / np.broadcast_to(np.asarray(rays.sigma_perp, dtype=np.float64), rays.ranges.shape)[rows]
        return new

    @property
    def size(self) -> int:
        return int(self.l.shape[0])

    def reweighted(self, sigma_l: FloatArray) -> LosProblem:
        """The same beams with other range standard deviations (the beams' arrays shared)."""
        new = LosProblem.__new__(LosProblem)
        new.o, new.u, new.l, new.isp = self.o, self.u, self.l, self.isp
        new.isl = 1.0 / np.broadcast_to(np.asarray(sigma_l, dtype=np.float64), self.l.shape)
        return new

    def linearise(
        self, cyl: Cylinder, jacobian: bool = True, frame: tuple[FloatArray, FloatArray] | None = None
    ) -> Linearised:
        lin, _ = self._evaluate(cyl, jacobian, frame, dense=False)
        return lin

    def complete(self, lin: Linearised) -> Linearised:
        """A cost-only linearisation (``jacobian=False``) with its normal matrix and gradient,
        from the intermediates it kept (no second pass over the beams' geometry)."""
        if lin.state is None:
            return lin
        full, _ = self._jacobian_part(lin, *lin.state, dense=False)  # type: ignore[misc]
        return full

    def jacobian(self, cyl: Cylinder, frame: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
        """The whitened Jacobian ``(2N, 5)`` at ``theta = 0`` (range rows, then miss rows; the miss
        rows of beams that hit are zero), as :func:`lrms.cylinder.refine.los_jacobian`."""
        _, jac = self._evaluate(cyl, True, frame, dense=True)
        assert jac is not None
        return jac

    def linearise_dense(
        self, cyl: Cylinder, frame: tuple[FloatArray, FloatArray] | None = None
    ) -> tuple[Linearised, FloatArray]:
        """:meth:`linearise` and :meth:`jacobian` from one pass over the beams."""
        lin, jac = self._evaluate(cyl, True, frame, dense=True)
        assert jac is not None
        return lin, jac

    def range_rows(self, cyl: Cylinder, frame: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
        """The range rows ``(5, N)`` of the whitened Jacobian at ``cyl`` (a beam that misses: its
        closest approach's row, as in :meth:`jacobian`; no miss rows), without the normal matrix:
        what a sandwich covariance with per-beam weights needs
        (:func:`lrms.cylinder.bias.weighted_sandwich`)."""
        lin, _ = self._evaluate(cyl, False, frame, dense=False)
        state: _State = lin.state  # type: ignore[assignment]
        r, v1, v2, vw, ue1, ue2, uw, aa, t, hit, _, _ = state
        jr, jm, miss, _, _, _ = self._range_part(r, v1, v2, vw, ue1, ue2, uw, aa, t, hit)
        jr[:, miss] = jm
        return jr

    def _range_part(
        self,
        r: float,
        v1: FloatArray,
        v2: FloatArray,
        vw: FloatArray,
        ue1: FloatArray,
        ue2: FloatArray,
        uw: FloatArray,
        aa: FloatArray,
        t: FloatArray,
        hit: NDArray[np.bool_],
    ) -> tuple[FloatArray, FloatArray, NDArray[np.intp], FloatArray, FloatArray, FloatArray]:
        """The range rows ``(5, N)`` of the hits (0 on the misses), the misses' closest-approach rows
        ``(5, M)``, the misses' indices, and the beams' ``q1, q2, h``."""
        q1 = v1 + t * ue1
        q2 = v2 + t * ue2
        h = vw + t * uw
        qu = q1 * ue1 + q2 * ue2
        safe_qu = np.where(np.abs(qu) > 1e-300, qu, 1e-300)
        f = np.where(hit, -self.isl / safe_qu, 0.0)  # hit rows: J = -dt / sigma_l, dt = (h q1, h q2, q1, q2, r) / qu
        jr = np.empty((5, t.shape[0]))
        jr[2] = q1 * f
        jr[3] = q2 * f
        jr[0] = h * jr[2]
        jr[1] = h * jr[3]
        jr[4] = r * f
        miss = np.flatnonzero(~hit)
        # closest approach: dt = -dH / A, H = q.u; the miss distance by the envelope theorem
        hm, q1m, q2m, uwm = h[miss], q1[miss], q2[miss], uw[miss]
        g = self.isl[miss] / aa[miss]  # J = -dt / sigma_l = dH / (A sigma_l)
        jm = np.empty((5, miss.size))
        jm[0] = -(q1m * uwm + hm * ue1[miss]) * g
        jm[1] = -(q2m * uwm + hm * ue2[miss]) * g
        jm[2] = -ue1[miss] * g
        jm[3] = -ue2[miss] * g
        jm[4] = 0.0
        return jr, jm, miss, q1, q2, h

    def _evaluate(
        self, cyl: Cylinder, jacobian: bool, frame: tuple[FloatArray, FloatArray] | None, dense: bool
    ) -> tuple[Linearised, FloatArray | None]:
        a, w, r = cyl.point, cyl.direction, cyl.radius
        e1, e2 = perpendicular_frame(w) if frame is None else frame
        # the beams in the cylinder's frame (e1, e2, w) by two 3 x 3 products: v = o - a has
        # coordinates (v1, v2, vw), u has (u1, u2, uw); the component across the axis is (1, 2)
        rot = np.stack([e1, e2, w])
        ov = rot @ self.o
        uv = rot @ self.u
        ra = rot @ a
        v1, v2, vw = ov[0] - ra[0], ov[1] - ra[1], ov[2] - ra[2]
        ue1, ue2, uw = uv[0], uv[1], uv[2]
        aa = np.maximum(ue1 * ue1 + ue2 * ue2, 1e-300)
        bb = v1 * ue1 + v2 * ue2
        cc = v1 * v1 + v2 * v2
        t_ca = -bb / aa
        d2 = np.maximum(cc - bb * bb / aa, 0.0)
        disc = aa * (r * r - d2)
        hit = disc >= 0
        t = t_ca - np.sqrt(np.maximum(disc, 0.0)) / aa  # a miss: the closest approach t_ca
        gap = np.where(hit, 0.0, np.sqrt(d2) - r)
        res_r = (self.l - t) * self.isl
        res_g = gap * self.isp
        cost = float(res_r @ res_r + res_g @ res_g)
        residuals = np.concatenate([res_r, res_g])
        state = (r, v1, v2, vw, ue1, ue2, uw, aa, t, hit, res_r, res_g)
        if not jacobian:
            return Linearised(cost, np.zeros((5, 5)), np.zeros(5), e1, e2, residuals, state), None
        return self._jacobian_part(Linearised(cost, np.zeros((5, 5)), np.zeros(5), e1, e2, residuals), *state, dense)

    def _jacobian_part(
        self,
        lin: Linearised,
        r: float,
        v1: FloatArray,
        v2: FloatArray,
        vw: FloatArray,
        ue1: FloatArray,
        ue2: FloatArray,
        uw: FloatArray,
        aa: FloatArray,
        t: FloatArray,
        hit: NDArray[np.bool_],
        res_r: FloatArray,
        res_g: FloatArray,
        dense: bool,
    ) -> tuple[Linearised, FloatArray | None]:
        jr, jm, miss, q1, q2, h = self._range_part(r, v1, v2, vw, ue1, ue2, uw, aa, t, hit)
        normal = jr @ jr.T
        gradient = jr @ res_r
        full = np.zeros((t.shape[0] * 2, 5)) if dense else None
        if miss.size:
            hm, q1m, q2m = h[miss], q1[miss], q2[miss]
            qn = np.maximum(np.sqrt(q1m * q1m + q2m * q2m), 1e-300)
            s = -self.isp[miss] / qn
            jg = np.empty((5, miss.size))
            jg[2] = q1m * s
            jg[3] = q2m * s
            jg[0] = hm * jg[2]
            jg[1] = hm * jg[3]
            jg[4] = -self.isp[miss]
            normal = normal + jm @ jm.T + jg @ jg.T
            gradient = gradient + jm @ res_r[miss] + jg @ res_g[miss]
            if full is not None:
                jr[:, miss] = jm
                full[t.shape[0] + miss] = jg.T
        if full is not None:
            full[: t.shape[0]] = jr.T
        return Linearised(lin.cost, normal, gradient, lin.e1, lin.e2, lin.residuals), full


class OrthogonalProblem:
    """Orthogonal distances to the surface over an isotropic ``sigma``."""

    def __init__(self, points: FloatArray, sigma: float) -> None:
        self.p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
        self.isg = 1.0 / float(sigma)

    @property
    def size(self) -> int:
        return int(self.p.shape[1])

    def linearise(self, cyl: Cylinder, jacobian: bool = True) -> Linearised:
        a, w, r = cyl.point, cyl.direction, cyl.radius
        e1, e2 = perpendicular_frame(w)
        p = self.p
        v0, v1, v2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
        q1 = v0 * e1[0] + v1 * e1[1] + v2 * e1[2]
        q2 = v0 * e2[0] + v1 * e2[1] + v2 * e2[2]
        qn = np.sqrt(q1 * q1 + q2 * q2)
        res = (qn - r) * self.isg
        cost = float(res @ res)
        if not jacobian:
            return Linearised(cost, np.zeros((5, 5)), np.zeros(5), e1, e2, res, cyl)
        h = v0 * w[0] + v1 * w[1] + v2 * w[2]
        s = -self.isg / np.maximum(qn, 1e-300)
        jac = np.empty((5, res.shape[0]))
        jac[2] = q1 * s
        jac[3] = q2 * s
        jac[0] = h * jac[2]
        jac[1] = h * jac[3]
        jac[4] = -self.isg
        return Linearised(cost, jac @ jac.T, jac @ res, e1, e2, res)

    def complete(self, lin: Linearised) -> Linearised:
        """A cost-only linearisation with its normal matrix and gradient (evaluated again: the
        orthogonal distances are cheap)."""
        return lin if not isinstance(lin.state, Cylinder) else self.linearise(lin.state)


Problem = LosProblem | OrthogonalProblem


def step(cyl: Cylinder, e1: FloatArray, e2: FloatArray, delta: FloatArray) -> Cylinder:
    """The cylinder at ``theta = delta`` in the local frame ``(e1, e2)`` of ``cyl``."""
    w = cyl.direction + delta[0] * e1 + delta[1] * e2
    a = cyl.point + delta[2] * e1 + delta[3] * e2
    r = cyl.radius + float(delta[4])
    w = w / math.sqrt(float(w @ w))
    if not (r > 0 and math.isfinite(r) and math.isfinite(float(a.sum() + w.sum()))):
        return Cylinder(a, w, r)  # raises FitError
    return Cylinder.trusted(a, w, r)


def levenberg_marquardt(problem: Problem, start: Cylinder, max_iter: int = 100) -> tuple[Cylinder, Linearised]:
    """Minimise ``problem``'s cost from ``start``; returns the solution and its linearisation.

    Marquardt's damping ``lambda diag(J^T J)`` (scale-free), raised tenfold on a step that does not
    lower the cost and lowered threefold on one that does. Converged when the Newton decrement
    ``g^T (J^T J)^-1 g`` (the decrease a Gauss-Newton step would still bring) is below
    :data:`DECREMENT_TOL` times ``cost / dof``, i.e. the remaining step is below 1e-4 of the
    parameters' standard errors; or, where the cost has kinks (a limb beam turning from hit to
    miss: the gradient does not vanish at such a minimum), after :data:`STALL` steps in a row that
    change the cost by less than :data:`FTOL` relative, or when the damped step is below
    ``sqrt(STEP_TOL)`` standard errors (:data:`STEP_TOL`). At most
    ``max_iter`` steps (accepted or not); a step to a non-positive radius is rejected."""
    cyl = start
    cur = problem.linearise(cyl)
    if not np.isfinite(cur.cost):
        raise FitError("cylinder refinement diverged")
    dof = max(cur.residuals.shape[0] // (2 if isinstance(problem, LosProblem) else 1) - 5, 1)
    lam = 1e-3
    stall = 0
    pair = np.empty((2, 5, 5))
    for _ in range(max_iter):
        scale = max(cur.cost / dof, 1e-300)
        # the plain and the damped normal matrix inverted in one call (the per-call overhead of
        # two 5 x 5 solves was a tenth of a small cloud's fit)
        pair[0] = pair[1] = cur.normal
        pair[1].flat[::6] += lam * np.maximum(cur.normal.diagonal(), 1e-300)
        try:
            sol = np.linalg.inv(pair) @ cur.gradient
        except np.linalg.LinAlgError:
            lam *= 10.0
            if lam > 1e12:
                break
            continue
        newton = float(cur.gradient @ sol[0])
        delta = -sol[1]
        if not np.isfinite(delta).all():
            raise FitError("cylinder refinement diverged")
        if newton <= DECREMENT_TOL * scale:
            break
        if float(delta @ cur.normal @ delta) <= STEP_TOL * scale:
            break  # the (damped) step is below sqrt(STEP_TOL) standard errors in every direction
        new_r = cyl.radius + float(delta[4])
        trial_cost = np.inf
        if new_r > 0:
            new = step(cyl, cur.e1, cur.e2, delta)
            trial = problem.linearise(new, jacobian=False)  # the Jacobian only if the step is taken
            trial_cost = trial.cost
        stall = stall + 1 if abs(trial_cost - cur.cost) <= FTOL * cur.cost else 0
        if trial_cost < cur.cost:
            cyl, cur = new, problem.complete(trial)
            lam = max(lam * 0.3, 1e-12)
        else:
            lam *= 10.0
        if stall >= STALL or lam > 1e12:
            break
    return cyl, cur


def covariance(lin: Linearised) -> FloatArray:
    """``(J^T J)^-1`` of a linearisation; :class:`FitError` when singular."""
    try:
        return np.asarray(np.linalg.inv(lin.normal), dtype=np.float64)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - degenerate geometry
        raise FitError("cylinder fit is degenerate (singular normal matrix)") from exc
