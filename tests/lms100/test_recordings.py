"""Every recorded telegram of real SICK devices decodes, whatever way the bytes arrive.

Recordings (tests/data/sick-recordings/, extracts of shared/reference/sick-recordings/; see its
README): an LMS111 and an LMS511 CoLa B session (every telegram, one complete frame each), a TiM781S
pcapng where each 3374-byte telegram came in two TCP segments (1448 + 1926), and an MRS1000 CoLa A
scan as text.
"""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Iterable

import numpy as np
import pytest

from drivers.lms100 import (
    CoLaConnection,
    Dialect,
    ErrorReply,
    FieldDefinition,
    FirmwareVersion,
    InputState,
    LocationName,
    Message,
    OutputRange,
    OutputStateEvent,
    RawTelegram,
    ReadFieldDefinition,
    ScanDataConfig,
    ScanDataEvent,
    SetAccessMode,
    SubscribeScanDataReply,
    decode_payload,
    frame,
)
from tests.lms100.pcapng import tcp_segments
from tests.lms100.recordings import LMS111, LMS511, MRS1000, RECORDINGS_DIR, TIM781S, session_frames


def _decode_stream(chunks: Iterable[bytes], dialect: Dialect) -> list[Message]:
    """Feed chunks to a connection that accepts both directions (recordings hold both)."""
    client = CoLaConnection(dialect, "client")
    out: list[Message] = []
    for chunk in chunks:
        client.receive_data(chunk)
        while True:
            payload = client.framer.next_payload()
            if payload is None:
                break
            out.append(decode_payload(payload, dialect))
    assert client.framer.buffered == 0 and client.framer.skipped_bytes == 0 and client.framer.errors == 0
    return out


def _one_byte_at_a_time(data: bytes) -> Iterable[bytes]:
    return (data[i : i + 1] for i in range(len(data)))


@pytest.mark.parametrize("name", [LMS111, LMS511])
def test_json_sessions_decode_and_reencode_byte_exact(name: str) -> None:
    telegrams = session_frames(name)
    assert len(telegrams) == 277
    msgs = _decode_stream(telegrams, Dialect.B)  # checksums are verified by the framer
    assert len(msgs) == 277
    for wire, msg in zip(telegrams, msgs, strict=True):
        assert frame(msg.encode(Dialect.B), Dialect.B) == wire
        if not isinstance(msg, RawTelegram):  # modelled telegrams also survive a trip through CoLa A
            assert decode_payload(msg.encode(Dialect.A), Dialect.A) == msg


@pytest.mark.parametrize("name", [LMS111, LMS511])
def test_json_sessions_fed_whole_and_one_byte_at_a_time(name: str) -> None:
    telegrams = session_frames(name)
    expected = _decode_stream(telegrams, Dialect.B)
    stream = b"".join(telegrams)
    assert _decode_stream([stream], Dialect.B) == expected
    assert _decode_stream(_one_byte_at_a_time(stream), Dialect.B) == expected


