"""The simulated drive's model on its own (no bus), on a manual clock so motion is deterministic."""

from __future__ import annotations

import itertools
import math

import pytest

from drivers.servo import cia402
from drivers.servo.cia402 import Mode, State
from sim.drive.model import ObjectAccessError, SimDrive


class ManualClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def enabled_drive(mode: Mode = Mode.PROFILE_POSITION) -> tuple[SimDrive, ManualClock, list[tuple[int, int]]]:
    clock = ManualClock()
    drive = SimDrive(1, clock=clock)
    events: list[tuple[int, int]] = []
    drive.add_emcy_listener(lambda code, reg: events.append((code, reg)))
    drive.write(cia402.MODES_OF_OPERATION, 0, int(mode))
    for cw in (0x06, 0x07, 0x0F):
        drive.write(cia402.CONTROLWORD, 0, cw)
    assert drive.state is State.OPERATION_ENABLED
    return drive, clock, events


def run(drive: SimDrive, clock: ManualClock, seconds: float, dt: float = 0.001) -> list[tuple[float, int, int, int]]:
    """Advance ``seconds``; trace of (t, demand, actual, statusword) every ``dt``."""
    trace = []
    for _ in range(round(seconds / dt)):
        clock.t += dt
        trace.append(
            (
                clock.t,
                drive.read(cia402.POSITION_DEMAND),
                drive.read(cia402.POSITION_ACTUAL),
                drive.read(cia402.STATUSWORD),
            )
        )
    return trace


def start_move(drive: SimDrive, target: int, velocity: int = 100_000, accel: int = 1_000_000) -> int:
    drive.write(cia402.PROFILE_VELOCITY, 0, velocity)
    drive.write(cia402.PROFILE_ACCELERATION, 0, accel)
    drive.write(cia402.PROFILE_DECELERATION, 0, accel)
    drive.write(cia402.TARGET_POSITION, 0, target)
    drive.write(cia402.CONTROLWORD, 0, 0x1F)
    sw = drive.read(cia402.STATUSWORD)
    drive.write(cia402.CONTROLWORD, 0, 0x0F)
    return sw


def test_state_machine_statuswords() -> None:
    drive = SimDrive(1, clock=ManualClock())
    seen = []
    for cw in (0x06, 0x07, 0x0F, 0x07, 0x06, 0x00):
        drive.write(cia402.CONTROLWORD, 0, cw)
        seen.append(drive.read(cia402.STATUSWORD) & 0x7F)
    assert seen == [0x31, 0x33, 0x37, 0x33, 0x31, 0x40]


def test_trapezoidal_move_lands_exactly_with_limited_velocity_and_acceleration() -> None:
    drive, clock, _ = enabled_drive()
    sw = start_move(drive, 50_000, velocity=100_000, accel=1_000_000)
    assert sw & cia402.SW_SET_POINT_ACK and not sw & cia402.SW_TARGET_REACHED
    assert not drive.read(cia402.STATUSWORD) & cia402.SW_SET_POINT_ACK  # cleared with bit 4
    trace = run(drive, clock, 0.7)
    demand = [d for _, d, _, _ in trace][::10]  # every 10 ms (positions are whole counts)
    vel = [(b - a) / 0.01 for a, b in itertools.pairwise(demand)]
    acc = [(b - a) / 0.01 for a, b in itertools.pairwise(vel)]
    assert max(vel) == pytest.approx(100_000, rel=0.01)
    assert max(abs(a) for a in acc) <= 1_000_000 * 1.05
    assert demand[-1] == 50_000 and trace[-1][2] == 50_000
    # 0.6 s trapezoid (0.1 s ramps, 0.4 s cruise): reached shortly after, not before
    reached = [t - 100.0 for t, _, _, sw in trace if sw & cia402.SW_TARGET_REACHED]
    assert 0.6 <= reached[0] <= 0.63
    assert all(sw & cia402.SW_TARGET_REACHED for t, _, _, sw in trace if t - 100.0 >= reached[0])


def test_triangular_move_and_following_lag() -> None:
    drive, clock, _ = enabled_drive()
    start_move(drive, 1_000, velocity=100_000, accel=1_000_000)
    trace = run(drive, clock, 0.2)
    lag = max(abs(d - a) for _, d, a, _ in trace)
    assert 0 < lag < 2000  # inside the default following-error window
    assert trace[-1][2] == 1_000
    assert drive.read(cia402.FOLLOWING_ERROR_ACTUAL) == 0


