"""Seed 003 reproduction: the simulated cylinder, its critical-point interval, and coverage.

Geometry (seed 003, Section 4.2): axis (0, 0, 1) through P(0.28, 2.53, 0.51), radius 0.138 m,
bottom C0(0.28, 2.53, -0.1); rig at the origin with p = 0.1 m; sigma_l^2 = 136.11 mm^2. The
seed does not give the height: we take P as the middle of the part, so the top is at
z = 1.12 m. Two point sets: 567 points spread uniformly over the visible surface (21 angles x 27
heights, as the seed's "567 densely packed points"), and a full LRMS sweep (LMS100 0.25 deg beam
grid, motor step 0.25 deg) ray-cast onto the part.

Run: ``.venv/bin/python -m bench.seed003_reproduction [--scans 1000] [--mc 200]``; sections with
``--only intervals bias coverage accuracy attainable`` (``attainable`` is not in the default set).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrms import kinematics
from lrms.budget import SensorErrors
from lrms.covariance import NoiseModel
from lrms.cylinder import Cylinder, Rays, rays_from_points
from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]

AXIS_POINT = np.array([0.28, 2.53, 0.51])
BOTTOM = np.array([0.28, 2.53, -0.10])
RADIUS = 0.138
TOP_Z = 2 * AXIS_POINT[2] - BOTTOM[2]
P = 0.1
SEED_HALF_WIDTH_MM = 6.36


def seed_cylinder(radius: float = RADIUS) -> Cylinder:
    return Cylinder(AXIS_POINT, np.array([0.0, 0.0, 1.0]), radius)


def visible_surface_points(
    n_theta: int = 21, n_z: int = 27, radius: float = RADIUS, margin: float = 0.02
) -> FloatArray:
    """Points spread uniformly (angle x height) over the part of the surface the rig sees."""
    c = AXIS_POINT[:2]
    to_rig = -c / np.linalg.norm(c)
    half = np.arccos(radius / np.linalg.norm(c))  # tangent beams from the origin
    phi0 = np.arctan2(to_rig[1], to_rig[0])
    th = phi0 + np.linspace(-half, half, n_theta + 2)[1:-1]
    z = np.linspace(BOTTOM[2] + margin, TOP_Z - margin, n_z)
    tt, zz = np.meshgrid(th, z, indexing="ij")
    pts = np.stack([c[0] + radius * np.cos(tt), c[1] + radius * np.sin(tt), zz], axis=-1)
    return np.asarray(pts.reshape(-1, 3), dtype=np.float64)


def sweep_points(
    step_alpha_deg: float = 0.25, step_beta_deg: float = 0.25, radius: float = RADIUS, p: float = P
) -> FloatArray:
    """Noise-free hits of a full sweep on the finite seed cylinder (no other objects)."""
    # beam grid restricted to the angular window that can see the part
    alpha = np.deg2rad(np.arange(0.0, 30.0, step_alpha_deg))
    beta = np.deg2rad(np.arange(-30.0, 90.0, step_beta_deg))
    aa, bb = np.meshgrid(alpha, beta, indexing="ij")
    o, d = kinematics.beam_rays(aa.ravel(), bb.ravel(), p)
    cyl = seed_cylinder(radius)
    t, gap = cyl.ray_range(o, d)
    pts = o + t[:, None] * d
    ok = (gap == 0) & (t > 0) & (pts[:, 2] >= BOTTOM[2]) & (pts[:, 2] <= TOP_Z)
    return np.asarray(pts[ok], dtype=np.float64)


def noisy_scan(truth: FloatArray, noise: NoiseModel, rng: np.random.Generator, p: float = P) -> tuple[FloatArray, Rays]:
    """Observe true points through the rig: perturb (l, alpha, beta) (Eq. 5), map by Eq. 1."""
    l, a, b = kinematics.inverse(truth, p)
    ln, an, bn = noise.perturb(l, a, b, rng)
    pts = kinematics.forward(ln, an, bn, p)
    return pts, rays_from_points(pts, p, noise)


def lrms_sweep(
    rng: np.random.Generator,
    clutter: float = 0.1,
    motor_step_deg: float = 0.25,
    scene_name: str = "seed003",
    crop: bool = True,
    angle_noise: bool = True,
) -> tuple[FloatArray, Cylinder, Rays]:
    """A noisy LRMS sweep ray-cast with ``sim.scene`` (helper B's scene, LMS100 sensor model).

    The part is the scene's 137.5 mm cylinder on its table (scene "seed003": with the room and its
    clutter objects, a box and a bottle on the table; "seed003-bare": part and table only); the
    motor turns from -35 to 75 deg
    in ``motor_step_deg``. With ``crop`` the cloud is cut to a box around the table (as an
    operator's region of interest would), then ``clutter`` times as many uniform random points
    are added in that box where the part does not hide them (not inside or behind it). Returns
    the rig-frame cloud (shuffled), the true cylinder, and the nominal beams that returned an
    echo from the cylinder (for the Cramer-Rao bound). ``angle_noise=False`` switches the
    sensor's angle noise off (every sweep then has the same beams).
    """
    from lrms.kinematics import RigCalibration
    from sim.scene import (
        SEED003_AXIS_DIRECTION,
        SEED003_AXIS_POINT,
        SEED003_DIAMETER,
        SEED003_HEIGHT,
        SensorModel,
        cast_beams,
        get_scene,
        lms1xx_device_angles,
    )

    scene = get_scene(scene_name)
    cal = RigCalibration()
    dev = lms1xx_device_angles(0.25)
    dev = dev[(dev > np.deg2rad(60)) & (dev < np.deg2rad(120))]
    mot = np.deg2rad(np.arange(-35.0, 75.0, motor_step_deg))[:, None]
    sensor = SensorModel() if angle_noise else SensorModel(sigma_alpha=0.0, sigma_beta=0.0)
    samples = cast_beams(scene, cal, sensor, dev, mot, rng)
    pts = samples.points(cal)
    part_index = [o.name for o in scene.objects].index("cylinder")
    on_part = samples.valid & (samples.index == part_index)
    o, d = cal.world_rays(np.broadcast_to(dev, on_part.shape)[on_part], np.broadcast_to(mot, on_part.shape)[on_part])
    part_rays = Rays(o, d, samples.ranges[on_part], np.full(o.shape[0], SensorModel().sigma_l), np.ones(o.shape[0]))
    c0 = np.asarray(SEED003_AXIS_POINT)
    lo = c0 + np.array([-0.6, -0.4, -0.05])
    hi = c0 + np.array([0.6, 0.4, 0.9])
    if crop:
        pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    part = Cylinder(c0, np.asarray(SEED003_AXIS_DIRECTION, dtype=float), SEED003_DIAMETER / 2)
    n_clutter = round(clutter * pts.shape[0])
    if n_clutter:
        junk = np.empty((0, 3))
        while junk.shape[0] < n_clutter:  # physical clutter: not inside or behind the part
            cand = rng.uniform(lo, hi, (2 * n_clutter, 3))
            r = rays_from_points(cand, cal.p)
            t, gap = part.ray_range(r.origins, r.dirs)
            hit_z = (r.origins + t[:, None] * r.dirs)[:, 2]
            occluded = (gap == 0) & (t < r.ranges) & (hit_z >= c0[2]) & (hit_z <= c0[2] + SEED003_HEIGHT)
            junk = np.vstack([junk, cand[~occluded]])
        pts = np.vstack([pts, junk[:n_clutter]])
    pts = pts[rng.permutation(pts.shape[0])]
    return pts, part, part_rays


@dataclass
class Coverage:
    name: str
    claimed: str
    inside: int
    total: int

    def line(self) -> str:
        share = self.inside / self.total
        se = np.sqrt(max(share * (1 - share), 1e-12) / self.total)
        return f"  {self.name:<52s} claims {self.claimed:<12s} measured {100 * share:6.2f} % +- {100 * se:.2f} %"


def section_intervals() -> None:
    from lrms.uncertainty import critical_point_interval

    noise = NoiseModel()
    print(f"== critical-point interval (Eq. 8-12, 25th percentile), seed's result: +-{SEED_HALF_WIDTH_MM:.2f} mm")
    for radius, label in ((RADIUS, "r = 0.138 m (seed Sect. 4.2)"), (0.1375 / 2, "d = 137.5 mm (CMM value)")):
        cyl = seed_cylinder(radius)
        sets = (
            ("567 surface points", visible_surface_points(radius=radius)),
            ("full sweep 0.25x0.6 deg", sweep_points(radius=radius, step_beta_deg=0.6)),
        )
        for name, truth in sets:
            for k in (1.0, 2.0, 3.0):
                ci = critical_point_interval(cyl, truth, noise=noise, k=k, p=P)
                print(
                    f"  {label:<29s} {name:<24s} n={truth.shape[0]:5d} k={k:.0f}: r_ce = {1e3 * ci.r_ce:6.2f} mm,"
                    f" d +- {1e3 * ci.half_width:6.2f} mm"
                )


def section_bias(n_scans: int, rng: np.random.Generator) -> None:
    from lrms.cylinder import fit_cylinder

    noise = NoiseModel()
    print(f"\n== fit bias on the seed's set-up, {n_scans} noisy full sweeps each (analytic ray cast, no clutter)")
    for radius in (0.1375 / 2, RADIUS):
        truth = sweep_points(radius=radius, step_beta_deg=0.6)
        cyl = seed_cylinder(radius)
        d_los, d_orth = np.empty(n_scans), np.empty(n_scans)
        for s in range(n_scans):
            pts, rays = noisy_scan(truth, noise, rng)
            d_los[s] = fit_cylinder(pts, rays=rays, noise=noise, initial=cyl).diameter
            d_orth[s] = fit_cylinder(pts, line_of_sight=False, noise=noise, initial=cyl).diameter
        for name, d in (("line of sight", d_los), ("orthogonal", d_orth)):
            err = 1e3 * (d - cyl.diameter)
            print(
                f"  d = {2e3 * radius:6.1f} mm, {truth.shape[0]:5d} points, {name:<14s}:"
                f" mean error {err.mean():+7.3f} mm"
                f" +- {err.std(ddof=1) / np.sqrt(n_scans):.3f} (s.e.), std {err.std(ddof=1):.3f} mm"
            )


#: Motor speed of the full-sweep coverage scans: 0.6 deg per scan at 25 Hz.
SWEEP_SPEED = float(np.deg2rad(0.6 * 25.0))


def systematic_scan(
    truth: FloatArray, noise: NoiseModel, errors: SensorErrors, rng: np.random.Generator, p: float = P
) -> tuple[FloatArray, Rays]:
    """:func:`noisy_scan` with one draw of ``errors``' systematic effects (range offset, scale and
    drift, angle zeros, per-scan motor-angle errors) from their distributions, as a real unit
    would carry them."""
    from lrms.budget import BeamGeometry, ReplicaSystematics

    l, a, b = kinematics.inverse(truth, p)
    sysm = ReplicaSystematics(errors, BeamGeometry(a, b, p, SWEEP_SPEED))
    lt, at, bt = (v[0] for v in sysm.perturb(l, a, b, 1, rng))
    ln, an, bn = noise.perturb(lt, at, bt, rng)
    pts = kinematics.forward(ln, an, bn, p)
    return pts, rays_from_points(pts, p, noise)


def section_coverage(
    n_scans: int, n_mc: int, k: float, points: str, rng: np.random.Generator, systematics: bool = False
) -> None:
    """Coverage of the three intervals and of the budget's ``d +- U`` (k = 2). Without
    ``systematics`` the scans carry the seed's noise only and the budget is built with no
    systematic inputs (:meth:`SensorErrors.none`); with it every scan carries one draw of an
    uncalibrated LMS1xx's systematic effects (:class:`SensorErrors` defaults) and the budget and
    the Monte Carlo replicas carry the same distributions. The Monte Carlo interval is computed
    twice on every scan, with the replicas' multi-start and without it (the interval before)."""
    from lrms.budget import BeamGeometry, cylinder_budget, replica_systematics
    from lrms.crb import cylinder_crb
    from lrms.cylinder import fit_cylinder
    from lrms.uncertainty import critical_point_interval, gum_interval, monte_carlo_interval

    noise = NoiseModel()
    cyl = seed_cylinder()
    d_true = cyl.diameter
    truth = visible_surface_points() if points == "567" else sweep_points(step_beta_deg=0.6)
    errors = SensorErrors() if systematics else SensorErrors.none()
    print(
        f"\n== coverage over {n_scans} simulated scans of {truth.shape[0]} points ({points}), r = 0.138 m, k = {k:g}, "
        f"systematic effects {'drawn (uncalibrated LMS1xx)' if systematics else 'none'}"
    )
    t0 = time.perf_counter()
    ci_truth = critical_point_interval(cyl, truth, noise=noise, k=k, p=P)
    d_los, d_orth, u_gum, u_c, w_mc, w_mc1 = (np.empty(n_scans) for _ in range(6))
    in_a_seed = in_a_own = in_b = in_c = in_c1 = in_a_orth = in_u = 0
    for s in range(n_scans):
        pts, rays = systematic_scan(truth, noise, errors, rng) if systematics else noisy_scan(truth, noise, rng)
        fit = fit_cylinder(pts, rays=rays, noise=noise, initial=cyl)
        orth = fit_cylinder(pts, line_of_sight=False, noise=noise, initial=cyl)
        d_los[s], d_orth[s] = fit.diameter, orth.diameter
        in_a_seed += ci_truth.d_min <= fit.diameter <= ci_truth.d_max
        in_a_orth += ci_truth.d_min <= orth.diameter <= ci_truth.d_max
        inl = rays.subset(fit.inliers)
        own = critical_point_interval(fit.cylinder, rays=inl, noise=noise, k=k, p=P)
        in_a_own += own.d_min <= d_true <= own.d_max
        g = gum_interval(fit)
        u_gum[s] = g.std
        in_b += g.low <= d_true <= g.high
        _, al, be = kinematics.inverse(pts[fit.inliers], P)
        beams = BeamGeometry(al, be, P, SWEEP_SPEED)
        budget = cylinder_budget(fit, inl, beams, errors=errors, noise=noise)
        u_c[s] = budget.combined
        in_u += abs(fit.diameter - d_true) <= budget.expanded
        if n_mc > 0:
            sysm = replica_systematics(budget, errors, beams)
            mc = monte_carlo_interval(fit, inl, noise=noise, n=n_mc, rng=rng, p=P, systematics=sysm)
            w_mc[s] = mc.high - mc.low
            in_c += mc.low <= d_true <= mc.high
            mc1 = monte_carlo_interval(fit, inl, noise=noise, n=n_mc, rng=rng, p=P, systematics=sysm, multistart=False)
            w_mc1[s] = mc1.high - mc1.low
            in_c1 += mc1.low <= d_true <= mc1.high
    dt = time.perf_counter() - t0
    n = n_scans
    rays_true = rays_from_points(truth, P, noise)
    crb = cylinder_crb(cyl, rays_true.origins, rays_true.dirs, noise.sigma_l).std_diameter
    print(f"  critical-point interval from the true geometry: d +- {1e3 * ci_truth.half_width:.2f} mm")
    for name, d in (("line-of-sight fit", d_los), ("orthogonal fit", d_orth)):
        print(f"  {name:<18s}: mean error {1e3 * (d.mean() - d_true):+.3f} mm, std {1e3 * d.std(ddof=1):.3f} mm")
    print(
        f"  Cramer-Rao bound on std(d): {1e3 * crb:.3f} mm; mean GUM u(d): {1e3 * u_gum.mean():.3f} mm; "
        f"mean budget u_c: {1e3 * u_c.mean():.3f} mm"
    )
    rows = [
        Coverage("(a) critical point from truth: LOS fits inside", "'almost all'", in_a_seed, n),
        Coverage("(a) critical point from truth: orthogonal fits inside", "'almost all'", in_a_orth, n),
        Coverage("(a) critical point from each fit: covers truth", "'almost all'", in_a_own, n),
        Coverage("(b) GUM d +- 2u (fit covariance): covers truth", "95.45 %", in_b, n),
        Coverage("budget d +- U (U = 2 u_c): covers truth", "~95 %", in_u, n),
    ]
    if n_mc > 0:
        rows.append(Coverage(f"(c) Monte Carlo, {n_mc} replicas, multi-start: covers truth", "95 %", in_c, n))
        rows.append(Coverage(f"(c) Monte Carlo, {n_mc} replicas, one solve (before)", "95 %", in_c1, n))
    for c in rows:
        print(c.line())
    if n_mc > 0:
        print(
            f"  mean Monte Carlo 95 % width {1e3 * w_mc.mean():.3f} mm (one solve: {1e3 * w_mc1.mean():.3f} mm) "
            f"vs GUM 4u {4e3 * u_gum.mean():.3f} mm, budget 2U {4e3 * u_c.mean():.3f} mm"
        )
    print(f"  ({dt:.0f} s)")


