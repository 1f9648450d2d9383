"""Elbow fit speed: Gauss-Helmert adjustment of seed 000's model on 47,160 and ~200k points.

Run: ``.venv/bin/python -m bench.bench_elbow``. Joint a of Table 1 (90 deg, 1D, D = 0.1 m, full
coverage, 1 mm Gaussian noise, random pose). For each size it prints the time of the automatic
initial values, of the Gauss-Helmert adjustment from them (median of 3 after one warm-up run), its iterations, and, as
the baseline measured in the same run, :func:`scipy.optimize.least_squares` (trust region
reflective, the same analytic Jacobian, the same start) on the same orthogonal residuals; the
ratio baseline / ours holds up better than absolute times on a loaded machine.
Goal (issue 5): <= 0.5 s for 47,160 points on one core.

The second table is the whole automatic fit, :func:`lrms.elbow.fit_auto` (initial values, the
adjustment, labelling, the straight-cylinder check) on the 47,160-point clouds of Table 1's
joints a, c, d and g (random pose, 1 mm noise, full coverage), single-threaded, CPU time (median
of ``--reps``): its ratio to the goal of issue 15 (<= 0.2 s), and with ``--baseline-tree DIR``
(another checkout, e.g. ``git worktree add /tmp/base <commit>``) the same fits of that tree,
interleaved in the same run in worker processes, with both trees' errors against the truth.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from lrms.elbow import design_matrices, fit_elbow, initial_values
from lrms.elbow.gauss_helmert import apply_update
from lrms.elbow.model import ElbowParams, condition
from sim.scene.joints import make_joint, random_pose

FloatArray = NDArray[np.float64]


T = TypeVar("T")


def _median_time(fn: Callable[[], T], repeat: int = 3) -> tuple[float, T]:
    times = []
    out = fn()
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _scipy_fit(points: FloatArray, init: ElbowParams) -> tuple[ElbowParams, int]:
    def fun(x: FloatArray) -> FloatArray:
        return condition(points, apply_update(init, x, None, False))

    def jac(x: FloatArray) -> FloatArray:
        _, amat, _ = design_matrices(points, apply_update(init, x, None, False))
        return amat

    res = least_squares(fun, np.zeros(8), jac=jac, method="trf", x_scale="jac")
    return apply_update(init, res.x, None, False), int(res.nfev)


AUTO_GOAL_S = 0.2
AUTO_JOINTS = ("a", "c", "d", "g")
REPO = Path(__file__).resolve().parents[1]


def auto_worker(joint: str, reps: int) -> dict[str, float]:
    """``fit_auto`` on one joint's 47,160-point cloud: median CPU and wall time, errors (mm, deg)."""
    import math

    from lrms.elbow import fit_auto
    from sim.scene.joints import TABLE1

    rng = np.random.default_rng(100 + ord(joint))
    c, rot = random_pose(rng)
    j = make_joint(joint, center=c, rot=rot, noise=0.001, rng=rng)
    flange = TABLE1[joint].flange

    def run() -> object:
        return fit_auto(j.points, flange=flange, rng=np.random.default_rng(0))

    fit = run()
    cpu, wall = [], []
    for _ in range(reps):
        t0, w0 = time.process_time(), time.perf_counter()
        fit = run()
        cpu.append(time.process_time() - t0)
        wall.append(time.perf_counter() - w0)
    p = fit.params  # type: ignore[attr-defined]
    t = j.truth
    axis = math.degrees(math.acos(min(1.0, abs(float(p.axis @ t.axis)))))
    return {
        "n": float(j.points.shape[0]),
        "cpu": float(np.median(cpu)),
        "wall": float(np.median(wall)),
        "dc_mm": float(np.linalg.norm(p.center - t.center)) * 1e3,
        "dA_mm": (p.A - t.A) * 1e3,
        "dD_mm": (p.D - t.D) * 1e3,
        "axis_deg": axis,
    }


