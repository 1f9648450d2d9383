"""One footprint-fit solve on noiseless first-hit clouds: speed and the bias left by the edge beams.

Seed 003's 137.5 mm part alone (no table, no room) at 2.53 m, noiseless LMS1xx first-hit echoes
(``--sub-rays`` of the simulator, every 4th scan of the bench's 0.4 deg sweep, beams clear of the
part's ends), and the first-hit family's solve (``lrms.cylinder.footprint_solve._solve``) started at the
true cylinder and threshold. Printed per threshold (10 / 30 / 50 %) and Jacobian: the fitted
diameter's error (mm), the fitted threshold, residual evaluations, wall time, and the time ratio of
the implicit-step Jacobian (``_first_jacobian``) against plain forward differences through the
Newton solve, measured in the same run. ``--share-u`` sets ``BeamOptics.share_u``.

Then ``--ideal`` sweeps of the ideal thin-beam sensor (seed 003's range noise) through
``fit_cylinder(..., optics=BeamOptics(share_u=...))``: which family the criterion picks (the thin
beam should win) and the diameter error.

Run: ``PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_footprint_fit [--sub-rays 32]
[--share-u 0.03] [--thresholds 0.1,0.3,0.5] [--ideal 2] [--baseline]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.special import logit

import lrms.cylinder.footprint_solve as fp
from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics, Cylinder, Rays, fit_cylinder, nominal_diameter_range
from lrms.cylinder.refine import _Frame
from lrms.kinematics import RigCalibration
from sim.scene import SEED003_DIAMETER, Footprint, LMS1xxSensor, Scene, SensorModel, cast_beams, get_scene
from sim.scene.library import SEED003_AXIS_POINT
from sim.scene.shapes import Cylinder as SceneCylinder

TRUTH = Cylinder(np.array([0.28, SEED003_AXIS_POINT[1], 0.0]), np.array([0.0, 0.0, 1.0]), SEED003_DIAMETER / 2)


def first_hit_rays(threshold: float, sub_rays: int) -> Rays:
    scene = Scene("part")
    base = TRUTH.point - np.array([0.0, 0.0, 0.5])
    scene.add(SceneCylinder(base, TRUTH.direction, TRUTH.radius, 1.5), name="cylinder")
    sensor = LMS1xxSensor(footprint=Footprint(sub_rays=sub_rays), edge_threshold=threshold, range_mode="first")
    dev, mot = np.meshgrid(np.deg2rad(np.arange(50.0, 130.0, 0.25)), np.deg2rad(np.arange(-20.0, 70.0, 1.6)))
    o, d = RigCalibration().world_rays(dev.ravel(), mot.ravel())
    e = sensor.echoes(scene, o, d, None)
    on = e.valid & (e.index == 0)
    o, d, r = o[on], d[on], e.range[on]
    z = o[:, 2] + r * d[:, 2]
    keep = (z > -0.3) & (z < 0.8)  # clear of the ends by more than 3 spot sigmas
    n = int(np.count_nonzero(keep))
    return Rays(o[keep], d[keep], r[keep], np.full(n, 0.012), np.full(n, 1e-3))


def solve_case(rays: Rays, threshold: float, optics: BeamOptics, jac: str) -> tuple[float, float, int, float]:
    fp._JACOBIAN = jac
    frame = _Frame.at(TRUTH.with_point_near(rays.points().mean(axis=0)))
    t0 = time.perf_counter()
    s = fp._solve(frame, rays, optics, "first", np.array([0, 0, 0, 0, 0, float(logit(threshold))]))
    dt = time.perf_counter() - t0
    fp._JACOBIAN = "implicit"
    return float(2 * frame.unpack(s.theta[:5])[2]) - SEED003_DIAMETER, s.tau, s.nfev, dt


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sub-rays", type=int, default=Footprint().sub_rays)
    ap.add_argument("--share-u", type=float, default=BeamOptics().share_u)
    ap.add_argument("--thresholds", default="0.1,0.3,0.5")
    ap.add_argument("--ideal", type=int, default=2, help="ideal-sensor sweeps through the whole footprint fit")
    ap.add_argument("--baseline", action="store_true", help="also solve with forward differences (time ratio)")
    args = ap.parse_args(argv)
    optics = BeamOptics(share_u=args.share_u)
    print(f"simulated sub-rays {args.sub_rays}, share_u {args.share_u}")
    for thr in (float(x) for x in args.thresholds.split(",")):
        rays = first_hit_rays(thr, args.sub_rays)
        times: dict[str, float] = {}
        for jac in ("implicit", "2-point") if args.baseline else ("implicit",):
            err, tau, nfev, dt = solve_case(rays, thr, optics, jac)
            times[jac] = dt
            print(
                f"  first hit {100 * thr:2.0f} %, {rays.ranges.size} beams, jac {jac:8s}: diameter error"
                f" {1e3 * err:+6.2f} mm, tau {tau:.3f}, {nfev:3d} evaluations, {dt:6.2f} s",
                flush=True,
            )
        if len(times) == 2:
            ratio = times["2-point"] / times["implicit"]
            print(f"  -> implicit Jacobian {ratio:.1f} x faster than forward differences")
    cal = RigCalibration()
    dev = np.deg2rad(np.arange(60.0, 120.0 + 1e-9, 0.25))
    mot = np.deg2rad(np.arange(-20.0, 70.0, 0.4))[:, None]
    c0 = np.asarray(SEED003_AXIS_POINT)
    for seed in range(args.ideal):
        samples = cast_beams(
            get_scene("seed003-bare"),
            cal,
            SensorModel(sigma_alpha=0.0, sigma_beta=0.0),
            dev,
            mot,
            np.random.default_rng(100 + seed),
        )
        pts = samples.points(cal)
        pts = pts[np.all((pts >= c0 + np.array([-0.6, -0.4, -0.05])) & (pts <= c0 + np.array([0.6, 0.4, 0.9])), axis=1)]
        t0 = time.perf_counter()
        fit = fit_cylinder(
            pts,
            noise=NoiseModel(),
            rng=np.random.default_rng(seed),
            optics=optics,
            diameter_range=nominal_diameter_range(SEED003_DIAMETER),
        )
        mode = {-1.0: "thin", 0.0: "weighted", 1.0: "first"}[fit.extra["edge_mode_first"]]
        aics = ", ".join(f"{k[4:]} {v:.1f}" for k, v in fit.extra.items() if k.startswith("aic_"))
        print(
            f"  ideal sweep {seed}: {mode:8s} wins (AIC {aics}), diameter error"
            f" {1e3 * (fit.diameter - SEED003_DIAMETER):+6.2f} mm, {time.perf_counter() - t0:5.1f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
