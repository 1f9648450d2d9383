"""The simulated node's SDO server frame by frame (a hand-written client on a python-can ``virtual``
bus): expedited and segmented transfers, toggle errors, size mismatches, unsupported block transfer."""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator

import can
import pytest

from drivers.servo import cia402
from sim.drive.can_node import SimCanNode

NODE = 6


class Client:
    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def request(self, data: bytes) -> bytes:
        self.bus.send(can.Message(arbitration_id=0x600 + NODE, data=data.ljust(8, b"\x00"), is_extended_id=False))
        deadline = time.monotonic() + 10.0  # against a hang: an answer must come
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(remaining)
            if msg is not None and msg.arbitration_id == 0x580 + NODE:
                return bytes(msg.data)
        raise AssertionError("no SDO response")


def abort_code(reply: bytes) -> int:
    assert reply[0] == 0x80, reply.hex()
    code: int = struct.unpack_from("<I", reply, 4)[0]
    return code


@pytest.fixture
def client() -> Iterator[tuple[Client, SimCanNode]]:
    channel = f"lrms-sdo-raw-{time.monotonic_ns()}"
    node = SimCanNode(can.Bus(interface="virtual", channel=channel), node_id=NODE).start()
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        yield Client(bus), node
    finally:
        bus.shutdown()
        node.stop()
        node.bus.shutdown()


def test_expedited_read_and_write_frames(client: tuple[Client, SimCanNode]) -> None:
    c, node = client
    # the reference example: write 0x1017 = 50 -> 2B 17 10 00 32 00 00 00, reply 60 17 10 00
    assert c.request(bytes.fromhex("2B17100032000000"))[:4] == bytes.fromhex("60171000")
    assert node.drive.raw(cia402.PRODUCER_HEARTBEAT_TIME) == 50
    reply = c.request(bytes.fromhex("4041600000000000"))  # read statusword: 2 bytes -> 0x4B
    assert reply[:4] == bytes.fromhex("4B416000") and struct.unpack_from("<H", reply, 4)[0] == 0x0240
    reply = c.request(bytes.fromhex("4064600000000000"))  # position: 4 bytes -> 0x43
    assert reply[0] == 0x43
    # size not indicated (0x22): four bytes, zero padded, accepted for a u16
    assert c.request(bytes.fromhex("2240600006000000"))[0] == 0x60
    assert node.drive.read(cia402.CONTROLWORD) == 0x0006


def test_segmented_upload_with_toggle(client: tuple[Client, SimCanNode]) -> None:
    c, _ = client
    reply = c.request(bytes.fromhex("4008100000000000"))
    assert reply[0] == 0x41
    size = struct.unpack_from("<I", reply, 4)[0]
    data, toggle = b"", 0
    while True:
        seg = c.request(bytes([0x60 | (toggle << 4)]))
        assert (seg[0] >> 4) & 1 == toggle
        unused = (seg[0] >> 1) & 7
        data += seg[1 : 8 - unused]
        if seg[0] & 1:
            break
        toggle ^= 1
    assert len(data) == size and data == b"LRMS simulated CiA 402 drive"


def test_segmented_upload_toggle_error_aborts(client: tuple[Client, SimCanNode]) -> None:
    c, _ = client
    assert c.request(bytes.fromhex("4008100000000000"))[0] == 0x41
    assert c.request(bytes([0x60]))[0] & 0xE0 == 0x00  # first segment, toggle 0
    assert abort_code(c.request(bytes([0x60]))) == cia402.ABORT_TOGGLE  # toggle not alternated
    assert abort_code(c.request(bytes([0x70]))) == cia402.ABORT_COMMAND  # the transfer is gone


def test_segmented_download_and_size_mismatch(client: tuple[Client, SimCanNode]) -> None:
    c, node = client
    text = b"0123456789"
    assert c.request(bytes([0x21]) + struct.pack("<HBI", cia402.USER_NOTE, 0, len(text)))[0] == 0x60
    assert c.request(bytes([0x00]) + text[:7])[0] == 0x20
    assert c.request(bytes([0x10 | ((7 - 3) << 1) | 1]) + text[7:])[0] == 0x30
    assert node.drive.read_bytes(cia402.USER_NOTE) == text
    # announced 12 bytes, sent 10
    assert c.request(bytes([0x21]) + struct.pack("<HBI", cia402.USER_NOTE, 0, 12))[0] == 0x60
    assert c.request(bytes([0x00]) + text[:7])[0] == 0x20
    assert abort_code(c.request(bytes([0x10 | (4 << 1) | 1]) + text[7:])) == cia402.ABORT_LENGTH_TOO_LOW
    assert node.drive.read_bytes(cia402.USER_NOTE) == text  # unchanged


def test_segmented_download_to_missing_object_aborts_at_once(client: tuple[Client, SimCanNode]) -> None:
    c, _ = client
    assert abort_code(c.request(bytes([0x21]) + struct.pack("<HBI", 0x2FFF, 0, 9))) == cia402.ABORT_NO_OBJECT
    assert abort_code(c.request(bytes([0x00]) + b"abcdefg")) == cia402.ABORT_COMMAND  # no transfer open


def test_block_transfer_and_unknown_commands_abort(client: tuple[Client, SimCanNode]) -> None:
    c, _ = client
    block_download = bytes([0xC2]) + struct.pack("<HBI", cia402.USER_NOTE, 0, 20)
    assert abort_code(c.request(block_download)) == cia402.ABORT_COMMAND
    block_upload = bytes([0xA0]) + struct.pack("<HB", cia402.DEVICE_NAME, 0) + bytes([127])
    assert abort_code(c.request(block_upload)) == cia402.ABORT_COMMAND
    reply = c.request(bytes([0xE0]))
    assert abort_code(reply) == cia402.ABORT_COMMAND
