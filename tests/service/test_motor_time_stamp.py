"""Motor samples timed by the drive's own latch time (0x1013), mapped to host time by the
recorder's clock model, against a simulated drive that is slow to process SYNC: the mapped time
stays on the true latch instant while the SYNC send time misses it by the delay."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from drivers.servo.cia402_can import Cia402CanMotor
from drivers.servo.interface import DriveConfig
from drivers.url import open_device
from lrms.kinematics import RigCalibration
from service.sweep import SweepError, SweepRecorder

CONFIG = DriveConfig(velocity_rad_s=math.radians(60.0), acceleration_rad_s2=math.radians(600.0))


def test_drive_time_lands_on_the_latch_instant_where_the_sync_time_does_not() -> None:
    with open_device("motor", "sim://?node=21&sync_hz=200", config=CONFIG) as m:
        assert isinstance(m, Cia402CanMotor) and m.drive_stamped
        node = m.sim_node
        # the drive latches 2..5 ms after the SYNC reached it: a slow drive (or a loaded host)
        node.sync_delay_s = 0.002
        node.sync_delay_jitter_s = 0.003
        m.enable()
        m.jog(math.radians(20.0))
        t0 = m.clock()
        deadline = t0 + 30.0
        while len(m.samples_since(t0)) < 600 and m.clock() < deadline:  # 3 s at 200 Hz
            time.sleep(0.05)
        m.stop()
        a = m.sample_arrays_since(t0)
        assert a.t_host_s.size >= 600
        recorder = SweepRecorder(RigCalibration())
        # in batches, as a sweep pulls them
        batches = [slice(i, i + 40) for i in range(0, a.t_host_s.size, 40)]
        mapped = np.concatenate(
            [recorder.motor_sample_times(a.t_host_s[b], a.drive_stamp_us[b], a.t_rx_host_s[b]) for b in batches]
        )
        assert recorder.motor_time_source == "drive"
        truth = node.drive.stamp_epoch + a.drive_stamp_us * 1e-6  # the drive clock is this host's monotonic clock
        settled = slice(200, None)  # after 1 s of pairs
        drive_err = mapped[settled] - truth[settled]
        sync_err = a.t_host_s[settled] - truth[settled]
        print(
            f"drive-time error: median {np.median(drive_err) * 1e3:.3f} ms,"
            f" max |.| {np.max(np.abs(drive_err)) * 1e3:.3f} ms;"
            f" SYNC-time error: median {np.median(sync_err) * 1e3:.3f} ms, std {np.std(sync_err) * 1e3:.3f} ms"
        )
        # the SYNC time is early by the processing delay (2..5 ms, plus the bus), and it scatters
        assert np.median(sync_err) < -0.0025
        assert np.std(sync_err) > 0.0006
        # the mapped drive time is the latch instant plus the least latch-to-host delay seen
        assert np.max(np.abs(drive_err)) < 0.001
        assert np.std(drive_err) < 0.0002


def test_samples_without_a_drive_stamp_keep_their_sync_time() -> None:
    recorder = SweepRecorder(RigCalibration())
    t = np.array([1.0, 1.005, 1.010])
    out = recorder.motor_sample_times(t, np.array([-1, -1, -1]), np.full(3, np.nan))
    assert np.array_equal(out, t) and recorder.motor_time_source == "sync"
    assert np.array_equal(recorder.motor_sample_times(t), t)
    # drive-stamped samples next to these: the result says the time bases were mixed
    recorder.motor_sample_times(np.array([2.0]), np.array([1_000_000]), np.array([2.0004]))
    assert recorder.motor_time_source == "mixed"
    with pytest.raises(SweepError, match="differ in length"):
        recorder.motor_sample_times(t, np.array([1, 2]), np.zeros(3))
