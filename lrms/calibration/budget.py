"""A calibration's row in a fitted diameter's GUM budget (:class:`lrms.budget.CalibrationInput`).

A cloud mapped with the calibrated rig ``theta`` (the estimate) instead of the true one moves the
fitted diameter by ``c . (theta - theta_true)`` to first order, with ``c_j`` the diameter's
response to mapping with parameter ``j`` changed: every inlier beam's origin, direction and
geometric range move (:meth:`lrms.kinematics.RigModel.rays`, ``geometric_range``), which changes
the fit's whitened residuals at its solution by ``dr_j`` (range rows ``(L - t) / s``, miss rows
``gap / sigma_perp``), and the solution by the fit's normal equations' response to that (the
gains of :mod:`lrms.budget`): ``c_j = g . dr_j`` (central differences of the rig model). The row
is ``u = sqrt(c^T V c)`` over the estimated parameters with the calibration's covariance ``V``,
correlations kept. It replaces the uncalibrated rows of the parameters it estimates: ``k0`` the
range offset, ``k1`` the range scale, ``alpha_zero`` the alpha zero.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.budget import CalibrationInput, _gain_rows
from lrms.calibration.result import CalibrationResult
from lrms.cylinder import CylinderFit, Rays
from lrms.kinematics import RigModel

FloatArray = NDArray[np.float64]

#: Budget rows of the uncalibrated rig that an estimated parameter supersedes.
REPLACES: dict[str, str] = {"k0": "range offset", "k1": "range scale", "alpha_zero": "alpha zero"}
#: SI unit of each parameter.
UNITS: dict[str, str] = {
    "k0": "m", "k1": "1", "p": "m", "q": "m", "tilt_x": "rad", "tilt_y": "rad", "alpha_zero": "rad",
    "beta_zero": "rad", "beta_scale": "1", "backlash": "rad", "time_offset": "s",
}  # fmt: skip
#: Central-difference step of each parameter (the model is smooth; these are far below its spread).
STEP: dict[str, float] = {
    "k0": 1e-5, "k1": 1e-6, "p": 1e-5, "q": 1e-5, "tilt_x": 1e-6, "tilt_y": 1e-6, "alpha_zero": 1e-6,
    "beta_zero": 1e-6, "beta_scale": 1e-6, "backlash": 1e-6, "time_offset": 1e-5,
}  # fmt: skip


def rig_sensitivities(
    fit: CylinderFit,
    rays: Rays,
    model: RigModel,
    names: tuple[str, ...],
    l: ArrayLike,
    alpha: ArrayLike,
    beta: ArrayLike,
    omega: ArrayLike | None = None,
) -> FloatArray:
    """``d(diameter) / d(parameter)`` (m per SI unit) for each of ``names``: the line-of-sight
    ``fit`` of the inlier beams ``rays`` (mapped with ``model``), whose readings are ``l``,
    ``alpha``, ``beta`` (and motor speed ``omega``), one per inlier."""
    g_range, g_miss, sig = _gain_rows(fit, rays)
    l_ = np.asarray(l, dtype=np.float64).reshape(-1)
    a_ = np.asarray(alpha, dtype=np.float64).reshape(-1)
    b_ = np.asarray(beta, dtype=np.float64).reshape(-1)
    w_ = None if omega is None else np.broadcast_to(np.asarray(omega, dtype=np.float64), l_.shape)
    if not (l_.shape == a_.shape == b_.shape == rays.ranges.shape):
        raise ValueError("one reading (l, alpha, beta) per inlier beam is needed")
    cyl = fit.cylinder

    def residuals(m: RigModel) -> tuple[FloatArray, FloatArray]:
        o, d = m.rays(a_, b_, w_)
        t, gap = cyl.ray_range(o, d)
        return (m.geometric_range(l_) - t) / sig, gap / rays.sigma_perp

    out = np.empty(len(names))
    for j, name in enumerate(names):
        h = STEP[name]
        v = getattr(model, name)
        rp, mp = residuals(replace(model, **{name: v + h}))
        rm, mm = residuals(replace(model, **{name: v - h}))
        out[j] = float(g_range @ ((rp - rm) / (2 * h)) + g_miss @ ((mp - mm) / (2 * h)))
    return out


def calibration_input(
    calibration: CalibrationResult,
    fit: CylinderFit,
    rays: Rays,
    l: ArrayLike,
    alpha: ArrayLike,
    beta: ArrayLike,
    omega: ArrayLike | None = None,
    label: str = "",
) -> CalibrationInput | None:
    """The calibration's budget row for ``fit`` (arguments as :func:`rig_sensitivities`; ``rays``
    mapped with ``calibration.model``); ``None`` when it estimated nothing."""
    names = tuple(calibration.estimated)
    if not names:
        return None
    idx = [RigModel.NAMES.index(n) for n in names]
    cov = calibration.covariance[np.ix_(idx, idx)]
    c = rig_sensitivities(fit, rays, calibration.model, names, l, alpha, beta, omega)
    what = f"calibration {label}: " if label else "calibration: "
    return CalibrationInput(
        names=names,
        covariance=0.5 * (cov + cov.T),
        sensitivity=c,
        units=tuple(UNITS[n] for n in names),
        replaces=tuple(REPLACES[n] for n in names if n in REPLACES),
        note=what + f"covariance of {', '.join(names)} through the diameter's response to each (sqrt(c^T V c), "
        "correlations kept)",
    )
