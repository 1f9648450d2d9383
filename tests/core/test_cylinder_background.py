"""The background planes' piece test does not depend on how densely the working sample covers a wall."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lrms.cylinder import DetectOptions
from lrms.cylinder.detect import WALL_CELL, _plane_extent, background_planes, plane_cell

DATA = Path(__file__).resolve().parents[1] / "data" / "cylinder" / "sweep-0cbed50a-no-scan46-every10th.npz"


def _points() -> np.ndarray:
    """The points of the file (0.5 mm steps; provenance in test_cylinder_second_look)."""
    return np.load(DATA)["points_halfmm"] * 5e-4


def _is_back_wall(normal: np.ndarray, offset: float) -> bool:
    return abs(float(normal[1])) > 0.99 and abs(abs(offset) - 6.0) < 0.1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_back_wall_of_a_room_sweep_is_found_on_a_sparse_sample(seed: int) -> None:
    # every 10th point of service sweep 0cbed50a without scan 46 (see test_cylinder_second_look):
    # 300 sampled points are the density of the default 3000 on the whole sweep, at which the
    # back wall at y = 6 m (sampled about every 0.15 m) was not one piece of 0.1 m cells and was
    # missed in 10 of 10 draws
    pts = _points()
    bg = background_planes(pts, DetectOptions(wall_sample=300), np.random.default_rng(seed))
    assert any(_is_back_wall(n, o) for n, o in bg.planes), bg.planes


@pytest.mark.parametrize("n", [60, 300, 3000])
def test_a_random_sample_of_a_wall_is_one_piece_at_any_density(n: int) -> None:
    rng = np.random.default_rng(n)
    wall = np.column_stack([rng.uniform(0.0, 3.0, n), np.full(n, 6.0), rng.uniform(0.0, 2.0, n)])
    assert _plane_extent(wall, np.array([0.0, 1.0, 0.0])) > 1.8


def test_objects_apart_in_one_plane_are_not_one_piece() -> None:
    # a dense 0.07 m strip (a cylinder's front) and two dense patches 0.6 m to either side, in line
    rng = np.random.default_rng(3)
    strip = np.column_stack([rng.uniform(0.0, 0.07, 300), np.zeros(300), rng.uniform(0.0, 1.0, 300)])
    left = np.column_stack([rng.uniform(-0.8, -0.6, 100), np.zeros(100), rng.uniform(0.0, 0.2, 100)])
    right = left + np.array([1.47, 0.0, 0.0])
    on = np.vstack([strip, left, right])
    uv = on[:, [0, 2]]
    assert plane_cell(uv) == WALL_CELL  # dense: the smallest cell
    assert _plane_extent(on, np.array([0.0, 1.0, 0.0])) < 0.1


def test_sampled_points_inside_a_wall_piece_join_the_wall() -> None:
    # on 300 sampled points the 32-neighbour normals straddle corners: a fifth of the back wall's
    # samples missed its normal gate and each kept the cloud's wall points nearest it in the
    # cylinder RANSAC's pool (share kept over 6 draws: 0.30 before, 0.20 with them joined)
    pts = _points()
    wall = np.flatnonzero(np.abs(pts[:, 1] - 6.0) < 0.03)
    kept = []
    for seed in range(6):
        bg = background_planes(pts, DetectOptions(wall_sample=300), np.random.default_rng(seed))
        kept.append(bg.off(pts, wall, 0.03).size / wall.size)
    assert np.mean(kept) < 0.23, kept
