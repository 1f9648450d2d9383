"""Golden telegrams of the LMS1xx CoLa protocol in both dialects, written from the protocol documentation.

CoLa A texts follow SICK's telegram listing examples (shared/reference/sick-cola.md, section 2).
CoLa B frames are the same parameters in big-endian binary, with the payload length and the XOR
checksum; the values the notes list as check values (SetAccessMode 0x17/0xB3, sEN LMDscandata
0x11/0x33, sEA 0x3C as seen on the wire, sRN LMDscandata 0x0F/0x05, sWN EIHstCola 0x0F/0x09,
sRN LMPoutputRange 0x12/0x5E, sRN SCdevicestate 0x11/0x30, sFA 0x05/0x77) appear literally below.
"""

from __future__ import annotations

import pytest

from drivers.lms100 import (
    AccessLevel,
    CoLaConnection,
    DeviceErrorReply,
    DeviceIdent,
    DeviceReady,
    DeviceState,
    Dialect,
    ErrorReply,
    FirmwareVersion,
    LocationName,
    Message,
    PollScan,
    RawTelegram,
    ReadDeviceIdent,
    ReadDeviceReady,
    ReadDeviceState,
    ReadFirmwareVersion,
    ReadOutputRange,
    ReadScanConfig,
    ReadScanDataConfig,
    ReadSerialNumber,
    Run,
    RunReply,
    ScanConfig,
    ScanDataConfig,
    SerialNumber,
    SetAccessMode,
    SetAccessModeReply,
    SetHostDialect,
    SetHostDialectReply,
    SetScanConfig,
    SetScanConfigReply,
    StartMeasurement,
    StartMeasurementReply,
    StopMeasurement,
    StopMeasurementReply,
    SubscribeScanData,
    SubscribeScanDataReply,
    TelegramError,
    WriteScanDataConfig,
    WriteScanDataConfigReply,
    cast,
    decode_payload,
    frame,
    is_reply_to,
    reply_kind,
)
from drivers.lms100._values import REAL, AsciiWriter, BinWriter
from drivers.lms100.framing import Framer

CLIENT_HASH = 0xF4724744
CFG_50HZ = (5000, 1, 5000, -450000, 2250000)
CFG_25HZ = (2500, 1, 2500, -450000, 2250000)

