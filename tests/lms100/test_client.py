"""The LMS100 TCP client against the simulated LMS100 (sim.scanner) over real TCP on 127.0.0.1.

Every command in both dialects, poll and stream, sFA errors, refused configurations, request
timeouts against a dead peer, a connection killed mid-stream (reconnect, session restore, the
gap in the scan counter), a stalled stream, queue overflow, and device URLs.
"""

from __future__ import annotations

import itertools
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, DeviceURLError
from drivers.lms100 import (
    CoLaConnection,
    DeviceErrorReply,
    DeviceState,
    OperatingHours,
    OutputRange,
    RawTelegram,
    ReadDeviceState,
    ReadOperatingHours,
    ReadOutputRange,
    Reboot,
    RebootReply,
    Scan,
    ScanDataEvent,
)
from drivers.lms100.client import (
    Backoff,
    LoginError,
    ScanConfigError,
    ScannerClient,
    ScannerStateError,
    open_url,
)
from drivers.url import DeviceURL, open_device
from sim.scanner import ScannerServer, SimulatedLMS100
from sim.scanner.device import DeviceClock

FAST = Backoff(initial_s=0.05, factor=2.0, max_s=0.2)

ServerFactory = Callable[..., ScannerServer]


@pytest.fixture
def make_server() -> Iterator[ServerFactory]:
    servers: list[ScannerServer] = []

    def make(dialect: str = "b", realtime: bool = False, scene: str = "wall", **device_kw: object) -> ScannerServer:
        device = SimulatedLMS100(scene, realtime=realtime, **device_kw)  # type: ignore[arg-type]
        server = ScannerServer(device, dialect=dialect).start()
        servers.append(server)
        return server

    yield make
    for s in servers:
        s.stop()


@pytest.fixture
def clients() -> Iterator[list[ScannerClient]]:
    made: list[ScannerClient] = []
    yield made
    for c in made:
        c.close()


def connect(server: ScannerServer, clients: list[ScannerClient], **kw: object) -> ScannerClient:
    host, port = server.address
    # a generous request timeout: it bounds answers that must come (a loaded CI machine is slow), no test waits it out
    opts: dict[str, object] = {"timeout_s": 10.0, "backoff": FAST}
    opts.update(kw)
    c = ScannerClient(host, port, server.dialect, **opts)  # type: ignore[arg-type]
    clients.append(c)
    return c.connect()


def wait_for(condition: Callable[[], bool], limit_s: float = 10.0) -> None:
    """Wait for a condition driven by other threads (a deadline against hangs, not a timing check)."""
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail("condition not reached")
        time.sleep(0.01)


def close_and_drain(c: ScannerClient) -> list[Scan]:
    """Close the client (its reader thread ends, so the stats are final) and take what was queued."""
    c.close()
    rest = []
    while True:
        try:
            rest.append(c.next_scan(0.0))
        except ScannerStateError:
            return rest


def lost_from_counters(scans: list[Scan]) -> int:
    counters = [s.scan_counter for s in scans]
    return sum((b - a) % 65536 - 1 for a, b in itertools.pairwise(counters))


def gaps_from_counters(scans: list[Scan]) -> int:
    return sum((b - a) % 65536 > 1 for a, b in itertools.pairwise(s.scan_counter for s in scans))


def take_queued(c: ScannerClient) -> list[Scan]:
    """The scans already in the client's queue (the client stays open and streaming)."""
    out = []
    while True:
        try:
            out.append(c.next_scan(0.0))
        except DeviceTimeoutError:
            return out


# -- commands ------------------------------------------------------------------------------------


