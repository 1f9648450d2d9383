"""Map the scanner's clock (microseconds since start-up) to host time, online.

Each received scan gives one pair: the device time at which the scanner handed the telegram to its
interface (``time_of_transmission_us``) and the host time at which the telegram was read. The host
time is the device time mapped through an unknown offset and a small rate error (crystal drift),
plus a transmission delay that is never negative and jitters (network, scheduling)::

    host = offset + (1 + drift) * device + delay,    delay >= d_min >= 0

The estimator keeps a sliding window of pairs and fits the line that lies below every pair and
is closest to them on average (the lower-envelope estimate of Moon, Skelly and Towsley, 1999):
it is the edge of the pairs' lower convex hull above the window's mean device time. Its error
shrinks like the jitter's scale over the number of pairs, unlike a least-squares line whose rate
error is the jitter's spread over the square root. The mapped time is then the earliest the
telegram could have been sent given everything seen. The constant part of the
delay (d_min) cannot be observed from one clock pair and stays in the offset.

The drift is only estimated once the window spans ``min_span_s`` of device time, and it is
clipped to ``max_drift_ppm``: a rate from a short window is dominated by jitter. A jump of
more than ``reset_threshold_s`` (device reboot, host clock step) restarts the estimate.

The device counter is 32 bits and wraps after about 71.6 minutes; :meth:`ClockSync.unwrap`
extends it to a monotonic 64-bit count.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from service.errors import ServiceError

FloatArray = NDArray[np.float64]

_WRAP = 1 << 32
_HALF = 1 << 31


class ClockSyncError(ServiceError):
    """The clock model was used before it had any data, or was fed something impossible."""


class ClockSync:
    """Online offset-and-drift estimate from device microseconds to host seconds."""

    def __init__(
        self,
        window: int = 512,
        min_span_s: float = 2.0,
        max_drift_ppm: float = 500.0,
        reset_threshold_s: float = 1.0,
        refit_every: int = 16,
    ) -> None:
        if window < 4:
            raise ClockSyncError("window must hold at least 4 pairs")
        self.window = window
        self.min_span_s = min_span_s
        self.max_drift = max_drift_ppm * 1e-6
        self.reset_threshold_s = reset_threshold_s
        self.refit_every = max(1, refit_every)
        self._dev = np.zeros(window)  # device seconds relative to _dev0
        self._host = np.zeros(window)  # host seconds relative to _host0
        self._n = 0  # pairs in the window
        self._head = 0
        self._dev0: int | None = None  # unwrapped device us of the first pair
        self._host0 = 0.0
        self._wraps = 0
        self._last_raw: int | None = None
        self.drift = 0.0
        self._rate_fitted = False
        self._offset = 0.0  # host - host0 at device time dev0
        self.resets = 0
        self.updates = 0

    # -- device counter -------------------------------------------------------------------
    def unwrap(self, device_us: int) -> int:
        """Extend a 32-bit device time to a monotonic count (call in arrival order)."""
        raw = int(device_us)
        if raw < 0 or raw >= _WRAP:
            raise ClockSyncError(f"device time {raw} us is not a 32-bit counter value")
        if self._last_raw is not None:
            if raw < self._last_raw - _HALF:
                self._wraps += 1
            elif raw > self._last_raw + _HALF and self._wraps > 0:
                # a late value from before the last wrap
                return raw + (self._wraps - 1) * _WRAP
        self._last_raw = raw
        return raw + self._wraps * _WRAP

    # -- estimation -----------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        return self._dev0 is not None

    @property
    def n(self) -> int:
        return self._n

    def _clear(self) -> None:
        self._n = 0
        self._head = 0
        self._dev0 = None
        self.drift = 0.0
        self._rate_fitted = False

    def update(self, device_us_unwrapped: int, host_s: float) -> None:
        """Add one (device time, host receive time) pair; ``device_us_unwrapped`` from :meth:`unwrap`."""
        if not np.isfinite(host_s):
            raise ClockSyncError(f"host time {host_s} is not finite")
        if self._dev0 is not None:
            predicted = float(self.to_host(device_us_unwrapped))
            if abs(host_s - predicted) > self.reset_threshold_s:
                self._clear()
                self.resets += 1
        if self._dev0 is None:
            self._dev0 = int(device_us_unwrapped)
            self._host0 = float(host_s)
            self._offset = 0.0
        d = (int(device_us_unwrapped) - self._dev0) * 1e-6
        h = float(host_s) - self._host0
        self._dev[self._head] = d
        self._host[self._head] = h
        self._head = (self._head + 1) % self.window
        self._n = min(self._n + 1, self.window)
        self.updates += 1
        self._fit()

    def _fit(self) -> None:
        d = self._dev[: self._n]
        h = self._host[: self._n]
        # the rate changes slowly: refit it every few pairs; the offset follows every pair
        if self.updates % self.refit_every == 0 or not self._rate_fitted:
            self.drift = 0.0
            self._rate_fitted = False
            if d.size >= 8 and float(d.max() - d.min()) >= self.min_span_s:
                slope = _envelope_slope(d, h)
                self.drift = float(np.clip(slope - 1.0, -self.max_drift, self.max_drift))
                self._rate_fitted = True
        self._offset = float(np.min(h - (1.0 + self.drift) * d))

    # -- mapping --------------------------------------------------------------------------
    def to_host(self, device_us_unwrapped: ArrayLike) -> FloatArray:
        """Host seconds for (unwrapped) device microseconds; floats allowed (beam times)."""
        if self._dev0 is None:
            raise ClockSyncError("clock model has no data yet")
        d = (np.asarray(device_us_unwrapped, dtype=np.float64) - self._dev0) * 1e-6
        return self._host0 + self._offset + (1.0 + self.drift) * d

    @property
    def offset_s(self) -> float:
        """Host time (s) at device time zero."""
        if self._dev0 is None:
            raise ClockSyncError("clock model has no data yet")
        return float(self.to_host(0.0))

    def residual_std(self) -> float:
        """Spread (s) of the window's residual delays: the jitter seen."""
        if self._n == 0:
            return 0.0
        d = self._dev[: self._n]
        h = self._host[: self._n]
        return float(np.std(h - self._offset - (1.0 + self.drift) * d))


def _envelope_slope(x: FloatArray, y: FloatArray) -> float:
    """Slope of the lower-convex-hull edge of the points above their mean x."""
    order = np.argsort(x, kind="stable")
    xs: list[float] = x[order].tolist()
    ys: list[float] = y[order].tolist()
    hull: list[int] = []
    for i in range(len(xs)):  # monotone chain, lower hull; O(n) on sorted x
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            if (xs[b] - xs[a]) * (ys[i] - ys[a]) - (ys[b] - ys[a]) * (xs[i] - xs[a]) <= 0.0:
                hull.pop()
            else:
                break
        hull.append(i)
    if len(hull) < 2:
        return 1.0
    xm = sum(xs) / len(xs)
    for a, b in itertools.pairwise(hull):
        if xs[b] >= xm and xs[b] > xs[a]:
            return (ys[b] - ys[a]) / (xs[b] - xs[a])
    a, b = hull[-2], hull[-1]
    return (ys[b] - ys[a]) / (xs[b] - xs[a]) if xs[b] > xs[a] else 1.0
