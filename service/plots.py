"""Figures (matplotlib, Agg backend; written to PNG files): a cylinder fit, a measurement's cloud
with its fitted circle, an elbow fit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.config import RigConfig
from service.errors import ServiceError


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


def plot_measurement(cloud_path: str | None, result: dict[str, Any], config: RigConfig, out: str | Path) -> None:
    """The region of interest of a measurement's cloud (3D and top view) with the fitted circle."""
    from service.pointio import read_points
    from service.sweep import roi_mask

    plt = _pyplot()
    if cloud_path is None:
        raise ServiceError("the measurement has no cloud to plot")
    pts = read_points(cloud_path)
    fit = config.fit
    keep = roi_mask(pts, fit.roi_min_m, fit.roi_max_m)
    roi = pts[keep]
    fig = plt.figure(figsize=(11, 5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    sub = roi[:: max(1, roi.shape[0] // 20000)]
    ax.scatter(sub[:, 0], sub[:, 1], sub[:, 2], s=0.5, c=sub[:, 2], cmap="viridis")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(f"{roi.shape[0]} points in the region of interest")
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.scatter(roi[:, 0], roi[:, 1], s=0.5, alpha=0.4)
    if result.get("model") == "cylinder":
        c = np.asarray(result["axis_point_m"])
        r = float(result["diameter_m"]) / 2
        t = np.linspace(0, 2 * np.pi, 200)
        ax2.plot(c[0] + r * np.cos(t), c[1] + r * np.sin(t), "r-", lw=1.5)
        u = result["uncertainty"]
        d, lo, hi = result["diameter_m"] * 1e3, u["d_min_m"] * 1e3, u["d_max_m"] * 1e3
        ax2.set_title(f"d = {d:.2f} mm  [{lo:.1f}, {hi:.1f}] mm (k={u['k']:g})")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x (m)")
    ax2.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def model_surface(params: Any, n_along: int = 60, n_around: int = 24) -> Any:
    """Points on the fitted model surface (world frame) for drawing: the bend and short legs."""
    import math

    a, r, d = params.A, params.D / 2, params.degree
    theta = np.linspace(math.pi / 2, math.pi / 2 + d, n_along)
    phi = np.linspace(0.0, 2 * math.pi, n_around)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    rho = a + r * np.cos(pp)
    m = np.stack([rho * np.cos(tt), r * np.sin(pp), rho * np.sin(tt)], axis=-1).reshape(-1, 3)
    return params.to_world(m)


def plot_elbow(points: Any, fit: Any, out: str) -> None:
    """3D view of the cloud coloured by residual, with the fitted bend drawn over it."""
    plt = _pyplot()

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