@pytest.mark.parametrize("dialect", ["a", "b"])
def test_identity_state_and_configuration_reads(
    make_server: ServerFactory, clients: list[ScannerClient], dialect: str
) -> None:
    # the device clock has run 1234.5 h (virtual, so it stands still while the test runs)
    server = make_server(dialect, clock=DeviceClock(realtime=False, start_us=12_345 * 360_000_000 + 7))
    c = connect(server, clients)
    ident = c.device_ident()
    assert (ident.device_name, ident.version) == ("LMS10x_FieldEval", "V1.36-21.10.2010")
    assert c.serial_number() == "19060042"
    assert c.firmware_version() == "V1.80.2"  # trailing blanks of the device string removed
    state = c.device_state()
    assert state.status == 7 and state.measuring and state.status_text == "measuring"
    assert c.device_ready() == 1
    cfg = c.scan_config()
    assert (cfg.scan_frequency_hz, cfg.angular_resolution_deg) == (25.0, 0.25)
    assert (cfg.start_angle_deg, cfg.stop_angle_deg) == (-45.0, 225.0)
    data_cfg = c.scan_data_config()
    assert data_cfg.output_rate == 1 and data_cfg.output_channel == (1, 0)
    # any other telegram through the generic request
    assert c.request(ReadOperatingHours(), OperatingHours).tenth_hours == 12_345
    assert c.request(ReadOutputRange(), OutputRange).start_angle == -450000
    assert c.stats.timeouts == 0 and c.stats.unexpected == 0


@pytest.mark.parametrize("dialect", ["a", "b"])
def test_login_configure_measure_run_and_poll(
    make_server: ServerFactory, clients: list[ScannerClient], dialect: str
) -> None:
    server = make_server(dialect)
    c = connect(server, clients)
    c.login()
    applied = c.set_scan_config(50.0, 0.5)
    assert applied.ok and applied.scan_frequency == 5000 and applied.angular_resolution == 5000
    c.set_scan_data_config(remission=True, resolution=1, time=True)
    got = c.scan_data_config()
    assert got.remission and got.resolution == 1 and got.time
    c.stop_measurement()
    assert not c.device_state().measuring
    c.start_measurement()
    c.run()
    assert c.wait_until_measuring(timeout_s=10.0).status == 7
    cfg = c.scan_config()
    assert (cfg.scan_frequency_hz, cfg.angular_resolution_deg) == (50.0, 0.5)
    scan = c.poll()
    assert scan.scan_frequency_hz == 50.0 and scan.angular_step_deg == 0.5 and scan.start_angle_deg == -45.0
    assert scan.ranges_m.shape == (541,) and scan.rssi is not None and scan.rssi.shape == (541,)
    assert scan.time_info is not None
    assert scan.serial_number == 19060042
    # the wall of the "wall" scene is 3 m ahead: the straight-ahead beam (90 deg) sees it
    ahead = int(np.argmin(np.abs(np.degrees(scan.angles_rad) - 90.0)))
    assert scan.ranges_m[ahead] == pytest.approx(3.0, abs=0.1)
    assert c.stats.received == 1


def test_a_deliberate_measurement_pause_is_not_counted_as_lost(
    make_server: ServerFactory, clients: list[ScannerClient]
) -> None:
    server = make_server("b", realtime=True)
    c = connect(server, clients)
    c.login()
    c.run()
    c.start_streaming()
    before = list(c.scans(count=3))
    c.login()  # Run ended the session's access level
    c.stop_measurement()
    time.sleep(0.3)  # the device's scan counter runs on while the laser is off
    # every scan sent before the stop (the stream ran on while login and stop were answered; a scan
    # already in flight at the stop lands well within the pause): the last of them is where the pause begins
    paused_at = before + take_queued(c)
    c.start_measurement()
    c.run()
    after = list(c.scans(count=3))
    resumed = after + close_and_drain(c)  # the stats are final once closed
    assert resumed[0].scan_counter - paused_at[-1].scan_counter > 1  # the counters do jump ...
    # ... but the pause is not counted as lost. Outside the pause the real-time simulator may skip a scan
    # when its thread runs late on a busy machine; such a loss is real and must be counted, the pause never.
    st = c.stats
    assert st.lost == lost_from_counters(paused_at) + lost_from_counters(resumed)
    assert st.gaps == gaps_from_counters(paused_at) + gaps_from_counters(resumed)
    assert st.received == len(paused_at) + len(resumed) and st.queue_drops == 0


