"""The elbow branch of ``lrms fit FILE --model elbow`` (seed 000), called by :mod:`service.cli.fit`.

``run_elbow(args, points)`` fits the elbow and returns the JSON-ready result; ``args`` carries
``degree`` ('90', '45', any number of degrees, or None to take it from the cloud), ``ratio``
('0.5', '1', '1.5', any number >= 0.5, 'free' or None), ``flange`` (bool) and ``plot`` (a PNG
path or None). Only the standard library is imported at module level.
"""

from __future__ import annotations

import argparse
from typing import Any


def add_elbow_arguments(parser: argparse.ArgumentParser) -> None:
    """The elbow options (for commands that fit elbows: register, brackets)."""
    parser.add_argument(
        "--degree", default=None, help="joint degree: 90, 45 or any angle in deg (default: from the cloud)"
    )
    parser.add_argument(
        "--ratio", default="free", help="A/D ratio: 0.5, 1, 1.5, any number >= 0.5, or 'free' (default)"
    )
    parser.add_argument("--flange", action="store_true", help="the joint has flanges: fit their diameter Df too")


def elbow_options(args: argparse.Namespace) -> tuple[float | None, float | None, bool]:
    """``(degree_rad or None, ratio or None, flange)`` from parsed arguments."""
    from lrms.elbow.model import parse_degree, parse_ratio

    deg = getattr(args, "degree", None)
    degree = None if deg is None or str(deg).strip().lower() in ("", "auto") else parse_degree(deg)
    ratio = parse_ratio(getattr(args, "ratio", None))
    return degree, ratio, bool(getattr(args, "flange", False))


def run_elbow(args: argparse.Namespace, points: Any) -> dict[str, Any]:
    """Fit an elbow to ``points`` (n, 3) in metres and return the result (raises FitError)."""
    import numpy as np

    from lrms.elbow import fit_auto

    degree, ratio, flange = elbow_options(args)
    pts = np.asarray(points, dtype=np.float64)
    fit = fit_auto(pts, degree=degree, ratio=ratio, flange=flange, rng=np.random.default_rng(0))
    result = fit.to_dict()
    plot = getattr(args, "plot", None)
    if plot:
        from service.plots import plot_elbow

        plot_elbow(pts, fit, str(plot))
        result["plot"] = str(plot)
    return result