def test_relative_move_and_queued_set_point() -> None:
    drive, clock, _ = enabled_drive()
    start_move(drive, 2_000)
    # a second set-point without "change immediately" waits for the first one
    drive.write(cia402.TARGET_POSITION, 0, 1_000)
    drive.write(cia402.CONTROLWORD, 0, 0x0F | cia402.CW_NEW_SET_POINT | cia402.CW_RELATIVE)
    drive.write(cia402.CONTROLWORD, 0, 0x0F)
    trace = run(drive, clock, 0.3)
    positions = [a for _, _, a, _ in trace]
    assert max(positions) == 3_000 and positions[-1] == 3_000


def test_software_limits_clamp_targets_and_stop_jogs() -> None:
    drive, clock, _ = enabled_drive()
    drive.write(cia402.SOFTWARE_POSITION_LIMIT, 1, -5_000)
    drive.write(cia402.SOFTWARE_POSITION_LIMIT, 2, 5_000)
    start_move(drive, 8_000)
    assert drive.read(cia402.STATUSWORD) & cia402.SW_INTERNAL_LIMIT
    run(drive, clock, 0.3)
    assert drive.read(cia402.POSITION_ACTUAL) == 5_000
    drive.write(cia402.MODES_OF_OPERATION, 0, int(Mode.PROFILE_VELOCITY))
    drive.write(cia402.TARGET_VELOCITY, 0, -200_000)
    trace = run(drive, clock, 0.5)
    assert min(a for _, _, a, _ in trace) >= -5_000
    assert trace[-1][2] == -5_000 and drive.read(cia402.STATUSWORD) & cia402.SW_INTERNAL_LIMIT
    with pytest.raises(ObjectAccessError) as info:
        drive.write(cia402.SOFTWARE_POSITION_LIMIT, 1, 6_000)  # min above max
    assert info.value.abort_code == cia402.ABORT_MAX_LESS_THAN_MIN


def test_profile_velocity_halt_and_speed_bits() -> None:
    drive, clock, _ = enabled_drive(Mode.PROFILE_VELOCITY)
    drive.write(cia402.TARGET_VELOCITY, 0, 50_000)
    run(drive, clock, 0.1)
    sw = drive.read(cia402.STATUSWORD)
    assert drive.read(cia402.VELOCITY_ACTUAL) == 50_000
    assert sw & cia402.SW_TARGET_REACHED and not sw & cia402.SW_SPEED_ZERO
    drive.write(cia402.CONTROLWORD, 0, 0x0F | cia402.CW_HALT)
    run(drive, clock, 0.1)
    sw = drive.read(cia402.STATUSWORD)
    assert drive.read(cia402.VELOCITY_ACTUAL) == 0 and sw & cia402.SW_SPEED_ZERO
    assert cia402.decode_state(sw) is State.OPERATION_ENABLED


def test_quick_stop_ramp_then_switch_on_disabled_or_stay() -> None:
    drive, clock, _ = enabled_drive(Mode.PROFILE_VELOCITY)
    drive.write(cia402.TARGET_VELOCITY, 0, 100_000)
    run(drive, clock, 0.2)
    drive.write(cia402.CONTROLWORD, 0, cia402.CMD_QUICK_STOP)
    assert drive.state is State.QUICK_STOP_ACTIVE
    run(drive, clock, 0.1)  # 4e6 counts/s^2 default: 25 ms ramp
    assert drive.state is State.SWITCH_ON_DISABLED  # option code 2 (default)

    drive, clock, _ = enabled_drive(Mode.PROFILE_VELOCITY)
    drive.write(cia402.QUICK_STOP_OPTION, 0, 6)
    drive.write(cia402.TARGET_VELOCITY, 0, 100_000)
    run(drive, clock, 0.2)
    drive.write(cia402.CONTROLWORD, 0, cia402.CMD_QUICK_STOP)
    run(drive, clock, 0.1)
    assert drive.state is State.QUICK_STOP_ACTIVE and drive.read(cia402.VELOCITY_ACTUAL) == 0
    drive.write(cia402.CONTROLWORD, 0, 0x0F)  # transition 16
    assert drive.state is State.OPERATION_ENABLED


