"""Scenes, the ray-cast of several shapes, the sensor model's statistics, and the named scenes."""

from __future__ import annotations

import numpy as np
import pytest

from lrms.kinematics import RigCalibration
from sim.scene import (
    SEED003_AXIS_POINT,
    SEED003_DIAMETER,
    SIGMA_L_SEED003,
    Box,
    Cylinder,
    Plane,
    Scene,
    SceneError,
    SensorModel,
    Sphere,
    TorusSection,
    beam_times,
    cast_beams,
    continuous_sweep_cloud,
    get_scene,
    list_scenes,
    lms1xx_device_angles,
    simulate_sweep,
    sweep_cloud,
)

CAL = RigCalibration()
DEG = np.pi / 180


def wall_scene(y: float, remission: float = 0.7) -> Scene:
    s = Scene("test-wall")
    s.add(Plane((0, y, 0), (0, -1, 0)), remission=remission, name="wall")
    return s


def test_scene_reports_nearest_object_index_remission_and_incidence() -> None:
    s = Scene()
    far = s.add(Plane((0, 5, 0), (0, -1, 0)), remission=0.9, name="far")
    near = s.add(Sphere((0, 3, 0), 0.5), remission=0.2, name="ball")
    o = np.zeros((3, 3))
    d = np.array([[0, 1, 0], [np.sin(0.3), np.cos(0.3), 0], [0, -1, 0]], dtype=float)
    h = s.raycast(o, d)
    assert h.range[0] == pytest.approx(2.5) and h.index[0] == near and h.remission[0] == 0.2
    assert h.range[1] == pytest.approx(5 / np.cos(0.3)) and h.index[1] == far
    assert h.cos_incidence[1] == pytest.approx(np.cos(0.3))
    assert np.isinf(h.range[2]) and h.index[2] == -1 and h.remission[2] == 0 and h.cos_incidence[2] == 0
    np.testing.assert_allclose(h.points(o, d)[0], [0, 2.5, 0])
    assert s.index_of("ball") == near


def test_bounding_sphere_culling_gives_the_brute_force_answer() -> None:
    scene = get_scene("seed003")
    scene.add(TorusSection((1.5, 3.0, 0.0), (0, 0, 1), 0.3, 0.08, np.pi / 2), name="elbow")
    rng = np.random.default_rng(2)
    dirs = rng.normal(size=(20000, 3))
    dirs[:, 1] = np.abs(dirs[:, 1]) * 3
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = rng.normal(0, 0.1, (20000, 3))
    hits = scene.raycast(origins, dirs)
    brute = np.stack([obj.shape.intersect(origins, dirs)[0] for obj in scene.objects], axis=1)
    np.testing.assert_array_equal(hits.range, brute.min(axis=1))
    hit = np.isfinite(hits.range)
    np.testing.assert_array_equal(hits.index[hit], brute.argmin(axis=1)[hit])
    assert len(set(hits.index.tolist())) >= 8  # most objects are seen


