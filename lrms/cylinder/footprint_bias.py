"""Second-order (Box 1971) bias correction of the footprint fit's solution.

The footprint fit (:mod:`lrms.cylinder.footprint`) is a nonlinear least-squares fit whose radius is
weakly determined (on seed 003's part at 2.5 m only the limb beams' ranges and the front's
curvature carry it), and its cost is skewed in the radius: steep toward small radii (the outer
detected beams fall off the model's silhouette), shallow toward large ones. A maximum-likelihood
estimate on such a cost is biased by the noise itself, to order ``sigma^2``:

``b = E[theta_hat] - theta = -1/2 A^-1 sum_i J_i tr(H_i C)``

(Box 1971) for whitened residuals ``r_i(theta)`` with Jacobian ``J`` (rows ``J_i``), Hessians
``H_i``, ``A = J^T J`` and ``C`` the parameters' covariance. As for the thin beam
(:func:`lrms.cylinder.bias.second_order_bias`), ``tr(H_i C)`` is taken as
``2 (E[r_i(theta + delta)] - r_i(theta))`` for ``delta ~ N(0, C)`` by the 3-point Gauss-Hermite
rule along each principal axis of ``C`` (nodes ``0``, ``+-sqrt(3 lambda_k) v_k``): the residuals
of a beam at the silhouette are not smooth enough for a local Hessian, and the rule needs
``2 p + 1`` evaluations of the residuals only. ``C`` is the fit's Gauss-Newton covariance
``(J^T J)^-1 max(1, chi2/dof)``: the sampling covariance the bias formula asks for, not the
profile-widened one the fit reports (that widening is for the interval, not the estimate).

The correction's own standard uncertainty: the formula is the leading term of a series whose
next terms are not evaluated, and the noise model behind ``C`` is itself an estimate; we take the
true bias as anywhere between none and twice the leading term (a rectangular distribution of
half-width ``|b|`` about ``b``: ``u = |b| / sqrt(3)``; ours, not Box's), carried as its own budget
row (``fit.extra["footprint_bias_u_m"]``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrms.errors import FitError

FloatArray = NDArray[np.float64]
#: Arrays taken as inputs (any float dtype).
AnyFloat = NDArray[np.floating[Any]]

#: Index of the radius in the footprint fit's parameter vector (``_Frame.unpack``).
RADIUS = 4


@dataclass(frozen=True)
class FootprintBias:
    """The second-order bias of a footprint fit's parameters and what it does to the diameter."""

    theta: FloatArray  # E[theta_hat] - theta, the fit's parameters (subtract to correct)
    diameter_m: float  # the diameter's bias (2 x the radius's): subtracted from the reported diameter
    u_m: float  # standard uncertainty of that correction (the budget row)


def second_order_bias(
    residuals: Callable[[FloatArray], FloatArray],
    theta: FloatArray,
    jac: AnyFloat,
    cov: AnyFloat,
) -> FloatArray:
    """Box's second-order bias ``-1/2 (J^T J)^-1 J^T t`` of the least-squares solution ``theta`` of
    the whitened ``residuals`` (a function of the parameters), ``t_i = tr(H_i C)`` by the 3-point
    Gauss-Hermite rule along the principal axes of ``cov`` (module notes); ``jac``: the residuals'
    Jacobian at ``theta``, rows as ``residuals``' output."""
    th = np.asarray(theta, dtype=np.float64)
    c = np.asarray(cov, dtype=np.float64)
    j = np.asarray(jac, dtype=np.float64)
    if c.shape != (th.size, th.size) or j.ndim != 2 or j.shape[1] != th.size:
        raise FitError(f"bias: covariance {c.shape} and Jacobian {j.shape} do not match {th.size} parameters")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(j))):
        raise FitError("bias: covariance and Jacobian must be finite")
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    steps = (np.sqrt(3.0 * np.maximum(lam, 0.0)) * vec).T  # rows: the Gauss-Hermite nodes' offsets
    centre = np.asarray(residuals(th), dtype=np.float64)
    if centre.shape != (j.shape[0],):
        raise FitError(f"bias: {centre.size} residuals for a Jacobian of {j.shape[0]} rows")
    second = np.zeros_like(centre)
    for step in steps:
        second += (residuals(th + step) + residuals(th - step) - 2.0 * centre) / 3.0
    return np.asarray(-0.5 * (np.linalg.pinv(j.T @ j) @ (j.T @ second)), dtype=np.float64)


def footprint_bias(
    residuals: Callable[[FloatArray], FloatArray],
    theta: FloatArray,
    jac: AnyFloat,
    cov: AnyFloat,
) -> FootprintBias:
    """:func:`second_order_bias` of a footprint fit (parameters as ``_Frame.unpack``, the radius
    at index 4), its diameter and the correction's standard uncertainty ``|b_d| / sqrt(3)``."""
    b = second_order_bias(residuals, theta, jac, cov)
    d = float(2.0 * b[RADIUS])
    if not np.isfinite(d):
        raise FitError("bias: the second-order bias is not finite")
    return FootprintBias(theta=b, diameter_m=d, u_m=abs(d) / np.sqrt(3.0))


#: The edge families whose solution is corrected (``footprint_fit``'s chosen family).
CORRECTED: tuple[str, ...] = ("weighted", "first")


def corrected(
    mode: str,
    theta: FloatArray,
    residuals: Callable[[FloatArray], FloatArray],
    jac: AnyFloat,
    cov: AnyFloat,
) -> tuple[FloatArray, dict[str, float]]:
    """The footprint fit's hook: ``theta`` less its :func:`footprint_bias` when ``mode`` is one of
    :data:`CORRECTED`, and the ``extra`` entries that record it: ``bias_correction_diameter_m``
    (subtracted from the diameter, as the thin beam's correction) and ``footprint_bias_u_m`` (its
    standard uncertainty, a budget row). Other families: ``theta`` as it is, no entries."""
    if mode not in CORRECTED:
        return np.asarray(theta, dtype=np.float64), {}
    b = footprint_bias(residuals, theta, jac, cov)
    return np.asarray(theta - b.theta, dtype=np.float64), {
        "bias_correction_diameter_m": b.diameter_m,
        "footprint_bias_u_m": b.u_m,
    }