def test_lms111_session() -> None:
    msgs = _decode_stream(session_frames(LMS111), Dialect.B)
    kinds = Counter(type(m).__name__ for m in msgs)
    assert kinds["ScanDataEvent"] == 175 and kinds["ErrorReply"] == 0
    assert msgs[0] == SetAccessMode(3, 0xF4724744)
    assert FirmwareVersion("V1.80.2  ") in msgs and LocationName("not defined") in msgs
    rng = next(m for m in msgs if isinstance(m, OutputRange))
    assert (rng.sectors, rng.angular_resolution, rng.start_angle, rng.stop_angle) == (1, 5000, -449997, 2249997)
    cfg = next(m for m in msgs if isinstance(m, ScanDataConfig))
    assert cfg.output_channel == (1, 0) and not cfg.remission and cfg.time and cfg.output_rate == 1
    assert SubscribeScanDataReply(True) in msgs
    # start-up reads of SICK's driver: 30 field definitions (10 full, 20 one-byte), the input state, and the
    # output state sent once after its subscription (3 outputs, 8 "not used", with the time block)
    fields = [m for m in msgs if isinstance(m, FieldDefinition)]
    assert [f.index for f in fields] == [*range(24), 23, *range(24, 30)]  # sRA field023 captured twice
    assert all(f.geometry is not None for f in fields[:10]) and all(f.geometry is None for f in fields[10:])
    assert [f.geometry.field_type for f in fields[:3] if f.geometry] == [2, 1, 3]
    assert [f.geometry.name for f in fields[:4] if f.geometry] == ["FIELD1", "FIELD2", "FIELD3", ""]
    assert [m for m in msgs if isinstance(m, InputState)] == [InputState(1, 0, (2, 2, 2, 2))] * 2
    (out,) = [m for m in msgs if isinstance(m, OutputStateEvent)]
    assert [s for s, _ in out.outputs] == [0, 0, 1] + [2] * 8 and out.time is not None
    assert out.system_counter == 1_948_949_250  # device us, 139 ms after the first scan's start

    scans = [m.scan for m in msgs if isinstance(m, ScanDataEvent)]
    for s in scans:
        assert (s.version, s.device_number, s.serial_number) == (1, 1, 18090362)
        assert s.scan_frequency == 5000 and s.scan_frequency_hz == 50.0 and s.measurement_frequency == 360
        assert [c.name for c in s.channels_16] == ["DIST1"] and s.channels_8 == [] and s.rssi is None
        assert s.ranges_m.shape == (541,) and s.ranges_m.dtype == np.float64
        assert s.start_angle_deg == -45.0 and s.angular_step_deg == 0.5
        assert s.angles_rad[0] == pytest.approx(np.deg2rad(-45.0)) and s.angles_rad[-1] == pytest.approx(
            np.deg2rad(225.0)
        )
        assert s.time_info is not None and (s.time_info.year, s.time_info.month, s.time_info.day) == (1970, 1, 1)
        assert s.position is None and s.name is None and s.comment is None and s.event is None and s.encoders == ()
        assert 0 < s.time_of_transmission_us - s.time_since_startup_us < 10_000
    first = scans[0]
    assert first.telegram_counter == 63336 and first.scan_counter == 4
    assert first.time_since_startup_us == 1_948_810_585 and first.time_of_transmission_us == 1_948_813_715
    assert first.digital_outputs == (1, 0)
    assert first.time_info is not None and (first.time_info.hour, first.time_info.minute) == (2, 55)
    assert first.time_info.second == 34 and first.time_info.microsecond == 889000
    assert first.channels_16[0].values[:5].tolist() == [0x5D, 0x50, 0x56, 0x59, 0x52]
    assert first.ranges_m[:3].tolist() == [0.093, 0.080, 0.086]
    # device status: first byte 1 in the first 7 scans after start, then 0; the error byte stays 0
    assert [s.device_status for s in scans[:8]] == [(1, 0)] * 7 + [(0, 0)]
    assert all(s.device_status[1] == 0 for s in scans)
    # three scans were captured twice (same counter, same bytes): decoded twice, not hidden
    counts = Counter(s.telegram_counter for s in scans)
    assert sorted(k for k, v in counts.items() if v == 2) == [63350, 63366, 63382]
    assert len(counts) == 172
    steps = np.diff([s.time_since_startup_us for s in scans])
    assert int((steps == 0).sum()) == 3
    assert np.all((steps == 0) | ((steps > 19_000) & (steps < 21_000)))


def test_lms511_session_with_sfa_and_8bit_rssi() -> None:
    msgs = _decode_stream(session_frames(LMS511), Dialect.B)
    errors = [(prev, m) for prev, m in itertools.pairwise(msgs) if isinstance(m, ErrorReply)]
    assert len(errors) == 18
    assert [prev for prev, _ in errors] == [ReadFieldDefinition(i) for i in range(30, 48)]
    assert all(e.code == 3 and "VARIABLE_UNKNOWNINDEX" in e.message for _, e in errors)
    assert FirmwareVersion("V1.80    ") in msgs and LocationName("SN 18110550") in msgs
    cfg = next(m for m in msgs if isinstance(m, ScanDataConfig))
    assert cfg.remission and cfg.resolution == 0  # RSSI as an 8-bit channel

    scans = [m.scan for m in msgs if isinstance(m, ScanDataEvent)]
    assert len(scans) == 136
    for s in scans:
        assert (s.version, s.serial_number) == (0, 18110550)  # the LMS511 sends version 0
        assert s.scan_frequency_hz == 25.0 and s.measurement_frequency == 540
        assert [c.name for c in s.channels_16] == ["DIST1"] and [c.name for c in s.channels_8] == ["RSSI1"]
        assert s.channels_8[0].values.dtype == np.uint8 and len(s.channels_8[0].values) == 1141
        assert s.ranges_m.shape == (1141,) and s.rssi is not None and s.rssi.shape == (1141,)
        assert s.start_angle_deg == -5.0 and s.angular_step_deg == 0.1667
        assert s.channels_8[0].start_angle_raw == -50000
    assert [s.device_status for s in scans[:2]] == [(1, 0), (0, 0)]
    assert (scans[0].telegram_counter, scans[0].scan_counter) == (10203, 10335)
    assert np.diff([s.scan_counter for s in scans]).tolist() == [1] * 135
    assert scans[0].rssi is not None and scans[0].rssi[:5].tolist() == [254.0] * 5
    assert scans[0].ranges_m[:3].tolist() == [0x0519 / 1000, 0x0514 / 1000, 0x0513 / 1000]
    steps = np.diff([s.time_since_startup_us for s in scans])
    assert steps.min() > 39_000 and steps.max() < 41_000


