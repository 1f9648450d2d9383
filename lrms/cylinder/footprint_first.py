"""The first-hit echo of the footprint model (:mod:`lrms.cylinder.footprint`, ``mode="first"``):
the range at which the covered share of the spot, taken in range order, reaches the threshold, in
closed form (:func:`first_hit_range`) and solved by a safeguarded Newton iteration (:func:`_first_newton`,
started from the one-node model's root, :data:`_START_NODES`); the share ``F(T)`` and its slope
(:func:`_first_share`) and its partials in the beam geometry (:func:`_first_share_grad`, for the
first-hit Jacobian in :mod:`lrms.cylinder.footprint`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

FloatArray = NDArray[np.float64]


#: Gauss-Hermite nodes and weights of the standard normal (the first-hit model's spread along the axis).
_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(8)
_GH_W = _GH_W / np.sqrt(2.0 * np.pi)


def first_hit_range(
    x0: FloatArray,
    t_ca: FloatArray,
    cos_axis: FloatArray,
    radius: float,
    s0: float,
    sd: float,
    tau: float,
    c: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """The first-hit range of each beam in closed form: the range ``T`` at which the share of the
    spot whose sub-rays meet the cylinder at a range ``<= T`` reaches ``min(tau, 0.999 c)``.

    A sub-ray at lateral offset ``x`` from the axis (across the beam and the axis) meets the
    cylinder at ``t_ca - sqrt(r^2 - x^2) / p`` (``p = |u x w|``), so the sub-rays nearer than
    ``T`` are those with ``|x| <= x_T = sqrt(r^2 - (p (t_ca - T))^2)`` and their share is
    ``F0(T) = Phi((x_T - x0) / s) - Phi((-x_T - x0) / s)`` (``s`` the spot sigma at ``T``).
    Along the axis the range changes by ``s cos_axis / p`` per sigma of the spot: ``F0`` is
    averaged over that Gaussian by Gauss-Hermite nodes. ``F(T) = target`` is solved by a
    safeguarded Newton iteration. Returns ``T`` and ``dT / dF`` at ``T`` (capped at 1 m per unit
    share): where the threshold falls near the limb, ``F`` is flat and a small error of the share
    moves ``T`` by millimetres. (The sub-rays' tilt across the beam changes their path length
    by ``t tilt^2 / 2``, about 0.02 mm at one sigma: left out.) Newton starts from the root of
    the one-node model (:data:`_START_NODES`), never from a previous solution (a warm start moved
    2 beams of a test cloud to another root, 7-9 mm away). ``F`` is not monotone in ``T`` (the
    spot widens with ``T``): where it crosses the target twice, which crossing is found depends
    on the start (docs/cylinder.md, section 7, branch fhspeed: 1 solve in about a million).
    """
    return _first_newton(x0, t_ca, cos_axis, radius, s0, sd, np.minimum(tau, 0.999 * c), c)


def _first_newton(
    x0: FloatArray,
    t_ca: FloatArray,
    cos_axis: FloatArray,
    radius: float | FloatArray,
    s0: float,
    sd: float,
    target: FloatArray,
    c: FloatArray,
    nodes: tuple[FloatArray, FloatArray] | None = None,
    tol: float = 1e-11,
) -> tuple[FloatArray, FloatArray]:
    """:func:`first_hit_range` at the share ``target`` of each beam, ``radius`` a number or one per
    beam (the Jacobian's columns solved in one call: each beam's iteration is its own). ``nodes``:
    the quadrature along the axis (default the 8 Gauss-Hermite nodes, started from the root of the
    one-node model, :data:`_START_NODES`, solved to ``START_TOL``)."""
    _, depth, ys = _front_scales(t_ca, cos_axis, radius, s0, sd)
    lo = t_ca - depth - 6.0 * ys - 1e-9
    hi = t_ca + 6.0 * ys + 1e-9
    # start: the front's one-sided quantile, well inside the bracket; for the full quadrature, the
    # root of the one-node model (an eighth of the cost per step) found from there
    big_t = np.clip(t_ca - depth + 0.5 * (1.0 - np.minimum(target / np.maximum(c, 1e-12), 1.0)) * depth, lo, hi)
    if nodes is None and _START_NODES is not None:
        pre, _ = _first_newton(x0, t_ca, cos_axis, radius, s0, sd, target, c, _START_NODES, START_TOL)
        big_t = np.clip(pre, lo, hi)
    # safeguarded Newton on the beams not yet converged only (most take 3-5 steps, a few bisect)
    act = np.arange(big_t.size)
    per_beam = None if np.ndim(radius) == 0 else np.asarray(radius, dtype=np.float64)
    fp_last = np.zeros(big_t.size)  # dF/dT at each beam's last iterate (the slope, read there)
    for _ in range(60):
        if act.size == 0:
            break
        bt = big_t[act]
        rad = radius if per_beam is None else per_beam[act]
        f, fp = _first_share(bt, x0[act], t_ca[act], cos_axis[act], rad, s0, sd, nodes)
        fp_last[act] = fp
        f = f - target[act]
        la = np.where(f < 0, bt, lo[act])
        ha = np.where(f >= 0, bt, hi[act])
        lo[act], hi[act] = la, ha
        step = bt - f / np.maximum(fp, 1e-300)
        # a Newton step inside the bracket, or one within tol of the iterate (converged: from the
        # side of the root where the last iterate stays the bracket's end, the step rounds onto it,
        # and bisecting there cost about 30 more steps on a fifth of the beams)
        take = ((step > la) & (step < ha)) | (np.abs(step - bt) < tol)
        new = np.where(take, step, 0.5 * (la + ha))
        big_t[act] = new
        act = act[np.abs(new - bt) >= tol]
    if act.size:  # not converged in 60 steps: the slope at the final iterate
        rad = radius if per_beam is None else per_beam[act]
        fp_last[act] = _first_share(big_t[act], x0[act], t_ca[act], cos_axis[act], rad, s0, sd, nodes)[1]
    # the slope at the last iterate, within 1e-11 m of the root (not one more evaluation of F)
    return np.asarray(big_t, dtype=np.float64), np.asarray(1.0 / np.maximum(fp_last, 1.0), dtype=np.float64)


def _front_scales(
    t_ca: FloatArray, cos_axis: FloatArray, radius: float | FloatArray, s0: float, sd: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per beam: ``p = |u x w|``, the range extent ``radius / p`` of the part's front along the beam,
    and the range change ``ys`` per sigma of the spot along the axis (``s cos_axis / p``)."""
    p = np.sqrt(np.maximum(1.0 - cos_axis * cos_axis, 1e-12))
    depth = radius / p  # range extent of the part's front along the beam
    ys = (s0 + sd * np.maximum(t_ca, 0.0)) * np.abs(cos_axis) / p
    return p, np.asarray(depth, dtype=np.float64), ys


