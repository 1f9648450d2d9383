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
from sim.scene.lms1xx import (
    LMS1XX_DIVERGENCE,
    LMS1XX_EXIT_DIAMETER,
    SENSOR_NAMES,
    Footprint,
    LMS1xxSensor,
    RangeSystematics,
    SubRayHits,
    make_sensor,
    sensor_name,
)
from sim.scene.scene import Hits, Scene, SceneObject
from sim.scene.sensor import (
    SIGMA_ALPHA_SEED003,
    SIGMA_BETA_SEED003,
    SIGMA_L_SEED003,
    BeamSamples,
    Echoes,
    Sensor,
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
    "LMS1XX_DIVERGENCE",
    "LMS1XX_EXIT_DIAMETER",
    "SEED003_AXIS_DIRECTION",
    "SEED003_AXIS_POINT",
    "SEED003_DIAMETER",
    "SEED003_HEIGHT",
    "SENSOR_NAMES",
    "SIGMA_ALPHA_SEED003",
    "SIGMA_BETA_SEED003",
    "SIGMA_L_SEED003",
    "T_MIN",
    "BeamSamples",
    "Box",
    "Cylinder",
    "Echoes",
    "Footprint",
    "Hits",
    "LMS1xxSensor",
    "Plane",
    "RangeSystematics",
    "Scene",
    "SceneError",
    "SceneObject",
    "Sensor",
    "SensorModel",
    "Shape",
    "Sphere",
    "SubRayHits",
    "TorusSection",
    "beam_times",
    "cast_beams",
    "continuous_sweep_cloud",
    "describe_scene",
    "get_scene",
    "list_scenes",
    "lms1xx_device_angles",
    "make_sensor",
    "register_scene",
    "sensor_name",
    "simulate_sweep",
    "sweep_cloud",
]
