"""Pure CiA 402 definitions: state decoding, transitions, homing status, EMCY, SDO aborts, DriveConfig."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.errors import DriverError
from drivers.servo import cia402
from drivers.servo.cia402 import Command, State
from drivers.servo.interface import (
    DriveConfig,
    DriveConfigError,
    MotorSample,
    SampleBuffer,
    SampleRangeError,
    TargetOutOfRange,
)


@pytest.mark.parametrize(
    ("word", "state"),
    [
        (0x0000, State.NOT_READY_TO_SWITCH_ON),
        (0x0640, State.SWITCH_ON_DISABLED),
        (0x0250, State.SWITCH_ON_DISABLED),
        (0x0631, State.READY_TO_SWITCH_ON),
        (0x0221, State.READY_TO_SWITCH_ON),
        (0x0633, State.SWITCHED_ON),
        (0x0637, State.OPERATION_ENABLED),
        (0x1637, State.OPERATION_ENABLED),
        (0x0617, State.QUICK_STOP_ACTIVE),
        (0x021F, State.FAULT_REACTION_ACTIVE),
        (0x0608, State.FAULT),
        (0x2218, State.FAULT),
    ],
)
def test_decode_state_uses_masks(word: int, state: State) -> None:
    assert cia402.decode_state(word) is state


def test_state_bits_decode_to_their_state() -> None:
    for state in State:
        assert cia402.decode_state(state.bits | cia402.SW_REMOTE | cia402.SW_TARGET_REACHED) is state


def test_invalid_statusword_is_an_error() -> None:
    with pytest.raises(cia402.StatuswordError):
        cia402.decode_state(0x0001)  # ready bit without anything else


@pytest.mark.parametrize(
    ("cw", "command"),
    [
        (0x0006, Command.SHUTDOWN),
        (0x0007, Command.SWITCH_ON),
        (0x000F, Command.ENABLE_OPERATION),
        (0x001F, Command.ENABLE_OPERATION),  # + new set-point
        (0x010F, Command.ENABLE_OPERATION),  # + halt
        (0x0000, Command.DISABLE_VOLTAGE),
        (0x000D, Command.DISABLE_VOLTAGE),
        (0x0002, Command.QUICK_STOP),
        (0x000B, Command.QUICK_STOP),
        (0x0080, Command.FAULT_RESET),
    ],
)
def test_decode_command(cw: int, command: Command) -> None:
    assert cia402.decode_command(cw) is command


def test_enable_walk_reaches_operation_enabled_through_the_drive_table() -> None:
    # the master-side walk and the drive-side table agree: from every reachable state
    for start in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.QUICK_STOP_ACTIVE):
        state, steps = start, 0
        while (cw := cia402.next_enable_command(state)) is not None:
            state = cia402.transition(state, cia402.decode_command(cw))
            steps += 1
            assert steps <= 3
        assert state is State.OPERATION_ENABLED


def test_transition_table_details() -> None:
    t = cia402.transition
    assert t(State.OPERATION_ENABLED, Command.QUICK_STOP) is State.QUICK_STOP_ACTIVE
    assert t(State.OPERATION_ENABLED, Command.SHUTDOWN) is State.READY_TO_SWITCH_ON
    assert t(State.OPERATION_ENABLED, Command.SWITCH_ON) is State.SWITCHED_ON
    assert t(State.SWITCHED_ON, Command.QUICK_STOP) is State.SWITCH_ON_DISABLED
    assert t(State.FAULT, Command.ENABLE_OPERATION) is State.FAULT
    assert t(State.FAULT, Command.FAULT_RESET) is State.SWITCH_ON_DISABLED
    assert t(State.SWITCH_ON_DISABLED, Command.ENABLE_OPERATION) is State.SWITCH_ON_DISABLED
    assert t(State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE) is State.SWITCH_ON_DISABLED


@pytest.mark.parametrize(
    ("bits", "status"),
    [
        (0, cia402.HomingStatus.IN_PROGRESS),
        (cia402.SW_TARGET_REACHED, cia402.HomingStatus.INTERRUPTED),
        (cia402.SW_HOMING_ATTAINED, cia402.HomingStatus.ATTAINED_NOT_REACHED),
        (cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED, cia402.HomingStatus.COMPLETED),
        (cia402.SW_HOMING_ERROR, cia402.HomingStatus.ERROR_MOVING),
        (cia402.SW_HOMING_ERROR | cia402.SW_TARGET_REACHED, cia402.HomingStatus.ERROR_STOPPED),
    ],
)
def test_homing_status(bits: int, status: cia402.HomingStatus) -> None:
    assert cia402.decode_homing_status(0x0237 | bits) is status


def test_emcy_round_trip_and_reason() -> None:
    frame = bytes([0x11, 0x86, 0x21, 1, 2, 3, 4, 5])
    emcy = cia402.Emcy.decode(frame)
    assert (emcy.code, emcy.register, emcy.vendor) == (0x8611, 0x21, b"\x01\x02\x03\x04\x05")
    assert emcy.reason == "following error"
    assert "following error" in str(emcy) and "device profile specific" in str(emcy)
    assert emcy.encode() == frame
    assert cia402.Emcy.decode(bytes(8)).is_reset
    with pytest.raises(ValueError):
        cia402.Emcy.decode(b"\x00\x00\x00")


def test_error_code_text_and_register() -> None:
    assert cia402.describe_error_code(0x2310) == "continuous over-current"
    assert "temperature" in cia402.describe_error_code(0x4321)
    assert "device specific" in cia402.describe_error_code(0xFF42)
    assert cia402.error_register_for(0x2310) == 0x03  # generic + current
    assert cia402.error_register_for(0x8130) == 0x11  # generic + communication
    assert cia402.error_register_for(0) == 0
    assert cia402.describe_error_register(0x03) == ["generic", "current"]


def test_sdo_abort_text() -> None:
    assert cia402.describe_sdo_abort(0x06020000) == "object does not exist in the object dictionary"
    assert cia402.describe_sdo_abort(0x08000022).endswith("present device state")
    assert "unknown" in cia402.describe_sdo_abort(0x12345678)


def test_data_types_and_pdo_entries() -> None:
    assert cia402.DataType.INT32.encode(-2) == b"\xfe\xff\xff\xff"
    assert cia402.DataType.UINT16.decode(b"\x41\x06") == 0x0641
    assert cia402.DataType.UINT8 is not cia402.DataType.BOOLEAN
    assert cia402.DataType.INT8.range == (-128, 127)
    assert cia402.pdo_map_entry(0x6064, 0, 32) == 0x60640020
    assert cia402.split_pdo_map_entry(0x60640020) == (0x6064, 0, 32)
    spec = cia402.object_spec(cia402.STATUSWORD)
    assert spec.pdo and not spec.access.writable
    assert cia402.mode_supported(0b100101, 1) and cia402.mode_supported(0b100101, 6)
    assert not cia402.mode_supported(0b100101, 8) and not cia402.mode_supported(0b100101, 99)


# ----------------------------------------------------------------------------------------------
# DriveConfig and the sample buffer
# ----------------------------------------------------------------------------------------------


def test_drive_config_conversions() -> None:
    c = DriveConfig(counts_per_rev=10_000, gear_ratio=50.0)
    assert c.counts_per_rad == pytest.approx(500_000 / (2 * math.pi))
    assert c.rad_to_counts(2 * math.pi) == 500_000
    assert c.counts_to_rad(250_000) == pytest.approx(math.pi)
    reverse = DriveConfig(gear_ratio=-50.0)
    assert reverse.rad_to_counts(math.pi) == -250_000
    assert reverse.rate_to_counts(math.pi) == 250_000  # rates are magnitudes
    with pytest.raises(TargetOutOfRange):
        c.rad_to_counts(1e6)


def test_drive_config_from_toml_with_degrees(tmp_path: object) -> None:
    text = """
