"""Named scenes: ``get_scene(name)`` builds a fresh :class:`Scene`, ``list_scenes()`` names them.

Coordinates are the world frame; with the default :class:`lrms.kinematics.RigCalibration` that is
the rig frame (y on the motor shaft, z up, the LMS1xx looking along +y at device angle 90 deg).

Other modules may add scenes with :func:`register_scene`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sim.scene.scene import Scene
from sim.scene.shapes import Box, Cylinder, Plane, SceneError, Sphere, TorusSection

#: Seed 003's part: a 137.5 mm diameter cylinder (CMM value), axis (0, 0, 1) through the centre
#: of its bottom circle C0 = (0.28, 2.53, -0.1) m, standing on the table top at z = -0.1 m.
SEED003_DIAMETER = 0.1375
SEED003_AXIS_POINT = (0.28, 2.53, -0.1)
SEED003_AXIS_DIRECTION = (0.0, 0.0, 1.0)
SEED003_HEIGHT = 0.8
#: Floor level of the seed003 room (table height 0.75 m).
SEED003_FLOOR_Z = -0.85

#: The ``elbow`` scene: a 90 deg pipe elbow (D = 250 mm, bend radius A = 350 mm) about 1.8 m in
#: front of the rig, its bend plane facing the rig; a floor.
ELBOW_CENTER = (0.3, 1.8, 0.05)
ELBOW_AXIS = (0.0, -1.0, 0.0)
ELBOW_START = (1.0, 0.0, 0.0)
ELBOW_BEND_RADIUS = 0.35
ELBOW_DIAMETER = 0.25
ELBOW_DEGREE = float(np.pi / 2)

#: The ``room-spheres`` calibration scene (issue 12): a room of six planes turned 8 deg about z
#: (walls at these distances from the rig along the room's own axes, floor and ceiling) and
#: reference spheres ``(centre, diameter)`` at different ranges and heights; spheres 4 and 5
#: form a 2 m sphere bar (centre distance ``ROOM_SPHERE_BAR[2]``) running away from the rig.
ROOM_YAW_DEG = 8.0
ROOM_WALLS = {"x_min": -2.2, "x_max": 3.1, "y_min": -1.8, "y_max": 5.5, "z_min": -1.3, "z_max": 1.9}
ROOM_SPHERES: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.6, 1.5, -0.3), 0.2),
    ((-0.8, 2.4, 0.45), 0.2),
    ((1.6, 3.4, -0.7), 0.2),
    ((-0.3, 4.6, 0.25), 0.2),
    ((-0.8, 1.2, -0.5), 0.25),
    ((-1.285071, 3.140285, -0.5), 0.25),
    ((1.5, -0.9, 0.3), 0.2),
)
ROOM_SPHERE_BAR = (4, 5, np.float64(1.999999939066499))

SceneFactory = Callable[[], Scene]
_SCENES: dict[str, tuple[SceneFactory, str]] = {}


def register_scene(name: str, factory: SceneFactory, description: str = "") -> None:
    """Make ``get_scene(name)`` call ``factory()``; a name can be registered once."""
    if not name or any(c.isspace() for c in name):
        raise SceneError(f"bad scene name {name!r}")
    if name in _SCENES and _SCENES[name][0] is not factory:
        raise SceneError(f"scene {name!r} is already registered")
    _SCENES[name] = (factory, description)


def list_scenes() -> list[str]:
    """Names of all registered scenes, sorted."""
    return sorted(_SCENES)


def describe_scene(name: str) -> str:
    if name not in _SCENES:
        raise SceneError(f"unknown scene {name!r} (known: {', '.join(sorted(_SCENES))})")
    return _SCENES[name][1]


def get_scene(name: str) -> Scene:
    """A new instance of the named scene."""
    entry = _SCENES.get(name)
    if entry is None:
        raise SceneError(f"unknown scene {name!r} (known: {', '.join(sorted(_SCENES))})")
    scene = entry[0]()
    scene.name = name
    return scene


def _rot_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def add_part_on_table(
    scene: Scene,
    axis_point: tuple[float, float, float],
    diameter: float,
    height: float,
    remission: float = 0.35,
    floor_z: float = SEED003_FLOOR_Z,
) -> None:
    """A standing cylindrical part (the object "cylinder", its axis from ``axis_point`` up) on a
    table: the top's upper face at the part's foot, 0.04 m thick, at least 1.2 m x 0.8 m and 0.4 m
    larger than the part; four 0.05 m legs 0.05 m in from its corners, down to ``floor_z``."""
    x0, y0, z0 = axis_point
    scene.add(Cylinder(axis_point, SEED003_AXIS_DIRECTION, diameter / 2, height), remission=remission, name="cylinder")
    sx, sy = max(1.2, diameter + 0.4), max(0.8, diameter + 0.4)
    top = 0.04
    scene.add(Box((x0, y0, z0 - top / 2), (sx, sy, top)), remission=0.6, name="table")
    leg_h = (z0 - top) - floor_z
    for i, (fx, fy) in enumerate(((-1, -1), (1, -1), (-1, 1), (1, 1))):
        centre = (x0 + fx * (sx / 2 - 0.05), y0 + fy * (sy / 2 - 0.05), floor_z + leg_h / 2)
        scene.add(Box(centre, (0.05, 0.05, leg_h)), remission=0.4, name=f"table_leg{i}")


def add_seed003_part(scene: Scene, floor_z: float = SEED003_FLOOR_Z) -> None:
    """Seed 003's cylinder on its table (table top z = -0.1 m, 1.2 m x 0.8 m, four legs down to
    ``floor_z``)."""
    add_part_on_table(scene, SEED003_AXIS_POINT, SEED003_DIAMETER, SEED003_HEIGHT, 0.35, floor_z)


def seed003() -> Scene:
    """Seed 003's experiment with a room around it: floor, back wall, and clutter on and near the table."""
    scene = Scene("seed003")
    add_seed003_part(scene)
    z_table = SEED003_AXIS_POINT[2]
    scene.add(Plane((0.0, 0.0, SEED003_FLOOR_Z), (0.0, 0.0, 1.0)), remission=0.2, name="floor")
    scene.add(
        Plane((0.0, 6.0, 1.0), (0.0, -1.0, 0.0), size=(12.0, 4.0), u_axis=(1.0, 0.0, 0.0)),
        remission=0.7,
        name="back_wall",
    )
    scene.add(Box((0.68, 2.42, z_table + 0.075), (0.15, 0.15, 0.15), _rot_z(np.deg2rad(20.0))), 0.5, "clutter_box")
    scene.add(Cylinder((-0.02, 2.75, z_table), (0.0, 0.0, 1.0), 0.035, 0.25), remission=0.8, name="clutter_bottle")
    scene.add(Cylinder((-0.9, 3.3, SEED003_FLOOR_Z), (0.0, 0.0, 1.0), 0.05, 2.2), remission=0.5, name="clutter_post")
    return scene


