"""Checks shared by the calibration scenes' tests (``room-spheres-axis``, ``hall-spheres-axis``):
a rig pose's matrix, the scene's spheres against their documented layout, the artefact's
distances against the layout's centres, and the beam along a pose's shaft meeting its far sphere."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lrms.calibration import Artefact
from lrms.kinematics import RigCalibration
from sim.scene import Scene, SensorModel, Sphere, cast_beams, get_scene, list_scenes

D = np.deg2rad

#: (centre m, diameter m) of each sphere, as the scene library lists them
Layout = Sequence[tuple[tuple[float, float, float], float]]
#: (position m, turn about z deg, tip about x deg) of a rig pose
Pose = tuple[tuple[float, float, float], float, float]


def pose_matrix(t: tuple[float, float, float], yaw_deg: float, tip_deg: float) -> np.ndarray:
    """The rig frame's pose: turned ``yaw_deg`` about z after a tip of ``tip_deg`` about x, at ``t``."""
    cz, sz, cx, sx = np.cos(D(yaw_deg)), np.sin(D(yaw_deg)), np.cos(D(tip_deg)), np.sin(D(tip_deg))
    m = np.eye(4)
    m[:3, :3] = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    m[:3, 3] = t
    return m


def assert_scene_spheres(name: str, layout: Layout) -> Scene:
    """The scene ``name`` is listed and its spheres are ``layout``'s, named ``sphere0``, ... in order."""
    assert name in list_scenes()
    scene = get_scene(name)
    spheres = [o for o in scene.objects if isinstance(o.shape, Sphere)]
    assert [o.name for o in spheres] == [f"sphere{i}" for i in range(len(layout))]
    for o, (centre, diameter) in zip(spheres, layout, strict=True):
        assert isinstance(o.shape, Sphere)
        np.testing.assert_array_equal(o.shape.center, centre)
        assert o.shape.radius == diameter / 2
    return scene


def assert_artefact_matches(artefact: dict[str, object], layout: Layout) -> None:
    """The artefact has ``layout``'s spheres and all their centre distances, to 1e-12 m."""
    art = Artefact.from_dict(artefact)
    n = len(layout)
    assert len(art.spheres) == n and len(art.distances) == n * (n - 1) // 2
    for d in art.distances:
        ca, cb = (np.asarray(layout[k][0]) for k in (d.a, d.b))
        assert abs(d.distance_m - np.linalg.norm(cb - ca)) < 1e-12


def assert_shaft_meets_sphere(
    scene: Scene, pose: Pose, k: int, centre: np.ndarray, expected_m: float
) -> tuple[np.ndarray, float]:
    """The beam along ``pose``'s shaft (device angle 90 deg) meets ``sphere{k}`` from at least 75 %
    of a -170..170 deg sweep's motor angles, and the sphere's centre lies ``expected_m`` (5 cm)
    along the shaft; returns the ranges of those hits and the distance along the shaft."""
    t, yaw, tip = pose
    m = pose_matrix(t, yaw, tip)
    motor = D(np.arange(-170.0, 171.0, 10.0))[:, None]
    cal = RigCalibration(world_from_rig=m)
    s = cast_beams(scene, cal, SensorModel.noiseless(), np.array([D(90.0)]), motor, np.random.default_rng(0))
    hit = s.valid[:, 0] & (s.index[:, 0] == scene.index_of(f"sphere{k}"))
    assert hit.mean() >= 0.75, (k, hit.mean())
    along = float((centre - np.asarray(t)) @ m[:3, 1])
    assert abs(along - expected_m) < 0.05, (k, along)
    return np.asarray(s.ranges[hit, 0]), along
