"""Precision floors of seed 000's Tables 3-6: what RMSE a fit of those clouds can be expected to reach.

Run: ``.venv/bin/python -m bench.seed000_bounds`` (floors and probabilities only, a few seconds);
``--ours REPS`` also fits REPS clouds per cell (47,160 points, start: the truth perturbed by 3 mm,
1 deg and 5 %, so the estimator alone is measured, not the automatic start) with the curvature
correction on and off; ``--tables 3,4,5,6``, ``--ratio free|fixed|both``, ``--poses N``.

For each cell (joint, noise level, reading of "+-N mm" as Gaussian sigma = N mm or uniform on
[-N, N] mm, i.e. sigma = N/sqrt(3); A/D free or fixed) the floor is the Gauss-Helmert covariance at
the true parameters with the known noise (``lrms.elbow.bounds.parameter_floor``) on the same
cloud the reproduction uses (``sim.scene.joints.make_joint``, 47,160 points), turned into the
expected RMSE of the seed's metrics (delta_T over the three centre coordinates, delta_R over omega
and psi, delta_AD over A and D) and averaged (in the mean square) over ``--poses`` random poses
(delta_T and delta_AD do not depend on the pose; delta_R does, through the Euler angles). For
Gaussian noise it is the Cramer-Rao bound of an unbiased estimator; for the uniform reading it is
the covariance of least squares (orthogonal-distance fitting), whose error is Gaussian too (a
linear combination of 47,160 independent errors).

``P``: the probability that ONE fit's metric comes out at or below the seed's printed value (plus
half its last digit: 0.05 mm, 0.0005 deg, i.e. the seed's "0" is read as < 0.05 mm), for an
estimator at the floor: Monte Carlo from N(0, floor) over the same poses. An RMSE pooled over
several fits would be less likely still. ``<1/2``, ``<1/3``: the seed's value (plus half a digit)
is below that fraction of the floor.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import combine_pvalues

from bench.seed000_tables import SEED_T3, SEED_T4, SEED_T5, SEED_T6, _errors, _perturbed, _row_name
from lrms.elbow import fit_elbow, metric_floors, parameter_floor
from lrms.elbow.bounds import sample_metrics
from lrms.errors import FitError
from sim.scene.joints import SEED_TABLE_LABELS, TABLE1, make_joint, random_pose

FloatArray = NDArray[np.float64]
METRICS = ("dT", "dR", "dAD")
HALF_DIGIT = {"dT": 0.05, "dR": 0.0005, "dAD": 0.05}  # half the seed's last printed digit (mm, deg, mm)
MC_DRAWS = 5000  # per pose


@dataclass
class UnitFloor:
    """Floors of one joint at sigma = 1 mm: expected RMSE (mm, deg, mm) and Monte Carlo draws."""

    rms: dict[str, float]
    draws: dict[str, FloatArray]


@dataclass
class Row:
    table: str
    row: str
    noise: float
    metric: str
    seed: float | None
    floor: dict[str, float] = field(default_factory=dict)  # by noise kind
    prob: dict[str, float] = field(default_factory=dict)
    ours: dict[bool, float] = field(default_factory=dict)  # by curvature correction
    matched: float = math.nan  # the floor (Gaussian) at the poses of our fits
    fails: dict[bool, int] = field(default_factory=dict)


def unit_floor(joint: str, D: float, fixed: bool, poses: int, seed: int) -> UnitFloor:
    spec = TABLE1[joint]
    ratio = spec.ratio if fixed else None
    rng = np.random.default_rng(seed)
    sq = {m: 0.0 for m in METRICS}
    draws: dict[str, list[FloatArray]] = {m: [] for m in METRICS}
    for _ in range(poses):
        c, rot = random_pose(rng)
        j = make_joint(spec, D=D, center=c, rot=rot)
        cov = parameter_floor(j.points, j.truth, 1e-3, ratio, spec.flange)
        mf = metric_floors(cov, j.truth, ratio)
        sq["dT"] += (mf.d_t * 1e3) ** 2 / poses
        sq["dR"] += math.degrees(mf.d_r) ** 2 / poses
        sq["dAD"] += (mf.d_ad * 1e3) ** 2 / poses
        d_t, d_r, d_ad = sample_metrics(cov, j.truth, ratio, MC_DRAWS, rng)
        draws["dT"].append(d_t * 1e3)
        draws["dR"].append(np.degrees(d_r))
        draws["dAD"].append(d_ad * 1e3)
    return UnitFloor({m: math.sqrt(v) for m, v in sq.items()}, {m: np.concatenate(v) for m, v in draws.items()})


def our_rmse(
    joint: str, D: float, noise_mm: float, fixed: bool, reps: int, correction: bool, seed: int
) -> tuple[dict[str, float], int, dict[str, float]]:
    """RMSE of our fits (perturbed-truth start, Gaussian noise) pooled over ``reps`` random poses, the
    number of failures, and the floor at the same poses (root mean square over the poses)."""
    spec = TABLE1[joint]
    ratio = spec.ratio if fixed else None
    rng = np.random.default_rng(seed)
    et, er, ead = [], [], []
    fl = {m: 0.0 for m in METRICS}
    fails = 0
    for _ in range(reps):
        c, rot = random_pose(rng)
        j = make_joint(spec, D=D, center=c, rot=rot)
        mf = metric_floors(parameter_floor(j.points, j.truth, noise_mm / 1e3, ratio, spec.flange), j.truth, ratio)
        fl["dT"] += (mf.d_t * 1e3) ** 2 / reps
        fl["dR"] += math.degrees(mf.d_r) ** 2 / reps
        fl["dAD"] += (mf.d_ad * 1e3) ** 2 / reps
        pts = j.points + rng.normal(0.0, noise_mm / 1e3, j.points.shape)
        try:
            fit = fit_elbow(pts, _perturbed(j.truth), ratio=ratio, flange=spec.flange, curvature_correction=correction)
        except FitError:
            fails += 1
            continue
        dt, dr, dad = _errors(fit, j.truth)
        et.append(dt)
        er.append(dr[:2])
        ead.append(dad)

    def rmse(v: list[FloatArray]) -> float:
        return float(np.sqrt(np.mean(np.square(np.array(v))))) if v else math.nan

    return {"dT": rmse(et), "dR": rmse(er), "dAD": rmse(ead)}, fails, {m: math.sqrt(v) for m, v in fl.items()}


BIAS_CELLS = (("b", 0.2, 20.0), ("d", 0.1, 3.0), ("a", 0.2, 6.0), ("f", 0.1, 2.0))


def gate_study(k: int) -> None:
    """Sharp joints: the axis gate on the bend only (default) or on the legs too."""
    print(f"\nSharp joints, axis gate on the bend only / on the legs too; {k} fits (correction on), Gaussian noise")
    for joint, D, noise, fixed in (("c", 0.1, 3.0, True), ("c", 0.2, 5.0, False), ("f", 0.1, 2.0, False)):
        spec = TABLE1[joint]
        ratio = spec.ratio if fixed else None
        for legs in (False, True):
            rng = np.random.default_rng(33)
            et, ead, ea, fl = [], [], [], []
            for _ in range(k):
                c, rot = random_pose(rng)
                j = make_joint(spec, D=D, center=c, rot=rot)
                mf = metric_floors(parameter_floor(j.points, j.truth, noise / 1e3, ratio), j.truth, ratio)
                fl.append((mf.d_t * 1e3, mf.d_ad * 1e3))
                pts = j.points + rng.normal(0.0, noise / 1e3, j.points.shape)
                fit = fit_elbow(pts, _perturbed(j.truth), ratio=ratio, gate_legs=legs)
                dt, _, dad = _errors(fit, j.truth)
                et.append(dt)
                ead.append(dad)
                ea.append(dad[0])
            ft, fad = np.sqrt(np.mean(np.square(fl), axis=0))
            dt_r = float(np.sqrt(np.mean(np.square(et)))) / ft
            dad_r = float(np.sqrt(np.mean(np.square(ead)))) / fad
            print(
                f"{joint} D={D:g} m +-{noise:g} mm A/D {'fixed' if fixed else 'free '} gate_legs={legs!s:<5}: "
                f"delta_T/floor {dt_r:.2f}, delta_AD/floor {dad_r:.2f}, mean A error "
                f"{np.mean(ea):+.3f} +- {np.std(ea, ddof=1) / math.sqrt(k):.3f} mm"
            )


def bias_study(k: int) -> None:
    """Mean errors (model frame) over ``k`` fits per cell, curvature correction on and off, plus
    the axis gate on a sharp joint and the floor of the points the gate keeps."""
    from lrms.elbow.gauss_helmert import AXIS_GATE, _usable

    print(f"\nBias: mean error +- standard error over {k} fits (47,160 points, A/D free, Gaussian noise,")
    print("start: truth perturbed); centre in the model frame (X: start leg, Z: towards the start leg's")
    print("centre line), mm; mean fit time s")
    for joint, D, noise in BIAS_CELLS:
        spec = TABLE1[joint]
        rng = np.random.default_rng(31)
        errs: dict[bool, list[FloatArray]] = {True: [], False: []}
        times: dict[bool, list[float]] = {True: [], False: []}
        for _ in range(k):
            c, rot = random_pose(rng)
            j = make_joint(spec, D=D, center=c, rot=rot, noise=noise / 1e3, rng=rng)
            for corr in errs:
                t0 = time.perf_counter()
                fit = fit_elbow(j.points, _perturbed(j.truth), flange=spec.flange, curvature_correction=corr)
                times[corr].append(time.perf_counter() - t0)
                p = fit.params
                if math.degrees(np.arccos(np.clip((np.trace(p.rot @ j.truth.rot.T) - 1) / 2, -1, 1))) > 90:
                    p = p.flipped()
                e = np.concatenate([j.truth.rot @ (p.center - j.truth.center), [p.A - j.truth.A, p.D - j.truth.D]])
                errs[corr].append(e * 1e3)
        for corr, ev in errs.items():
            a = np.array(ev)
            m, se = a.mean(axis=0), a.std(axis=0, ddof=1) / math.sqrt(k)
            parts = "  ".join(
                f"{n} {mm:+.3f}+-{s:.3f}" for n, mm, s in zip(("X", "Y", "Z", "A", "D"), m, se, strict=True)
            )
            print(
                f"{joint} D={D:g} m +-{noise:g} mm, correction {'on ' if corr else 'off'}: {parts}  "
                f"time {np.mean(times[corr]):.3f}"
            )
    # the axis gate on a sharp joint
    rng = np.random.default_rng(32)
    print(f"\nAxis gate, joint c, D = 0.2 m, +-5 mm Gaussian, {k} fits (correction on): delta_T, delta_AD (mm)")
    for gate in (0.0, AXIS_GATE):
        et, ead, fa, fg = [], [], [], []
        for _ in range(k):
            c, rot = random_pose(rng)
            j = make_joint("c", D=0.2, center=c, rot=rot)
            use = _usable(j.points, j.truth, 0.005, AXIS_GATE)
            fa.append(metric_floors(parameter_floor(j.points, j.truth, 0.005), j.truth).d_t * 1e3)
            fg.append(metric_floors(parameter_floor(j.points[use], j.truth, 0.005), j.truth).d_t * 1e3)
            pts = j.points + rng.normal(0.0, 0.005, j.points.shape)
            dt, _, dad = _errors(fit_elbow(pts, _perturbed(j.truth), axis_gate=gate), j.truth)
            et.append(dt)
            ead.append(dad)
        print(
            f"axis_gate {gate:g}: delta_T {np.sqrt(np.mean(np.square(et))):.3f}, delta_AD "
            f"{np.sqrt(np.mean(np.square(ead))):.3f}; floor delta_T all points {np.sqrt(np.mean(np.square(fa))):.3f}, "
            f"points the gate keeps {np.sqrt(np.mean(np.square(fg))):.3f}"
        )


def table_rows(tables: set[str]) -> list[tuple[str, str, float, float, str, float | None]]:
    """(table, seed row, D, noise mm, metric, seed value) for every cell with noise > 0."""
    out: list[tuple[str, str, float, float, str, float | None]] = []
    specs = [
        ("3", SEED_T3, 0.1, [0, 1, 2, 3]),
        ("4", SEED_T4, 0.2, [3, 4, 5, 6]),
        ("6", SEED_T6, 0.2, [20, 40, 60, 80]),
    ]
    for name, tab, D, noises in specs:
        if name not in tables:
            continue
        for row, vals in tab.items():
            for n, v in zip(noises, vals, strict=True):
                if n == 0:
                    continue
                out.append((name, row, D, n, "dT", None if v is None else float(v[0])))
                out.append((name, row, D, n, "dR", None if v is None else float(v[1])))
    if "5" in tables:
        for row, vals5 in SEED_T5.items():
            for n, v5 in zip([0, 3, 4, 5, 6], vals5, strict=True):
                if n:
                    out.append(("5", row, 0.2, n, "dAD", None if v5 is None else float(v5)))
    return out


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--tables", default="3,4,5,6")
    ap.add_argument("--ratio", choices=["free", "fixed", "both"], default="both")
    ap.add_argument("--poses", type=int, default=4, help="random poses averaged per joint (default 4)")
    ap.add_argument("--ours", type=int, default=0, help="fits per cell for our RMSE (0: none)")
    ap.add_argument("--no-compare", action="store_true", help="with --ours: skip the uncorrected fits")
    ap.add_argument("--bias", type=int, default=0, help="fits per cell of the bias study (0: skip it)")
    ap.add_argument("--gate", type=int, default=0, help="fits per cell of the sharp-joint gate study (0: skip it)")
    args = ap.parse_args(argv)
    if args.bias:
        bias_study(args.bias)
    if args.gate:
        gate_study(args.gate)
    tables = set(args.tables.split(","))
    modes = [False, True] if args.ratio == "both" else [args.ratio == "fixed"]
    t0 = time.perf_counter()
    cells = table_rows(tables)
    for fixed in modes:
        mode = "A/D fixed" if fixed else "A/D free"
        units: dict[tuple[str, float], UnitFloor] = {}
        rows: list[Row] = []
        for tab, row, D, n, metric, seed in cells:
            joint = SEED_TABLE_LABELS[row]
            if (joint, D) not in units:
                units[joint, D] = unit_floor(joint, D, fixed, args.poses, seed=ord(joint) + int(1000 * D))
            u = units[joint, D]
            r = Row(tab, row, n, metric, seed)
            for kind, sig in (("gauss", n), ("uniform", n / math.sqrt(3))):
                r.floor[kind] = u.rms[metric] * sig
                if seed is not None:
                    r.prob[kind] = float(np.mean(u.draws[metric] * sig <= seed + HALF_DIGIT[metric]))
            rows.append(r)
        print(f"\n{mode}: floors at sigma = 1 mm (scale with the noise sigma; dT, dAD in mm, dR in deg)")
        print(f"{'joint':<14}{'D m':>6}{'dT':>9}{'dR':>9}{'dAD':>9}")
        for (joint, D), u in sorted(units.items(), key=lambda kv: (kv[0][1], kv[0][0])):
            sp = TABLE1[joint]
            name = f"{joint} {sp.degree_deg:.0f}deg {sp.ratio:g}D" + (" fl" if sp.flange else "")
            print(f"{name:<14}{D:>6.1f}{u.rms['dT']:>9.4f}{u.rms['dR']:>9.4f}{u.rms['dAD']:>9.4f}")
        if args.ours:
            # one set of fits per (table, row, noise): the three metrics come from the same fits
            done: dict[tuple[str, str, float, bool], tuple[dict[str, float], int, dict[str, float]]] = {}
            for r in rows:
                D = 0.1 if r.table == "3" else 0.2
                tab_key = "4" if r.table == "5" else r.table
                for corr in [True] if args.no_compare else [True, False]:
                    key = (tab_key, r.row, r.noise, corr)
                    if key not in done:
                        done[key] = our_rmse(
                            SEED_TABLE_LABELS[r.row],
                            D,
                            r.noise,
                            fixed,
                            args.ours,
                            corr,
                            seed=int(r.noise * 100) + ord(r.row),
                        )
                    r.ours[corr] = done[key][0][r.metric]
                    r.fails[corr] = done[key][1]
                    r.matched = done[key][2][r.metric]
        _print(rows, mode, args)
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")


def _print(rows: list[Row], mode: str, args: argparse.Namespace) -> None:
    print(
        f"\n=== {mode}: floors (expected RMSE of one fit at the Cramer-Rao / least-squares bound), "
        f"{args.poses} poses per joint ==="
    )
    head = (
        f"{'tab':<4}{'joint':<20}{'noise':>6}{'metric':>7}{'seed':>8}{'floor G':>10}{'P G':>8}{'floor U':>10}{'P U':>8}"
    )
    if args.ours:
        head += (
            f"{'ours':>9}{'/flG':>9}"
            + ("" if args.no_compare else f"{'uncorr':>9}{'/flG':>9}")
            + f"{'flG*':>9}{'ours/flG*':>10}"
        )
    print(head)
    for r in rows:
        seed = "n/a" if r.seed is None else (f"{r.seed:.3f}" if r.metric == "dR" else f"{r.seed:.1f}")
        fmt = ".4f" if r.metric == "dR" else ".3f"
        pg = f"{r.prob['gauss']:.3f}" if "gauss" in r.prob else "-"
        pu = f"{r.prob['uniform']:.3f}" if "uniform" in r.prob else "-"
        line = (
            f"{r.table:<4}{_row_name(r.row):<20}{r.noise:>6g}{r.metric:>7}{seed:>8}"
            f"{format(r.floor['gauss'], fmt):>10}{pg:>8}{format(r.floor['uniform'], fmt):>10}{pu:>8}"
        )
        for corr in [True] if args.no_compare else [True, False]:
            if corr in r.ours:
                o = r.ours[corr]
                f = "" if not r.fails.get(corr) else f"({r.fails[corr]}f)"
                line += f" {format(o, fmt) + f:>8} {o / r.floor['gauss']:>8.2f}"
        if r.ours:
            line += f" {format(r.matched, fmt):>8} {r.ours[True] / r.matched:>9.2f}"
        print(line)
    # summary per table
    print(
        f"\nsummary ({mode}): seed cells (noise > 0, seed value given) whose value (+ half a printed digit) is"
        " below the floor (<1), half of it (<1/2), a third (<1/3); whose P is below 5 % and 1 %"
    )
    print(
        f"{'table':<7}{'cells':>6}{'G <1':>6}{'G <1/2':>8}{'G <1/3':>8}{'G P<5%':>8}{'G P<1%':>8}"
        f"{'U <1':>6}{'U <1/2':>8}{'U <1/3':>8}{'U P<5%':>8}{'U P<1%':>8}"
        + (f"{'ours/flG* med':>14}{'max':>7}" if args.ours else "")
    )
    all_probs: dict[str, list[tuple[str, float]]] = {"gauss": [], "uniform": []}
    for tab in sorted({r.table for r in rows}):
        sel = [r for r in rows if r.table == tab and r.seed is not None]
        for kind in all_probs:
            all_probs[kind] += [(tab, r.prob[kind]) for r in sel]
        counts = []
        for kind in ("gauss", "uniform"):
            below = [(r.seed or 0.0) + HALF_DIGIT[r.metric] for r in sel]
            counts += [
                sum(b < r.floor[kind] for b, r in zip(below, sel, strict=True)),
                sum(b < r.floor[kind] / 2 for b, r in zip(below, sel, strict=True)),
                sum(b < r.floor[kind] / 3 for b, r in zip(below, sel, strict=True)),
                sum(r.prob[kind] < 0.05 for r in sel),
                sum(r.prob[kind] < 0.01 for r in sel),
            ]
        line = f"{tab:<7}{len(sel):>6}" + "".join(f"{c:>{6 if k % 5 == 0 else 8}}" for k, c in enumerate(counts))
        if args.ours:
            ratios = [r.ours[True] / r.matched for r in rows if r.table == tab and True in r.ours]
            ratios = [x for x in ratios if math.isfinite(x)]
            if ratios:
                line += f"{np.median(ratios):>14.2f}{max(ratios):>7.2f}"
        print(line)
    # the tables as a whole: are the seed's values, taken together, lower than a floor estimator gives?
    floor_p = 0.5 / (args.poses * MC_DRAWS)  # Monte Carlo resolution
    print(
        "Fisher's combined p (one-sided: all cells as low as the seed's by chance, one fit per cell at the floor)"
        " and log10 P(an estimator at the floor, one fit per cell, is at or below the seed in every cell):"
    )
    for kind, probs in all_probs.items():
        for tab in [*sorted({t for t, _ in probs}), "all"]:
            ps = np.array([max(p, floor_p) for t, p in probs if tab in ("all", t)])
            fisher = float(combine_pvalues(ps, method="fisher").pvalue)
            print(
                f"  {kind:<8} table {tab:<4} cells {ps.size:>3}: Fisher p = {fisher:.2g}, "
                f"log10 P(every cell) = {float(np.sum(np.log10(ps))):.1f}"
            )


if __name__ == "__main__":
    main()