def test_tim781s_pcapng_split_segments() -> None:
    segments = [s for s in tcp_segments(RECORDINGS_DIR / TIM781S) if s.src_port == 2112]
    assert [len(s.payload) for s in segments] == [1448, 1926] * 16
    conn = CoLaConnection(Dialect.B, "client")
    scans = []
    for first, second in zip(segments[::2], segments[1::2], strict=True):
        conn.receive_data(first.payload)
        assert conn.next_message() is None  # half a telegram: wait, no error
        conn.receive_data(second.payload)
        msg = conn.next_message()
        assert isinstance(msg, ScanDataEvent) and conn.next_message() is None
        scans.append(msg.scan)
    stream = b"".join(s.payload for s in segments)
    assert len(stream) == 16 * 3374
    assert [m.scan for m in _decode_stream(_one_byte_at_a_time(stream), Dialect.B)] == scans  # type: ignore[attr-defined]
    assert [m.scan for m in _decode_stream([stream], Dialect.B)] == scans  # type: ignore[attr-defined]
    for s in scans:
        assert s.serial_number == 18480390 and s.scan_frequency_hz == 15.0 and s.measurement_frequency == 162
        assert [c.name for c in s.channels_16] == ["DIST1", "RSSI1"] and s.channels_8 == []
        assert all(c.values.dtype == np.uint16 and len(c.values) == 811 for c in s.channels_16)
        assert s.start_angle_deg == -45.0 and s.channels_16[0].step_raw == 3333
        assert s.rssi is not None and s.rssi.max() > 255  # 16-bit RSSI
    assert (scans[0].telegram_counter, scans[0].scan_counter) == (44977, 44981)
    assert scans[0].digital_outputs == (8, 0)
    assert scans[0].channels_16[0].values[:5].tolist() == [626, 657, 616, 2, 2]
    assert scans[0].channels_16[1].values[:3].tolist() == [8177, 7678, 7840]
    assert np.diff([s.telegram_counter for s in scans]).tolist() == [1] * 15


def test_mrs1000_cola_a_scan() -> None:
    raw = (RECORDINGS_DIR / MRS1000).read_bytes()
    msgs = _decode_stream([raw], Dialect.A)
    assert len(msgs) == 1 and isinstance(msgs[0], ScanDataEvent)
    assert _decode_stream(_one_byte_at_a_time(raw), Dialect.A) == msgs
    assert _decode_stream([raw[i : i + 1448] for i in range(0, len(raw), 1448)], Dialect.A) == msgs
    s = msgs[0].scan
    assert (s.version, s.device_number, s.serial_number) == (1, 0, 0x107FA24)
    assert (s.telegram_counter, s.scan_counter) == (0x3FB0, 0x3FB0)
    assert (s.time_since_startup_us, s.time_of_transmission_us) == (0x9B6285F9, 0x9B6384B8)
    assert s.layer_angle == -500 and s.layer_angle_deg == -5.0
    assert s.scan_frequency_hz == 50.0 and s.measurement_frequency == 0xB4
    assert [c.name for c in s.channels_16] == ["DIST1", "DIST2", "DIST3"]
    assert [c.name for c in s.channels_8] == ["RSSI1", "RSSI2", "RSSI3"]
    assert all(len(c.values) == 1101 for c in s.channels_16 + s.channels_8)
    assert s.start_angle_deg == -47.5 and s.angular_step_deg == 0.25
    assert s.channels_16[0].values[:8].tolist() == [0, 0, 0, 0x6E0, 0x6F5, 0x703, 0x703, 0x705]
    assert s.rssi is not None and s.rssi[3:5].tolist() == [52.0, 71.0]
    assert int((s.channels_16[0].values == 0).sum()) > 100  # many "no echo" zeros
    assert s.time_info is not None and (s.time_info.year, s.time_info.hour, s.time_info.minute) == (1970, 1, 55)
    # our CoLa A encoder writes exactly what the device wrote
    assert frame(msgs[0].encode(Dialect.A), Dialect.A) == raw
