"""Sweeps: scans plus timestamped motor samples to a 3D cloud.

Each beam gets its own motor angle. A scan's beam ``i`` fires at device time
``time_since_startup + i * dt`` with ``dt = step / (360 deg * scan frequency)`` (the mirror turns
once per scan period; 27.8 us on an LMS1xx in both of its modes). :class:`service.timesync.ClockSync`
maps that to host time, and the shaft angle at that instant is interpolated linearly between
the timestamped motor samples around it (vectorized ``np.interp`` over every beam of the sweep).
Beams outside the motor samples' time span get no angle and are counted, never extrapolated.

Every scan is counted: the 16-bit scan counter's gaps (wrap-aware) are summed and listed, and
the result carries them, so that a lost scan is always visible.

The pure functions here are used both live (:func:`run_sweep`) and offline by
``lrms replay``, which feeds the logged telegrams and motor samples through the same code.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.kinematics import RigCalibration, forward
from service.errors import ServiceError
from service.timesync import ClockSync

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class SweepError(ServiceError):
    """A sweep could not be run or mapped (device fault, no data, bad parameters)."""


# -- records ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanRecord:
    """What the sweep keeps of one scan (device times already unwrapped to 64 bits)."""

    host_ns: int
    """Host time (ns since the epoch) at which the telegram was read."""
    scan_counter: int
    telegram_counter: int
    t0_us: int
    """Device time of beam 0 (time since start-up, unwrapped)."""
    ttx_us: int
    """Device time of transmission (unwrapped)."""
    start_angle_rad: float
    step_rad: float
    scan_frequency_hz: float
    ranges_m: FloatArray

    @property
    def beam_dt_us(self) -> float:
        return beam_interval_us(self.step_rad, self.scan_frequency_hz)


def beam_interval_us(step_rad: float, scan_frequency_hz: float) -> float:
    """Time between two beams: the mirror turns ``step`` in ``step / (2 pi f)`` seconds."""
    if step_rad <= 0 or scan_frequency_hz <= 0:
        raise SweepError(f"bad scan geometry: step {step_rad} rad at {scan_frequency_hz} Hz")
    return step_rad / (2.0 * math.pi * scan_frequency_hz) * 1e6


@dataclass
class MotorTrack:
    """Timestamped motor samples (host ns, output-shaft rad, rad/s), appended in any order."""

    t_ns: list[int] = field(default_factory=list)
    position: list[float] = field(default_factory=list)
    velocity: list[float] = field(default_factory=list)

    def add(self, t_ns: int, position: float, velocity: float = float("nan")) -> None:
        self.t_ns.append(int(t_ns))
        self.position.append(float(position))
        self.velocity.append(float(velocity))

    def __len__(self) -> int:
        return len(self.t_ns)

    def arrays(self) -> tuple[IntArray, FloatArray]:
        """Sorted, de-duplicated times and positions."""
        t = np.asarray(self.t_ns, dtype=np.int64)
        p = np.asarray(self.position, dtype=np.float64)
        t, idx = np.unique(t, return_index=True)
        return t, p[idx]


@dataclass
class GapCounter:
    """Counts scans and the scans missing between them (16-bit wrapping counter)."""

    modulus: int = 1 << 16
    received: int = 0
    missing: int = 0
    duplicates: int = 0
    gaps: list[tuple[int, int]] = field(default_factory=list)
    """(scan counter after which scans are missing, how many)."""
    _last: int | None = None

    def add(self, counter: int) -> int:
        """Record one scan; return how many scans were missing before it."""
        self.received += 1
        if self._last is None:
            self._last = counter
            return 0
        step = (counter - self._last) % self.modulus
        if step == 0:
            self.duplicates += 1
            return 0
        self._last = counter
        lost = step - 1
        if lost and lost < self.modulus // 2:
            self.missing += lost
            self.gaps.append(((counter - step) % self.modulus, lost))
            return lost
        return 0

    def reset_reference(self) -> None:
        """After a reconnect the device may restart its counter: do not call that a gap."""
        self._last = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "received": self.received,
            "missing": self.missing,
            "duplicates": self.duplicates,
            "gaps": [list(g) for g in self.gaps[:100]],
        }


# -- mapping ------------------------------------------------------------------------------


def interpolate_angle(t: ArrayLike, sample_t: ArrayLike, sample_angle: ArrayLike) -> FloatArray:
    """Linear interpolation of a sampled angle at times ``t``; NaN outside the samples' span."""
    tt = np.asarray(t, dtype=np.float64)
    st = np.asarray(sample_t, dtype=np.float64)
    sa = np.asarray(sample_angle, dtype=np.float64)
    if st.ndim != 1 or st.shape != sa.shape or st.size < 2:
        raise SweepError("need at least two motor samples to interpolate the motor angle")
    if np.any(np.diff(st) <= 0):
        raise SweepError("motor sample times must increase strictly")
    out = np.interp(tt, st, sa)
    out[(tt < st[0]) | (tt > st[-1])] = np.nan
    return out