# (message, CoLa A payload text, CoLa B complete frame as hex)
GOLDEN: list[tuple[Message, bytes, str]] = [
    (
        SetAccessMode(3, CLIENT_HASH),
        b"sMN SetAccessMode 03 F4724744",
        "02020202 00000017 734D4E20 53657441 63636573 734D6F64 6520 03F4724744 B3",
    ),
    (
        SetAccessMode(2, 0xB21ACE26),
        b"sMN SetAccessMode 02 B21ACE26",
        "02020202 00000017 734D4E20 5365744163636573734D6F6465 20 02B21ACE26 77",
    ),
    (
        SetAccessMode(4, 0x81BE23AA),
        b"sMN SetAccessMode 04 81BE23AA",
        "02020202 00000017 734D4E20 5365744163636573734D6F6465 20 0481BE23AA 87",
    ),
    (
        SetAccessModeReply(True),
        b"sAN SetAccessMode 1",
        "02020202 00000013 73414E20 5365744163636573734D6F6465 20 01 38",
    ),
    (
        SetAccessModeReply(False),
        b"sAN SetAccessMode 0",
        "02020202 00000013 73414E20 5365744163636573734D6F6465 20 00 39",
    ),
    (ReadScanConfig(), b"sRN LMPscancfg", "02020202 0000000E 73524E20 4C4D507363616E636667 63"),
    (
        ScanConfig(*CFG_50HZ),
        b"sRA LMPscancfg 1388 1 1388 FFF92230 225510",
        "02020202 00000021 73524120 4C4D507363616E636667 20 00001388 0001 00001388 FFF92230 00225510 3E",
    ),
    (
        SetScanConfig(*CFG_25HZ),
        b"sMN mLMPsetscancfg +2500 +1 +2500 -450000 +2250000",
        "02020202 00000025 734D4E20 6D4C4D50736574736361 6E636667 20 000009C4 0001 000009C4 FFF92230 00225510 21",
    ),
    (
        SetScanConfigReply(0, *CFG_25HZ),
        b"sAN mLMPsetscancfg 0 9C4 1 9C4 FFF92230 225510",
        "02020202 00000026 73414E20 6D4C4D507365747363616E636667 20 00 000009C4 0001 000009C4 FFF92230 00225510 2D",
    ),
    (
        SetScanConfigReply(1, *CFG_50HZ),
        b"sAN mLMPsetscancfg 1 1388 1 1388 FFF92230 225510",
        "02020202 00000026 73414E20 6D4C4D507365747363616E636667 20 01 00001388 0001 00001388 FFF92230 00225510 2C",
    ),
    (
        WriteScanDataConfig((1, 0), True, 1, 0, (0, 0), False, False, False, True, 1),
        b"sWN LMDscandatacfg 01 00 1 1 0 00 00 0 0 0 1 +1",
        "02020202 00000020 73574E20 4C4D447363616E64617461636667 20 0100 01 01 00 0000 00 00 00 01 0001 43",
    ),
    (
        WriteScanDataConfigReply(),
        b"sWA LMDscandatacfg",
        "02020202 00000013 73574120 4C4D447363616E64617461636667 20 4D",
    ),
    (ReadScanDataConfig(), b"sRN LMDscandatacfg", "02020202 00000012 73524E20 4C4D447363616E64617461636667 67"),
    (
        ScanDataConfig((1, 0), False, 0, 0, (0, 0), False, False, False, True, 1),
        b"sRA LMDscandatacfg 1 0 0 0 0 0 0 0 0 0 1 1",
        "02020202 00000020 73524120 4C4D447363616E64617461636667 20 0100 00 00 00 0000 00 00 00 01 0001 49",
    ),
    (StartMeasurement(), b"sMN LMCstartmeas", "02020202 00000010 734D4E20 4C4D4373746172746D656173 68"),
    (StartMeasurementReply(0), b"sAN LMCstartmeas 0", "02020202 00000012 73414E20 4C4D4373746172746D656173 20 00 44"),
    (StopMeasurement(), b"sMN LMCstopmeas", "02020202 0000000F 734D4E20 4C4D4373746F706D656173 10"),
    (StopMeasurementReply(0), b"sAN LMCstopmeas 0", "02020202 00000011 73414E20 4C4D4373746F706D656173 20 00 3C"),
    (Run(), b"sMN Run", "02020202 00000007 734D4E20 52756E 19"),
    (RunReply(True), b"sAN Run 1", "02020202 00000009 73414E20 52756E 20 01 34"),
    (ReadDeviceState(), b"sRN STlms", "02020202 00000009 73524E20 53546C6D73 3A"),
    (
        DeviceState(7, False, "00:34:19", "01.01.1970", 0, 0, 0),
        b"sRA STlms 7 0 8 00:34:19 A 01.01.1970 0 0 0",
        "02020202 00000029 73524120 53546C6D73 20 0007 00 0008 30303A33343A3139 000A 30312E30312E31393730"
        " 0000 0000 0000 10",
    ),
    (ReadDeviceIdent(), b"sRN DeviceIdent", "02020202 0000000F 73524E20 4465766963654964656E74 25"),
    (
        DeviceIdent("LMS10x_FieldEval", "V1.36-21.10.2010"),
        b"sRA DeviceIdent 10 LMS10x_FieldEval 10 V1.36-21.10.2010",
        "02020202 00000034 73524120 4465766963654964656E74 20 0010 4C4D533130785F4669656C644576616C"
        " 0010 56312E33362D32312E31302E32303130 62",
    ),
    (ReadSerialNumber(), b"sRN SerialNumber", "02020202 00000010 73524E20 53657269616C4E756D626572 4C"),
    (
        SerialNumber("18090362"),
        b"sRA SerialNumber 8 18090362",
        "02020202 0000001B 73524120 53657269616C4E756D626572 20 0008 3138303930333632 6C",
    ),
    (ReadFirmwareVersion(), b"sRN FirmwareVersion", "02020202 00000013 73524E20 4669726D7761726556657273696F6E 24"),
    (
        FirmwareVersion("V1.80.2  "),
        b"sRA FirmwareVersion 9 V1.80.2  ",
        "02020202 0000001F 73524120 4669726D7761726556657273696F6E 20 0009 56312E38302E322020 5F",
    ),
    (
        LocationName("not defined"),
        b"sRA LocationName B not defined",
        "02020202 0000001E 73524120 4C6F636174696F6E4E616D65 20 000B 6E6F7420646566696E6564 45",
    ),
    (ReadDeviceReady(), b"sRN SCdevicestate", "02020202 00000011 73524E20 5343646576696365737461746 5 30"),
    (DeviceReady(1), b"sRA SCdevicestate 1", "02020202 00000013 73524120 53436465766963657374617465 20 01 1E"),
    (SetHostDialect(1), b"sWN EIHstCola 1", "02020202 0000000F 73574E20 454948737443 6F6C61 20 01 09"),
    (SetHostDialectReply(), b"sWA EIHstCola", "02020202 0000000E 73574120 4549487374436F6C61 20 07"),
    (ReadOutputRange(), b"sRN LMPoutputRange", "02020202 00000012 73524E20 4C4D506F757470757452616E6765 5E"),
    (PollScan(), b"sRN LMDscandata", "02020202 0000000F 73524E20 4C4D447363616E64617461 05"),
    (SubscribeScanData(True), b"sEN LMDscandata 1", "02020202 00000011 73454E20 4C4D447363616E64617461 20 01 33"),
    (SubscribeScanData(False), b"sEN LMDscandata 0", "02020202 00000011 73454E20 4C4D447363616E64617461 20 00 32"),
    (SubscribeScanDataReply(True), b"sEA LMDscandata 1", "02020202 00000011 73454120 4C4D447363616E64617461 20 01 3C"),
    (SubscribeScanDataReply(False), b"sEA LMDscandata 0", "02020202 00000011 73454120 4C4D447363616E64617461 20 00 3D"),
    (ErrorReply(3), b"sFA 3", "02020202 00000005 734641 0003 77"),
    (ErrorReply(1), b"sFA 1", "02020202 00000005 734641 0001 75"),
    (ErrorReply(0x11), b"sFA 11", "02020202 00000005 734641 0011 65"),
]


