"""The ``hall-spheres-axis`` calibration scene (issue 12, docs/calibration.md "The hall layout"):
its spheres are where the docs say and clear of the hall's walls, its artefact's distances are
theirs, and each rig pose looks along its shaft at its far sphere with no sphere hiding another."""

from __future__ import annotations

import numpy as np

from lrms.calibration import Artefact
from lrms.kinematics import RigCalibration
from sim.scene import SensorModel, Sphere, cast_beams, get_scene, list_scenes
from sim.scene.library import (
    HALL_AXIS_POSES,
    HALL_AXIS_SPHERES,
    HALL_CENTRE,
    HALL_WALLS,
    HALL_YAW_DEG,
    hall_axis_artefact,
)

D = np.deg2rad


def pose_matrix(t: tuple[float, float, float], yaw_deg: float, tip_deg: float) -> np.ndarray:
    cz, sz, cx, sx = np.cos(D(yaw_deg)), np.sin(D(yaw_deg)), np.cos(D(tip_deg)), np.sin(D(tip_deg))
    m = np.eye(4)
    m[:3, :3] = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    m[:3, 3] = t
    return m


def test_hall_scene_has_the_documented_spheres_inside_the_hall_and_its_artefact_matches() -> None:
    assert "hall-spheres-axis" in list_scenes()
    scene = get_scene("hall-spheres-axis")
    spheres = [o for o in scene.objects if isinstance(o.shape, Sphere)]
    assert [o.name for o in spheres] == [f"sphere{i}" for i in range(len(HALL_AXIS_SPHERES))]
    yaw = D(HALL_YAW_DEG)
    to_hall = np.array([[np.cos(yaw), np.sin(yaw), 0], [-np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    centre = np.array([HALL_CENTRE[0], HALL_CENTRE[1], 0.0])
    lo = np.array([HALL_WALLS["x_min"], HALL_WALLS["y_min"], HALL_WALLS["z_min"]])
    hi = np.array([HALL_WALLS["x_max"], HALL_WALLS["y_max"], HALL_WALLS["z_max"]])
    points = [(np.asarray(c), d / 2) for c, d in HALL_AXIS_SPHERES]
    points += [(np.asarray(t), 0.2) for t, _, _ in HALL_AXIS_POSES]
    for at, r in points:  # the spheres and the rigs clear of the walls
        x = centre + to_hall @ (at - centre)
        assert np.all(x - r > lo + 0.3) and np.all(x + r < hi - 0.3), at
    for o, (c, diameter) in zip(spheres, HALL_AXIS_SPHERES, strict=True):
        assert isinstance(o.shape, Sphere)
        np.testing.assert_array_equal(o.shape.center, c)
        assert o.shape.radius == diameter / 2
    art = Artefact.from_dict(hall_axis_artefact())
    assert len(art.spheres) == 4 and len(art.distances) == 6
    for d in art.distances:
        ca, cb = (np.asarray(HALL_AXIS_SPHERES[k][0]) for k in (d.a, d.b))
        assert abs(d.distance_m - np.linalg.norm(cb - ca)) < 1e-12


def test_each_pose_looks_along_its_shaft_at_its_far_sphere_and_sees_every_sphere_whole() -> None:
    """Sphere k lies on pose k's shaft line at the documented distance (the beam along the shaft
    meets it at most motor angles) and, from every pose, no sphere's disc overlaps another's."""
    scene = get_scene("hall-spheres-axis")
    motor = D(np.arange(-170.0, 171.0, 10.0))[:, None]
    centres = [np.asarray(c) for c, _ in HALL_AXIS_SPHERES]
    radii = [d / 2 for _, d in HALL_AXIS_SPHERES]
    for k, ((t, yaw, tip), expected_m) in enumerate(zip(HALL_AXIS_POSES, (9.0, 9.2, 6.6), strict=True)):
        m = pose_matrix(t, yaw, tip)
        cal = RigCalibration(world_from_rig=m)
        s = cast_beams(scene, cal, SensorModel.noiseless(), np.array([D(90.0)]), motor, np.random.default_rng(0))
        hit = s.valid[:, 0] & (s.index[:, 0] == scene.index_of(f"sphere{k}"))
        assert hit.mean() >= 0.75, (k, hit.mean())
        along = float((centres[k] - np.asarray(t)) @ m[:3, 1])
        assert abs(along - expected_m) < 0.05
        r = s.ranges[hit, 0]
        assert np.all(r >= along - radii[k] - 0.01) and np.all(r < along)
        v = [c - np.asarray(t) for c in centres]
        for i in range(len(v)):
            for j in range(i + 1, len(v)):
                sep = np.arccos(v[i] @ v[j] / np.linalg.norm(v[i]) / np.linalg.norm(v[j]))
                need = np.arcsin(radii[i] / np.linalg.norm(v[i])) + np.arcsin(radii[j] / np.linalg.norm(v[j]))
                assert sep > need + D(2.0), (k, i, j)