def test_raycast_rejects_bad_rays_and_scene_rejects_bad_objects() -> None:
    s = Scene()
    with pytest.raises(SceneError):
        s.raycast(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(SceneError):
        s.raycast(np.zeros((1, 3)), np.array([[0.0, 2.0, 0.0]]))
    s.add(Box((0, 1, 0), (1, 1, 1)), name="b")
    with pytest.raises(SceneError):
        s.add(Box((0, 2, 0), (1, 1, 1)), name="b")
    with pytest.raises(SceneError):
        s.add(Box((0, 2, 0), (1, 1, 1)), remission=-1)
    with pytest.raises(SceneError):
        s.add("not a shape")  # type: ignore[arg-type]


# ------------------------------------------------------------------ sensor model and beams
def test_noiseless_wall_ranges_follow_the_rig_geometry() -> None:
    dev = lms1xx_device_angles(0.5)
    assert len(dev) == 541 and len(lms1xx_device_angles()) == 1081
    r = simulate_sweep(wall_scene(3.0), CAL, SensorModel.noiseless(), dev, np.array([0.0]))
    alpha = dev - np.pi / 2
    ahead = np.abs(alpha) < 80 * DEG
    # Beam from (p, 0, 0) along (sin a, cos a, 0): reaches y = 3 at 3 / cos a.
    np.testing.assert_allclose(r[0, ahead], 3 / np.cos(alpha[ahead]), rtol=0, atol=1e-12)
    assert np.all(r[0, np.abs(alpha) > 90.01 * DEG] == 0)  # looking backwards: no echo


def test_noiseless_seed003_beam_through_the_axis_hits_the_front_of_the_cylinder() -> None:
    x0, y0, _ = SEED003_AXIS_POINT
    p = CAL.p
    alpha = np.arctan2(x0 - p, y0)  # horizontal plane (beta = 0): beam aimed at the axis
    r = simulate_sweep(get_scene("seed003"), CAL, SensorModel.noiseless(), CAL.device_angle(alpha)[None], [0.0])
    assert r[0, 0] == pytest.approx(np.hypot(x0 - p, y0) - SEED003_DIAMETER / 2, abs=1e-12)


def test_range_noise_statistics_match_sigma_l() -> None:
    n = 200_000
    sensor = SensorModel(sigma_alpha=0.0, sigma_beta=0.0)
    r = cast_beams(wall_scene(2.5), CAL, sensor, np.full(n, np.pi / 2), 0.0, np.random.default_rng(7)).ranges
    err = r.ravel() - 2.5
    assert sensor.sigma_l == pytest.approx(np.sqrt(136.11e-6)) == SIGMA_L_SEED003
    assert abs(err.mean()) < 4 * SIGMA_L_SEED003 / np.sqrt(n)
    assert err.std() == pytest.approx(SIGMA_L_SEED003, rel=0.01)  # std error of the std: 0.16 %


def test_angle_noise_statistics_match_sigma_alpha_and_sigma_beta() -> None:
    n = 100_000
    rng = np.random.default_rng(11)
    # alpha noise: wall y = 3, nominal alpha 30 deg: range = 3 / cos(alpha + d_alpha).
    s_a = SensorModel(sigma_l=0.0, sigma_alpha=0.01, sigma_beta=0.0)
    r = cast_beams(wall_scene(3.0), CAL, s_a, np.full(n, CAL.device_angle(30 * DEG)), 0.0, rng).ranges
    d_alpha = np.arccos(3.0 / r) - 30 * DEG
    assert d_alpha.std() == pytest.approx(0.01, rel=0.02)
    # beta noise: ceiling z = 1, beam along alpha = 90 deg at nominal beta = 45 deg.
    ceiling = Scene()
    ceiling.add(Plane((0, 0, 1), (0, 0, -1)))
    s_b = SensorModel(sigma_l=0.0, sigma_alpha=0.0, sigma_beta=0.02)
    rb = cast_beams(ceiling, CAL, s_b, CAL.device_angle(90 * DEG), np.full(n, 45 * DEG), rng).ranges
    beta = np.arcsin(1.0 / (rb + CAL.p))  # (l + p) sin beta = 1
    assert (beta - 45 * DEG).std() == pytest.approx(0.02, rel=0.02)


def test_range_limits_and_weak_echoes_report_zero() -> None:
    sensor = SensorModel.noiseless()
    ahead = np.array([np.pi / 2])
    assert simulate_sweep(wall_scene(0.3), CAL, sensor, ahead, [0.0])[0, 0] == 0.0  # 0.3 m: too close
    assert simulate_sweep(wall_scene(25.0), CAL, sensor, ahead, [0.0])[0, 0] == 0.0  # beyond 20 m
    assert simulate_sweep(wall_scene(19.9), CAL, sensor, ahead, [0.0])[0, 0] == pytest.approx(19.9)
    assert simulate_sweep(wall_scene(3.0, remission=0.005), CAL, sensor, ahead, [0.0])[0, 0] == 0.0
    assert np.all(simulate_sweep(get_scene("empty"), CAL, SensorModel(), lms1xx_device_angles(), [0.0, 0.5]) == 0)


def test_quantum_rssi_and_seeded_reproducibility() -> None:
    sensor = SensorModel(quantum=0.001)
    dev = lms1xx_device_angles()
    a = cast_beams(get_scene("seed003"), CAL, sensor, dev, 0.2, np.random.default_rng(3))
    b = cast_beams(get_scene("seed003"), CAL, sensor, dev, 0.2, np.random.default_rng(3))
    np.testing.assert_array_equal(a.ranges, b.ranges)
    mm = a.ranges[a.valid] * 1000
    np.testing.assert_allclose(mm, np.round(mm), atol=1e-6)
    np.testing.assert_allclose(a.rssi[a.valid], 200 * a.remission[a.valid] * a.cos_incidence[a.valid])
    assert np.all(a.rssi[~a.valid] == 0)
    with pytest.raises(SceneError):
        SensorModel(sigma_l=-1.0)
    with pytest.raises(SceneError):
        SensorModel(range_min=5.0, range_max=1.0)
    with pytest.raises(SceneError):
        lms1xx_device_angles(0.1)


def test_sweep_cloud_of_seed003_puts_cylinder_points_on_the_cylinder() -> None:
    scene = get_scene("seed003")
    cloud, samples = sweep_cloud(scene, CAL, SensorModel(), np.arange(-15, 60, 1.0) * DEG, np.random.default_rng(5))
    on_cyl = samples.valid & (samples.index == scene.index_of("cylinder"))
    pts = CAL.map_samples(samples.ranges[on_cyl], samples.device_angle[on_cyl], samples.motor_angle[on_cyl])
    radial = np.hypot(pts[:, 0] - SEED003_AXIS_POINT[0], pts[:, 1] - SEED003_AXIS_POINT[1])
    assert on_cyl.sum() > 500
    # Noise is almost all along the line of sight (about the y direction here): radial residual ~ sigma_l.
    assert abs(np.median(radial) - SEED003_DIAMETER / 2) < 2e-3
    assert cloud.shape == (int(samples.valid.sum()), 3)


def test_named_scenes() -> None:
    names = list_scenes()
    assert {"seed003", "seed003-bare", "empty", "wall"} <= set(names)
    a, b = get_scene("seed003"), get_scene("seed003")
    assert a is not b and a.name == "seed003"
    assert {"cylinder", "table", "floor"} <= {o.name for o in a.objects}
    assert len(get_scene("empty")) == 0 and len(get_scene("wall")) == 1
    cyl = a.objects[a.index_of("cylinder")].shape
    assert isinstance(cyl, Cylinder) and cyl.radius == SEED003_DIAMETER / 2
    with pytest.raises(SceneError, match="unknown scene"):
        get_scene("nope")


def test_continuous_sweep_gives_every_beam_the_motor_angle_at_its_time() -> None:
    speed = np.deg2rad(20.0)  # rad/s
    cloud, s = continuous_sweep_cloud(
        get_scene("seed003"), CAL, SensorModel(), np.deg2rad(-10), np.deg2rad(50), speed, np.random.default_rng(8)
    )
    assert s.ranges.shape == (int(3.0 * 25) + 1, 1081)  # 60 deg at 20 deg/s = 3 s of 25 Hz scans
    dt = 0.04 * 0.25 / 360
    np.testing.assert_allclose(np.diff(s.motor_angle[5]), speed * dt)  # the plane turns during a scan
    np.testing.assert_allclose(s.motor_angle[1, 0] - s.motor_angle[0, 0], speed * 0.04)
    assert s.motor_angle.max() <= np.deg2rad(50) + 1e-12
    np.testing.assert_allclose(beam_times(3), [0.0, dt, 2 * dt])
    on_cyl = s.valid & (s.index == 0)
    pts = CAL.map_samples(s.ranges[on_cyl], s.device_angle[on_cyl], s.motor_angle[on_cyl])
    radial = np.hypot(pts[:, 0] - SEED003_AXIS_POINT[0], pts[:, 1] - SEED003_AXIS_POINT[1])
    assert on_cyl.sum() > 300 and abs(np.median(radial) - SEED003_DIAMETER / 2) < 2e-3
    assert cloud.shape[0] == s.valid.sum()
    with pytest.raises(SceneError):
        continuous_sweep_cloud(get_scene("wall"), CAL, SensorModel(), 0.0, 1.0, 0.0)