def _b(hex_text: str) -> bytes:
    return bytes.fromhex(hex_text.replace(" ", ""))


@pytest.mark.parametrize(
    ("msg", "text_a", "frame_b"), GOLDEN, ids=[f"{m.kind}-{m.name or 'err'}" for m, _, _ in GOLDEN]
)
def test_golden_encode_and_decode_both_dialects(msg: Message, text_a: bytes, frame_b: str) -> None:
    wire_b = _b(frame_b)
    assert msg.encode(Dialect.A) == text_a
    assert frame(msg.encode(Dialect.A), Dialect.A) == b"\x02" + text_a + b"\x03"
    assert frame(msg.encode(Dialect.B), Dialect.B) == wire_b
    assert decode_payload(text_a, Dialect.A) == msg
    for dialect, wire in ((Dialect.A, b"\x02" + text_a + b"\x03"), (Dialect.B, wire_b)):
        framer = Framer(dialect)
        framer.feed(wire)
        payload = framer.next_payload()
        assert payload is not None and framer.next_payload() is None
        assert decode_payload(payload, dialect) == msg
        assert type(decode_payload(payload, dialect)) is type(msg)


def test_documented_b_check_values_are_in_the_golden_table() -> None:
    frames = {m.encode(Dialect.B): _b(f) for m, _, f in GOLDEN}
    documented = {
        SetAccessMode(3, CLIENT_HASH): (0x17, 0xB3),
        SubscribeScanData(True): (0x11, 0x33),
        SubscribeScanDataReply(True): (0x11, 0x3C),
        PollScan(): (0x0F, 0x05),
        SetHostDialect(1): (0x0F, 0x09),
        ReadOutputRange(): (0x12, 0x5E),
        ReadDeviceReady(): (0x11, 0x30),
        ErrorReply(3): (0x05, 0x77),
        ErrorReply(1): (0x05, 0x75),
    }
    for msg, (length, checksum) in documented.items():
        wire = frames[msg.encode(Dialect.B)]
        assert int.from_bytes(wire[4:8], "big") == length
        assert wire[-1] == checksum


def test_cola_a_numbers_accept_hex_and_signed_decimal() -> None:
    hex_form = decode_payload(b"sMN mLMPsetscancfg 1388 1 1388 FFF92230 225510", Dialect.A)
    dec_form = decode_payload(b"sMN mLMPsetscancfg +5000 +1 +5000 -450000 +2250000", Dialect.A)
    assert hex_form == dec_form == SetScanConfig(*CFG_50HZ)
    assert isinstance(dec_form, SetScanConfig)
    assert dec_form.scan_frequency_hz == 50.0 and dec_form.angular_resolution_deg == 0.5
    assert (dec_form.start_angle_deg, dec_form.stop_angle_deg) == (-45.0, 225.0)
    # SetAccessMode with the level written without a leading zero, as some clients do
    assert decode_payload(b"sMN SetAccessMode 3 F4724744", Dialect.A) == SetAccessMode(3, CLIENT_HASH)
    assert SetAccessMode.default(AccessLevel.MAINTENANCE) == SetAccessMode(2, 0xB21ACE26)


