"""Figures of a cylinder measurement (matplotlib, Agg backend; written to PNG files)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def cylinder_figure(
    points: NDArray[np.float64],
    inliers: NDArray[np.intp],
    axis_point: NDArray[np.float64],
    axis_direction: NDArray[np.float64],
    radius: float,
    centripetal_radii: NDArray[np.float64] | None,
    critical_radius: float | None,
    path: str | Path,
    title: str = "",
    max_points: int = 20_000,
) -> None:
    """Points (inliers highlighted) with the fitted cylinder, and the centripetal-radius
    histogram with its CDF (seed 003, Fig. 7), in one PNG."""
    plt = _pyplot()
    fig = plt.figure(figsize=(12, 5.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    rng = np.random.default_rng(0)
    mask = np.zeros(points.shape[0], dtype=bool)
    mask[inliers] = True
    show = np.arange(points.shape[0])
    if show.size > max_points:
        show = np.sort(rng.choice(show, max_points, replace=False))
    out, inn = show[~mask[show]], show[mask[show]]
    ax.scatter(*points[out].T, s=1, c="0.6", label="other points")
    ax.scatter(*points[inn].T, s=1, c="tab:blue", label="cylinder inliers")
    w = axis_direction / np.linalg.norm(axis_direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(w, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(w, e1)
    if inn.size:
        s = (points[inliers] - axis_point) @ w
        s0, s1 = float(s.min()), float(s.max())
    else:
        s0, s1 = -radius, radius
    th, hh = np.meshgrid(np.linspace(0, 2 * np.pi, 48), np.linspace(s0, s1, 12))
    surf = (
        axis_point[:, None, None]
        + w[:, None, None] * hh
        + radius * (e1[:, None, None] * np.cos(th) + e2[:, None, None] * np.sin(th))
    )
    ax.plot_wireframe(surf[0], surf[1], surf[2], color="tab:red", linewidth=0.4, alpha=0.6)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(title or f"fitted cylinder, d = {2e3 * radius:.2f} mm")
    ax.legend(loc="upper left", fontsize=8, markerscale=6)
    ax2 = fig.add_subplot(1, 2, 2)
    if centripetal_radii is not None and centripetal_radii.size:
        mm = 1e3 * centripetal_radii
        ax2.hist(mm, bins=30, color="tab:blue", alpha=0.7)
        ax2.set_xlabel("centripetal radius r_ce (mm)")
        ax2.set_ylabel("points")
        ax3 = ax2.twinx()
        x = np.sort(mm)
        ax3.plot(x, np.arange(1, x.size + 1) / x.size, color="tab:orange", label="CDF")
        ax3.set_ylim(0, 1.02)
        ax3.set_ylabel("cumulative share")
        if critical_radius is not None:
            c = 1e3 * critical_radius
            ax3.axvline(c, color="tab:green", linestyle=":")
            ax3.axhline(0.25, color="tab:green", linestyle=":")
            ax2.set_title(f"critical point: r_ce = {c:.2f} mm (25th percentile)")
    else:
        ax2.text(0.5, 0.5, "no centripetal radii", ha="center", va="center")
    fig.tight_layout()
    fig.savefig(str(path), dpi=110)
    plt.close(fig)
