"""Rig calibration bench (issue 12): random miscalibrations, recovered on the simulated room with
spheres, and seed 003's 137.5 mm part measured before and after calibration.

Each run draws a rig within SICK's and a machine shop's tolerances (range offset +-30 mm, scale
+-1000 ppm, optical centre offsets p and q +-5 mm, tilts and zeros +-0.3 deg, motor scale
+-1000 ppm), simulates calibration sweeps of the room with spheres (``--layout``; ideal thin
beam, seed 003's noise: sigma_l = 11.67 mm), calibrates (:func:`lrms.calibration.calibrate`), and
compares every estimated parameter with the truth (in its canonical form: the tilt about the
shaft moved into the motor zero and q; :meth:`lrms.kinematics.RigModel.canonical`).

Then it sweeps seed 003's part (-35..75 deg, 0.2 deg steps, beams 60..120 deg) without noise
(the rig's systematic effect alone: with noise, the two rigs' clouds differ by a noise draw of
the fit, about 0.3 mm) with the same true rig and with an ideal rig, and fits the cylinder by
line of sight three times: ideal rig; miscalibrated rig mapped with the nominal Eq. 1 (before);
mapped with the calibration (after). The rotation about the shaft (motor zero plus tilt about the shaft)
is the rig's pose, not in the cloud: "after" takes it from the truth, as a levelling of the rig
would.

Artefact layouts (``--layout``; docs/calibration.md, "What limits k1 and the motor scale"):

* ``room``: the ``room-spheres`` scene as it is (a 2 m sphere bar from 1.5 to 3.5 m).
* ``long-bar``: the bar's two 0.25 m spheres moved to 1.2 and 5.2 m on one line of sight (a 4 m
  bar running straight away from the rig); everything else as ``room``.
* ``network``: ``room`` with every centre-to-centre distance of the seven spheres known (21
  distances, as a laser tracker or a CMM measures a sphere network), each to ``--u-distance``.
* ``network-large`` (the default): ``network`` in the ``room-spheres-large`` scene, every sphere
  twice the diameter (0.4 and 0.5 m: four times the beams on each).
* ``axis``: the ``room-spheres-axis`` scene (five 0.5 m spheres, 10 known distances), each pose
  looking along its motor shaft at a sphere on that line; its own poses
  (:data:`sim.scene.library.ROOM_AXIS_POSES`) instead of :data:`POSES`. For k1
  (docs/calibration.md, "The axis layout").
* ``hall``: the ``hall-spheres-axis`` scene (a 12 m workshop hall, four 0.5 m spheres, 6 known
  distances), the axis layout's idea with 6.6-9.2 m from each pose to its far sphere on its shaft;
  its own poses (:data:`sim.scene.library.HALL_AXIS_POSES`). For k1 (docs/calibration.md, "The
  hall layout").

``--speed``: the sweeps' motor speed, 20 deg/s (``--speed 10`` for ``hall`` gives twice the sphere
beams: k1's std 11.3 ppm instead of 15.5, but p's reported std came out 1.4x optimistic over 19 rigs,
untraced; docs/calibration.md, "The hall layout: what limits k1").
``--k1-budget``: k1's standard deviation from the final normal matrix, as is and with each group of
observations (a sphere's beams in one sweep, all sphere beams, all plane beams) counted twice and
the diameters' / distances' uncertainties halved or 100x: which data would shrink it.
``--start N``: begin at run N (the rigs of runs 0..N-1 are drawn and skipped), to rerun one rig.

``--sweep-deg`` is the motor span, centred on 0 (180: -90..90; 340: -170..170, where most of
the room is seen twice, from both halves of the 270 deg scan).

``--poses N`` (1-3): one sweep from each of N rig poses (:data:`POSES`: the origin; 3.0 m along
+y turned 180 deg about z and tipped 1 deg; 1.8 m along +x turned 90 deg), adjusted with a
separate unknown pose per sweep (``calibrate(..., poses="separate")``); ``--sweeps`` sweeps from
each pose.

    python -m bench.bench_calibration [--runs 20] [--start 0] [--poses 3] [--speed 20] [--sweeps 1]
        [--plane-points 5000] [--seed 0]
        [--layout room|long-bar|network|network-large|axis|hall] [--sweep-deg 340] [--u-distance 3e-5]
        [--no-part] [--lms1xx] [--resegmentations 4] [--save runs.json] [--k1-budget]
    python -m bench.bench_calibration --combine a.json b.json   # the tables over several --save files

The defaults are the documented design of docs/calibration.md ("k1 over 20 random rigs").

``--resegmentations N``: the calibration re-segments at most N times (1: once, the rule before;
docs/calibration.md, "The axis layout"). Each run prints every sphere's beams kept by the
adjustment / usable (echoes at cos(incidence) >= 0.3, what the adjustment can use) / simulated on
it and every parameter's error / reported std.

``--lms1xx``: also seed 003's part measured with the LMS1xx footprint sensor (noise on) as the
service measures it (:func:`lms_part`), before (nominal mapping, uncalibrated budget) and after
(the calibration's model and its budget row): the diameter error against the reported U.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy import sparse

from lrms.calibration import (
    GOAL,
    AdjustOptions,
    Artefact,
    CalibrationError,
    CalibrationOptions,
    CalibrationResult,
    Observations,
    calibrate,
)
from lrms.calibration.adjust import MIN_COS, Adjustment
from lrms.cylinder import Cylinder, Rays, fit_cylinder
from lrms.kinematics import RigCalibration, RigModel
from sim.scene import (
    SEED003_AXIS_DIRECTION,
    SEED003_AXIS_POINT,
    SEED003_DIAMETER,
    Scene,
    SensorModel,
    Sphere,
    cast_beams,
    continuous_sweep_cloud,
    get_scene,
    lms1xx_device_angles,
)
from sim.scene.library import (
    HALL_AXIS_POSES,
    ROOM_AXIS_POSES,
    ROOM_SPHERE_BAR,
    ROOM_SPHERES,
    ROOM_SPHERES_LARGE_FACTOR,
    hall_axis_artefact,
    room_axis_artefact,
    room_spheres_artefact,
)

D = np.deg2rad


def draw_rig(rng: np.random.Generator) -> RigModel:
    u = rng.uniform
    return RigModel(
        k0=u(-0.03, 0.03), k1=u(-1e-3, 1e-3), p=0.1 + u(-0.005, 0.005), q=u(-0.005, 0.005),
        tilt_x=D(u(-0.3, 0.3)), tilt_y=D(u(-0.3, 0.3)), alpha_zero=D(u(-0.3, 0.3)), beta_zero=D(u(-0.3, 0.3)),
        beta_scale=u(-1e-3, 1e-3),
    )  # fmt: skip


#: ``long-bar``: the bar's spheres (4 and 5) at 1.2 and 5.2 m, 10 deg apart as seen from the rig
#: (on one line of sight the near sphere would hide the far one): 3.9 m of the bar along the line
#: of sight; the far sphere 0.5 m from the far wall and 0.6 m above the floor
LONG_BAR_CENTRES = (
    1.2 * np.array([0.15, 0.98, -0.13]) / np.linalg.norm([0.15, 0.98, -0.13]),
    5.2 * np.array([0.32, 0.94, -0.13]) / np.linalg.norm([0.32, 0.94, -0.13]),
)


def layout(name: str, u_distance_m: float) -> tuple[Scene, Artefact]:
    """The calibration scene and its artefact for ``--layout`` (see the module docstring)."""
    centres = [np.asarray(c, dtype=np.float64) for c, _ in ROOM_SPHERES]
    art = room_spheres_artefact()
    if name == "room":
        return get_scene("room-spheres"), Artefact.from_dict(art)
    if name == "axis":
        return get_scene("room-spheres-axis"), Artefact.from_dict(room_axis_artefact(u_distance_m))
    if name == "hall":
        return get_scene("hall-spheres-axis"), Artefact.from_dict(hall_axis_artefact(u_distance_m))
    scene = get_scene("room-spheres")
    if name == "long-bar":
        a, b, _ = ROOM_SPHERE_BAR
        centres[a], centres[b] = LONG_BAR_CENTRES
        kept = [o for o in scene.objects if o.name not in (f"sphere{a}", f"sphere{b}")]
        scene = Scene("room-long-bar")
        for o in kept:
            scene.add(o.shape, o.remission, o.name)
        for i in (a, b):
            scene.add(Sphere(centres[i], ROOM_SPHERES[i][1] / 2), remission=0.8, name=f"sphere{i}")
        dist = float(np.linalg.norm(centres[b] - centres[a]))
        art["distances_m"] = [{"a": a, "b": b, "distance_m": dist, "u_distance_m": u_distance_m}]
    elif name in ("network", "network-large"):
        if name == "network-large":
            scene = get_scene("room-spheres-large")
            art = room_spheres_artefact(ROOM_SPHERES_LARGE_FACTOR)
        n = len(centres)
        art["distances_m"] = [
            {"a": i, "b": j, "distance_m": float(np.linalg.norm(centres[j] - centres[i])), "u_distance_m": u_distance_m}
            for i in range(n)
            for j in range(i + 1, n)
        ]
    else:
        raise SystemExit(f"unknown layout {name!r}")
    return scene, Artefact.from_dict(art)


def _pose(t: tuple[float, float, float], yaw_deg: float, tip_deg: float = 0.0) -> np.ndarray:
    m = np.eye(4)
    cz, sz = np.cos(D(yaw_deg)), np.sin(D(yaw_deg))
    cx, sx = np.cos(D(tip_deg)), np.sin(D(tip_deg))
    m[:3, :3] = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    m[:3, 3] = t
    return m


#: ``--poses``: the rig's poses in the room (world_from_rig), all inside ``room-spheres`` and at
#: least 1.3 m from every sphere.
POSES = (np.eye(4), _pose((0.3, 3.0, 0.0), 180.0, 1.0), _pose((1.8, 1.0, 0.3), 90.0))
#: ``--layout axis``: the poses of ``room-spheres-axis`` (:data:`sim.scene.library.ROOM_AXIS_POSES`).
AXIS_POSES = tuple(_pose(t, yaw, tip) for t, yaw, tip in ROOM_AXIS_POSES)
#: ``--layout hall``: the poses of ``hall-spheres-axis`` (:data:`sim.scene.library.HALL_AXIS_POSES`).
HALL_POSES = tuple(_pose(t, yaw, tip) for t, yaw, tip in HALL_AXIS_POSES)


def calibration_sweep(
    rig: RigModel,
    speed_deg_s: float,
    seed: int,
    scene: Scene,
    span_deg: float = 180.0,
    pose: np.ndarray | None = None,
    hits: dict[str, int] | None = None,
    usable: dict[str, int] | None = None,
) -> Observations:
    """One simulated calibration sweep; ``hits``, when given, gathers the valid beams simulated on
    each scene object (by name), ``usable`` those of them an adjustment can use (cos(incidence) >=
    :data:`lrms.calibration.adjust.MIN_COS`: no silhouettes)."""
    cal = RigCalibration(model=rig, world_from_rig=np.eye(4) if pose is None else pose)
    half = D(span_deg / 2)
    _, s = continuous_sweep_cloud(
        scene, cal, SensorModel(), -half, half, D(speed_deg_s), rng=np.random.default_rng(seed)
    )
    v = s.valid
    if hits is not None:
        for k, n in zip(*np.unique(s.index[v], return_counts=True), strict=True):
            if k >= 0:
                name = scene.objects[int(k)].name
                hits[name] = hits.get(name, 0) + int(n)
    if usable is not None:
        good = v & (s.cos_incidence >= MIN_COS)
        for k, n in zip(*np.unique(s.index[good], return_counts=True), strict=True):
            if k >= 0:
                name = scene.objects[int(k)].name
                usable[name] = usable.get(name, 0) + int(n)
    return Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))


def part_fit(true_rig: RigModel, mapping: RigModel, seed: int) -> tuple[float, np.ndarray]:
    """Diameter and axis of seed 003's part swept by ``true_rig``, mapped with ``mapping``."""
    scene = get_scene("seed003-bare")
    cal = RigCalibration(model=true_rig)
    dev = lms1xx_device_angles(0.25)
    dev = dev[(dev > D(60)) & (dev < D(120))]
    mot = D(np.arange(-35.0, 75.0, 0.2))[:, None]
    s = cast_beams(scene, cal, SensorModel.noiseless(), dev, mot, np.random.default_rng(seed))
    on = s.valid & (s.index == scene.index_of("cylinder"))
    alpha = cal.alpha(np.broadcast_to(dev, on.shape)[on])
    beta = cal.beta(np.broadcast_to(mot, on.shape)[on])
    o, d = mapping.rays(alpha, beta)
    n = o.shape[0]
    sig = SensorModel().sigma_l
    rays = Rays(o, d, mapping.geometric_range(s.ranges[on]), np.full(n, sig), np.full(n, 1e-4))
    start = Cylinder(np.asarray(SEED003_AXIS_POINT), np.asarray(SEED003_AXIS_DIRECTION, float), SEED003_DIAMETER / 2)
    fit = fit_cylinder(rays.points(), rays=rays, initial=start, p=mapping.p)
    return fit.diameter, fit.cylinder.direction / np.linalg.norm(fit.cylinder.direction)


