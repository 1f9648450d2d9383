"""The elbow model (seed 000 Eq. 1-9) against hand geometry, and its analytic derivatives."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lrms.elbow.gauss_helmert import apply_update, design_matrices
from lrms.elbow.model import (
    BEND,
    END,
    START,
    ElbowParams,
    condition,
    condition_seed,
    euler_from_matrix,
    euler_jacobian,
    parse_degree,
    parse_ratio,
    portions,
    r1,
    r2,
    r3,
    rotation_matrix,
)
from lrms.errors import LrmsError
from sim.scene.joints import TABLE1, make_joint, random_pose


def test_rotation_matrices_are_the_passive_ones() -> None:
    a = 0.3
    # a frame rotation: the X axis of a frame turned by +a about Z has world coordinates (cos a, sin a, 0);
    # in the new frame that world vector reads (1, 0, 0)
    np.testing.assert_allclose(r3(a) @ np.array([math.cos(a), math.sin(a), 0.0]), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r1(a) @ np.array([0.0, math.cos(a), math.sin(a)]), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(r2(a) @ np.array([math.sin(a), 0.0, math.cos(a)]), [0, 0, 1], atol=1e-15)
    for r in (r1(a), r2(a), r3(a)):
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_euler_round_trip() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        om, ps, ka = rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(-3, 3)
        rot = rotation_matrix(om, ps, ka)
        np.testing.assert_allclose(rot, r2(ka) @ r3(ps) @ r1(om), atol=1e-15)
        back = euler_from_matrix(rot)
        np.testing.assert_allclose(rotation_matrix(*back), rot, atol=1e-12)
        np.testing.assert_allclose(back, (om, ps, ka), atol=1e-9)


def test_euler_jacobian_matches_finite_differences() -> None:
    from scipy.spatial.transform import Rotation

    om, ps, ka = 0.4, -0.7, 2.1
    rot = rotation_matrix(om, ps, ka)
    jac = euler_jacobian(om, ps, ka)
    h = 1e-7
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        plus = np.array(euler_from_matrix(Rotation.from_rotvec(-w).as_matrix() @ rot))
        minus = np.array(euler_from_matrix(Rotation.from_rotvec(w).as_matrix() @ rot))
        np.testing.assert_allclose((plus - minus) / (2 * h), jac[:, k], atol=1e-6)


def _hand_elbow(A: float = 0.1, D: float = 0.1, deg: float = 90.0, df: float | None = None) -> ElbowParams:
    return ElbowParams(np.zeros(3), np.eye(3), A, D, math.radians(deg), df)


def test_hand_geometry_points_on_the_surface() -> None:
    p = _hand_elbow(A=0.1, D=0.1, deg=90.0)
    r = 0.05
    pts = np.array(
        [
            [0.0, 0.0, 0.1 + r],  # outer side at the bend start (theta = 90 deg)
            [0.0, r, 0.1],  # top of the tube at the bend start
            [-(0.1 + r) * math.cos(math.radians(10)), 0.0, (0.1 + r) * math.sin(math.radians(10))],  # outer, 170 deg
            [-(0.1 - r) * math.cos(math.pi / 4), 0.0, (0.1 - r) * math.sin(math.pi / 4)],  # inner side mid-bend
            [0.3, 0.0, 0.1 - r],  # on the start leg, 0.3 m out
            [-0.1, -r, -0.4],  # on the end leg (along -Z for 90 deg)
        ]
    )
    np.testing.assert_allclose(condition(pts, p), 0.0, atol=1e-15)
    np.testing.assert_allclose(condition_seed(pts, p), 0.0, atol=1e-15)
    np.testing.assert_array_equal(portions(pts, p), [BEND, BEND, BEND, BEND, START, END])
    # a point 7 mm outside and 3 mm inside, anywhere: the condition is the signed distance
    out = np.array([[0.0, 0.0, 0.1 + r + 0.007], [0.25, 0.0, 0.1 + r - 0.003], [-0.1, r + 0.007, -0.2]])
    np.testing.assert_allclose(condition(out, p), [0.007, -0.003, 0.007], atol=1e-15)
    # the seed's algebraic form has the same sign and zero set: (s - R)(s + R)
    s = condition(out, p) + r
    np.testing.assert_allclose(condition_seed(out, p), (s - r) * (s + r), atol=1e-15)


def test_45_degree_end_leg_direction() -> None:
    p = _hand_elbow(A=0.1, D=0.1, deg=45.0)
    th0 = math.radians(135.0)
    centre_end = 0.1 * np.array([math.cos(th0), 0.0, math.sin(th0)])
    along = np.array([-math.sin(th0), 0.0, math.cos(th0)])  # leaving the bend
    outward = np.array([math.cos(th0), 0.0, math.sin(th0)])
    pts = centre_end + 0.2 * along + 0.05 * outward
    assert condition(pts[None], p)[0] == pytest.approx(0.0, abs=1e-15)
    assert portions(pts[None], p)[0] == END


def test_flange_radius_on_the_legs() -> None:
    p = _hand_elbow(A=0.1, D=0.1, deg=90.0, df=0.16)
    pts = np.array(
        [[0.2, 0.0, 0.1 + 0.08], [-0.1 - 0.08, 0.0, -0.3], [-0.15 * math.sqrt(0.5), 0.0, 0.15 * math.sqrt(0.5)]]
    )
    np.testing.assert_allclose(condition(pts, p), 0.0, atol=1e-12)


def test_world_pose_and_flipped_labelling_describe_the_same_surface() -> None:
    rng = np.random.default_rng(5)
    for name in ("a", "d", "g"):
        c, rot = random_pose(rng)
        j = make_joint(name, center=c, rot=rot, n_along=40, step_deg=6.0)
        np.testing.assert_allclose(condition(j.points, j.truth), 0.0, atol=1e-12)
        flip = j.truth.flipped()
        if TABLE1[name].flange is False:
            np.testing.assert_allclose(condition(j.points, flip), 0.0, atol=1e-12)
        assert not np.allclose(flip.rot, j.truth.rot)


@pytest.mark.parametrize("ratio,flange", [(None, False), (1.5, False), (None, True)])
def test_design_matrices_match_finite_differences(ratio: float | None, flange: bool) -> None:
    rng = np.random.default_rng(2)
    c, rot = random_pose(rng, extent=1.0)
    name = "g" if flange else "b"
    j = make_joint(name, center=c, rot=rot, n_along=30, step_deg=10.0, noise=0.002, rng=rng)
    p = j.truth
    if ratio is not None:
        p = replace(p, A=ratio * p.D)
    f, amat, b = design_matrices(j.points, p, ratio=ratio, flange=flange)
    u = amat.shape[1]
    h = 1e-7
    for k in range(u):
        d = np.zeros(u)
        d[k] = h
        fp = condition(j.points, apply_update(p, d, ratio, flange))
        fm = condition(j.points, apply_update(p, -d, ratio, flange))
        np.testing.assert_allclose((fp - fm) / (2 * h), amat[:, k], atol=2e-6, err_msg=f"column {k}")
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (condition(j.points + e, p) - condition(j.points - e, p)) / (2 * h)
        np.testing.assert_allclose(fd, b[:, k], atol=2e-6)
    np.testing.assert_allclose(f, condition(j.points, p), atol=1e-15)


def test_parse_degree_and_ratio() -> None:
    assert parse_degree("90") == pytest.approx(math.pi / 2)
    assert parse_degree("30.5") == pytest.approx(math.radians(30.5))
    assert parse_ratio("free") is None
    assert parse_ratio("1.5") == 1.5
    for bad in ("0", "190", "ninety"):
        with pytest.raises(LrmsError):
            parse_degree(bad)
    for bad in ("0.3", "x"):
        with pytest.raises(LrmsError):
            parse_ratio(bad)
