"""A picture of a measurement: the cloud in the region of interest and the fitted model."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.config import RigConfig
from service.errors import ServiceError
from service.sweep import roi_mask


def read_ply_points(path: str | Path) -> NDArray[np.float64]:
    """x, y, z of a cloud written by :func:`service.rig.write_ply`."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ServiceError(f"{path} is not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    props = [line.split()[2] for line in header if line.startswith("property ")]
    types = {"float": "<f4", "int": "<i4", "double": "<f8"}
    dtype = [(line.split()[2], types[line.split()[1]]) for line in header if line.startswith("property ")]
    if props[:3] != ["x", "y", "z"]:
        raise ServiceError(f"{path}: expected x, y, z properties first")
    rec = np.frombuffer(data[end + len(b"end_header\n") :], dtype=dtype)
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)


def plot_measurement(cloud_path: str | None, result: dict[str, Any], config: RigConfig, out: str | Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if cloud_path is None:
        raise ServiceError("the measurement has no cloud to plot")
    pts = read_ply_points(cloud_path)
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
