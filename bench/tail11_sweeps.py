"""Diagnostic (issue 11, the energy-weighted tail): rebuild single sweeps of the coverage run of
``bench_sensor_model --clouds roi --fit footprint --no-offset --no-ideal`` exactly as it draws them
(the roi beams' subset draw, the same seed stream, 0-based sweep indices as in its --jsonl), fit
each as it does, print the fit's diagnostics, and profile the energy-weighted family's cost in the
diameter (every other parameter, spot scale included, re-minimized at each fixed radius) to see
whether the likelihood has a second minimum or the fit sits on a bound.

    PYTHONPATH=. OMP_NUM_THREADS=1 python -m bench.tail11_sweeps --edge 0.3:weighted --seed 11 \
        --cache /work/runs/cache --only 109,292,367 [--profile]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np
from scipy.optimize import least_squares

from bench import bench_sensor_model as bsm
from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics, fit_cylinder, nominal_diameter_range
from lrms.cylinder.footprint_solve import _box, _end_trim, _fit_scale, _residuals, _solve
from lrms.cylinder.model import rays_from_points
from lrms.cylinder.refine import _Frame
from lrms.errors import LrmsError
from lrms.uncertainty import gum_interval
from sim.scene import Footprint, LMS1xxSensor
from sim.scene.library import SEED003_AXIS_POINT

OFFSETS_MM = (-24.0, -16.0, -8.0, -4.0, 0.0, 4.0, 8.0)


def profile(pts: np.ndarray, fit, optics: BeamOptics, truth_d: float) -> None:  # type: ignore[no-untyped-def]
    """The weighted family's cost at fixed diameters about the fitted one and at the truth."""
    rays = rays_from_points(pts, noise=NoiseModel())
    idx = fit.inliers
    keep = _end_trim(fit.cylinder, rays.subset(idx), optics)
    use = idx[keep]
    if use.size > 4000:
        use = np.sort(np.random.default_rng(4).choice(use, 4000, replace=False))
    work = rays.subset(use)
    frame = _Frame.at(fit.cylinder.with_point_near(pts[use].mean(axis=0)))
    free = _solve(frame, work, optics, "weighted", np.zeros(6))
    r0 = float(frame.unpack(free.theta[:5])[2])
    dof = work.ranges.size - 6
    c0 = free.cost
    spot = float(2.0 / optics.profile_sigma * optics.sigma(float(np.linalg.norm(frame.a))))
    lo, hi, xs = _box("weighted", spot, 6)
    m = np.array([0, 1, 2, 3, 5])
    print(
        f"    free weighted: D {2e3 * r0:.2f} mm (err {1e3 * (2 * r0 - truth_d):+.2f}), chi2/dof {c0 / dof:.3f},"
        f" spot {np.exp(free.theta[5]):.3f}, d_radius {1e3 * free.theta[4]:+.2f} mm of box"
        f" [{1e3 * lo[4]:+.1f}, {1e3 * hi[4]:+.1f}]"
    )
    base_r = r0 - free.theta[4]  # frame radius (theta[4] = 0)
    targets = [(f"{o:+.0f}", 2 * r0 + o / 1e3) for o in OFFSETS_MM] + [("truth", truth_d)]
    for name, d in targets:
        dr = d / 2 - base_r
        if not lo[4] <= dr <= hi[4]:
            print(f"      D {1e3 * d:7.2f} ({name:>5s}): outside the fit's radius box")
            continue

        def res(p: np.ndarray, dr: float = dr) -> np.ndarray:
            th = np.insert(p, 4, dr)
            return _residuals(th, frame, work, optics, "weighted")

        out = least_squares(
            res,
            np.clip(free.theta[m], lo[m] + 1e-12, hi[m] - 1e-12),
            bounds=(lo[m], hi[m]),
            x_scale=xs[m],
            diff_step=np.full(5, 1e-5),
            ftol=1e-8,
            max_nfev=300,
        )
        c = 2 * out.cost
        print(
            f"      D {1e3 * d:7.2f} ({name:>5s}): dchi2 {c - c0:8.2f} (/chi2dof {(c - c0) / (c0 / dof):8.2f}),"
            f" spot {np.exp(out.x[4]):.3f}"
        )


