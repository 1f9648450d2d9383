"""Field definitions, LIDinputstate, LIDoutputstate and their subscriptions: golden bytes from the recordings.

CoLa B frames below are copied from the LMS111 (``20210302_lms111``) and LMS511 (``20210301_lms511``)
sessions in tests/data/sick-recordings/ (entry numbers in comments); the decoded values are read off
those bytes by hand. CoLa A has no recording: its texts are the same fields as tokens (our mapping).
"""

from __future__ import annotations

import pytest

from drivers.lms100 import (
    Dialect,
    DynamicField,
    FieldDefinition,
    FieldGeometry,
    InputState,
    InputStateEvent,
    Message,
    OutputStateEvent,
    RawTelegram,
    ReadFieldDefinition,
    ReadInputState,
    RectangularField,
    ScanTime,
    SubscribeFieldResultsReply,
    SubscribeInputState,
    SubscribeOutputState,
    SubscribeOutputStateReply,
    TelegramError,
    decode_payload,
    frame,
    is_modelled,
    is_reply_to,
)
from tests.lms100.recordings import LMS111, LMS511, session


def _b(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


# An unconfigured field as the LMS111 answers field003..field009 (entry 27): scale 1.0, offset 0,
# 0.5 deg grid from -45 deg, type 2 (segmented), number 0, no segment / rectangle / radial / dynamic
# block, name flag 1 with an empty name, comment flag 0.
FIELD003 = "02020202 0000002D 735241206669656C6430303320 3F800000 00000000 00001388 FFF92230 02 00 0000 0000 0000 0000 0001 0000 0000 02"  # noqa: E501
# field010..029: one byte 00 (entry 41).
FIELD010 = "02020202 0000000E 735241206669656C6430313020 00 33"
# field001, a rectangle (entry 23): reference 169.6951 deg / 1118 mm, turned -7 deg, 400 x 100 mm, "FIELD2".
FIELD001 = (
    "02020202 00000045 735241206669656C6430303120 3F800000 00000000 00001388 FFF92230 01 02 0000"
    " 0001 0019E4B7 045E FFFEEE90 00000190 00000064 0000 0000 0001 0006 4649454C4432 0000 EC"
)
# field002, a dynamic field (entry 25): 180 deg / 1000 mm, 2000 x 1000 mm, 5000 mm/s -> 2000 mm, "FIELD3".
FIELD002 = (
    "02020202 0000004B 735241206669656C6430303220 3F800000 00000000 00001388 FFF92230 03 03 0000 0000 0000"
    " 0001 001B7740 03E8 00000000 000007D0 000003E8 1388 000007D0 0001 0006 4649454C4433 0000 C0"
)
# sRA LIDinputstate on the LMS111 (entry 82): version 1, counter 0, inputs 2 2 2 2, no time block.
LMS111_INPUTS = "02020202 0000001E 73524120 4C4944696E7075747374617465 20 0001 00000000 02020202 0000 21"
# the LMS511's (entry 117): version 0, counter 5920746, inputs 0, time 1970-01-01 00:00:02.527000.
LMS511_INPUTS = (
    "02020202 00000029 73524120 4C4944696E7075747374617465 20 0000 005A57EA 00000000"
    " 0001 07B2 01 01 00 00 02 00080A98 EB"
)
# sSN LIDoutputstate on the LMS111 (entry 108): 11 outputs, the third active, then the time block.
LMS111_OUTPUTS = (
    "02020202 0000005D 73534E20 4C49446F75747075747374617465 20 0001 742A9B02"
    " 00 000000FC 00 00000112 01 0000005D" + " 02 00000000" * 8 + " 0001 07B2 01 01 02 37 23 000061A8 59"
)

CASES: list[tuple[Message, str, bytes]] = [
    (FieldDefinition(3, FieldGeometry()), FIELD003, b"sRA field003 3F800000 00000000 1388 FFF92230 2 0 0 0 0 0 1 0 0"),
    (FieldDefinition(10, None), FIELD010, b"sRA field010 0"),
    (
        FieldDefinition(
            1,
            FieldGeometry(
                field_type=1, field_number=2, rectangle=RectangularField(1696951, 1118, -70000, 400, 100), name="FIELD2"
            ),
        ),
        FIELD001,
        b"sRA field001 3F800000 00000000 1388 FFF92230 1 2 0 1 19E4B7 45E FFFEEE90 190 64 0 0 1 6 FIELD2 0",
    ),
    (
        FieldDefinition(
            2,
            FieldGeometry(
                field_type=3,
                field_number=3,
                dynamic=DynamicField(1800000, 1000, 0, 2000, 1000, max_speed=5000, max_length=2000),
                name="FIELD3",
            ),
        ),
        FIELD002,
        b"sRA field002 3F800000 00000000 1388 FFF92230 3 3 0 0 0 1 1B7740 3E8 0 7D0 3E8 1388 7D0 1 6 FIELD3 0",
    ),
    (InputState(1, 0, (2, 2, 2, 2)), LMS111_INPUTS, b"sRA LIDinputstate 1 0 2 2 2 2 0"),
    (
        InputState(0, 5920746, (0, 0, 0, 0), ScanTime(1970, 1, 1, 0, 0, 2, 527000)),
        LMS511_INPUTS,
        b"sRA LIDinputstate 0 5A57EA 0 0 0 0 1 7B2 1 1 0 0 2 80A98",
    ),
    (
        OutputStateEvent(
            1, 1948949250, ((0, 252), (0, 274), (1, 93)) + ((2, 0),) * 8, ScanTime(1970, 1, 1, 2, 55, 35, 25000)
        ),
        LMS111_OUTPUTS,
        b"sSN LIDoutputstate 1 742A9B02 0 FC 0 112 1 5D" + b" 2 0" * 8 + b" 1 7B2 1 1 2 37 23 61A8",
    ),
]


@pytest.mark.parametrize(("msg", "wire_b", "text_a"), CASES)
def test_golden_frames_both_ways(msg: Message, wire_b: str, text_a: bytes) -> None:
    wire = _b(wire_b)
    assert frame(msg.encode(Dialect.B), Dialect.B) == wire
    assert decode_payload(wire[8:-1], Dialect.B) == msg
    assert msg.encode(Dialect.A) == text_a
    assert decode_payload(text_a, Dialect.A) == msg


@pytest.mark.parametrize(("msg", "wire_b", "text_a"), CASES)
def test_golden_frames_are_in_the_recordings(msg: Message, wire_b: str, text_a: bytes) -> None:
    frames = {t.frame for t in session(LMS111)} | {t.frame for t in session(LMS511)}
    assert _b(wire_b) in frames


def test_requests_and_subscriptions() -> None:
    assert ReadFieldDefinition(0).encode(Dialect.B) == b"sRN field000"
    assert frame(ReadFieldDefinition(29).encode(Dialect.B), Dialect.B) == _b(
        "02020202 0000000C 73524E206669656C64303239 16"  # LMS111 entry 79
    )
    assert decode_payload(b"sRN field047", Dialect.A) == ReadFieldDefinition(47)
    assert ReadInputState().encode(Dialect.A) == b"sRN LIDinputstate"
    assert frame(SubscribeOutputState(True).encode(Dialect.B), Dialect.B) == _b(
        "02020202 00000014 73454E20 4C49446F75747075747374617465 20 01 50"  # LMS111 entry 96
    )
    assert decode_payload(b"sEA LFErec 1", Dialect.A) == SubscribeFieldResultsReply(True)
    assert SubscribeInputState(False).encode(Dialect.A) == b"sEN LIDinputstate 0"
    assert is_reply_to(FieldDefinition(7, None), ReadFieldDefinition(7))
    assert not is_reply_to(FieldDefinition(7, None), ReadFieldDefinition(8))
    assert is_reply_to(SubscribeOutputStateReply(True), SubscribeOutputState(True))
    assert is_modelled("sRN", "field012") and is_modelled("sRA", "field999")
    assert not is_modelled("sWN", "field012") and not is_modelled("sRN", "field1234")


def test_input_state_event_shares_the_body() -> None:
    ev = InputStateEvent(1, 7, (1, 0, 0, 1))
    assert ev.encode(Dialect.B) == b"sSN LIDinputstate " + _b("0001 00000007 01000001 0000")
    assert decode_payload(ev.encode(Dialect.A), Dialect.A) == ev


def test_output_state_without_time_and_count_from_length() -> None:
    ev = OutputStateEvent(1, 0, ((0, 0), (1, 3)))
    assert ev.encode(Dialect.B) == b"sSN LIDoutputstate " + _b("0001 00000000 00 00000000 01 00000003 0000")
    assert decode_payload(ev.encode(Dialect.B), Dialect.B) == ev
    assert ev.encode(Dialect.A) == b"sSN LIDoutputstate 1 0 0 0 1 3 0"
    assert decode_payload(ev.encode(Dialect.A), Dialect.A) == ev
    assert decode_payload(b"sSN LIDoutputstate 1 0 0", Dialect.A) == OutputStateEvent(1, 0, ())


def test_radial_field_stays_raw() -> None:
    # a radial block (flag 1) has a layout in no source we have: the telegram is kept as raw bytes
    params = _b("3F800000 00000000 00001388 FFF92230 00 01 0000 0000 0001 0000 0001 0000 0000")
    msg = decode_payload(b"sRA field004 " + params, Dialect.B)
    assert msg == RawTelegram("sRA", "field004", params)


@pytest.mark.parametrize(
    ("payload", "dialect", "match"),
    [
        (b"sRA field010 \x01", Dialect.B, "must be 0"),
        (b"sRA field010 1", Dialect.A, "must be 0"),
        (b"sRN field010 \x00", Dialect.B, "no parameters"),
        (
            b"sRA field003 " + _b("3F800000 00000000 00001388 FFF92230 02 00 0002 0000 0000 0000 0001 0000 0000"),
            Dialect.B,
            "segmented field flag must be 0 or 1",
        ),
        (
            b"sRA field003 " + _b("3F800000 00000000 00001388 FFF92230 02 00 0000 0000 0000 0000 0001 0000 0000 00"),
            Dialect.B,
            "trailing",
        ),
        (b"sSN LIDoutputstate " + _b("0001 00000000 00 00000000 01 000000"), Dialect.B, "fit no layout"),
        (b"sSN LIDoutputstate " + _b("0001 00000000 00 00000000 0001"), Dialect.B, "too short"),
        (b"sSN LIDoutputstate 1 0 0 0 1", Dialect.A, "too short"),
        (b"sRA LIDinputstate " + _b("0001 00000000 02020202"), Dialect.B, "too short"),
        (b"sRA LIDinputstate 1 0 2 2 2 2 0 5", Dialect.A, "trailing"),
    ],
)
def test_malformed_telegrams_raise(payload: bytes, dialect: Dialect, match: str) -> None:
    with pytest.raises(TelegramError, match=match):
        decode_payload(payload, dialect)


def test_bad_values_do_not_encode() -> None:
    with pytest.raises(TelegramError, match=r"0\.\.999"):
        ReadFieldDefinition(1000)
    with pytest.raises(TelegramError, match="4 inputs"):
        InputState(1, 0, (1, 2, 3), None).encode(Dialect.B)  # type: ignore[arg-type]
    with pytest.raises(TelegramError, match="does not fit"):
        OutputStateEvent(1, 0, ((256, 0),)).encode(Dialect.B)
