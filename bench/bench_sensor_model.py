"""Today's cylinder fit on clouds of the realistic LMS1xx model (beam footprint), against the ideal sensor.

The "before" figures of issue 11: the same fit (``lrms.cylinder.fit_cylinder`` with its defaults
and seed 003's noise model, as ``bench/seed003_reproduction.py`` calls it) on sweeps of

* the ideal thin-beam sensor (``SensorModel``: seed 003's 11.67 mm range noise), and
* the LMS1xx footprint model (``LMS1xxSensor``: 8 mm + 15 mrad spot, 128 sub-rays, SICK's noise)
  with the edge behaviour varied: detection thresholds 10 / 30 / 50 % of the full-spot energy,
  energy-weighted ("wtd") vs first-hit ("1st") range,

for seed 003's 137.5 mm part at 2.53 m in the ``seed003-room`` scene (walls, floor, ceiling,
neighbouring parts) and parts of D = 0.3 m and 1.0 m at 2, 3.5 and 5 m in the same room
(``part_in_room``). Each sweep: motor -20..70 deg in 0.4 deg steps (the default rig's 10 deg/s at
25 Hz), beams 50..130 deg of the LMS1xx's 0.25 deg grid. Two clouds per sweep: "roi" (cut to a box
around the part's table, as the service's region of interest) and "room" (every echo in the beam
window: walls, floor, neighbours). No systematic range error unless a "+15 mm" row says so.

The angle noise (1.74e-3 deg, 0.08 mm at 2.5 m) is left out, so the geometry of a scene is ray-cast
once and each sweep draws new range noise (and, for the LMS1xx, new echoes from the same sub-ray
hits): the sweeps differ by noise only. Printed per case: sweeps fitted / failed (no cylinder,
or a diameter more than 50 % off: "gross"), mean error of the diameter (mm) +- its standard error,
the spread (std, mm), the mean GUM standard uncertainty the fit reports, and the share of sweeps
whose d +- 2 u covers the truth.

``--fit footprint`` fits the same clouds with the beam-footprint model (``fit_cylinder(...,
optics=BeamOptics())``: LMS1xx spot, edge family and threshold estimated, not told) and a nominal
diameter (+-10 %); its u is the fit's with the edge-model row (``extra["edge_model_u_m"]``) in
quadrature. ``--fit both`` prints both fits per case, on the same clouds.

Run: ``.venv/bin/python -m bench.bench_sensor_model [--sweeps 20] [--only seed003|parts] [--clouds roi,room]
[--fit thin|footprint|both]
[--edges 0.3:first,...] [--sub-rays 128] [--no-offset] [--parts 0.3:3.5,...]``. With the footprint fit,
each row also counts the family the model choice picked (1st / wtd / thin).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics, fit_cylinder, nominal_diameter_range
from lrms.errors import LrmsError
from lrms.kinematics import RigCalibration
from lrms.uncertainty import gum_interval
from sim.scene import Footprint, LMS1xxSensor, RangeSystematics, Scene, SensorModel, SubRayHits, lms1xx_device_angles
from sim.scene.library import SEED003_AXIS_POINT, part_in_room

FloatArray = NDArray[np.float64]
Draw = Callable[[np.random.Generator], tuple[FloatArray, NDArray[np.bool_]]]

MOTOR = np.deg2rad(np.arange(-20.0, 70.0 + 1e-9, 0.4))
BEAMS = lms1xx_device_angles(0.25)
BEAMS = BEAMS[(np.deg2rad(50) <= BEAMS) & (np.deg2rad(130) >= BEAMS)]
#: The simulated sensor's sub-ray pattern (``--sub-rays``): the simulator's default 128; 32 moves a
#: noiseless first-hit fit by about 1 mm (docs/cylinder.md, section 7).
FOOTPRINT = Footprint()
EDGE_FAMILY = [(thr, mode) for thr in (0.1, 0.3, 0.5) for mode in ("weighted", "first")]
OFFSET_ROW = True


@dataclass
class Geometry:
    """One scene's sweep ray-cast once: beam rays, the thin beams' hits and the sub-ray hits."""

    name: str
    diameter: float
    origins: FloatArray
    dirs: FloatArray
    true_range: FloatArray
    echo: FloatArray
    sub: SubRayHits
    roi_lo: FloatArray
    roi_hi: FloatArray


def cast_geometry(name: str, scene: Scene, diameter: float, sensor: LMS1xxSensor) -> Geometry:
    cal = RigCalibration()
    dev, mot = np.broadcast_arrays(BEAMS[None, :], MOTOR[:, None])
    o, d = cal.world_rays(dev.ravel(), mot.ravel())
    hits = scene.raycast(o, d)
    sub = sensor.cast_footprints(scene, o, d)
    part = scene.objects[scene.index_of("cylinder")].shape
    centre, _ = part.bounding_sphere()
    half = np.array([diameter / 2 + 0.35, diameter / 2 + 0.3, 0.0])
    lo = np.array([centre[0], centre[1], SEED003_AXIS_POINT[2] - 0.05]) - half
    hi = np.array([centre[0], centre[1], SEED003_AXIS_POINT[2] + 0.9]) + half
    return Geometry(name, diameter, o, d, hits.range, hits.remission * hits.cos_incidence, sub, lo, hi)


def ideal_draw(g: Geometry) -> Draw:
    sensor = SensorModel(sigma_alpha=0.0, sigma_beta=0.0)
    return lambda rng: sensor.measure(g.true_range, g.echo, rng)


def lms_draw(g: Geometry, sensor: LMS1xxSensor) -> Draw:
    def draw(rng: np.random.Generator) -> tuple[FloatArray, NDArray[np.bool_]]:
        e = sensor.form_echoes(g.sub, rng)
        return e.range, e.valid

    return draw


@dataclass
class Row:
    errors: list[float] = dataclasses.field(default_factory=list)
    u: list[float] = dataclasses.field(default_factory=list)
    failed: int = 0
    gross: int = 0
    points: int = 0
    sweeps: int = 0
    modes: list[str] = dataclasses.field(default_factory=list)

    def text(self) -> str:
        n = len(self.errors)
        head = f"{n:3d} ok {self.failed:2d} failed {self.gross:2d} gross, {self.points / max(self.sweeps, 1):6.0f} pts"
        if n == 0:
            return head
        e = 1e3 * np.array(self.errors)
        u = 1e3 * np.array(self.u)
        se = e.std(ddof=1) / np.sqrt(n) if n > 1 else float("nan")
        sd = e.std(ddof=1) if n > 1 else float("nan")
        cover = np.mean(np.abs(e) <= 2 * u)
        picked = "".join(f", {m} x{self.modes.count(m)}" for m in ("1st", "wtd", "thin") if m in self.modes)
        return (
            f"{head}: mean error {e.mean():+7.2f} +- {se:5.2f} mm, std {sd:6.2f} mm,"
            f" u_GUM {u.mean():6.2f} mm, |e| <= 2u {100 * cover:5.1f} %{picked}"
        )


def run_case(g: Geometry, draw: Draw, sweeps: int, cloud: str, seed: int, fits: list[str]) -> dict[str, Row]:
    rng = np.random.default_rng(seed)
    noise = NoiseModel()
    rows = {f: Row() for f in fits}
    for _ in range(sweeps):
        ranges, valid = draw(rng)
        pts = g.origins[valid] + ranges[valid, None] * g.dirs[valid]
        if cloud == "roi":
            pts = pts[np.all((pts >= g.roi_lo) & (pts <= g.roi_hi), axis=1)]
        fit_seed = int(rng.integers(1 << 31))
        for kind, row in rows.items():
            row.points += pts.shape[0]
            row.sweeps += 1
            try:
                if kind == "thin":
                    fit = fit_cylinder(pts, noise=noise, rng=np.random.default_rng(fit_seed))
                else:
                    fit = fit_cylinder(
                        pts,
                        noise=noise,
                        rng=np.random.default_rng(fit_seed),
                        optics=BeamOptics(),
                        diameter_range=nominal_diameter_range(g.diameter),
                    )
            except LrmsError:
                row.failed += 1
                continue
            err = fit.diameter - g.diameter
            if abs(err) > 0.5 * g.diameter:
                row.gross += 1
                continue
            row.errors.append(err)
            if "edge_mode_first" in fit.extra:
                row.modes.append({1.0: "1st", 0.0: "wtd"}.get(fit.extra["edge_mode_first"], "thin"))
            row.u.append(float(np.hypot(gum_interval(fit).std, fit.extra.get("edge_model_u_m", 0.0))))
    return rows


def bench_scene(g: Geometry, sweeps: int, clouds: list[str], family: bool, seed: int, fits: list[str]) -> None:
    base = LMS1xxSensor(footprint=FOOTPRINT)
    cases: list[tuple[str, Draw]] = [("ideal thin beam (seed 003 noise)", ideal_draw(g))]
    edges = EDGE_FAMILY if family else [(0.3, "weighted")]
    for thr, mode in edges:
        sensor = dataclasses.replace(base, edge_threshold=thr, range_mode=mode)  # type: ignore[arg-type]
        cases.append((f"LMS1xx thr {100 * thr:2.0f} % {'wtd' if mode == 'weighted' else '1st'}", lms_draw(g, sensor)))
    if family and OFFSET_ROW:
        offset = dataclasses.replace(base, systematics=RangeSystematics(offset_m=0.015))
        cases.append(("LMS1xx thr 30 % wtd, +15 mm offset", lms_draw(g, offset)))
    print(f"\n== {g.name}: D = {1e3 * g.diameter:.1f} mm, {sweeps} sweeps per case")
    for cloud in clouds:
        for label, draw in cases:
            t0 = time.perf_counter()
            rows = run_case(g, draw, sweeps, cloud, seed, fits)
            dt = time.perf_counter() - t0
            for kind, row in rows.items():
                print(f"  {cloud:4s} {kind:9s} {label:36s} {row.text()}  ({dt:5.1f} s)", flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sweeps", type=int, default=20)
    parser.add_argument("--only", choices=("seed003", "parts"), default=None)
    parser.add_argument("--clouds", default="roi,room", help="comma list of roi, room")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--fit", choices=("thin", "footprint", "both"), default="thin")
    parser.add_argument("--edges", default=None, help="comma list of THR:MODE (0.3:weighted, 0.1:first) for the family")
    parser.add_argument("--sub-rays", type=int, default=Footprint().sub_rays, help="sub-rays per beam of the LMS1xx")
    parser.add_argument("--no-offset", action="store_true", help="leave out the +15 mm range offset row")
    parser.add_argument("--parts", default=None, help="comma list of D:R (m) for --only parts (default: all six)")
    args = parser.parse_args(argv)
    global FOOTPRINT, OFFSET_ROW
    FOOTPRINT = Footprint(sub_rays=args.sub_rays)
    OFFSET_ROW = not args.no_offset
    fits = ["thin", "footprint"] if args.fit == "both" else [args.fit]
    if args.edges:
        EDGE_FAMILY[:] = [(float(e.split(":")[0]), e.split(":")[1]) for e in args.edges.split(",")]
    clouds = [c for c in args.clouds.split(",") if c]
    if not clouds or any(c not in ("roi", "room") for c in clouds):
        parser.error("--clouds takes roi and/or room")
    sensor = LMS1xxSensor(footprint=FOOTPRINT)
    print(
        f"beams per sweep: {MOTOR.size} scans x {BEAMS.size} = {MOTOR.size * BEAMS.size:,};"
        f" sub-rays per beam: {sensor.footprint.sub_rays}"
    )
    scenes: list[tuple[str, float, float, bool]] = []
    if args.only in (None, "seed003"):
        scenes.append(("seed003-room (137.5 mm at 2.53 m)", 0.1375, SEED003_AXIS_POINT[1], True))
    if args.only in (None, "parts"):
        parts = [(d, r) for d in (0.3, 1.0) for r in (2.0, 3.5, 5.0)]
        if args.parts:
            parts = [(float(x.split(":")[0]), float(x.split(":")[1])) for x in args.parts.split(",")]
        scenes += [(f"room, D {d:.1f} m at {r:.1f} m", d, r, False) for d, r in parts]
    for label, diameter, distance, family in scenes:
        t0 = time.perf_counter()
        g = cast_geometry(label, part_in_room(diameter, distance), diameter, sensor)
        print(f"\n(ray cast of {label}: {time.perf_counter() - t0:.1f} s)")
        bench_scene(g, args.sweeps, clouds, family, args.seed, fits)


if __name__ == "__main__":
    main()