def trace_families() -> None:
    """Wrap the footprint fit's family solver (this process only) to print each family's solution:
    its diameter change from the thin beam's, where that sits in the radius box, tau and spot."""
    from lrms.cylinder import footprint as fp

    inner = fp._fit_families

    def traced(frame, work, optics, modes, starts, gate, first_multi=None):  # type: ignore[no-untyped-def]
        out = inner(frame, work, optics, modes, starts, gate, first_multi)
        spot = float(2.0 / optics.profile_sigma * optics.sigma(float(np.linalg.norm(frame.a))))
        aic = fp._aics(out, frame, work, optics, gate)
        for s in out:
            lo, hi, _ = _box(s.mode, spot, s.theta.size)
            print(
                f"    family {s.mode:8s} on {work.ranges.size} beams: dD from thin {2e3 * s.theta[4]:+7.2f} mm"
                f" (radius box [{1e3 * lo[4]:+.1f}, {1e3 * hi[4]:+.1f}] mm), tau {s.tau:.3f},"
                f" spot {_fit_scale(s.theta, s.mode):.3f}, aic {aic[s.mode]:.1f}",
                flush=True,
            )
        return out

    fp._fit_families = traced


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--edge", default="0.3:weighted")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--only", required=True, help="comma list of 0-based sweep indices (the --jsonl's)")
    ap.add_argument("--cache", required=True)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--trace", action="store_true", help="print every edge family's solution (radius vs its box)")
    ap.add_argument(
        "--weighted-profile-interval",
        action="store_true",
        help="the energy-weighted family's u from the profile-likelihood interval (WEIGHTED_PROFILE_INTERVAL)",
    )
    args = ap.parse_args(argv)
    if args.weighted_profile_interval:
        from lrms.cylinder import footprint

        footprint.WEIGHTED_PROFILE_INTERVAL = True
    thr, mode = float(args.edge.split(":")[0]), args.edge.split(":")[1]
    only = sorted(int(x) for x in args.only.split(","))
    sys.modules["__main__"].Geometry = bsm.Geometry  # type: ignore[attr-defined]
    sensor = LMS1xxSensor(footprint=Footprint())
    diameter = 0.1375
    g = bsm.cached_geometry(args.cache, "seed003-room", diameter, SEED003_AXIS_POINT[1], sensor)
    draw = bsm.lms_draw(g, dataclasses.replace(sensor, edge_threshold=thr, range_mode=mode), bsm.roi_beams(g))
    rng = np.random.default_rng(args.seed)
    optics = BeamOptics()
    if args.trace:
        trace_families()
    for sweep in range(only[-1] + 1):
        ranges, valid = draw(rng)
        fit_seed = int(rng.integers(1 << 31))
        if sweep not in only:
            continue
        pts = g.origins[valid] + ranges[valid, None] * g.dirs[valid]
        pts = pts[np.all((pts >= g.roi_lo) & (pts <= g.roi_hi), axis=1)]
        t0 = time.process_time()
        try:
            fit = fit_cylinder(
                pts,
                noise=NoiseModel(),
                rng=np.random.default_rng(fit_seed),
                optics=optics,
                diameter_range=nominal_diameter_range(diameter),
            )
        except LrmsError as exc:
            print(f"sweep {sweep}: {len(pts)} pts, failed: {exc}")
            continue
        x = fit.extra
        ug = gum_interval(fit).std
        u = float(
            np.sqrt(
                ug**2 + sum(x.get(k, 0.0) ** 2 for k in ("edge_model_u_m", "edge_family_u_m", "footprint_bias_u_m"))
            )
        )
        print(
            f"sweep {sweep}: {len(pts)} pts, {fit.inliers.size} inliers, err {1e3 * (fit.diameter - diameter):+.2f}"
            " mm,"
            f" u {1e3 * u:.2f} (gum {1e3 * ug:.2f}, jtj {1e3 * x.get('footprint_u_jtj_m', np.nan) / 2:.2f},"
            f" prof {1e3 * x.get('footprint_u_profile_m', np.nan) / 2:.2f},"
            f" family {1e3 * x.get('edge_family_u_m', 0):.2f},"
            f" bias {1e3 * x.get('footprint_bias_u_m', 0):.2f}), chi2/dof {fit.chi2_dof:.3f},"
            f" mode {x.get('edge_mode_first')}, spot {x.get('edge_spot_scale', np.nan):.3f}"
            f" +- {x.get('edge_spot_scale_u', np.nan):.3f},"
            f" thin {1e3 * (x['thin_beam_diameter_m'] - diameter):+.2f} mm,"
            f" aic thin {x.get('aic_thin', np.nan):.1f} wtd {x.get('aic_weighted', np.nan):.1f}"
            f" first {x.get('aic_first', np.nan):.1f}, excess {1e3 * x.get('nominal_excess_m', 0):+.2f} mm,"
            f" axis {np.round(fit.cylinder.direction, 3)}"
            f"  ({time.process_time() - t0:.1f} s cpu)",
            flush=True,
        )
        if args.profile:
            profile(pts, fit, optics, diameter)
            print(f"    ({time.process_time() - t0:.1f} s cpu with the profile)", flush=True)


if __name__ == "__main__":
    main()
