"""An independent CiA 402 master, the ``canopen`` library's ``BaseNode402``, drives our simulated
drive over a python-can ``virtual`` bus: PDO configuration upload, state machine walk through its
RPDO/TPDO, a profile-position move, EMCY, fault reset and homing."""

from __future__ import annotations

import time
from collections.abc import Iterator

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from drivers.servo import cia402
from drivers.servo.cia402 import State
from drivers.servo.cia402_can import canopen_object_dictionary
from sim.drive.can_node import SimCanNode

NODE = 4


@pytest.fixture
def peer() -> Iterator[tuple[BaseNode402, SimCanNode, canopen.Network]]:
    channel = f"lrms-peer-402-{time.monotonic_ns()}"
    node = SimCanNode(can.Bus(interface="virtual", channel=channel), node_id=NODE).start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    master = BaseNode402(NODE, canopen_object_dictionary())
    # the library's timeouts (0.2 - 0.8 s) are tight for a shared 2-core test machine (they are deadlines for
    # answers that must come; none of these tests waits one out)
    master.TIMEOUT_CHECK_TPDO = 5.0
    master.TIMEOUT_SWITCH_STATE_SINGLE = 5.0
    master.TIMEOUT_SWITCH_STATE_FINAL = 10.0
    master.TIMEOUT_SWITCH_OP_MODE = 5.0
    network.add_node(master)
    try:
        yield master, node, network
    finally:
        network.sync.stop()
        network.disconnect()
        node.stop()
        node.bus.shutdown()


def wait_statusword(master: BaseNode402, bits: int, timeout: float = 10.0) -> int:
    deadline = time.monotonic() + timeout
    while True:
        sw = int(master.check_statusword(timeout=5.0))
        if sw & bits == bits:
            return sw
        if time.monotonic() > deadline:
            raise AssertionError(f"statusword 0x{sw:04X} never had bits 0x{bits:04X}")


def test_basenode402_walks_state_machine_and_moves(peer: tuple[BaseNode402, SimCanNode, canopen.Network]) -> None:
    master, node, network = peer
    master.nmt.state = "PRE-OPERATIONAL"
    master.sdo[0x1017].raw = 20
    master.nmt.wait_for_heartbeat(timeout=10.0)
    master.setup_402_state_machine()  # reads our PDO configuration by SDO
    assert 0x6041 in master.tpdo_values and 0x6040 in master.rpdo_pointers
    assert master.sdo[0x1000].raw & 0xFFFF == 402
    assert master.sdo[0x1008].raw == "LRMS simulated CiA 402 drive"  # segmented upload
    master.nmt.state = "OPERATIONAL"
    network.sync.start(0.01)

    master.state = "OPERATION ENABLED"  # controlword by RPDO1, statusword from TPDO1
    assert master.state == "OPERATION ENABLED"
    assert node.drive.state is State.OPERATION_ENABLED

    master.op_mode = "PROFILED POSITION"
    assert master.sdo[0x6061].raw == 1  # op_mode only logs failures: read it back

    master.sdo[0x6081].raw = 200_000
    master.sdo[0x6083].raw = 2_000_000
    master.sdo[0x6084].raw = 2_000_000
    master.sdo[0x607A].raw = 30_000
    master.controlword = 0x003F  # enable operation + new set-point + change immediately
    wait_statusword(master, cia402.SW_SET_POINT_ACK)
    master.controlword = 0x000F
    sw = wait_statusword(master, cia402.SW_TARGET_REACHED | 0x0027)
    assert cia402.decode_state(sw) is State.OPERATION_ENABLED
    assert master.tpdo_values[0x6064] == pytest.approx(30_000, abs=20)  # position from the same TPDO
    # target reached means inside the position window (for its time); the servo loop then settles on the
    # target itself as the drive's clock runs on (how far it got by the time of this read depends on how
    # busy the machine is): wait for the drive to be exactly there
    deadline = time.monotonic() + 10.0
    while (position := node.drive.read(cia402.POSITION_ACTUAL)) != 30_000:
        assert time.monotonic() < deadline, f"the drive settled at {position}, not 30000"
        time.sleep(0.01)

    # a fault the master sees as EMCY and statusword, and clears with its own reset
    node.drive.inject_fault("over_current")
    emcy = master.emcy.wait(0x2310, timeout=10.0)
    assert emcy is not None and emcy.code == 0x2310 and emcy.register == 0x03
    deadline = time.monotonic() + 10.0
    while master.state != "FAULT":
        master.check_statusword(timeout=5.0)
        assert time.monotonic() < deadline
    master.controlword = 0x0000
    master.check_statusword(timeout=5.0)
    master.controlword = 0x0080  # rising edge of bit 7
    master.check_statusword(timeout=5.0)
    master.state = "OPERATION ENABLED"
    assert node.drive.state is State.OPERATION_ENABLED

    # homing, the library's own way (method 37: here is home)
    master.sdo[0x6098].raw = 37
    assert master.homing(timeout=10.0) is True
    assert node.drive.read(cia402.POSITION_ACTUAL) == 0


def test_basenode402_rejects_unsupported_mode(peer: tuple[BaseNode402, SimCanNode, canopen.Network]) -> None:
    master, _node, _network = peer
    master.nmt.state = "PRE-OPERATIONAL"
    master.setup_402_state_machine()
    with pytest.raises(TypeError):
        master.op_mode = "CYCLIC SYNCHRONOUS POSITION"  # bit 7 of 0x6502 is clear
    with pytest.raises(canopen.SdoAbortedError) as info:
        master.sdo[0x6060].raw = 8  # and the drive refuses it directly too
    assert info.value.code == cia402.ABORT_INVALID_VALUE
