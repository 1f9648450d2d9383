"""Exact ray intersections of every shape against hand-computed geometry."""

from __future__ import annotations

import numpy as np
import pytest

from sim.scene import Box, Cylinder, Plane, SceneError, Sphere, TorusSection


def rays(*pairs: tuple[tuple[float, float, float], tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    o = np.array([p[0] for p in pairs], dtype=float)
    d = np.array([p[1] for p in pairs], dtype=float)
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


# ---------------------------------------------------------------- planes
def test_infinite_plane_hits_both_faces_and_misses_parallel_and_behind() -> None:
    plane = Plane((0, 3, 0), (0, -1, 0))
    o, d = rays(
        ((0, 0, 0), (0, 1, 0)),  # head on: 3 m
        ((1, 0, 0), (0, 1, 1)),  # 45 deg: 3 sqrt 2
        ((0, 5, 0), (0, -1, 0)),  # from behind: 2 m
        ((0, 0, 0), (1, 0, 0)),  # parallel: miss
        ((0, 0, 0), (0, -1, 0)),  # pointing away: miss
    )
    t, n = plane.intersect(o, d)
    np.testing.assert_allclose(t[:3], [3.0, 3 * np.sqrt(2), 2.0], rtol=0, atol=1e-12)
    assert np.all(np.isinf(t[3:]))
    np.testing.assert_allclose(n[0], [0, -1, 0])
    assert np.all(np.isnan(n[3:]))


def test_finite_plane_is_a_rectangle() -> None:
    rect = Plane((0, 2, 0), (0, -1, 0), size=(1.0, 0.4), u_axis=(1, 0, 0))  # x in [-0.5, 0.5], z in [-0.2, 0.2]
    o, d = rays(
        ((0.49, 0, 0.19), (0, 1, 0)),
        ((0.51, 0, 0.0), (0, 1, 0)),
        ((0.0, 0, 0.21), (0, 1, 0)),
        ((0.5, 0, -0.2), (0, 1, 0)),  # exactly on the corner: inside (closed rectangle)
    )
    t, _ = rect.intersect(o, d)
    np.testing.assert_allclose(t[[0, 3]], [2.0, 2.0], atol=1e-12)
    assert np.isinf(t[1]) and np.isinf(t[2])


# ---------------------------------------------------------------- sphere
def test_sphere_outside_inside_grazing_miss() -> None:
    s = Sphere((0, 5, 0), 1.0)
    o, d = rays(
        ((0, 0, 0), (0, 1, 0)),  # front surface at 4
        ((0, 5, 0), (1, 0, 0)),  # from the centre: 1
        ((1, 0, 0), (0, 1, 0)),  # tangent at (1, 5, 0)
        ((1.001, 0, 0), (0, 1, 0)),  # just outside
    )
    t, n = s.intersect(o, d)
    np.testing.assert_allclose(t[:3], [4.0, 1.0, 5.0], atol=1e-12)
    assert np.isinf(t[3])
    np.testing.assert_allclose(n[0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(n[2], [1, 0, 0], atol=1e-12)


# ---------------------------------------------------------------- cylinder
def test_cylinder_lateral_hits_match_hand_geometry() -> None:
    r = 0.06875
    cyl = Cylinder((0.28, 2.53, -0.1), (0, 0, 1), r, 0.8)
    o, d = rays(((0.28, 0, 0), (0, 1, 0)), ((0.28 + 0.05, 0, 0.3), (0, 1, 0)))
    t, n = cyl.intersect(o, d)
    # Ray along y through the axis: front surface at y = 2.53 - r.
    assert t[0] == pytest.approx(2.53 - r, abs=1e-12)
    np.testing.assert_allclose(n[0], [0, -1, 0], atol=1e-12)
    # Offset by 5 cm: y = 2.53 - sqrt(r^2 - 0.05^2); normal (0.05, -sqrt(.), 0) / r.
    dy = np.sqrt(r**2 - 0.05**2)
    assert t[1] == pytest.approx(2.53 - dy, abs=1e-12)
    np.testing.assert_allclose(n[1], [0.05 / r, -dy / r, 0], atol=1e-12)


def test_cylinder_inside_grazing_ends_and_caps() -> None:
    cyl = Cylinder((0, 0, 0), (0, 0, 1), 1.0, 2.0)  # z in [0, 2]
    o, d = rays(
        ((0, 0, 1), (1, 0, 0)),  # from the axis: wall at 1
        ((1, -5, 1), (0, 1, 0)),  # tangent line x = 1: touches at y = 0
        ((1.0001, -5, 1), (0, 1, 0)),  # just outside: miss
        ((0, -5, 2.5), (0, 1, 0)),  # above the top end: miss
        ((0, -5, 0), (0, 5, 1)),  # from below the bottom, up into the bottom edge region
        ((0.5, 0, 5), (0, 0, -1)),  # from above along the axis direction: top cap at 3
        ((0.5, 0, -3), (0, 0, 1)),  # from below: bottom cap at 3
        ((0, 0, 1), (0, 0, 1)),  # inside, along the axis: top cap at 1
    )
    t, n = cyl.intersect(o, d)
    assert t[0] == pytest.approx(1.0, abs=1e-12)
    assert t[1] == pytest.approx(5.0, abs=1e-12)
    assert np.isinf(t[2]) and np.isinf(t[3])
    # Ray 4 enters the wall at y = -1, z = 0.2 (t = sqrt(16 + 0.16^2 * ...)): direction (0, 5, 1)/sqrt26.
    # At y = -1: s = 4 along y -> z = 0.8; point (0, -1, 0.8), inside the z range.
    assert t[4] == pytest.approx(np.sqrt(4**2 + 0.8**2), abs=1e-12)
    assert t[5] == pytest.approx(3.0, abs=1e-12) and t[6] == pytest.approx(3.0, abs=1e-12)
    np.testing.assert_allclose(n[5], [0, 0, 1])
    np.testing.assert_allclose(n[6], [0, 0, -1])
    assert t[7] == pytest.approx(1.0, abs=1e-12)


def test_uncapped_cylinder_is_an_open_tube() -> None:
    tube = Cylinder((0, 0, 0), (0, 0, 1), 1.0, 2.0, capped=False)
    o, d = rays(((0.5, 0, 5), (0, 0, -1)), ((0, 0, -1), (0, 0.6, 0.8)))
    t, _ = tube.intersect(o, d)
    assert np.isinf(t[0])  # straight through the open ends
    # Second ray: reaches radius 1 at s = 1/0.6, z = -1 + 0.8/0.6 = 0.333: inside the tube's span.
    assert t[1] == pytest.approx(1 / 0.6, abs=1e-12)


def test_tilted_cylinder_matches_rotated_geometry() -> None:
    axis = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    cyl = Cylinder((0, 4, 0), axis, 0.5, 3.0)
    o, d = rays(((0.5 * np.sqrt(2), 0, 0.5 * np.sqrt(2)), (0, 1, 0)))  # meets the axis point at 1 m along axis
    t, n = cyl.intersect(o, d)
    assert t[0] == pytest.approx(3.5, abs=1e-12)
    np.testing.assert_allclose(n[0], [0, -1, 0], atol=1e-12)


# ---------------------------------------------------------------- box
def test_box_faces_inside_edges_and_rotation() -> None:
    box = Box((0, 5, 0), (2.0, 1.0, 0.5))  # x in [-1, 1], y in [4.5, 5.5], z in [-.25, .25]
    o, d = rays(
        ((0, 0, 0), (0, 1, 0)),  # front face at 4.5
        ((0, 5, 0), (0, 1, 0)),  # inside: back face at 0.5
        ((2, 5, 0), (-1, 0, 0)),  # side face x = 1 at 1
        ((0, 0, 0.3), (0, 1, 0)),  # above: miss
        ((0, 0, 0.25), (0, 1, 0)),  # on the top face plane: grazing along it, enters at y = 4.5
        ((0, 0, 0), (0, -1, 0)),  # away
    )
    t, n = box.intersect(o, d)
    np.testing.assert_allclose(t[[0, 1, 2, 4]], [4.5, 0.5, 1.0, 4.5], atol=1e-12)
    assert np.isinf(t[3]) and np.isinf(t[5])
    np.testing.assert_allclose(n[0], [0, -1, 0])
    np.testing.assert_allclose(n[1], [0, 1, 0])
    np.testing.assert_allclose(n[2], [1, 0, 0])
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    diamond = Box((0, 5, 0), (1.0, 1.0, 1.0), [[c, -s, 0], [s, c, 0], [0, 0, 1]])
    t2, n2 = diamond.intersect(*rays(((0, 0, 0), (0, 1, 0))))
    assert t2[0] == pytest.approx(5 - np.sqrt(0.5), abs=1e-12)  # the corner points at the rig
    assert np.linalg.norm(n2[0]) == pytest.approx(1.0)


# ---------------------------------------------------------------- torus section
def test_torus_section_hits_match_hand_geometry() -> None:
    big_a, r = 1.0, 0.25
    quarter = TorusSection((0, 0, 0), (0, 0, 1), big_a, r, np.pi / 2, start=(1, 0, 0))  # angles 0..90 deg
    o, d = rays(
        ((2, 0.5, 0), (-1, 0, 0)),  # outer surface at x = sqrt(1.25^2 - 0.25)
        ((0, 0, 0), (1, 0, 0)),  # from the centre: inner surface at 0.75
        ((3, 0, 0.25), (-1, 0, 0)),  # grazing the top of the tube at (1, 0, 0.25)
        ((3, 0, 0.2501), (-1, 0, 0)),  # just above: miss
        ((0, 0, 0), (-1, 0, 0)),  # towards 180 deg: outside the section
        ((1, 0.5, 2), (0, 0, -1)),  # down through the tube centre line at 26.6 deg: top at z = r
        ((0, 0, 0), (np.cos(np.radians(95)), np.sin(np.radians(95)), 0)),  # just past the section's end
        ((0, 0, 0), (np.cos(np.radians(85)), np.sin(np.radians(85)), 0)),  # just inside it
    )
    t, n = quarter.intersect(o, d)
    assert t[0] == pytest.approx(2 - np.sqrt(1.25**2 - 0.25), abs=1e-12)
    assert t[1] == pytest.approx(0.75, abs=1e-12)
    np.testing.assert_allclose(n[1], [-1, 0, 0], atol=1e-9)
    assert t[2] == pytest.approx(2.0, abs=1e-6)
    np.testing.assert_allclose(n[2], [0, 0, 1], atol=1e-5)
    assert np.isinf(t[3]) and np.isinf(t[4]) and np.isinf(t[6])
    rho = np.hypot(1.0, 0.5)
    assert t[5] == pytest.approx(2 - np.sqrt(r**2 - (rho - big_a) ** 2), abs=1e-12)
    assert t[7] == pytest.approx(0.75, abs=1e-12)


def test_torus_from_inside_the_tube_and_far_away() -> None:
    whole = TorusSection((10, 20, 0), (0, 1, 0), 0.6, 0.1)  # full torus in the x-z plane about (10, 20, 0)
    o, d = rays(
        ((10.6, 20, 0), (0, 1, 0)),  # on the tube centre line, along the axis: wall at 0.1
        ((10.6, 0, 0), (0, 1, 0)),  # 20 m away, parallel to the axis, through the tube: 19.9
        ((10, 0, 0), (0, 1, 0)),  # through the hole: miss
    )
    t, n = whole.intersect(o, d)
    assert t[0] == pytest.approx(0.1, abs=1e-12)
    assert t[1] == pytest.approx(19.9, abs=1e-10)
    assert np.isinf(t[2])
    np.testing.assert_allclose(n[1], [0, -1, 0], atol=1e-9)


@pytest.mark.parametrize(("big_a", "r"), [(0.4, 0.1), (0.1, 0.1), (1.0, 0.01)])  # ring, horn (0.5D elbow), thin
def test_torus_random_rays_land_on_the_surface_inside_the_section(big_a: float, r: float) -> None:
    rng = np.random.default_rng(4)
    axis = np.array([0.3, -0.2, 1.0])
    tor = TorusSection((0.5, 3.0, 0.2), axis, big_a, r, np.deg2rad(135), start=(1, 1, 0))
    o = rng.normal(0, 0.05, (4000, 3))
    target = tor.center + rng.normal(0, 0.8 * big_a, (4000, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n = tor.intersect(o, d)
    hit = np.isfinite(t)
    assert 10 < hit.sum() < 4000
    p = o[hit] + t[hit, None] * d[hit]
    loc = (p - tor.center) @ tor._frame
    rho = np.hypot(loc[:, 0], loc[:, 1])
    np.testing.assert_allclose(np.hypot(rho - big_a, loc[:, 2]), r, atol=1e-12)
    assert np.all(tor.angle_of(p) <= np.deg2rad(135) + 1e-12)
    np.testing.assert_allclose(np.linalg.norm(n[hit], axis=1), 1.0)
    # The first hit: the ray crosses no part of the section's surface before it. Sampled densely:
    # a change of inside/outside between two consecutive samples that are both within the
    # section's angles is a crossing (entering through an open end changes the angle instead).
    s = np.linspace(0, 1, 400)[None, :] * t[hit, None]
    q = o[hit, None, :] + s[..., None] * d[hit, None, :]
    ql = (q - tor.center) @ tor._frame
    inside = np.hypot(np.hypot(ql[..., 0], ql[..., 1]) - big_a, ql[..., 2]) < r
    in_section = tor.angle_of(q) <= np.deg2rad(135)
    crossing = (inside[:, 1:] != inside[:, :-1]) & in_section[:, 1:] & in_section[:, :-1]
    assert not crossing[:, :-1].any()
    if r < big_a:
        assert (inside[:, :-1] & in_section[:, :-1]).any()  # some rays enter through an open end


@pytest.mark.parametrize(
    "make",
    [
        lambda: Plane((0, 0, 0), (0, 0, 0)),
        lambda: Plane((0, 0, 0), (0, 0, 1), size=(1.0, -1.0)),
        lambda: Cylinder((0, 0, 0), (0, 0, 1), 0.0, 1.0),
        lambda: Cylinder((0, 0, np.nan), (0, 0, 1), 1.0, 1.0),
        lambda: Box((0, 0, 0), (1, 1, 0)),
        lambda: Box((0, 0, 0), (1, 1, 1), np.diag([1.0, 1.0, -1.0])),
        lambda: TorusSection((0, 0, 0), (0, 0, 1), 1.0, 0.1, 7.0),
        lambda: TorusSection((0, 0, 0), (0, 0, 1), 1.0, 0.1, 1.0, start=(0, 0, 2)),
        lambda: Sphere((0, 0), 1.0),
    ],
)
def test_bad_shape_parameters_raise_typed_errors(make: object) -> None:
    with pytest.raises(SceneError):
        make()  # type: ignore[operator]
