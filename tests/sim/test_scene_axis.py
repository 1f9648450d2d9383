"""The ``room-spheres-axis`` calibration scene (issue 12, docs/calibration.md "The axis layout"):
its spheres are where the docs say, and each rig pose looks along its shaft at its far sphere."""

from __future__ import annotations

import numpy as np

from lrms.calibration import Artefact
from lrms.kinematics import RigCalibration
from sim.scene import SensorModel, Sphere, cast_beams, get_scene, list_scenes
from sim.scene.library import ROOM_AXIS_POSES, ROOM_AXIS_SPHERES, ROOM_WALLS, ROOM_YAW_DEG, room_axis_artefact

D = np.deg2rad


def pose_matrix(t: tuple[float, float, float], yaw_deg: float, tip_deg: float) -> np.ndarray:
    cz, sz, cx, sx = np.cos(D(yaw_deg)), np.sin(D(yaw_deg)), np.cos(D(tip_deg)), np.sin(D(tip_deg))
    m = np.eye(4)
    m[:3, :3] = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    m[:3, 3] = t
    return m


def test_axis_scene_has_the_documented_spheres_inside_the_room_and_its_artefact_matches() -> None:
    assert "room-spheres-axis" in list_scenes()
    scene = get_scene("room-spheres-axis")
    spheres = [o for o in scene.objects if isinstance(o.shape, Sphere)]
    assert [o.name for o in spheres] == [f"sphere{i}" for i in range(len(ROOM_AXIS_SPHERES))]
    yaw = D(ROOM_YAW_DEG)
    to_room = np.array([[np.cos(yaw), np.sin(yaw), 0], [-np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    lo = np.array([ROOM_WALLS["x_min"], ROOM_WALLS["y_min"], ROOM_WALLS["z_min"]])
    hi = np.array([ROOM_WALLS["x_max"], ROOM_WALLS["y_max"], ROOM_WALLS["z_max"]])
    for o, (centre, diameter) in zip(spheres, ROOM_AXIS_SPHERES, strict=True):
        assert isinstance(o.shape, Sphere)
        np.testing.assert_array_equal(o.shape.center, centre)
        assert o.shape.radius == diameter / 2
        c = to_room @ np.asarray(centre)
        assert np.all(c - diameter / 2 > lo + 0.2) and np.all(c + diameter / 2 < hi - 0.2)  # clear of the walls
    art = Artefact.from_dict(room_axis_artefact())
    assert len(art.spheres) == 5 and len(art.distances) == 10
    for d in art.distances:
        ca, cb = (np.asarray(ROOM_AXIS_SPHERES[k][0]) for k in (d.a, d.b))
        assert abs(d.distance_m - np.linalg.norm(cb - ca)) < 1e-12


def test_each_pose_looks_along_its_shaft_at_its_far_sphere() -> None:
    """Sphere k straddles pose k's shaft line: the beam along the shaft (device angle 90 deg) from
    most motor angles of a -170..170 deg sweep meets it, at the documented distance."""
    scene = get_scene("room-spheres-axis")
    motor = D(np.arange(-170.0, 171.0, 10.0))[:, None]
    for k, ((t, yaw, tip), expected_m) in enumerate(zip(ROOM_AXIS_POSES, (4.8, 2.0, 3.3), strict=True)):
        cal = RigCalibration(world_from_rig=pose_matrix(t, yaw, tip))
        s = cast_beams(scene, cal, SensorModel.noiseless(), np.array([D(90.0)]), motor, np.random.default_rng(0))
        hit = s.valid[:, 0] & (s.index[:, 0] == scene.index_of(f"sphere{k}"))
        assert hit.mean() >= 0.75, (k, hit.mean())
        centre, diameter = ROOM_AXIS_SPHERES[k]
        shaft = pose_matrix(t, yaw, tip)[:3, 1]
        along = float((np.asarray(centre) - np.asarray(t)) @ shaft)
        assert abs(along - expected_m) < 0.05
        r = s.ranges[hit, 0]  # the near half of the sphere, its front on the line at along - radius
        assert np.all(r >= along - diameter / 2 - 0.01) and np.all(r < along)
        assert abs(np.min(r) - (along - diameter / 2)) < 0.03
