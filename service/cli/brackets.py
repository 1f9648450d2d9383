"""``lrms brackets FILE``: mounting brackets on an elbow (seed 000, Section 2.3.2)."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "find mounting brackets on a pipe elbow: points off the fitted elbow, grouped (seed 000)"


def configure(parser: argparse.ArgumentParser) -> None:
    from service.cli.fit_elbow import add_elbow_arguments

    parser.add_argument("file", help="point file of the elbow cloud")
    add_elbow_arguments(parser)
    parser.add_argument(
        "--threshold-mm", type=float, default=None, help="residual threshold (default: 4 sigma0, at least 2 %% of D)"
    )
    parser.add_argument("--min-points", type=int, default=8, help="DBSCAN: points within eps for a core point")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from lrms.elbow.brackets import detect_brackets
    from service.cli.fit_elbow import elbow_options
    from service.pointio import read_points

    degree, ratio, flange = elbow_options(args)
    pts = read_points(args.file)
    thr = None if args.threshold_mm is None else args.threshold_mm / 1e3
    res = detect_brackets(
        pts,
        degree=degree,
        ratio=ratio,
        flange=flange,
        threshold=thr,
        min_samples=args.min_points,
        rng=np.random.default_rng(0),
    )
    out = res.to_dict()
    out["elbow"] = res.fit.to_dict()
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    print(
        f"elbow: D = {res.fit.params.D * 1e3:.1f} mm, A = {res.fit.params.A * 1e3:.1f} mm, "
        f"sigma0 = {res.fit.sigma0 * 1e3:.2f} mm; threshold {res.threshold * 1e3:.2f} mm, "
        f"{res.candidates.size} points above it"
    )
    for k, (g, c) in enumerate(zip(res.groups, res.centroids, strict=True)):
        print(f"group {k}: {g.size} points, centroid ({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) m")
    if res.cylinder is not None:
        cy = res.cylinder
        print(
            f"bracket (group 0): {res.bracket.size} points on a cylinder of diameter {cy.diameter * 1e3:.1f} mm, "
            f"length {res.length * 1e3:.1f} mm, axis ({cy.direction[0]:.3f}, {cy.direction[1]:.3f}, "
            f"{cy.direction[2]:.3f})"
        )
    return 0
