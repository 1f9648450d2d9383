"""``lrms register A B --model elbow``: the rigid transform taking cloud B into cloud A's frame."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "register cloud B to cloud A by one elbow joint seen in both (seed 000, Eq. 11)"


def configure(parser: argparse.ArgumentParser) -> None:
    from service.cli.fit_elbow import add_elbow_arguments

    parser.add_argument("first", metavar="A", help="point file of the reference cloud")
    parser.add_argument("second", metavar="B", help="point file of the cloud to transform")
    parser.add_argument("--model", choices=["elbow"], default="elbow", help="the feature seen in both clouds")
    add_elbow_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from lrms.elbow import fit_auto
    from lrms.elbow.registration import register
    from service.cli.fit_elbow import elbow_options
    from service.pointio import read_points

    degree, ratio, flange = elbow_options(args)
    fits = []
    for path in (args.first, args.second):
        pts = read_points(path)
        fits.append(fit_auto(pts, degree=degree, ratio=ratio, flange=flange, rng=np.random.default_rng(0)))
    reg = register(fits[0], fits[1])
    if args.json:
        out = {"transform": reg.to_dict(), "fit_a": fits[0].to_dict(), "fit_b": fits[1].to_dict()}
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    for row in reg.matrix:
        print(" ".join(f"{x: .9f}" for x in row))
    st = reg.sigma_translation * 1e3
    sr = reg.sigma_rotation_deg
    sj = reg.sigma_at_joint * 1e3
    print(f"# sigma translation (mm): {st[0]:.3f} {st[1]:.3f} {st[2]:.3f}", file=sys.stderr)
    print(f"# sigma at the joint (mm): {sj[0]:.3f} {sj[1]:.3f} {sj[2]:.3f}", file=sys.stderr)
    print(f"# sigma rotation (deg): {sr[0]:.4f} {sr[1]:.4f} {sr[2]:.4f}", file=sys.stderr)
    return 0