#: ``--lms1xx``: the region of interest around seed 003's part (rig frame = world), as bench_sensor_model's "roi".
_ROI_HALF = np.array([SEED003_DIAMETER / 2 + 0.35, SEED003_DIAMETER / 2 + 0.3, 0.0])
PART_ROI = (
    np.array([SEED003_AXIS_POINT[0], SEED003_AXIS_POINT[1], SEED003_AXIS_POINT[2] - 0.05]) - _ROI_HALF,
    np.array([SEED003_AXIS_POINT[0], SEED003_AXIS_POINT[1], SEED003_AXIS_POINT[2] + 0.9]) + _ROI_HALF,
)


def lms_part(
    true_rig: RigModel, mapping: RigModel, calibration: CalibrationResult | None, seed: int
) -> dict[str, float]:
    """Seed 003's part measured as the service measures it, with the LMS1xx footprint sensor: a
    step-and-scan sweep (-35..75 deg, 0.4 deg steps, beams 60..120 deg) by ``true_rig`` with
    SICK's noise and the beam footprint, the readings in :data:`PART_ROI` mapped with ``mapping``,
    fitted with the footprint model (``BeamOptics``, with the calibration's spot scale when it has one:
    ``CalibrationResult.beam_optics``; nominal diameter +-10 %) by
    :func:`service.fitting.cylinder_result`, whose budget carries the calibration's row (and
    without a calibration the uncalibrated LMS1xx rows). Returns the diameter error (m), U (m, k = 2)
    and the calibration row's u (m; 0 without one)."""
    from lrms.budget import BeamGeometry
    from lrms.calibration.budget import calibration_input
    from lrms.covariance import NoiseModel
    from lrms.cylinder import BeamOptics, nominal_diameter_range
    from lrms.errors import LrmsError
    from service.fitting import cylinder_result
    from sim.scene import LMS1xxSensor

    truth = RigCalibration(model=true_rig)
    dev = lms1xx_device_angles(0.25)
    dev = dev[(dev > D(60)) & (dev < D(120))]
    mot = D(np.arange(-35.0, 75.0, 0.4))[:, None]
    rng = np.random.default_rng(seed)
    s = cast_beams(get_scene("seed003-bare"), truth, LMS1xxSensor(), dev, mot, rng)
    shape = s.valid.shape
    alpha = truth.alpha(np.broadcast_to(dev, shape))[s.valid]
    beta = truth.beta(np.broadcast_to(mot, shape))[s.valid]
    scan = np.broadcast_to(np.arange(shape[0])[:, None], shape)[s.valid]
    l = s.ranges[s.valid]
    o, d = mapping.rays(alpha, beta)
    geo = mapping.geometric_range(l)
    pts = o + geo[:, None] * d
    keep = np.all((pts >= PART_ROI[0]) & (pts <= PART_ROI[1]), axis=1)
    l, alpha, beta, scan, o, d, geo = l[keep], alpha[keep], beta[keep], scan[keep], o[keep], d[keep], geo[keep]
    nm = NoiseModel()
    lateral = np.hypot(l * nm.sigma_alpha, (l * np.sin(alpha) + mapping.p) * nm.sigma_beta)
    rays = Rays(o, d, geo, np.full(l.shape, nm.sigma_l * (1.0 + mapping.k1)), np.maximum(lateral, 1e-7))
    row = None
    if calibration is not None:
        cal = dataclasses.replace(calibration, model=mapping)

        def row(fit: object, inlier_rays: Rays) -> object:
            i = fit.inliers  # type: ignore[attr-defined]
            return calibration_input(cal, fit, inlier_rays, l[i], alpha[i], beta[i], None, "bench")  # type: ignore[arg-type]

    try:
        result, _, _ = cylinder_result(
            rays.points(),
            rays=rays,
            noise=nm,
            p=mapping.p,
            rng=np.random.default_rng(seed),
            optics=BeamOptics() if calibration is None else calibration.beam_optics(BeamOptics()),
            diameter_range=nominal_diameter_range(SEED003_DIAMETER),
            beams=BeamGeometry(alpha, beta, mapping.p, 0.0, scan),
            calibration=row,  # type: ignore[arg-type]
        )
    except LrmsError as exc:  # e.g. no cylinder of the nominal diameter in a badly mapped cloud
        print(f"        fit failed: {exc}")
        return {"error": float("nan"), "U": float("nan"), "u_cal": float("nan")}
    unc = result["uncertainty"]
    u_cal = sum(r["u_m"] for r in unc["budget"] if r["source"] == "calibration")
    top = sorted(unc["budget"], key=lambda r: -float(r["u_m"] or 0.0))[:3]
    print("        largest rows: " + ", ".join(f"{r['source']} {1e3 * float(r['u_m'] or 0.0):.2f} mm" for r in top))
    return {"error": result["diameter_m"] - SEED003_DIAMETER, "U": unc["expanded_m"], "u_cal": u_cal}


