"""Calibration observations of three spheres before a wall, for the spot scale from sphere limbs
(issue 12; lrms/calibration/optics.py).

:func:`spheres_sweep` sweeps :func:`spheres_scene` with any sensor model on the nominal rig and
returns what ``lrms.calibration.calibrate`` takes: the observations and the artefact (the three
spheres' diameters and their three centre distances). The tests and ``bench/bench_spot_scale_disc.py``
share it, so the bench measures the scene the tests check.
"""

from __future__ import annotations

import numpy as np

from lrms.calibration import Artefact, Observations
from lrms.kinematics import RigCalibration
from sim.scene.scene import Scene
from sim.scene.sensor import Sensor, cast_beams, lms1xx_device_angles
from sim.scene.shapes import FloatArray, Plane, Sphere

#: Three spheres ahead of the rig, ``(centre m, diameter m)``; a wall at y = 4.5 m behind them.
SPOT_SPHERES: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.6, 1.5, -0.3), 0.2),
    ((-0.8, 2.4, 0.45), 0.2),
    ((0.3, 3.4, -0.2), 0.25),
)


def spheres_scene() -> Scene:
    """:data:`SPOT_SPHERES` (remission 0.8) before an infinite wall at y = 4.5 m (remission 0.5)."""
    scene = Scene("spheres")
    for i, (c, d) in enumerate(SPOT_SPHERES):
        scene.add(Sphere(np.array(c), d / 2), remission=0.8, name=f"sphere{i}")
    scene.add(Plane((0.0, 4.5, 0.0), (0.0, -1.0, 0.0)), remission=0.5, name="back_wall")
    return scene


def spheres_truth() -> list[tuple[FloatArray, float]]:
    """The spheres' true ``(centre, radius)``, as ``estimate_spot_scale`` takes them."""
    return [(np.array(c, dtype=np.float64), d / 2) for c, d in SPOT_SPHERES]


def spheres_sweep(sensor: Sensor, seed: int = 1, step_deg: float = 0.3) -> tuple[Observations, Artefact]:
    """A step-and-scan sweep of :func:`spheres_scene` by the nominal rig: motor -25..25 deg in
    ``step_deg`` steps, device beams 45..135 deg at 0.25 deg (few beams, so a footprint sensor
    stays quick), noise drawn from ``default_rng(seed)``. Returns the valid beams as observations
    and the artefact (diameters and the three exact centre distances; planes on)."""
    cal = RigCalibration()
    dev = lms1xx_device_angles(0.25)
    dev = dev[(dev > np.deg2rad(45)) & (dev < np.deg2rad(135))]
    mot = np.deg2rad(np.arange(-25.0, 25.0, step_deg))[:, None]
    s = cast_beams(spheres_scene(), cal, sensor, dev, mot, np.random.default_rng(seed))
    v = s.valid
    obs = Observations.from_raw(
        s.ranges[v], cal.alpha(np.broadcast_to(dev, v.shape))[v], cal.beta(np.broadcast_to(mot, v.shape))[v]
    )
    centres = [c for c, _ in spheres_truth()]
    n = len(centres)
    art = Artefact.from_dict(
        {
            "planes": True,
            "spheres": [{"diameter_m": d} for _, d in SPOT_SPHERES],
            "distances_m": [
                {"a": i, "b": j, "distance_m": float(np.linalg.norm(centres[i] - centres[j]))}
                for i in range(n)
                for j in range(i + 1, n)
            ],
        }
    )
    return obs, art
