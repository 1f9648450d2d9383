"""LMDscandata decoding throughput of the CoLa codec against the LMS100's real-time rate.

Run: ``.venv/bin/python -m bench.bench_lms100_codec``. For a 1081-point scan (0.25 deg, 25 Hz) it
prints decoded telegrams/s and the multiple of the sensor's 25 telegrams/s, for CoLa A and CoLa B,
for DIST1 only and DIST1 + RSSI1: payload decode alone, and framing + decode with the stream fed in
1448-byte chunks (one TCP segment of a 1500-byte MTU), plus encoding. A naive per-token CoLa A
parser (``split`` + ``int(tok, 16)``, DIST1 values only, no header), measured in the same run, is the
baseline of the last column, a ratio that holds up better than absolute rates on a loaded machine.
Goals (issue 2): >= 200x real time for CoLa A, >= 1000x for CoLa B.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from drivers.lms100 import (
    CoLaConnection,
    Dialect,
    Scan,
    ScanDataEvent,
    ScanTime,
    decode_payload,
    frame,
    make_channel,
)

SCAN_RATE_HZ = 25.0
POINTS = 1081
CHUNK = 1448


def make_scan(rssi: bool, seed: int = 0) -> Scan:
    rng = np.random.default_rng(seed)
    dist = rng.integers(500, 20000, POINTS).astype(np.uint16)
    channels = [make_channel("DIST1", dist, -45.0, 0.25)]
    if rssi:
        channels.append(make_channel("RSSI1", rng.integers(0, 255, POINTS).astype(np.uint16), -45.0, 0.25))
    return Scan(
        serial_number=18090362,
        telegram_counter=4711,
        scan_counter=4711,
        time_since_startup_us=1_948_810_585,
        time_of_transmission_us=1_948_813_715,
        digital_outputs=(7, 0),
        scan_frequency=2500,
        measurement_frequency=360,
        channels_16=channels,
        time_info=ScanTime(1970, 1, 1, 2, 55, 34, 889000),
    )


def rate(fn: Callable[[], int], windows: int = 7, window_s: float = 0.2) -> float:
    """Items per CPU second of ``fn`` (which returns how many items it processed).

    Best of ``windows`` windows of ``window_s`` seconds of this process's CPU time
    (``time.process_time``), as ``timeit`` recommends: on a shared machine the best window is the
    closest estimate of what one uncontended core does.
    """
    fn()  # warm-up
    best = 0.0
    for _ in range(windows):
        items = 0
        start = time.process_time()
        while (elapsed := time.process_time() - start) < window_s:
            items += fn()
        best = max(best, items / elapsed)
    return best


def naive_cola_a(payload: bytes) -> int:
    """Baseline: tokenise on spaces and convert every value with int(tok, 16) (no strings handled)."""
    toks = payload.split(b" ")
    n = int(toks[25], 16)  # value count of the first channel in this fixed layout
    values = [int(t, 16) for t in toks[26 : 26 + n]]
    return len(values)


def _decode_once(payload: bytes, dialect: Dialect) -> int:
    decode_payload(payload, dialect)
    return 1


def _encode_once(msg: ScanDataEvent, dialect: Dialect) -> int:
    msg.encode(dialect)
    return 1


def main() -> None:
    print(f"LMS100 real-time rate: {SCAN_RATE_HZ:.0f} telegrams/s of {POINTS} points (0.25 deg, 25 Hz)")
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print("rates: best of 7 windows of 0.2 s process CPU time; last column: ratio to the naive parser")
    payload_naive = ScanDataEvent(make_scan(False)).encode(Dialect.A)
    assert naive_cola_a(payload_naive) == POINTS
    naive = rate(partial(naive_cola_a, payload_naive)) / POINTS
    print(f"{'case':58s} {'telegrams/s':>12s} {'x real time':>12s} {'x naive A':>10s}")

    def show(label: str, per_s: float) -> None:
        print(f"{label:58s} {per_s:12,.0f} {per_s / SCAN_RATE_HZ:11,.0f}x {per_s / naive:9.1f}x")

    show("baseline: naive CoLa A split + int(tok, 16), DIST1", naive)

    for rssi in (False, True):
        scan = make_scan(rssi)
        content = "DIST1+RSSI1" if rssi else "DIST1"
        for dialect in (Dialect.A, Dialect.B):
            msg = ScanDataEvent(scan)
            payload = msg.encode(dialect)
            assert decode_payload(payload, dialect) == msg
            show(
                f"CoLa {dialect.name} decode_payload, {content} ({len(payload)} B)",
                rate(partial(_decode_once, payload, dialect)),
            )
            batch = 50
            stream = frame(payload, dialect) * batch
            chunks = [stream[i : i + CHUNK] for i in range(0, len(stream), CHUNK)]

            def framed(chunks: list[bytes] = chunks, d: Dialect = dialect) -> int:
                conn = CoLaConnection(d, "client")
                n = 0
                for c in chunks:
                    conn.receive_data(c)
                    while conn.next_message() is not None:
                        n += 1
                return n

            assert framed() == batch
            show(f"CoLa {dialect.name} framing+decode, {CHUNK}-byte chunks, {content}", rate(framed))
            show(f"CoLa {dialect.name} encode, {content}", rate(partial(_encode_once, msg, dialect)))

    payload_b = ScanDataEvent(make_scan(True)).encode(Dialect.B)
    stream = frame(payload_b, Dialect.B) * 200
    chunks = [stream[i : i + CHUNK] for i in range(0, len(stream), CHUNK)]

    def frame_only() -> int:
        from drivers.lms100 import Framer

        f = Framer(Dialect.B)
        for c in chunks:
            f.feed(c)
            while f.next_payload() is not None:
                pass
        return len(stream)

    mb_s = rate(frame_only) / 1e6
    print(f"CoLa B framing alone (checksum verified), {CHUNK}-byte chunks: {mb_s:,.0f} MB/s")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