[motor]
counts_per_rev = 131072
gear_ratio = 100
velocity_deg_s = 10.0
min_angle_deg = -30
max_angle_deg = 90
homing_method = 35
"""
    c = DriveConfig.from_toml(text)
    assert c.counts_per_rev == 131072 and c.gear_ratio == 100.0 and c.homing_method == 35
    assert c.velocity_rad_s == pytest.approx(math.radians(10))
    assert c.min_angle_rad == pytest.approx(math.radians(-30))
    lo, hi = c.software_limits_counts() or (0, 0)
    assert lo == c.rad_to_counts(math.radians(-30)) and hi == c.rad_to_counts(math.radians(90))
    with pytest.raises(TargetOutOfRange, match="above the software limit"):
        c.check_angle(math.radians(91))


@pytest.mark.parametrize(
    "table",
    [
        {"counts_per_rev": 0},
        {"counts_per_rev": 1.5},
        {"gear_ratio": 0},
        {"velocity_deg_s": -1},
        {"velocity_deg_s": 200},  # above max_velocity
        {"min_angle_deg": 10, "max_angle_deg": 5},
        {"colour": "red"},
        {"velocity_rad_s": 0.1, "velocity_deg_s": 5},
        {"gear_ratio": "fifty"},
    ],
)
def test_drive_config_rejects_bad_values(table: dict[str, object]) -> None:
    with pytest.raises(DriveConfigError) as info:
        DriveConfig.from_dict(table)
    assert isinstance(info.value, DriverError)


def test_drive_config_missing_table() -> None:
    with pytest.raises(DriveConfigError, match=r"\[motor\]"):
        DriveConfig.from_toml("name = 'x'\n")


def test_sample_buffer_ring_and_since() -> None:
    buf = SampleBuffer(capacity=8)
    for k in range(20):
        buf.push(MotorSample(float(k), k * 0.1, 1.0, 0x0237))
    assert buf.total == 20
    arrays = buf.arrays_since()
    assert list(arrays.t_host_s) == [float(k) for k in range(12, 20)]  # the newest 8, oldest first
    later = buf.since(16.0)
    assert [s.t_host_s for s in later] == [17.0, 18.0, 19.0]
    assert buf.latest() == MotorSample(19.0, pytest.approx(1.9), 1.0, 0x0237)


def test_sample_buffer_interpolates_positions_without_extrapolating() -> None:
    buf = SampleBuffer(capacity=16)
    with pytest.raises(SampleRangeError):
        buf.positions_at([0.0])
    for k in range(10):
        buf.push(MotorSample(1.0 + 0.01 * k, 0.5 * k, 0.0, 0x0237))
    got = buf.positions_at(np.array([1.0, 1.005, 1.0425, 1.09]))
    assert got == pytest.approx([0.0, 0.25, 2.125, 4.5])
    assert buf.positions_at([]).shape == (0,)
    for bad in ([0.99], [1.0, 1.2], [float("nan")]):
        with pytest.raises(SampleRangeError, match="outside"):
            buf.positions_at(bad)