@dataclass(frozen=True)
class MappedSweep:
    """The mapped samples of a sweep (valid beams only), all arrays of length K."""

    points: FloatArray  # (K, 3) world frame
    ranges: FloatArray  # l (m)
    alpha: FloatArray  # rad
    beta: FloatArray  # rad
    scan_index: IntArray
    beam_time_s: FloatArray  # host seconds relative to ``t_ref_ns``
    t_ref_ns: int
    beams_total: int
    beams_no_echo: int
    beams_out_of_range: int
    beams_without_motor: int
    beams_outside_sweep: int

    @property
    def rig_points(self) -> FloatArray:
        return forward(self.ranges, self.alpha, self.beta)

    def stats(self) -> dict[str, int]:
        return {
            "beams_total": self.beams_total,
            "points": int(self.points.shape[0]),
            "beams_no_echo": self.beams_no_echo,
            "beams_out_of_range": self.beams_out_of_range,
            "beams_without_motor_sample": self.beams_without_motor,
            "beams_outside_sweep": self.beams_outside_sweep,
        }


def map_sweep(
    scans: Sequence[ScanRecord],
    motor_t_ns: ArrayLike,
    motor_angle: ArrayLike,
    clock: ClockSync,
    calibration: RigCalibration,
    min_range_m: float = 0.05,
    max_range_m: float = 20.0,
    beta_window: tuple[float, float] | None = None,
) -> MappedSweep:
    """Map scans to world points, each beam with the motor angle at its own instant.

    ``beta_window`` (rad, either order) keeps only beams whose interpolated beta lies inside it
    (the constant-velocity part of a sweep).
    """
    if not scans:
        raise SweepError("no scans to map")
    mt = np.asarray(motor_t_ns, dtype=np.int64)
    ma = np.asarray(motor_angle, dtype=np.float64)
    if mt.size < 2:
        raise SweepError(f"need at least two motor samples, got {mt.size}")
    t_ref = int(mt[0])
    counts = np.fromiter((s.ranges_m.size for s in scans), dtype=np.int64, count=len(scans))
    total = int(counts.sum())
    scan_idx = np.repeat(np.arange(len(scans), dtype=np.int64), counts)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    beam = np.arange(total, dtype=np.int64) - np.repeat(starts, counts)
    ranges = np.concatenate([s.ranges_m for s in scans]).astype(np.float64, copy=False)
    t0 = np.array([s.t0_us for s in scans], dtype=np.float64)
    dt = np.array([s.beam_dt_us for s in scans], dtype=np.float64)
    a0 = np.array([s.start_angle_rad for s in scans], dtype=np.float64)
    da = np.array([s.step_rad for s in scans], dtype=np.float64)
    dev_us = t0[scan_idx] + beam * dt[scan_idx]
    device_angle = a0[scan_idx] + beam * da[scan_idx]
    # host seconds relative to the first motor sample (keeps float64 resolution at ns level)
    host_rel = clock.to_host(dev_us) - t_ref * 1e-9
    motor_rel = (mt - t_ref) * 1e-9
    motor_at_beam = interpolate_angle(host_rel, motor_rel, ma)
    beta = calibration.beta(motor_at_beam)
    no_echo = ranges <= 0.0
    out_of_range = ~no_echo & ((ranges < min_range_m) | (ranges > max_range_m))
    no_motor = np.isnan(beta)
    keep = ~no_echo & ~out_of_range & ~no_motor
    outside = np.zeros(total, dtype=bool)
    if beta_window is not None:
        lo, hi = sorted(beta_window)
        with np.errstate(invalid="ignore"):
            outside = keep & ((beta < lo) | (beta > hi))
        keep &= ~outside
    alpha = calibration.alpha(device_angle[keep])
    pts = calibration.to_world(forward(ranges[keep], alpha, beta[keep], calibration.p))
    return MappedSweep(
        points=pts,
        ranges=ranges[keep],
        alpha=alpha,
        beta=beta[keep],
        scan_index=scan_idx[keep],
        beam_time_s=host_rel[keep],
        t_ref_ns=t_ref,
        beams_total=total,
        beams_no_echo=int(no_echo.sum()),
        beams_out_of_range=int(out_of_range.sum()),
        beams_without_motor=int((no_motor & ~no_echo & ~out_of_range).sum()),
        beams_outside_sweep=int(outside.sum()),
    )


def roi_mask(points: FloatArray, roi_min: ArrayLike | None, roi_max: ArrayLike | None) -> NDArray[np.bool_]:
    """Points inside the axis-aligned box [roi_min, roi_max] (world frame); None = unbounded."""
    keep = np.ones(points.shape[0], dtype=bool)
    if roi_min is not None:
        keep &= np.all(points >= np.asarray(roi_min, dtype=np.float64), axis=1)
    if roi_max is not None:
        keep &= np.all(points <= np.asarray(roi_max, dtype=np.float64), axis=1)
    return keep
