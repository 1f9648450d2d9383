"""Rules of the client's lost-scan accounting (pure functions, no I/O)."""

from __future__ import annotations

from drivers.lms100.transport import Backoff, DroppingQueue, GapTracker

PERIOD_US = 40_000.0  # 25 Hz


def feed(
    tracker: GapTracker, counters: list[int], times_us: list[int], step: int = 1, period_us: float = PERIOD_US
) -> list[tuple[int, bool, bool]]:
    out = []
    for c, t in zip(counters, times_us, strict=True):
        r = tracker.update(c, t, period_us, step)
        out.append((r.lost, r.duplicate, r.restart))
    return out


def test_consecutive_scans_and_counter_wrap_lose_nothing() -> None:
    g = GapTracker()
    counters = [65534, 65535, 0, 1]
    times = [1_000_000 + 40_000 * i for i in range(4)]
    assert [r[0] for r in feed(g, counters, times)] == [0, 0, 0, 0]


def test_a_gap_counts_the_missing_scans() -> None:
    g = GapTracker()
    assert feed(g, [10, 11, 15], [0, 40_000, 200_000]) == [(0, False, False), (0, False, False), (3, False, False)]


def test_gap_across_the_wrap_and_microsecond_clock_wrap() -> None:
    g = GapTracker()
    t0 = (1 << 32) - 50_000  # the device clock wraps between the two scans
    assert feed(g, [65530, 3], [t0, (t0 + 9 * 40_000) % (1 << 32)])[1] == (8, False, False)


def test_output_rate_step_is_not_a_loss() -> None:
    g = GapTracker()
    assert [r[0] for r in feed(g, [0, 2, 4, 8], [0, 80_000, 160_000, 320_000], step=2)] == [0, 0, 0, 1]


def test_duplicate_telegram() -> None:
    g = GapTracker()
    assert feed(g, [5, 5], [200_000, 200_000])[1] == (0, True, False)


def test_restart_by_clock_or_counter_reset_is_not_a_loss() -> None:
    g = GapTracker()
    assert feed(g, [500, 3], [20_000_000, 120_000])[1] == (0, False, True)  # clock went back
    g = GapTracker()
    assert feed(g, [500, 3], [20_000_000, 20_200_000])[1] == (0, False, True)  # counter went back


def test_long_outage_spanning_whole_counter_wraps() -> None:
    # 50 Hz: the uint16 counter wraps after 21.8 min, well inside the device clock's 35 min half-range
    g = GapTracker()
    missing = 70_000  # more than one wrap of the counter
    c1 = (100 + missing + 1) % 65536
    t1 = 1_000_000 + (missing + 1) * 20_000
    assert feed(g, [100, c1], [1_000_000, t1 % (1 << 32)], period_us=20_000.0)[1] == (missing, False, False)


def test_dropping_queue_keeps_newest_and_reports_drops() -> None:
    q: DroppingQueue[int] = DroppingQueue(2)
    assert [q.put(i) for i in range(4)] == [True, True, False, False]
    assert [q.get(0), q.get(0), q.get(0)] == [2, 3, None]


def test_backoff_grows_to_its_cap_and_stops() -> None:
    assert list(Backoff(initial_s=0.1, factor=2.0, max_s=0.5, max_attempts=5).delays()) == [0.1, 0.2, 0.4, 0.5, 0.5]
