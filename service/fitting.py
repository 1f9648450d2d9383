"""Fits after a sweep: the mapped cloud, a region of interest, and the model the request names.

The cylinder is fitted in the rig frame with every point's own beam (origin and direction from
its alpha and beta, not re-derived from the point), so the line-of-sight fit of
:func:`lrms.cylinder.fit_cylinder` sees exactly what the rig measured. The uncertainty is reported
three ways (:mod:`lrms.uncertainty`): the seed's critical-point interval at coverage factor ``k``,
the GUM standard uncertainty from the fit's covariance, and optionally a Monte Carlo interval.
Positions in the result are in the world frame (``world_from_rig`` of the calibration).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrms import kinematics
from lrms.covariance import NoiseModel
from lrms.errors import FitError
from service.config import RigConfig
from service.models import MeasurementRequest
from service.sweep import MappedSweep, roi_mask

FloatArray = NDArray[np.float64]

#: Points farther than this many robust standard deviations from the fitted elbow are trimmed.
ELBOW_TRIM = 4.0


def noise_model(config: RigConfig) -> NoiseModel:
    n = config.noise
    return NoiseModel(
        sigma_l=n.sigma_l_m,
        sigma_alpha=float(np.deg2rad(n.sigma_alpha_deg)),
        sigma_beta=float(np.deg2rad(n.sigma_beta_deg)),
    )


def _roi(request: MeasurementRequest, config: RigConfig) -> tuple[Any, Any]:
    if request.roi is not None:
        return request.roi.min_m, request.roi.max_m
    return config.fit.roi_min_m, config.fit.roi_max_m


def select(mapped: MappedSweep, request: MeasurementRequest, config: RigConfig) -> NDArray[np.bool_]:
    lo, hi = _roi(request, config)
    return roi_mask(mapped.points, lo, hi)


def fit(mapped: MappedSweep, request: MeasurementRequest, config: RigConfig) -> dict[str, Any]:
    """The fit result as JSON-ready data (raises :class:`FitError` if the model is not found)."""
    keep = select(mapped, request, config)
    n_roi = int(np.count_nonzero(keep))
    if n_roi == 0:
        raise FitError("no points inside the region of interest")
    if request.target == "cylinder":
        out = fit_cylinder_result(mapped, keep, request, config)
    else:
        out = fit_elbow_result(mapped, keep, request, config)
    out["points_in_roi"] = n_roi
    return out


def _vec(v: Any) -> list[float]:
    return [float(x) for x in np.asarray(v, dtype=np.float64).reshape(-1)]


def fit_cylinder_result(
    mapped: MappedSweep, keep: NDArray[np.bool_], request: MeasurementRequest, config: RigConfig
) -> dict[str, Any]:
    from lrms.cylinder import Rays, fit_cylinder
    from lrms.uncertainty import critical_point_interval, gum_interval, monte_carlo_interval

    cal = config.calibration
    nm = noise_model(config)
    l = mapped.ranges[keep]
    alpha = mapped.alpha[keep]
    beta = mapped.beta[keep]
    origins, dirs = kinematics.beam_rays(alpha, beta, cal.p)
    lateral = np.hypot(l * nm.sigma_alpha, (l * np.sin(alpha) + cal.p) * nm.sigma_beta)
    rays = Rays(
        origins=origins,
        dirs=dirs,
        ranges=l,
        sigma_l=np.full(l.shape, nm.sigma_l),
        sigma_perp=np.maximum(lateral, 1e-7),
    )
    seed = request.options.seed if request.options.seed is not None else 0
    rng = np.random.default_rng(seed)
    result = fit_cylinder(rays.points(), line_of_sight=True, p=cal.p, noise=nm, rays=rays, rng=rng)
    k = request.options.k if request.options.k is not None else config.fit.k
    inlier_rays = rays.subset(result.inliers)
    cpi = critical_point_interval(result.cylinder, rays=inlier_rays, noise=nm, k=k, p=cal.p)
    gum = gum_interval(result, coverage_factor=2.0)
    mc: dict[str, Any] | None = None
    if request.options.monte_carlo > 0:
        m = monte_carlo_interval(
            result, inlier_rays, noise=nm, n=max(10, request.options.monte_carlo), p=cal.p, rng=rng
        )
        mc = {"low_m": m.low, "high_m": m.high, "std_m": m.std, "coverage": m.coverage, "n_failed": m.n_failed}
    cyl = result.cylinder
    rot = cal.world_from_rig[:3, :3]
    direction = rot @ cyl.direction
    if direction[int(np.argmax(np.abs(direction)))] < 0:  # an axis has no sign: report it canonically
        direction = -direction
    return {
        "target": "cylinder",
        "diameter_m": float(result.diameter),
        "axis_point_m": _vec(cal.to_world(cyl.point)),
        "axis_direction": _vec(direction),
        "rmse_m": float(result.rmse),
        "n_inliers": int(result.n_inliers),
        "chi2_dof": float(result.chi2_dof),
        "uncertainty": {
            "k": float(k),
            "d_min_m": float(cpi.d_min),
            "d_max_m": float(cpi.d_max),
            "std_m": float(result.std_diameter),
            "critical_point": {"r_ce_m": float(cpi.r_ce), "percentile": float(cpi.percentile)},
            "gum": {"low_m": gum.low, "high_m": gum.high, "coverage": gum.coverage, "coverage_factor": 2.0},
            "monte_carlo": mc,
        },
        "fit_seed": seed,
    }


def fit_elbow_result(
    mapped: MappedSweep, keep: NDArray[np.bool_], request: MeasurementRequest, config: RigConfig
) -> dict[str, Any]:
    """The elbow (seed 000) fitted to the ROI's points (world frame) by :func:`lrms.elbow.fit_auto`.

    ``fit_auto`` finds the start values, trims points off the surface (``ELBOW_TRIM`` robust
    sigmas), labels the legs canonically and refuses a cloud that is not an elbow (too few points
    on the bend, or a residual spread out of proportion). Every point is weighted by its own
    variance: the mean of the diagonal of its Eq. 7 covariance (from its range and angles). The
    full 3 x 3 matrices are not passed: their range-to-lateral ratio (~100:1) leaves the
    adjustment unconverged on a one-sided sweep of the ``elbow`` scene (D 4.9 m after 300
    iterations, offline).
    """
    from lrms.covariance import point_covariances
    from lrms.elbow import fit_auto

    cal = config.calibration
    pts = mapped.points[keep]
    cov = point_covariances(mapped.ranges[keep], mapped.alpha[keep], mapped.beta[keep], noise_model(config), cal.p)
    variance = np.trace(cov, axis1=-2, axis2=-1) / 3.0  # invariant under the rotation to the world frame
    opts = request.options
    seed = opts.seed if opts.seed is not None else 0
    degree = None if opts.degree_deg is None else float(np.deg2rad(opts.degree_deg))
    fit = fit_auto(
        pts,
        degree=degree,
        ratio=opts.ratio,
        flange=opts.flange,
        cov=variance,
        trim=ELBOW_TRIM,
        rng=np.random.default_rng(seed),
    )
    out: dict[str, Any] = {"target": "elbow", **fit.to_dict(), "fit_seed": seed}
    if fit.inliers is not None:
        out["n_inliers"] = int(np.count_nonzero(fit.inliers))
    return out