#: The room of :func:`part_in_room` (``seed003-room``): walls at these x (m), the wall behind the
#: rig at this y, the ceiling at this z, and the back wall this far behind the part's far side.
ROOM_SIDE_WALLS_X = (-2.5, 3.0)
ROOM_REAR_WALL_Y = -1.5
ROOM_CEILING_Z = 2.2
ROOM_BACK_GAP = 1.2


def add_room(scene: Scene, back_wall_y: float) -> None:
    """A closed room around the rig: floor, ceiling, back wall at ``back_wall_y``, side and rear walls.

    Remissions (ours): floor 0.2 (concrete), walls 0.6 (painted), ceiling 0.5.
    """
    z0, z1 = SEED003_FLOOR_Z, ROOM_CEILING_Z
    xl, xr = ROOM_SIDE_WALLS_X
    yr = ROOM_REAR_WALL_Y
    height, zc = z1 - z0, 0.5 * (z0 + z1)
    width, xc = xr - xl, 0.5 * (xl + xr)
    depth, yc = back_wall_y - yr, 0.5 * (back_wall_y + yr)
    scene.add(Plane((0.0, 0.0, z0), (0.0, 0.0, 1.0)), remission=0.2, name="floor")
    scene.add(Plane((0.0, 0.0, z1), (0.0, 0.0, -1.0)), remission=0.5, name="ceiling")
    x_axis = (1.0, 0.0, 0.0)
    y_axis = (0.0, 1.0, 0.0)
    scene.add(Plane((xc, back_wall_y, zc), (0, -1, 0), size=(width, height), u_axis=x_axis), 0.6, "back_wall")
    scene.add(Plane((xc, yr, zc), (0, 1, 0), size=(width, height), u_axis=x_axis), 0.6, "rear_wall")
    scene.add(Plane((xl, yc, zc), (1, 0, 0), size=(depth, height), u_axis=y_axis), 0.6, "left_wall")
    scene.add(Plane((xr, yc, zc), (-1, 0, 0), size=(depth, height), u_axis=y_axis), 0.6, "right_wall")


