"""Sweeps: scans plus timestamped motor samples to a 3D cloud.

Each beam gets its own motor angle. A scan's beam ``i`` fires at device time
``time_since_startup + i * dt`` with ``dt = step / (360 deg * scan frequency)`` (the mirror turns
once per scan period; 27.8 us on an LMS1xx in both of its modes). :class:`service.timesync.ClockSync`
maps that to host time, and the shaft angle at that instant is interpolated linearly between
the timestamped motor samples around it (vectorized ``np.interp`` over every beam of the sweep).
Beams outside the motor samples' time span get no angle and are counted, never extrapolated.

A motor sample's time is the drive's own latch time when the drive reports one (CANopen 0x1013
mapped next to the position: ``drive_stamp_us``), mapped to host time by a second
:class:`~service.timesync.ClockSync` fed with (drive stamp, host receive time) pairs
(:meth:`SweepRecorder.motor_sample_times`); otherwise it is the host time of the SYNC that
triggered the sample, which is late-latched by however long the drive took to process that
SYNC (milliseconds on a loaded host with a simulated drive). The result says which
(``motor_time_source``).

Every scan is counted: the 16-bit scan counter's gaps (wrap-aware) are summed and listed, and
the result carries them, so that a lost scan is always visible.

The pure functions here are used both live (:func:`run_sweep`) and offline by
``lrms replay``, which feeds the logged telegrams and motor samples through the same code.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.kinematics import RigCalibration, RigModel
from service.errors import ServiceError
from service.mcaplog import foxglove_time
from service.models import APPROACH_SPEED_DEG_S, run_up_deg, step_dwell_s
from service.timesync import ClockSync

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
IntArray = NDArray[np.int64]


class SweepError(ServiceError):
    """A sweep could not be run or mapped (device fault, no data, bad parameters)."""


class TravelLimitError(SweepError):
    """A sweep would command the drive beyond the rig's travel limits, maximum speed or
    acceleration; raised before the command is sent."""


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

    def extend(self, t_ns: ArrayLike, position: ArrayLike, velocity: ArrayLike) -> None:
        """A batch of samples (equal-length arrays)."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        p = np.asarray(position, dtype=np.float64).reshape(-1)
        v = np.asarray(velocity, dtype=np.float64).reshape(-1)
        if not t.shape == p.shape == v.shape:
            raise ValueError(f"motor sample arrays differ in length: {t.shape}, {p.shape}, {v.shape}")
        self.t_ns.extend(t.tolist())
        self.position.extend(p.tolist())
        self.velocity.extend(v.tolist())

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


def interpolate_speed(t: ArrayLike, sample_t: ArrayLike, sample_angle: ArrayLike) -> FloatArray:
    """The motor speed (rad/s) at times ``t``: the slope of the sampled angle's segment around each
    time, i.e. the derivative of :func:`interpolate_angle`'s polyline. NaN outside the samples' span.

    Its sign is the direction of motion (the rig model's backlash term); at rest between two equal
    samples it is 0, and the model applies no backlash there.
    """
    tt = np.asarray(t, dtype=np.float64)
    st = np.asarray(sample_t, dtype=np.float64)
    sa = np.asarray(sample_angle, dtype=np.float64)
    if st.ndim != 1 or st.shape != sa.shape or st.size < 2:
        raise SweepError("need at least two motor samples to interpolate the motor speed")
    if np.any(np.diff(st) <= 0):
        raise SweepError("motor sample times must increase strictly")
    slope = np.diff(sa) / np.diff(st)
    seg = np.clip(np.searchsorted(st, tt, side="right") - 1, 0, st.size - 2)
    out = slope[seg]
    out[(tt < st[0]) | (tt > st[-1]) | np.isnan(tt)] = np.nan
    return np.asarray(out, dtype=np.float64)