@pytest.mark.parametrize("dialect", ["a", "b"])
def test_stream_delivers_consecutive_scans_and_unsubscribes(
    make_server: ServerFactory, clients: list[ScannerClient], dialect: str
) -> None:
    server = make_server(dialect)
    c = connect(server, clients)
    with pytest.raises(ScannerStateError, match="not streaming"):
        c.next_scan(0.1)
    c.start_streaming()
    assert c.streaming
    scans = list(c.scans(count=20))
    counters = [s.scan_counter for s in scans]
    assert counters == list(range(counters[0], counters[0] + 20))
    assert all(s.ranges_m.shape == (1081,) for s in scans)
    # records: host receive time and the telegram exactly as framed on the wire
    records = [c.next_record() for _ in range(3)]
    assert records[0].host_time_s <= records[1].host_time_s <= records[2].host_time_s <= time.monotonic()
    decoder = CoLaConnection(dialect, role="client")
    for r in records:
        assert r.raw is not None
        decoder.receive_data(r.raw)
        again = decoder.next_message()
        assert isinstance(again, ScanDataEvent) and again.scan.scan_counter == r.scan.scan_counter
        np.testing.assert_array_equal(again.scan.ranges_m, r.scan.ranges_m)
    assert records[0].scan.scan_counter == counters[-1] + 1
    c.stop_streaming()
    assert not c.streaming
    # drain what was queued before the unsubscription reached the device, then nothing more comes
    while True:
        try:
            c.next_scan(0.2)
        except ScannerStateError:
            break
    st = c.stats
    assert st.received >= 20 and st.lost == 0 and st.gaps == 0 and st.queue_drops == 0


def test_sfa_errors_are_raised_with_their_meaning(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    c = connect(make_server("a"), clients)
    with pytest.raises(DeviceErrorReply, match="METHODIN_ACCESSDENIED") as method:
        c.set_scan_config(50.0, 0.5)  # not logged in
    assert method.value.code == 0x01
    with pytest.raises(DeviceErrorReply, match="VARIABLE_WRITE_ACCESSDENIED") as write:
        c.set_scan_data_config(remission=True)
    assert write.value.code == 0x0A
    with pytest.raises(DeviceErrorReply, match="VARIABLE_UNKNOWNINDEX") as unknown:
        c.request(RawTelegram("sRN", "field030"), RawTelegram)
    assert unknown.value.code == 0x03
    assert "sRN field030" in str(unknown.value)
    # the link is still fine afterwards
    assert c.device_state().measuring


def test_refused_scan_configurations_raise_with_the_device_status(
    make_server: ServerFactory, clients: list[ScannerClient]
) -> None:
    c = connect(make_server("b"), clients)
    c.login()
    with pytest.raises(ScanConfigError, match=re.escape("50 Hz with 0.5 deg")) as res:
        c.set_scan_config(50.0, 0.25)  # 50 Hz needs 0.5 deg on an LMS1xx
    assert res.value.status == 2
    with pytest.raises(ScanConfigError) as freq:
        c.set_scan_config(35.0, 0.5)
    assert freq.value.status == 1
    with pytest.raises(ScanConfigError) as area:
        c.set_scan_config(25.0, 0.25, start_deg=-60.0)
    assert area.value.status == 4
    with pytest.raises(ScanConfigError, match="malformed"):
        c.set_scan_config(25.0, 0.25, start_deg=100.0, stop_deg=0.0)
    with pytest.raises(ScanConfigError, match="output_rate"):
        c.set_scan_data_config(output_rate=0)
    cfg = c.scan_config()  # nothing was applied
    assert (cfg.scan_frequency, cfg.angular_resolution) == (2500, 2500)


def test_login_refused(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    c = connect(make_server("b"), clients)
    with pytest.raises(LoginError, match="refused SetAccessMode level 3: wrong password hash") as refused:
        c.login(3, password_hash=0x12345678)
    assert "12345678" not in str(refused.value) and str(0x12345678) not in str(refused.value)  # a secret
    with pytest.raises(LoginError, match="does not fit 32 bits") as too_big:
        c.login(3, password_hash=0x1_2345_6789)
    assert "123456789" not in str(too_big.value)
    with pytest.raises(LoginError, match="unknown access level"):
        c.login(9)
    c.login(2)  # maintenance with its factory hash
    c.login()


# -- timeouts and broken peers -------------------------------------------------------------------


class ScriptedPeer:
    """A TCP peer on 127.0.0.1 that answers every received chunk with fixed bytes (or never)."""

    def __init__(self, answer: Callable[[bytes], bytes] | None) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.2)
        self.answer = answer
        self.received = bytearray()
        self.accepted = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    @property
    def port(self) -> int:
        return int(self.listener.getsockname()[1])

    def _serve(self) -> None:
        conns: list[socket.socket] = []
        while not self.stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            conns.append(conn)
            self.accepted += 1
            conn.settimeout(0.2)
            while not self.stop.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                if not data:
                    break
                self.received += data
                if self.answer is not None:
                    conn.sendall(self.answer(data))
        for conn in conns:
            conn.close()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2)
        self.listener.close()