def test_set_scan_config_helpers_and_status_texts() -> None:
    assert SetScanConfig.from_hz_deg(25, 0.25) == SetScanConfig(2500, 1, 2500, -450000, 2250000)
    ok = SetScanConfigReply(0, *CFG_25HZ)
    bad = SetScanConfigReply(3, *CFG_50HZ)
    assert ok.ok and ok.status_text == "ok"
    assert not bad.ok and bad.status_text == "frequency and angular resolution not allowed"


def test_device_state_text_and_strings_with_spaces() -> None:
    st = decode_payload(b"sRA STlms 7 0 8 00:34:19 A 01.01.1970 0 0 0", Dialect.A)
    assert isinstance(st, DeviceState) and st.measuring and st.status_text == "measuring"
    old = decode_payload(b"sRA STlms 3 0 8 00:34:19 8 01.01.70 0 0 0", Dialect.A)
    assert isinstance(old, DeviceState) and old.date == "01.01.70" and old.status_text == "idle"
    # length-prefixed strings keep inner and trailing spaces
    name = decode_payload(b"sRA LocationName F a b  c d e f g ", Dialect.A)
    assert name == LocationName("a b  c d e f g ")
    assert name.encode(Dialect.A) == b"sRA LocationName F a b  c d e f g "
    assert decode_payload(b"sRA FirmwareVersion 9 V1.80    ", Dialect.A) == FirmwareVersion("V1.80    ")


def test_error_reply_code_to_message_and_exception() -> None:
    err = decode_payload(b"sFA 3", Dialect.A)
    assert isinstance(err, ErrorReply) and err.code == 3
    assert "VARIABLE_UNKNOWNINDEX" in err.message and "unknown variable" in err.message
    exc = err.to_exception("sRN field030")
    assert isinstance(exc, DeviceErrorReply) and exc.code == 3 and exc.message == err.message
    assert "sRN field030" in str(exc)
    assert "not in the SOPAS error table" in ErrorReply(0x7777).message
    with pytest.raises(DeviceErrorReply) as info:
        cast(err, SerialNumber)
    assert info.value.code == 3
    assert cast(SerialNumber("1"), SerialNumber) == SerialNumber("1")
    with pytest.raises(TelegramError, match="expected SerialNumber"):
        cast(RunReply(True), SerialNumber)


def test_unmodelled_names_decode_raw_and_round_trip() -> None:
    lfe = _b("73534E20 4C4645726563 20 0004 0001 01")
    raw = decode_payload(lfe, Dialect.B)
    assert raw == RawTelegram("sSN", "LFErec", _b("0004 0001 01"))
    assert raw.encode(Dialect.B) == lfe
    bare = decode_payload(b"sRN LFPmeanfilter", Dialect.A)
    assert bare == RawTelegram("sRN", "LFPmeanfilter", None) and bare.encode(Dialect.A) == b"sRN LFPmeanfilter"
    assert decode_payload(b"sMA mSCreboot", Dialect.A) == RawTelegram("sMA", "mSCreboot", None)


@pytest.mark.parametrize(
    ("payload", "dialect", "match"),
    [
        (b"xRN LMDscandata", Dialect.A, "unknown CoLa command type"),
        (b"sXX LMDscandata", Dialect.B, "unknown CoLa command type"),
        (b"sRNLMDscandata", Dialect.A, "followed by a space"),
        (b"sRN LMD scan", Dialect.A, "LMD"),  # unmodelled name with junk params -> raw (no error), checked below
        (b"sAN Run", Dialect.A, "too short"),
        (b"sAN Run 1 2", Dialect.A, "trailing"),
        (b"sAN Run \x01\x02", Dialect.B, "trailing"),
        (b"sRA LMPscancfg 1388 1 1388 FFF92230", Dialect.A, "too short"),
        (b"sRA LMPscancfg 1388 1 1388 FFF92230 12345678A", Dialect.A, "bad hex"),
        (b"sRA LMPscancfg 1388 1 1388 FFF92230 +99999999999", Dialect.A, "does not fit"),
        (b"sRA LMPscancfg 1388  1 1388 FFF92230 225510", Dialect.A, "empty parameter"),
        (b"sRA SerialNumber 9 18090362", Dialect.A, "string is cut"),
        (b"sRA SerialNumber 8 1809036299", Dialect.A, "not followed by a space"),
        (b"sRA SerialNumber \x00\x09abc", Dialect.B, "too short"),
        (b"sFA", Dialect.B, "uint16 code"),
        (b"sFA 1 2", Dialect.A, "trailing"),
        (b"sFA\x00\x03\x00", Dialect.B, "uint16 code"),
        (b"sRN \xff\xfe", Dialect.B, "bad telegram name"),
    ],
)
def test_bad_telegrams_raise_telegram_error(payload: bytes, dialect: Dialect, match: str) -> None:
    if payload == b"sRN LMD scan":
        assert decode_payload(payload, dialect) == RawTelegram("sRN", "LMD", b"scan")
        return
    with pytest.raises(TelegramError, match=match):
        decode_payload(payload, dialect)


