"""CoLa A / CoLa B framing: chunking, resynchronisation, and typed errors for broken frames."""

from __future__ import annotations

import functools
import operator
import random

import pytest

from drivers.lms100 import Dialect, Framer, FramingError, frame, xor_checksum
from drivers.lms100.errors import CoLaError
from drivers.lms100.framing import MAGIC

# sEN LMDscandata 1 (documented: length 0x11, checksum 0x33) and sFA 3 (0x05, 0x77)
SEN_B = bytes.fromhex("02020202 00000011 73454E20 4C4D447363616E64617461 20 01 33".replace(" ", ""))
SFA_B = bytes.fromhex("0202020200000005734641000377")
# an LMS111 sRA LIDinputstate reply (recorded) whose payload contains 02 02 02 02
LID_PAYLOAD = b"sRA LIDinputstate " + bytes.fromhex("000100000000020202020000")


def _drain(f: Framer) -> tuple[list[bytes], int]:
    """All payloads available now, counting (and stepping over) FramingErrors."""
    out: list[bytes] = []
    errors = 0
    while True:
        try:
            p = f.next_payload()
        except FramingError:
            errors += 1
            continue
        if p is None:
            return out, errors
        out.append(p)


def test_frame_layouts() -> None:
    assert frame(b"sEN LMDscandata \x01", Dialect.B) == SEN_B
    assert frame(b"sFA\x00\x03", Dialect.B) == SFA_B
    assert frame(b"sRN STlms", Dialect.A) == b"\x02sRN STlms\x03"
    with pytest.raises(FramingError, match="STX"):
        frame(b"sRA X \x03", Dialect.A)


def test_xor_checksum_matches_a_plain_fold() -> None:
    rnd = random.Random(7)
    for n in [0, 1, 7, 8, 9, 15, 16, 17, 100, 1191]:
        data = bytes(rnd.randrange(256) for _ in range(n))
        assert xor_checksum(data) == functools.reduce(operator.xor, data, 0)


@pytest.mark.parametrize("dialect", [Dialect.A, Dialect.B])
def test_any_chunking_gives_the_same_payloads(dialect: Dialect) -> None:
    payloads = [b"sRN LMDscandata", b"sAN Run 1", b"sRA SerialNumber 8 18090362", b"sEA LMDscandata 0"]
    if dialect is Dialect.B:
        payloads.append(LID_PAYLOAD)
    stream = b"".join(frame(p, dialect) for p in payloads)
    for size in [1, 2, 3, 5, 8, 13, len(stream)]:
        f = Framer(dialect)
        got: list[bytes] = []
        for i in range(0, len(stream), size):
            f.feed(stream[i : i + size])
            got.extend(_drain(f)[0])
        assert got == payloads, size
        assert f.buffered == 0 and f.skipped_bytes == 0 and f.frames == len(payloads)


def test_b_payload_with_magic_inside_is_not_a_frame_start() -> None:
    f = Framer(Dialect.B)
    f.feed(frame(LID_PAYLOAD, Dialect.B) + SEN_B)
    assert _drain(f) == ([LID_PAYLOAD, SEN_B[8:-1]], 0)


def test_b_bad_checksum_is_dropped_then_reported_and_the_next_frame_survives() -> None:
    bad = SEN_B[:-1] + b"\x34"
    f = Framer(Dialect.B)
    f.feed(bad + SFA_B)
    with pytest.raises(FramingError, match="checksum mismatch: frame says 0x34, payload XOR is 0x33"):
        f.next_payload()
    assert f.next_payload() == b"sFA\x00\x03"
    assert f.next_payload() is None and f.errors == 1


@pytest.mark.parametrize("length", [0xFFFFFFFF, 0x02020202, 1 << 20, 0, 2])
def test_b_absurd_length(length: int) -> None:
    f = Framer(Dialect.B, max_payload=65536)
    f.feed(MAGIC + length.to_bytes(4, "big") + b"sRA" + SFA_B)
    with pytest.raises(FramingError, match="absurd payload length"):
        f.next_payload()
    # a length of 02 02 02 02 forms further magics, each reported; the real frame is found after them
    assert _drain(f)[0] == [b"sFA\x00\x03"]


def test_b_payload_must_start_with_a_command_type() -> None:
    f = Framer(Dialect.B)
    f.feed(MAGIC + b"\x00\x00\x00\x10" + b"xyz" + SEN_B)
    with pytest.raises(FramingError, match="command type"):
        f.next_payload()
    assert _drain(f)[0] == [SEN_B[8:-1]]


def test_b_garbage_is_skipped_and_counted() -> None:
    f = Framer(Dialect.B)
    garbage = b"hello\x00\x03\xff" + b"\x02\x02"  # ends with a partial magic that is not one
    f.feed(garbage)
    assert f.next_payload() is None
    assert f.skipped_bytes == len(garbage) - 2  # the trailing 02 02 is kept: it could start a magic
    f.feed(SEN_B)
    # 02 02 + 02 02 02 02 00 ... looks like a magic with length 0x02020000: absurd, dropped byte by byte
    payloads, errors = _drain(f)
    assert payloads == [SEN_B[8:-1]] and errors >= 1


def test_b_incomplete_frame_waits() -> None:
    f = Framer(Dialect.B)
    for i in range(len(SEN_B) - 1):
        f.feed(SEN_B[i : i + 1])
        assert f.next_payload() is None
    f.feed(SEN_B[-1:])
    assert f.next_payload() == SEN_B[8:-1]


def test_a_garbage_interrupted_and_overlong_frames() -> None:
    f = Framer(Dialect.A, max_payload=64)
    f.feed(b"noise\x03\x03 \x02sRN STlms\x03")
    assert _drain(f) == ([b"sRN STlms"], 0)
    assert f.skipped_bytes == len(b"noise\x03\x03 ")
    # a frame cut short by the next STX: error, then the new frame
    f.feed(b"\x02sRA STlms 7 0\x02sAN Run 1\x03")
    with pytest.raises(FramingError, match="interrupted by a new STX"):
        f.next_payload()
    assert f.next_payload() == b"sAN Run 1"
    # longer than max_payload without ETX
    f.feed(b"\x02sSN LMDscandata " + b"A " * 40 + b"\x03\x02sAN Run 0\x03")
    with pytest.raises(FramingError, match="without ETX"):
        f.next_payload()
    assert _drain(f)[0] == [b"sAN Run 0"]
    # STX followed by something that is no command type
    f.feed(b"\x02hello\x03\x02sFA 3\x03")
    with pytest.raises(FramingError, match="command type"):
        f.next_payload()
    assert _drain(f)[0] == [b"sFA 3"]


def test_a_overlong_detected_while_streaming_in_small_chunks() -> None:
    f = Framer(Dialect.A, max_payload=32)
    data = b"\x02sSN " + b"B" * 100
    errors = 0
    for i in range(0, len(data), 3):
        f.feed(data[i : i + 3])
        errors += _drain(f)[1]
    assert errors == 1
    f.feed(b"\x03\x02sAN Run 1\x03")
    assert _drain(f)[0] == [b"sAN Run 1"]


def test_framer_arguments_and_error_hierarchy() -> None:
    with pytest.raises(ValueError, match="max_payload"):
        Framer(Dialect.B, max_payload=1)
    assert Framer("a").dialect is Dialect.A  # type: ignore[arg-type]
    assert issubclass(FramingError, CoLaError)