def _worker(tree: Path, joint: str, reps: int) -> dict[str, float]:
    """:func:`auto_worker` in a fresh single-threaded process on ``tree``'s code (this file's
    worker is passed as text, so the tree needs only ``lrms.elbow.fit_auto`` and ``sim``)."""
    src = Path(__file__).read_text()
    code = (
        "import sys, json\n"
        f"sys.path.insert(0, {str(tree)!r})\n"
        f"ns = {{'__name__': 'bench_worker', '__file__': {str(Path(__file__))!r}}}\n"
        f"exec(compile({src!r}, 'bench_elbow', 'exec'), ns)\n"
        f"print(json.dumps(ns['auto_worker']({joint!r}, {reps})))\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"worker on {tree} failed: {out.stderr[-800:]}")
    result: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def auto_table(reps: int, baseline: Path | None) -> None:
    trees = [("this tree", REPO)] + ([("baseline", baseline)] if baseline is not None else [])
    print(f"\nfit_auto, single-threaded, CPU s (median of {reps}); goal {AUTO_GOAL_S} s")
    head = f"{'joint':>5} {'tree':>10} {'points':>7} {'cpu s':>7} {'wall s':>7} {'goal/cpu':>8} "
    print(head + f"{'|dc| mm':>8} {'dA mm':>7} {'dD mm':>7} {'axis deg':>8}")
    ours: list[float] = []
    base: list[float] = []
    for joint in AUTO_JOINTS:
        for name, tree in trees:  # interleaved: one joint on each tree before the next joint
            r = _worker(tree, joint, reps)
            (ours if name == "this tree" else base).append(r["cpu"])
            print(
                f"{joint:>5} {name:>10} {int(r['n']):>7} {r['cpu']:>7.3f} {r['wall']:>7.3f} "
                f"{AUTO_GOAL_S / r['cpu']:>8.2f} {r['dc_mm']:>8.3f} {r['dA_mm']:>7.3f} {r['dD_mm']:>7.3f} "
                f"{r['axis_deg']:>8.4f}"
            )
    if base:
        ratios = [b / o for b, o in zip(base, ours, strict=True)]
        pairs = zip(AUTO_JOINTS, ratios, strict=True)
        print("baseline / this tree (CPU): " + ", ".join(f"{j} {x:.2f}x" for j, x in pairs))


def main() -> None:
    ap = argparse.ArgumentParser(description="elbow fit speed (Gauss-Helmert and fit_auto)")
    ap.add_argument("--reps", type=int, default=5, help="timed fit_auto runs per joint and tree")
    ap.add_argument("--baseline-tree", type=Path, default=None, help="another checkout to time alongside")
    ap.add_argument("--skip-gh", action="store_true", help="only the fit_auto table")
    args = ap.parse_args()
    if not args.skip_gh:
        gauss_helmert_table()
    auto_table(args.reps, args.baseline_tree)


def gauss_helmert_table() -> None:
    rng = np.random.default_rng(1)
    print(
        f"{'points':>8} {'init s':>8} {'GH s':>8} {'iter':>5} {'scipy s':>8} {'nfev':>5} {'scipy/GH':>9} "
        f"{'|dc| um':>8} {'GH-scipy um':>11}"
    )
    for n_along in (131, 556):
        c, rot = random_pose(rng)
        j = make_joint("a", center=c, rot=rot, n_along=n_along, noise=0.001, rng=rng)
        pts = j.points
        t0 = time.perf_counter()
        init = initial_values(pts, rng=np.random.default_rng(0))
        t_init = time.perf_counter() - t0
        t_gh, fit = _median_time(partial(fit_elbow, pts, init))
        t_sp, (sp, nfev) = _median_time(partial(_scipy_fit, pts, init))
        dc = np.linalg.norm(fit.params.center - j.truth.center) * 1e6
        dd = np.linalg.norm(fit.params.center - sp.center) * 1e6
        print(
            f"{pts.shape[0]:>8} {t_init:>8.3f} {t_gh:>8.3f} {fit.iterations:>5} {t_sp:>8.3f} {nfev:>5} "
            f"{t_sp / t_gh:>9.2f} {dc:>8.1f} {dd:>11.3f}"
        )
    print("goal: GH <= 0.5 s at 47,160 points")


if __name__ == "__main__":
    main()
