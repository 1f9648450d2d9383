"""``lrms replay``: re-run mapping and fit on a measurement's raw log and compare with the stored result."""

from __future__ import annotations

import argparse

HELP = "re-run mapping and fits offline from a measurement's MCAP log"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="raw log of a measurement")
    parser.add_argument("--full", action="store_true", help="print the stored result beside the replayed one")


def run(args: argparse.Namespace) -> int:
    import os

    # one BLAS thread: the fits are then bit-for-bit repeatable (lrms replay), and the rig's
    # threads keep the cores
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import json
    import sys

    from service.replay import replay

    out = replay(args.file)
    if not args.full:
        out.pop("stored", None)
    print(json.dumps(out, indent=2))
    if out.get("truncated"):
        print("note: the log is cut short (the process did not finish it); replayed what it holds", file=sys.stderr)
    if out.get("reproduced") is False:
        print(f"the replay differs from the stored result (max abs diff {out['max_abs_diff']})", file=sys.stderr)
        return 2
    return 0