def motor_timing_jitter(
    t_s: ArrayLike,
    angle: ArrayLike,
    window: tuple[float, float] | None,
    span_s: tuple[float, float] | None = None,
    min_samples: int = 20,
) -> float | None:
    """The scatter (s) of the motor samples' time stamps about a constant-speed motion, measured.

    A sample's time stamp is the host time of the SYNC it answers (the drive latched its
    position when the SYNC reached it), or the drive's own latch time mapped to host time. Any
    error in it that varies from sample to
    sample (a busy host, a queue on the link) shows as scatter of angle about the straight line
    of a constant-speed sweep, ``delta_angle = speed x delta_t``. The samples whose angle lies
    inside ``window`` (motor rad, the constant-velocity part) and, given, inside the time span ``span_s``
    (that of the sweep's beams: the approach may cross the window too) are fitted with a quadratic in time
    (a slow change of speed is motion, not jitter) and the residuals' standard deviation over
    the fitted speed is returned. A real velocity ripple counts here too, which errs on the
    safe side. ``None`` when there is no such part (step-and-scan, under ``min_samples``, at rest).
    """
    if window is None:
        return None
    t = np.asarray(t_s, dtype=np.float64)
    a = np.asarray(angle, dtype=np.float64)
    lo, hi = sorted(window)
    inside = np.isfinite(a) & (a >= lo) & (a <= hi)
    if span_s is not None:
        inside &= (t >= span_s[0]) & (t <= span_s[1])
    if np.count_nonzero(inside) < max(min_samples, 4):
        return None
    tt, aa = t[inside], a[inside]
    tc = tt - tt.mean()
    coef = np.polynomial.polynomial.polyfit(tc, aa, 2)
    speed = abs(float(coef[1]))
    if speed < 1e-6:  # rad/s: at rest, no timing can be read from the angle
        return None
    resid = aa - np.polynomial.polynomial.polyval(tc, coef)
    return float(np.std(resid, ddof=3) / speed)


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
    #: the motor samples' timing scatter in the sweep, measured (:func:`motor_timing_jitter`); None: not measurable
    motor_timing_jitter_s: float | None = None
    #: the motor speed at each beam (rad/s, :func:`interpolate_speed`); None: not known
    motor_speed: FloatArray | None = None
    #: the rig model the points were mapped with (``RigCalibration.rig``)
    rig: RigModel = field(default_factory=RigModel)

    @property
    def rig_points(self) -> FloatArray:
        """The points in the rig frame (the same model as :attr:`points`, without ``world_from_rig``)."""
        return self.rig.forward(self.ranges, self.alpha, self.beta, self.motor_speed)

    def beam_rays(self, keep: NDArray[np.bool_] | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Rig-frame beam origins and unit directions and the geometric ranges (``k0 + (1 + k1) l``)
        of the beams (``keep``: a mask or index of them), by the model the points were mapped with:
        ``origins + ranges * dirs`` are :attr:`rig_points`."""
        sel = slice(None) if keep is None else keep
        speed = None if self.motor_speed is None else self.motor_speed[sel]
        o, d = self.rig.rays(self.alpha[sel], self.beta[sel], speed)
        return o, d, self.rig.geometric_range(self.ranges[sel])

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

    The points come from ``calibration.rig`` (:class:`lrms.kinematics.RigModel`: range offset and
    scale, optical centre p and q, the scan plane's tilts, the angular zeros, motor scale, backlash
    and the scan/motor time offset), vectorised over every beam; the backlash and time offset act
    through the motor speed at each beam (:func:`interpolate_speed`, the slope of the motor
    samples around it: its sign is the direction of motion). The nominal model is Eq. 1 bit for
    bit. ``beta_window`` (rad, either order) keeps only beams whose interpolated beta (the
    encoder's plane angle, before the model's corrections) lies inside it (the constant-velocity
    part of a sweep).
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
    ranges_all = np.concatenate([s.ranges_m for s in scans]).astype(np.float64, copy=False)
    # only beams with a usable echo go through timing, interpolation and Eq. 1
    no_echo = ranges_all <= 0.0
    out_of_range = ~no_echo & ((ranges_all < min_range_m) | (ranges_all > max_range_m))
    echo = np.flatnonzero(~no_echo & ~out_of_range)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    scan_idx = np.searchsorted(starts, echo, side="right") - 1
    beam = echo - starts[scan_idx]
    ranges = ranges_all[echo]
    t0 = np.array([s.t0_us for s in scans], dtype=np.float64)
    dt = np.array([s.beam_dt_us for s in scans], dtype=np.float64)
    a0 = np.array([s.start_angle_rad for s in scans], dtype=np.float64)
    da = np.array([s.step_rad for s in scans], dtype=np.float64)
    dev_us = t0[scan_idx] + beam * dt[scan_idx]
    # host seconds relative to the first motor sample (keeps float64 resolution at ns level)
    host_rel = clock.to_host(dev_us) - t_ref * 1e-9
    motor_rel = (mt - t_ref) * 1e-9
    beta = calibration.beta(interpolate_angle(host_rel, motor_rel, ma))
    no_motor = np.isnan(beta)
    keep = ~no_motor
    outside = np.zeros(beta.shape, dtype=bool)
    if beta_window is not None:
        lo, hi = sorted(beta_window)
        with np.errstate(invalid="ignore"):
            outside = keep & ((beta < lo) | (beta > hi))
        keep &= ~outside
    alpha = calibration.alpha(a0[scan_idx[keep]] + beam[keep] * da[scan_idx[keep]])
    speed = interpolate_speed(host_rel[keep], motor_rel, ma)
    rig = calibration.rig
    pts = rig.forward(ranges[keep], alpha, beta[keep], speed)
    if not np.array_equal(calibration.world_from_rig, np.eye(4)):
        pts = calibration.to_world(pts)
    return MappedSweep(
        points=pts,
        ranges=ranges[keep],
        alpha=alpha,
        beta=beta[keep],
        scan_index=scan_idx[keep].astype(np.int64),
        beam_time_s=host_rel[keep],
        t_ref_ns=t_ref,
        beams_total=total,
        beams_no_echo=int(no_echo.sum()),
        beams_out_of_range=int(out_of_range.sum()),
        beams_without_motor=int(no_motor.sum()),
        beams_outside_sweep=int(outside.sum()),
        motor_timing_jitter_s=motor_timing_jitter(
            motor_rel,
            ma,
            None
            if beta_window is None
            else (float(calibration.motor_angle(beta_window[0])), float(calibration.motor_angle(beta_window[1]))),
            (float(host_rel[keep].min()), float(host_rel[keep].max())) if np.any(keep) else None,
        ),
        motor_speed=speed,
        rig=rig,
    )


def roi_mask(points: FloatArray, roi_min: ArrayLike | None, roi_max: ArrayLike | None) -> NDArray[np.bool_]:
    """Points inside the axis-aligned box [roi_min, roi_max] (world frame); None = unbounded."""
    keep = np.ones(points.shape[0], dtype=bool)
    if roi_min is not None:
        keep &= np.all(points >= np.asarray(roi_min, dtype=np.float64), axis=1)
    if roi_max is not None:
        keep &= np.all(points <= np.asarray(roi_max, dtype=np.float64), axis=1)
    return keep


# -- recording ----------------------------------------------------------------------------


class SweepRecorder:
    """Turns received scans and motor samples into records, feeding the clock model and the log.

    Live sweeps and ``lrms replay`` both go through this class with the same inputs (host times
    as integer nanoseconds), so a replay reproduces the live result exactly.
    """

    def __init__(self, calibration: RigCalibration, log: Any | None = None, dialect: str = "b") -> None:
        self.calibration = calibration
        self.log = log
        self.dialect = dialect
        self.clock = ClockSync()
        #: the drive's latch clock (0x1013, us) to host time, from (stamp, receive time) pairs
        self.motor_clock = ClockSync(window=2048, refit_every=64)
        self.gaps = GapCounter()
        self.scans: list[ScanRecord] = []
        self.motor = MotorTrack()
        #: motor samples timed by the drive's latch time / by the SYNC time (live sweeps)
        self.motor_samples_drive_timed = 0
        self.motor_samples_sync_timed = 0
        #: the time source a replayed log's live sweep reported (its ``motor_time_source`` event)
        self.logged_motor_time_source: str | None = None
        self.scan_frequency_hz: float | None = None

    def add_scan(self, scan: Any, host_ns: int, raw: bytes | None = None) -> ScanRecord:
        """One decoded scan (``drivers.lms100.Scan``) read at host time ``host_ns``."""
        u0 = self.clock.unwrap(int(scan.time_since_startup_us))
        utx = self.clock.unwrap(int(scan.time_of_transmission_us))
        self.clock.update(utx, host_ns * 1e-9)
        self.gaps.add(int(scan.scan_counter))
        ch = scan.dist1
        rec = ScanRecord(
            host_ns=int(host_ns),
            scan_counter=int(scan.scan_counter),
            telegram_counter=int(scan.telegram_counter),
            t0_us=u0,
            ttx_us=utx,
            start_angle_rad=float(ch.start_angle_rad),
            step_rad=float(ch.step_rad),
            scan_frequency_hz=float(scan.scan_frequency_hz),
            ranges_m=np.asarray(scan.ranges_m, dtype=np.float64),
        )
        self.scan_frequency_hz = rec.scan_frequency_hz
        self.scans.append(rec)
        if self.log is not None:
            if raw is not None:
                self.log.log_telegram(host_ns, raw, self.dialect)
            n = rec.ranges_m.size
            a0 = float(self.calibration.alpha(rec.start_angle_rad))
            a1 = float(self.calibration.alpha(rec.start_angle_rad + (n - 1) * rec.step_rad))
            self.log.log_scan(host_ns, rec.ranges_m, a0, a1)
            if len(self.motor) >= 2:
                beta = float(self.calibration.beta(self.motor.position[-1]))
                self.log.log_plane_pose(host_ns, beta, self.calibration.p)
        return rec

    def motor_sample_times(
        self, t_sync_s: ArrayLike, drive_stamp_us: ArrayLike | None = None, t_rx_s: ArrayLike | None = None
    ) -> FloatArray:
        """Host seconds of a batch of motor samples (in arrival order): where a sample has a
        drive time stamp (``drive_stamp_us`` >= 0, raw 32-bit us, with its host receive time
        ``t_rx_s``), that stamp mapped to host time by :attr:`motor_clock` after every pair of
        the batch has fed it; elsewhere the SYNC time ``t_sync_s``."""
        t = np.array(t_sync_s, dtype=np.float64).reshape(-1)
        if drive_stamp_us is None:
            self.motor_samples_sync_timed += t.size
            return t
        stamps = np.asarray(drive_stamp_us, dtype=np.int64).reshape(-1)
        rx = np.asarray(t_rx_s, dtype=np.float64).reshape(-1)
        if not t.shape == stamps.shape == rx.shape:
            raise SweepError(f"motor sample arrays differ in length: {t.shape}, {stamps.shape}, {rx.shape}")
        stamped = (stamps >= 0) & np.isfinite(rx)
        idx = np.flatnonzero(stamped)
        if idx.size:
            clock = self.motor_clock
            unwrapped = np.array([clock.unwrap(int(u)) for u in stamps[idx]], dtype=np.int64)
            for u, h in zip(unwrapped.tolist(), rx[idx].tolist(), strict=True):
                clock.update(u, h)
            t[idx] = clock.to_host(unwrapped)
        self.motor_samples_drive_timed += idx.size
        self.motor_samples_sync_timed += t.size - idx.size
        return t

    @property
    def motor_time_source(self) -> str | None:
        """``"drive"`` (every motor sample timed by the drive's latch time), ``"sync"`` (by the
        SYNC time; a Modbus drive's poll time), ``"mixed"``; in a replay (the log's samples are
        already mapped) the live sweep's, from its ``motor_time_source`` event; else None."""
        d, s = self.motor_samples_drive_timed, self.motor_samples_sync_timed
        if d and s:
            return "mixed"
        return "drive" if d else "sync" if s else self.logged_motor_time_source

    def add_motor(self, t_ns: int, position: float, velocity: float) -> None:
        self.motor.add(t_ns, position, velocity)
        if self.log is not None:
            self.log.log_motor(t_ns, position, velocity)

    def add_motor_batch(self, t_ns: ArrayLike, position: ArrayLike, velocity: ArrayLike) -> None:
        """Many motor samples at once (host ns, rad, rad/s); each is logged as its own JointStates."""
        n = len(self.motor)
        self.motor.extend(t_ns, position, velocity)
        if self.log is not None:
            log_motor = self.log.log_motor
            for t, p, v in zip(self.motor.t_ns[n:], self.motor.position[n:], self.motor.velocity[n:], strict=True):
                log_motor(t, p, v)

    def scans_between(self, t_start_ns: int, t_end_ns: int | None) -> list[ScanRecord]:
        """Scans whose first beam falls at or after ``t_start_ns`` (and, given, at or before ``t_end_ns``)."""
        if not self.scans:
            return []
        t0 = np.array([s.t0_us for s in self.scans], dtype=np.float64)
        host = self.clock.to_host(t0)
        keep = host >= t_start_ns * 1e-9
        if t_end_ns is not None:
            keep &= host <= t_end_ns * 1e-9
        return [s for s, k in zip(self.scans, keep, strict=True) if k]

    def map(
        self,
        t_start_ns: int,
        t_end_ns: int | None,
        beta_window: tuple[float, float] | None,
        min_range_m: float,
        max_range_m: float,
    ) -> MappedSweep:
        scans = self.scans_between(t_start_ns, t_end_ns)
        if not scans:
            raise SweepError("no scans were received during the sweep")
        mt, mp = self.motor.arrays()
        return map_sweep(scans, mt, mp, self.clock, self.calibration, min_range_m, max_range_m, beta_window)


# -- running a sweep on devices -----------------------------------------------------------


@dataclass(frozen=True)
class SweepPlan:
    """A resolved sweep in radians (beta, scan-plane angle) with the motion that realises it."""

    start: float
    stop: float
    speed: float
    acceleration: float
    mode: str = "constant"
    step: float = math.radians(1.0)
    scans_per_step: int = 1
    approach_speed: float = math.radians(APPROACH_SPEED_DEG_S)

    @property
    def direction(self) -> float:
        return 1.0 if self.stop > self.start else -1.0

    @property
    def run_up(self) -> float:
        """Extra travel before ``start`` and after ``stop`` to be at constant speed over the window."""
        return math.radians(run_up_deg(math.degrees(self.speed), math.degrees(self.acceleration)))

    def beta_window(self) -> tuple[float, float]:
        return (min(self.start, self.stop), max(self.start, self.stop))

    def step_targets(self) -> FloatArray:
        n = math.floor(abs(self.stop - self.start) / self.step + 1e-9) + 1
        return np.asarray(self.start + self.direction * self.step * np.arange(n), dtype=np.float64)

    def approach_target(self) -> float:
        """Beta of the approach's end: ``start`` less the run-up (constant mode) or ``start``."""
        return self.start - self.direction * (self.run_up if self.mode == "constant" else 0.0)

    def targets(self) -> list[tuple[float, float]]:
        """Every move of the sweep in order, as (beta, speed): the approach, then the sweep to
        ``stop`` plus the run-up, or to each step."""
        moves = [(self.approach_target(), self.approach_speed)]
        if self.mode == "constant":
            moves.append((self.stop + self.direction * self.run_up, self.speed))
        else:
            moves += [(float(t), self.speed) for t in self.step_targets()]
        return moves


@dataclass(frozen=True)
class MotionLimits:
    """What the drive may be commanded: shaft angles (drive frame, rad), speed (rad/s) and
    acceleration (rad/s^2) at the output shaft (the rig's ``[motor]`` limits)."""

    min_angle: float
    max_angle: float
    max_speed: float
    max_acceleration: float

    def check(self, motor_angle: float, speed: float, acceleration: float) -> None:
        """Raise :class:`TravelLimitError` unless the move is within the limits."""
        if not math.isfinite(motor_angle) or not self.min_angle <= motor_angle <= self.max_angle:
            raise TravelLimitError(
                f"refusing to move the shaft to {math.degrees(motor_angle):.3f} deg: outside the travel limits "
                f"[{math.degrees(self.min_angle):g}, {math.degrees(self.max_angle):g}] deg"
            )
        if not 0.0 < speed <= self.max_speed:
            raise TravelLimitError(
                f"refusing to move at {math.degrees(speed):g} deg/s: the motor's maximum is "
                f"{math.degrees(self.max_speed):g} deg/s"
            )
        if not 0.0 < acceleration <= self.max_acceleration:
            raise TravelLimitError(
                f"refusing to accelerate at {math.degrees(acceleration):g} deg/s^2: the motor's maximum is "
                f"{math.degrees(self.max_acceleration):g} deg/s^2"
            )

    def check_plan(self, plan: SweepPlan, calibration: RigCalibration) -> None:
        """Every move of ``plan`` (:meth:`SweepPlan.targets`), before any is commanded."""
        for beta, speed in plan.targets():
            self.check(float(calibration.motor_angle(beta)), speed, plan.acceleration)


class _Motion(threading.Thread):
    def __init__(self, fn: Callable[[], None]) -> None:
        super().__init__(name="lrms-sweep-motion", daemon=True)
        self.fn = fn
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self.fn()
        except BaseException as exc:  # handed to the sweep loop
            self.error = exc


@dataclass
class SweepOutcome:
    recorder: SweepRecorder
    t_start_ns: int
    t_end_ns: int
    plan: SweepPlan
    scanner_stats: dict[str, Any]
    duration_s: float


def stop_motor(motor: Any) -> str | None:
    """Quick-stop the motor after a failed or cancelled sweep; if that fails, disable it.

    Returns ``None`` when the quick stop was accepted, else what went wrong (both errors when
    the disable failed too), which the caller puts into the ``sweep_aborted`` event and the
    failure reason: a motor that may still be turning is never reported as stopped.
    """
    try:
        motor.quick_stop()
        return None
    except Exception as exc:  # any driver or transport error: the stop is not confirmed
        quick = f"{type(exc).__name__}: {exc}"
        log.error("quick stop after the aborted sweep failed: %s; disabling the motor", quick)
    try:
        motor.disable()
    except Exception as exc:
        log.error("disabling the motor failed too: %s: %s", type(exc).__name__, exc)
        return f"motor stop failed: quick stop: {quick}; disable: {type(exc).__name__}: {exc}"
    return f"motor quick stop failed ({quick}); the motor was disabled instead"


def run_sweep(
    scanner: Any,
    motor: Any,
    recorder: SweepRecorder,
    plan: SweepPlan,
    *,
    clock_ns: Callable[[float], int],
    read_scan: Callable[[float], tuple[Any, float, bytes | None]],
    progress: Callable[[float, str], None] | None = None,
    cancelled: Callable[[], bool] | None = None,
    on_event: Callable[[str, dict[str, Any]], None] | None = None,
    scan_silence_s: float = 3.0,
    motion_timeout_s: float | None = None,
    max_duration_s: float | None = None,
    limits: MotionLimits | None = None,
) -> SweepOutcome:
    """Run one sweep: approach, then sweep (constant speed or step-and-scan), recording all along.

    ``read_scan(timeout)`` returns ``(scan, host monotonic s, raw telegram)`` or raises the
    driver's timeout; ``clock_ns(t_monotonic)`` turns host seconds into the log's integer ns (``round(t * 1e9)``
    plus a fixed offset: motor sample batches are converted with ``clock_ns(0.0)`` as that offset).
    The motor runs on its own thread; this loop reads scans, watches for faults, cancellation
    and scanner silence. On *any* error the motor is stopped (quick stop) before the error is
    raised; the caller records the reason. A sweep still running ``max_duration_s`` after it began
    (approach included) fails with ``exceeded max duration N s`` (checked at least every 0.1 s).
    With ``limits``, every move of the plan is checked before the motor is enabled, and each one
    again before it is commanded (:class:`TravelLimitError`).
    """
    from drivers.errors import DeviceTimeoutError

    cal = recorder.calibration
    if limits is not None:
        limits.check_plan(plan, cal)
    report = progress or (lambda f, m: None)
    is_cancelled = cancelled or (lambda: False)
    emit = on_event or (lambda kind, data: None)
    abort = threading.Event()
    t_begin = time.monotonic()
    sample_cursor = [t_begin - 0.5]
    phase = ["approach"]
    sweep_t = [0, 0]  # start and end, ns

    def pull_motor() -> None:
        arr = motor.sample_arrays_since(sample_cursor[0])
        if len(arr.t_host_s):
            sample_cursor[0] = float(arr.t_host_s[-1])
            t_s = recorder.motor_sample_times(
                arr.t_host_s, getattr(arr, "drive_stamp_us", None), getattr(arr, "t_rx_host_s", None)
            )
            t_ns = np.rint(t_s * 1e9).astype(np.int64) + clock_ns(0.0)
            recorder.add_motor_batch(t_ns, arr.position_rad, arr.velocity_rad_s)

    def move(beta: float, speed: float) -> None:
        target = float(cal.motor_angle(beta))
        if limits is not None:
            limits.check(target, speed, plan.acceleration)
        motor.move_to(target, velocity=speed, acceleration=plan.acceleration, wait=True, timeout=motion_timeout_s)

    def motion() -> None:
        move(plan.approach_target(), plan.approach_speed)
        if abort.is_set():
            return
        phase[0] = "sweep"
        sweep_t[0] = clock_ns(time.monotonic())
        emit("sweep_start", {"time": foxglove_time(sweep_t[0])})
        if plan.mode == "constant":
            move(plan.stop + plan.direction * plan.run_up, plan.speed)
        else:
            for target in plan.step_targets():
                if abort.is_set():
                    return
                move(float(target), plan.speed)
                if abort.wait(step_dwell_s(plan.scans_per_step, recorder.scan_frequency_hz or 25.0)):
                    return
        sweep_t[1] = clock_ns(time.monotonic())
        emit("sweep_end", {"time": foxglove_time(sweep_t[1])})
        phase[0] = "run-out"

    cover_until = [math.nan]  # host s: the last beam of the first scan seen to begin after the sweep's end

    def end_covered() -> bool:
        """The scans reach past the sweep's end (a scan whose first beam is later has come, so every
        scan of the sweep is in), and the motor samples reach past that scan's last beam (so every
        beam of the sweep has samples on both sides). Pulls the motor samples that have arrived.
        The scan is fixed once found: measured against the newest scan instead, the motor samples
        chase a target that moves on with every scan (a scan arrives just after its last beam,
        before the sample that follows it) and the run-out can last until its time limit."""
        pull_motor()
        if not recorder.scans or not len(recorder.motor) or not recorder.clock.ready:
            return False
        if math.isnan(cover_until[0]):
            last = recorder.scans[-1]
            first_beam, last_beam = recorder.clock.to_host(
                np.array([last.t0_us, last.t0_us + last.ranges_m.size * last.beam_dt_us], dtype=np.float64)
            )
            if not first_beam * 1e9 > sweep_t[1]:
                return False
            cover_until[0] = float(last_beam)
        return bool(recorder.motor.t_ns[-1] * 1e-9 >= cover_until[0])

    mover = _Motion(motion)
    try:
        if not getattr(scanner, "streaming", False):
            scanner.start_streaming()
        motor.enable()
        mover.start()
        last_scan = time.monotonic()
        span = abs(plan.stop - plan.start)
        tail_until: float | None = None
        tail_limit = math.inf
        while True:
            if is_cancelled():
                from service.jobs import Cancelled

                raise Cancelled("cancelled by request")
            if max_duration_s is not None and time.monotonic() - t_begin > max_duration_s:
                raise SweepError(f"exceeded max duration {max_duration_s:g} s")
            try:
                scan, t_host, raw = read_scan(0.1)
            except DeviceTimeoutError:
                if time.monotonic() - last_scan > scan_silence_s:
                    raise SweepError(f"no scan from the scanner for {scan_silence_s:g} s (connection lost?)") from None
                scan = None
            if scan is not None:
                last_scan = time.monotonic()
                pull_motor()
                missing_before = recorder.gaps.missing
                recorder.add_scan(scan, clock_ns(t_host), raw)
                if recorder.gaps.missing > missing_before:
                    emit(
                        "scan_gap",
                        {
                            "missing": recorder.gaps.missing - missing_before,
                            "before_scan_counter": int(scan.scan_counter),
                        },
                    )
                if len(recorder.motor):
                    beta = float(cal.beta(recorder.motor.position[-1]))
                    done = min(max((beta - plan.start) * plan.direction / span, 0.0), 1.0)
                    report(
                        0.05 + 0.8 * done if phase[0] != "approach" else 0.02,
                        f"{phase[0]}: beta {math.degrees(beta):.1f} deg",
                    )
            if not mover.is_alive():
                if mover.error is not None:
                    raise mover.error
                # keep reading until the scans and the motor samples cover the end of the sweep: at
                # least two scan periods, then until end_covered() (on a starved host the last motor
                # samples can come late), but no longer than the scanner may stay silent
                now = time.monotonic()
                if tail_until is None:
                    tail_until = now + 2.0 / (recorder.scan_frequency_hz or 25.0) + 0.05
                    tail_limit = now + scan_silence_s
                if now >= tail_until and (now >= tail_limit or end_covered()):
                    break
        pull_motor()
        emit("motor_time_source", {"source": recorder.motor_time_source})
    except BaseException as exc:
        abort.set()
        stop_error = stop_motor(motor)
        if mover.ident is not None:  # started (enabling the motor may have failed before it was)
            mover.join(5.0)
        with contextlib.suppress(Exception):
            pull_motor()
        reason = str(exc) or type(exc).__name__
        event: dict[str, Any] = {"reason": reason, "phase": phase[0]}
        if stop_error is not None:
            event["motor_stop_error"] = stop_error
        emit("sweep_aborted", event)
        if stop_error is None:
            raise
        message = f"{reason}; {stop_error}"
        from service.jobs import Cancelled

        if isinstance(exc, Cancelled):
            raise Cancelled(message) from exc
        raise SweepError(message) from exc
    finally:
        with contextlib.suppress(Exception):
            scanner.stop_streaming()
    stats = scanner.stats.as_dict() if hasattr(scanner, "stats") else {}
    return SweepOutcome(recorder, sweep_t[0], sweep_t[1], plan, stats, time.monotonic() - t_begin)