#: The Newton start of the first-hit range: the root of the one-node model (the spot's centre
#: along the axis), to START_TOL (m); None: the front's quantile alone (before this, median 6 steps
#: of the full quadrature per beam).
_START_NODES: tuple[FloatArray, FloatArray] | None = (np.zeros(1), np.ones(1))
START_TOL = 1e-7


def _first_share(
    big_t: FloatArray,
    x0: FloatArray,
    t_ca: FloatArray,
    cos_axis: FloatArray,
    radius: float | FloatArray,
    s0: float,
    sd: float,
    nodes: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """``F(T)`` of :func:`first_hit_range` (the share of the spot met at a range ``<= T``) and ``dF/dT``
    (the front's widening and the spot's growth with ``T`` on the part's near side; ``radius`` a
    number or one per beam; ``nodes``: the quadrature along the axis, default
    :data:`_GH_X` / :data:`_GH_W`)."""
    p, depth, ys = _front_scales(t_ca, cos_axis, radius, s0, sd)
    if np.ndim(radius):
        radius = np.asarray(radius, dtype=np.float64)[:, None]
    gx, gw = (_GH_X, _GH_W) if nodes is None else nodes
    eta = gx[None, :]
    h = gw[None, :]
    ax0 = np.abs(x0)[:, None]
    pp = p[:, None]
    tt = big_t[:, None] - eta * ys[:, None]
    dd = t_ca[:, None] - tt
    inside = (dd > 0) & (dd < depth[:, None])
    x2 = np.where(dd <= 0, radius * radius, np.maximum(radius * radius - np.square(pp * dd), 0.0))
    xt = np.sqrt(x2)
    sig = s0 + sd * np.maximum(np.minimum(tt, t_ca[:, None]), 0.0)
    zp, zm = (xt - ax0) / sig, (-xt - ax0) / sig
    f = np.sum(h * (ndtr(zp) - ndtr(zm)), axis=1)
    dxt = np.where(inside, np.square(pp) * dd / np.maximum(xt, 1e-9 * radius), 0.0)
    phi_p, phi_m = np.exp(-0.5 * zp * zp), np.exp(-0.5 * zm * zm)
    dens = (phi_p + phi_m) / (np.sqrt(2 * np.pi) * sig)
    # the spot widens with T on the part's near side (sig grows while the node's range is < t_ca)
    dsig = sd * ((tt < t_ca[:, None]) & (tt > 0.0))
    widen = -(phi_p * zp - phi_m * zm) / (np.sqrt(2 * np.pi) * sig) * dsig
    return np.asarray(f, dtype=np.float64), np.asarray(np.sum(h * (dens * dxt + widen), axis=1), dtype=np.float64)


def _first_share_grad(
    big_t: FloatArray,
    x0: FloatArray,
    t_ca: FloatArray,
    cos_axis: FloatArray,
    radius: float,
    s0: float,
    sd: float,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """``F(T)`` and ``dF/dT`` as :func:`_first_share`, and the partial derivatives of ``F`` at fixed
    ``T`` in the beam geometry: columns ``x0``, ``t_ca``, ``cos_axis``, ``radius`` (``(N, 4)``), in
    the same pass (no further ``ndtr``). The Jacobian's columns come from them by the chain rule
    (:func:`_first_jacobian`) instead of one evaluation of ``F`` per column."""
    cos_ = cos_axis[:, None]
    p = np.sqrt(np.maximum(1.0 - cos_ * cos_, 1e-12))
    spot = (s0 + sd * np.maximum(t_ca, 0.0))[:, None]
    q = np.abs(cos_) / p
    ys = spot * q
    dys_dt = sd * (t_ca > 0.0)[:, None] * q
    dys_dc = spot * np.sign(cos_) / (p * p * p)
    eta = _GH_X[None, :]
    h = _GH_W[None, :]
    ax0 = np.abs(x0)[:, None]
    tc = t_ca[:, None]
    tt = big_t[:, None] - eta * ys
    dd = tc - tt
    inside = (dd > 0) & (dd < radius / p)
    x2 = np.where(dd <= 0, radius * radius, np.maximum(radius * radius - np.square(p * dd), 0.0))
    xt = np.sqrt(x2)
    m = np.minimum(tt, tc)
    sig = s0 + sd * np.maximum(m, 0.0)
    zp, zm = (xt - ax0) / sig, (-xt - ax0) / sig
    f = np.sum(h * (ndtr(zp) - ndtr(zm)), axis=1)
    phi_p = np.exp(-0.5 * zp * zp) / np.sqrt(2 * np.pi)
    phi_m = np.exp(-0.5 * zm * zm) / np.sqrt(2 * np.pi)
    inv_xt = 1.0 / np.maximum(xt, 1e-9 * radius)
    # d xt: on the front (inside) xt = sqrt(r^2 - (p dd)^2); behind the axis (dd <= 0) xt = r
    dxt_ddd = np.where(inside, -p * p * dd * inv_xt, 0.0)
    dxt_dp = np.where(inside, -p * dd * dd * inv_xt, 0.0)
    dxt_dr = np.where(inside, radius * inv_xt, np.where(dd <= 0, 1.0, 0.0))
    # d sig: sd where the node's range (capped at t_ca) is positive
    live = sd * (m > 0.0)
    front = tt < tc
    a_x = (phi_p + phi_m) / sig  # weight of d xt
    a_a = -(phi_p - phi_m) / sig  # of d |x0|
    a_s = -(phi_p * zp - phi_m * zm) / sig  # of d sig
    # partials of the node's range tt and depth dd in t_ca and cos_axis (T fixed)
    dtt_dt, dtt_dc = -eta * dys_dt, -eta * dys_dc
    ddd_dt, ddd_dc = 1.0 - dtt_dt, -dtt_dc
    dsig_dt = live * np.where(front, dtt_dt, 1.0)
    dsig_dc = live * np.where(front, dtt_dc, 0.0)
    dp_dc = -cos_ / p
    d_x0 = np.sum(h * a_a, axis=1) * np.sign(x0)
    d_t = np.sum(h * (a_x * dxt_ddd * ddd_dt + a_s * dsig_dt), axis=1)
    d_c = np.sum(h * (a_x * (dxt_ddd * ddd_dc + dxt_dp * dp_dc) + a_s * dsig_dc), axis=1)
    d_r = np.sum(h * a_x * dxt_dr, axis=1)
    # dF/dT as _first_share has it: the front's widening and the spot's growth with T (the implicit
    # step's divisor; with the growth left out, rows were 3-7 % off, and 47x where F is nearly flat)
    fp = np.sum(h * (a_x * np.where(inside, p * p * dd * inv_xt, 0.0) + a_s * live * front), axis=1)
    grad = np.stack([d_x0, d_t, d_c, d_r], axis=1)
    # a node near the front's tip (xt -> 0, dxt / d dd -> infinity): F is far from linear there
    # over the Jacobian's steps, so such a beam's change is evaluated, not linearised
    near = np.any((dd > 0) & (np.abs(radius * radius - np.square(p * dd)) < np.square(_LINEAR_XT * radius)), axis=1)
    return (
        np.asarray(f, dtype=np.float64),
        np.asarray(fp, dtype=np.float64),
        np.asarray(grad, dtype=np.float64),
        np.asarray(near, dtype=np.bool_),
    )


#: Lateral half-width (share of the radius) of a node's front below which :func:`_first_jacobian`
#: evaluates the beam's change of ``F`` instead of linearising it (the square root's tip).
_LINEAR_XT = 0.1
