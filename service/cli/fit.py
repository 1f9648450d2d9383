"""``lrms fit FILE --model cylinder|elbow``: fit a model to a point cloud and state its uncertainty.

Cylinder: RANSAC detection, then the line-of-sight fit (each point's beam recovered by
inverting Eq. 1 with the rig at the origin and inner parameter ``--p``), the critical-point
interval (seed 003, Eq. 8-12, ellipsoids of ``--k``), the GUM standard uncertainty, the GUM budget
(:mod:`lrms.budget`: one row per source, ``U = k u_c`` with ``--coverage-factor``, type-B inputs
from ``--config``'s ``[scanner.errors]`` / ``[motor.errors]`` or an uncalibrated LMS1xx's) and,
with ``--monte-carlo N``, a GUM-S1 interval that draws the budget's systematic effects too.
``--no-line-of-sight`` is for clouds from elsewhere: orthogonal distances, isotropic noise.
Elbow: delegated to :mod:`service.cli.fit_elbow`.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

HELP = "fit a cylinder (diameter with uncertainty) or a pipe elbow to a point cloud file"
#: Exit status of a cylinder fit outside ``--nominal-diameter``'s range by more than 3 of its u
#: (:class:`lrms.errors.NominalDiameterError`: a wrong part or a fit gone astray); other errors exit
#: with 1, a fit outside the range within 3 u is reported with 0 and a warning line.
EXIT_NOMINAL_DIAMETER = 3


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="point cloud: .xyz / .txt / .csv (x y z, extra columns ignored) or .ply, metres")
    parser.add_argument("--model", choices=("cylinder", "elbow"), default="cylinder")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--plot", metavar="PNG", default=None, help="write a figure")
    parser.add_argument(
        "--calibration",
        metavar="CAL.json",
        default=None,
        help="a rig calibration (lrms calibrate --out): the cloud is re-mapped with the calibrated rig",
    )
    cyl = parser.add_argument_group("cylinder")
    cyl.add_argument("--p", type=float, default=0.1, help="inner parameter p of the rig, m (default 0.1)")
    cyl.add_argument(
        "--no-line-of-sight",
        dest="line_of_sight",
        action="store_false",
        help="the cloud is not from this rig at the origin: orthogonal-distance fit, isotropic noise",
    )
    cyl.add_argument(
        "--sigma-l-mm",
        type=float,
        default=None,
        help="range noise sigma_l in mm (default 11.67, seed 003); with --no-line-of-sight the isotropic "
        "noise (default: the fit's rms residual)",
    )
    cyl.add_argument(
        "--k",
        type=float,
        default=None,
        help="error ellipsoid factor k of the critical-point interval (default 3: service.config.DEFAULT_K)",
    )
    cyl.add_argument(
        "--monte-carlo", type=int, default=0, metavar="N", help="also a Monte Carlo interval from N replicas"
    )
    cyl.add_argument("--seed", type=int, default=0, help="random seed (RANSAC, Monte Carlo)")
    cyl.add_argument(
        "--nominal-diameter",
        type=float,
        default=None,
        metavar="D",
        help="nominal diameter (m): reject other sizes (a fit outside within 3 u of it: a warning)",
    )
    cyl.add_argument(
        "--diameter-tolerance",
        type=float,
        default=None,
        metavar="T",
        help="accepted deviation from the nominal diameter (m; default 10 %% of it)",
    )
    cyl.add_argument(
        "--optics",
        choices=("lms1xx", "ideal"),
        default="ideal",
        help="beam model of the line-of-sight fit: ideal (thin beam, default) or lms1xx (footprint, expected echo)",
    )
    cyl.add_argument("--spot-exit-mm", type=float, default=8.0, help="light spot at the front screen, mm (LMS1xx: 8)")
    cyl.add_argument(
        "--divergence-mrad", type=float, default=15.0, help="beam divergence, full angle, mrad (LMS1xx: 15)"
    )
    cyl.add_argument(
        "--coverage-factor",
        type=float,
        default=None,
        help="k of the budget's expanded uncertainty U = k u_c (default 2, or --config's [fit] coverage_factor)",
    )
    cyl.add_argument(
        "--config",
        metavar="RIG_TOML",
        default=None,
        help="rig config whose [scanner.errors] and [motor.errors] give the budget's type-B inputs "
        "(default: an uncalibrated LMS1xx, docs/cylinder.md)",
    )
    cyl.add_argument(
        "--sweep-speed-deg-s",
        type=float,
        default=10.0,
        help="motor speed during the sweep, for the budget's timing row (default 10; 0: step-and-scan)",
    )
    elbow = parser.add_argument_group("elbow")
    elbow.add_argument(
        "--degree", default=None, help="joint degree: 90, 45, any angle in deg (default: from the cloud)"
    )
    elbow.add_argument("--ratio", default="free", help="A/D ratio: 0.5, 1, 1.5 or free (default)")
    elbow.add_argument("--flange", action="store_true", help="the joint has flanges")


def run(args: argparse.Namespace) -> int:
    from lrms.errors import NominalDiameterError

    try:
        return _run(args)
    except NominalDiameterError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_NOMINAL_DIAMETER


def _run(args: argparse.Namespace) -> int:
    from service.pointio import read_points

    points = read_points(args.file)
    calibration = None
    if args.calibration:
        points, calibration = _apply_calibration(args, points)  # (calibration, readings)
    result = _run_elbow(args, points) if args.model == "elbow" else fit_cylinder_file(args, points, calibration)
    if calibration is not None:
        result["calibration"] = {"file": str(args.calibration), "created": calibration[0].created}
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        _print_text(result)
    return 0


def _run_elbow(args: argparse.Namespace, points: Any) -> dict[str, Any]:
    from service.errors import ServiceError

    try:
        from service.cli.fit_elbow import run_elbow
    except ModuleNotFoundError as exc:
        if exc.name == "service.cli.fit_elbow":
            raise ServiceError("the elbow model is not available in this installation (service.cli.fit_elbow)") from exc
        raise
    result: dict[str, Any] = run_elbow(args, points)
    return {"model": "elbow", "file": str(args.file), **result}


def _apply_calibration(args: argparse.Namespace, points: Any) -> tuple[Any, Any]:
    """Re-map a nominal-Eq.-1 cloud with the calibrated rig (the calibration's nominal p is the
    cloud's). Returns the calibrated points and ``(calibration, readings)``."""
    from pathlib import Path

    from lrms.calibration import CalibrationError, CalibrationResult, Observations

    try:
        text = Path(args.calibration).read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(f"cannot read the calibration {args.calibration}: {exc.strerror or exc}") from None
    cal = CalibrationResult.from_json(text)
    if args.p != 0.1 and abs(cal.nominal.p - args.p) > 1e-12:
        raise CalibrationError(f"--p {args.p} differs from the calibration's nominal p {cal.nominal.p}")
    args.p = cal.nominal.p
    obs = Observations.from_points(points, cal.nominal.p)
    if len(obs) != len(points):
        raise CalibrationError("some points lie on the motor axis: their readings cannot be recovered")
    return cal.model.forward(obs.l, obs.alpha, obs.beta), (cal, obs)


def fit_cylinder_file(args: argparse.Namespace, points: Any, calibration: Any = None) -> dict[str, Any]:
    """The cylinder branch: :func:`service.fitting.cylinder_result`, optional plot; a JSON-ready dict."""
    import numpy as np

    from lrms import kinematics
    from lrms.budget import BeamGeometry, SensorErrors
    from lrms.covariance import NoiseModel
    from lrms.cylinder import nominal_diameter_range, rays_from_points
    from lrms.errors import LrmsError
    from service.fitting import cylinder_result

    if args.p < 0 or not np.isfinite(args.p):
        raise LrmsError(f"--p must be a length >= 0, got {args.p}")
    if args.sigma_l_mm is not None and not args.sigma_l_mm > 0:
        raise LrmsError(f"--sigma-l-mm must be > 0, got {args.sigma_l_mm}")
    if args.k is not None and not 0 < args.k <= 10:
        raise LrmsError(f"--k must be in (0, 10], got {args.k}")
    if args.coverage_factor is not None and not 0 < args.coverage_factor <= 10:
        raise LrmsError(f"--coverage-factor must be in (0, 10], got {args.coverage_factor}")
    if not (np.isfinite(args.sweep_speed_deg_s) and 0 <= args.sweep_speed_deg_s <= 360):
        raise LrmsError(f"--sweep-speed-deg-s must be in [0, 360], got {args.sweep_speed_deg_s}")
    errors = SensorErrors()
    coverage_factor = 2.0
    if args.config is not None:
        from service.config import load_config

        cfg = load_config(args.config)
        errors, coverage_factor = cfg.sensor_errors(), cfg.fit.coverage_factor
    if args.coverage_factor is not None:
        coverage_factor = float(args.coverage_factor)
    if not (np.isfinite(args.spot_exit_mm) and args.spot_exit_mm >= 0):
        raise LrmsError(f"--spot-exit-mm must be >= 0, got {args.spot_exit_mm}")
    if not (np.isfinite(args.divergence_mrad) and args.divergence_mrad >= 0):
        raise LrmsError(f"--divergence-mrad must be >= 0, got {args.divergence_mrad}")
    if args.diameter_tolerance is not None and args.nominal_diameter is None:
        raise LrmsError("--diameter-tolerance needs --nominal-diameter")
    diameter_range = None
    if args.nominal_diameter is not None:
        if not (np.isfinite(args.nominal_diameter) and args.nominal_diameter > 0):
            raise LrmsError(f"--nominal-diameter must be > 0 m, got {args.nominal_diameter}")
        diameter_range = nominal_diameter_range(args.nominal_diameter, args.diameter_tolerance)
    optics = None
    if args.optics == "lms1xx":
        from lrms.cylinder import BeamOptics  # the footprint model (scipy.special): on first use

        optics = BeamOptics(exit_diameter_m=args.spot_exit_mm / 1e3, divergence_rad=args.divergence_mrad / 1e3)
        if calibration is not None:  # the calibration's spot scale from its reference spheres, if any
            optics = calibration[0].beam_optics(optics)
    noise = NoiseModel() if args.sigma_l_mm is None else NoiseModel(sigma_l=args.sigma_l_mm / 1e3)
    pts = np.asarray(points, dtype=np.float64)
    rays = rays_from_points(pts, args.p, noise) if args.line_of_sight else None
    if calibration is not None and args.line_of_sight:  # the beams of the calibrated rig
        from lrms.cylinder import Rays

        cal, obs = calibration
        model = cal.model
        o, d = model.rays(obs.alpha, obs.beta)
        perp = np.hypot(obs.l * noise.sigma_alpha, (obs.l * np.sin(obs.alpha) + model.p) * noise.sigma_beta)
        rays = Rays(o, d, model.geometric_range(obs.l), np.full(obs.l.size, noise.sigma_l), perp)
    cal_row = None
    if calibration is not None and args.line_of_sight:  # the calibration's covariance as a budget row

        def cal_row(fit: Any, inlier_rays: Any) -> Any:
            from lrms.calibration.budget import calibration_input

            c, o = calibration
            i = fit.inliers
            return calibration_input(c, fit, inlier_rays, o.l[i], o.alpha[i], o.beta[i], None, str(args.calibration))

    beams = None
    if rays is not None:
        speed = float(np.deg2rad(args.sweep_speed_deg_s))
        if calibration is not None:  # the calibrated rig's beam angles
            beams = BeamGeometry(calibration[1].alpha, calibration[1].beta, calibration[0].model.p, speed)
        else:
            _, alpha, beta = kinematics.inverse(pts, args.p)
            beams = BeamGeometry(alpha, beta, args.p, speed)
    core, fit, crit = cylinder_result(
        pts,
        rays=rays,
        noise=noise,
        p=args.p,
        k=args.k,
        monte_carlo=args.monte_carlo or 0,
        rng=np.random.default_rng(args.seed),
        isotropic_sigma=None if args.sigma_l_mm is None else noise.sigma_l,
        optics=optics,
        diameter_range=diameter_range,
        errors=errors,
        beams=beams,
        coverage_factor=coverage_factor,
        calibration=cal_row,
    )
    result: dict[str, Any] = {"model": "cylinder", "file": str(args.file), **core}
    if args.plot:
        from service.plots import cylinder_figure

        cyl = fit.cylinder
        cylinder_figure(pts, fit.inliers, cyl.point, cyl.direction, cyl.radius, crit.radii, crit.r_ce, args.plot)
        result["plot"] = str(args.plot)
    return result


def _print_text(result: dict[str, Any]) -> None:
    if result.get("model") != "cylinder":
        for key, value in result.items():
            print(f"{key}: {value}")
        return
    u = result["uncertainty"]
    d = result["diameter_m"] * 1e3
    print(f"file: {result['file']}  ({result['n_inliers']} of {result['n_points']} points on the cylinder)")
    print(f"diameter: {d:.3f} mm   rms residual: {result['rmse_m'] * 1e3:.2f} mm   chi2/dof: {result['chi2_dof']:.2f}")
    ap = ", ".join(f"{v:.4f}" for v in result["axis_point_m"])
    ad = ", ".join(f"{v:.5f}" for v in result["axis_direction"])
    print(f"axis: point ({ap}) m, direction ({ad})")
    print(
        f"critical point (k={u['critical_point']['k']:g}): [{u['d_min_m'] * 1e3:.3f}, {u['d_max_m'] * 1e3:.3f}] mm"
        f" = d +- {(u['d_max_m'] - u['d_min_m']) * 500:.3f} mm"
    )
    g = u["gum"]
    print(f"GUM: u(d) = {g['std_m'] * 1e3:.3f} mm, 95 %: [{g['low_m'] * 1e3:.3f}, {g['high_m'] * 1e3:.3f}] mm")
    fp = result.get("footprint")
    if fp:
        thin = fp["thin_beam_diameter_m"]
        tau = "" if fp["edge_threshold"] is None else f", threshold {100 * fp['edge_threshold']:.0f} %"
        print(
            f"footprint: edge model {fp['edge_mode']}{tau}, u(edge) = {fp['edge_model_u_m'] * 1e3:.3f} mm,"
            f" u(family) = {fp.get('edge_family_u_m', 0.0) * 1e3:.3f} mm"
            + ("" if thin is None else f", thin-beam fit {thin * 1e3:.3f} mm")
        )
    if result.get("diameter_range_excess_m") is not None:
        lo, hi = (1e3 * x for x in result["diameter_range_m"])
        print(
            f"warning: the diameter is outside the nominal range [{lo:.1f}, {hi:.1f}] mm by"
            f" {result['diameter_range_excess_m'] * 1e3:+.2f} mm ({result['diameter_range_excess_u']:.2f} u of the fit)"
        )
    if u.get("monte_carlo"):
        m = u["monte_carlo"]
        print(f"Monte Carlo ({m['n']}): 95 %: [{m['low_m'] * 1e3:.3f}, {m['high_m'] * 1e3:.3f}] mm")
    print(budget_table(u))
    if result.get("plot"):
        print(f"plot: {result['plot']}")


def budget_table(u: dict[str, Any]) -> str:
    """The budget of a result's ``uncertainty`` as a text table (u in mm)."""
    lines = [
        "uncertainty budget (GUM):",
        f"  {'source':<26s} {'type':<4s} {'u_x':>10s} {'unit':<4s} {'c (m/unit)':>11s} {'u (mm)':>8s}  distribution",
    ]
    for r in u["budget"]:
        lines.append(
            f"  {r['source']:<26s} {r['type']:<4s} {r['u_x']:>10.4g} {r['unit']:<4s} {r['c']:>11.4g} "
            f"{r['u_m'] * 1e3:>8.4f}  {r['distribution']}"
        )
    lines.append(f"  combined u_c = {u['combined_m'] * 1e3:.3f} mm ({u['correlation']})")
    lines.append(f"  expanded U = {u['k']:g} u_c = {u['expanded_m'] * 1e3:.3f} mm")
    return "\n".join(lines)
