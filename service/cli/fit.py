"""``lrms fit FILE --model cylinder|elbow``: fit a model to a point cloud and state its uncertainty.

Cylinder: RANSAC detection, then the line-of-sight fit (each point's beam recovered by
inverting Eq. 1 with the rig at the origin and inner parameter ``--p``), the critical-point
interval (seed 003, Eq. 8-12, ellipsoids of ``--k``), the GUM standard uncertainty and, with
``--monte-carlo N``, a GUM-S1 interval. ``--no-line-of-sight`` is for clouds from elsewhere:
orthogonal distances, isotropic noise. Elbow: delegated to :mod:`service.cli.fit_elbow`.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

HELP = "fit a cylinder (diameter with uncertainty) or a pipe elbow to a point cloud file"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="point cloud: .xyz / .txt / .csv (x y z, extra columns ignored) or .ply, metres")
    parser.add_argument("--model", choices=("cylinder", "elbow"), default="cylinder")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--plot", metavar="PNG", default=None, help="write a figure")
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
    cyl.add_argument("--k", type=float, default=1.0, help="error ellipsoid factor k of the critical-point interval")
    cyl.add_argument(
        "--monte-carlo", type=int, default=0, metavar="N", help="also a Monte Carlo interval from N replicas"
    )
    cyl.add_argument("--seed", type=int, default=0, help="random seed (RANSAC, Monte Carlo)")
    elbow = parser.add_argument_group("elbow")
    elbow.add_argument(
        "--degree", default=None, help="joint degree: 90, 45, any angle in deg (default: from the cloud)"
    )
    elbow.add_argument("--ratio", default="free", help="A/D ratio: 0.5, 1, 1.5 or free (default)")
    elbow.add_argument("--flange", action="store_true", help="the joint has flanges")


def run(args: argparse.Namespace) -> int:
    from service.pointio import read_points

    points = read_points(args.file)
    result = _run_elbow(args, points) if args.model == "elbow" else fit_cylinder_file(args, points)
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


def fit_cylinder_file(args: argparse.Namespace, points: Any) -> dict[str, Any]:
    """The cylinder branch: fit, three intervals, optional plot; a JSON-ready dict."""
    import numpy as np

    from lrms.covariance import NoiseModel
    from lrms.cylinder import fit_cylinder, rays_from_points
    from lrms.errors import LrmsError
    from lrms.uncertainty import critical_point_interval, gum_interval, monte_carlo_interval

    if args.p < 0 or not np.isfinite(args.p):
        raise LrmsError(f"--p must be a length >= 0, got {args.p}")
    if args.sigma_l_mm is not None and not args.sigma_l_mm > 0:
        raise LrmsError(f"--sigma-l-mm must be > 0, got {args.sigma_l_mm}")
    noise = NoiseModel() if args.sigma_l_mm is None else NoiseModel(sigma_l=args.sigma_l_mm / 1e3)
    rng = np.random.default_rng(args.seed)
    pts = np.asarray(points, dtype=np.float64)
    rays = rays_from_points(pts, args.p, noise) if args.line_of_sight else None
    fit = fit_cylinder(pts, line_of_sight=args.line_of_sight, p=args.p, noise=noise, rays=rays, rng=rng)
    cyl = fit.cylinder
    if rays is not None:
        inlier_rays = rays.subset(fit.inliers)
        crit = critical_point_interval(cyl, rays=inlier_rays, noise=noise, k=args.k, p=args.p)
    else:
        iso = noise.sigma_l if args.sigma_l_mm is not None else fit.rmse
        surf = pts[fit.inliers]
        rad = cyl.radial(surf)
        surf = surf - rad * (1.0 - cyl.radius / np.linalg.norm(rad, axis=1))[:, None]
        crit = critical_point_interval(cyl, surf, k=args.k, isotropic_sigma=iso)
    gum = gum_interval(fit)
    unc: dict[str, Any] = {
        "k": args.k,
        "d_min_m": crit.d_min,
        "d_max_m": crit.d_max,
        "critical_r_ce_m": crit.r_ce,
        "std_m": gum.std,
        "gum": {"std_m": gum.std, "low_m": gum.low, "high_m": gum.high, "coverage": round(gum.coverage, 4)},
    }
    if args.monte_carlo:
        if rays is not None:
            mc = monte_carlo_interval(fit, inlier_rays, noise=noise, n=args.monte_carlo, rng=rng, p=args.p)
        else:
            mc = monte_carlo_interval(
                fit,
                points=pts[fit.inliers],
                isotropic_sigma=None if args.sigma_l_mm is None else noise.sigma_l,
                n=args.monte_carlo,
                rng=rng,
            )
        unc["monte_carlo"] = {
            "n": args.monte_carlo,
            "std_m": mc.std,
            "low_m": mc.low,
            "high_m": mc.high,
            "coverage": mc.coverage,
            "failed": mc.n_failed,
        }
    result: dict[str, Any] = {
        "model": "cylinder",
        "file": str(args.file),
        "n_points": int(pts.shape[0]),
        "n_inliers": fit.n_inliers,
        "diameter_m": cyl.diameter,
        "radius_m": cyl.radius,
        "axis_point_m": cyl.point.tolist(),
        "axis_direction": cyl.direction.tolist(),
        "rmse_m": fit.rmse,
        "chi2_dof": fit.chi2_dof,
        "line_of_sight": fit.line_of_sight,
        "p_m": args.p,
        "sigma_l_m": noise.sigma_l if args.line_of_sight else (fit.rmse if args.sigma_l_mm is None else noise.sigma_l),
        "base_point_m": None if fit.base_point is None else fit.base_point.tolist(),
        "covariance": {
            "parameters": ["tilt_e1_rad", "tilt_e2_rad", "shift_e1_m", "shift_e2_m", "radius_m"],
            "e1": fit.frame[0].tolist(),
            "e2": fit.frame[1].tolist(),
            "matrix": fit.covariance.tolist(),
        },
        "uncertainty": unc,
    }
    if args.plot:
        from service.plots import cylinder_figure

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
        f"critical point (k={u['k']:g}): [{u['d_min_m'] * 1e3:.3f}, {u['d_max_m'] * 1e3:.3f}] mm"
        f" = d +- {(u['d_max_m'] - u['d_min_m']) * 500:.3f} mm"
    )
    g = u["gum"]
    print(f"GUM: u(d) = {g['std_m'] * 1e3:.3f} mm, 95 %: [{g['low_m'] * 1e3:.3f}, {g['high_m'] * 1e3:.3f}] mm")
    if "monte_carlo" in u:
        m = u["monte_carlo"]
        print(f"Monte Carlo ({m['n']}): 95 %: [{m['low_m'] * 1e3:.3f}, {m['high_m'] * 1e3:.3f}] mm")
    if result.get("plot"):
        print(f"plot: {result['plot']}")
