"""The spot scale from sphere limbs (issue 12; lrms/calibration/optics.py) with the limb echo's
spot an endless Gaussian (``extent=inf``, calibrations before the disc cut) and cut to the disc of
``BeamOptics.extent`` = 1.5 spot radii (as the simulator's spot and the footprint fit's
energy-weighted family): three spheres before a wall, a step-and-scan sweep by the nominal rig
(``sim.scene.spot_spheres.spheres_sweep``, the scene of tests/core/test_calibration_optics.py), the
rig and the spheres' centres known, so only the limb-echo model differs.

    python -m bench.bench_spot_scale_disc [--scales 1.0 1.6] [--sub-rays 32 128] [--seeds 1]
        [--step 0.5] [--noisy]

Prints per case: the true scale, both estimates (relative error, u, limb beams, rms residual).
"""

from __future__ import annotations

import argparse
import math
import time

from lrms.calibration.optics import estimate_spot_scale
from lrms.kinematics import RigModel
from sim.scene import LMS1xxSensor
from sim.scene.lms1xx import Footprint
from sim.scene.spot_spheres import spheres_sweep, spheres_truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 1.6])
    ap.add_argument("--sub-rays", type=int, nargs="+", default=[32, 128])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1])
    ap.add_argument("--step", type=float, default=0.5, help="motor step, deg")
    ap.add_argument("--noisy", action="store_true", help="the LMS1xx's range and angle noise (default: none)")
    a = ap.parse_args(argv)
    quiet = {} if a.noisy else dict(sigma_typical=0.0, sigma_max=0.0, spread_noise=0.0, sigma_alpha=0.0, sigma_beta=0.0)
    m = RigModel()
    spheres = spheres_truth()
    for sub in a.sub_rays:
        for scale in a.scales:
            for seed in a.seeds:
                t0 = time.perf_counter()
                fp = Footprint(exit_diameter_m=0.008 * scale, divergence_rad=0.015 * scale, sub_rays=sub)
                obs, _ = spheres_sweep(LMS1xxSensor(footprint=fp, **quiet), seed, a.step)  # type: ignore[arg-type]
                o, d = m.rays(obs.alpha, obs.beta)
                rng = m.geometric_range(obs.l)
                row = [f"sub_rays {sub:4d} true {scale:.2f} seed {seed}"]
                for name, ext in (("endless", math.inf), ("disc 1.5", 1.5)):
                    g = estimate_spot_scale(o, d, rng, spheres, 0.008, 0.015, 0.25, 0.012, extent=ext)
                    row.append(
                        f"{name}: none"
                        if g is None
                        else f"{name}: s {g.scale:.4f} ({(g.scale / scale - 1) * 100:+.2f} %, u {g.u:.3f}, "
                        f"{g.beams} beams, rms {g.rms_m * 1e3:.2f} mm)"
                    )
                print(" | ".join(row), f"[{time.perf_counter() - t0:.0f} s]", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