class NormalCapture:
    """``--k1-budget``: records the last adjustment's system (the :class:`Adjustment`, its free
    names and weighted Jacobian) when :meth:`Adjustment.covariance` is called, to recompute k1's
    standard deviation from the normal matrix with some observations weighted differently."""

    def __enter__(self) -> NormalCapture:
        self.last: tuple[Adjustment, list[str], sparse.csr_matrix] | None = None
        self._orig = Adjustment.covariance
        capture = self

        def covariance(adj: Adjustment, names: list[str], jac: sparse.csr_matrix, r: np.ndarray) -> object:
            capture.last = (adj, names, jac)
            return capture._orig(adj, names, jac, r)

        Adjustment.covariance = covariance  # type: ignore[method-assign,assignment]
        return self

    def __exit__(self, *exc: object) -> None:
        Adjustment.covariance = self._orig  # type: ignore[method-assign]


def k1_budget(adj: Adjustment, names: list[str], jac: sparse.csr_matrix) -> dict[str, float]:
    """k1's standard deviation (ppm) from the normal matrix of the final adjustment, as it is and
    with groups of observations weighted as if there were more (or better) of them: each sphere's
    beams per sweep, every sphere's / every plane's beams, the diameters' and distances'
    uncertainties. The a-priori std (variance factor 1): what the data's design allows."""
    st = adj.state
    n_rows = jac.shape[0]
    group: dict[str, np.ndarray] = {}
    row = 0
    for pl in st.planes:
        group.setdefault("planes", np.zeros(n_rows, bool))[row : row + pl.index.size] = True
        row += pl.index.size
    for sp in st.spheres:
        w = adj.which[sp.index]
        for k in np.unique(w):
            m = np.zeros(n_rows, bool)
            m[row + np.flatnonzero(w == k)] = True
            group[f"sphere {sp.artefact_index} sweep {k} ({int(m.sum())} beams)"] = m
        group.setdefault("spheres", np.zeros(n_rows, bool))[row : row + sp.index.size] = True
        row += sp.index.size
    group["diameters"] = np.zeros(n_rows, bool)
    group["diameters"][row : row + len(st.spheres)] = True
    row += len(st.spheres)
    group["distances"] = np.zeros(n_rows, bool)
    group["distances"][row : row + len(adj.distances)] = True
    k = names.index("k1")

    def std(weights: np.ndarray) -> float:
        wj = sparse.diags(np.sqrt(weights)) @ jac
        return float(np.sqrt(np.linalg.inv((wj.T @ wj).toarray())[k, k])) * 1e6

    one = np.ones(n_rows)
    out = {"as is": std(one)}
    for name, m in group.items():
        for factor, label in (
            ((4.0, "u / 2"), (1e-4, "u x 100")) if name in ("diameters", "distances") else ((2.0, "x 2"),)
        ):
            w = one.copy()
            w[m] *= factor
            out[f"{name} {label}"] = std(w)
    return out


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip(abs(float(a @ b)), -1.0, 1.0))))


