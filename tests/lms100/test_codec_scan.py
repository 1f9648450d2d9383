"""LMDscandata: golden scans in both dialects, every optional block, derived arrays and typed errors."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.lms100 import (
    Channel,
    Dialect,
    Encoder,
    PollScan,
    Position,
    Scan,
    ScanDataEvent,
    ScanDataReply,
    ScanEvent,
    ScanTime,
    TelegramError,
    decode_payload,
    frame,
    make_channel,
)
from drivers.lms100.scan import format_hex_tokens, parse_hex_tokens

# The LMS111 header quoted in shared/reference/sick-cola.md, section 3, with a 3-value DIST1 channel
# and the TiM-style tail "no 8-bit channel, no position, name 'not defined', no comment/time/event".
GOLDEN_A = (
    b"sRA LMDscandata 1 1 8D4C04 0 0 45FF 37 280F6 28A73 0 0 7 0 0 1388 168 0 1 DIST1 3F800000 00000000"
    b" FFF92230 1388 3 1F4 3E8 0 0 0 1 B not defined 0 0 0"
)
GOLDEN_B_FRAME = (
    "02020202 0000006C 73524120 4C4D447363616E64617461 20"
    " 0001 0001 008D4C04 00 00 45FF 0037 000280F6 00028A73 00 00 07 00 0000 00001388 00000168 0000"
    " 0001 4449535431 3F800000 00000000 FFF92230 1388 0003 01F4 03E8 0000"
    " 0000 0000 0001 000B 6E6F7420646566696E6564 0000 0000 0000 31"
)
# same scan as an event with the time block the notes decode (07B2 01 01 02 37 22 000D90A8) and no name
GOLDEN_TIME_A = (
    b"sSN LMDscandata 1 1 8D4C04 0 0 45FF 37 280F6 28A73 0 0 7 0 0 1388 168 0 1 DIST1 3F800000 00000000"
    b" FFF92230 1388 3 1F4 3E8 0 0 0 0 0 1 7B2 1 1 2 37 22 D90A8 0"
)
GOLDEN_TIME_B_FRAME = (
    "02020202 0000006A 73534E20 4C4D447363616E64617461 20"
    " 0001 0001 008D4C04 00 00 45FF 0037 000280F6 00028A73 00 00 07 00 0000 00001388 00000168 0000"
    " 0001 4449535431 3F800000 00000000 FFF92230 1388 0003 01F4 03E8 0000"
    " 0000 0000 0000 0000 0001 07B2 01 01 02 37 22 000D90A8 0000 97"
)


def _golden_scan(name: str | None = "not defined", time_info: ScanTime | None = None) -> Scan:
    return Scan(
        version=1,
        device_number=1,
        serial_number=0x8D4C04,
        device_status=(0, 0),
        telegram_counter=0x45FF,
        scan_counter=0x37,
        time_since_startup_us=0x280F6,
        time_of_transmission_us=0x28A73,
        digital_inputs=(0, 0),
        digital_outputs=(7, 0),
        layer_angle=0,
        scan_frequency=5000,
        measurement_frequency=360,
        channels_16=[make_channel("DIST1", np.array([500, 1000, 0], dtype=np.uint16), -45.0, 0.5)],
        name=name,
        time_info=time_info,
    )


def _b(hex_text: str) -> bytes:
    return bytes.fromhex(hex_text.replace(" ", ""))


def test_golden_scan_reply_both_dialects() -> None:
    msg = ScanDataReply(_golden_scan())
    assert msg.encode(Dialect.A) == GOLDEN_A
    assert frame(msg.encode(Dialect.B), Dialect.B) == _b(GOLDEN_B_FRAME)
    assert decode_payload(GOLDEN_A, Dialect.A) == msg
    assert decode_payload(_b(GOLDEN_B_FRAME)[8:-1], Dialect.B) == msg
    s = msg.scan
    assert s.ranges_m.tolist() == [0.5, 1.0, 0.0] and s.ranges_m.dtype == np.float64
    assert np.allclose(np.rad2deg(s.angles_rad), [-45.0, -44.5, -44.0], rtol=0, atol=1e-12)
    assert s.rssi is None and s.name == "not defined"
    assert (s.start_angle_deg, s.angular_step_deg, s.scan_frequency_hz, s.measurement_frequency_hz) == (
        -45.0,
        0.5,
        50.0,
        36000.0,
    )


def test_golden_scan_event_with_time_block() -> None:
    t = ScanTime(1970, 1, 1, 2, 55, 34, 889000)
    msg = ScanDataEvent(_golden_scan(name=None, time_info=t))
    assert msg.encode(Dialect.A) == GOLDEN_TIME_A
    assert frame(msg.encode(Dialect.B), Dialect.B) == _b(GOLDEN_TIME_B_FRAME)
    for dialect, payload in ((Dialect.A, GOLDEN_TIME_A), (Dialect.B, _b(GOLDEN_TIME_B_FRAME)[8:-1])):
        got = decode_payload(payload, dialect)
        assert isinstance(got, ScanDataEvent) and got.scan.time_info == t and got == msg


def _full_scan() -> Scan:
    rng = np.random.default_rng(3)
    return Scan(
        version=1,
        device_number=7,
        serial_number=0xFFFFFFFF,
        device_status=(1, 2),
        telegram_counter=65535,
        scan_counter=0,
        time_since_startup_us=0xFFFFFFFF,
        time_of_transmission_us=1,
        digital_inputs=(3, 255),
        digital_outputs=(0x3C, 1),
        layer_angle=-500,
        scan_frequency=2500,
        measurement_frequency=360,
        encoders=(Encoder(123456, 42), Encoder(0xFFFFFFFF, 0xFFFF)),
        channels_16=[
            make_channel("DIST1", rng.integers(0, 65536, 1081), -45.0, 0.25, scale=2.0),
            make_channel("DIST2", rng.integers(0, 65536, 1081), -45.0, 0.25, scale=1.0, offset=-3.5),
            make_channel("RSSI1", rng.integers(0, 65536, 1081), -45.0, 0.25),
        ],
        channels_8=[make_channel("RSSI2", rng.integers(0, 256, 1081), -45.0, 0.25)],
        position=Position(1.5, -2.25, 0.125, 0.0, 90.0, -180.0, 3, 1),
        name="rig scanner 1",
        comment="  two  spaces  ",
        time_info=ScanTime(2026, 11, 21, 12, 40, 59, 999999),
        event=ScanEvent("FDIN", 77, 123456789, -450000),
    )


@pytest.mark.parametrize("dialect", [Dialect.A, Dialect.B])
def test_every_optional_block_round_trips(dialect: Dialect) -> None:
    msg = ScanDataEvent(_full_scan())
    payload = msg.encode(dialect)
    got = decode_payload(payload, dialect)
    assert got == msg
    assert isinstance(got, ScanDataEvent)
    s = got.scan
    assert s.channels_16[2].values.dtype == np.uint16 and s.channels_8[0].values.dtype == np.uint8
    # scale 2.0: a raw value v is 2v mm
    assert np.array_equal(s.ranges_m, s.channels_16[0].values.astype(np.float64) * 2.0 / 1000.0)
    assert s.rssi is not None and np.array_equal(s.rssi, s.channels_16[2].values.astype(np.float64))
    dist2 = s.channel("DIST2")
    assert dist2 is not None and np.array_equal(dist2.scaled(), dist2.values - 3.5)
    assert s.layer_angle_deg == -5.0 and s.angles_rad.shape == (1081,)
    assert np.rad2deg(s.angles_rad[-1]) == pytest.approx(225.0, abs=1e-9)
    assert decode_payload(payload, dialect).encode(dialect) == payload


def test_rssi_as_8bit_channel_and_missing_dist1() -> None:
    s = Scan(channels_8=[make_channel("RSSI1", np.array([1, 2, 255], dtype=np.uint8), 0.0, 1.0)])
    assert s.rssi is not None and s.rssi.tolist() == [1.0, 2.0, 255.0]
    with pytest.raises(TelegramError, match="no DIST1"):
        _ = s.ranges_m
    with pytest.raises(TelegramError, match="no DIST1"):
        _ = s.start_angle_deg


def test_channel_equality_and_angles_in_device_units() -> None:
    a = make_channel("DIST1", [1, 2, 3], -45.0, 0.3333)
    assert a.start_angle_raw == -450000 and a.step_raw == 3333
    assert a == make_channel("DIST1", np.array([1, 2, 3], dtype=np.uint16), -45.0, 0.3333)
    assert a != make_channel("DIST1", [1, 2, 4], -45.0, 0.3333)
    assert a != make_channel("DIST1", [1, 2], -45.0, 0.3333)
    assert a != make_channel("DIST2", [1, 2, 3], -45.0, 0.3333)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (GOLDEN_A.replace(b" 3 1F4 3E8 0 ", b" 4 1F4 3E8 0 "), "LMDscandata"),  # count larger than the values
        (GOLDEN_A.replace(b"1F4 3E8", b"1F4 3G8"), "invalid character"),
        (GOLDEN_A.replace(b"1F4 3E8", b"1F4 13E8A"), "1..4 hex digits"),
        (GOLDEN_A.replace(b"1F4 3E8", b"1F4  3E8"), "1..4 hex digits"),
        (GOLDEN_A.replace(b" 1 B not defined", b" 2 B not defined"), "name flag is 2"),
        (GOLDEN_A.replace(b"B not defined", b"C not defined"), "string"),
        (GOLDEN_A + b" 0", b"trailing"),
        (GOLDEN_A[:-2], "too short"),
        (GOLDEN_A.replace(b"DIST1 3F800000", b"DIST1 3F80000Z"), "bad REAL"),
    ],
)
def test_bad_cola_a_scans(text: bytes, match: str | bytes) -> None:
    with pytest.raises(TelegramError, match=match if isinstance(match, str) else match.decode()):
        decode_payload(text, Dialect.A)


def test_bad_cola_b_scans() -> None:
    payload = _b(GOLDEN_B_FRAME)[8:-1]
    for cut in [17, 40, 60, 90, len(payload) - 1]:
        with pytest.raises(TelegramError):
            decode_payload(payload[:cut], Dialect.B)
    with pytest.raises(TelegramError, match="trailing"):
        decode_payload(payload + b"\x00", Dialect.B)
    n_at = payload.index(b"\x13\x88\x00\x03") + 2  # value count of DIST1
    with pytest.raises(TelegramError, match="announces 65535 values"):
        decode_payload(payload[:n_at] + b"\xff\xff" + payload[n_at + 2 :], Dialect.B)


def test_encoding_bad_scans_raises_telegram_error() -> None:
    base = _golden_scan()
    for bad in [
        Scan(channels_16=[make_channel("DIST1", [70000], 0.0, 1.0)]),
        Scan(channels_16=[make_channel("DIST1", [-1], 0.0, 1.0)]),
        Scan(channels_8=[make_channel("RSSI1", [256], 0.0, 1.0)]),
        Scan(channels_16=[make_channel("DIST", [1], 0.0, 1.0)]),
        Scan(channels_16=[make_channel("DIST1", [1.5], 0.0, 1.0)]),
        Scan(channels_16=[make_channel("DIST1", [1], 0.0, 7.0)]),  # step 70000 > uint16
        Scan(serial_number=-1),
        Scan(device_status=(256, 0)),
        Scan(event=ScanEvent("TOOLONG", 0, 0, 0)),
    ]:
        for dialect in (Dialect.A, Dialect.B):
            with pytest.raises(TelegramError):
                ScanDataEvent(bad).encode(dialect)
    assert ScanDataEvent(base).encode(Dialect.B)  # the good one encodes


def test_hex_token_helpers_match_python_int() -> None:
    rng = np.random.default_rng(11)
    values = np.concatenate([[0, 1, 15, 16, 255, 256, 4095, 4096, 65535], rng.integers(0, 65536, 500)])
    text = format_hex_tokens(values, 4)
    assert text == b" ".join(b"%X" % int(v) for v in values)
    parsed, pos = parse_hex_tokens(text + b" tail", 0, len(values), 4)
    assert parsed.tolist() == values.tolist() and pos == len(text) + 1
    lower, _ = parse_hex_tokens(b"ff a0 0", 0, 3, 2)
    assert lower.tolist() == [255, 160, 0]
    with pytest.raises(TelegramError):
        parse_hex_tokens(b"1 2", 0, 3, 4)


def test_poll_reply_is_a_scan_and_the_request_has_no_parameters() -> None:
    assert PollScan().encode(Dialect.B) == b"sRN LMDscandata"
    assert PollScan().encode(Dialect.A) == b"sRN LMDscandata"
    reply = decode_payload(GOLDEN_A, Dialect.A)
    assert isinstance(reply, ScanDataReply)
    (dist,) = reply.scan.channels_16
    assert isinstance(dist, Channel) and (dist.name, dist.scale, dist.offset) == ("DIST1", 1.0, 0.0)
    assert dist.values.dtype == np.uint16 and dist.values.tolist() == [500, 1000, 0]
    assert np.rad2deg(dist.start_angle_rad) == pytest.approx(-45.0) and np.rad2deg(dist.step_rad) == pytest.approx(0.5)


def test_cola_a_scan_with_signed_decimals_takes_the_general_path() -> None:
    decimal = GOLDEN_A.replace(b"LMDscandata 1 1 8D4C04", b"LMDscandata +1 +1 +9260036").replace(
        b"FFF92230 1388 3 ", b"-450000 +5000 +3 "
    )
    assert decimal != GOLDEN_A
    assert decode_payload(decimal, Dialect.A) == decode_payload(GOLDEN_A, Dialect.A)
    lower = GOLDEN_A.replace(b"8D4C04", b"8d4c04").replace(b"1F4 3E8", b"1f4 3e8")
    assert decode_payload(lower, Dialect.A) == decode_payload(GOLDEN_A, Dialect.A)
