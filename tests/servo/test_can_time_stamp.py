"""The drive's own latch time (CiA 301 object 0x1013) in every motor sample: the simulated drive
answers it over SDO and latches it with the position at SYNC; our CANopen driver maps it next to
the position when the drive has it, over a real python-can bus (``virtual`` and socketcand)."""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Iterator

import can
import numpy as np
import pytest

from drivers.servo import cia402
from drivers.servo.cia402 import CodecError, ObjectSpec
from drivers.servo.cia402_can import CanUrlOptions, Cia402CanMotor
from drivers.servo.interface import DriveConfig, MotorSample
from drivers.url import open_device
from sim.drive.can_node import SimCanNode
from sim.drive.model import ObjectAccessError, SimDrive
from sim.drive.socketcand import SimulatedCanDrive
from tests.servo.util import wait_for

CONFIG = DriveConfig(velocity_rad_s=math.radians(60.0), acceleration_rad_s2=math.radians(600.0))


def jogging_samples(m: Cia402CanMotor, n: int = 60) -> list[MotorSample]:
    m.enable()
    m.jog(math.radians(20.0))
    wait_for(lambda: abs(math.degrees(m.velocity_rad_s()) - 20.0) < 0.2)
    t0 = m.clock()
    wait_for(lambda: len(m.samples_since(t0)) >= n)
    samples = m.samples_since(t0)
    m.stop()
    return samples


def check_latch_times(samples: list[MotorSample], drive: SimDrive) -> None:
    """Each stamp is the drive's clock at the latch: after the SYNC was sent, before the TPDO came."""
    for s in samples:
        assert s.drive_stamp_us is not None and s.t_rx_host_s is not None
        t_latch = drive.stamp_epoch + s.drive_stamp_us * 1e-6  # a fresh drive: no wrap yet
        assert s.t_host_s - 1e-6 <= t_latch <= s.t_rx_host_s + 1e-6
    stamps = np.array([s.drive_stamp_us for s in samples])
    assert np.all(np.diff(stamps) > 0)


def test_the_sim_drive_answers_0x1013_with_its_clock_in_microseconds() -> None:
    with open_device("motor", "sim://?node=11&sync_hz=100", config=CONFIG) as m:
        assert isinstance(m, Cia402CanMotor)
        drive = m.sim_node.drive
        t_before = time.monotonic()
        (a,) = struct.unpack("<I", m.sdo_upload(cia402.HIGH_RES_TIMESTAMP))
        t_after = time.monotonic()
        assert (t_before - drive.stamp_epoch) * 1e6 - 1 <= a <= (t_after - drive.stamp_epoch) * 1e6 + 1
        time.sleep(0.05)
        (b,) = struct.unpack("<I", m.sdo_upload(cia402.HIGH_RES_TIMESTAMP))
        assert b - a >= 50_000


def test_the_driver_maps_the_stamp_next_to_the_position_and_reports_it_per_sample() -> None:
    with open_device("motor", "sim://?node=12&sync_hz=100", config=CONFIG) as m:
        assert isinstance(m, Cia402CanMotor)
        assert m.drive_stamped
        drive = m.sim_node.drive
        # the drive holds the mapping the driver wrote: position + stamp in TPDO1, 64 bits
        assert drive.pdo_mapping(cia402.TPDO_MAP) == list(cia402.SAMPLE_TPDOS_STAMPED[0])
        assert drive.pdo_mapping(cia402.TPDO_MAP + 1) == list(cia402.SAMPLE_TPDOS_STAMPED[1])
        samples = jogging_samples(m)
        check_latch_times(samples, drive)
        # statusword (now in TPDO2) still reaches the samples and the state machine
        assert all(cia402.decode_state(s.statusword) is cia402.State.OPERATION_ENABLED for s in samples)
        a = m.sample_arrays_since(samples[0].t_host_s - 1e-9)
        assert a.drive_stamp_us[0] == samples[0].drive_stamp_us and np.all(a.drive_stamp_us >= 0)


def test_the_stamp_comes_across_socketcand_too() -> None:
    with SimulatedCanDrive(node=13) as sim:
        m = open_device("motor", sim.url + "&sync_hz=100", config=CONFIG)
        try:
            assert isinstance(m, Cia402CanMotor) and m.drive_stamped
            check_latch_times(jogging_samples(m), sim.drive)
            # a second, passive master reads which layout the first one mapped from the drive
            with open_device("motor", sim.url + "&setup=0&sync_hz=0&master_id=0", config=CONFIG) as passive:
                assert isinstance(passive, Cia402CanMotor) and passive.drive_stamped
        finally:
            m.close()