def section_accuracy(
    n_sweeps: int,
    rng: np.random.Generator,
    scene_name: str = "seed003",
    clutter: float = 0.1,
    grazing_sigma: float | None = None,
    bias_correction: bool = True,
) -> None:
    """Accuracy of the full pipeline against the Cramer-Rao bound, with the diagnostics that
    locate the excess: the bound over the fit's own inliers, the maximum-likelihood fit of the
    true part echoes started at the truth ("oracle", the same beams as the bound), and the fit's
    inliers that are not part echoes (count and mean whitened range residual)."""
    from scipy.spatial import cKDTree

    from lrms.crb import cylinder_crb
    from lrms.cylinder import GRAZING_SIGMA, DetectOptions, bias_corrected, fit_cylinder, refine_cylinder

    noise = NoiseModel()
    g_sigma = GRAZING_SIGMA if grazing_sigma is None else grazing_sigma
    options = DetectOptions(
        threshold=max(0.03, 2.5 * noise.sigma_l), grazing_sigma=g_sigma, bias_correction=bias_correction
    )
    print(
        f"\n== accuracy: {n_sweeps} ray-cast LRMS sweeps (sim.scene {scene_name!r}: 137.5 mm part, table,"
        f" + {100 * clutter:g} % uniform clutter); fit weights' lateral term {1e3 * g_sigma:g} mm;"
        f" second-order bias correction {'on' if bias_correction else 'off'}"
    )
    t0 = time.perf_counter()
    err, oracle, crb, crb_inl, n_in, n_pts, fails = [], [], [], [], [], [], 0
    extra_n, extra_res, dropped, corr, oracle_corr = [], [], [], [], []
    for _ in range(n_sweeps):
        pts, part, part_rays = lrms_sweep(rng, clutter=clutter, scene_name=scene_name)
        try:
            fit = fit_cylinder(pts, noise=noise, rng=rng, options=options)
        except LrmsError as exc:  # counted and reported
            fails += 1
            print(f"  fit failed: {exc}")
            continue
        err.append(fit.diameter - part.diameter)
        corr.append(fit.extra.get("bias_correction_diameter_m", 0.0))
        crb.append(cylinder_crb(part, part_rays.origins, part_rays.dirs, noise.sigma_l).std_diameter)
        inl = rays_from_points(pts[fit.inliers], P, noise)
        crb_inl.append(cylinder_crb(part, inl.origins, inl.dirs, noise.sigma_l).std_diameter)
        true_pts = part_rays.points()
        true_rays = rays_from_points(true_pts, P, noise)
        ml = refine_cylinder(true_pts, part, rays=true_rays, gate=np.inf, max_rounds=1)
        oracle.append(ml.diameter - part.diameter)
        oracle_corr.append(bias_corrected(ml, true_rays).diameter - part.diameter)
        on_part = cKDTree(true_pts).query(pts[fit.inliers])[0] < 1e-6
        t, _ = part.ray_range(inl.origins[~on_part], inl.dirs[~on_part])
        extra_n.append(int(np.count_nonzero(~on_part)))
        extra_res.extend(((inl.ranges[~on_part] - t) / noise.sigma_l).tolist())
        dropped.append(true_pts.shape[0] - int(np.count_nonzero(on_part)))
        n_in.append(fit.n_inliers)
        n_pts.append(pts.shape[0])
    e = 1e3 * np.asarray(err)
    c = 1e3 * float(np.sqrt(np.mean(np.square(crb))))  # rms over sweeps: the bound on the pooled spread
    ci = 1e3 * float(np.sqrt(np.mean(np.square(crb_inl))))
    spread = float(e.std(ddof=1))
    se_ratio = 1.0 / np.sqrt(2.0 * (e.size - 1))  # relative standard error of a std estimate
    print(f"  points per sweep {np.mean(n_pts):.0f}, inliers {np.mean(n_in):.0f}, failures {fails}")
    print(f"  mean diameter error {e.mean():+.4f} mm (s.e. {spread / np.sqrt(e.size):.4f}); goal |mean| <= 0.1 mm")
    print(
        f"  spread (std) {spread:.4f} mm; Cramer-Rao bound {c:.4f} mm; ratio {spread / c:.3f}"
        f" (+- {spread / c * se_ratio:.3f}; goal <= 1.25)"
    )
    if bias_correction:
        u = e + 1e3 * np.asarray(corr)  # the same fits before the correction
        print(
            f"  correction subtracted: mean {1e3 * np.mean(corr):+.4f} mm (std {1e3 * np.std(corr, ddof=1):.4f});"
            f" before it: mean {u.mean():+.4f} mm, spread {u.std(ddof=1):.4f} mm, ratio {u.std(ddof=1) / c:.3f}"
        )
    mad = 1.4826 * float(np.median(np.abs(e - np.median(e))))
    worst = np.sort(np.abs(e))[-3:][::-1]
    print(f"  robust spread (1.4826 MAD) {mad:.4f} mm, ratio {mad / c:.3f}; largest |errors| {np.round(worst, 3)} mm")
    print(f"  bound over the fit's own inliers {ci:.4f} mm (ratio {spread / ci:.3f})")
    o = 1e3 * np.asarray(oracle)
    print(
        f"  oracle (ML on the true part echoes, started at the truth): mean {o.mean():+.4f} mm"
        f" (s.e. {o.std(ddof=1) / np.sqrt(o.size):.4f}), std {o.std(ddof=1):.4f} mm, ratio {o.std(ddof=1) / c:.3f}"
    )
    oc = 1e3 * np.asarray(oracle_corr)
    print(
        f"  oracle with the second-order bias correction: mean {oc.mean():+.4f} mm"
        f" (s.e. {oc.std(ddof=1) / np.sqrt(oc.size):.4f}), std {oc.std(ddof=1):.4f} mm, ratio {oc.std(ddof=1) / c:.3f}"
    )
    xr = np.asarray(extra_res)
    print(
        f"  inliers that are not part echoes: {np.mean(extra_n):.1f} per sweep, mean whitened range residual"
        f" {xr.mean() if xr.size else 0.0:+.2f} ({np.count_nonzero(xr < 0)} in front,"
        f" {np.count_nonzero(xr > 0)} behind);"
        f" part echoes not among the inliers: {np.mean(dropped):.1f} per sweep"
    )
    print(f"  ({time.perf_counter() - t0:.0f} s)")


