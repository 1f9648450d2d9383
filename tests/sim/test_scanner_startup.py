"""What SICK's driver (sick_scan_xd, LMS1xx) reads at start-up, answered by the simulator over real TCP.

Expected values follow the LMS111 recording (tests/data/sick-recordings/, see docs/simulator.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from drivers.lms100 import (
    DeviceReady,
    ErrorReply,
    FieldDefinition,
    FieldGeometry,
    InputState,
    InputStateEvent,
    OutputRange,
    OutputStateEvent,
    PollScan,
    RawTelegram,
    ReadDeviceReady,
    ReadFieldDefinition,
    ReadInputState,
    ReadOutputRange,
    Run,
    RunReply,
    ScanDataReply,
    SetAccessMode,
    SetAccessModeReply,
    SetScanConfig,
    SetScanConfigReply,
    SubscribeInputState,
    SubscribeInputStateReply,
    SubscribeOutputState,
    SubscribeOutputStateReply,
    WriteOutputRange,
    WriteOutputRangeReply,
    WriteScanDataConfig,
    WriteScanDataConfigReply,
    frame,
)
from drivers.lms100.framing import Dialect
from sim.scanner import ScannerServer, SimulatedLMS100, SimulatorError
from tests.sim.conftest import Link

Connect = Callable[..., Link]
DIALECTS = ["a", "b"]


@pytest.fixture(params=DIALECTS)
def server(request: pytest.FixtureRequest) -> Iterator[ScannerServer]:
    with ScannerServer(SimulatedLMS100("seed003", realtime=False), dialect=request.param) as srv:
        yield srv


def _login(link: Link) -> None:
    assert link.request(SetAccessMode()) == SetAccessModeReply(True)


def test_field_definitions_input_state_and_ready_state(server: ScannerServer, connect: Connect) -> None:
    link = connect(server.address, server.dialect.value)
    assert link.request(ReadDeviceReady()) == DeviceReady(1)
    _login(link)
    assert link.request(ReadDeviceReady()) == DeviceReady(0)  # 0 while logged in, as the LMS111 answers
    other = connect(server.address, server.dialect.value)
    assert other.request(ReadDeviceReady()) == DeviceReady(0)  # the device is in configuration mode
    fields = [link.request(ReadFieldDefinition(i)) for i in range(30)]
    assert fields == [FieldDefinition(i, FieldGeometry()) for i in range(10)] + [
        FieldDefinition(i, None) for i in range(10, 30)
    ]
    assert link.request(ReadFieldDefinition(30)) == ErrorReply(3)  # an LMS1xx has 30
    assert link.request(ReadInputState()) == InputState(1, 0, (2, 2, 2, 2))
    assert link.request(Run()) == RunReply(True)
    assert link.request(ReadDeviceReady()) == DeviceReady(1)


def test_field000_is_the_recorded_32_byte_answer_in_cola_b() -> None:
    # the LMS111's unconfigured field (recording entry 27), produced by the device's default field table
    with ScannerServer(SimulatedLMS100("seed003", realtime=False), dialect="b") as srv:
        link = Link(srv.address, "b")
        try:
            link.sock.sendall(frame(b"sRN field003", Dialect.B))
            data = b""
            while len(data) < 54:
                data += link.sock.recv(4096)
        finally:
            link.close()
    assert data.hex().upper() == (
        "020202020000002D735241206669656C64303033203F8000000000000000001388FFF922300200000000000000000000010000000002"
    )


def test_output_state_at_subscription_and_on_change(server: ScannerServer, connect: Connect) -> None:
    dev = server.device
    link = connect(server.address, server.dialect.value)
    quiet = connect(server.address, server.dialect.value)  # never subscribes: gets no I/O event
    assert link.request(SubscribeOutputState(True)) == SubscribeOutputStateReply(True)
    first = link.event()
    assert isinstance(first, OutputStateEvent) and first.version == 1
    assert first.outputs == ((0, 0),) * 3 + ((2, 0),) * 8 and first.time is None  # time block follows LMDscandatacfg
    dev.set_outputs([False, True, False])
    change = link.event()
    assert isinstance(change, OutputStateEvent)
    assert change.outputs[:3] == ((0, 0), (1, 1), (0, 0)) and change.system_counter >= first.system_counter
    dev.set_outputs([False, True, False])  # no change, no event
    dev.set_outputs([False, False, False])
    off = link.event()
    assert isinstance(off, OutputStateEvent) and off.outputs[:3] == ((0, 0), (0, 1), (0, 0))
    # with the time block on in LMDscandatacfg, the events carry it (as the LMS111's, 74 bytes in CoLa B)
    _login(link)
    assert link.request(WriteScanDataConfig(time=True)) == WriteScanDataConfigReply()
    assert link.request(Run()) == RunReply(True)
    dev.set_outputs([True, True, True])
    timed = link.event()
    assert isinstance(timed, OutputStateEvent) and timed.time is not None and timed.time.year == 1970
    assert [s for s, _ in timed.outputs] == [1, 1, 1] + [2] * 8
    assert len(timed.encode(Dialect.B)) == len("sSN LIDoutputstate ") + 74
    assert quiet.request(PollScan()) is not None and quiet.other_events == []
    poll = quiet.request(PollScan())
    assert isinstance(poll, ScanDataReply) and poll.scan.digital_outputs == (0b111, 0)
    assert link.request(SubscribeOutputState(False)) == SubscribeOutputStateReply(False)
    dev.set_outputs([False, False, False])
    assert link.request(ReadDeviceReady()) == DeviceReady(1) and link.other_events == []


def test_input_state_event_only_on_change(server: ScannerServer, connect: Connect) -> None:
    link = connect(server.address, server.dialect.value)
    assert link.request(SubscribeInputState(True)) == SubscribeInputStateReply(True)
    assert link.request(ReadInputState()) == InputState(1, 0, (2, 2, 2, 2))  # no event at subscription
    assert link.other_events == []
    server.device.set_inputs([1, 0, 0, 0])
    ev = link.event()
    assert isinstance(ev, InputStateEvent) and ev.inputs == (1, 0, 0, 0)
    got = link.request(ReadInputState())
    assert isinstance(got, InputState) and got.inputs == (1, 0, 0, 0) and got.system_counter == ev.system_counter
    with pytest.raises(SimulatorError, match="4 values"):
        server.device.set_inputs([1, 2])
    with pytest.raises(SimulatorError, match="3 switching outputs"):
        server.device.set_outputs([True])
    with pytest.raises(SimulatorError, match="FieldGeometry or None"):
        SimulatedLMS100("seed003", realtime=False, fields=["field"])  # type: ignore[list-item]


@pytest.mark.parametrize(
    ("hz", "res", "start", "stop", "n", "first"),
    [
        (50, 5000, -449997, 2249997, 541, -450000),  # what sick_scan_xd writes; the LMS111 sends 541 from -45 deg
        (25, 2500, -449997, 2249997, 1081, -450000),
        (50, 5000, -447500, 2247500, 541, -450000),  # exactly half a step: the outer beam
        (50, 5000, -447499, 2247499, 539, -445000),  # past half a step: the inner one
        (25, 2500, 0, 900000, 361, 0),  # on the grid: as written
    ],
)
def test_output_range_goes_to_the_nearest_beam(
    connect: Connect, hz: int, res: int, start: int, stop: int, n: int, first: int
) -> None:
    for dialect in DIALECTS:
        with ScannerServer(SimulatedLMS100("seed003", realtime=False), dialect=dialect) as srv:
            link = connect(srv.address, dialect)
            _login(link)
            reply = link.request(SetScanConfig.from_hz_deg(hz, res / 1e4))
            assert isinstance(reply, SetScanConfigReply) and reply.ok
            assert link.request(WriteOutputRange(1, res, start, stop)) == WriteOutputRangeReply()
            assert link.request(ReadOutputRange()) == OutputRange(1, res, start, stop)  # kept as written
            assert link.request(Run()) == RunReply(True)
            scan = link.request(PollScan())
            assert isinstance(scan, ScanDataReply)
            s = scan.scan
            assert s.ranges_m.shape == (n,) and s.channels_16[0].start_angle_raw == first
            assert s.channels_16[0].step_raw == res
            assert np.rad2deg(s.angles_rad[-1]) == pytest.approx((first + (n - 1) * res) / 1e4)


def test_every_rejected_request_is_logged(
    server: ScannerServer, connect: Connect, caplog: pytest.LogCaptureFixture
) -> None:
    link = connect(server.address, server.dialect.value)
    caplog.set_level(logging.WARNING, logger="sim.scanner.device")
    assert link.request(RawTelegram("sRN", "LFPmeanfilter")) == ErrorReply(3)
    assert link.request(WriteOutputRange(1, 2500, -449997, 2249997)) == ErrorReply(0x0A)  # not logged in
    assert link.request(SetAccessMode(3, 0x12345678)) == SetAccessModeReply(False)
    _login(link)
    assert link.request(WriteOutputRange(1, 5000, -449997, 2249997)) == ErrorReply(4)  # scan runs at 0.25 deg
    assert link.request(RawTelegram("sEN", "InertialMeasurementUnit", b"1" if server.dialect.value == "a" else b"\x01"))
    link.send_raw(frame(b"sWN LMPoutputRange 1", server.dialect))  # parameters missing
    assert link.reply() == ErrorReply(8)
    messages = [r.getMessage() for r in caplog.records if r.name == "sim.scanner.device"]
    assert len(messages) == 6, messages
    expect = [
        ("LFPmeanfilter", "is not simulated", "sFA error 0x03"),
        ("WriteOutputRange", "needs access level 3", "sFA error 0x0A"),
        ("SetAccessMode", "wrong access level or password", "SetAccessModeReply(success=False)"),
        ("WriteOutputRange", "differs from the scan's 2500", "sFA error 0x04"),
        ("InertialMeasurementUnit", "event 'InertialMeasurementUnit' is not simulated", "sFA error 0x0F"),
        ("sWN LMPoutputRange 1", "cannot decode it", "sFA error 0x08"),
    ]
    for msg, (telegram, reason, answer) in zip(messages, expect, strict=True):
        assert msg.startswith("simulated LMS100 rejected") and telegram in msg and reason in msg and answer in msg
    # the refused password hash is a secret: in no log line, in hex or decimal
    assert not any(s in m.upper() for m in messages for s in ("12345678", str(0x12345678))), messages