def part_in_room(
    diameter: float = SEED003_DIAMETER,
    distance: float = SEED003_AXIS_POINT[1],
    height: float = SEED003_HEIGHT,
    remission: float = 0.35,
    name: str = "room",
) -> Scene:
    """A cylindrical part of ``diameter`` on a table ``distance`` along +y, in a closed room.

    The part stands on a table (top at z = -0.1 m, at least 1.2 x 0.8 m and 0.4 m larger than the
    part) with its near side 0.21 m to the right of the motor shaft, as seed 003's part (axis
    x = 0.28 m for D = 137.5 mm), so the fan of scan planes covers it. Around it: the room of
    :func:`add_room` (back wall :data:`ROOM_BACK_GAP` behind the part), and neighbouring parts on
    the floor: a 250 mm cylinder 1 m high beside and behind the table, and a 0.5 m crate on the
    other side. The part is the object named "cylinder".
    """
    if not (np.isfinite(diameter) and 0.0 < diameter <= 2.0):
        raise SceneError(f"part diameter must be within (0, 2] m, got {diameter!r}")
    if not (np.isfinite(distance) and 1.0 <= distance <= 8.0):
        raise SceneError(f"part distance must be within [1, 8] m, got {distance!r}")
    x0 = SEED003_AXIS_POINT[0] + 0.5 * (diameter - SEED003_DIAMETER)
    z0 = SEED003_AXIS_POINT[2]
    scene = Scene(name)
    add_part_on_table(scene, (x0, distance, z0), diameter, height, remission)
    sx = max(1.2, diameter + 0.4)
    far = distance + diameter / 2
    scene.add(
        Cylinder((x0 + sx / 2 + 0.5, far + 0.4, SEED003_FLOOR_Z), (0.0, 0.0, 1.0), 0.125, 1.0),
        remission=0.3,
        name="neighbour_part",
    )
    scene.add(Box((x0 - sx / 2 - 0.6, far + 0.3, SEED003_FLOOR_Z + 0.25), (0.5, 0.5, 0.5)), 0.5, "neighbour_crate")
    add_room(scene, far + ROOM_BACK_GAP)
    return scene


def seed003_room() -> Scene:
    """Seed 003's part on its table in a closed room (walls 1.2 m behind it), with neighbouring parts."""
    return part_in_room(name="seed003-room")


def seed003_bare() -> Scene:
    """Only seed 003's cylinder and its table: no room, no clutter."""
    scene = Scene("seed003-bare")
    add_seed003_part(scene)
    return scene


def empty() -> Scene:
    """Nothing at all: every beam misses (the device reports 0)."""
    return Scene("empty")


def wall() -> Scene:
    """An infinite wall 3 m ahead (the plane y = 3 m, facing the rig), remission 0.7."""
    scene = Scene("wall")
    scene.add(Plane((0.0, 3.0, 0.0), (0.0, -1.0, 0.0)), remission=0.7, name="wall")
    return scene