def test_a_passive_master_with_drive_stamp_0_decodes_the_stamped_layout_it_finds() -> None:
    """drive_stamp=0 only chooses what a master maps itself: joining a drive the other master
    mapped stamped, the passive one decodes that layout (else statusword and position are garbage)."""
    with SimulatedCanDrive(node=16) as sim:
        m = open_device("motor", sim.url + "&sync_hz=100", config=CONFIG)
        try:
            assert isinstance(m, Cia402CanMotor) and m.drive_stamped
            m.enable()
            m.move_to(math.radians(15.0), wait=True)
            url = sim.url + "&setup=0&sync_hz=0&master_id=0&drive_stamp=0"
            with open_device("motor", url, config=CONFIG) as passive:
                assert isinstance(passive, Cia402CanMotor) and passive.drive_stamped
                t0 = passive.clock()
                wait_for(lambda: len(passive.samples_since(t0)) >= 5)
                for s in passive.samples_since(t0):
                    assert math.degrees(s.position_rad) == pytest.approx(15.0, abs=0.01)
                    assert cia402.decode_state(s.statusword) is cia402.State.OPERATION_ENABLED
                    assert s.drive_stamp_us is not None and s.drive_stamp_us >= 0
        finally:
            m.close()


def test_drive_stamp_0_keeps_the_plain_layout_and_sync_times() -> None:
    with open_device("motor", "sim://?node=14&sync_hz=100&drive_stamp=0", config=CONFIG) as m:
        assert isinstance(m, Cia402CanMotor)
        assert not m.drive_stamped
        assert m.sim_node.drive.pdo_mapping(cia402.TPDO_MAP) == list(cia402.SAMPLE_TPDOS_PLAIN[0])
        samples = jogging_samples(m, 20)
        assert all(s.drive_stamp_us is None and s.t_rx_host_s is None for s in samples)
        assert np.all(m.sample_arrays_since().drive_stamp_us == -1)


class DriveWithoutTimeStamp(SimDrive):
    """A drive whose object dictionary has no 0x1013 (SDO abort 0x06020000, as real ones answer)."""

    @staticmethod
    def spec(index: int, subindex: int = 0) -> ObjectSpec:
        if index == cia402.HIGH_RES_TIMESTAMP:
            raise ObjectAccessError(index, subindex, cia402.ABORT_NO_OBJECT)
        return SimDrive.spec(index, subindex)


@pytest.fixture
def plain_drive_bus() -> Iterator[tuple[can.BusABC, SimCanNode]]:
    channel = f"lrms-no-stamp-{time.monotonic_ns()}"
    node = SimCanNode(can.Bus(interface="virtual", channel=channel), DriveWithoutTimeStamp(15)).start()
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        yield bus, node
    finally:
        node.stop()
        node.bus.shutdown()


def test_a_drive_without_0x1013_gets_the_plain_layout(plain_drive_bus: tuple[can.BusABC, SimCanNode]) -> None:
    bus, node = plain_drive_bus
    m = Cia402CanMotor(bus, CanUrlOptions(node=15, sync_hz=100), config=CONFIG)
    try:
        assert not m.drive_stamped
        assert node.drive.pdo_mapping(cia402.TPDO_MAP) == list(cia402.SAMPLE_TPDOS_PLAIN[0])
        samples = jogging_samples(m, 20)
        assert all(s.drive_stamp_us is None for s in samples)
        assert samples[-1].position_rad > samples[0].position_rad
    finally:
        m.close()


def test_unpack_pdo_reads_the_mapped_objects_and_refuses_short_frames() -> None:
    data = struct.pack("<iI", -123456, 0xFFFFFFF0)
    assert cia402.unpack_pdo(cia402.SAMPLE_TPDOS_STAMPED[0], data) == {
        cia402.POSITION_ACTUAL: -123456,
        cia402.HIGH_RES_TIMESTAMP: 0xFFFFFFF0,
    }
    assert cia402.unpack_pdo(cia402.SAMPLE_TPDOS_STAMPED[1], struct.pack("<Hi", 0x0237, -5)) == {
        cia402.STATUSWORD: 0x0237,
        cia402.VELOCITY_ACTUAL: -5,
    }
    with pytest.raises(CodecError, match="shorter"):
        cia402.unpack_pdo(cia402.SAMPLE_TPDOS_STAMPED[0], data[:7])
    with pytest.raises(CodecError, match="not a mappable"):
        cia402.unpack_pdo(((cia402.POSITION_ACTUAL, 0, 16),), data)
