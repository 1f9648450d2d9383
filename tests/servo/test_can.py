"""Our CANopen driver against our simulated drive on a real python-can ``virtual`` bus (in-process)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import can
import numpy as np
import pytest

from drivers.errors import DeviceURLError, DriverError
from drivers.servo import cia402
from drivers.servo.cia402 import State
from drivers.servo.cia402_can import CanUrlOptions, Cia402CanMotor, SdoTimeout, open_url
from drivers.servo.interface import (
    DriveConfig,
    HeartbeatLost,
    MotorFault,
    MotorStateError,
    SdoAbort,
    TargetOutOfRange,
)
from drivers.url import open_device
from sim.drive.can_node import SimCanNode
from sim.drive.model import SimDrive
from tests.servo.util import wait_for

FAST = DriveConfig(
    velocity_rad_s=math.radians(60.0),
    acceleration_rad_s2=math.radians(1200.0),
    max_acceleration_rad_s2=math.radians(2000.0),
    min_angle_rad=math.radians(-100.0),
    max_angle_rad=math.radians(100.0),
)


@pytest.fixture
def motor() -> Iterator[Cia402CanMotor]:
    # the default heartbeat, lost after 5 x 100 ms: a busy test machine does not fake a loss
    m = open_device("motor", "sim://?node=5&heartbeat_ms=100", config=FAST)
    try:
        yield m
    finally:
        m.close()


def drive_of(m: Cia402CanMotor) -> SimDrive:
    drive = m.sim_node.drive
    assert isinstance(drive, SimDrive)
    return drive


def test_enable_move_and_samples(motor: Cia402CanMotor) -> None:
    assert motor.state is State.SWITCH_ON_DISABLED
    motor.enable()
    assert motor.state is State.OPERATION_ENABLED
    t0 = motor.clock()
    motor.move_to(math.radians(12.0), wait=True)
    assert math.degrees(motor.position_rad()) == pytest.approx(12.0, abs=0.01)
    drive_counts = drive_of(motor).read(cia402.POSITION_ACTUAL)
    assert drive_counts == pytest.approx(FAST.rad_to_counts(math.radians(12.0)), abs=15)
    a = motor.sample_arrays_since(t0)
    assert np.all(np.diff(a.t_host_s) > 0)  # monotonic stamps
    assert a.position_rad[0] < math.radians(0.5) and a.position_rad[-1] == pytest.approx(math.radians(12.0), abs=2e-4)
    assert np.max(a.velocity_rad_s) == pytest.approx(math.radians(60.0), rel=0.02)  # 0.15 s of cruise
    # every sample carries the statusword of the same SYNC; target reached only at the end
    reached = (a.statusword & cia402.SW_TARGET_REACHED) != 0
    assert reached[-1] and not reached[len(reached) // 2]
    # back, with a callback collecting samples
    got: list[float] = []
    remove = motor.add_sample_callback(lambda s: got.append(s.position_rad))
    motor.move_to(0.0, velocity=math.radians(30.0), wait=True)
    remove()
    assert len(got) > 5 and got[-1] == pytest.approx(0.0, abs=2e-4)


def test_one_sample_per_sync_at_the_default_rate() -> None:
    # The rate itself (200 SYNC/s by default) is a benchmark: bench/bench_servo.py measures it.
    with open_device("motor", "sim://?node=7") as m:
        assert isinstance(m, Cia402CanMotor) and m.options.sync_hz == 200.0
        wait_for(lambda: m.sample_count >= 260, timeout=10.0)
        before = m.sample_count
        a = m.sample_arrays_since()
        after = m.sample_count
        assert before <= len(a.t_host_s) <= after  # the buffer holds every sample so far
        assert np.all(np.diff(a.t_host_s) > 0)  # strictly increasing stamps
        # every stamp is the send time of one of our SYNCs, and they are consecutive SYNCs:
        # none skipped, none answered twice, so samples == SYNCs from the first answered one
        index = {t: i for i, t in enumerate(m.sync_history)}
        ids = np.array([index[t] for t in a.t_host_s])
        assert np.all(np.diff(ids) == 1)
        assert m.sync_count >= ids[-1] + 1  # the SYNCs answered were all counted as sent


def test_jog_stop_and_quick_stop(motor: Cia402CanMotor) -> None:
    motor.enable()
    motor.jog(math.radians(-20.0))
    wait_for(lambda: abs(math.degrees(motor.velocity_rad_s()) + 20.0) < 0.05)
    motor.stop()
    motor.wait_reached(10.0)
    assert motor.state is State.OPERATION_ENABLED
    assert abs(motor.velocity_rad_s()) < math.radians(0.05)
    motor.jog(math.radians(20.0))
    wait_for(lambda: motor.velocity_rad_s() > math.radians(19.0))
    motor.quick_stop()
    wait_for(lambda: motor.state is State.SWITCH_ON_DISABLED)
    assert abs(motor.velocity_rad_s()) < math.radians(0.05)
    with pytest.raises(MotorStateError, match="enable"):
        motor.move_to(0.1)
    with pytest.raises(TargetOutOfRange):
        motor.jog(math.radians(1000.0))


def test_disable_and_software_limits(motor: Cia402CanMotor) -> None:
    motor.enable()
    with pytest.raises(TargetOutOfRange, match="software limit"):
        motor.move_to(math.radians(101.0))
    # the drive's own limit (tighter than the host's) clamps the target and raises bit 11
    motor._write_object(cia402.SOFTWARE_POSITION_LIMIT, 2, FAST.rad_to_counts(math.radians(1.0)))
    motor.move_to(math.radians(2.0), wait=True)
    assert math.degrees(motor.position_rad()) == pytest.approx(1.0, abs=0.01)
    assert motor.statusword & cia402.SW_INTERNAL_LIMIT
    motor.disable()
    assert motor.state is State.READY_TO_SWITCH_ON


def test_home_sets_zero_here(motor: Cia402CanMotor) -> None:
    motor.enable()
    motor.move_to(math.radians(2.0), wait=True)
    motor.home()
    assert motor.position_rad() == pytest.approx(0.0, abs=1e-5)
    assert drive_of(motor).read(cia402.MODES_OF_OPERATION_DISPLAY) == cia402.Mode.HOMING
    motor.move_to(math.radians(-1.0), wait=True)  # back to profile position after homing
    assert math.degrees(motor.position_rad()) == pytest.approx(-1.0, abs=0.01)
    with pytest.raises(SdoAbort) as info:
        motor.home(method=1)  # no index pulse on the simulated drive
    assert info.value.code == cia402.ABORT_INVALID_VALUE


def test_home_on_switch_moves_and_reports_progress(motor: Cia402CanMotor) -> None:
    motor.enable()
    t0 = motor.clock()
    motor.home(method=19, timeout=10.0)  # switch edge 5000 raw counts above the start
    a = motor.sample_arrays_since(t0)
    status = [cia402.decode_homing_status(int(sw)) for sw in a.statusword]
    assert cia402.HomingStatus.IN_PROGRESS in status
    assert status[-1] is cia402.HomingStatus.COMPLETED
    assert np.max(np.abs(a.velocity_rad_s)) > 0.0  # it travelled to find the switch
    assert abs(motor.position_rad()) < FAST.counts_to_rad(60)  # the edge reads 0 (home offset)


def test_sdo_segmented_transfers_and_abort_codes(motor: Cia402CanMotor) -> None:
    assert motor.sdo_upload(cia402.DEVICE_NAME) == b"LRMS simulated CiA 402 drive"  # 28 bytes: segmented
    note = b"beta axis, rig 3, reducer 50:1 (seg)"
    motor.sdo_download(cia402.USER_NOTE, 0, note, force_segment=True)
    assert drive_of(motor).read_bytes(cia402.USER_NOTE) == note
    assert motor.sdo_upload(cia402.USER_NOTE) == note
    motor.sdo_download(cia402.USER_NOTE, 0, b"ab", force_segment=True)  # short segmented
    assert motor.sdo_upload(cia402.USER_NOTE) == b"ab"  # expedited upload
    cases = [
        (lambda: motor.sdo_upload(0x2345), 0x06020000, "does not exist"),
        (lambda: motor.sdo_upload(cia402.IDENTITY, 9), 0x06090011, "sub-index"),
        (lambda: motor.sdo_download(cia402.STATUSWORD, 0, b"\x00\x00"), 0x06010002, "read-only"),
        (lambda: motor.sdo_download(cia402.MODES_OF_OPERATION, 0, b"\x08"), 0x06090030, "value range"),
        (lambda: motor.sdo_download(cia402.CONTROLWORD, 0, b"\x06\x00\x00"), 0x06070012, "too high"),
        (lambda: motor.sdo_download(cia402.TPDO_MAP, 1, b"\x20\x00\x64\x60"), 0x08000022, "device state"),
    ]
    for call, code, text in cases:
        with pytest.raises(SdoAbort) as info:
            call()
        assert info.value.code == code
        assert text in info.value.reason and f"0x{code:08X}" in str(info.value)
        assert isinstance(info.value, DriverError)


def test_emcy_over_current_decoded_and_reset(motor: Cia402CanMotor) -> None:
    motor.enable()
    motor.jog(math.radians(10.0))
    drive_of(motor).inject_fault("over_current")
    wait_for(lambda: len(motor.emcy_history) >= 1)
    _, emcy = motor.emcy_history[-1]
    assert (emcy.code, emcy.register) == (0x2310, 0x03) and emcy.reason == "continuous over-current"
    wait_for(lambda: motor.state is State.FAULT)
    fault = motor.fault()
    assert fault is not None and fault.code == 0x2310 and fault.reason == "continuous over-current"
    with pytest.raises(MotorFault, match="over-current"):
        motor.enable()
    motor.reset_fault()
    assert motor.fault() is None and motor.state is State.SWITCH_ON_DISABLED
    wait_for(lambda: motor.emcy_history[-1][1].is_reset)  # EMCY 0x0000 after the reset
    motor.enable()
    assert motor.state is State.OPERATION_ENABLED


def test_injected_stall_following_error_fault(motor: Cia402CanMotor) -> None:
    motor.enable()
    drive_of(motor).inject_fault("following_error")
    motor.move_to(math.radians(5.0))
    with pytest.raises(MotorFault) as info:
        motor.wait_reached(10.0)
    assert info.value.code == cia402.ERR_FOLLOWING_ERROR and info.value.reason == "following error"
    assert info.value.statusword is not None and info.value.statusword & cia402.SW_FOLLOWING_ERROR
    drive_of(motor).clear_injected()
    motor.reset_fault()
    motor.enable()
    motor.move_to(math.radians(0.5), wait=True)
    assert math.degrees(motor.position_rad()) == pytest.approx(0.5, abs=0.01)


def test_heartbeat_loss_is_a_fault_until_it_returns() -> None:
    # lost after 5 x 100 ms, as in the fixture: a shorter period lets a busy test machine fake a loss
    with open_device("motor", "sim://?node=5&heartbeat_ms=100", config=FAST) as motor:
        assert isinstance(motor, Cia402CanMotor)
        heartbeat_loss_round_trip(motor)


def heartbeat_loss_round_trip(motor: Cia402CanMotor) -> None:
    motor.enable()
    drive_of(motor).inject_fault("heartbeat_loss")
    wait_for(lambda: motor.fault() is not None)
    fault = motor.fault()
    assert fault is not None and fault.code == cia402.ERR_HEARTBEAT and "heartbeat lost" in fault.reason
    with pytest.raises(HeartbeatLost):
        motor.move_to(0.1)
    with pytest.raises(HeartbeatLost, match="still no heartbeat"):
        motor.reset_fault()
    # the driver asked the silent drive for a quick stop
    wait_for(lambda: drive_of(motor).state is State.SWITCH_ON_DISABLED)
    drive_of(motor).clear_injected()
    # the reset clears the fault once a heartbeat came after it (it waits only a few periods for one): wait
    # for the drive's next heartbeat to reach the driver rather than race the node's ticker thread
    wait_for(lambda: motor._last_heartbeat is not None and motor._last_heartbeat > fault.t_host_s)
    motor.reset_fault()
    assert motor.fault() is None
    motor.enable()
    assert motor.state is State.OPERATION_ENABLED


def test_controlword_over_rpdo_is_applied_by_the_node() -> None:
    # the node applies RPDO1 (controlword, event-driven); NMT state rules PDOs
    channel = "lrms-test-rpdo"
    node = SimCanNode(can.Bus(interface="virtual", channel=channel), node_id=9).start()
    master = can.Bus(interface="virtual", channel=channel)
    try:
        master.send(can.Message(arbitration_id=0x000, data=[0x01, 9], is_extended_id=False))  # start
        master.send(can.Message(arbitration_id=0x209, data=[0x06, 0x00], is_extended_id=False))
        wait_for(lambda: node.drive.state is State.READY_TO_SWITCH_ON)
        master.send(can.Message(arbitration_id=0x000, data=[0x02, 9], is_extended_id=False))  # stop
        wait_for(lambda: node.nmt_state == 0x04)
        master.send(can.Message(arbitration_id=0x209, data=[0x07, 0x00], is_extended_id=False))
        master.send(can.Message(arbitration_id=0x609, data=[0x40, 0x41, 0x60, 0, 0, 0, 0, 0], is_extended_id=False))
        seen = []
        deadline = time.monotonic() + 0.1
        while (msg := master.recv(max(0.0, deadline - time.monotonic()))) is not None:
            seen.append(msg.arbitration_id)
        assert node.drive.state is State.READY_TO_SWITCH_ON  # stopped: the RPDO was not applied
        assert 0x589 not in seen  # and the SDO request got no answer
        master.send(can.Message(arbitration_id=0x000, data=[0x81, 0], is_extended_id=False))  # reset all nodes
        boot = master.recv(10.0)  # NMT still works when stopped: the node reboots
        assert boot is not None and boot.arbitration_id == 0x709 and bytes(boot.data) == b"\x00"
        wait_for(lambda: node.nmt_state == 0x7F)
    finally:
        master.shutdown()
        node.stop()
        node.bus.shutdown()


def test_url_errors() -> None:
    with pytest.raises(DeviceURLError, match="unknown option"):
        open_device("motor", "canopen+virtual://x?node=1&speed=3")
    with pytest.raises(DeviceURLError, match="outside"):
        open_device("motor", "canopen+virtual://x?node=200")
    with pytest.raises(DriverError, match="udp_multicast"):
        open_url("canopen+udp_multicast://239.0.0.1?node=1")
    with pytest.raises(DriverError, match="host:port"):
        open_url("canopen+socketcand:///can0?node=1")


def test_no_drive_on_the_bus_is_a_timeout() -> None:
    with pytest.raises(SdoTimeout):
        Cia402CanMotor.open_bus(
            {"interface": "virtual", "channel": "lrms-test-empty"}, CanUrlOptions(node=3, sdo_timeout=0.05)
        )


def test_two_threads_share_one_motor(motor: Cia402CanMotor) -> None:
    motor.enable()
    errors: list[BaseException] = []

    def poll() -> None:
        try:
            for _ in range(30):
                motor.fault()
                motor._read_object(cia402.POSITION_ACTUAL)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=poll)
    t.start()
    motor.move_to(math.radians(1.0), wait=True)
    t.join()
    assert not errors
    assert math.degrees(motor.position_rad()) == pytest.approx(1.0, abs=0.01)


def test_passive_second_master_watches_without_disturbing() -> None:
    channel = f"lrms-test-passive-{time.monotonic_ns()}"
    node = SimCanNode(can.Bus(interface="virtual", channel=channel), node_id=2).start()
    bus_kw = {"interface": "virtual", "channel": channel}
    try:
        with Cia402CanMotor.open_bus(bus_kw, CanUrlOptions(node=2), config=FAST) as owner:
            owner.enable()
            owner.jog(math.radians(10.0))
            commands_before = list(node.nmt_commands)
            watcher = Cia402CanMotor.open_bus(bus_kw, CanUrlOptions(node=2, setup=False, sync_hz=0), config=FAST)
            with watcher:
                assert node.nmt_commands == commands_before  # no NMT from the watcher
                start = watcher.sample_count
                wait_for(lambda: watcher.sample_count - start >= 20)
                assert watcher.sync_count == 0  # it produced no SYNC: the owner's were stamped
                a = watcher.sample_arrays_since()
                assert np.all(np.diff(a.t_host_s) > 0)
                assert watcher.state is State.OPERATION_ENABLED
                assert watcher.fault() is None
                # both see the same frames: every position the watcher got, the owner got too
                t_last = watcher.sample_arrays_since().t_host_s[-1]
                wait_for(lambda: owner.sample_arrays_since().t_host_s[-1] > t_last + 0.05)
                theirs = set(watcher.sample_arrays_since().position_rad.tolist())
                mine = set(owner.sample_arrays_since().position_rad.tolist())
                assert len(theirs) >= 20 and theirs <= mine
            owner.stop()
            owner.wait_reached(10.0)
        # the node answers frames in order: once it has answered an SDO request sent after the owner's last
        # SYNC, the TPDOs for all of the owner's SYNCs are out, and a late one cannot reach the next master
        probe = can.Bus(interface="virtual", channel=channel)
        try:
            probe.send(can.Message(arbitration_id=0x602, data=[0x40, 0x41, 0x60, 0, 0, 0, 0, 0], is_extended_id=False))
            deadline = time.monotonic() + 10.0
            while (msg := probe.recv(max(0.0, deadline - time.monotonic()))) is None or msg.arbitration_id != 0x582:
                assert time.monotonic() < deadline, "the node never answered the SDO request"
        finally:
            probe.shutdown()
        # alone on the bus (no SYNC anywhere): status by SDO, no samples
        with Cia402CanMotor.open_bus(bus_kw, CanUrlOptions(node=2, setup=False, sync_hz=0), config=FAST) as alone:
            assert alone.state is State.OPERATION_ENABLED
            assert alone.sample_count == 0
            assert alone.position_rad() > 0.0  # by SDO
    finally:
        node.stop()
        node.bus.shutdown()


def test_sync_rate_option_values() -> None:
    with pytest.raises(DeviceURLError, match="sync_hz"):
        open_device("motor", "canopen+virtual://x?node=1&sync_hz=5")


def test_late_tpdos_keep_their_own_sync_stamp() -> None:
    # TPDOs leave 1.5 SYNC periods late: each sample still carries the time of the SYNC it
    # answers. The i-th SYNC sent is the i-th the node received (same bus, in order); the
    # sample stamped with SYNC i must hold the position the drive latched at SYNC i.
    with open_device("motor", "sim://?node=8&sync_hz=100") as m:
        assert isinstance(m, Cia402CanMotor)
        node = m.sim_node
        m.enable()
        m.jog(math.radians(30.0))
        wait_for(lambda: abs(math.degrees(m.velocity_rad_s()) - 30.0) < 0.1)
        node.tpdo_latency_s = 0.015
        t0 = m.clock() + 0.1
        wait_for(lambda: len(m.samples_since(t0)) >= 40)
        # samples first, then the histories: a sample read after them could answer a SYNC they do not hold
        # yet (the SYNCs go on at 100 Hz); a SYNC is in both histories before its answer is sampled
        samples = m.samples_since(t0)
        sent = list(m.sync_history)
        latched = [p for _, p in node.sync_log]
        assert len(sent) < 4096 and len(latched) < 2000  # nothing dropped from either history
        index = {t: i for i, t in enumerate(sent)}
        for s in samples:
            i = index[s.t_host_s]  # every stamp is the send time of one of our SYNCs
            assert FAST.rad_to_counts(s.position_rad) == latched[i]
        # and they are consecutive SYNCs: none skipped, none used twice
        ids = [index[s.t_host_s] for s in samples]
        assert ids == list(range(ids[0], ids[0] + len(ids)))
        m.stop()


def test_lost_tpdo_answers_are_detected_and_pairing_recovers() -> None:
    with open_device("motor", "sim://?node=9&sync_hz=100") as m:
        assert isinstance(m, Cia402CanMotor)
        node = m.sim_node
        m.enable()
        m.jog(math.radians(30.0))
        wait_for(lambda: abs(math.degrees(m.velocity_rad_s()) - 30.0) < 0.1)
        m.pairing_window_s = 1.0  # (5 s by default)
        node.drop_tpdos = 1  # one SYNC goes unanswered while the drive stays Operational
        wait_for(lambda: m.resyncs >= 1)
        t0 = m.clock() + 0.05
        wait_for(lambda: len(m.samples_since(t0)) >= 20)
        samples = m.samples_since(t0)  # before the histories, as in the test above
        index = {t: i for i, t in enumerate(m.sync_history)}
        latched = [p for _, p in node.sync_log]
        for s in samples:
            assert FAST.rad_to_counts(s.position_rad) == latched[index[s.t_host_s]]
        assert m.resyncs == 1
        m.stop()


def test_sdo_string_round_trips_of_every_length(motor: Cia402CanMotor) -> None:
    rng = np.random.default_rng(7)
    for n in [*range(0, 23), 48, 127, 255]:
        text = bytes(rng.integers(32, 127, n, dtype=np.uint8))
        for force_segment in (False, True):
            motor.sdo_download(cia402.USER_NOTE, 0, text, force_segment=force_segment)
            assert motor.sdo_upload(cia402.USER_NOTE) == text, (n, force_segment)
    with pytest.raises(SdoAbort) as info:
        motor.sdo_download(cia402.USER_NOTE, 0, b"x" * 256)
    assert info.value.code == cia402.ABORT_LENGTH_TOO_HIGH


def test_quick_stop_that_holds_then_disable(motor: Cia402CanMotor) -> None:
    # quick-stop option 6: stay in Quick stop active after the ramp; disable leaves it
    motor.sdo_download(cia402.QUICK_STOP_OPTION, 0, (6).to_bytes(2, "little", signed=True))
    motor.enable()
    motor.jog(math.radians(15.0))
    wait_for(lambda: motor.velocity_rad_s() > math.radians(14.0))
    motor.quick_stop()
    wait_for(lambda: motor.state is State.QUICK_STOP_ACTIVE and abs(motor.velocity_rad_s()) < 1e-3)
    motor.disable()
    assert motor.state is State.SWITCH_ON_DISABLED
    motor.enable()  # and back from there
    assert motor.state is State.OPERATION_ENABLED