def elbow() -> Scene:
    """A 90 deg pipe elbow (``ELBOW_*``) and a floor."""
    scene = Scene("elbow")
    scene.add(
        TorusSection(ELBOW_CENTER, ELBOW_AXIS, ELBOW_BEND_RADIUS, ELBOW_DIAMETER / 2, ELBOW_DEGREE, ELBOW_START),
        remission=0.5,
        name="elbow",
    )
    scene.add(Plane((0.0, 0.0, SEED003_FLOOR_Z), (0.0, 0.0, 1.0)), remission=0.2, name="floor")
    return scene


#: ``room-spheres-large``: the same room and sphere centres with every sphere this much larger
#: (0.4 and 0.5 m: four times the beams on each; docs/calibration.md, "k1 over 20 rigs").
ROOM_SPHERES_LARGE_FACTOR = 2.0


def room_spheres_artefact(diameter_factor: float = 1.0) -> dict[str, object]:
    """The ``room-spheres`` scene's artefact description (the ``lrms calibrate --artefact`` JSON);
    ``diameter_factor``: :data:`ROOM_SPHERES_LARGE_FACTOR` for ``room-spheres-large``."""
    a, b, dist = ROOM_SPHERE_BAR
    return {
        "planes": True,
        "spheres": [{"diameter_m": d * diameter_factor} for _, d in ROOM_SPHERES],
        "distances_m": [{"a": a, "b": b, "distance_m": dist}],
    }


def room_spheres(diameter_factor: float = 1.0, name: str = "room-spheres") -> Scene:
    """A calibration room: six planes (``ROOM_WALLS``, turned ``ROOM_YAW_DEG``) and ``ROOM_SPHERES``
    (diameters times ``diameter_factor``)."""
    scene = Scene(name)
    rot = _rot_z(np.deg2rad(ROOM_YAW_DEG))
    w = ROOM_WALLS
    for wall, axis, value in (
        ("wall_x_min", 0, w["x_min"]),
        ("wall_x_max", 0, w["x_max"]),
        ("wall_y_min", 1, w["y_min"]),
        ("wall_y_max", 1, w["y_max"]),
        ("floor", 2, w["z_min"]),
        ("ceiling", 2, w["z_max"]),
    ):
        normal = np.zeros(3)
        normal[axis] = -np.sign(value)  # facing the rig
        scene.add(Plane(rot @ (-normal * abs(value)), rot @ normal), remission=0.5, name=wall)
    for i, (centre, diameter) in enumerate(ROOM_SPHERES):
        scene.add(Sphere(centre, diameter_factor * diameter / 2), remission=0.8, name=f"sphere{i}")
    return scene


def room_spheres_part() -> Scene:
    """``room-spheres`` with seed 003's part on its table (legs down to the room's floor): the
    calibration sweep and the part's measurement on one simulated rig (the service's whole loop,
    ``POST /api/v1/calibrations`` then a measurement with the calibration)."""
    scene = room_spheres(1.0, "room-spheres-part")
    add_seed003_part(scene, ROOM_WALLS["z_min"])
    return scene


def room_spheres_large() -> Scene:
    """``room-spheres`` with every sphere :data:`ROOM_SPHERES_LARGE_FACTOR` times larger."""
    return room_spheres(ROOM_SPHERES_LARGE_FACTOR, "room-spheres-large")


