"""Property tests (hypothesis) and fuzzing of the CoLa codec.

- every modelled telegram and any scan survive encode -> decode in both dialects;
- a stream of telegrams cut at arbitrary points decodes to the same messages;
- garbage between telegrams is skipped (only FramingErrors may be reported) and no telegram is lost;
- random and mutated bytes never raise anything but a CoLaError subclass.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import string
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.lms100 import (
    RAD_PER_UNIT,
    Channel,
    CoLaConnection,
    CoLaError,
    Dialect,
    DynamicField,
    Encoder,
    ErrorReply,
    FieldDefinition,
    FieldGeometry,
    Framer,
    FramingError,
    InputState,
    InputStateEvent,
    Message,
    OutputStateEvent,
    Position,
    RawTelegram,
    ReadFieldDefinition,
    RectangularField,
    Scan,
    ScanDataEvent,
    ScanDataReply,
    ScanEvent,
    ScanTime,
    SegmentPoint,
    TelegramError,
    decode_payload,
    frame,
    message_classes,
)
from drivers.lms100._values import Field, int_range
from drivers.lms100.framing import MAGIC

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
dialects = st.sampled_from([Dialect.A, Dialect.B])

_TEXT = st.text(
    alphabet=st.characters(min_codepoint=0, max_codepoint=255, blacklist_characters="\x02\x03"), max_size=40
)


def _field_strategy(f: Field) -> st.SearchStrategy[Any]:
    if f.kind == "int":
        lo, hi = int_range(f.size, f.signed)
        return st.integers(lo, hi)
    if f.kind == "bool":
        return st.booleans()
    if f.kind == "str":
        return _TEXT
    if f.kind == "pair":
        return st.tuples(st.integers(0, 255), st.integers(0, 255))
    return st.floats(width=32, allow_nan=False)


# classes laid out by their FIELDS table (the others, scans and I/O states, have their own strategies)
_FIELD_CLASSES = [
    cls for cls in message_classes().values() if [f.name for f in dataclasses.fields(cls)] == [n for n, _ in cls.FIELDS]
]
_CUSTOM_CLASSES = {ScanDataEvent, ScanDataReply, InputState, InputStateEvent, OutputStateEvent}


@st.composite
def field_messages(draw: st.DrawFn) -> Message:
    cls = draw(st.sampled_from(_FIELD_CLASSES))
    return cls(*(draw(_field_strategy(f)) for _, f in cls.FIELDS))


_UNMODELLED_NAMES = st.from_regex(r"\Afld[0-9]{3}\Z|\AX[A-Za-z0-9_]{0,20}\Z")
_KINDS = st.sampled_from(["sRN", "sRA", "sWN", "sWA", "sMN", "sMA", "sAN", "sEN", "sEA", "sSN"])


@st.composite
def raw_telegrams(draw: st.DrawFn, dialect: Dialect) -> RawTelegram:
    params = draw(
        st.none()
        | (
            st.binary(max_size=60)
            if dialect is Dialect.B
            else st.binary(max_size=60).map(lambda b: b.replace(b"\x02", b"x").replace(b"\x03", b"y"))
        )
    )
    return RawTelegram(draw(_KINDS), draw(_UNMODELLED_NAMES), params)


@st.composite
def channels(draw: st.DrawFn, bits: int) -> Channel:
    n = draw(st.integers(0, 40))
    dtype = np.uint16 if bits == 16 else np.uint8
    values = np.array(draw(st.lists(st.integers(0, (1 << bits) - 1), min_size=n, max_size=n)), dtype=dtype)
    name = draw(st.sampled_from(["DIST1", "DIST2", "RSSI1", "RSSI2", "DIST5", "ANGL1"]))
    return Channel(
        name=name,
        scale=draw(st.floats(width=32, allow_nan=False)),
        offset=draw(st.floats(width=32, allow_nan=False)),
        start_angle_rad=draw(st.integers(-(1 << 31), (1 << 31) - 1)) * RAD_PER_UNIT,
        step_rad=draw(st.integers(0, 0xFFFF)) * RAD_PER_UNIT,
        values=values,
    )


u8, u16, u32 = st.integers(0, 255), st.integers(0, 0xFFFF), st.integers(0, 0xFFFFFFFF)
f32 = st.floats(width=32, allow_nan=False)


@st.composite
def scans(draw: st.DrawFn) -> Scan:
    return Scan(
        version=draw(u16),
        device_number=draw(u16),
        serial_number=draw(u32),
        device_status=(draw(u8), draw(u8)),
        telegram_counter=draw(u16),
        scan_counter=draw(u16),
        time_since_startup_us=draw(u32),
        time_of_transmission_us=draw(u32),
        digital_inputs=(draw(u8), draw(u8)),
        digital_outputs=(draw(u8), draw(u8)),
        layer_angle=draw(st.integers(-32768, 32767)),
        scan_frequency=draw(u32),
        measurement_frequency=draw(u32),
        encoders=tuple(draw(st.lists(st.builds(Encoder, u32, u16), max_size=2))),
        channels_16=draw(st.lists(channels(16), max_size=3)),
        channels_8=draw(st.lists(channels(8), max_size=2)),
        position=draw(st.none() | st.builds(Position, f32, f32, f32, f32, f32, f32, u8, u8)),
        name=draw(st.none() | _TEXT),
        comment=draw(st.none() | _TEXT),
        time_info=draw(st.none() | st.builds(ScanTime, u16, u8, u8, u8, u8, u8, u32)),
        event=draw(
            st.none()
            | st.builds(
                ScanEvent,
                st.text(alphabet=string.ascii_uppercase, min_size=4, max_size=4),
                u32,
                u32,
                st.integers(-(1 << 31), (1 << 31) - 1),
            )
        ),
    )


@st.composite
def any_messages(draw: st.DrawFn, dialect: Dialect) -> Message:
    choice = draw(st.integers(0, 9))
    if choice < 6:
        return draw(field_messages())
    if choice < 8:
        return draw(st.sampled_from([ScanDataEvent, ScanDataReply]))(draw(scans()))
    if choice < 9:
        return ErrorReply(draw(u16))
    return draw(raw_telegrams(dialect))


@SETTINGS
@given(dialects, field_messages())
def test_every_modelled_telegram_round_trips(dialect: Dialect, msg: Message) -> None:
    payload = msg.encode(dialect)
    assert decode_payload(payload, dialect) == msg
    assert decode_payload(payload, dialect).encode(dialect) == payload


def test_every_registered_class_has_a_strategy() -> None:
    assert set(message_classes().values()) == set(_FIELD_CLASSES) | _CUSTOM_CLASSES


_U8, _U16, _U32, _I16, _I32 = (st.integers(*int_range(n, sg)) for n, sg in ((1, 0), (2, 0), (4, 0), (2, 1), (4, 1)))


@st.composite
def scan_times(draw: st.DrawFn) -> ScanTime:
    return ScanTime(draw(_U16), draw(_U8), draw(_U8), draw(_U8), draw(_U8), draw(_U8), draw(_U32))


@st.composite
def field_geometries(draw: st.DrawFn) -> FieldGeometry:
    rect = st.builds(RectangularField, _I32, _U16, _I32, _U32, _U32)
    dyn = st.builds(DynamicField, _I32, _U16, _I32, _U32, _U32, _I16, _U32)
    seg = st.lists(st.builds(SegmentPoint, _U16, _U16, _U16), max_size=5).map(tuple)
    return FieldGeometry(
        draw(st.floats(width=32, allow_nan=False)),
        draw(st.floats(width=32, allow_nan=False)),
        draw(_U32),
        draw(_I32),
        draw(_U8),
        draw(_U8),
        draw(st.none() | seg),
        draw(st.none() | rect),
        draw(st.none() | dyn),
        draw(st.none() | _TEXT),
        draw(st.none() | _TEXT),
    )


@st.composite
def io_messages(draw: st.DrawFn) -> Message:
    time = draw(st.none() | scan_times())
    kind = draw(st.sampled_from(["field", "input", "input_event", "output", "read_field"]))
    if kind == "field":
        return FieldDefinition(draw(st.integers(0, 999)), draw(st.none() | field_geometries()))
    if kind == "read_field":
        return ReadFieldDefinition(draw(st.integers(0, 999)))
    if kind == "output":
        outputs = draw(st.lists(st.tuples(_U8, _U32), max_size=16).map(tuple))
        return OutputStateEvent(draw(_U16), draw(_U32), outputs, time)
    inputs = (draw(_U8), draw(_U8), draw(_U8), draw(_U8))
    cls = InputState if kind == "input" else InputStateEvent
    return cls(draw(_U16), draw(_U32), inputs, time)


@SETTINGS
@given(dialects, io_messages())
def test_field_and_io_telegrams_round_trip(dialect: Dialect, msg: Message) -> None:
    payload = msg.encode(dialect)
    got = decode_payload(payload, dialect)
    assert got == msg and type(got) is type(msg)
    assert got.encode(dialect) == payload


@SETTINGS
@given(dialects, scans(), st.booleans())
def test_scans_round_trip(dialect: Dialect, scan: Scan, event: bool) -> None:
    msg = ScanDataEvent(scan) if event else ScanDataReply(scan)
    payload = msg.encode(dialect)
    got = decode_payload(payload, dialect)
    assert got == msg and type(got) is type(msg)
    assert got.encode(dialect) == payload


@SETTINGS
@given(st.data(), dialects)
def test_raw_and_error_telegrams_round_trip(data: st.DataObject, dialect: Dialect) -> None:
    raw = data.draw(raw_telegrams(dialect))
    assert decode_payload(raw.encode(dialect), dialect) == raw
    err = ErrorReply(data.draw(u16))
    assert decode_payload(err.encode(dialect), dialect) == err


@SETTINGS
@given(st.data(), dialects)
def test_stream_cut_at_random_points(data: st.DataObject, dialect: Dialect) -> None:
    msgs = data.draw(st.lists(any_messages(dialect), min_size=1, max_size=6))
    stream = b"".join(frame(m.encode(dialect), dialect) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=20)))
    bounds = [0, *cuts, len(stream)]
    f = Framer(dialect)
    got: list[Message] = []
    for a, b in itertools.pairwise(bounds):
        f.feed(stream[a:b])
        while (p := f.next_payload()) is not None:
            got.append(decode_payload(p, dialect))
    assert got == msgs
    assert f.buffered == 0 and f.errors == 0


def _garbage(dialect: Dialect) -> st.SearchStrategy[bytes]:
    if dialect is Dialect.A:  # anything without STX (ETX and binary bytes included)
        return st.binary(max_size=40).map(lambda b: b.replace(b"\x02", b"\x03"))
    return st.binary(max_size=40).filter(lambda b: MAGIC not in b)  # may still hold 02 bytes and bogus starts


@SETTINGS
@given(st.data(), dialects)
def test_garbage_between_telegrams_is_skipped(data: st.DataObject, dialect: Dialect) -> None:
    msgs = data.draw(st.lists(any_messages(dialect), min_size=1, max_size=5))
    parts: list[bytes] = []
    for m in msgs:
        parts.append(data.draw(_garbage(dialect)))
        parts.append(frame(m.encode(dialect), dialect))
    parts.append(data.draw(_garbage(dialect).map(lambda b: b.replace(b"\x02", b"\x00"))))
    stream = b"".join(parts)
    chunk = data.draw(st.integers(1, 64))
    f = Framer(dialect)
    got: list[Message] = []
    for i in range(0, len(stream), chunk):
        f.feed(stream[i : i + chunk])
        while True:
            try:
                p = f.next_payload()
            except FramingError:
                continue
            if p is None:
                break
            got.append(decode_payload(p, dialect))
    assert got == msgs


def _feed_all(conn: CoLaConnection, chunks: list[bytes]) -> int:
    """Feed everything; return how many messages decoded. Only CoLaErrors may escape next_message."""
    n = 0
    for c in chunks:
        conn.receive_data(c)
        while True:
            try:
                msg = conn.next_message()
            except CoLaError:
                continue
            if msg is None:
                break
            n += 1
    return n


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300), dialects, st.sampled_from(["client", "device"]), st.integers(1, 50))
def test_fuzz_random_bytes(data: bytes, dialect: Dialect, role: str, chunk: int) -> None:
    conn = CoLaConnection(dialect, "client" if role == "client" else "device")
    _feed_all(conn, [data[i : i + chunk] for i in range(0, len(data), chunk)])
    with contextlib.suppress(TelegramError):
        decode_payload(data, dialect)


_SEED_B = [
    frame(m.encode(Dialect.B), Dialect.B)
    for m in [
        ScanDataEvent(
            Scan(
                channels_16=[Channel("DIST1", 1.0, 0.0, -0.78, 0.0087, np.arange(20, dtype=np.uint16))],
                channels_8=[Channel("RSSI1", 1.0, 0.0, -0.78, 0.0087, np.arange(20, dtype=np.uint8))],
                name="n a m e",
                time_info=ScanTime(1970, 1, 1, 0, 0, 0, 0),
            )
        ),
        ErrorReply(3),
    ]
]


@st.composite
def mutated(draw: st.DrawFn, dialect: Dialect) -> bytes:
    if dialect is Dialect.B:
        base = bytearray(draw(st.sampled_from(_SEED_B)))
    else:
        msg = draw(any_messages(Dialect.A))
        base = bytearray(frame(msg.encode(Dialect.A), Dialect.A))
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.integers(0, 2))
        i = draw(st.integers(0, len(base)))
        if op == 0 and i < len(base):
            base[i] = draw(u8)
        elif op == 1:
            base[i:i] = draw(st.binary(min_size=1, max_size=4))
        elif i < len(base):
            del base[i : i + draw(st.integers(1, 8))]
    return bytes(base)


@settings(max_examples=300, deadline=None)
@given(st.data(), dialects)
def test_fuzz_mutated_telegrams(data: st.DataObject, dialect: Dialect) -> None:
    wire = data.draw(mutated(dialect))
    for role in ("client", "device"):
        conn = CoLaConnection(dialect, "client" if role == "client" else "device")
        _feed_all(conn, [wire])
    payload = wire[8:-1] if dialect is Dialect.B else wire[1:-1]
    try:
        msg = decode_payload(payload, dialect)
    except TelegramError:
        return
    # whatever decodes must encode again without crashing (or refuse with a typed error)
    with contextlib.suppress(TelegramError):
        msg.encode(dialect)
