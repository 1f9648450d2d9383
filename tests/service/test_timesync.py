"""Clock mapping against synthetic clocks: offset, drift, one-sided jitter, counter wrap, resets."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from service.timesync import ClockSync, ClockSyncError

DRIFT = 80e-6  # the device crystal runs 80 ppm slow against the host
D_MIN = 0.4e-3  # the smallest transmission delay (s)


def _pairs(
    n: int, rng: np.random.Generator, start_us: int = (1 << 32) - 5_000_000, period_us: int = 20_000
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Device transmission times (raw uint32, wrapping) and host receive times."""
    dev = start_us + period_us * np.arange(n, dtype=np.int64)
    jitter = rng.exponential(1.5e-3, n)  # transmission/scheduling delay, one-sided
    spikes = rng.random(n) < 0.02  # occasional long stalls (GC, busy host)
    jitter[spikes] += rng.uniform(5e-3, 40e-3, int(spikes.sum()))
    t_rel = (dev - start_us) * 1e-6
    true_send = 1_700_000_000.0 + (1 + DRIFT) * t_rel
    return dev % (1 << 32), np.asarray(true_send, dtype=np.float64), true_send + D_MIN + jitter


def test_offset_drift_and_wrap_with_jitter() -> None:
    rng = np.random.default_rng(1)
    raw, true_send, host = _pairs(3000, rng)  # 60 s at 50 Hz, crossing the 32-bit wrap
    assert raw.min() < 1_000_000 < 4_000_000_000 < raw.max()  # the counter does wrap
    sync = ClockSync()
    errs = []
    for i, (r, h) in enumerate(zip(raw, host, strict=True)):
        u = sync.unwrap(int(r))
        sync.update(u, float(h))
        if i >= 600:  # after 12 s of data
            errs.append(float(sync.to_host(u)) - (true_send[i] + D_MIN))
    errs_a = np.abs(np.asarray(errs))
    # mapped times sit on the minimum-delay envelope: far inside the 1.5 ms mean jitter
    assert errs_a.max() < 150e-6, errs_a.max()
    assert abs(sync.drift - DRIFT) < 5e-6
    # the raw receive times are off by the jitter: the model must beat them by a wide margin
    raw_err = np.abs(host[600:] - (true_send[600:] + D_MIN))
    assert np.median(errs_a) < 0.1 * np.median(raw_err)


def test_beam_times_between_scans_are_interpolated_on_the_model() -> None:
    rng = np.random.default_rng(2)
    raw, _true_send, host = _pairs(1000, rng, start_us=123_456)
    sync = ClockSync()
    for r, h in zip(raw, host, strict=True):
        sync.update(sync.unwrap(int(r)), float(h))
    beam_us = raw[-1] - 15_000 + 27.78 * np.arange(541)  # floats: beam instants of one scan
    mapped = sync.to_host(beam_us)
    expected = 1_700_000_000.0 + (1 + DRIFT) * (beam_us - 123_456) * 1e-6 + D_MIN
    assert mapped.shape == (541,)
    assert np.max(np.abs(mapped - expected)) < 150e-6


def test_short_window_does_not_invent_drift() -> None:
    sync = ClockSync(min_span_s=2.0)
    rng = np.random.default_rng(3)
    raw, _, host = _pairs(20, rng)  # 0.4 s only
    for r, h in zip(raw, host, strict=True):
        sync.update(sync.unwrap(int(r)), float(h))
    assert sync.drift == 0.0


def test_jump_restarts_the_model() -> None:
    sync = ClockSync()
    for i in range(300):
        sync.update(sync.unwrap(1_000_000 + 20_000 * i), 50.0 + 0.02 * i)
    assert sync.resets == 0
    # the device rebooted: its counter starts again near zero while host time runs on
    u = sync.unwrap(1000)
    sync.update(u, 56.1)
    assert sync.resets == 1 and sync.n == 1
    assert float(sync.to_host(u + 20_000)) == pytest.approx(56.12, abs=1e-9)


def test_errors() -> None:
    sync = ClockSync()
    with pytest.raises(ClockSyncError, match="no data"):
        sync.to_host(0)
    with pytest.raises(ClockSyncError, match="32-bit"):
        sync.unwrap(1 << 32)
    with pytest.raises(ClockSyncError, match="finite"):
        sync.update(0, float("nan"))
    with pytest.raises(ClockSyncError):
        ClockSync(window=2)
