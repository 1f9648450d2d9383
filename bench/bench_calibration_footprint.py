"""Rig calibration under the LMS1xx beam footprint (issue 12): the room with large spheres swept by
miscalibrated rigs with the footprint sensor, calibrated with the thin-beam adjustment and with the
footprint-aware one (``CalibrationOptions(optics=BeamOptics())``: limb / edge beams censored,
sphere beams' curvature bias corrected, spot scale estimated with the calibrated rig).

    python -m bench.bench_calibration_footprint [--runs 3] [--seed 0] [--speed 40] [--sub-rays 32]
        [--plane-points 5000] [--spot-scale 1.0] [--mode both|thin|optics]

Prints per run and parameter: estimate - truth, reported std, |error| / std; and the spot scale.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.bench_calibration import draw_rig, layout
from lrms.calibration import AdjustOptions, CalibrationOptions, Observations, calibrate
from lrms.cylinder import BeamOptics
from lrms.kinematics import RigCalibration, RigModel
from sim.scene import LMS1xxSensor, continuous_sweep_cloud
from sim.scene.lms1xx import Footprint

D = np.deg2rad


def footprint_sweep(rig: RigModel, speed_deg_s: float, seed: int, sub_rays: int, scale: float) -> Observations:
    """A two-face sweep (-170..170 deg) of ``room-spheres-large`` by ``rig`` with the LMS1xx footprint sensor."""
    scene, _ = layout("network-large", 3e-5)
    cal = RigCalibration(model=rig)
    fp = Footprint(exit_diameter_m=0.008 * scale, divergence_rad=0.015 * scale, sub_rays=sub_rays)
    _, s = continuous_sweep_cloud(
        scene, cal, LMS1xxSensor(footprint=fp), -D(170), D(170), D(speed_deg_s), rng=np.random.default_rng(seed)
    )
    v = s.valid
    return Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed", type=float, default=40.0, help="sweep speed, deg/s (25 Hz scans)")
    ap.add_argument("--sub-rays", type=int, default=32)
    ap.add_argument("--plane-points", type=int, default=5000)
    ap.add_argument("--spot-scale", type=float, default=1.0, help="true spot size / nominal")
    ap.add_argument("--mode", choices=("both", "thin", "optics"), default="both")
    args = ap.parse_args(argv)
    _, art = layout("network-large", 3e-5)
    rng = np.random.default_rng(args.seed)
    modes = ("thin", "optics") if args.mode == "both" else (args.mode,)
    for run in range(args.runs):
        truth = draw_rig(rng)
        t0 = time.process_time()
        obs = footprint_sweep(truth, args.speed, args.seed * 1000 + run, args.sub_rays, args.spot_scale)
        print(f"run {run}: {len(obs)} beams, simulated in {time.process_time() - t0:.0f} s CPU")
        for mode in modes:
            t0 = time.process_time()
            opts = CalibrationOptions(
                adjust=AdjustOptions(max_plane_points=args.plane_points),
                optics=BeamOptics() if mode == "optics" else None,
            )
            res = calibrate([obs], art, options=opts)
            std = dict(zip(RigModel.NAMES, np.sqrt(np.clip(np.diag(res.covariance), 0, None)), strict=True))
            est, tv = res.model.vector(), truth.canonical().vector()
            cells = []
            for n in res.estimated:
                j = RigModel.NAMES.index(n)
                unit, f = RigModel.UNITS[n]
                e = est[j] - tv[j]
                cells.append(f"{n} {e * f:+.3f}+-{std[n] * f:.3f}{unit} ({abs(e) / max(std[n], 1e-300):.1f})")
            print(f"  {mode:6s} ({time.process_time() - t0:.0f} s CPU): " + "; ".join(cells))
            if res.optics is not None:
                print(f"         spot scale {res.optics['spot_scale']:.3f} +- {res.optics['spot_scale_u']:.3f}"
                      f" (true {args.spot_scale})")  # fmt: skip
            censored = getattr(res, "censored", None)
            if censored:
                print(f"         censored beams: {censored}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