def test_injected_stall_trips_following_error_then_reset() -> None:
    drive, clock, events = enabled_drive()
    drive.inject_fault("following_error")
    start_move(drive, 100_000)
    run(drive, clock, 0.2)
    sw = drive.read(cia402.STATUSWORD)
    assert cia402.decode_state(sw) is State.FAULT
    assert sw & cia402.SW_FOLLOWING_ERROR
    assert drive.read(cia402.ERROR_CODE) == cia402.ERR_FOLLOWING_ERROR
    assert events == [(0x8611, 0x21)]
    drive.write(cia402.CONTROLWORD, 0, 0x00)
    drive.write(cia402.CONTROLWORD, 0, 0x80)
    assert drive.state is State.SWITCH_ON_DISABLED
    assert drive.read(cia402.ERROR_CODE) == 0 and events[-1] == (0, 0)


def test_over_current_fault_reaction_and_edge_triggered_reset() -> None:
    drive, clock, events = enabled_drive(Mode.PROFILE_VELOCITY)
    drive.write(cia402.TARGET_VELOCITY, 0, 100_000)
    run(drive, clock, 0.2)
    drive.inject_fault("over_current")
    assert drive.state is State.FAULT_REACTION_ACTIVE  # ramps down first
    run(drive, clock, 0.1)
    assert drive.state is State.FAULT and drive.read(cia402.VELOCITY_ACTUAL) == 0
    assert events == [(cia402.ERR_OVER_CURRENT, 0x03)]
    for cw in (0x06, 0x07, 0x0F):  # no way out but fault reset
        drive.write(cia402.CONTROLWORD, 0, cw)
    assert drive.state is State.FAULT
    drive.write(cia402.CONTROLWORD, 0, 0x80)  # rising edge (previous word had bit 7 clear)
    assert drive.state is State.SWITCH_ON_DISABLED


def test_homing_here_sets_position_to_home_offset() -> None:
    drive, clock, _ = enabled_drive()
    start_move(drive, 3_000)
    run(drive, clock, 0.2)
    drive.write(cia402.HOME_OFFSET, 0, 500)
    drive.write(cia402.MODES_OF_OPERATION, 0, int(Mode.HOMING))
    assert drive.read(cia402.MODES_OF_OPERATION_DISPLAY) == Mode.HOMING
    drive.write(cia402.HOMING_METHOD, 0, 37)
    drive.write(cia402.CONTROLWORD, 0, 0x1F)
    run(drive, clock, 0.01)
    sw = drive.read(cia402.STATUSWORD)
    assert cia402.decode_homing_status(sw) is cia402.HomingStatus.COMPLETED
    assert drive.read(cia402.POSITION_ACTUAL) == 500
    # absolute targets are now in homed coordinates
    drive.write(cia402.CONTROLWORD, 0, 0x0F)
    drive.write(cia402.MODES_OF_OPERATION, 0, int(Mode.PROFILE_POSITION))
    start_move(drive, 0)
    run(drive, clock, 0.2)
    assert drive.read(cia402.POSITION_ACTUAL) == 0


@pytest.mark.parametrize(
    ("index", "sub", "value", "code"),
    [
        (0x1234, 0, 1, cia402.ABORT_NO_OBJECT),
        (cia402.IDENTITY, 9, 1, cia402.ABORT_NO_SUBINDEX),
        (cia402.STATUSWORD, 0, 1, cia402.ABORT_READ_ONLY),
        (cia402.DEVICE_TYPE, 0, 1, cia402.ABORT_READ_ONLY),
        (cia402.MODES_OF_OPERATION, 0, 200, cia402.ABORT_VALUE_TOO_HIGH),
        (cia402.MODES_OF_OPERATION, 0, 8, cia402.ABORT_INVALID_VALUE),  # CSP not supported
        (cia402.HOMING_METHOD, 0, 1, cia402.ABORT_INVALID_VALUE),
        (cia402.PROFILE_VELOCITY, 0, -1, cia402.ABORT_VALUE_TOO_LOW),
        (cia402.TPDO_MAP + 2, 1, 0x60850020, cia402.ABORT_NOT_MAPPABLE),  # quick stop decel: not mappable
        (cia402.TPDO_MAP + 2, 1, 0x60640010, cia402.ABORT_NOT_MAPPABLE),  # wrong length
        (cia402.RPDO_MAP + 2, 1, 0x60410010, cia402.ABORT_NOT_MAPPABLE),  # statusword is read-only
    ],
)
def test_refused_writes_carry_sdo_abort_codes(index: int, sub: int, value: int, code: int) -> None:
    drive = SimDrive(1, clock=ManualClock())
    with pytest.raises(ObjectAccessError) as info:
        drive.write(index, sub, value)
    assert info.value.abort_code == code


