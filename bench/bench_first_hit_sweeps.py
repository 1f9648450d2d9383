"""The footprint fit sweep by sweep, with its diagnostics: the clouds of one
``bench_sensor_model`` case rebuilt (the same scene cast, sensor, seed and draws, region of
interest), each fitted as that bench fits it (``optics=BeamOptics()``, nominal diameter +-10 %,
the bench's per-sweep fit seed), one line per sweep: the error, the bench's u (the fit's, the
spot-size and the model-choice rows in quadrature), the family won, the threshold tau, the
criteria of the thin beam and both families, the thin-beam diameter and the time.

For looking into single sweeps of a coverage run (docs/cylinder.md, section 7, round 4)::

    PYTHONPATH=. OMP_NUM_THREADS=1 python -m bench.bench_first_hit_sweeps --edge 0.1:first --seed 2 \
        --sweeps 20 --cache /work/runs/cache [--only 13,14]

``--cache`` as in ``bench_sensor_model`` (the 128-sub-ray cast of ``seed003-room``; cast afresh
and written there when missing). Run the same command on another tree for a before / after.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from bench import bench_sensor_model as bsm
from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics, fit_cylinder, nominal_diameter_range
from lrms.errors import LrmsError
from lrms.uncertainty import gum_interval
from sim.scene import Footprint, LMS1xxSensor
from sim.scene.library import SEED003_AXIS_POINT


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--edge", default="0.1:first", help="THR:MODE of the simulated receiver (first or weighted)")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--sweeps", type=int, default=20)
    ap.add_argument("--only", default=None, help="comma list of sweep numbers (1-based) to fit; the rest are drawn")
    ap.add_argument("--cache", default=None)
    args = ap.parse_args(argv)
    thr, mode = float(args.edge.split(":")[0]), args.edge.split(":")[1]
    if mode not in ("first", "weighted") or not 0.0 < thr < 1.0:
        ap.error("--edge takes THR:MODE with 0 < THR < 1 and MODE first or weighted")
    only = {int(x) for x in args.only.split(",")} if args.only else None
    # a cache written by ``python -m bench.bench_sensor_model`` pickled its Geometry as __main__'s
    sys.modules["__main__"].Geometry = bsm.Geometry  # type: ignore[attr-defined]
    sensor = LMS1xxSensor(footprint=Footprint())
    diameter = 0.1375
    g = bsm.cached_geometry(args.cache, "seed003-room", diameter, SEED003_AXIS_POINT[1], sensor)
    draw = bsm.lms_draw(g, dataclasses.replace(sensor, edge_threshold=thr, range_mode=mode))
    rng = np.random.default_rng(args.seed)
    errs: list[float] = []
    us: list[float] = []
    failed = 0
    for k in range(1, args.sweeps + 1):
        ranges, valid = draw(rng)
        pts = g.origins[valid] + ranges[valid, None] * g.dirs[valid]
        pts = pts[np.all((pts >= g.roi_lo) & (pts <= g.roi_hi), axis=1)]
        fit_seed = int(rng.integers(1 << 31))
        if only is not None and k not in only:
            continue
        t0 = time.perf_counter()
        try:
            fit = fit_cylinder(
                pts,
                noise=NoiseModel(),
                rng=np.random.default_rng(fit_seed),
                optics=BeamOptics(),
                diameter_range=nominal_diameter_range(diameter),
            )
        except LrmsError as exc:
            failed += 1
            print(f"sweep {k:3d}: failed: {exc}", flush=True)
            continue
        x = fit.extra
        u = float(
            np.sqrt(
                gum_interval(fit).std ** 2
                + sum(x.get(k, 0.0) ** 2 for k in ("edge_model_u_m", "edge_family_u_m", "footprint_bias_u_m"))
            )
        )
        e = fit.diameter - diameter
        errs.append(e)
        us.append(u)
        won = {1.0: "first", 0.0: "weighted"}.get(x.get("edge_mode_first", -1.0), "thin")
        print(
            f"sweep {k:3d}: error {1e3 * e:+7.2f} mm, u {1e3 * u:5.2f} mm, {won:8s}"
            f" tau {x.get('edge_threshold', np.nan):.3f},"
            f" crit thin {x.get('aic_thin', np.nan):.1f} weighted {x.get('aic_weighted', np.nan):.1f}"
            f" first {x.get('aic_first', np.nan):.1f}, thin beam {1e3 * (x['thin_beam_diameter_m'] - diameter):+.2f} mm"
            f"  ({time.perf_counter() - t0:.1f} s)",
            flush=True,
        )
    if errs:
        ee, uu = 1e3 * np.array(errs), 1e3 * np.array(us)
        sd = float(ee.std(ddof=1)) if ee.size > 1 else float("nan")
        print(
            f"{ee.size} fitted, {failed} failed: mean error {ee.mean():+.2f} +- {sd / np.sqrt(ee.size):.2f} mm,"
            f" std {sd:.2f} mm, mean u {uu.mean():.2f} mm, |e| <= 2u {int(np.sum(np.abs(ee) <= 2 * uu))} of"
            f" {ee.size + failed}"
        )


if __name__ == "__main__":
    main()
