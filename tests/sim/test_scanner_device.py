"""The simulated LMS100 over real TCP (127.0.0.1, ephemeral port), driven by the codec's client side."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from drivers.lms100 import (
    AccessLevel,
    DeviceIdent,
    DeviceReady,
    DeviceState,
    ErrorReply,
    FirmwareVersion,
    LocationName,
    OutputRange,
    PollScan,
    PowerOnCount,
    RawTelegram,
    ReadDeviceIdent,
    ReadDeviceReady,
    ReadDeviceState,
    ReadFirmwareVersion,
    ReadLocationName,
    ReadOutputRange,
    ReadPowerOnCount,
    ReadScanConfig,
    ReadScanDataConfig,
    ReadSerialNumber,
    Reboot,
    RebootReply,
    Run,
    RunReply,
    SaveParameters,
    SaveParametersReply,
    ScanConfig,
    ScanDataConfig,
    ScanDataReply,
    SerialNumber,
    SetAccessMode,
    SetAccessModeReply,
    SetScanConfig,
    SetScanConfigReply,
    StartMeasurement,
    StartMeasurementReply,
    StopMeasurement,
    SubscribeOutputStateReply,
    SubscribeScanData,
    SubscribeScanDataReply,
    WriteOutputRange,
    WriteOutputRangeReply,
    WriteScanDataConfig,
    WriteScanDataConfigReply,
    frame,
)
from drivers.lms100.framing import Dialect
from lrms.kinematics import RigCalibration
from sim.scanner import ScannerServer, SimulatedLMS100, SimulatorError
from sim.scene import SEED003_AXIS_POINT, SEED003_DIAMETER, SIGMA_L_SEED003, LMS1xxSensor, Plane, Scene, SensorModel
from tests.sim.conftest import Link

Connect = Callable[..., Link]
DIALECTS = ["a", "b"]


@pytest.fixture
def fast_server(request: pytest.FixtureRequest) -> Iterator[ScannerServer]:
    dialect = getattr(request, "param", "b")
    with ScannerServer(SimulatedLMS100("seed003", realtime=False), dialect=dialect) as srv:
        yield srv


def login(link: Link, level: AccessLevel = AccessLevel.AUTHORIZED_CLIENT) -> None:
    assert link.request(SetAccessMode.default(level)) == SetAccessModeReply(True)


@pytest.mark.parametrize("fast_server", DIALECTS, indirect=True)
def test_identity_serial_firmware_and_state(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address, fast_server.dialect.value)
    assert link.request(ReadDeviceIdent()) == DeviceIdent("LMS10x_FieldEval", "V1.36-21.10.2010")
    serial = link.request(ReadSerialNumber())
    assert isinstance(serial, SerialNumber) and int(serial.serial) == fast_server.device.serial_number
    assert link.request(ReadFirmwareVersion()) == FirmwareVersion("V1.80.2  ")
    assert link.request(ReadLocationName()) == LocationName("simulated LMS100")
    assert link.request(ReadPowerOnCount()) == PowerOnCount(1)
    state = link.request(ReadDeviceState())
    assert isinstance(state, DeviceState) and state.status == 7 and state.date == "01.01.1970"
    assert link.request(ReadDeviceReady()) == DeviceReady(1)
    assert link.request(ReadScanConfig()) == ScanConfig(2500, 1, 2500, -450000, 2250000)
    assert link.request(ReadOutputRange()) == OutputRange(1, 2500, -450000, 2250000)


@pytest.mark.parametrize("fast_server", DIALECTS, indirect=True)
def test_access_levels_and_passwords(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address, fast_server.dialect.value)
    # Not logged in: methods are denied with sFA 1, variable writes with sFA A.
    assert link.request(SetScanConfig.from_hz_deg(50, 0.5)) == ErrorReply(0x01)
    assert link.request(StartMeasurement()) == ErrorReply(0x01)
    assert link.request(WriteScanDataConfig()) == ErrorReply(0x0A)
    # Wrong password hash and unknown level are refused with sAN SetAccessMode 0.
    assert link.request(SetAccessMode(3, 0xB21ACE26)) == SetAccessModeReply(False)
    assert link.request(SetAccessMode(7, 0xF4724744)) == SetAccessModeReply(False)
    # Maintenance (2) logs in but may not configure.
    login(link, AccessLevel.MAINTENANCE)
    assert link.request(SetScanConfig.from_hz_deg(50, 0.5)) == ErrorReply(0x01)
    # Authorized client (3) and service (4) may.
    login(link, AccessLevel.AUTHORIZED_CLIENT)
    assert link.request(SetScanConfig.from_hz_deg(50, 0.5)) == SetScanConfigReply(0, 5000, 1, 5000, -450000, 2250000)
    login(link, AccessLevel.SERVICE)
    assert link.request(WriteScanDataConfig()) == WriteScanDataConfigReply()
    # Run ends the login.
    assert link.request(Run()) == RunReply(True)
    assert link.request(StartMeasurement()) == ErrorReply(0x01)
    # The login belongs to the connection: a second client is not logged in.
    login(link)
    other = connect(fast_server.address, fast_server.dialect.value)
    assert other.request(StopMeasurement()) == ErrorReply(0x01)


@pytest.mark.parametrize(
    ("hz", "deg", "status"),
    [
        (25, 0.25, 0),
        (25, 0.5, 2),  # 25 Hz only at 0.25 deg
        (50, 0.5, 0),
        (50, 0.25, 2),  # 50 Hz only at 0.5 deg
        (35, 0.5, 1),
        (75, 0.5, 1),
        (35, 0.1, 3),
        (25, 1.0, 2),
    ],
)
def test_only_lms1xx_scan_configurations_are_accepted(
    fast_server: ScannerServer, connect: Connect, hz: float, deg: float, status: int
) -> None:
    link = connect(fast_server.address)
    login(link)
    before = link.request(ReadScanConfig())
    reply = link.request(SetScanConfig.from_hz_deg(hz, deg))
    assert isinstance(reply, SetScanConfigReply) and reply.status == status
    after = link.request(ReadScanConfig())
    assert isinstance(after, ScanConfig)
    if status == 0:
        assert (after.scan_frequency, after.angular_resolution) == (round(hz * 100), round(deg * 10000))
    else:
        assert after == before  # a refused configuration changes nothing
    assert (reply.scan_frequency, reply.angular_resolution) == (after.scan_frequency, after.angular_resolution)


def test_scan_area_and_sector_errors_and_sfa_codes(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address)
    login(link)
    bad_area = link.request(SetScanConfig.from_hz_deg(25, 0.25, -50.0, 225.0))
    assert isinstance(bad_area, SetScanConfigReply) and bad_area.status == 4
    two_sectors = link.request(SetScanConfig(2500, 2, 2500, -450000, 2250000))
    assert isinstance(two_sectors, SetScanConfigReply) and two_sectors.status == 5
    # Output range outside the scan area: value out of range.
    assert link.request(WriteOutputRange(1, 2500, -460000, 0)) == ErrorReply(0x04)
    # An LMS1xx has two echoes (mask 1, 2, 3): a third echo (mask 4) or 0x1F (LMS5xx) is out of range.
    assert link.request(WriteScanDataConfig(output_channel=(4, 0))) == ErrorReply(0x04)
    assert link.request(WriteScanDataConfig(output_channel=(0x1F, 0))) == ErrorReply(0x04)
    # Unknown variable / method / event, a known method with missing parameters, a reply sent as a request.
    assert link.request(RawTelegram("sRN", "field030")) == ErrorReply(0x03)
    assert link.request(RawTelegram("sMN", "mNoSuchMethod")) == ErrorReply(0x02)
    assert link.request(RawTelegram("sEN", "InertialMeasurementUnit", b"\x01")) == ErrorReply(0x0F)
    assert link.request(RawTelegram("sEN", "LIDoutputstate", b"\x01")) == SubscribeOutputStateReply(True)
    link.send_raw(frame(b"sMN mLMPsetscancfg \x00\x00\x13\x88", Dialect.B))
    assert link.reply() == ErrorReply(0x08)
    link.send_raw(frame(b"sRA LMPscancfg", Dialect.B))
    assert link.reply() == ErrorReply(0x0C)
    # A broken checksum is dropped; the connection keeps working.
    good = frame(b"sRN STlms", Dialect.B)
    link.send_raw(good[:-1] + bytes([good[-1] ^ 0xFF]))
    assert isinstance(link.request(ReadDeviceState()), DeviceState)
    assert fast_server.framing_errors == 1


def test_cola_a_invalid_characters_answer_sfa_11(connect: Connect) -> None:
    with ScannerServer(SimulatedLMS100("empty", realtime=False), dialect="a") as srv:
        link = connect(srv.address, "a")
        link.send_raw(b"\x02sRN LMPscancfg\x01\x7f\x03")
        assert link.reply() == ErrorReply(0x11)
        link.send_raw(b"\x02sMN mLMPsetscancfg +5000\x03")
        assert link.reply() == ErrorReply(0x08)


@pytest.mark.parametrize("fast_server", DIALECTS, indirect=True)
def test_fast_stream_counters_and_device_clock(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address, fast_server.dialect.value)
    assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
    scans = link.scans(120)
    counters = np.array([s.scan_counter for s in scans])
    telegrams = np.array([s.telegram_counter for s in scans])
    starts = np.array([s.time_since_startup_us for s in scans], dtype=np.int64)
    sent = np.array([s.time_of_transmission_us for s in scans], dtype=np.int64)
    # Every scan, none lost: counters +1, device clock +40 ms (25 Hz) per scan.
    assert np.all(np.diff(counters) == 1) and np.all(np.diff(telegrams) == 1)
    assert np.all(np.diff(starts) == 40_000)
    # Transmission after the scan's last beam: 1080 beams x 27.78 us + 1 ms.
    assert np.all(sent - starts == round(1080 * 40_000 * 0.25 / 360) + 1000)
    first = scans[0]
    assert first.scan_frequency == 2500 and first.measurement_frequency == 360
    assert first.ranges_m.shape == (1081,) and first.start_angle_deg == -45.0 and first.angular_step_deg == 0.25
    assert first.serial_number == fast_server.device.serial_number
    # A fresh device reports status (1, 0) in its first 7 scans, then (0, 0).
    assert [s.device_status for s in scans[:8]] == [(1, 0)] * 7 + [(0, 0)]
    assert link.request(SubscribeScanData(False)) == SubscribeScanDataReply(False)
    # The device clock never runs backwards: a poll afterwards is later than every streamed scan.
    polled = link.request(PollScan())
    assert isinstance(polled, ScanDataReply)
    assert polled.scan.time_since_startup_us > starts[-1] and polled.scan.scan_counter > counters[-1]


def test_reconfiguration_changes_rate_and_beams_and_counters_continue(
    fast_server: ScannerServer, connect: Connect
) -> None:
    link = connect(fast_server.address)
    assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
    before = link.scans(3)
    login(link)
    reply = link.request(SetScanConfig.from_hz_deg(50, 0.5))
    assert isinstance(reply, SetScanConfigReply) and reply.ok
    assert link.request(WriteScanDataConfig(remission=True, resolution=0, time=True, output_rate=4)) == (
        WriteScanDataConfigReply()
    )
    assert link.request(Run()) == RunReply(True)
    link.events.clear()  # scans of the old configuration may still be in flight
    scans = [s for s in link.scans(40) if s.scan_frequency == 5000][-10:]
    assert len(scans) == 10
    counters = np.array([s.scan_counter for s in scans])
    assert np.all(np.diff(counters) == 4)  # every 4th scan
    assert np.all(np.diff([s.telegram_counter for s in scans]) == 1)
    assert np.all(np.diff([s.time_since_startup_us for s in scans]) == 4 * 20_000)
    assert counters[0] > before[-1].scan_counter
    s = scans[0]
    assert s.ranges_m.shape == (541,) and s.measurement_frequency == 360
    assert s.channels_8 and s.channels_8[0].name == "RSSI1" and s.rssi is not None
    assert s.time_info is not None and s.time_info.year == 1970
    assert link.request(ReadScanDataConfig()) == ScanDataConfig(
        (1, 0), True, 0, 0, (0, 0), False, False, False, True, 4
    )


def test_login_pauses_scans_until_run_and_stop_start_measurement(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address)
    login(link)
    assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
    # Configuration mode: the fast device would stream at once, yet nothing arrives before this reply.
    assert isinstance(link.request(ReadDeviceState()), DeviceState)
    assert link.events == []
    assert link.request(StopMeasurement()) != ErrorReply(0x01)
    state = link.request(ReadDeviceState())
    assert isinstance(state, DeviceState) and state.status != 7
    assert link.request(StartMeasurement()) == StartMeasurementReply(0)
    state = link.request(ReadDeviceState())
    assert isinstance(state, DeviceState) and state.status == 7
    assert link.events == []
    assert link.request(Run()) == RunReply(True)
    scans = link.scans(10)
    assert np.all(np.diff([s.scan_counter for s in scans]) == 1)
    assert scans[0].device_status == (1, 0)  # measuring restarted: start-up status again


def test_two_clients_receive_the_same_scans(fast_server: ScannerServer, connect: Connect) -> None:
    a = connect(fast_server.address)
    b = connect(fast_server.address)
    a.request(SubscribeScanData(True))
    b.request(SubscribeScanData(True))
    sa = {s.scan_counter: s for s in a.scans(60)}
    sb = {s.scan_counter: s for s in b.scans(60)}
    common = sorted(set(sa) & set(sb))
    assert len(common) >= 20
    for k in common:
        assert sa[k].telegram_counter == sb[k].telegram_counter
        np.testing.assert_array_equal(sa[k].ranges_m, sb[k].ranges_m)


def test_drop_clients_and_reconnect(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address)
    assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
    last = link.scans(5)[-1]
    assert fast_server.drop_clients() == 1
    with pytest.raises((ConnectionError, OSError)):
        for _ in range(10_000):
            link.scans(1)
    again = connect(fast_server.address)
    assert again.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
    assert again.scans(1)[0].scan_counter > last.scan_counter
    assert fast_server.connections == 2


def test_reboot_restores_saved_configuration(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address)
    login(link)
    assert link.request(SetScanConfig.from_hz_deg(50, 0.5)) == SetScanConfigReply(0, 5000, 1, 5000, -450000, 2250000)
    assert link.request(SaveParameters()) == SaveParametersReply(True)
    assert link.request(SetScanConfig.from_hz_deg(25, 0.25)) == SetScanConfigReply(0, 2500, 1, 2500, -450000, 2250000)
    assert link.request(ReadScanConfig()) == ScanConfig(2500, 1, 2500, -450000, 2250000)  # applied, not saved
    assert link.request(Reboot()) == RebootReply()
    with pytest.raises((ConnectionError, OSError)):
        link.request(ReadDeviceState())
    again = connect(fast_server.address)
    assert again.request(ReadPowerOnCount()) == PowerOnCount(2)
    assert again.request(ReadScanConfig()) == ScanConfig(5000, 1, 5000, -450000, 2250000)


def test_output_range_limits_the_beams(fast_server: ScannerServer, connect: Connect) -> None:
    link = connect(fast_server.address)
    login(link)
    assert link.request(WriteOutputRange(1, 2500, 0, 1800000)) == WriteOutputRangeReply()
    assert link.request(Run()) == RunReply(True)
    polled = link.request(PollScan())
    assert isinstance(polled, ScanDataReply)
    assert polled.scan.start_angle_deg == 0.0 and polled.scan.ranges_m.shape == (721,)


# ---------------------------------------------------------------- ranges against the scene
def test_ranges_match_seed003_geometry_within_noise(connect: Connect) -> None:
    with ScannerServer(SimulatedLMS100("seed003", realtime=False, seed=3)) as srv:
        link = connect(srv.address)
        scan = link.request(PollScan())
        assert isinstance(scan, ScanDataReply)
        cal = RigCalibration()
        x0, y0, _ = SEED003_AXIS_POINT
        alpha = np.arctan2(x0 - cal.p, y0)  # the beam aimed at the axis, plane horizontal (motor at 0)
        angles = scan.scan.angles_rad
        j = int(np.argmin(np.abs(cal.alpha(angles) - alpha)))
        # The neighbouring beams all land on the cylinder's front; exact ranges from the circle.
        js = np.arange(j - 3, j + 4)
        a = cal.alpha(angles[js])
        ox, dx, dy = cal.p, np.sin(a), np.cos(a)
        r = SEED003_DIAMETER / 2
        b = dx * (ox - x0) + dy * (0 - y0)
        c = (ox - x0) ** 2 + y0**2 - r**2
        expected = -b - np.sqrt(b * b - c)
        assert np.all(np.abs(scan.scan.ranges_m[js] - expected) < 5 * SIGMA_L_SEED003)


def test_plane_turning_during_the_scan_uses_each_beams_time(connect: Connect) -> None:
    floor = Scene("floor")
    floor.add(Plane((0, 0, -1.0), (0, 0, 1)), remission=0.5)
    omega = np.deg2rad(90.0)  # rad/s of device-clock time
    calls: list[np.ndarray] = []

    def motor(t: np.ndarray) -> np.ndarray:
        calls.append(t.copy())
        return -np.deg2rad(30.0) + omega * t

    device = SimulatedLMS100(floor, motor_angle_at=motor, sensor=SensorModel.noiseless(), realtime=False)
    with ScannerServer(device) as srv:
        link = connect(srv.address)
        assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
        scan = link.scans(4)[3]
    t0 = scan.time_since_startup_us / 1e6
    times = t0 + np.arange(1081) * (0.04 * 0.25 / 360)
    assert any(np.allclose(c, times, rtol=0, atol=1e-9) for c in calls)
    cal = RigCalibration()
    a = cal.alpha(scan.angles_rad)
    beta = motor(times)
    # Beam from p (cos b, 0, sin b) along (sin a cos b, cos a, sin a sin b) reaches z = -1 at:
    with np.errstate(divide="ignore"):
        expected = (-1.0 - cal.p * np.sin(beta)) / (np.sin(a) * np.sin(beta))
    ok = (expected > 0.5) & (expected < 20)
    assert ok.sum() > 200
    np.testing.assert_allclose(scan.ranges_m[ok], expected[ok], atol=0.0005 + 1e-9)  # whole mm on the wire
    assert np.all(scan.ranges_m[~ok] == 0)


def test_realtime_stream_paces_by_the_device_clock(connect: Connect) -> None:
    device = SimulatedLMS100("wall", time_scale=4.0)  # real-time mode, clock 4x faster than the host
    with ScannerServer(device, dialect="a") as srv:
        link = connect(srv.address, "a")
        assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
        scans = link.scans(6)
    steps = np.diff([s.time_since_startup_us for s in scans])
    counters = np.diff([s.scan_counter for s in scans])
    assert np.all(steps == 40_000 * counters) and np.all(counters >= 1)
    r = scans[-1].ranges_m
    ahead = np.abs(scans[-1].angles_rad - np.pi / 2) < np.deg2rad(30)
    a = scans[-1].angles_rad[ahead] - np.pi / 2
    assert np.all(np.abs(r[ahead] - 3.0 / np.cos(a)) < 6 * SIGMA_L_SEED003)


def test_a_realtime_stream_that_falls_behind_counts_the_scans_it_passes_over(connect: Connect) -> None:
    device = SimulatedLMS100("wall")  # real time, 25 Hz
    with ScannerServer(device, dialect="b") as srv:
        link = connect(srv.address, "b")
        assert link.request(SubscribeScanData(True)) == SubscribeScanDataReply(True)
        before = link.scans(2)
        with device.lock:  # the streaming thread stalls for 10 scan periods, as on a starved host
            time.sleep(0.4)
        after = link.scans(3)
    counters = np.array([s.scan_counter for s in before + after])
    gaps = int(np.sum(np.diff(counters) - 1))
    # every gap a client sees is a scan the server counted as passed over (it may have counted
    # more by now: scans passed over after the last one read)
    assert 1 <= gaps <= srv.scans_skipped, (counters, srv.scans_skipped)


def test_bad_server_and_device_arguments() -> None:
    with pytest.raises(SimulatorError):
        ScannerServer(SimulatedLMS100("empty"), dialect="c")
    with pytest.raises(SimulatorError):
        SimulatedLMS100("empty", time_scale=0.0)
    with pytest.raises(SimulatorError):
        SimulatedLMS100("empty", serial_number=-1)
    with ScannerServer(SimulatedLMS100("empty")) as busy, pytest.raises(SimulatorError, match="cannot listen"):
        ScannerServer(SimulatedLMS100("empty"), port=busy.address[1]).start()
    with pytest.raises(SimulatorError, match="not started"):
        _ = ScannerServer(SimulatedLMS100("empty")).address


def test_a_login_left_open_ends_with_its_connection(fast_server: ScannerServer, connect: Connect) -> None:
    admin = connect(fast_server.address)
    login(admin)
    watcher = connect(fast_server.address)
    watcher.request(SubscribeScanData(True))
    assert isinstance(watcher.request(ReadDeviceState()), DeviceState) and watcher.events == []  # paused
    admin.close()  # never sent Run
    assert len(watcher.scans(3)) == 3


def test_a_failing_motor_callback_is_an_internal_error_not_a_dead_server(connect: Connect) -> None:
    def broken(t: np.ndarray) -> np.ndarray:
        raise RuntimeError("encoder unplugged")

    with ScannerServer(SimulatedLMS100("wall", motor_angle_at=broken, realtime=False)) as srv:
        link = connect(srv.address)
        assert link.request(PollScan()) == ErrorReply(0x14)
        assert link.request(ReadDeviceIdent()) == DeviceIdent("LMS10x_FieldEval", "V1.36-21.10.2010")


@pytest.mark.parametrize("resolution", [0, 1])
def test_lms1xx_sensor_streams_two_echoes_and_rssi(connect: Connect, resolution: int) -> None:
    """The footprint sensor through the real protocol: DIST1 + DIST2 (output channel 3) and RSSI1 +
    RSSI2 as 8-bit (resolution 0) or 16-bit channels; second echoes where the spot straddles the
    part's silhouette with the room's back wall 1.2 m behind it."""
    device = SimulatedLMS100("seed003-room", sensor=LMS1xxSensor(), realtime=False, seed=2)
    with ScannerServer(device) as srv:
        link = connect(srv.address)
        login(link)
        cfg = WriteScanDataConfig(output_channel=(3, 0), remission=True, resolution=resolution)
        assert link.request(cfg) == WriteScanDataConfigReply()
        read = link.request(ReadScanDataConfig())
        assert isinstance(read, ScanDataConfig) and tuple(read.output_channel) == (3, 0)
        assert link.request(Run()) == RunReply(True)
        reply = link.request(PollScan())
        assert isinstance(reply, ScanDataReply)
        scan = reply.scan
        names16 = [c.name for c in scan.channels_16]
        names8 = [c.name for c in scan.channels_8]
        if resolution == 0:
            assert names16 == ["DIST1", "DIST2"] and names8 == ["RSSI1", "RSSI2"]
        else:
            assert names16 == ["DIST1", "DIST2", "RSSI1", "RSSI2"] and names8 == []
        d1, d2 = scan.ranges_m, scan.channel("DIST2").scaled() / 1000.0  # type: ignore[union-attr]
        rssi1, rssi2 = scan.rssi, scan.channel("RSSI2").scaled()  # type: ignore[union-attr]
        assert rssi1 is not None
        assert np.array_equal(d1 > 0, rssi1 > 0) and np.array_equal(d2 > 0, rssi2 > 0)
        two = d2 > 0
        assert 1 <= np.count_nonzero(two) < 20  # only at depth steps
        assert np.all(d2[two] - d1[two] > 0.3)  # the second echo lies behind the first
        assert np.count_nonzero(d1 > 0) > 1000  # a closed room: nearly every beam returns
        # Back to the first echo only: DIST2 and RSSI2 are gone.
        login(link)
        assert link.request(WriteScanDataConfig(output_channel=(1, 0), remission=True)) == WriteScanDataConfigReply()
        assert link.request(Run()) == RunReply(True)
        again = link.request(PollScan())
        assert isinstance(again, ScanDataReply) and again.scan.channel("DIST2") is None