def test_encoding_out_of_range_values_is_a_telegram_error() -> None:
    with pytest.raises(TelegramError, match="does not fit"):
        ScanConfig(1 << 32, 1, 5000, 0, 0).encode(Dialect.B)
    with pytest.raises(TelegramError, match="does not fit"):
        SetAccessMode(3, -1).encode(Dialect.A)
    with pytest.raises(TelegramError, match="latin-1"):
        SerialNumber("\u20ac").encode(Dialect.B)
    with pytest.raises(TelegramError, match="STX/ETX"):
        SerialNumber("a\x03b").encode(Dialect.A)
    with pytest.raises(TelegramError, match="unknown CoLa command type"):
        RawTelegram("sXX", "Foo").encode(Dialect.A)


@pytest.mark.parametrize(("writer", "one_and_a_half"), [(BinWriter, b"\x3f\xc0\x00\x00"), (AsciiWriter, b"3FC00000")])
def test_reals_are_the_ieee_single_bit_pattern_and_overflow_is_a_telegram_error(
    writer: type[BinWriter | AsciiWriter], one_and_a_half: bytes
) -> None:
    w = writer()
    w.put(REAL, 1.5)
    assert w.getvalue() == one_and_a_half
    with pytest.raises(TelegramError, match="bad REAL 1e"):
        writer().put(REAL, 1e300)
    with pytest.raises(TelegramError, match="bad REAL"):
        writer().put(REAL, "1.5")


def test_reply_matching() -> None:
    assert reply_kind(PollScan()) == "sRA"
    assert reply_kind(SetAccessMode()) == "sAN"
    assert reply_kind(SubscribeScanData(True)) == "sEA"
    assert is_reply_to(SubscribeScanDataReply(True), SubscribeScanData(True))
    assert is_reply_to(ErrorReply(3), ReadSerialNumber())
    assert not is_reply_to(SerialNumber("1"), ReadDeviceIdent())
    assert is_reply_to(RawTelegram("sMA", "LMCstartmeas"), StartMeasurement())
    with pytest.raises(TelegramError, match="not a request"):
        reply_kind(RunReply(True))


@pytest.mark.parametrize("dialect", [Dialect.A, Dialect.B])
def test_connection_exchange_both_roles(dialect: Dialect) -> None:
    client = CoLaConnection(dialect, "client")
    device = CoLaConnection(dialect, "device")
    requests: list[Message] = [SetAccessMode(), ReadScanConfig(), SetScanConfig(*CFG_25HZ), StartMeasurement(), Run()]
    wire = b"".join(client.send(m) for m in requests)
    for i in range(0, len(wire), 7):
        device.receive_data(wire[i : i + 7])
    assert device.messages() == requests
    replies: list[Message] = [SetAccessModeReply(True), ScanConfig(*CFG_50HZ), ErrorReply(8), StartMeasurementReply(0)]
    client.receive_data(b"".join(device.send(m) for m in replies))
    assert client.messages() == replies
    assert client.messages_sent == 5 and device.messages_received == 5
    # directions are enforced both ways, and the connection stays usable afterwards
    with pytest.raises(TelegramError, match="client does not send sRA"):
        client.send(ScanConfig(*CFG_50HZ))
    with pytest.raises(TelegramError, match="device does not send sRN"):
        device.send(PollScan())
    client.receive_data(device.send(RunReply(True)) + frame(PollScan().encode(dialect), dialect))
    client.receive_data(device.send(RunReply(True)))
    assert client.next_message() == RunReply(True)
    with pytest.raises(TelegramError, match="client does not expect sRN"):
        client.next_message()
    assert client.next_message() == RunReply(True)
    assert client.next_message() is None
    with pytest.raises(ValueError, match="role"):
        CoLaConnection(dialect, "server")  # type: ignore[arg-type]
