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
The roi cloud's echoes are formed on the beams whose ray meets the ROI box alone (about 30 % of
seed 003's sweep; an echo outside that set cannot be in the box): each sweep's range noise is drawn
for all beams and the kept beams' taken, so the clouds are those of the whole sweep's echo formation
(checked equal), at about a ninth of its cost; ``--all-beams`` forms every beam's echoes.

The angle noise (1.74e-3 deg, 0.08 mm at 2.5 m) is left out, so the geometry of a scene is ray-cast
once and each sweep draws new range noise (and, for the LMS1xx, new echoes from the same sub-ray
hits): the sweeps differ by noise only. ``--sweep-list`` fits the given sweeps of the stream
alone (the others drawn, not fitted), ``--dump DIR`` saves each fitted sweep's cloud and fit seed
(npz) for refitting it elsewhere; a failed sweep's line gives its index. Printed per case: sweeps
fitted / failed (no cylinder, or a diameter more than 50 % off: "gross"), mean error of the
diameter (mm) +- its standard error, the spread (std, mm), the mean GUM standard uncertainty the
fit reports, and the share of sweeps whose d +- 2 u covers the truth.

``--fit footprint`` fits the same clouds with the beam-footprint model (``fit_cylinder(...,
optics=BeamOptics())``: LMS1xx spot, edge family, threshold and spot scale estimated, not told)
and a nominal diameter (+-10 %); its u is the fit's with the edge-model rows (``extra["edge_model_u_m"]``,
the spot size, 0 unless ``--hold-spot`` holds the spot at its nominal size, and
``extra["edge_family_u_m"]``, the model choice) in quadrature. ``--fit both`` prints
both fits per case, on the same clouds.

For a long unattended run (the >= 400-sweep coverage check of issue 11): ``--progress N`` prints a
line every N sweeps of a case, ``--cache DIR`` keeps each scene's ray cast (the 128-sub-ray cast
takes minutes) in DIR for the next run, ``--no-ideal`` leaves out the ideal-sensor rows, and a
summary table at the end gives per case n, mean error +- s.e., spread, mean U (k = 2) and the
coverage with its exact (Clopper-Pearson) binomial 95 % interval. Example:
``PYTHONPATH=. OMP_NUM_THREADS=1 python -m bench.bench_sensor_model --only seed003 --clouds roi
--fit footprint --no-offset --no-ideal --edges 0.3:first,0.3:weighted --sweeps 400 --progress 20
--cache /tmp/lrms-geom``.