def test_pdo_length_limit() -> None:
    drive = SimDrive(1, clock=ManualClock())
    m = cia402.TPDO_MAP + 2
    for sub, entry in enumerate((0x60640020, 0x606C0020, 0x60410010), start=1):
        drive.write(m, sub, entry)
    with pytest.raises(ObjectAccessError) as info:
        drive.write(m, 0, 3)  # 80 bits > 64
    assert info.value.abort_code == cia402.ABORT_PDO_LENGTH
    drive.write(m, 0, 2)
    assert drive.pdo_mapping(m) == [(0x6064, 0, 32), (0x606C, 0, 32)]


def test_strings_and_wire_encoding() -> None:
    drive = SimDrive(1, clock=ManualClock())
    assert drive.read_bytes(cia402.DEVICE_NAME) == b"LRMS simulated CiA 402 drive"
    drive.write_bytes(cia402.USER_NOTE, 0, b"rig 3, axis beta")
    assert drive.read_bytes(cia402.USER_NOTE) == b"rig 3, axis beta"
    with pytest.raises(ObjectAccessError) as info:
        drive.write_bytes(cia402.CONTROLWORD, 0, b"\x06\x00\x00")
    assert info.value.abort_code == cia402.ABORT_LENGTH_TOO_HIGH
    with pytest.raises(ObjectAccessError):
        drive.read(cia402.DEVICE_NAME)  # not an integer
    assert drive.read(cia402.DEVICE_TYPE) & 0xFFFF == 402
    with pytest.raises(ValueError):
        drive.inject_fault("gremlins")
    assert math.isfinite(drive.read(cia402.HIGH_RES_TIMESTAMP))


@pytest.mark.parametrize(("method", "start"), [(19, 0), (19, 9_000), (21, 0), (21, 9_000)])
def test_homing_on_the_switch_edge_takes_time_and_latches_the_edge(method: int, start: int) -> None:
    clock = ManualClock()
    drive = SimDrive(1, clock=clock, position=start)
    drive.write(cia402.MODES_OF_OPERATION, 0, int(Mode.HOMING))
    for cw in (0x06, 0x07, 0x0F):
        drive.write(cia402.CONTROLWORD, 0, cw)
    drive.write(cia402.HOMING_METHOD, 0, method)
    drive.write(cia402.HOME_OFFSET, 0, 100)
    drive.write(cia402.CONTROLWORD, 0, 0x1F)
    statuses = []
    for _ in range(3000):
        run(drive, clock, 0.001)
        status = cia402.decode_homing_status(drive.read(cia402.STATUSWORD))
        if not statuses or statuses[-1] != status:
            statuses.append(status)
        if status is cia402.HomingStatus.COMPLETED:
            break
    H = cia402.HomingStatus
    assert statuses == [H.IN_PROGRESS, H.ATTAINED_NOT_REACHED, H.COMPLETED]
    # the raw edge (5000 counts) now reads the home offset; the axis stopped just past it
    position = drive.read(cia402.POSITION_ACTUAL)
    assert abs(position - 100) < 60
    drive.write(cia402.CONTROLWORD, 0, 0x0F)
    drive.write(cia402.MODES_OF_OPERATION, 0, int(Mode.PROFILE_POSITION))
    start_move(drive, 100)
    run(drive, clock, 0.1)
    assert drive.read(cia402.POSITION_ACTUAL) == 100
    assert drive.read(cia402.POSITION_DEMAND) == 100


def test_homing_interrupted_by_clearing_bit4() -> None:
    drive, clock, _ = enabled_drive(Mode.HOMING)
    drive.write(cia402.HOMING_METHOD, 0, 19)
    drive.write(cia402.CONTROLWORD, 0, 0x1F)
    run(drive, clock, 0.05)
    assert cia402.decode_homing_status(drive.read(cia402.STATUSWORD)) is cia402.HomingStatus.IN_PROGRESS
    drive.write(cia402.CONTROLWORD, 0, 0x0F)
    run(drive, clock, 0.1)
    assert cia402.decode_homing_status(drive.read(cia402.STATUSWORD)) is cia402.HomingStatus.INTERRUPTED
    assert drive.read(cia402.VELOCITY_ACTUAL) == 0
