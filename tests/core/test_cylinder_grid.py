"""The detection's grid neighbourhoods (lrms/cylinder/grid.py) and the plane piece test's
connected components, against scipy's k-d tree and image labelling."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from bench import seed003_reproduction as seed
from lrms.cylinder.detect import _cell_components
from lrms.cylinder.grid import grid_normals, nearest_in_grid
from lrms.cylinder.model import estimate_normals


def test_cell_components_are_scipy_ndimage_labels() -> None:
    rng = np.random.default_rng(5)
    for trial in range(200):
        n = int(rng.integers(1, 300))
        cells = np.column_stack([rng.integers(0, rng.integers(1, 25), n), rng.integers(0, rng.integers(1, 25), n)])
        if trial % 3 == 0:  # sparser: more, smaller components
            cells = cells * 2
        grid = np.zeros(tuple(cells.max(axis=0) + 1), dtype=bool)
        grid[cells[:, 0], cells[:, 1]] = True
        labels, _ = ndimage.label(grid, structure=np.ones((3, 3), dtype=bool))
        assert np.array_equal(_cell_components(cells), labels[cells[:, 0], cells[:, 1]] - 1)


def test_grid_normals_of_a_cylinder_are_radial_within_a_few_degrees() -> None:
    """Coarser than the k nearest neighbours' PCA on a dense, nearly clean surface (the cell
    neighbourhood is a cube about twice the k-th neighbour distance wide, centred on the cell,
    not the point), but within the few degrees the RANSACs need (their angle gate is 30 deg)."""
    cyl = seed.seed_cylinder()
    rng = np.random.default_rng(8)
    pts = seed.visible_surface_points(60, 60)
    pts = pts + rng.normal(0.0, 2e-3, pts.shape)
    rad = cyl.radial(pts)
    rad /= np.linalg.norm(rad, axis=1)[:, None]

    def angles(n: np.ndarray) -> np.ndarray:
        return np.degrees(np.arccos(np.clip(np.abs(np.sum(n * rad, axis=1)), 0.0, 1.0)))

    grid, knn = angles(grid_normals(pts, 32)), angles(estimate_normals(pts, 32))
    assert np.allclose(np.linalg.norm(grid_normals(pts, 32), axis=1), 1.0)
    assert np.median(knn) < np.median(grid) < 4.0 and np.percentile(grid, 90) < 10.0


def test_grid_normals_of_scan_lines_look_across_the_lines() -> None:
    """Sparse lines on a plane (a grazing table): a neighbourhood of one line has no normal, the
    next cell size, holding several lines, does."""
    x = np.linspace(0.0, 1.0, 200)
    lines = [np.column_stack([x, np.full_like(x, y), np.zeros_like(x)]) for y in np.arange(0.0, 1.0, 0.08)]
    pts = np.vstack(lines) + np.random.default_rng(1).normal(0.0, 1e-4, (200 * len(lines), 3))
    n = grid_normals(pts, 32)
    assert np.percentile(np.abs(n[:, 2]), 5) > 0.99


def test_nearest_in_grid_is_the_nearest_within_a_cell() -> None:
    rng = np.random.default_rng(4)
    data = rng.uniform(0.0, 1.0, (3000, 3)) * [1.0, 1.0, 0.2]
    queries = rng.uniform(-0.2, 1.2, (2000, 3))
    cell = 0.02
    got = nearest_in_grid(data, queries, cell)
    dist, ref = cKDTree(data).query(queries, k=1)
    near = dist <= cell  # the nearest of all whenever it lies within a cell
    assert near.sum() > 50 and np.array_equal(got[near], ref[near])
    # farther queries get a near point from coarser cells: within twice the true distance
    far_d = np.linalg.norm(data[got[~near]] - queries[~near], axis=1)
    assert np.all(got >= 0) and np.all(far_d <= 2.0 * dist[~near] + 1e-12)
