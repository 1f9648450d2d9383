"""The LMS1xx footprint sensor model against closed-form expectations (sim/scene/lms1xx.py).

Geometry of every case: one beam from the origin along +y; its sub-ray pattern's first axis is +x
(u = d x z), so a wall edge at x = 0 runs through the spot's centre.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lrms.kinematics import RigCalibration
from sim.scene import (
    Footprint,
    LMS1xxSensor,
    Plane,
    RangeSystematics,
    Scene,
    SceneError,
    SensorModel,
    cast_beams,
    get_scene,
    lms1xx_device_angles,
    make_sensor,
)
from sim.scene.lms1xx import LMS1XX_MIN_ENERGY, EchoFilter, SubRayHits

ORIGIN = np.zeros((1, 3))
AHEAD = np.array([[0.0, 1.0, 0.0]])
BIG = 20.0


def half_plane(scene: Scene, y: float, x_from: float, remission: float, name: str) -> None:
    """A wall across the beam at ``y`` covering x >= ``x_from`` (an edge parallel to z)."""
    scene.add(Plane((x_from + BIG / 2, y, 0.0), (0, -1, 0), size=(BIG, BIG), u_axis=(1, 0, 0)), remission, name)


def spot_radius(fp: Footprint, r: float) -> float:
    return fp.exit_diameter_m / 2 + r * np.tan(fp.divergence_rad / 2)


def test_spot_diameter_is_sicks_figure() -> None:
    fp = Footprint()
    np.testing.assert_allclose(fp.diameter(np.array([0.0, 2.5, 5.0])), [0.008, 0.0455, 0.083])
    assert 2 * spot_radius(fp, 2.5) == pytest.approx(0.0455, abs=1e-6)  # the sub-rays' cone has it too
    a, b, w = fp.pattern()
    k = fp.sub_rays
    assert k == 128  # the default: the sampling error of the covered share well below the fit's goal
    assert a.shape == b.shape == w.shape == (k,) and w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(a[: k // 2], -a[k // 2 :])  # point symmetric: each line through the centre halves it
    assert np.max(np.hypot(a, b)) <= fp.extent


@pytest.mark.parametrize("r", [1.0, 2.5, 5.0])
def test_half_covered_spot_on_a_silhouette_edge(r: float) -> None:
    scene = Scene("edge")
    half_plane(scene, r, 0.0, 0.5, "wall")
    full = Scene("full")
    full.add(Plane((0, r, 0), (0, -1, 0)), remission=0.5, name="wall")
    sensor = LMS1xxSensor(edge_threshold=0.3)
    half_e = sensor.echoes(scene, ORIGIN, AHEAD, None)
    full_e = sensor.echoes(full, ORIGIN, AHEAD, None)
    assert half_e.coverage is not None and half_e.energy is not None and full_e.energy is not None
    assert half_e.coverage[0] == pytest.approx(0.5, abs=1e-12)
    assert half_e.energy[0] == pytest.approx(0.5 * full_e.energy[0], rel=1e-9)
    assert full_e.energy[0] == pytest.approx(0.5 / r**2, rel=1e-3)  # remission x cos / r^2, white at 1 m = 1
    # One surface: the energy-weighted range is the plane's range (sub-ray paths lean out by < 1e-4).
    assert half_e.valid[0] and half_e.range[0] == pytest.approx(r, abs=2e-4 * r)
    assert half_e.index[0] == 0 and not half_e.valid2[0]  # type: ignore[index]
    # Above the threshold's share, the half-covered spot is a dropout; the full one is not.
    strict = dataclasses.replace(sensor, edge_threshold=0.6)
    assert not strict.echoes(scene, ORIGIN, AHEAD, None).valid[0]
    assert strict.echoes(full, ORIGIN, AHEAD, None).valid[0]


def test_covered_energy_follows_the_gaussian_profile_and_the_divergence() -> None:
    """An edge one profile sigma (spot diameter / 4) off the centre: the covered share of a Gaussian
    truncated at 1.5 spot radii (3 sigma), from a fine grid, within the pattern's stated 0.03 at 128;
    so too with the pattern turned (``rotation_rad``), whose sampling error is another."""
    x = np.linspace(-3, 3, 1201)
    gx, gy = np.meshgrid(x, x)
    g = np.exp(-0.5 * (gx**2 + gy**2)) * (gx**2 + gy**2 <= 9)
    expected = float((g * (gx > 1)).sum() / g.sum())
    shares = {}
    for turn in (0.0, 0.9):
        fp = Footprint(sub_rays=128, rotation_rad=turn)
        for r in (1.0, 4.0):
            scene = Scene("edge")
            half_plane(scene, r, spot_radius(fp, r) / 2, 0.5, "wall")
            e = LMS1xxSensor(footprint=fp, edge_threshold=0.0).echoes(scene, ORIGIN, AHEAD, None)
            assert e.coverage is not None
            assert e.coverage[0] == pytest.approx(expected, abs=0.03)
            shares[turn, r] = float(e.coverage[0])
    assert shares[0.0, 1.0] != shares[0.9, 1.0]  # another pattern, another sampling of the edge


def test_a_turned_pattern_keeps_its_rings_weights_and_symmetry() -> None:
    a, b, w = Footprint().pattern()
    ta, tb, tw = Footprint(rotation_rad=0.7).pattern()
    np.testing.assert_allclose(np.hypot(ta, tb), np.hypot(a, b), atol=1e-15)
    np.testing.assert_array_equal(tw, w)
    turned = np.angle(np.exp(1j * (np.arctan2(tb, ta) - np.arctan2(b, a) - 0.7)))
    np.testing.assert_allclose(turned, 0.0, atol=1e-12)
    k = a.size
    np.testing.assert_allclose(ta[: k // 2], -ta[k // 2 :])  # still point symmetric: a half-covered spot is 1/2


def test_depth_step_inside_the_spot_mixed_pixel_and_first_hit() -> None:
    r1, r2, rem1, rem2 = 2.5, 2.7, 0.35, 0.7  # a 0.2 m step: one echo (separation 0.6 m)
    scene = Scene("step")
    half_plane(scene, r1, 0.0, rem1, "near")
    scene.add(Plane((0, r2, 0), (0, -1, 0)), remission=rem2, name="far")
    sensor = LMS1xxSensor(edge_threshold=0.3)
    e = sensor.echoes(scene, ORIGIN, AHEAD, None)
    e1, e2 = 0.5 * rem1 / r1**2, 0.5 * rem2 / r2**2  # each half of the spot's energy
    assert e.valid[0] and e.coverage is not None and e.coverage[0] == pytest.approx(1.0)
    assert e.range[0] == pytest.approx((e1 * r1 + e2 * r2) / (e1 + e2), abs=5e-4)
    assert e.energy is not None and e.energy[0] == pytest.approx(e1 + e2, rel=1e-3)
    assert e.index[0] == 1  # the far half (white, 0.7) returns more energy than the near one (0.35)
    first = dataclasses.replace(sensor, range_mode="first").echoes(scene, ORIGIN, AHEAD, None)
    assert first.range[0] == pytest.approx(r1, abs=5e-4)
    # The leading edge crosses a 60 % threshold only once the far half has come in: the far range.
    late = dataclasses.replace(sensor, range_mode="first", edge_threshold=0.6).echoes(scene, ORIGIN, AHEAD, None)
    assert late.valid[0] and late.range[0] == pytest.approx(r2, abs=5e-4)


def test_deep_step_gives_two_echoes_first_and_last() -> None:
    r1, r2 = 2.5, 3.5  # 1 m apart: two pulses
    scene = Scene("step")
    half_plane(scene, r1, 0.0, 0.35, "near")
    scene.add(Plane((0, r2, 0), (0, -1, 0)), remission=0.7, name="far")
    sensor = LMS1xxSensor(edge_threshold=0.3)
    e = sensor.echoes(scene, ORIGIN, AHEAD, None)
    assert e.valid[0] and e.valid2 is not None and e.valid2[0]
    assert e.range[0] == pytest.approx(r1, abs=5e-4) and e.range2 is not None
    assert e.range2[0] == pytest.approx(r2, abs=5e-4)
    assert (e.index[0], e.index2[0]) == (0, 1)  # type: ignore[index]
    assert e.coverage is not None and e.coverage[0] == pytest.approx(0.5, abs=1e-12)
    last = dataclasses.replace(sensor, echo_filter="last").echoes(scene, ORIGIN, AHEAD, None)
    assert last.range[0] == pytest.approx(r2, abs=5e-4) and last.range2 is not None
    assert last.range2[0] == pytest.approx(r1, abs=5e-4)
    # Each half is below a 0.6 threshold: both echoes drop out.
    none = dataclasses.replace(sensor, edge_threshold=0.6).echoes(scene, ORIGIN, AHEAD, None)
    assert not none.valid[0] and none.range[0] == 0.0 and none.valid2 is not None and not none.valid2[0]


def test_weak_returns_drop_out_at_the_sensitivity_limit() -> None:
    """SICK: 18 m on 10 % remission. Just inside it an echo, just outside none (head-on, full spot)."""
    sensor = LMS1xxSensor(range_max=30.0)
    for r, seen in ((17.5, True), (18.5, False)):
        scene = Scene("far")
        scene.add(Plane((0, r, 0), (0, -1, 0)), remission=0.1, name="wall")
        e = sensor.echoes(scene, ORIGIN, AHEAD, None)
        assert bool(e.valid[0]) is seen
        assert bool(e.range[0] > 0) is seen and bool(e.rssi[0] > 0) is seen
    assert pytest.approx(0.1 / 18**2) == LMS1XX_MIN_ENERGY


def test_noise_grows_for_weak_echoes_and_inclined_surfaces() -> None:
    n = 4000
    rng = np.random.default_rng(1)
    sensor = LMS1xxSensor()
    near = Scene("near")
    near.add(Plane((0, 2.0, 0), (0, -1, 0)), remission=0.9, name="wall")
    e = sensor.echoes(near, np.zeros((n, 3)), np.tile(AHEAD, (n, 1)), rng)
    sd = float(np.std(e.range - e.true_range, ddof=1))
    assert sd == pytest.approx(0.012, rel=0.06)  # strong echo: SICK's typical 12 mm
    weak = Scene("weak")
    weak.add(Plane((0, 17.9, 0), (0, -1, 0)), remission=0.1, name="wall")
    e = sensor.echoes(weak, np.zeros((n, 3)), np.tile(AHEAD, (n, 1)), rng)
    assert float(np.std(e.range - e.true_range, ddof=1)) == pytest.approx(0.020, rel=0.06)  # at the limit: 20 mm
    tilted = Scene("tilted")
    tilted.add(Plane((0, 2.0, 0), (np.sin(1.2), -np.cos(1.2), 0)), remission=0.9, name="wall")
    e = sensor.echoes(tilted, np.zeros((n, 3)), np.tile(AHEAD, (n, 1)), rng)
    assert float(np.std(e.range - e.true_range, ddof=1)) > 1.2 * sd


def test_range_systematics_offset_scale_temperature_warmup() -> None:
    scene = Scene("wall")
    scene.add(Plane((0, 3.0, 0), (0, -1, 0)), remission=0.5, name="wall")
    sys_ = RangeSystematics(
        offset_m=0.015, scale=0.001, temperature_coeff_m_per_k=1e-4, temperature_c=45.0, warmup_m=0.01, warmup_tau_s=600
    )
    sensor = LMS1xxSensor(systematics=sys_)
    times = np.array([0.0, 600.0, 1e6])
    e = sensor.echoes(scene, np.zeros((3, 3)), np.tile(AHEAD, (3, 1)), None, times)
    base = e.true_range
    expected = base * 1.001 + 0.015 + 1e-4 * 20 + 0.01 * np.exp(-times / 600)
    np.testing.assert_allclose(e.range, expected, atol=1e-12)
    walk = LMS1xxSensor(systematics=RangeSystematics(walk_m_per_decade=0.005))
    w = walk.echoes(scene, ORIGIN, AHEAD, None)
    assert w.energy is not None
    assert w.range[0] - w.true_range[0] == pytest.approx(-0.005 * np.log10(w.energy[0]))


@pytest.mark.parametrize(
    "make",
    [
        lambda: Footprint(divergence_rad=-0.001),
        lambda: Footprint(exit_diameter_m=float("nan")),
        lambda: Footprint(sub_rays=31),
        lambda: Footprint(profile_sigma=0.0),
        lambda: Footprint(rotation_rad=float("nan")),
        lambda: Footprint(rotation_rad=7.0),
        lambda: LMS1xxSensor(edge_threshold=1.5),
        lambda: LMS1xxSensor(edge_threshold=-0.1),
        lambda: LMS1xxSensor(sigma_typical=0.03, sigma_max=0.02),
        lambda: LMS1xxSensor(range_mode="median"),  # type: ignore[arg-type]
        lambda: LMS1xxSensor(echo_filter="all"),  # type: ignore[arg-type]
        lambda: LMS1xxSensor(echo_separation_m=0.0),
        lambda: RangeSystematics(offset_m=float("inf")),
        lambda: RangeSystematics(warmup_tau_s=0.0),
        lambda: make_sensor("lms2xx"),
    ],
)
def test_bad_parameters_are_typed_errors(make: object) -> None:
    with pytest.raises(SceneError):
        make()  # type: ignore[operator]


def test_vectorized_shapes_and_chunking_give_the_same_answer() -> None:
    scene = get_scene("seed003-room")
    cal = RigCalibration()
    dev = lms1xx_device_angles(0.5)[200:340]
    mot = np.deg2rad(np.linspace(-10, 60, 6))[:, None]
    big = LMS1xxSensor()
    small = LMS1xxSensor(chunk_rays=3 * big.footprint.sub_rays)  # three beams per ray cast
    a = cast_beams(scene, cal, big, dev, mot, np.random.default_rng(5))
    b = cast_beams(scene, cal, small, dev, mot, np.random.default_rng(5))
    for name in ("ranges", "valid", "true_range", "index", "rssi", "coverage", "energy", "ranges2", "valid2", "rssi2"):
        va, vb = getattr(a, name), getattr(b, name)
        assert va.shape == (6, 140), name
        np.testing.assert_array_equal(va, vb)
    assert a.valid.mean() > 0.9  # a closed room: nearly every beam has an echo
    part = scene.index_of("cylinder")
    assert np.any(a.index == part) and np.any(a.valid2)  # the part, and second echoes at its silhouette


def test_ideal_sensor_is_unchanged_and_has_no_second_echo() -> None:
    samples = cast_beams(get_scene("wall"), RigCalibration(), SensorModel.noiseless(), lms1xx_device_angles(0.5), 0.0)
    assert samples.ranges2 is None and samples.coverage is None
    ahead = np.abs(samples.device_angle - np.pi / 2) < 1e-9
    assert samples.ranges[ahead][0] == pytest.approx(3.0)
    assert isinstance(make_sensor("ideal", sigma_l=0.02), SensorModel)
    lms = make_sensor("lms1xx", sigma_l=0.02, sigma_alpha=0.0)
    assert isinstance(lms, LMS1xxSensor) and lms.sigma_alpha == 0.0 and lms.sigma_typical == 0.012
    # the streaming device trades sampling accuracy for speed: fewer sub-rays than the model's default
    assert lms.footprint.sub_rays == 32 < Footprint().sub_rays


def test_room_scene_and_part_in_room() -> None:
    from sim.scene.library import part_in_room

    scene = get_scene("seed003-room")
    names = {o.name for o in scene.objects}
    assert {"cylinder", "table", "floor", "back_wall", "left_wall", "right_wall", "neighbour_part"} <= names
    big = part_in_room(1.0, 5.0)
    assert big.objects[big.index_of("cylinder")].shape.bounding_sphere()[1] > 0.5
    with pytest.raises(SceneError):
        part_in_room(-0.1, 3.0)
    with pytest.raises(SceneError):
        part_in_room(0.3, 0.2)


@pytest.mark.parametrize(("echo_filter", "objects"), [("first", 3), ("last", 3), ("first", 400), ("last", 400)])
def test_an_echo_belongs_to_the_object_returning_most_of_its_energy(echo_filter: EchoFilter, objects: int) -> None:
    """Hand-made sub-ray hits, one echo per beam over several objects: the echo's index is the
    object whose sub-rays carry most of its energy (the lowest index on a tie), whatever the
    chunking. 3 objects: the dense (echo, object) table; 400: the sparse sum over sorted pairs."""
    k, n = 16, 60
    sensor = LMS1xxSensor(footprint=Footprint(sub_rays=k), edge_threshold=0.0, min_energy=0.0, echo_filter=echo_filter)
    rng = np.random.default_rng(3)
    t = 2.0 + 0.01 * rng.random((n, k))
    idx = rng.integers(0, objects, (n, k))
    cos = rng.uniform(0.2, 1.0, (n, k))
    rem = rng.uniform(0.1, 1.0, (n, k))
    miss = rng.random((n, k)) < 0.1
    t[miss], idx[miss], cos[miss], rem[miss] = np.inf, -1, 0.0, 0.0
    t[0], idx[0], cos[0], rem[0] = 2.0, [objects - 1, 1] * (k // 2), 1.0, 0.5  # two objects return equally
    hits = SubRayHits(t, idx, cos, rem)
    e = sensor.form_echoes(hits, np.random.default_rng(1))
    hit = ~miss
    hit[0] = True
    per_object = np.zeros((n, objects))
    np.add.at(per_object, (np.nonzero(hit)[0], idx[hit]), (rem * cos / t**2)[hit] / k)
    assert e.valid.all() and e.valid2 is not None and not e.valid2.any()
    np.testing.assert_array_equal(e.index, np.argmax(per_object, axis=1))
    assert e.index[0] == 1
    beam_by_beam = dataclasses.replace(sensor, chunk_rays=k).form_echoes(hits, np.random.default_rng(1))
    for name, value in dataclasses.asdict(e).items():
        np.testing.assert_array_equal(getattr(beam_by_beam, name), value, err_msg=name)
