"""The normals' k-nearest-neighbour search: pykdtree against scipy's cKDTree (the fallback).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python -m bench.bench_knn [--reps 5]``. On issue 15's
clouds (:func:`bench.cylinder_clouds.issue15_cloud`) it times the tree's build and a query of every
point for its ``k = 24`` nearest (:func:`lrms.cylinder.model.knn_query`, what
:func:`~lrms.cylinder.model.estimate_normals` does per chunk), both backends interleaved, CPU time
(least of ``--reps``), checks that they return the same indices, and prints the ratio cKDTree /
pykdtree. pykdtree runs on one thread (``OMP_NUM_THREADS`` unset: see ``_pykdtree``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.cylinder_clouds import issue15_cloud
from lrms.cylinder.model import KnnBackend, knn_query


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--k", type=int, default=24)
    args = ap.parse_args()
    print(f"{'points':>8} {'pykdtree s':>11} {'cKDTree s':>10} {'cKDTree / pykdtree':>19}")
    for n in (3000, 30_000, 100_000):
        pts = issue15_cloud(n, seed=0)
        backends: tuple[KnnBackend, ...] = ("pykdtree", "scipy")
        idx = {b: knn_query(pts, b)(pts, args.k) for b in backends}
        if not np.array_equal(idx["pykdtree"], idx["scipy"]):
            raise SystemExit(f"{n} points: the backends' neighbours differ")
        times: dict[str, list[float]] = {b: [] for b in backends}
        for _ in range(args.reps):
            for b in backends:
                t0 = time.process_time()
                knn_query(pts, b)(pts, args.k)
                times[b].append(time.process_time() - t0)
        a, c = min(times["pykdtree"]), min(times["scipy"])
        print(f"{n:>8} {a:>11.4f} {c:>10.4f} {c / a:>18.2f}x")
    print(f"(build + query of every point, k = {args.k}; CPU seconds, least of {args.reps} interleaved runs)")


if __name__ == "__main__":
    main()
