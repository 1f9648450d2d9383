"""The ``hall-spheres-axis`` calibration scene (issue 12, docs/calibration.md "The hall layout"):
its spheres are where the docs say and clear of the hall's walls, its artefact's distances are
theirs, and each rig pose looks along its shaft at its far sphere with no sphere hiding another."""

from __future__ import annotations

import numpy as np

from sim.scene import get_scene
from sim.scene.library import (
    HALL_AXIS_POSES,
    HALL_AXIS_SPHERES,
    HALL_CENTRE,
    HALL_WALLS,
    HALL_YAW_DEG,
    hall_axis_artefact,
)
from tests.sim._scenes import D, assert_artefact_matches, assert_scene_spheres, assert_shaft_meets_sphere


def test_hall_scene_has_the_documented_spheres_inside_the_hall_and_its_artefact_matches() -> None:
    assert_scene_spheres("hall-spheres-axis", HALL_AXIS_SPHERES)
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
    assert_artefact_matches(hall_axis_artefact(), HALL_AXIS_SPHERES)
    assert len(HALL_AXIS_SPHERES) == 4  # so the artefact holds all 6 centre distances


def test_each_pose_looks_along_its_shaft_at_its_far_sphere_and_sees_every_sphere_whole() -> None:
    """Sphere k lies on pose k's shaft line at the documented distance (the beam along the shaft
    meets it at most motor angles) and, from every pose, no sphere's disc overlaps another's."""
    scene = get_scene("hall-spheres-axis")
    centres = [np.asarray(c) for c, _ in HALL_AXIS_SPHERES]
    radii = [d / 2 for _, d in HALL_AXIS_SPHERES]
    for k, (pose, expected_m) in enumerate(zip(HALL_AXIS_POSES, (9.0, 9.2, 6.6), strict=True)):
        r, along = assert_shaft_meets_sphere(scene, pose, k, centres[k], expected_m)
        assert np.all(r >= along - radii[k] - 0.01) and np.all(r < along)
        v = [c - np.asarray(pose[0]) for c in centres]
        for i in range(len(v)):
            for j in range(i + 1, len(v)):
                sep = np.arccos(v[i] @ v[j] / np.linalg.norm(v[i]) / np.linalg.norm(v[j]))
                need = np.arcsin(radii[i] / np.linalg.norm(v[i])) + np.arcsin(radii[j] / np.linalg.norm(v[j]))
                assert sep > need + D(2.0), (k, i, j)
