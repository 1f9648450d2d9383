"""Per-beam motor angles against an analytic trajectory, scan gap counting, mapping to 3D."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from lrms.kinematics import RigCalibration, forward
from service.sweep import GapCounter, ScanRecord, SweepError, beam_interval_us, interpolate_angle, map_sweep
from service.timesync import ClockSync
from tests.service.test_calibrated_mapping import ALL_TERMS

HOST0_NS = 1_763_700_000_000_000_000
DEV0_US = 4_294_000_000  # close to the 32-bit wrap: it wraps during the sweep
DRIFT = 30e-6


def beta_true(t: np.ndarray) -> np.ndarray:
    """A smooth shaft trajectory (rad) over host seconds since HOST0: ramp plus a wobble."""
    return -0.35 + 0.17 * t + 0.01 * np.sin(2 * np.pi * 0.5 * t)


def _sweep(
    rng: np.random.Generator, n_scans: int = 250
) -> tuple[list[ScanRecord], ClockSync, NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    f, step = 50.0, np.deg2rad(0.5)
    n_beams = 541
    dt_us = beam_interval_us(step, f)
    clock = ClockSync()
    scans = []
    truth_t = []
    for k in range(n_scans):
        dev_t0 = k * 20_000  # device us since DEV0
        t_true0 = (1 + DRIFT) * dev_t0 * 1e-6  # host seconds of beam 0
        ttx = dev_t0 + 16_000
        recv = (1 + DRIFT) * ttx * 1e-6 + 0.0003 + rng.exponential(0.001)
        raw_t0 = (DEV0_US + dev_t0) % (1 << 32)
        raw_tx = (DEV0_US + ttx) % (1 << 32)
        u0 = clock.unwrap(raw_t0)
        utx = clock.unwrap(raw_tx)
        host_ns = HOST0_NS + round(recv * 1e9)
        clock.update(utx, host_ns * 1e-9)
        scans.append(
            ScanRecord(
                host_ns=host_ns,
                scan_counter=k,
                telegram_counter=k,
                t0_us=u0,
                ttx_us=utx,
                start_angle_rad=np.deg2rad(-45.0),
                step_rad=step,
                scan_frequency_hz=f,
                ranges_m=rng.uniform(0.6, 4.0, n_beams),
            )
        )
        truth_t.append(t_true0 + np.arange(n_beams) * dt_us * 1e-6 + 0.0003)
    # motor samples at 200 Hz with host timestamps (sampling delay already in the timestamps)
    mt = np.arange(-0.1, n_scans * 0.02 + 0.1, 0.005)
    return scans, clock, HOST0_NS + np.round(mt * 1e9).astype(np.int64), beta_true(mt), np.concatenate(truth_t)


def test_beam_interval_is_the_mirror_turning_the_step() -> None:
    assert beam_interval_us(np.deg2rad(0.5), 50.0) == pytest.approx(1e6 / 36000)
    assert beam_interval_us(np.deg2rad(0.25), 25.0) == pytest.approx(1e6 / 36000)
    with pytest.raises(SweepError):
        beam_interval_us(0.0, 50.0)


def test_each_beam_gets_the_motor_angle_at_its_instant() -> None:
    rng = np.random.default_rng(5)
    scans, clock, mt_ns, mpos, beam_t_true = _sweep(rng)
    calib = RigCalibration()
    m = map_sweep(scans, mt_ns, mpos, clock, calib, min_range_m=0.05)
    assert m.beams_total == 250 * 541 and m.points.shape == (250 * 541, 3)
    t_rel = beam_t_true - (mt_ns[0] - HOST0_NS) * 1e-9
    # the beam times come out on the clock model (sub-0.2 ms), so beta matches the analytic curve
    assert np.max(np.abs(m.beam_time_s - t_rel)) < 2e-4
    err = m.beta - beta_true(beam_t_true)
    assert np.max(np.abs(err)) < 0.17 * 2e-4 + 1e-5  # rate x time error + interpolation error
    # within one scan the plane turns (~0.2 rad/s x 15 ms): first and last beam differ by that
    turned = m.beta[540] - m.beta[0]
    assert turned > 2.5e-3
    assert turned == pytest.approx(beta_true(beam_t_true[540:541])[0] - beta_true(beam_t_true[:1])[0], rel=1e-2)
    # the 3D points follow Eq. 1 with those angles
    alpha = calib.alpha(np.deg2rad(-45.0) + np.deg2rad(0.5) * np.tile(np.arange(541), 250))
    expect = forward(np.concatenate([s.ranges_m for s in scans]), alpha, beta_true(beam_t_true))
    assert np.max(np.linalg.norm(m.points - expect, axis=1)) < 4.0 * 5e-5


def test_beams_outside_motor_samples_and_window_are_counted_not_invented() -> None:
    rng = np.random.default_rng(6)
    scans, clock, mt_ns, mpos, _ = _sweep(rng, n_scans=100)
    cut = len(mt_ns) // 2
    m = map_sweep(scans, mt_ns[:cut], mpos[:cut], clock, RigCalibration())
    assert m.beams_without_motor > 0 and not np.any(np.isnan(m.beta))
    assert m.points.shape[0] + m.beams_without_motor == m.beams_total
    w = map_sweep(scans, mt_ns, mpos, clock, RigCalibration(), beta_window=(-0.3, -0.25))
    assert w.beams_outside_sweep > 0 and np.all((w.beta >= -0.3) & (w.beta <= -0.25))


def test_no_echo_and_range_limits() -> None:
    rng = np.random.default_rng(7)
    scans, clock, mt_ns, mpos, _ = _sweep(rng, n_scans=10)
    scans[3].ranges_m[:100] = 0.0
    scans[4].ranges_m[:10] = 30.0
    m = map_sweep(scans, mt_ns, mpos, clock, RigCalibration(), max_range_m=20.0)
    assert m.beams_no_echo == 100 and m.beams_out_of_range == 10
    assert m.points.shape[0] == 10 * 541 - 110


def test_interpolation_errors() -> None:
    with pytest.raises(SweepError, match="two motor samples"):
        interpolate_angle([0.0], [0.0], [1.0])
    with pytest.raises(SweepError, match="increase"):
        interpolate_angle([0.0], [0.0, 0.0], [1.0, 2.0])
    out = interpolate_angle([-1.0, 0.5, 2.0], [0.0, 1.0], [0.0, 2.0])
    assert np.isnan(out[0]) and out[1] == 1.0 and np.isnan(out[2])


def test_gap_counter_counts_every_missing_scan_across_the_wrap() -> None:
    g = GapCounter()
    for c in [65530, 65531, 65533, 65535, 0, 4, 4, 5]:
        g.add(c)
    assert g.received == 8 and g.duplicates == 1
    assert g.missing == 1 + 1 + 3 and g.gaps == [(65531, 1), (65533, 1), (0, 3)]
    g.reset_reference()
    assert g.add(100) == 0


def test_motor_samples_are_added_as_one_batch() -> None:
    from service.sweep import MotorTrack

    track = MotorTrack()
    track.add(5, 0.5, 0.1)
    track.extend(np.array([1, 3, 2]), np.array([0.1, 0.3, 0.2]), np.array([0.0, 0.0, 0.0]))
    assert len(track) == 4
    t, p = track.arrays()
    assert t.tolist() == [1, 2, 3, 5] and p.tolist() == [0.1, 0.2, 0.3, 0.5]
    with pytest.raises(ValueError, match="differ in length"):
        track.extend([1, 2], [0.1], [0.0, 0.0])


def test_motor_timing_jitter_reads_the_time_stamps_scatter_from_a_constant_speed_sweep() -> None:
    from service.sweep import motor_timing_jitter

    rng = np.random.default_rng(3)
    t_sync = np.arange(0.0, 5.0, 0.005)  # 200 Hz SYNC times
    speed = np.deg2rad(20.0)
    for sigma in (0.0002, 0.002):
        latch = t_sync + 0.004 + rng.normal(0.0, sigma, t_sync.size)  # drive latches late, by a varying delay
        angle = -0.5 + speed * latch  # constant speed
        est = motor_timing_jitter(t_sync, angle, (-0.45, 1.0), (0.2, 4.8))
        assert est is not None and est == pytest.approx(sigma, rel=0.1)
    # the approach crossing the window before the sweep is left out by the time span
    angle = np.where(t_sync < 1.0, 0.3 - speed * t_sync, speed * (t_sync - 1.0) - 0.1)
    assert motor_timing_jitter(t_sync, angle, (-0.05, 1.0), (1.5, 4.8)) == pytest.approx(0.0, abs=1e-9)
    # at rest, or without a window (step-and-scan), or too few samples: nothing to read
    assert motor_timing_jitter(t_sync, np.zeros_like(t_sync), (-1.0, 1.0)) is None
    assert motor_timing_jitter(t_sync, speed * t_sync, None) is None
    assert motor_timing_jitter(t_sync[:10], speed * t_sync[:10], (-1.0, 1.0)) is None


def test_the_nominal_rig_model_maps_bit_for_bit_as_eq1() -> None:
    """A nominal ``RigModel`` (p given or not, world pose or not) gives exactly Eq. 1's points and beams."""
    from lrms.kinematics import RigModel, beam_rays

    rng = np.random.default_rng(8)
    scans, clock, mt_ns, mpos, _ = _sweep(rng, n_scans=20)
    pose = np.eye(4)
    pose[:3, 3] = [0.5, -1.0, 2.0]
    for calib in (
        RigCalibration(),
        RigCalibration(p=0.12),
        RigCalibration(model=RigModel(p=0.12)),
        RigCalibration(p=0.12, world_from_rig=pose),
    ):
        m = map_sweep(scans, mt_ns, mpos, clock, calib)
        assert m.rig.is_nominal() and m.rig.p == calib.p
        rig_pts = forward(m.ranges, m.alpha, m.beta, calib.p)
        assert np.array_equal(m.rig_points, rig_pts)
        posed = not np.array_equal(calib.world_from_rig, np.eye(4))
        assert np.array_equal(m.points, calib.to_world(rig_pts) if posed else rig_pts)
        o, d, ranges = m.beam_rays()
        o_eq1, d_eq1 = beam_rays(m.alpha, m.beta, calib.p)
        assert np.array_equal(o, o_eq1) and np.array_equal(d, d_eq1) and np.array_equal(ranges, m.ranges)