#: ``room-spheres-axis`` (docs/calibration.md, "The axis layout"): the ``room-spheres`` room with five
#: 0.5 m spheres placed for the range scale k1. Each rig pose of :data:`ROOM_AXIS_POSES` looks
#: along its motor shaft at a sphere straddling that line (every scan plane contains the shaft,
#: so every scan crosses it: the most beams a sphere can get), with a sphere about 1 m from the
#: rig beside the line; all 10 centre distances are known. Centres (m) in the first pose's rig frame.
ROOM_AXIS_SPHERES: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.0, 4.8, 0.0), 0.5),  # far on the first pose's shaft (4.8 m)
    ((0.45, 1.0, 0.035), 0.5),  # 1.1 m beside the first pose's shaft; straddles the second's (2 m)
    ((-1.5, 0.2, 0.3), 0.5),  # far on the third pose's shaft (3.3 m)
    ((-0.4, 2.4, 0.35), 0.5),  # 1 m from the second pose
    ((1.0, -0.3, -0.3), 0.5),  # 1.1 m from the first and the third pose
)
#: The rig poses of ``room-spheres-axis``: (position m, turn about z deg, tip about x deg) of the
#: rig frame in the first pose's frame: the origin looking along +y; 3 m along +y turned to look
#: back (-y), tipped 1 deg; at (1.8, 0.2, 0.3) looking along -x.
ROOM_AXIS_POSES: tuple[tuple[tuple[float, float, float], float, float], ...] = (
    ((0.0, 0.0, 0.0), 0.0, 0.0),
    ((0.3, 3.0, 0.0), 180.0, 1.0),
    ((1.8, 0.2, 0.3), 90.0, 0.0),
)


def room_axis_artefact(u_distance_m: float = 3e-5) -> dict[str, object]:
    """``room-spheres-axis``'s artefact: the five 0.5 m spheres and all 10 centre distances (each
    with standard uncertainty ``u_distance_m``, as a laser tracker or CMM measures the network)."""
    return _axis_artefact(ROOM_AXIS_SPHERES, u_distance_m)


def _axis_artefact(
    spheres: tuple[tuple[tuple[float, float, float], float], ...], u_distance_m: float
) -> dict[str, object]:
    """An artefact of ``spheres`` ((centre m, diameter m) each) with all their centre distances,
    each with standard uncertainty ``u_distance_m``; the walls (planes) are used too."""
    c = [np.asarray(x, dtype=np.float64) for x, _ in spheres]
    n = len(c)
    return {
        "planes": True,
        "spheres": [{"diameter_m": d} for _, d in spheres],
        "distances_m": [
            {"a": i, "b": j, "distance_m": float(np.linalg.norm(c[j] - c[i])), "u_distance_m": u_distance_m}
            for i in range(n)
            for j in range(i + 1, n)
        ],
    }


def room_spheres_axis() -> Scene:
    """The ``room-spheres`` room with the spheres of :data:`ROOM_AXIS_SPHERES`."""
    scene = room_spheres(1.0, "room-spheres-axis")
    room = Scene("room-spheres-axis")
    for o in scene.objects:
        if not o.name.startswith("sphere"):
            room.add(o.shape, o.remission, o.name)
    for i, (centre, diameter) in enumerate(ROOM_AXIS_SPHERES):
        room.add(Sphere(centre, diameter / 2), remission=0.8, name=f"sphere{i}")
    return room


#: ``hall-spheres-axis`` (docs/calibration.md, "The hall layout"): the axis layout's idea in a
#: 12.4 m x 8.4 m workshop hall (walls turned 3 deg about the hall's centre (0, 4.8) m, floor
#: -1.3 m, ceiling 2.7 m), so that each rig pose's far sphere on its shaft line is 6.6-9.2 m away
#: and its near sphere 1.1-1.3 m: the lever of k1 is 5.5-8 m per pose instead of 1-3.7 m. Four
#: spheres of 0.5 m, all 6 centre distances known. Spheres 0 and 1 serve two poses each: sphere 0
#: is far on pose 0's shaft (9.0 m) and near pose 1 (1.3 m), sphere 1 the reverse. Centres (m)
#: in the first pose's rig frame.
HALL_YAW_DEG = 3.0
HALL_WALLS = {"x_min": -4.2, "x_max": 4.2, "y_min": -1.4, "y_max": 11.0, "z_min": -1.3, "z_max": 2.7}
HALL_CENTRE = (0.0, 4.8)
HALL_AXIS_SPHERES: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.0, 9.0, 0.0), 0.5),  # far on pose 0's shaft (9.0 m); 1.3 m from pose 1, 22 deg off its shaft
    ((0.0, 1.001, 0.611), 0.5),  # far on pose 1's shaft (9.2 m); 1.2 m from pose 0, 31 deg off its shaft
    ((-3.3, 3.0, 0.3), 0.5),  # far on pose 2's shaft (6.6 m)
    ((2.333, 3.451, 0.032), 0.5),  # 1.1 m from pose 2, 28 deg off its shaft
)
#: The rig poses of ``hall-spheres-axis`` (position m, turn about z deg, tip about x deg): the
#: origin looking along +y; 10.2 m along +y and 0.45 m up, turned to look back (-y), tipped
#: 1 deg; at (3.3, 3.0, 0.3) looking along -x across the hall.
HALL_AXIS_POSES: tuple[tuple[tuple[float, float, float], float, float], ...] = (
    ((0.0, 0.0, 0.0), 0.0, 0.0),
    ((0.0, 10.2, 0.45), 180.0, 1.0),
    ((3.3, 3.0, 0.3), 90.0, 0.0),
)


