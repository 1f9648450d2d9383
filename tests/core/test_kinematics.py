"""Eq. 1 of seed 003 and the rig calibration."""

from __future__ import annotations

import numpy as np
import pytest

from lrms import kinematics as k
from lrms.errors import LrmsError


def test_forward_matches_eq1_by_hand() -> None:
    l, a, b, p = 2.0, np.deg2rad(30), np.deg2rad(20), 0.1
    x = l * np.sin(a) * np.cos(b) + p * np.cos(b)
    y = l * np.cos(a)
    z = l * np.sin(a) * np.sin(b) + p * np.sin(b)
    np.testing.assert_allclose(k.forward(l, a, b, p), [x, y, z], rtol=0, atol=1e-15)


def test_inverse_round_trip() -> None:
    rng = np.random.default_rng(1)
    l = rng.uniform(0.5, 20, 1000)
    a = rng.uniform(0.01, np.pi - 0.01, 1000)
    b = rng.uniform(-1.5, 1.5, 1000)
    l2, a2, b2 = k.inverse(k.forward(l, a, b, 0.1), 0.1)
    np.testing.assert_allclose(l2, l, atol=1e-12)
    np.testing.assert_allclose(a2, a, atol=1e-12)
    np.testing.assert_allclose(b2, b, atol=1e-12)


def test_rays_reach_the_mapped_point() -> None:
    a = np.linspace(-1, 2, 7)
    b = 0.3
    o, d = k.beam_rays(a, b, 0.1)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    np.testing.assert_allclose(o + 3.0 * d, k.forward(3.0, a, b, 0.1), atol=1e-14)


def test_jacobian_matches_finite_differences() -> None:
    x0 = np.array([2.5, 0.4, 0.2])
    j = k.jacobian(*x0, p=0.1)
    h = 1e-6
    for col in range(3):
        dx = np.zeros(3)
        dx[col] = h
        fd = (k.forward(*(x0 + dx), p=0.1) - k.forward(*(x0 - dx), p=0.1)) / (2 * h)
        np.testing.assert_allclose(j[:, col], fd, atol=1e-8)


def test_calibration_device_angles_and_world_pose() -> None:
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = [1, 2, 3]
    cal = k.RigCalibration.from_dict({"p_m": 0.1, "motor_zero_deg": 10, "world_from_rig": t.tolist()})
    # device 90 deg (straight ahead) looks along the shaft (+y) at motor angle == motor zero
    pt = cal.map_samples(2.0, np.deg2rad(90), np.deg2rad(10))
    np.testing.assert_allclose(cal.to_rig(pt), [0.1, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pt, rot @ [0.1, 2.0, 0.0] + [1, 2, 3], atol=1e-12)
    o, d = cal.world_rays(np.deg2rad(90), np.deg2rad(10))
    np.testing.assert_allclose(o + 2.0 * d, pt, atol=1e-12)
    np.testing.assert_allclose(cal.device_angle(cal.alpha(0.7)), 0.7)


def test_calibration_rejects_bad_config() -> None:
    with pytest.raises(LrmsError, match="unknown"):
        k.RigCalibration.from_dict({"p": 0.1})
    with pytest.raises(LrmsError, match="orthonormal"):
        k.RigCalibration(world_from_rig=np.diag([2.0, 1, 1, 1]))
    with pytest.raises(LrmsError, match="shape"):
        k.inverse(np.zeros((4, 2)))
    with pytest.raises(LrmsError, match="broadcast"):
        k.forward(np.ones(3), np.ones(4), 0.0)
    with pytest.raises(LrmsError, match="broadcast"):
        k.jacobian(np.ones(3), np.ones(2), 0.0)
    assert np.isnan(k.forward(np.nan, 0.5, 0.1)).all()  # no echo stays marked
