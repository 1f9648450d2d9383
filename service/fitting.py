"""Fits after a sweep: the mapped cloud, a region of interest, and the model the request names.

The cylinder is fitted in the rig frame with every point's own beam (origin and direction from
its alpha, beta and motor speed by the rig model the cloud was mapped with, not re-derived from
the point), so the line-of-sight fit of
:func:`lrms.cylinder.fit_cylinder` sees exactly what the rig measured. The uncertainty is reported
three ways (:mod:`lrms.uncertainty`): the seed's critical-point interval at ellipsoid factor ``k``,
the GUM standard uncertainty from the fit's covariance, and optionally a Monte Carlo interval; and
the GUM budget of :mod:`lrms.budget` (one row per source, ``u_c``, ``U = k u_c``, k = 2), whose
systematic effects the Monte Carlo replicas draw too.
Positions in the result are in the world frame (``world_from_rig`` of the calibration).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms import kinematics
from lrms.budget import BeamGeometry, CalibrationInput, SensorErrors
from lrms.covariance import NoiseModel
from lrms.errors import FitError
from service.defaults import DEFAULT_K

if TYPE_CHECKING:
    # the rig's config, request and sweep types (pydantic, the MCAP log) are needed only by the
    # service's own fits: ``lrms fit FILE`` imports this module without them (docs/architecture.md)
    from service.calstore import StoredCalibration
    from service.config import RigConfig
    from service.models import MeasurementRequest
    from service.sweep import MappedSweep

FloatArray = NDArray[np.float64]
#: A calibration's budget row, built once the fit is known: ``(fit, inlier rays) -> row``.
CalibrationRow = Callable[[Any, Any], CalibrationInput | None]

#: Points farther than this many robust standard deviations from the fitted elbow are trimmed.
ELBOW_TRIM = 4.0
#: The GUM interval is the fit's standard uncertainty times this factor (about 95 %).
GUM_COVERAGE_FACTOR = 2.0
#: Motor speed assumed for the budget's timing row when none is given (the rig's default sweep).
DEFAULT_SWEEP_SPEED_DEG_S = 10.0


def noise_model(config: RigConfig) -> NoiseModel:
    return NoiseModel(**config.noise.si())


def _roi(request: MeasurementRequest, config: RigConfig) -> tuple[Any, Any]:
    if request.roi is not None:
        return request.roi.min_m, request.roi.max_m
    return config.fit.roi_min_m, config.fit.roi_max_m


def select(mapped: MappedSweep, request: MeasurementRequest, config: RigConfig) -> NDArray[np.bool_]:
    lo, hi = _roi(request, config)
    from service.sweep import roi_mask

    return roi_mask(mapped.points, lo, hi)


def fit(
    mapped: MappedSweep,
    request: MeasurementRequest,
    config: RigConfig,
    calibration: StoredCalibration | None = None,
) -> dict[str, Any]:
    """The fit result as JSON-ready data (raises :class:`FitError` if the model is not found).

    ``calibration``: the rig's active calibration (:mod:`service.calstore`); ``mapped`` was mapped
    with it (:func:`rig_kinematics`), the cylinder's beams are its rig model's,
    its covariance is a row of the budget, and ``result["calibration"]`` names it
    (``{"id", "name", "created"}``; ``None``: the rig's ``[kinematics]`` as configured).

    Target ``"calibration"``: the rig model adjusted to the whole sweep
    (:func:`service.calibrating.calibration_result`), no region of interest."""
    if getattr(request, "calibration", None) is not None:  # a JobRequest of a calibration sweep
        from service.calibrating import calibration_result

        out = calibration_result(mapped, request, config)  # type: ignore[arg-type]
        out["calibration"] = None if calibration is None else calibration.reference()
        return out
    keep = select(mapped, request, config)
    n_roi = int(np.count_nonzero(keep))
    if n_roi == 0:
        raise FitError("no points inside the region of interest")
    if request.target == "cylinder":
        out = fit_cylinder_result(mapped, keep, request, config, calibration)
    else:
        out = fit_elbow_result(mapped, keep, request, config, calibration)
    out["points_in_roi"] = n_roi
    out["calibration"] = None if calibration is None else calibration.reference()
    return out


def rig_kinematics(config: RigConfig, calibration: StoredCalibration | None) -> kinematics.RigCalibration:
    """The rig's ``[kinematics]`` with the active calibration's rig model in place of its own."""
    base = config.calibration
    return base if calibration is None else base.with_model(calibration.calibration.model)


def _vec(v: Any) -> list[float]:
    return [float(x) for x in np.asarray(v, dtype=np.float64).reshape(-1)]


def cylinder_result(
    points: ArrayLike,
    *,
    rays: Any = None,
    noise: NoiseModel,
    p: float,
    k: float | None = None,
    monte_carlo: int = 0,
    rng: np.random.Generator,
    isotropic_sigma: float | None = None,
    world_from_rig: FloatArray | None = None,
    optics: Any = None,
    diameter_range: tuple[float, float] | None = None,
    errors: SensorErrors | None = None,
    beams: BeamGeometry | None = None,
    coverage_factor: float = 2.0,
    calibration: CalibrationInput | CalibrationRow | None = None,
) -> tuple[dict[str, Any], Any, Any]:
    """Cylinder fit, its three intervals and the JSON result: the one implementation behind the
    service's cylinder measurements and ``lrms fit --model cylinder``.

    ``points``: rig-frame points (n, 3). ``rays`` (:class:`lrms.cylinder.Rays`): every point's
    own beam; given, the fit is the line-of-sight fit and the critical-point ellipsoids sit where
    the beams meet the cylinder; ``None``: the orthogonal fit with isotropic ellipsoids of
    ``isotropic_sigma`` (``None``: the fit's rms residual) on the inliers projected onto the
    surface. ``k``: coverage factor of the critical-point interval (``None``:
    :data:`service.defaults.DEFAULT_K`). ``monte_carlo``: Monte Carlo refits (0: none).
    ``world_from_rig`` (4 x 4): positions and directions of the result in that frame; the axis
    direction's sign is canonical (largest component positive). ``errors``: the budget's type-B
    inputs (default :class:`lrms.budget.SensorErrors`: an uncalibrated LMS1xx); ``beams``: every
    point's scan and motor angle, scan index and the motor speed (default: the angles recovered
    from the points, scans from beta, 10 deg/s); ``coverage_factor``: k of ``U = k u_c``;
    ``calibration``: a calibration's row (:class:`lrms.budget.CalibrationInput`), or a function
    giving it from the fit and its inlier rays (:data:`CalibrationRow`; line-of-sight fits only).

    Returns ``(result, fit, critical_point_interval)``. Result keys: ``model``, ``n_points``,
    ``n_inliers``, ``diameter_m``, ``radius_m``, ``axis_point_m``, ``axis_direction``, ``rmse_m``,
    ``chi2_dof``, ``line_of_sight``, ``bias_correction_m`` (what the second-order bias correction
    subtracted from the diameter; ``None`` when not applied), ``p_m``, ``sigma_l_m``, ``base_point_m``, ``covariance``
    {``parameters``, ``e1``, ``e2``, ``matrix``}, ``uncertainty`` {``budget`` (rows {``source``,
    ``type``, ``u_x``, ``unit``, ``c``, ``u_m``, ``distribution``, ``note``}), ``combined_m``,
    ``expanded_m``, ``k`` (the budget's coverage factor), ``correlation``, ``d_min_m``, ``d_max_m``,
    ``std_m``, ``critical_point`` {``k``, ``r_ce_m``, ``percentile``}, ``gum`` {``std_m``, ``low_m``,
    ``high_m``, ``coverage``, ``coverage_factor``}, ``monte_carlo`` ({``n``, ``low_m``, ``high_m``,
    ``std_m``, ``coverage``, ``n_failed``, ``footprint_type_a_u_m`` (a footprint fit's type A beyond
    the thin-beam replicas', drawn as a diameter error), ``systematics``, ``multistart``} or ``None``)}.
    """
    from lrms.budget import cylinder_budget, replica_systematics
    from lrms.cylinder import fit_cylinder
    from lrms.uncertainty import critical_point_interval, gum_interval, monte_carlo_interval

    kk = DEFAULT_K if k is None else float(k)
    err = errors if errors is not None else SensorErrors()
    pts = np.asarray(points, dtype=np.float64)
    line_of_sight = rays is not None
    fit = fit_cylinder(
        pts,
        line_of_sight=line_of_sight,
        p=p,
        noise=noise,
        rays=rays,
        rng=rng,
        optics=optics if line_of_sight else None,
        diameter_range=diameter_range,
    )
    cyl = fit.cylinder
    sigma_l = noise.sigma_l if line_of_sight or isotropic_sigma is not None else float(fit.rmse)
    if line_of_sight:
        inlier_rays = rays.subset(fit.inliers)
        crit = critical_point_interval(cyl, rays=inlier_rays, noise=noise, k=kk, p=p)
    else:
        iso = float(fit.rmse) if isotropic_sigma is None else float(isotropic_sigma)
        surf = pts[fit.inliers]
        rad = cyl.radial(surf)
        surf = surf - rad * (1.0 - cyl.radius / np.linalg.norm(rad, axis=1))[:, None]
        crit = critical_point_interval(cyl, surf, k=kk, isotropic_sigma=iso)
    gum = gum_interval(fit, coverage_factor=GUM_COVERAGE_FACTOR)
    inlier_beams: BeamGeometry | None = None
    if line_of_sight:
        if beams is None:
            _, al, be = kinematics.inverse(pts, p)
            beams = BeamGeometry(al, be, p, float(np.deg2rad(DEFAULT_SWEEP_SPEED_DEG_S)))
        inlier_beams = beams.subset(fit.inliers)
    cal_row: CalibrationInput | None = None
    if isinstance(calibration, CalibrationInput):
        cal_row = calibration
    elif calibration is not None and line_of_sight:
        cal_row = calibration(fit, inlier_rays)
    budget = cylinder_budget(
        fit,
        inlier_rays if line_of_sight else None,
        inlier_beams,
        errors=err,
        noise=noise,
        calibration=cal_row,
        k=coverage_factor,
    )
    mc: dict[str, Any] | None = None
    if monte_carlo > 0:
        if line_of_sight:
            assert inlier_beams is not None
            sysm = replica_systematics(budget, err, inlier_beams)
            m = monte_carlo_interval(fit, inlier_rays, noise=noise, n=monte_carlo, p=p, rng=rng, systematics=sysm)
        else:
            m = monte_carlo_interval(
                fit, points=pts[fit.inliers], isotropic_sigma=isotropic_sigma, n=monte_carlo, rng=rng
            )
        mc = {
            "n": int(monte_carlo),
            "low_m": float(m.low),
            "high_m": float(m.high),
            "std_m": float(m.std),
            "coverage": float(m.coverage),
            "n_failed": int(m.n_failed),
            "footprint_type_a_u_m": float(m.footprint_type_a_u),
            "systematics": bool(line_of_sight),
            "multistart": bool(line_of_sight),
        }
    tf = np.eye(4) if world_from_rig is None else np.asarray(world_from_rig, dtype=np.float64)
    rot = tf[:3, :3]

    def to_frame(x: Any) -> list[float]:
        return _vec(rot @ np.asarray(x, dtype=np.float64) + tf[:3, 3])

    direction = rot @ cyl.direction
    if direction[int(np.argmax(np.abs(direction)))] < 0:  # an axis has no sign: report it canonically
        direction = -direction
    result = {
        "model": "cylinder",
        "n_points": int(pts.shape[0]),
        "n_inliers": int(fit.n_inliers),
        "diameter_m": float(fit.diameter),
        "radius_m": float(cyl.radius),
        "axis_point_m": to_frame(cyl.point),
        "axis_direction": _vec(direction),
        "rmse_m": float(fit.rmse),
        "chi2_dof": float(fit.chi2_dof),
        "line_of_sight": bool(line_of_sight),
        "bias_correction_m": fit.extra.get("bias_correction_diameter_m"),  # a float (fit_cylinder's)
        "p_m": float(p),
        "sigma_l_m": float(sigma_l),
        "base_point_m": None if fit.base_point is None else to_frame(fit.base_point),
        "covariance": {
            "parameters": ["tilt_e1_rad", "tilt_e2_rad", "shift_e1_m", "shift_e2_m", "radius_m"],
            "e1": _vec(rot @ fit.frame[0]),
            "e2": _vec(rot @ fit.frame[1]),
            "matrix": np.asarray(fit.covariance, dtype=np.float64).tolist(),
        },
        "footprint": _footprint_json(fit.extra) if optics is not None and line_of_sight else None,
        "diameter_range_m": None if diameter_range is None else [float(diameter_range[0]), float(diameter_range[1])],
        # outside the range within its uncertainty (lrms.cylinder.nominal_check): the diameter minus
        # the nearer bound, and that in units of the fit's u; None inside it
        "diameter_range_excess_m": fit.extra.get("nominal_excess_m"),
        "diameter_range_excess_u": fit.extra.get("nominal_excess_u"),
        "uncertainty": {
            **budget.to_dict(),
            "d_min_m": float(crit.d_min),
            "d_max_m": float(crit.d_max),
            "std_m": float(fit.std_diameter),
            "critical_point": {"k": kk, "r_ce_m": float(crit.r_ce), "percentile": float(crit.percentile)},
            "gum": {
                "std_m": float(gum.std),
                "low_m": float(gum.low),
                "high_m": float(gum.high),
                "coverage": float(gum.coverage),
                "coverage_factor": GUM_COVERAGE_FACTOR,
            },
            "monte_carlo": mc,
        },
    }
    return result, fit, crit


def _footprint_json(extra: dict[str, float]) -> dict[str, Any]:
    """The footprint fit's findings (:func:`lrms.cylinder.footprint_fit`): the edge family the data
    chose, the fitted threshold, the thin-beam diameter and the edge model's budget row."""
    code = extra.get("edge_mode_first", -1.0)
    tau = extra.get("edge_threshold", float("nan"))
    return {
        "edge_mode": {1.0: "first", 0.0: "weighted"}.get(code, "thin"),
        "edge_threshold": float(tau) if np.isfinite(tau) else None,
        "edge_model_u_m": float(extra.get("edge_model_u_m", 0.0)),
        # the spot's scale (x the nominal) and its u when the fit estimated it (then edge_model_u_m is 0)
        "spot_scale": extra.get("edge_spot_scale"),
        "spot_scale_u": extra.get("edge_spot_scale_u"),
        # the model choice's row (Akaike-weighted spread of the families' diameters) and the weights
        "edge_family_u_m": float(extra.get("edge_family_u_m", 0.0)),
        "akaike_weights": {
            k.removeprefix("akaike_weight_"): float(v) for k, v in extra.items() if k.startswith("akaike_weight_")
        },
        "thin_beam_diameter_m": extra.get("thin_beam_diameter_m"),
        # the fit's diameter u from J^T J and from the cost's profile in the radius (the larger is used)
        "u_jacobian_m": extra.get("footprint_u_jtj_m"),
        "u_profile_m": extra.get("footprint_u_profile_m"),
        # first hit: the profile-likelihood interval's ends (diameter offsets from the result, m)
        "profile_interval_m": (
            [extra["footprint_profile_lo_m"], extra["footprint_profile_hi_m"]]
            if "footprint_profile_lo_m" in extra
            else None
        ),
        # a profile that met a lower cost restarted the family's solve there: how often, and the move
        "profile_restarts": int(extra.get("footprint_profile_restarts", 0)),
        "profile_moved_m": float(extra.get("footprint_profile_moved_m", 0.0)),
    }


def optics_for(config: RigConfig, calibration: StoredCalibration | None = None) -> Any:
    """The fit's beam optics from ``[scanner.optics]`` (``None``: the thin beam), with the active
    calibration's spot scale applied when it has one (``CalibrationResult.beam_optics``: the scale
    times the nominal spot stored with it; :class:`CalibrationError` when ``[scanner.optics]`` gives
    another nominal spot than the calibration's)."""
    if config.optics_model == "ideal":
        return None
    from lrms.cylinder import BeamOptics

    o = config.scanner.optics
    nominal = BeamOptics(exit_diameter_m=o.spot_exit_m, divergence_rad=o.divergence_rad)
    return nominal if calibration is None else calibration.calibration.beam_optics(nominal)


def fit_cylinder_result(
    mapped: MappedSweep,
    keep: NDArray[np.bool_],
    request: MeasurementRequest,
    config: RigConfig,
    calibration: StoredCalibration | None = None,
) -> dict[str, Any]:
    """The cylinder of a measurement: :func:`cylinder_result` with every point's own beam (the
    active calibration's rig model: its beams and geometric ranges, its covariance as a budget row)."""
    from lrms.cylinder import Rays

    cal = rig_kinematics(config, calibration)
    nm = noise_model(config)
    l = mapped.ranges[keep]
    alpha = mapped.alpha[keep]
    beta = mapped.beta[keep]
    from service.models import resolve_sweep

    sweep = resolve_sweep(request.sweep, config)
    speed = 0.0 if sweep.mode == "step" else float(np.deg2rad(sweep.speed_deg_s))  # step-and-scan: at rest
    # every beam by the rig model the cloud was mapped with (RigModel: tilts, zeros, k0, k1, backlash, ...),
    # so that origins + ranges * dirs are the mapped points; nominal: Eq. 1's beams bit for bit
    origins, dirs, ranges = mapped.beam_rays(keep)
    # the motor speed of every beam (backlash and time-offset terms of the calibration's budget row):
    # the mapped one, else the sweep's, signed
    if mapped.motor_speed is not None:
        omega = mapped.motor_speed[keep]
    else:
        omega = np.full(l.shape, speed * (1.0 if sweep.stop_deg >= sweep.start_deg else -1.0))
    lateral = np.hypot(l * nm.sigma_alpha, (l * np.sin(alpha) + cal.p) * nm.sigma_beta)
    rays = Rays(
        origins=origins,
        dirs=dirs,
        ranges=ranges,
        sigma_l=np.full(l.shape, nm.sigma_l * (1.0 + mapped.rig.k1)),
        sigma_perp=np.maximum(lateral, 1e-7),
    )
    seed = request.options.seed if request.options.seed is not None else 0
    k = request.options.k if request.options.k is not None else config.fit.k
    beams = BeamGeometry(alpha, beta, cal.p, speed, mapped.scan_index[keep])
    cal_row: CalibrationRow | None = None
    if calibration is not None:
        stored = calibration

        def cal_row(fit: Any, inlier_rays: Any) -> CalibrationInput | None:
            from lrms.calibration.budget import calibration_input

            i = fit.inliers
            return calibration_input(
                stored.calibration, fit, inlier_rays, l[i], alpha[i], beta[i], omega[i], stored.name or stored.id
            )

    result, _, _ = cylinder_result(
        rays.points(),
        rays=rays,
        noise=nm,
        p=cal.p,
        k=k,
        monte_carlo=request.options.monte_carlo,
        rng=np.random.default_rng(seed),
        world_from_rig=cal.world_from_rig,
        optics=optics_for(config, calibration),
        diameter_range=_diameter_range(request),
        errors=sweep_errors(config, mapped),
        beams=beams,
        coverage_factor=config.fit.coverage_factor,
        calibration=cal_row,
    )
    result["fit_seed"] = seed
    return result


def sweep_errors(config: RigConfig, mapped: MappedSweep) -> SensorErrors:
    """The budget's type-B inputs of one sweep: ``[scanner.errors]`` and ``[motor.errors]``, with the
    motor timing jitter raised to what the sweep's own motor samples show when that is larger
    (:func:`service.sweep.motor_timing_jitter`: a busy host or link makes it so)."""
    err = config.sensor_errors()
    measured = mapped.motor_timing_jitter_s
    if measured is not None and np.isfinite(measured) and measured > err.timing_jitter_u_s:
        err = dataclasses.replace(err, timing_jitter_u_s=float(measured))
    return err


def _diameter_range(request: MeasurementRequest) -> tuple[float, float] | None:
    o = request.options
    if o.nominal_diameter_m is None:
        return None
    from lrms.cylinder import nominal_diameter_range

    return nominal_diameter_range(o.nominal_diameter_m, o.diameter_tolerance_m)


def fit_elbow_result(
    mapped: MappedSweep,
    keep: NDArray[np.bool_],
    request: MeasurementRequest,
    config: RigConfig,
    calibration: StoredCalibration | None = None,
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

    cal = rig_kinematics(config, calibration)
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
    out: dict[str, Any] = {**fit.to_dict(), "fit_seed": seed}
    if fit.inliers is not None:
        out["n_inliers"] = int(np.count_nonzero(fit.inliers))
    return out