def test_request_times_out_when_the_peer_never_answers(clients: list[ScannerClient]) -> None:
    peer = ScriptedPeer(answer=None)  # accepts and reads, never answers: a dead device
    try:
        c = ScannerClient("127.0.0.1", peer.port, "b", timeout_s=0.3, reconnect=False)
        clients.append(c)
        c.connect()
        with pytest.raises(DeviceTimeoutError, match=re.escape("did not answer sRN STlms within 0.3 s")):
            c.device_state()
        with pytest.raises(DeviceTimeoutError):
            c.poll()
        assert c.stats.timeouts == 2
        wait_for(lambda: len(peer.received) >= 2 * 17)
        assert bytes(peer.received).startswith(b"\x02\x02\x02\x02\x00\x00\x00\x09sRN STlms")
    finally:
        peer.close()


def test_with_reconnect_a_request_timeout_starts_a_fresh_connection(clients: list[ScannerClient]) -> None:
    # a late answer must never be taken for the answer to the next request: the link is renewed
    peer = ScriptedPeer(answer=None)
    try:
        c = ScannerClient("127.0.0.1", peer.port, "a", timeout_s=0.3, backoff=FAST)
        clients.append(c)
        c.connect()
        with pytest.raises(DeviceTimeoutError):
            c.serial_number()
        wait_for(lambda: c.stats.reconnects == 1)
        # the client's connect completes in the listener's backlog; the peer only counts the new link once
        # it has seen the old one close, so wait for its accept rather than read the counter at once
        wait_for(lambda: peer.accepted == 2)
        assert peer.accepted == 2
        st = c.stats
        assert (st.timeouts, st.connection_losses) == (1, 1)
    finally:
        peer.close()


def test_bad_telegrams_are_counted_and_skipped(clients: list[ScannerClient]) -> None:
    device = CoLaConnection("b", role="device")
    good = device.send(DeviceState(7, False, "00:00:01", "01.01.1970"))
    broken = bytearray(good)
    broken[-1] ^= 0xFF  # wrong checksum
    peer = ScriptedPeer(answer=lambda _req: b"garbage" + bytes(broken) + good)
    try:
        c = ScannerClient("127.0.0.1", peer.port, "b", timeout_s=10.0, reconnect=False)
        clients.append(c)
        c.connect()
        assert c.request(ReadDeviceState(), DeviceState).status == 7
        assert c.stats.bad_telegrams == 1
    finally:
        peer.close()


