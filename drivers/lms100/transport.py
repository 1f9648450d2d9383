"""Codec-independent pieces of the LMS100 TCP client: statistics, scan-counter gap tracking,
the bounded scan queue and the reconnect back-off schedule.

Nothing here touches a socket or the CoLa codec, so the rules (what counts as a lost scan, what
happens when the consumer is too slow) are stated once and used by :mod:`drivers.lms100.client`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from typing import Generic, TypeVar

log = logging.getLogger("drivers.lms100.client")

COUNTER_MODULO = 1 << 16  # telegram and scan counters are uint16 and wrap
CLOCK_MODULO = 1 << 32  # the device's microsecond clock is uint32 and wraps after ~71.6 min


@dataclass(frozen=True)
class ScannerStats:
    """A snapshot of what the client saw on its link to the scanner.

    ``received``     scans delivered by the device (stream and poll replies).
    ``lost``         scans the device made but we never received, from scan-counter gaps in the
                     stream (including gaps across a reconnect).
    ``gaps``         number of distinct gaps (one gap may hide many lost scans).
    ``duplicates``   streamed scans whose scan counter did not advance (repeated telegram).
    ``device_restarts`` times the device clock went backwards (the device rebooted; counters reset,
                     so the gap across it is unknown and not counted as lost).
    ``reconnects``   successful reconnections (session restored).
    ``connection_losses`` times the link dropped or stalled.
    ``bad_telegrams`` framing or decoding errors on received bytes (the telegram was skipped).
    ``queue_drops``  scans received but discarded because the consumer did not keep up (the
                     oldest queued scan is dropped to make room).
    ``unexpected``   telegrams that matched no pending request and no handled event.
    ``timeouts``     requests that got no answer within the timeout.
    """

    received: int = 0
    lost: int = 0
    gaps: int = 0
    duplicates: int = 0
    device_restarts: int = 0
    reconnects: int = 0
    connection_losses: int = 0
    bad_telegrams: int = 0
    queue_drops: int = 0
    unexpected: int = 0
    timeouts: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class StatsCounter:
    """Thread-safe mutable counters behind :class:`ScannerStats`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values = ScannerStats().as_dict()

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._values[name] += n

    def snapshot(self) -> ScannerStats:
        with self._lock:
            return ScannerStats(**self._values)


@dataclass(frozen=True)
class GapReport:
    """What one streamed scan told us about the sequence."""

    lost: int = 0  # scans missing right before this one
    duplicate: bool = False
    restart: bool = False


class GapTracker:
    """Detects lost scans from the uint16 scan counter of consecutive streamed scans.

    The expected advance per telegram is ``step`` (the LMDscandatacfg output rate: every n-th
    scan is sent). A counter that advanced by ``d`` (modulo 2**16) means ``d // step - 1`` scans
    were lost. Because the counter wraps after 65536 scans (22 min at 50 Hz), a long outage is
    resolved with the device's microsecond clock: the number of whole counter wraps that fit the
    elapsed device time is added. A device clock that runs backwards, or a counter that advanced
    further than the elapsed device time allows, means the device restarted (counters reset);
    that is reported as a restart, not as lost scans, and the sequence starts afresh.
    """

    def __init__(self) -> None:
        self._last_counter: int | None = None
        self._last_time_us: int | None = None

    def reset(self) -> None:
        self._last_counter = None
        self._last_time_us = None

    def update(self, scan_counter: int, time_us: int, scan_period_us: float | None, step: int = 1) -> GapReport:
        last_c, last_t = self._last_counter, self._last_time_us
        self._last_counter, self._last_time_us = scan_counter, time_us
        if last_c is None or last_t is None:
            return GapReport()
        dt = (time_us - last_t) % CLOCK_MODULO
        if dt > CLOCK_MODULO // 2:
            return GapReport(restart=True)  # clock went backwards: device restarted
        delta = (scan_counter - last_c) % COUNTER_MODULO
        if delta == 0 and dt == 0:
            return GapReport(duplicate=True)
        if scan_period_us and scan_period_us > 0:
            expected = dt / scan_period_us  # scans the device clock allows between the two
            if delta > 1.5 * expected + 2:
                # more scans than time allows: the counters were reset (device restart)
                return GapReport(restart=True)
            # whole counter wraps hidden in a long outage, judged from the device clock
            wraps = round((expected - delta) / COUNTER_MODULO)
            if wraps > 0:
                delta += wraps * COUNTER_MODULO
        if delta == 0:
            return GapReport(duplicate=True)
        step = max(1, step)
        missing = max(0, delta // step - 1)
        return GapReport(lost=missing)


T = TypeVar("T")


class DroppingQueue(Generic[T]):
    """A bounded FIFO that never blocks the producer: when full, the oldest item is dropped.

    Every drop is counted (``on_drop`` is called) so an overflow is always reported.
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError("queue size must be >= 1")
        self._items: deque[T] = deque()
        self._maxsize = maxsize
        self._cond = threading.Condition()
        self._closed_error: BaseException | None = None

    def put(self, item: T) -> bool:
        """Append ``item``; return False if the oldest item had to be dropped to make room."""
        with self._cond:
            dropped = False
            if len(self._items) >= self._maxsize:
                self._items.popleft()
                dropped = True
            self._items.append(item)
            self._cond.notify()
            return not dropped

    def get(self, timeout: float | None) -> T | None:
        """The oldest item, or None after ``timeout`` s; raises the error set by :meth:`fail`."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._items:
                if self._closed_error is not None:
                    raise self._closed_error
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._items.popleft()

    def fail(self, error: BaseException | None) -> None:
        """Make waiting and future :meth:`get` calls raise ``error`` once the queue is empty."""
        with self._cond:
            self._closed_error = error
            self._cond.notify_all()

    def clear(self) -> int:
        with self._cond:
            n = len(self._items)
            self._items.clear()
            return n

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


@dataclass(frozen=True)
class Backoff:
    """Exponential back-off between reconnect attempts: initial, initial*factor, ... capped at max."""

    initial_s: float = 0.2
    factor: float = 2.0
    max_s: float = 5.0
    max_attempts: int | None = None  # None: keep trying until the client is closed

    def delays(self) -> Iterator[float]:
        delay = self.initial_s
        attempt = 0
        while self.max_attempts is None or attempt < self.max_attempts:
            yield delay
            attempt += 1
            delay = min(self.max_s, delay * self.factor)
