"""The cylinder fit of this tree against another checkout's, on the same clouds, interleaved.

Run: ``PYTHONPATH=. python -m bench.bench_cylinder_ab --baseline-tree DIR [--size 10000]
[--seeds 0,1,2,3] [--reps 3] [--rounds 2]``, where DIR is another checkout (e.g. ``git worktree add
/tmp/base <commit>`` or ``git archive <commit> | tar -x -C /tmp/base``). Each round runs each tree in a
fresh single-threaded process (``OMP_NUM_THREADS=1``), alternating which goes first; a process fits
every cloud (issue 15's standing 0.276 m cylinder with 30 % outliers, ``bench.cylinder_clouds``,
built from the same seeds in both) ``--reps`` times after one warm-up fit. Per cloud the least time
over all rounds is kept; printed: both trees' sums, the ratio this / baseline (the speed measure on
a shared machine: both see the same load), and both trees' mean |radius error| and per-cloud
radius errors (their difference is the accuracy change; compare it with the clouds' scatter).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent


def _worker(size: int, seeds: list[int], reps: int) -> None:
    from bench.cylinder_clouds import issue15_cloud, truth
    from lrms.cylinder import fit_cylinder

    clouds = [issue15_cloud(size, seed=s) for s in seeds]
    fit_cylinder(clouds[0][: min(size, 20_000)])  # warm-up: imports, caches
    out = []
    for c in clouds:
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fit = fit_cylinder(c)
            times.append(time.perf_counter() - t0)
        out.append((min(times), float(fit.cylinder.radius - truth().radius)))
    print(json.dumps(out))


def _run(tree: Path, size: int, seeds: str, reps: int) -> list[list[float]]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(tree)}
    # this file runs in both trees (the baseline may predate it); lrms and the clouds come from ``tree``
    argv = [sys.executable, str(Path(__file__).resolve()), "--worker", "--size", str(size), "--seeds", seeds]
    proc = subprocess.run([*argv, "--reps", str(reps)], cwd=tree, env=env, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{tree}: the fit failed:\n{proc.stderr[-2000:]}")
    result: list[list[float]] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline-tree", type=Path, help="another checkout to time against (required)")
    ap.add_argument("--size", type=int, default=10_000, help="points per cloud")
    ap.add_argument("--seeds", default="0,1,2,3", help="comma list of cloud seeds")
    ap.add_argument("--reps", type=int, default=3, help="fits of each cloud per process")
    ap.add_argument("--rounds", type=int, default=2, help="processes per tree, alternating")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    if args.worker:
        _worker(args.size, seeds, args.reps)
        return 0
    if args.baseline_tree is None or not (args.baseline_tree / "bench" / "cylinder_clouds.py").is_file():
        ap.error("--baseline-tree must be another checkout of lrms (with bench/cylinder_clouds.py)")
    trees = {"this": HERE, "baseline": args.baseline_tree.resolve()}
    runs: dict[str, list[list[list[float]]]] = {"this": [], "baseline": []}
    for k in range(args.rounds):
        for name in ("baseline", "this") if k % 2 == 0 else ("this", "baseline"):
            runs[name].append(_run(trees[name], args.size, args.seeds, args.reps))
    best = {}
    for name, rr in runs.items():
        arr = np.asarray(rr)  # rounds, clouds, (time, radius error)
        best[name] = arr[:, :, 0].min(axis=0)
        dr = arr[0, :, 1]
        print(
            f"{name:8s} n={args.size} sum of per-cloud least times {best[name].sum():.3f} s"
            f"  mean |dr| {1e3 * np.mean(np.abs(dr)):.4f} mm  dr (um) {np.round(1e6 * dr, 1).tolist()}"
        )
    print(f"ratio this / baseline: {best['this'].sum() / best['baseline'].sum():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