def test_connection_refused_raises_connection_error() -> None:
    s = socket.create_server(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(DeviceConnectionError, match="cannot connect"):
        ScannerClient("127.0.0.1", port, "a", timeout_s=1.0).connect()
    with pytest.raises(ScannerStateError, match="not connected"):
        ScannerClient("127.0.0.1", port, "a", timeout_s=1.0).device_state()


# -- reconnect, gaps, stalls, overflow -----------------------------------------------------------


@pytest.mark.parametrize("dialect", ["a", "b"])
def test_killed_connection_reconnects_and_the_gap_is_counted(
    make_server: ServerFactory, clients: list[ScannerClient], dialect: str
) -> None:
    # real-time device (25 Hz): it keeps scanning while the client is away
    server = make_server(dialect, realtime=True)
    c = connect(server, clients, backoff=Backoff(initial_s=0.15, max_s=0.5))
    c.login()
    c.set_scan_config(25.0, 0.25)
    c.set_scan_data_config(time=True)
    c.start_measurement()
    c.run()
    c.start_streaming()
    before = [c.next_scan() for _ in range(3)]
    epoch = server.device.epoch_start_us
    assert server.drop_clients() == 1
    after = [c.next_scan() for _ in range(5)]
    assert c.connected and c.streaming
    assert c.device_state().measuring
    # the device kept its scan configuration, so the restore did not send mLMPsetscancfg again
    # (that would restart the device's scan timing, and make a real LMS1xx busy for ~30 s)
    assert server.device.epoch_start_us == epoch
    assert all(s.time_info is not None for s in after)
    everything = before + after + close_and_drain(c)
    st = c.stats
    assert st.connection_losses == 1 and st.reconnects == 1
    # >= 0.15 s away at 25 Hz: at least three scans were made meanwhile and never received
    assert st.gaps >= 1 and st.lost >= 3
    assert st.lost == lost_from_counters(everything)  # every lost scan accounted for, none invented
    assert st.received == len(everything) and st.queue_drops == 0
    assert server.connections == 2


def test_device_reboot_restores_the_session(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    server = make_server("b", realtime=True)
    c = connect(server, clients, backoff=Backoff(initial_s=0.1, max_s=0.5))
    c.login()
    c.set_scan_config(50.0, 0.5)  # volatile, like the next line: a reboot forgets both
    c.set_scan_data_config(remission=True, resolution=1, time=True)
    c.start_measurement()
    c.run()
    c.start_streaming()
    first = [c.next_scan()]
    # the counter after the reboot restarts below this, unless reconnecting takes longer than 150
    # scans (3 s at 50 Hz): at 20 (0.4 s) a loaded machine once saw the new counter past the old one
    while first[-1].scan_counter < 150:
        first.append(c.next_scan())
    admin = connect(server, clients, reconnect=False)
    admin.login()
    admin.request(Reboot(), RebootReply)  # the device answers, then drops every connection and reboots
    wait_for(lambda: c.stats.reconnects >= 1)
    later = [c.next_scan() for _ in range(3)]
    everything = first + later + close_and_drain(c)
    resets = [i for i in range(1, len(everything)) if everything[i].scan_counter < everything[i - 1].scan_counter]
    assert len(resets) == 1
    rebooted = everything[resets[0] :]
    # the restore logged in and wrote both configurations again: 50 Hz, RSSI and time are back
    assert all(s.rssi is not None and s.time_info is not None and s.scan_frequency_hz == 50.0 for s in rebooted)
    st = c.stats
    assert st.device_restarts == 1  # the counter restart is not reported as lost scans
    assert st.lost == lost_from_counters(everything[: resets[0]]) + lost_from_counters(rebooted)


def test_without_reconnect_a_lost_link_is_an_error(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    server = make_server("b")
    c = connect(server, clients, reconnect=False)
    c.start_streaming()
    c.next_scan()
    server.drop_clients()
    with pytest.raises(DeviceConnectionError, match="reconnect is off"):
        while True:
            c.next_scan(10.0)
    with pytest.raises(DeviceConnectionError):
        c.device_state()
    assert c.stats.connection_losses == 1 and c.stats.reconnects == 0


def test_reconnect_gives_up_after_max_attempts(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    server = make_server("a")
    c = connect(server, clients, backoff=Backoff(initial_s=0.02, max_s=0.05, max_attempts=3))
    c.start_streaming()
    c.next_scan()
    server.stop()  # the device is gone for good: connections are refused
    with pytest.raises(DeviceConnectionError, match="gave up reconnecting after 3 attempt"):
        while True:
            c.next_scan(10.0)
    assert not c.connected


def test_a_stalled_stream_is_treated_as_a_dead_link(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    server = make_server("b", realtime=True)
    c = connect(server, clients, stall_timeout_s=0.3)
    c.start_streaming()
    c.next_scan()
    other = connect(server, clients, reconnect=False)
    other.login()
    other.stop_measurement()  # scans stop: the subscriber hears nothing any more
    wait_for(lambda: c.stats.reconnects >= 1)
    assert c.stats.connection_losses >= 1
    other.start_measurement()
    other.run()
    c.next_scan()  # the re-subscribed stream flows again


def test_queue_overflow_drops_oldest_and_counts(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    server = make_server("b")  # fast mode: scans as fast as the client reads them
    c = connect(server, clients, queue_size=3)
    c.start_streaming()
    wait_for(lambda: c.stats.queue_drops >= 5)
    kept = close_and_drain(c)
    st = c.stats
    assert st.received == st.queue_drops + len(kept)
    assert 1 <= len(kept) <= 3 and st.lost == 0
    # the queue kept the newest scans
    assert [s.scan_counter for s in kept] == list(range(kept[0].scan_counter, kept[0].scan_counter + len(kept)))


def test_closed_client_refuses_calls(make_server: ServerFactory) -> None:
    server = make_server("b")
    host, port = server.address
    with ScannerClient(host, port, "b", timeout_s=10.0) as c:
        c.start_streaming()
        c.next_scan()
    with pytest.raises(ScannerStateError, match="closed"):
        c.device_state()
    with pytest.raises(ScannerStateError, match="closed"):
        c.connect()


# -- URLs ----------------------------------------------------------------------------------------


def test_open_url_connects_with_dialect_and_options(make_server: ServerFactory, clients: list[ScannerClient]) -> None:
    server = make_server("a")
    c = open_device("scanner", server.url + "&timeout=7.5&reconnect=0&queue=8&retries=2&backoff=0.01")
    clients.append(c)
    assert isinstance(c, ScannerClient) and c.connected
    assert (c.dialect.value, c.timeout_s, c.reconnect, c.backoff.max_attempts) == ("a", 7.5, False, 2)
    assert c.device_state().measuring


@pytest.mark.parametrize("keep_raw", [False, True])
def test_open_device_passes_keep_raw_on(
    make_server: ServerFactory, clients: list[ScannerClient], keep_raw: bool
) -> None:
    c = open_device("scanner", make_server("b").url, keep_raw=keep_raw, timeout_s=10.0)
    clients.append(c)
    assert isinstance(c, ScannerClient) and c.keep_raw is keep_raw and c.timeout_s == 10.0
    c.start_streaming()
    record = c.next_record()
    c.stop_streaming()
    if keep_raw:
        assert record.raw is not None and record.raw.startswith(b"\x02\x02\x02\x02")
    else:
        assert record.raw is None
    assert record.scan.ranges_m.shape == (1081,)


@pytest.mark.parametrize(
    ("url", "port", "dialect"),
    [
        ("tcp://127.0.0.1?cola=a", 2111, "a"),
        ("tcp://127.0.0.1?cola=b", 2112, "b"),
        ("tcp://127.0.0.1:2112", 2112, "b"),
        ("tcp://127.0.0.1:9000", 9000, "a"),
        ("tcp://127.0.0.1:9000?cola=b", 9000, "b"),
    ],
)
def test_url_default_ports_and_dialects(url: str, port: int, dialect: str) -> None:
    c = open_url(DeviceURL.parse(url), connect=False)
    assert (c.port, c.dialect.value) == (port, dialect)


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("tcp://127.0.0.1:2111?cola=c", "expected one of a, b"),
        ("tcp://127.0.0.1:2111?cloa=b", "unknown option"),
        ("tcp://127.0.0.1:2111?timeout=-1", "outside"),
        ("tcp://127.0.0.1:2111?timeout=soon", "not a number"),
        ("tcp://127.0.0.1:2111?reconnect=maybe", "not a boolean"),
        ("tcp://127.0.0.1:2111?queue=0", "outside"),
        ("tcp://127.0.0.1:2111/scanner", "must not have a path"),
        ("tcp://:2111?cola=a", "no host"),
    ],
)
def test_bad_urls_are_rejected(url: str, message: str) -> None:
    with pytest.raises(DeviceURLError, match=message):
        open_device("scanner", url, connect=False)


def test_unknown_keyword_is_rejected() -> None:
    with pytest.raises(DeviceURLError, match="unknown keyword"):
        open_device("scanner", "tcp://127.0.0.1:2111", connect=False, colour="red")
