"""Issue 15's benchmark clouds: a standing cylinder on a table with clutter, seen by the rig.

The seed 003 part (r = 0.138 m, D = 0.276 m, axis at about 2.5 m from the rig, standing on a table
at z = -0.10 m, rig at the origin with p = 0.1 m). Of ``n`` points, 70 % lie on the part's visible
surface, 15 % on the table top (a 1.2 m x 1.0 m rectangle around the part, less what the part
covers or hides) and 15 % are clutter (uniform in the box above the table, not inside or behind
the part): 30 % outliers including a table. Every point is observed through Eq. 1 with the seed's
noise (range noise 11.67 mm along the line of sight; ``NoiseModel()``). Deterministic for a seed.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from bench.seed003_reproduction import AXIS_POINT, BOTTOM, RADIUS, TOP_Z, P, noisy_scan, seed_cylinder
from lrms.covariance import NoiseModel
from lrms.cylinder import Cylinder, rays_from_points

FloatArray = NDArray[np.float64]

#: Shares of the cloud: part, table, clutter.
SHARES = (0.70, 0.15, 0.15)


def truth() -> Cylinder:
    """The true cylinder of every cloud."""
    return seed_cylinder()


def _visible(pts: FloatArray, cyl: Cylinder) -> NDArray[np.bool_]:
    """Points outside the part and not hidden behind it from the rig."""
    rays = rays_from_points(pts, P)
    t, gap = cyl.ray_range(rays.origins, rays.dirs)
    hidden = (gap == 0) & (t < rays.ranges - 1e-6) & (t > 0)
    return np.asarray(~hidden & (cyl.axis_distance(pts) > cyl.radius), dtype=np.bool_)


def _rejection(draw: object, n: int, cyl: Cylinder) -> FloatArray:
    out: list[FloatArray] = []
    got = 0
    while got < n:
        cand = draw(2 * (n - got) + 16)  # type: ignore[operator]
        cand = cand[_visible(cand, cyl)]
        out.append(cand)
        got += cand.shape[0]
    return np.asarray(np.vstack(out)[:n], dtype=np.float64)


def issue15_cloud(n: int, seed: int = 0, noise: NoiseModel | None = None) -> FloatArray:
    """``n`` rig-frame points (shuffled): part, table and clutter, observed with the rig's noise."""
    nm = noise if noise is not None else NoiseModel()
    rng = np.random.default_rng(seed)
    cyl = truth()
    n_part = round(SHARES[0] * n)
    n_table = round(SHARES[1] * n)
    n_junk = n - n_part - n_table
    c = AXIS_POINT[:2]
    half = np.arccos(RADIUS / np.linalg.norm(c)) * 0.98
    phi0 = np.arctan2(-c[1], -c[0])
    th = phi0 + rng.uniform(-half, half, n_part)
    z = rng.uniform(BOTTOM[2], TOP_Z, n_part)
    part = np.column_stack([c[0] + RADIUS * np.cos(th), c[1] + RADIUS * np.sin(th), z])
    lo = np.array([c[0] - 0.6, c[1] - 0.5, BOTTOM[2]])
    hi = np.array([c[0] + 0.6, c[1] + 0.5, TOP_Z])

    def table_draw(m: int) -> FloatArray:
        xy = rng.uniform(lo[:2], hi[:2], (m, 2))
        return np.column_stack([xy, np.full(m, BOTTOM[2])])

    def junk_draw(m: int) -> FloatArray:
        return np.asarray(rng.uniform(lo + np.array([0, 0, 0.01]), hi, (m, 3)), dtype=np.float64)

    table = _rejection(table_draw, n_table, cyl)
    junk = _rejection(junk_draw, n_junk, cyl)
    truth_pts = np.vstack([part, table, junk])
    pts, _ = noisy_scan(truth_pts, nm, rng)
    return np.asarray(pts[rng.permutation(n)], dtype=np.float64)
