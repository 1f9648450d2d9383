"""The ``room-spheres-axis`` calibration scene (issue 12, docs/calibration.md "The axis layout"):
its spheres are where the docs say, and each rig pose looks along its shaft at its far sphere."""

from __future__ import annotations

import numpy as np

from sim.scene import get_scene
from sim.scene.library import ROOM_AXIS_POSES, ROOM_AXIS_SPHERES, ROOM_WALLS, ROOM_YAW_DEG, room_axis_artefact
from tests.sim._scenes import D, assert_artefact_matches, assert_scene_spheres, assert_shaft_meets_sphere


def test_axis_scene_has_the_documented_spheres_inside_the_room_and_its_artefact_matches() -> None:
    assert_scene_spheres("room-spheres-axis", ROOM_AXIS_SPHERES)
    yaw = D(ROOM_YAW_DEG)
    to_room = np.array([[np.cos(yaw), np.sin(yaw), 0], [-np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    lo = np.array([ROOM_WALLS["x_min"], ROOM_WALLS["y_min"], ROOM_WALLS["z_min"]])
    hi = np.array([ROOM_WALLS["x_max"], ROOM_WALLS["y_max"], ROOM_WALLS["z_max"]])
    for centre, diameter in ROOM_AXIS_SPHERES:
        c = to_room @ np.asarray(centre)
        assert np.all(c - diameter / 2 > lo + 0.2) and np.all(c + diameter / 2 < hi - 0.2)  # clear of the walls
    assert_artefact_matches(room_axis_artefact(), ROOM_AXIS_SPHERES)
    assert len(ROOM_AXIS_SPHERES) == 5  # so the artefact holds all 10 centre distances


def test_each_pose_looks_along_its_shaft_at_its_far_sphere() -> None:
    """Sphere k straddles pose k's shaft line: the beam along the shaft (device angle 90 deg) from
    most motor angles of a -170..170 deg sweep meets it, at the documented distance."""
    scene = get_scene("room-spheres-axis")
    for k, (pose, expected_m) in enumerate(zip(ROOM_AXIS_POSES, (4.8, 2.0, 3.3), strict=True)):
        centre, diameter = ROOM_AXIS_SPHERES[k]
        r, along = assert_shaft_meets_sphere(scene, pose, k, np.asarray(centre), expected_m)
        # the near half of the sphere, its front on the line at along - radius
        assert np.all(r >= along - diameter / 2 - 0.01) and np.all(r < along)
        assert abs(np.min(r) - (along - diameter / 2)) < 0.03