Run: ``.venv/bin/python -m bench.bench_sensor_model [--sweeps 20] [--only seed003|parts] [--clouds roi,room]
[--fit thin|footprint|both]
[--edges 0.3:first,...] [--sub-rays 128] [--no-offset] [--parts 0.3:3.5,...]``. With the footprint fit,
each row also counts the family the model choice picked (1st / wtd / thin). The parts' rows are
the 30 % energy-weighted edge alone unless ``--edges`` names a family (then that family, as for
seed 003's part).
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
from numpy.typing import NDArray

from bench.coverage_log import append_record, coverage_interval, done_sweeps, sweep_key, tree_revision
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
IDEAL_ROW = True
#: The footprint fit's optics (``--hold-spot``: the spot held at its nominal size, its 15 % carried as a row).
OPTICS = BeamOptics()
PROGRESS = 0
#: Sweep indices (in the case's random stream) to fit (``--sweep-list``); None: every sweep.
SWEEP_LIST: set[int] | None = None
#: Directory to save each fitted sweep's cloud and fit seed in (``--dump``), or None.
DUMP: Path | None = None
#: Echo formation of the roi cloud on the beams that meet the ROI box alone (``--all-beams``: off).
ROI_BEAMS = True
#: (scene, cloud, fit, case, row) of every case run, for the summary table.
SUMMARY: list[tuple[str, str, str, str, Row]] = []
#: File each fitted sweep's record is appended to (``--jsonl``, bench/coverage_log.py), or None.
JSONL: Path | None = None
#: The sweeps already in JSONL (skipped: drawn, not fitted again) and the tree's commit.
DONE: set[tuple[object, ...]] = set()
REV = "unknown"
#: Sub-ray patterns of the roi cloud's sweeps (``--patterns P``): sweep s is drawn from the cast of
#: the pattern turned by ``pi (s mod P) / P`` (``Footprint.rotation_rad``; 1: the cached cast alone).
PATTERNS = 1


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


def lms_draw(
    g: Geometry, sensor: LMS1xxSensor, keep: NDArray[np.intp] | None = None, turned: list[SubRayHits] | None = None
) -> Draw:
    """Echoes of every beam; with ``keep`` (sorted beam indices, :func:`roi_beams`) echo formation
    runs on those beams alone, their ranges and validity the same as in the whole sweep's (see
    :class:`SubsetNormals`), the other beams invalid. ``turned`` (with ``keep``): the ``keep``
    beams' casts of further sub-ray patterns (:func:`turned_casts`); the draws then take the cached
    cast and these in turn, one pattern per sweep."""
    n = g.origins.shape[0]
    if keep is None:

        def draw(rng: np.random.Generator) -> tuple[FloatArray, NDArray[np.bool_]]:
            e = sensor.form_echoes(g.sub, rng)
            return e.range, e.valid

        return draw
    subs = [SubRayHits(g.sub.range[keep], g.sub.index[keep], g.sub.cos_incidence[keep], g.sub.remission[keep])]
    subs += turned or []
    count = [0]

    def draw_subset(rng: np.random.Generator) -> tuple[FloatArray, NDArray[np.bool_]]:
        sub = subs[count[0] % len(subs)]
        count[0] += 1
        e = sensor.form_echoes(sub, cast(np.random.Generator, SubsetNormals(rng, keep, n)))
        ranges, valid = np.zeros(n), np.zeros(n, dtype=bool)
        ranges[keep], valid[keep] = e.range, e.valid
        return ranges, valid

    return draw_subset


class SubsetNormals:
    """The generator echo formation draws its range noise from when it runs on a subset ``keep`` of
    a sweep's ``n`` beams: each draw of ``(len(keep),)`` normals is drawn for all ``n`` beams from
    ``rng`` and the subset's returned, so the stream and every kept beam's noise are those of the
    whole sweep. Any other use of the generator is an error (the bench would silently differ)."""

    def __init__(self, rng: np.random.Generator, keep: NDArray[np.intp], n: int) -> None:
        self.rng, self.keep, self.n = rng, keep, n

    def standard_normal(self, shape: tuple[int, ...]) -> FloatArray:
        if tuple(shape) != (self.keep.size,):
            raise RuntimeError(f"subset echo formation drew {shape}, expected ({self.keep.size},)")
        return np.asarray(self.rng.standard_normal(self.n)[self.keep], dtype=np.float64)

    def __getattr__(self, name: str) -> object:
        raise RuntimeError(f"subset echo formation used the generator's {name}: not mirrored for the whole sweep")


def turned_casts(scene: Scene, g: Geometry, keep: NDArray[np.intp], patterns: int) -> list[SubRayHits]:
    """The ``keep`` beams' sub-rays cast against ``scene`` (the one ``g`` was cast from) with the
    pattern turned by ``pi p / patterns``, p = 1 .. patterns - 1 (the cached cast is p = 0)."""
    out = []
    for p in range(1, patterns):
        fp = dataclasses.replace(FOOTPRINT, rotation_rad=float(np.pi * p / patterns))
        out.append(LMS1xxSensor(footprint=fp).cast_footprints(scene, g.origins[keep], g.dirs[keep]))
    return out


def roi_beams(g: Geometry) -> NDArray[np.intp]:
    """The beams whose ray (range >= 0) meets the ROI box: the only ones whose echo can be in the
    "roi" cloud, whatever its range (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / g.dirs
        t1, t2 = (g.roi_lo - g.origins) * inv, (g.roi_hi - g.origins) * inv
    # nan: a beam along a slab's face (0 x inf), taken as inside it
    t_near = np.max(np.nan_to_num(np.minimum(t1, t2), nan=-np.inf), axis=1)
    t_far = np.min(np.nan_to_num(np.maximum(t1, t2), nan=np.inf), axis=1)
    return np.flatnonzero((t_near <= t_far) & (t_far >= 0.0))


@dataclass
class Row:
    errors: list[float] = dataclasses.field(default_factory=list)
    u: list[float] = dataclasses.field(default_factory=list)
    failed: int = 0
    gross: int = 0
    #: fitted just outside the nominal diameter range, within its u (``extra["nominal_excess_m"]``)
    flagged: int = 0
    points: int = 0
    sweeps: int = 0
    modes: list[str] = dataclasses.field(default_factory=list)

    def text(self) -> str:
        n = len(self.errors)
        head = f"{n:3d} ok {self.failed:2d} failed {self.gross:2d} gross, {self.points / max(self.sweeps, 1):6.0f} pts"
        if self.flagged:
            head += f" ({self.flagged} outside the nominal range, flagged)"
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


def run_case(
    g: Geometry, draw: Draw, sweeps: int, cloud: str, seed: int, fits: list[str], label: str = ""
) -> dict[str, Row]:
    rng = np.random.default_rng(seed)
    noise = NoiseModel()
    rows = {f: Row() for f in fits}

    def record(kind: str, sweep: int) -> dict[str, object]:
        return {
            "scene": g.name,
            "cloud": cloud,
            "fit": kind,
            "case": label,
            "sub_rays": FOOTPRINT.sub_rays,
            "hold_spot": not OPTICS.fit_spot,
            "patterns": PATTERNS,
            "seed": seed,
            "sweep": sweep,
            "rev": REV,
        }

    for sweep in range(sweeps):
        ranges, valid = draw(rng)
        fit_seed = int(rng.integers(1 << 31))
        if SWEEP_LIST is not None and sweep not in SWEEP_LIST:
            continue  # drawn (the stream stays that of every sweep), not fitted
        if all(sweep_key(record(kind, sweep)) in DONE for kind in fits):
            continue  # logged by an earlier run of the same --jsonl file
        pts = g.origins[valid] + ranges[valid, None] * g.dirs[valid]
        if cloud == "roi":
            pts = pts[np.all((pts >= g.roi_lo) & (pts <= g.roi_hi), axis=1)]
        if DUMP is not None:
            DUMP.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(DUMP / f"{cloud}-seed{seed}-sweep{sweep:04d}.npz", points=pts, fit_seed=fit_seed)
        for kind, row in rows.items():
            rec = record(kind, sweep)
            if sweep_key(rec) in DONE:
                continue
            rec["points"] = int(pts.shape[0])
            row.points += pts.shape[0]
            row.sweeps += 1
            cpu0, wall0 = time.process_time(), time.perf_counter()

            def log(status: str, rec: dict[str, object] = rec, cpu0: float = cpu0, wall0: float = wall0) -> None:
                if JSONL is not None:
                    rec["status"] = status
                    rec["cpu_s"] = time.process_time() - cpu0
                    rec["wall_s"] = time.perf_counter() - wall0
                    append_record(JSONL, rec)

            try:
                if kind == "thin":
                    fit = fit_cylinder(pts, noise=noise, rng=np.random.default_rng(fit_seed))
                else:
                    fit = fit_cylinder(
                        pts,
                        noise=noise,
                        rng=np.random.default_rng(fit_seed),
                        optics=OPTICS,
                        diameter_range=nominal_diameter_range(g.diameter),
                    )
            except LrmsError as ex:
                print(f"    !! {kind} sweep {sweep}: {type(ex).__name__}: {ex}", flush=True)
                row.failed += 1
                rec["reason"] = f"{type(ex).__name__}: {ex}"
                log("failed")
                continue
            except (ArithmeticError, ValueError, np.linalg.LinAlgError) as ex:
                # not ours: an unattended 400-sweep run must not die on one sweep
                print(f"    !! {kind} sweep {sweep}: {type(ex).__name__}: {ex}", flush=True)
                row.failed += 1
                rec["reason"] = f"{type(ex).__name__}: {ex}"
                log("failed")
                continue
            err = fit.diameter - g.diameter
            rec["error_m"] = err
            if abs(err) > 0.5 * g.diameter:
                row.gross += 1
                log("gross")
                continue
            row.errors.append(err)
            if "nominal_excess_m" in fit.extra:
                row.flagged += 1
                print(
                    f"    .. {kind} sweep {sweep}: {1e3 * fit.diameter:.1f} mm, flagged: outside the nominal range"
                    f" by {1e3 * fit.extra['nominal_excess_m']:+.1f} mm ({fit.extra['nominal_excess_u']:.2f} u)",
                    flush=True,
                )
            if "edge_mode_first" in fit.extra:
                row.modes.append({1.0: "1st", 0.0: "wtd"}.get(fit.extra["edge_mode_first"], "thin"))
            x = fit.extra
            u_fit = gum_interval(fit).std
            u = float(
                np.sqrt(
                    u_fit**2
                    + sum(x.get(k, 0.0) ** 2 for k in ("edge_model_u_m", "edge_family_u_m", "footprint_bias_u_m"))
                )
            )
            row.u.append(u)
            rec.update(
                u_m=u,
                U_m=2 * u,
                covered=bool(abs(err) <= 2 * u),
                won={1.0: "first", 0.0: "weighted"}.get(x.get("edge_mode_first", -1.0), "thin"),
                tau=x.get("edge_threshold"),
                spot_scale=x.get("edge_spot_scale"),
                flagged="nominal_excess_m" in x,
                profile_restarts=x.get("footprint_profile_restarts"),
                profile_moved_m=x.get("footprint_profile_moved_m"),
            )
            log("ok")
        done = len(rows[fits[0]].errors) + rows[fits[0]].failed + rows[fits[0]].gross
        if PROGRESS and done % PROGRESS == 0:
            for kind, row in rows.items():
                print(f"    .. {kind} {done}/{sweeps}: {row.text()}", flush=True)
    return rows


def bench_scene(
    g: Geometry, sweeps: int, clouds: list[str], family: bool, seed: int, fits: list[str], scene: Scene | None = None
) -> None:
    base = LMS1xxSensor(footprint=FOOTPRINT)
    cases: list[tuple[str, LMS1xxSensor | None]] = [("ideal thin beam (seed 003 noise)", None)] if IDEAL_ROW else []
    edges = EDGE_FAMILY if family else [(0.3, "weighted")]
    for thr, mode in edges:
        sensor = dataclasses.replace(base, edge_threshold=thr, range_mode=mode)  # type: ignore[arg-type]
        cases.append((f"LMS1xx thr {100 * thr:2.0f} % {'wtd' if mode == 'weighted' else '1st'}", sensor))
    if family and OFFSET_ROW:
        offset = dataclasses.replace(base, systematics=RangeSystematics(offset_m=0.015))
        cases.append(("LMS1xx thr 30 % wtd, +15 mm offset", offset))
    print(f"\n== {g.name}: D = {1e3 * g.diameter:.1f} mm, {sweeps} sweeps per case")
    for cloud in clouds:
        # the roi cloud's echoes formed on the beams that can reach the ROI alone: the same clouds
        keep = roi_beams(g) if cloud == "roi" and ROI_BEAMS else None
        turned: list[SubRayHits] = []
        if PATTERNS > 1 and keep is not None and scene is not None:
            t0 = time.perf_counter()
            turned = turned_casts(scene, g, keep, PATTERNS)
            print(f"  ({PATTERNS - 1} turned patterns of {keep.size} beams cast: {time.perf_counter() - t0:.1f} s)")
        for label, case_sensor in cases:
            draw = ideal_draw(g) if case_sensor is None else lms_draw(g, case_sensor, keep, turned)
            t0 = time.perf_counter()
            rows = run_case(g, draw, sweeps, cloud, seed, fits, label)
            dt = time.perf_counter() - t0
            for kind, row in rows.items():
                print(f"  {cloud:4s} {kind:9s} {label:36s} {row.text()}  ({dt:5.1f} s)", flush=True)
                SUMMARY.append((g.name, cloud, kind, label, row))


def summary_table() -> None:
    """Per case: n, mean error +- s.e., spread, mean U (k = 2), coverage of d +- U with its
    Clopper-Pearson 95 % interval (the goal: 95 % within it)."""
    print("\n== summary (errors and U in mm; covered: |error| <= U = 2 u; 95 % binomial interval)")
    print(
        f"  {'scene':34s} {'cloud':5s} {'fit':9s} {'case':36s} {'n':>4s} {'mean':>7s} {'s.e.':>5s}"
        f" {'std':>6s} {'mean U':>7s} {'covered':>9s} {'95 % interval':>15s}"
    )
    for scene, cloud, kind, label, row in SUMMARY:
        n = len(row.errors)
        if n == 0:
            print(f"  {scene:34s} {cloud:5s} {kind:9s} {label:36s} {0:4d}  (failed {row.failed}, gross {row.gross})")
            continue
        e = 1e3 * np.array(row.errors)
        big_u = 2e3 * np.array(row.u)
        k = int(np.count_nonzero(np.abs(e) <= big_u))
        lo, hi = coverage_interval(k, n)
        sd = e.std(ddof=1) if n > 1 else float("nan")
        print(
            f"  {scene:34s} {cloud:5s} {kind:9s} {label:36s} {n:4d} {e.mean():+7.2f} {sd / np.sqrt(n):5.2f}"
            f" {sd:6.2f} {big_u.mean():7.2f} {k:4d}/{n:<4d} [{100 * lo:5.1f}, {100 * hi:5.1f}] %"
            + (f"  (failed {row.failed}, gross {row.gross})" if row.failed or row.gross else "")
        )


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
    parser.add_argument("--no-ideal", action="store_true", help="leave out the ideal thin-beam rows")
    parser.add_argument(
        "--hold-spot", action="store_true", help="footprint fit: hold the spot at its nominal size (before round 7)"
    )
    parser.add_argument("--progress", type=int, default=0, help="print a line every N sweeps of a case")
    parser.add_argument(
        "--all-beams", action="store_true", help="form the roi cloud's echoes on every beam (slower, same clouds)"
    )
    parser.add_argument("--cache", default=None, help="directory keeping each scene's ray cast between runs")
    parser.add_argument(
        "--sweep-list", default=None, help="comma list of sweep indices to fit (the others drawn, not fitted)"
    )
    parser.add_argument("--dump", default=None, help="directory to save each fitted sweep's cloud (npz) in")
    parser.add_argument(
        "--jsonl", default=None, help="append each fitted sweep's record to this file; sweeps already in it are skipped"
    )
    parser.add_argument(
        "--sweep-range", default=None, help="A:B: fit sweeps A..B-1 of the stream (the first A drawn, not fitted)"
    )
    parser.add_argument(
        "--patterns",
        type=int,
        default=1,
        help="sub-ray patterns of the roi cloud (turned by pi/P), one per sweep in turn (default 1: the cached cast)",
    )
    args = parser.parse_args(argv)
    global FOOTPRINT, OFFSET_ROW, IDEAL_ROW, PROGRESS, ROI_BEAMS, SWEEP_LIST, DUMP, OPTICS, JSONL, DONE, REV, PATTERNS
    if args.patterns < 1:
        parser.error("--patterns must be >= 1")
    if args.patterns > 1 and (args.all_beams or args.clouds != "roi"):
        parser.error("--patterns turns the roi cloud's beams only: give --clouds roi, without --all-beams")
    PATTERNS = args.patterns
    SWEEP_LIST = None if args.sweep_list is None else {int(i) for i in args.sweep_list.split(",") if i}
    if args.sweep_range is not None:
        try:
            first, stop = (int(x) for x in args.sweep_range.split(":"))
        except ValueError:
            parser.error("--sweep-range takes A:B (integers)")
        if not 0 <= first < stop:
            parser.error("--sweep-range A:B needs 0 <= A < B")
        chunk = set(range(first, stop))
        SWEEP_LIST = chunk if SWEEP_LIST is None else SWEEP_LIST & chunk
        args.sweeps = stop
    JSONL = None if args.jsonl is None else Path(args.jsonl)
    DONE = done_sweeps(JSONL)
    REV = tree_revision()
    if DONE:
        print(f"resuming: {len(DONE)} sweep records already in {JSONL}", flush=True)
    DUMP = None if args.dump is None else Path(args.dump)
    OPTICS = BeamOptics(fit_spot=not args.hold_spot)
    ROI_BEAMS = not args.all_beams
    FOOTPRINT = Footprint(sub_rays=args.sub_rays)
    OFFSET_ROW = not args.no_offset
    IDEAL_ROW = not args.no_ideal
    PROGRESS = max(args.progress, 0)
    if args.sweeps < 1:
        parser.error("--sweeps must be >= 1")
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
        # the parts get the edge family only when --edges names it (else 30 % energy-weighted alone)
        scenes += [(f"room, D {d:.1f} m at {r:.1f} m", d, r, bool(args.edges)) for d, r in parts]
    for label, diameter, distance, family in scenes:
        t0 = time.perf_counter()
        g = cached_geometry(args.cache, label, diameter, distance, sensor)
        print(f"\n(ray cast of {label}: {time.perf_counter() - t0:.1f} s)")
        bench_scene(g, args.sweeps, clouds, family, args.seed, fits, part_in_room(diameter, distance))
    summary_table()


def cached_geometry(cache: str | None, label: str, diameter: float, distance: float, sensor: LMS1xxSensor) -> Geometry:
    """The scene's ray cast, from ``cache`` (a directory) when it holds one for the same part,
    distance and sub-ray count (written there after a fresh cast)."""
    if cache is None:
        return cast_geometry(label, part_in_room(diameter, distance), diameter, sensor)
    path = Path(cache) / f"geometry-d{1e3 * diameter:.1f}-r{distance:.3f}-sub{sensor.footprint.sub_rays}.pkl"
    if path.exists():
        with path.open("rb") as f:
            g: Geometry = pickle.load(f)
        return dataclasses.replace(g, name=label)
    g = cast_geometry(label, part_in_room(diameter, distance), diameter, sensor)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump(g, f, protocol=pickle.HIGHEST_PROTOCOL)
    return g


if __name__ == "__main__":
    main()
