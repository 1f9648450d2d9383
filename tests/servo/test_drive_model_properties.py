"""Property tests of the simulated drive's trajectory generator (hypothesis, manual clock)."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.servo import cia402
from drivers.servo.cia402 import Mode
from sim.drive.model import SimDrive


class ManualClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@settings(max_examples=25, deadline=None)
@given(
    start=st.integers(-50_000, 50_000),
    distance=st.integers(-60_000, 60_000),
    velocity=st.integers(5_000, 400_000),
    accel=st.integers(100_000, 5_000_000),
)
def test_profile_position_moves_land_exactly_within_limits(
    start: int, distance: int, velocity: int, accel: int
) -> None:
    clock = ManualClock()
    drive = SimDrive(1, clock=clock, position=start)
    drive.write(cia402.MODES_OF_OPERATION, 0, int(Mode.PROFILE_POSITION))
    for cw in (0x06, 0x07, 0x0F):
        drive.write(cia402.CONTROLWORD, 0, cw)
    drive.write(cia402.PROFILE_VELOCITY, 0, velocity)
    drive.write(cia402.PROFILE_ACCELERATION, 0, accel)
    drive.write(cia402.PROFILE_DECELERATION, 0, accel)
    drive.write(cia402.FOLLOWING_ERROR_WINDOW, 0, 0xFFFFFFFF)  # fast profiles may lag more than 2000
    drive.write(cia402.TARGET_POSITION, 0, start + distance)
    drive.write(cia402.CONTROLWORD, 0, 0x1F)
    drive.write(cia402.CONTROLWORD, 0, 0x0F)
    # trapezoid (or triangle) duration
    d = abs(distance)
    t_ramp = velocity / accel
    duration = 2 * t_ramp + (d - velocity * t_ramp) / velocity if d >= velocity * t_ramp else 2 * math.sqrt(d / accel)
    dt = 0.002
    previous = start
    steps = math.ceil((duration + 0.05) / dt)
    for _ in range(steps):
        clock.t += dt
        demand = drive.read(cia402.POSITION_DEMAND)
        assert abs(demand - previous) <= velocity * dt * 1.001 + 1  # never faster than the profile
        if distance >= 0:
            assert start - 1 <= demand <= start + distance  # no overshoot, no backing up
        else:
            assert start + distance <= demand <= start + 1
        if clock.t < duration - 0.005:  # not there before the profile says so
            assert demand != start + distance or d <= velocity * dt
        previous = demand
    assert drive.read(cia402.POSITION_DEMAND) == start + distance
    assert drive.read(cia402.POSITION_ACTUAL) == start + distance
    assert drive.read(cia402.STATUSWORD) & cia402.SW_TARGET_REACHED