def print_tables(errs: dict[str, list[float]], stds: dict[str, list[float]], rows: Sequence[tuple[float, ...]]) -> None:
    """The issue's tables: parameter recovery and the part before / after."""
    print("\nparameter recovery (estimated - canonical truth), reported std, goal:")
    print(
        f"  {'param':11s} {'unit':4s} {'rms err':>9s} {'max|err|':>9s} {'mean std':>9s} {'<=3sd':>6s} {'goal':>7s} ok"
    )
    for name, e in errs.items():
        unit, f = RigModel.UNITS[name]
        ea, sa = np.asarray(e) * f, np.asarray(stds[name]) * f
        inside = float(np.mean(np.abs(ea) <= 3 * sa))
        goal = GOAL[name] * f
        ok = "yes" if np.max(np.abs(ea)) <= goal else "no"
        print(
            f"  {name:11s} {unit:4s} {np.sqrt(np.mean(ea**2)):9.4f} {np.max(np.abs(ea)):9.4f} {np.mean(sa):9.4f} "
            f"{100 * inside:7.0f}% {goal:7.3g}  {ok}"
        )
    everything = np.asarray(rows)
    # the part's rows of the runs that measured it (``--no-part`` runs hold nan diameters, no axis)
    r = everything[np.isfinite(everything[:, 0])]
    print(
        "\nseed 003 part (137.5 mm, noiseless sweep) against the ideal-rig fit, before / after calibration"
        f" ({r.shape[0]} of {everything.shape[0]} runs measured it):"
    )
    print(f"  {'':24s} {'before':>12s} {'after':>12s} {'goal':>8s}")
    print(f"  {'diameter rms (mm)':24s} {1e3 * np.sqrt(np.mean(r[:, 0] ** 2)):12.3f} "
          f"{1e3 * np.sqrt(np.mean(r[:, 2] ** 2)):12.3f} {0.1:8.2f}")  # fmt: skip
    print(f"  {'diameter max |err| (mm)':24s} {1e3 * np.max(np.abs(r[:, 0])):12.3f} "
          f"{1e3 * np.max(np.abs(r[:, 2])):12.3f} {0.1:8.2f}")  # fmt: skip
    print(f"  {'axis rms (deg)':24s} {np.sqrt(np.mean(r[:, 1] ** 2)):12.4f} {np.sqrt(np.mean(r[:, 3] ** 2)):12.4f} "
          f"{0.02:8.3f}")  # fmt: skip
    print(f"  {'axis max (deg)':24s} {np.max(r[:, 1]):12.4f} {np.max(r[:, 3]):12.4f} {0.02:8.3f}")
    print(f"  variance factor of the calibrations: {np.min(everything[:, 4]):.3f} .. {np.max(everything[:, 4]):.3f}")


