"""Monte Carlo of the line-of-sight fit's bias with and without the miss rows in its second-order
bias correction (docs/cylinder.md, "Another local minimum, another bias correction").

Offline sweeps of the default simulated rig (``seed003``, ideal sensor, each beam at its true motor
angle, 20 deg/s; the harness of ``tests/service/test_fit_type_a.py``), one noise seed per sweep,
fitted by ``service.fitting.fit``; at its bias-correction step the grazing-weighted fit and its
beams are taken, and each variant's correction is computed on that same fit. Prints per variant the
corrected diameter's mean error +- its standard error and RMS(error / std_m). One process, no
threads: ``python -m bench.bias_miss_rows --sweep short --seeds 1000:3280`` (2280 sweeps took about
10 min on the shared machine), ``--sweep full --seeds 3:323``.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import erf

import lrms.cylinder.pipeline as pipeline
from lrms.cylinder import bias
from lrms.cylinder.lm import LosProblem
from lrms.cylinder.model import Rays
from lrms.cylinder.refine import CylinderFit, _covariance
from service import fitting
from service.config import load_config
from service.models import MeasurementRequest
from service.sweep import MappedSweep
from sim.scene import get_scene, make_sensor
from sim.scene.sensor import continuous_sweep_cloud

FloatArray = NDArray[np.float64]
TRUE_D = 0.1375
SPEED = math.radians(20.0)
SWEEPS = {"short": (-5.0, 20.0), "full": (-20.0, 70.0)}
#: name: (miss rows in A, weight of the miss rows' terms in the sum, miss rows' weight in A erf-scaled)
VARIANTS: dict[str, tuple[bool, str, bool]] = {
    "before (in A and sum)": (True, "one", False),
    "(1) in neither": (False, "zero", False),
    "adopted (in A only)": (True, "zero", False),
    "in A, terms x erf": (True, "erf", False),
    "A and terms x erf": (True, "erf", True),
}


def offline_sweep(seed: int, lo_deg: float, hi_deg: float) -> MappedSweep:
    cal = load_config(None).calibration
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0.0, SPEED / 25.0)
    start, stop = float(cal.motor_angle(math.radians(lo_deg))), float(cal.motor_angle(math.radians(hi_deg)))
    _, s = continuous_sweep_cloud(get_scene("seed003"), cal, make_sensor("ideal"), start + phase, stop, SPEED, rng)
    valid = s.valid
    ranges = s.ranges[valid]
    alpha = cal.alpha(np.broadcast_to(s.device_angle, valid.shape)[valid])
    beta = cal.beta(s.motor_angle[valid])
    scans = np.broadcast_to(np.arange(valid.shape[0])[:, None], valid.shape)[valid]
    speed = np.full(ranges.shape, SPEED)
    return MappedSweep(
        points=cal.rig.forward(ranges, alpha, beta, speed),
        ranges=ranges,
        alpha=alpha,
        beta=beta,
        scan_index=scans.astype(np.int64),
        beam_time_s=np.zeros(ranges.shape),
        t_ref_ns=0,
        beams_total=int(valid.size),
        beams_no_echo=int(np.count_nonzero(~valid)),
        beams_out_of_range=0,
        beams_without_motor=0,
        beams_outside_sweep=0,
        motor_speed=speed,
        rig=cal.rig,
    )


def corrections(fit: CylinderFit, rays: Rays) -> dict[str, float]:
    """Each variant's correction of the diameter (m) at ``fit`` (its inlier beams ``rays``)."""
    frame = bias._fit_frame(fit)
    sig = bias.grazing_sigmas(fit.cylinder, rays, fit.extra.get("grazing_sigma_m", 0.0))
    lam, vec = np.linalg.eigh(0.5 * (fit.covariance + fit.covariance.T))
    steps = (np.sqrt(3.0 * np.maximum(lam, 0.0)) * vec).T
    problem = LosProblem(Rays(rays.origins, rays.dirs, rays.ranges, np.asarray(sig), rays.sigma_perp))

    def res(th: FloatArray) -> FloatArray:
        return problem.linearise(frame.cylinder(th), jacobian=False).residuals

    centre = res(np.zeros(5))
    second = np.zeros_like(centre)
    for step in steps:
        second += (res(step) + res(-step) - 2.0 * centre) / 3.0
    n = rays.ranges.shape[0]
    jac = problem.jacobian(fit.cylinder, frame=(frame.e1, frame.e2))
    w = erf(np.abs(centre[n:]) / math.sqrt(2.0))
    out = {}
    for name, (in_a, terms, a_erf) in VARIANTS.items():
        ja = jac.copy()
        ja[n:] *= (w[:, None] if a_erf else 1.0) if in_a else 0.0
        jt = jac.copy()
        jt[n:] *= {"one": 1.0, "zero": 0.0, "erf": w[:, None]}[terms]
        out[name] = float(2.0 * (-0.5 * (_covariance(ja) @ (jt.T @ second)))[4])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--sweep", choices=sorted(SWEEPS), default="short")
    ap.add_argument("--seeds", default="1000:1200", help="first:last (exclusive)")
    args = ap.parse_args()
    first, last = (int(x) for x in args.seeds.split(":"))
    captured: dict[str, Any] = {}
    original = bias.bias_corrected

    def capture(fit: CylinderFit, rays: Rays) -> CylinderFit:
        captured["fit"], captured["rays"] = fit, rays
        return original(fit, rays)

    vars(pipeline)["bias_corrected"] = capture  # the pipeline calls it by this name
    config = load_config(None)
    raw, u, corr = [], [], []
    for seed in range(first, last):
        captured.clear()
        result = fitting.fit(offline_sweep(seed, *SWEEPS[args.sweep]), MeasurementRequest(target="cylinder"), config)
        if "fit" not in captured:
            continue
        raw.append(captured["fit"].diameter - TRUE_D)
        u.append(result["uncertainty"]["std_m"])
        corr.append(corrections(captured["fit"], captured["rays"]))
    r, s = np.array(raw), np.array(u)
    print(f"{args.sweep} sweeps: {r.size} fits of seeds {first}..{last - 1}")
    rows = [("none", np.zeros(r.size))] + [(k, np.array([c[k] for c in corr])) for k in VARIANTS]
    for name, c in rows:
        e = r - c
        se = e.std(ddof=1) / math.sqrt(e.size)
        rms = math.sqrt(float(np.mean((e / s) ** 2)))
        print(f"  {name:24s} mean error {1e3 * e.mean():+.3f} +- {1e3 * se:.3f} mm  RMS(err/u) {rms:.3f}")


if __name__ == "__main__":
    main()
