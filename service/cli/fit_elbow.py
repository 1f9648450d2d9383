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
        plot_elbow(pts, fit, str(plot))
        result["plot"] = str(plot)
    return result


def model_surface(params: Any, n_along: int = 60, n_around: int = 24) -> Any:
    """Points on the fitted model surface (world frame) for drawing: the bend and short legs."""
    import math

    import numpy as np

    a, r, d = params.A, params.D / 2, params.degree
    theta = np.linspace(math.pi / 2, math.pi / 2 + d, n_along)
    phi = np.linspace(0.0, 2 * math.pi, n_around)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    rho = a + r * np.cos(pp)
    m = np.stack([rho * np.cos(tt), r * np.sin(pp), rho * np.sin(tt)], axis=-1).reshape(-1, 3)
    return params.to_world(m)


def plot_elbow(points: Any, fit: Any, out: str) -> None:
    """3D view of the cloud coloured by residual, with the fitted bend drawn over it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    pts = np.asarray(points, dtype=np.float64)
    step = max(1, pts.shape[0] // 20000)
    sub = pts[::step]
    res = np.asarray(fit.residuals)[::step] * 1e3 if fit.residuals.shape[0] == pts.shape[0] else None
    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    sc = ax.scatter(sub[:, 0], sub[:, 1], sub[:, 2], s=0.5, c=res if res is not None else "0.5", cmap="coolwarm")
    surf = model_surface(fit.params)
    ax.plot(surf[:, 0], surf[:, 1], surf[:, 2], color="k", linewidth=0.2, alpha=0.5)
    if res is not None:
        fig.colorbar(sc, ax=ax, shrink=0.6, label="residual (mm)")
    p = fit.params
    ax.set_title(f"elbow: D = {p.D * 1e3:.1f} mm, A = {p.A * 1e3:.1f} mm, rmse {fit.rmse * 1e3:.2f} mm")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    fig.savefig(out, dpi=120)
    plt.close(fig)