def section_attainable(n_sweeps: int, rng: np.random.Generator) -> None:
    """Is the bound attainable? The line-of-sight fit of exactly the bound's beams (the true part
    echoes, bare scene, no clutter), started at the truth, with the simulator's ranges and with
    ranges redrawn from the pure model (nominal range + Gaussian sigma_l) on the same beams."""
    from lrms.crb import cylinder_crb
    from lrms.cylinder import refine_cylinder

    noise = NoiseModel()
    print(f"\n== attainability of the bound: {n_sweeps} sweeps, ML on the true part echoes from the truth")
    for angle_noise in (True, False):
        errs: dict[str, list[float]] = {"simulator ranges": [], "pure-model ranges": []}
        crb = []
        for _ in range(n_sweeps):
            _, part, pr = lrms_sweep(rng, clutter=0.0, scene_name="seed003-bare", crop=False, angle_noise=angle_noise)
            crb.append(cylinder_crb(part, pr.origins, pr.dirs, noise.sigma_l).std_diameter)
            t, _ = part.ray_range(pr.origins, pr.dirs)
            model = t + rng.normal(0.0, noise.sigma_l, t.shape)
            for key, l in (("simulator ranges", pr.ranges), ("pure-model ranges", model)):
                pts = pr.origins + l[:, None] * pr.dirs
                fit = refine_cylinder(pts, part, rays=rays_from_points(pts, P, noise), gate=np.inf, max_rounds=1)
                errs[key].append(fit.diameter - part.diameter)
        c = 1e3 * float(np.sqrt(np.mean(np.square(crb))))
        print(f"  sensor angle noise {'on' if angle_noise else 'off'}: bound {c:.4f} mm")
        for key, v in errs.items():
            e = 1e3 * np.asarray(v)
            sd = float(e.std(ddof=1))
            print(
                f"    {key:<18s} mean {e.mean():+.4f} mm (s.e. {sd / np.sqrt(e.size):.4f}), std {sd:.4f} mm,"
                f" ratio {sd / c:.3f} (+- {sd / c / np.sqrt(2.0 * (e.size - 1)):.3f})"
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=int, default=1000, help="simulated scans for the coverage check")
    ap.add_argument("--mc", type=int, default=200, help="Monte Carlo replicas per scan (0: skip interval c)")
    ap.add_argument("--bias-scans", type=int, default=100)
    ap.add_argument("--sweeps", type=int, default=200, help="ray-cast sweeps for the accuracy goal")
    ap.add_argument("--k", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--points", choices=["567", "sweep"], default="567")
    ap.add_argument(
        "--systematics",
        action="store_true",
        help="coverage: every scan carries one draw of an uncalibrated LMS1xx's systematic effects",
    )
    ap.add_argument("--scene", default="seed003", help="sim.scene scene of the accuracy sweeps")
    ap.add_argument("--clutter", type=float, default=0.1, help="share of uniform clutter points (accuracy)")
    ap.add_argument(
        "--grazing-sigma-mm",
        type=float,
        default=None,
        help="lateral term of the fit's weights (accuracy; default lrms.cylinder.GRAZING_SIGMA, 0: plain ML)",
    )
    ap.add_argument(
        "--no-bias-correction",
        action="store_true",
        help="fit without the second-order bias correction (accuracy)",
    )
    ap.add_argument(
        "--only",
        choices=["intervals", "bias", "coverage", "accuracy", "attainable"],
        nargs="*",
        default=None,
        help="sections to run",
    )
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    only = set(args.only or ["intervals", "bias", "coverage", "accuracy"])
    print("Seed 003 reproduction (rig at the origin, p = 0.1 m, sigma_l^2 = 136.11 mm^2)")
    if "intervals" in only:
        section_intervals()
    if "bias" in only:
        section_bias(args.bias_scans, rng)
    if "coverage" in only:
        section_coverage(args.scans, args.mc, args.k, args.points, rng, args.systematics)
    if "accuracy" in only:
        gs = None if args.grazing_sigma_mm is None else 1e-3 * args.grazing_sigma_mm
        section_accuracy(args.sweeps, rng, args.scene, args.clutter, gs, not args.no_bias_correction)
    if "attainable" in only:
        section_attainable(args.sweeps, rng)
    return 0


if __name__ == "__main__":
    sys.exit(main())
