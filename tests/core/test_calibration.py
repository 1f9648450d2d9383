"""Rig calibration (issue 12): the generalised rig model, recovery of known errors on a simulated
room with spheres (ideal thin beam, seed 003's noise), the identifiability report on degenerate
artefacts, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lrms import kinematics as k
from lrms.calibration import (
    AdjustOptions,
    Artefact,
    ArtefactError,
    CalibrationError,
    CalibrationOptions,
    CalibrationResult,
    CloudTooSmallError,
    DetectionError,
    Identifiability,
    Observations,
    SphereSpec,
    apply_to_points,
    calibrate,
)
from lrms.errors import LrmsError
from sim.scene import Scene, SensorModel, Sphere, continuous_sweep_cloud, get_scene
from sim.scene.library import room_spheres_artefact

D = np.deg2rad
FAST = CalibrationOptions(adjust=AdjustOptions(max_plane_points=5000))
#: A rig off by errors within SICK's and a machine shop's tolerances (issue 12's goals).
TRUE_RIG = k.RigModel(
    k0=0.02, k1=500e-6, p=0.103, q=-0.002, tilt_x=D(0.2), tilt_y=D(0.1), alpha_zero=D(-0.15), beta_zero=D(0.1),
    beta_scale=-400e-6,
)  # fmt: skip


def sweep(scene: Scene, rig: k.RigModel, speed_deg_s: float = 10.0, seed: int = 0) -> Observations:
    """A -90..90 deg sweep of ``scene`` by a rig whose true geometry is ``rig``, as raw readings."""
    cal = k.RigCalibration(model=rig)
    _, s = continuous_sweep_cloud(
        scene, cal, SensorModel(), D(-90), D(90), D(speed_deg_s), rng=np.random.default_rng(seed)
    )
    v = s.valid
    return Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))


# -- the model ---------------------------------------------------------------------------------


def test_nominal_model_is_eq1_exactly() -> None:
    rng = np.random.default_rng(3)
    l, a, b = rng.uniform(0.5, 10, 500), rng.uniform(-2.3, 2.3, 500), rng.uniform(-1.5, 1.5, 500)
    assert np.array_equal(k.RigModel().forward(l, a, b), k.forward(l, a, b))
    o, d = k.RigModel().rays(a, b)
    o0, d0 = k.beam_rays(a, b)
    assert np.array_equal(o, o0) and np.array_equal(d, d0)
    # the general path (any non-nominal parameter, here a vanishing one) agrees to rounding
    general = k.RigModel(k0=1e-300).forward(l, a, b)
    np.testing.assert_allclose(general, k.forward(l, a, b), rtol=0, atol=1e-12)


def test_each_parameter_moves_the_points_as_documented() -> None:
    l, a, b = 3.0, D(30.0), D(20.0)
    base = k.forward(l, a, b)
    # range offset and scale: along the beam
    d = k.beam_rays(a, b)[1]
    np.testing.assert_allclose(k.RigModel(k0=0.01).forward(l, a, b), base + 0.01 * d, atol=1e-15)
    np.testing.assert_allclose(k.RigModel(k1=1e-3).forward(l, a, b), base + 3e-3 * d, atol=1e-15)
    # angular zero = alpha shifted; encoder zero = a rotation about the shaft (y unchanged)
    np.testing.assert_allclose(k.RigModel(alpha_zero=0.01).forward(l, a, b), k.forward(l, a + 0.01, b), atol=1e-15)
    z = k.RigModel(beta_zero=0.01).forward(l, a, b)
    np.testing.assert_allclose(z, k.forward(l, a, b + 0.01), atol=1e-15)
    # q: the optical centre across the scan plane (at beta = 0 that is +z)
    np.testing.assert_allclose(k.RigModel(q=0.005).forward(l, a, 0.0), k.forward(l, a, 0.0) + np.array([0, 0, 0.005]))
    # tilt_x lifts the beam along the shaft (alpha = 0) out of the scan plane
    pt = k.RigModel(tilt_x=0.01).forward(2.0, 0.0, 0.0)
    np.testing.assert_allclose(pt, [0.1, 2 * np.cos(0.01), 2 * np.sin(0.01)], atol=1e-15)
    # backlash and time offset act on the plane angle through the motor speed
    m = k.RigModel(backlash=0.002, time_offset=0.01)
    np.testing.assert_allclose(m.plane_angle(0.5, 0.2), 0.5 - 0.001 + 0.002)
    np.testing.assert_allclose(m.plane_angle(0.5, -0.2), 0.5 + 0.001 - 0.002)
    np.testing.assert_allclose(m.forward(l, a, b), k.forward(l, a, b))  # speed unknown: no effect


def test_tilt_about_the_shaft_is_a_motor_zero_and_a_turned_optical_centre() -> None:
    rng = np.random.default_rng(4)
    l, a, b = rng.uniform(0.5, 10, 200), rng.uniform(-2.3, 2.3, 200), rng.uniform(-1.5, 1.5, 200)
    m = k.RigModel(tilt_y=0.01, q=0.003, p=0.102, beta_zero=0.02, tilt_x=0.004, k0=0.02)
    c = m.canonical()
    assert c.tilt_y == 0.0 and c.beta_zero == pytest.approx(0.03)
    np.testing.assert_allclose(m.forward(l, a, b), c.forward(l, a, b), atol=1e-12)


def test_rig_calibration_takes_the_model_from_config() -> None:
    cal = k.RigCalibration.from_dict({"p_m": 0.11, "range_offset_m": 0.01, "tilt_x_deg": 0.1, "backlash_deg": 0.05})
    assert cal.rig.k0 == 0.01 and cal.rig.p == 0.11 and cal.rig.tilt_x == pytest.approx(D(0.1))
    assert cal.rig.backlash == pytest.approx(D(0.05))
    assert k.RigCalibration().rig == k.RigModel()
    with pytest.raises(LrmsError, match="disagree"):
        k.RigCalibration(p=0.2, model=k.RigModel(p=0.1))
    with pytest.raises(LrmsError, match="unknown"):
        k.RigCalibration.from_dict({"range_offset_mm": 1})
    with pytest.raises(LrmsError, match="finite"):
        k.RigModel(k0=float("nan"))


def test_simulated_scanner_reports_through_the_true_rig() -> None:
    """The simulator's beams leave along the true rig's rays and report (true - k0) / (1 + k1)."""
    scene = get_scene("wall")
    rig = k.RigModel(k0=0.02, k1=1e-3, tilt_x=D(0.2), q=0.003)
    cal = k.RigCalibration(model=rig)
    _, s = continuous_sweep_cloud(scene, cal, SensorModel.noiseless(), D(-10), D(10), D(20))
    v = s.valid
    pts = rig.forward(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))
    np.testing.assert_allclose(pts[:, 1], 3.0, atol=1e-9)  # the wall y = 3 m, exactly, through the true rig
    nominal = k.forward(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))
    assert np.abs(nominal[:, 1] - 3.0).max() > 0.01  # mapped with Eq. 1 it is visibly not


# -- the adjustment ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def room_result() -> CalibrationResult:
    return calibrate(
        [sweep(get_scene("room-spheres"), TRUE_RIG)], Artefact.from_dict(room_spheres_artefact()), options=FAST
    )


def test_recovers_known_errors_on_a_room_with_spheres(room_result: CalibrationResult) -> None:
    res = room_result
    truth = TRUE_RIG.canonical()  # the tilt about the shaft is carried by q and the (held) zero
    assert set(res.estimated) == {"k0", "k1", "p", "q", "tilt_x", "alpha_zero", "beta_scale"}
    # no motor speeds in these observations: backlash and time offset cannot show
    assert set(res.identifiability.held) == {"beta_zero", "tilt_y", "backlash", "time_offset"}
    std = res.std()
    for name in res.estimated:
        err = getattr(res.model, name) - getattr(truth, name)
        assert abs(err) <= 3 * std[name], (name, err, std[name])
    assert std["k0"] < 1e-3 and std["p"] < 0.2e-3 and std["tilt_x"] < D(0.01) and std["alpha_zero"] < D(0.01)
    assert 0.9 < res.residuals["variance_factor"] < 1.1
    assert res.residuals["planes"] == 6 and res.residuals["spheres"] == 7
    corr = res.correlations()
    np.testing.assert_allclose(np.diag(corr), 1.0)
    assert np.all(np.abs(corr) <= 1 + 1e-12)


def test_result_json_round_trip_and_applying_it(room_result: CalibrationResult) -> None:
    back = CalibrationResult.from_json(room_result.to_json())
    assert back.model == room_result.model
    np.testing.assert_array_equal(back.covariance, room_result.covariance)
    assert back.identifiability.held == room_result.identifiability.held
    data = json.loads(room_result.to_json())
    assert data["std"].keys() == set(room_result.estimated)
    # a cloud mapped with the nominal Eq. 1 re-mapped with the calibration lands on the wall
    cal = k.RigCalibration(model=TRUE_RIG)
    _, s = continuous_sweep_cloud(get_scene("wall"), cal, SensorModel.noiseless(), D(-5), D(5), D(20))
    v = s.valid
    pts = k.forward(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))  # as the software maps
    fixed = apply_to_points(pts, room_result)
    # the held rotation about the shaft (beta_zero) only turns the wall about y: its distance stays
    assert np.abs(pts[:, 1] - 3.0).max() > 0.015
    assert np.abs(fixed[:, 1] - 3.0).max() < 0.003
    with pytest.raises(LrmsError, match="schema"):
        CalibrationResult.from_json('{"schema": "other"}')


def test_one_plane_cannot_give_the_scale_or_the_centre() -> None:
    res = calibrate([sweep(get_scene("wall"), TRUE_RIG)], Artefact(planes=True), options=FAST)
    held = res.identifiability.held
    assert {"k1", "p", "q", "tilt_x", "beta_scale"} <= set(held)
    assert "known length" in held["k1"] and "several orientations" in held["p"]
    assert set(res.estimated) == {"k0", "alpha_zero"}


def test_spheres_all_at_one_range_cannot_separate_offset_and_scale() -> None:
    scene = Scene("ring")
    for i, az in enumerate(D([-40.0, -10.0, 20.0, 50.0])):
        scene.add(Sphere((2.5 * np.sin(az), 2.5 * np.cos(az), 0.3 * (i - 1.5)), 0.1), 0.8, f"s{i}")
    art = Artefact(planes=False, spheres=tuple(SphereSpec(0.2) for _ in range(4)))
    res = calibrate([sweep(scene, TRUE_RIG, speed_deg_s=2.5)], art, options=FAST)
    assert "k1" in res.identifiability.held and "k0" in res.estimated
    assert "sphere-bar" in res.identifiability.held["k1"]


# -- bad input -----------------------------------------------------------------------------------


def test_bad_artefacts_are_typed_errors() -> None:
    with pytest.raises(ArtefactError, match="diameter"):
        Artefact.from_dict({"planes": True, "spheres": [{"diameter_m": -0.2}]})
    with pytest.raises(ArtefactError, match="unknown"):
        Artefact.from_dict({"planes": True, "sphere": []})
    with pytest.raises(ArtefactError, match="two different"):
        Artefact.from_dict({"spheres": [{"diameter_m": 0.2}], "distances_m": [{"a": 0, "b": 1, "distance_m": 1}]})
    with pytest.raises(ArtefactError, match="numbers"):
        Artefact.from_dict({"spheres": [{"diameter_m": "big"}]})
    with pytest.raises(ArtefactError, match="planes or spheres"):
        Artefact.from_dict({"planes": False})


def test_too_small_a_cloud_and_missing_spheres_are_typed_errors() -> None:
    obs = sweep(get_scene("wall"), TRUE_RIG, speed_deg_s=20.0)
    with pytest.raises(CloudTooSmallError):
        calibrate([obs.subset(np.arange(500))], Artefact(planes=True))
    with pytest.raises(DetectionError, match="no spheres found"):
        calibrate([obs], Artefact(planes=True, spheres=(SphereSpec(0.2),)), options=FAST)
    ball = Scene("ball")
    ball.add(Sphere((0.0, 2.0, 0.0), 0.3), 0.8, "ball")
    with pytest.raises(DetectionError, match="no planes"):
        calibrate([sweep(ball, TRUE_RIG, speed_deg_s=5.0)], Artefact(planes=True), options=FAST)


def test_data_that_determine_no_parameter_are_an_error_not_a_calibration() -> None:
    """A 5 deg sweep of seed 003's table scene, with one 0.2 m sphere in the artefact and no planes:
    a "sphere" in the clutter determines none of the rig's parameters. An error naming what was
    found and what data would determine each parameter, not a calibration of the nominal rig
    (which could be stored and activated as if it were one)."""
    cal = k.RigCalibration(model=k.RigModel())
    _, s = continuous_sweep_cloud(
        get_scene("seed003"), cal, SensorModel(), D(0), D(5), D(10), rng=np.random.default_rng(0)
    )
    v = s.valid
    obs = Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))
    art = Artefact(planes=False, spheres=(SphereSpec(0.2),))
    with pytest.raises(CalibrationError, match=r"determine none of the rig's parameters \(0 planes, 1 spheres") as exc:
        calibrate([obs], art, options=FAST)
    assert "k1: not determined by these data" in str(exc.value) and "known length" in str(exc.value)


def test_a_singular_condition_is_null_in_json_and_infinite_again() -> None:
    ident = Identifiability(held={}, rank=1, condition=float("inf"))
    text = json.dumps(ident.to_dict(), allow_nan=False)  # strict JSON: no Infinity
    assert json.loads(text)["condition"] is None
    assert Identifiability.from_dict(json.loads(text)).condition == float("inf")


def test_half_turn_inverse_recovers_readings_on_both_sides_of_the_shaft() -> None:
    rng = np.random.default_rng(5)
    l, a, b = rng.uniform(0.5, 10, 2000), rng.uniform(-2.35, 2.35, 2000), rng.uniform(-1.5, 1.5, 2000)
    l2, a2, b2 = k.inverse(k.forward(l, a, b), half_turn=True)
    np.testing.assert_allclose(np.c_[l2, a2, b2], np.c_[l, a, b], atol=1e-9)
    obs = Observations.from_points(k.forward(l, a, b))
    np.testing.assert_allclose(obs.alpha, a, atol=1e-9)


def test_two_sweeps_show_one_combination_of_backlash_and_time_offset() -> None:
    """+10 deg/s and -20 deg/s: only -backlash + 30 deg/s x time_offset differs between the sweeps."""
    rig = k.RigModel(k0=0.01, p=0.102, tilt_x=D(0.1), backlash=D(0.05), time_offset=0.004)
    cal = k.RigCalibration(model=rig)
    sweeps = []
    for lo, hi, speed, seed in ((-90.0, 90.0, 10.0, 1), (90.0, -90.0, 20.0, 2)):
        _, s = continuous_sweep_cloud(
            get_scene("room-spheres"), cal, SensorModel(), D(lo), D(hi), D(speed), rng=np.random.default_rng(seed)
        )
        v = s.valid
        moving = np.abs(s.motor_angle - D(lo)) < abs(D(hi - lo)) - 1e-12
        omega = np.where(moving, np.sign(hi - lo) * D(speed), 0.0)
        sweeps.append(
            Observations.from_raw(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]), omega[v])
        )
    res = calibrate(sweeps, Artefact.from_dict(room_spheres_artefact()), options=FAST)
    assert "time_offset" in res.identifiability.held and "backlash" in res.estimated
    assert "three different signed speeds" in res.identifiability.held["time_offset"]
    combination = rig.backlash - D(30.0) * rig.time_offset  # what a free backlash alone must carry
    assert abs(res.model.backlash - combination) < 3 * res.std()["backlash"]


def test_a_sphere_network_is_matched_as_a_whole() -> None:
    """Six equal spheres found in an order unrelated to the artefact's, with every centre distance
    given (a network measured by a tracker): each found sphere gets its own artefact index. Matching
    one distance at a time (the first pair that fits, the rest in found order) cannot do this."""
    from lrms.calibration.detect import DetectOptions, detect_spheres

    rng = np.random.default_rng(4)
    centres = np.array([[0.6, 1.5, -0.3], [-0.8, 2.4, 0.45], [1.6, 3.4, -0.7], [-0.3, 4.6, 0.25],
                        [1.5, -0.9, 0.3], [0.2, 2.0, 1.0]])  # fmt: skip
    order = [3, 0, 5, 1, 4, 2]  # the order the clusters come in
    clouds = []
    for c in centres[order]:
        v = rng.normal(size=(300, 3))
        v /= np.linalg.norm(v, axis=1)[:, None]
        v = v[(v @ -c) > 0]  # the half facing the rig at the origin
        clouds.append(c + 0.1 * v)
    pts = np.concatenate(clouds)
    n = len(centres)
    art = Artefact.from_dict(
        {
            "planes": True,
            "spheres": [{"diameter_m": 0.2}] * n,
            "distances_m": [
                {"a": i, "b": j, "distance_m": float(np.linalg.norm(centres[i] - centres[j]))}
                for i in range(n)
                for j in range(i + 1, n)
            ],
        }
    )
    segs = detect_spheres(pts, np.arange(len(pts)), art, DetectOptions())
    assert len(segs) == n
    for s in segs:
        assert np.allclose(s.center, centres[s.artefact_index], atol=1e-6), (s.artefact_index, s.center)