def _full_model() -> dict[str, float]:
    return dict(ALL_TERMS)  # every [kinematics] term, as the calibrated-mapping test uses them


def test_map_sweep_applies_every_term_of_the_rig_model() -> None:
    """Every [kinematics] term moves the points as ``RigModel.forward`` says, with the motor speed
    at each beam (the analytic trajectory's derivative) for backlash and time offset; the beams of
    ``MappedSweep.beam_rays`` meet the points."""
    from lrms.kinematics import RigModel

    rng = np.random.default_rng(9)
    scans, clock, mt_ns, mpos, beam_t = _sweep(rng, n_scans=40)
    ranges = np.concatenate([s.ranges_m for s in scans])
    full = _full_model()
    nominal = map_sweep(scans, mt_ns, mpos, clock, RigCalibration(p=0.103))
    speed_true = 0.17 + 0.01 * np.pi * np.cos(np.pi * beam_t)  # d beta_true / dt > 0: one direction
    for key in full:
        if key == "p_m":
            continue
        calib = RigCalibration.from_dict({"p_m": 0.103, key: full[key]})
        m = map_sweep(scans, mt_ns, mpos, clock, calib)
        assert np.array_equal(m.beta, nominal.beta)  # the encoder's angle; the model corrects it
        expect = calib.rig.forward(ranges, m.alpha, m.beta, speed_true)
        moved = float(np.max(np.linalg.norm(m.points - nominal.points, axis=1)))
        assert moved > 5e-4, key  # the term is applied: >= 0.5 mm somewhere at these magnitudes
        # the speed is the slope of the 200 Hz samples' polyline: off the derivative by up to
        # |beta''| dt / 2 = 0.1 rad/s^2 x 2.5 ms = 2.5e-4 rad/s, x 4 ms x 4 m = 4 um (time offset only)
        assert np.max(np.linalg.norm(m.points - expect, axis=1)) < (1e-5 if key == "time_offset_s" else 1e-12), key
    calib = RigCalibration.from_dict(full)
    m = map_sweep(scans, mt_ns, mpos, clock, calib)
    assert np.max(np.abs(m.motor_speed - speed_true)) < 2e-3  # type: ignore[operator]
    assert np.max(np.linalg.norm(m.points - calib.rig.forward(ranges, m.alpha, m.beta, speed_true), axis=1)) < 1e-5
    o, d, geo = m.beam_rays()
    assert np.max(np.linalg.norm(o + geo[:, None] * d - m.points, axis=1)) < 1e-12
    assert np.allclose(geo, 0.015 + (1 + 800e-6) * ranges)
    # backlash follows the direction of motion: the same sweep run backwards takes +backlash/2
    only = RigCalibration.from_dict({"backlash_deg": 0.08})
    up = map_sweep(scans, mt_ns, mpos, clock, only)
    down = map_sweep(scans, mt_ns, -mpos, clock, only)
    half = np.deg2rad(0.04)
    assert np.allclose(up.rig_points, forward(up.ranges, up.alpha, up.beta - half), atol=1e-12)
    assert np.allclose(down.rig_points, forward(down.ranges, down.alpha, down.beta + half), atol=1e-12)
    assert isinstance(m.rig, RigModel) and m.rig == calib.rig


def test_interpolated_motor_speed_is_the_polyline_slope() -> None:
    from service.sweep import interpolate_speed

    out = interpolate_speed([-1.0, 0.5, 1.0, 1.5, 2.5], [0.0, 1.0, 2.0], [0.0, 2.0, 2.0])
    assert np.isnan(out[0]) and out[1] == 2.0 and out[2] == 0.0 and out[3] == 0.0 and np.isnan(out[4])
    with pytest.raises(SweepError, match="two motor samples"):
        interpolate_speed([0.0], [0.0], [1.0])
    with pytest.raises(SweepError, match="increase"):
        interpolate_speed([0.0], [1.0, 0.0], [1.0, 2.0])