def hall_axis_artefact(u_distance_m: float = 3e-5) -> dict[str, object]:
    """``hall-spheres-axis``'s artefact: the four 0.5 m spheres and all 6 centre distances (each
    with standard uncertainty ``u_distance_m``: a laser tracker network; docs/calibration.md)."""
    return _axis_artefact(HALL_AXIS_SPHERES, u_distance_m)


def hall_spheres_axis() -> Scene:
    """A workshop hall of six planes (``HALL_WALLS`` turned ``HALL_YAW_DEG`` about ``HALL_CENTRE``)
    with the spheres of :data:`HALL_AXIS_SPHERES`."""
    scene = Scene("hall-spheres-axis")
    rot = _rot_z(np.deg2rad(HALL_YAW_DEG))
    centre = np.array([HALL_CENTRE[0], HALL_CENTRE[1], 0.0])
    w = HALL_WALLS
    for wall, axis, value in (
        ("wall_x_min", 0, w["x_min"] - centre[0]),
        ("wall_x_max", 0, w["x_max"] - centre[0]),
        ("wall_y_min", 1, w["y_min"] - centre[1]),
        ("wall_y_max", 1, w["y_max"] - centre[1]),
        ("floor", 2, w["z_min"]),
        ("ceiling", 2, w["z_max"]),
    ):
        normal = np.zeros(3)
        normal[axis] = -np.sign(value)  # facing the hall's centre
        scene.add(Plane(centre + rot @ (-normal * abs(value)), rot @ normal), remission=0.5, name=wall)
    for i, (c, diameter) in enumerate(HALL_AXIS_SPHERES):
        scene.add(Sphere(c, diameter / 2), remission=0.8, name=f"sphere{i}")
    return scene


register_scene("seed003", seed003, "seed 003: 137.5 mm cylinder on a table 2.53 m along +y, floor, wall, clutter")
register_scene(
    "seed003-room",
    seed003_room,
    "seed 003's part on its table in a closed room: walls, floor, ceiling, neighbouring parts",
)
register_scene("seed003-bare", seed003_bare, "seed 003's cylinder and table only")
register_scene("empty", empty, "nothing: every beam misses")
register_scene("wall", wall, "an infinite wall at y = 3 m")
register_scene("room-spheres", room_spheres, "calibration room: 6 planes, 7 reference spheres (a 2 m sphere bar)")
register_scene(
    "room-spheres-part",
    room_spheres_part,
    "calibration room with seed 003's part on its table 2.53 m along +y (calibrate, then measure)",
)
register_scene(
    "room-spheres-large", room_spheres_large, "calibration room: 6 planes, 7 reference spheres of 0.4 / 0.5 m"
)
register_scene(
    "room-spheres-axis",
    room_spheres_axis,
    "calibration room for k1: 5 spheres of 0.5 m on and beside the shaft lines",
)
register_scene(
    "hall-spheres-axis",
    hall_spheres_axis,
    "12 m workshop hall for k1: 4 spheres of 0.5 m, far ones 6.6-9.2 m out on the shaft lines",
)
register_scene("elbow", elbow, "a 90 deg pipe elbow, D 250 mm, A 350 mm, 1.8 m ahead; floor")