def combine(files: list[str]) -> int:
    """``--combine``: the tables over the runs saved by several ``--save`` files."""
    errs: dict[str, list[float]] = {}
    stds: dict[str, list[float]] = {}
    rows: list[tuple[float, ...]] = []
    for f in files:
        d = json.loads(Path(f).read_text(encoding="utf-8"))
        for k, v in d["errs"].items():
            errs.setdefault(k, []).extend(v)
            stds.setdefault(k, []).extend(d["stds"][k])
        rows.extend(tuple(r) for r in d["rows"])
    print(f"{len(rows)} runs from {', '.join(files)}")
    print_tables(errs, stds, rows)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--speed", type=float, default=20.0, help="calibration sweep speed, deg/s (25 Hz scans)")
    ap.add_argument("--sweeps", type=int, default=1, help="calibration sweeps per run (independent noise)")
    ap.add_argument("--plane-points", type=int, default=5000, help="beams used per plane")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", type=int, default=0, help="first run (the rigs of the runs before are drawn, not run)")
    ap.add_argument(
        "--resegmentations", type=int, default=AdjustOptions.max_resegmentations,
        help="re-segmentation rounds at most (1: the single re-segmentation of before)",
    )  # fmt: skip
    ap.add_argument(
        "--layout", choices=("room", "long-bar", "network", "network-large", "axis", "hall"), default="network-large"
    )
    ap.add_argument("--sweep-deg", type=float, default=340.0, help="motor span of a sweep, centred on 0")
    ap.add_argument("--u-distance", type=float, default=3e-5, help="u of the long bar's / network's distances, m")
    ap.add_argument("--poses", type=int, default=3, choices=(1, 2, 3), help="rig poses, one sweep set each")
    ap.add_argument(
        "--lms1xx", action="store_true", help="also measure the part with the LMS1xx footprint sensor: error vs U"
    )
    ap.add_argument("--no-part", action="store_true", help="skip the seed 003 part before / after")
    ap.add_argument(
        "--k1-budget", action="store_true", help="print k1's std from the normal matrix with data groups reweighted"
    )
    ap.add_argument("--save", metavar="FILE.json", default=None, help="write the runs' errors after every run")
    ap.add_argument("--combine", nargs="+", metavar="FILE.json", default=None, help="tables over --save files")
    args = ap.parse_args(argv)
    if args.combine:
        return combine(args.combine)
    rng = np.random.default_rng(args.seed)
    scene, art = layout(args.layout, args.u_distance)
    poses = {"axis": AXIS_POSES, "hall": HALL_POSES}.get(args.layout, POSES)
    opts = CalibrationOptions(
        adjust=AdjustOptions(max_plane_points=args.plane_points, max_resegmentations=args.resegmentations)
    )
    errs: dict[str, list[float]] = {}
    stds: dict[str, list[float]] = {}
    rows = []
    lms: list[tuple[dict[str, float], dict[str, float]]] = []
    failures: list[str] = []
    t0 = time.perf_counter()
    for _ in range(args.start):
        draw_rig(rng)
    for run in range(args.start, args.start + args.runs):
        rig = draw_rig(rng)
        hits: dict[str, int] = {}
        usable: dict[str, int] = {}
        sweep_seed = args.seed * 100_000 + 100 * run
        sweeps = [
            calibration_sweep(rig, args.speed, sweep_seed + 10 * j + k, scene, args.sweep_deg, poses[j], hits, usable)
            for j in range(args.poses)
            for k in range(args.sweeps)
        ]
        try:
            with NormalCapture() as cap:
                res = calibrate(sweeps, art, options=opts, poses="separate" if args.poses > 1 else "shared")
        except CalibrationError as exc:  # e.g. a sweep that cannot be registered: counted, not fatal
            failures.append(f"run {run}: {exc}")
            print(f"run {run:2d}: calibration failed: {exc}", flush=True)
            continue
        lost = sorted(set(range(len(art.spheres))) - {sf.artefact_index for sf in res.surfaces if sf.kind == "sphere"})
        if lost:
            print(f"        artefact spheres not in the adjustment: {lost}", flush=True)
        if args.k1_budget and cap.last is not None and "k1" in cap.last[1]:
            print("        k1 std (ppm) from the normal matrix, data reweighted:", flush=True)
            for label, v in k1_budget(*cap.last).items():
                print(f"          {label:40s} {v:7.2f}", flush=True)
        truth = rig.canonical()
        std = res.std()
        worst = ("", 0.0)
        for name in res.estimated:
            errs.setdefault(name, []).append(getattr(res.model, name) - getattr(truth, name))
            stds.setdefault(name, []).append(std[name])
            z = abs(errs[name][-1]) / std[name]
            worst = (name, z) if z > worst[1] else worst
        print(
            f"        spheres kept / usable / simulated ({res.residuals['resegmentations']:.0f} re-segmentations): "
            + ", ".join(
                f"{sf.artefact_index} {sf.points}/{usable.get(f'sphere{sf.artefact_index}', 0)}"
                f"/{hits.get(f'sphere{sf.artefact_index}', 0)}"
                for sf in res.surfaces
                if sf.kind == "sphere"
            )
            + "\n        error / std: "
            + " ".join(f"{n} {errs[n][-1] / std[n]:+.1f}" for n in res.estimated),
            flush=True,
        )
        posed = dataclasses.replace(res.model, beta_zero=truth.beta_zero)  # the rig's pose about the shaft
        seed = 10_000 + run
        if args.no_part:
            d_ideal = d_before = d_after = float("nan")
            a_ideal = a_before = a_after = np.array([0.0, 0.0, 1.0])
        else:
            d_ideal, a_ideal = part_fit(RigModel(), RigModel(), seed)
            d_before, a_before = part_fit(rig, RigModel(), seed)
            d_after, a_after = part_fit(rig, posed, seed)
        if args.lms1xx:
            lms.append((lms_part(rig, RigModel(), None, seed), lms_part(rig, posed, res, seed)))
            b, a = lms[-1]
            print(
                f"        LMS1xx part: before {b['error'] * 1e3:+6.2f} mm (U {b['U'] * 1e3:.2f}), after "
                f"{a['error'] * 1e3:+6.2f} mm (U {a['U'] * 1e3:.2f}, calibration row u {a['u_cal'] * 1e3:.3f} mm)",
                flush=True,
            )
        rows.append(
            (d_before - d_ideal, angle_deg(a_before, a_ideal), d_after - d_ideal, angle_deg(a_after, a_ideal),
             res.residuals["variance_factor"])
        )  # fmt: skip
        if args.save:
            Path(args.save).write_text(json.dumps({"errs": errs, "stds": stds, "rows": rows}), encoding="utf-8")
        print(
            f"run {run:2d}: k0 {rig.k0 * 1e3:+6.1f} mm k1 {rig.k1 * 1e6:+6.0f} ppm  part dD before "
            f"{rows[-1][0] * 1e3:+6.2f} mm after {rows[-1][2] * 1e3:+6.3f} mm, axis before {rows[-1][1]:.3f} deg "
            f"after {rows[-1][3]:.4f} deg  (s0^2 {rows[-1][4]:.3f}, worst {worst[0]} {worst[1]:.1f} std)",
            flush=True,
        )
    elapsed = time.perf_counter() - t0
    print(
        f"\n{args.runs} runs in {elapsed:.0f} s; layout {args.layout}; {args.poses} pose(s) x {args.sweeps} "
        f"calibration sweep(s) per run at "
        f"{args.speed} deg/s, {-args.sweep_deg / 2:g}..{args.sweep_deg / 2:g} deg, <= {args.plane_points} beams per "
        f"plane; ideal thin beam, sigma_l = 11.67 mm"
    )
    if failures:
        print(f"{len(failures)} of {args.runs} calibrations failed: " + "; ".join(failures))
    if not rows:
        return 1
    print_tables(errs, stds, rows)
    if lms:
        print("\nseed 003 part with the LMS1xx footprint (noise on; footprint fit; U with k = 2), before / after:")
        for label, k in (("before", 0), ("after", 1)):
            ee = np.array([x[k]["error"] for x in lms]) * 1e3
            uu = np.array([x[k]["U"] for x in lms]) * 1e3
            failed = int(np.sum(np.isnan(ee)))
            ee, uu = ee[~np.isnan(ee)], uu[~np.isnan(ee)]
            if ee.size == 0:
                print(f"  {label:7s} every fit failed ({failed})")
                continue
            print(
                f"  {label:7s} error rms {np.sqrt(np.mean(ee**2)):6.3f} mm, max |e| {np.max(np.abs(ee)):6.3f} mm, "
                f"mean U {np.mean(uu):6.3f} mm, |e| <= U in {int(np.sum(np.abs(ee) <= uu))} of {len(ee)} "
                f"({failed} fits failed)"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
