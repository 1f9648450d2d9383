"""Replay the client side of the recorded LMS111 session (SICK's driver starting up) against the simulator.

The recording (tests/data/sick-recordings/20210302_lms111, see its README) holds both directions of a
sick_scan start-up against a real LMS111 in CoLa B. Every request in it is sent to the simulated LMS100
over real TCP, one at a time (CoLa B: the recorded bytes as they are; CoLa A: the same request
re-encoded), and the simulator's answers are compared with the device's: same command type (sRA / sAN /
sWA / sEA / sFA), same name, same CoLa B payload length, and the same bytes unless listed in
``VALUES_DIFFER``. The events (``sSN``) the device sent during the session are compared by kind, name
and length.

The simulated device is set up as the recorded one was: 50 Hz / 0.5 deg, the output range an earlier
driver run had left (-449997..2249997, which its first read shows), location name "not defined" and
the recorded unit's 30 field definitions (decoded from the recording). The recording shows a few
telegrams twice (capture retransmissions, README); a copy of a reply to the same or the previous request
is not expected twice.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import pytest

from drivers.lms100 import (
    DeviceReady,
    Dialect,
    FieldDefinition,
    Message,
    ReadDeviceReady,
    Run,
    RunReply,
    ScanDataEvent,
    SetAccessMode,
    SetAccessModeReply,
    SetScanConfig,
    SetScanConfigReply,
    WriteOutputRange,
    WriteOutputRangeReply,
    decode_payload,
    frame,
)
from drivers.lms100.messages import REQUEST_KINDS
from sim.scanner import ScannerServer, SimulatedLMS100
from tests.lms100.recordings import LMS111, session
from tests.sim.conftest import Link

Connect = Callable[..., Link]

#: Recorded requests that cannot apply to the simulator, with the reason. None so far: every request
#: of the recorded start-up is replayed and checked.
NOT_REPLAYED: dict[tuple[str, str], str] = {}

#: Answers whose kind, name and length must match but whose values are the recorded unit's own.
VALUES_DIFFER: dict[tuple[str, str], str] = {
    ("sRA", "ODoprh"): "operating hours of the recorded unit (1110 h) vs the simulated clock's",
    ("sRA", "ODpwrc"): "power-on count of the recorded unit (63) vs the simulator's",
}

#: Request kinds (command type + name) in the recorded start-up.
RECORDED_REQUEST_KINDS = 48


@dataclass
class Exchange:
    request: Message
    request_frame: bytes
    replies: list[Message]
    reply_lengths: list[int]
    reply_payloads: list[bytes]


def _recorded_exchanges() -> tuple[list[Exchange], list[tuple[str, str, int]]]:
    """Each recorded request with the (deduplicated) replies before the next request; the events."""
    exchanges: list[Exchange] = []
    events: list[tuple[str, str, int]] = []
    for t in session(LMS111):
        msg = decode_payload(t.payload, Dialect.B)
        if msg.kind in REQUEST_KINDS:
            exchanges.append(Exchange(msg, t.frame, [], [], []))
        elif msg.kind == "sSN":
            events.append((msg.kind, msg.name, len(t.payload)))
        elif not any(t.payload in ex.reply_payloads for ex in exchanges[-2:]):  # not a retransmitted copy
            ex = exchanges[-1]
            ex.replies.append(msg)
            ex.reply_lengths.append(len(t.payload))
            ex.reply_payloads.append(t.payload)
    return exchanges, events


def _recorded_device() -> SimulatedLMS100:
    exchanges, _ = _recorded_exchanges()
    fields = [r for ex in exchanges for r in ex.replies if isinstance(r, FieldDefinition)]
    assert [f.index for f in fields] == list(range(30))
    return SimulatedLMS100("seed003", realtime=False, location_name="not defined", fields=[f.geometry for f in fields])


def _configure_like_the_recorded_unit(server: ScannerServer, connect: Connect) -> None:
    setup = connect(server.address, server.dialect.value)
    assert setup.request(SetAccessMode()) == SetAccessModeReply(True)
    reply = setup.request(SetScanConfig.from_hz_deg(50, 0.5))
    assert isinstance(reply, SetScanConfigReply) and reply.ok
    # the recorded unit's first read shows the range an earlier run of the driver had written
    assert setup.request(WriteOutputRange(1, 5000, -449997, 2249997)) == WriteOutputRangeReply()
    assert setup.request(Run()) == RunReply(True)
    setup.close()


def test_recording_shape() -> None:
    exchanges, events = _recorded_exchanges()
    assert len(exchanges) == 49  # LMPoutputRange is read twice
    assert len({(ex.request.kind, ex.request.name) for ex in exchanges}) == RECORDED_REQUEST_KINDS
    assert all(len(ex.replies) == 1 for ex in exchanges)  # one answer per request, none an sFA
    assert {(k, n) for k, n, _ in events} == {("sSN", "LMDscandata"), ("sSN", "LIDoutputstate")}


@pytest.mark.parametrize("dialect", ["b", "a"])
def test_replay_lms111_startup(connect: Connect, dialect: str) -> None:
    exchanges, recorded_events = _recorded_exchanges()
    with ScannerServer(_recorded_device(), dialect=dialect) as server:
        _configure_like_the_recorded_unit(server, connect)
        link = connect(server.address, dialect)
        checked: set[tuple[str, str]] = set()
        for ex in exchanges:
            key = (ex.request.kind, ex.request.name)
            if key in NOT_REPLAYED:
                continue
            wire = ex.request_frame if dialect == "b" else frame(ex.request.encode(Dialect.A), Dialect.A)
            link.send_raw(wire)
            got = [link.reply() for _ in ex.replies]
            for want, want_len, want_payload, have in zip(
                ex.replies, ex.reply_lengths, ex.reply_payloads, got, strict=True
            ):
                where = f"{ex.request.kind} {ex.request.name} -> {want.kind} {want.name}"
                assert (have.kind, have.name) == (want.kind, want.name), f"{where}: got {have!r}"
                have_b = have.encode(Dialect.B)
                assert len(have_b) == want_len, f"{where}: payload {len(have_b)} bytes, recorded {want_len}"
                if (want.kind, want.name) not in VALUES_DIFFER:
                    assert have_b == want_payload, f"{where}: got {have!r}, recorded {want!r}"
            checked.add(key)
        # nothing else was answered: the next reply is the answer to one more request
        assert link.request(ReadDeviceReady()) == DeviceReady(1)
        # the events the LMS111 sent in that session: scans and one output state, same kinds and lengths
        # (the simulator sends the output state right after its subscription: it is already here)
        want_events = set(recorded_events)
        have_events = {("sSN", "LMDscandata", len(ScanDataEvent(s).encode(Dialect.B))) for s in link.scans(3)}
        have_events |= {(e.kind, e.name, len(e.encode(Dialect.B))) for e in link.other_events}
        assert have_events == want_events
    assert len(checked) == RECORDED_REQUEST_KINDS - len(NOT_REPLAYED)
