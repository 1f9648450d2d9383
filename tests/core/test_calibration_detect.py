"""Detection of the calibration surfaces (issue 12): a slab of the loose plane threshold through the
caps of reference spheres whose fronts line up is no plane of the room; its points are the
spheres' (docs/calibration.md, "Spurious planes on the spheres")."""

from __future__ import annotations

import numpy as np

from lrms.calibration import Artefact
from lrms.calibration.detect import DetectOptions, detect_surfaces, plane_support_ok

RADIUS = 0.25
#: Three 0.5 m spheres 3 m out, their fronts (seen from the rig at the origin) on one plane y ~ 2.75 m,
#: in a triangle (a slab through their caps spreads in two directions, as a plane must).
CENTRES = np.array([[-0.6, 3.0, -0.4], [0.6, 3.0, -0.4], [0.0, 3.0, 0.6]])


def sphere_hits(rng: np.random.Generator, centre: np.ndarray, n: int) -> np.ndarray:
    """``n`` points where rays from the origin, uniform in solid angle, meet the sphere (as a
    scanner samples it: densest at the cap facing the rig)."""
    d0 = centre / np.linalg.norm(centre)
    cos_max = np.cos(np.arcsin(RADIUS / np.linalg.norm(centre)))
    cos_t, phi = rng.uniform(cos_max, 1.0, 3 * n), rng.uniform(0.0, 2 * np.pi, 3 * n)
    e1 = np.cross(d0, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d0, e1)
    sin_t = np.sqrt(1.0 - cos_t**2)
    d = cos_t[:, None] * d0 + (sin_t * np.cos(phi))[:, None] * e1 + (sin_t * np.sin(phi))[:, None] * e2
    a = d @ centre
    disc = RADIUS**2 - (centre @ centre - a * a)
    ok = disc > 0
    t = a[ok] - np.sqrt(disc[ok])
    return np.asarray((t[:, None] * d[ok])[:n])


def scene(rng: np.random.Generator, wall: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A floor (z = -1 m, 20,000 points), the three spheres (16,000, 6,000, 6,000 hits) and, with
    ``wall``, a wall 3 cm behind the spheres' backs (y = 3.28 m, 6 x 2.9 m clear of the floor, 8,000 points, also in
    their shadows); 10 mm noise. Returns the points and each one's label (0 floor, 1-3 the
    spheres, 4 the wall)."""
    parts = [np.column_stack([rng.uniform(-2, 2, 20_000), rng.uniform(0.5, 4, 20_000), np.full(20_000, -1.0)])]
    parts += [sphere_hits(rng, c, n) for c, n in zip(CENTRES, (16_000, 6000, 6000), strict=True)]
    if wall:
        parts.append(np.column_stack([rng.uniform(-3, 3, 8000), np.full(8000, 3.28), rng.uniform(-0.9, 2, 8000)]))
    label = np.concatenate([np.full(len(p), k) for k, p in enumerate(parts)])
    return np.concatenate(parts) + rng.normal(scale=0.01, size=(len(label), 3)), label


ARTEFACT = Artefact.from_dict({"planes": True, "spheres": [{"diameter_m": 2 * RADIUS}] * 3})


def test_a_slab_through_the_caps_of_spheres_is_not_a_plane() -> None:
    """The slab y = 2.75 +- 0.06 m holds about 70 % of every sphere's hits: more than a plane needs,
    spread over 1 m in two directions, and the big sphere's cap more than half of it: the plane
    detection alone takes it (and with seed 0 another slab of the rims), leaving the spheres
    100-2,900 of their hits (this test failed so before the rule). Its points on the found
    spheres are the spheres'; without them nothing is left for a plane: no plane but the floor,
    and every sphere keeps all its hits."""
    for seed in (0, 1):
        pts, label = scene(np.random.default_rng(seed))
        planes, spheres = detect_surfaces(pts, ARTEFACT, DetectOptions(), np.random.default_rng(0))
        assert len(planes) == 1 and abs(abs(planes[0].normal[2]) - 1.0) < 1e-3  # the floor
        assert np.all(label[planes[0].index] == 0)
        assert len(spheres) == 3
        for s in spheres:
            own = label[s.index]
            k = int(np.bincount(own).argmax())
            assert np.count_nonzero(own == k) >= 0.99 * np.count_nonzero(label == k), (seed, k)
            assert np.linalg.norm(s.center - CENTRES[k - 1]) < 0.01


def test_a_wall_behind_the_spheres_keeps_its_points() -> None:
    """Only points on the side of a found sphere's surface facing the rig are taken off a plane: a
    wall 3 cm behind the spheres' backs (within the sphere threshold of their shells) stays a plane
    with all its points."""
    pts, label = scene(np.random.default_rng(5), wall=True)
    planes, spheres = detect_surfaces(pts, ARTEFACT, DetectOptions(), np.random.default_rng(0))
    walls = [p for p in planes if abs(abs(p.normal[1]) - 1.0) < 1e-2 and abs(abs(p.offset) - 3.28) < 0.02]
    assert len(walls) == 1
    assert np.count_nonzero(label[walls[0].index] == 4) == np.count_nonzero(label == 4)
    assert len(spheres) == 3


def test_one_cap_with_leftovers_of_the_walls_is_not_a_plane() -> None:
    """The hall layout's far sphere (0.5 m, 9 m out on the shaft; docs/calibration.md, "A lost far
    sphere"): a RANSAC slab y = 8.8 +- 0.06 m holding about 65 % of its hits (one connected cap,
    0.5 m across) and 160 leftovers of the room's surfaces where the slab cuts them (a bent floor,
    ceiling and side walls beyond the plane threshold). The leftovers spread the slab over metres,
    so it passed the plane tests and took the sphere (seed 11 run 6 of the hall bench: a 4,106-beam
    "plane", variance factor 1.14, k1 without its longest lever). The extent is now that of the
    slab's main patch, the cap alone (0.12 m): not a plane. A wall (3 x 2 m) with the same
    leftovers still is one."""
    rng = np.random.default_rng(3)
    n_edge = 40
    x, z = rng.uniform(-4.2, 4.2, n_edge), rng.uniform(-1.3, 2.7, n_edge)
    edges = np.concatenate([
        np.column_stack([x, np.full(n_edge, 8.8), np.full(n_edge, -1.2)]),
        np.column_stack([x, np.full(n_edge, 8.8), np.full(n_edge, 2.6)]),
        np.column_stack([np.full(n_edge, -4.1), np.full(n_edge, 8.8), z]),
        np.column_stack([np.full(n_edge, 4.1), np.full(n_edge, 8.8), z]),
    ])  # fmt: skip
    cap = sphere_hits(rng, np.array([0.0, 9.0, 0.0]), 5000) + rng.normal(scale=0.02, size=(5000, 3))
    cap = cap[np.abs(cap[:, 1] - 8.8) < 0.06]
    assert 3000 < len(cap) < 3500
    slab = np.concatenate([cap, edges])
    assert not plane_support_ok(slab, np.arange(len(slab)), DetectOptions(), np.random.default_rng(0))
    wall = np.column_stack([rng.uniform(-1.5, 1.5, 3000), np.full(3000, 8.8), rng.uniform(-1.0, 1.0, 3000)])
    wall = np.concatenate([wall, edges]) + rng.normal(scale=0.01, size=(len(wall) + len(edges), 3))
    assert plane_support_ok(wall, np.arange(len(wall)), DetectOptions(), np.random.default_rng(0))
