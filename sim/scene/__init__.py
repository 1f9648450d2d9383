"""The simulated world: shapes, scenes, exact vectorized ray casting and the LMS100 sensor model.

Typical use (a noisy LRMS sweep of seed 003's cylinder)::

    from lrms.kinematics import RigCalibration
    from sim.scene import SensorModel, get_scene, sweep_cloud
    cloud, samples = sweep_cloud(get_scene("seed003"), RigCalibration(), SensorModel(),
                                 np.deg2rad(np.arange(-20, 70, 0.1)), rng=np.random.default_rng(1))
"""

from sim.scene.library import (
    SEED003_AXIS_DIRECTION,
    SEED003_AXIS_POINT,
    SEED003_DIAMETER,
    SEED003_HEIGHT,
    describe_scene,
    get_scene,
    list_scenes,
    register_scene,
)
from sim.scene.scene import Hits, Scene, SceneObject
from sim.scene.sensor import (
    SIGMA_ALPHA_SEED003,
    SIGMA_BETA_SEED003,
    SIGMA_L_SEED003,
    BeamSamples,
    SensorModel,
    beam_times,
    cast_beams,
    continuous_sweep_cloud,
    lms1xx_device_angles,
    simulate_sweep,
    sweep_cloud,
)
from sim.scene.shapes import T_MIN, Box, Cylinder, Plane, SceneError, Shape, Sphere, TorusSection

__all__ = [
    "SEED003_AXIS_DIRECTION",
    "SEED003_AXIS_POINT",
    "SEED003_DIAMETER",
    "SEED003_HEIGHT",
    "SIGMA_ALPHA_SEED003",
    "SIGMA_BETA_SEED003",
    "SIGMA_L_SEED003",
    "T_MIN",
    "BeamSamples",
    "Box",
    "Cylinder",
    "Hits",
    "Plane",
    "Scene",
    "SceneError",
    "SceneObject",
    "SensorModel",
    "Shape",
    "Sphere",
    "TorusSection",
    "beam_times",
    "cast_beams",
    "continuous_sweep_cloud",
    "describe_scene",
    "get_scene",
    "list_scenes",
    "lms1xx_device_angles",
    "register_scene",
    "simulate_sweep",
    "sweep_cloud",
]
