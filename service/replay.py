"""Re-run a logged measurement offline: decode the raw telegrams, map, fit, compare.

The live pipeline and this one share :class:`service.sweep.SweepRecorder` and
:func:`service.rig.finish_measurement`, and the log keeps every input with its integer-ns host
time, so a replay of a complete log reproduces the stored result. A log cut short by a crash
replays up to where it ends (its sweep may be incomplete; the fit then says so), and so does one
the service rebuilt from such a file on restart (``recovered`` gives its recovery record).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from drivers.lms100.errors import CoLaError
from drivers.lms100.messages import ScanDataEvent, ScanDataReply
from drivers.lms100.protocol import CoLaConnection
from lrms.kinematics import RigModel
from service import mcaplog, mcaprecovery
from service.config import RigConfig, parse_config
from service.errors import ServiceError
from service.fitting import rig_kinematics
from service.models import JobRequest, ResolvedSweep
from service.sweep import SweepRecorder

if TYPE_CHECKING:
    from service.calstore import StoredCalibration

FloatArray = NDArray[np.float64]


class ReplayError(ServiceError):
    pass


@dataclass
class LoadedLog:
    """A measurement's raw log read back: its record, the recorder fed with every logged scan and
    motor sample (mapping with the kinematics the measurement used), the sweep's start and end."""

    meta: dict[str, Any]
    config: RigConfig
    calibration: StoredCalibration | None
    recorder: SweepRecorder
    t_start: int
    t_end: int | None
    stored: dict[str, Any] | None
    truncated: bool
    bad_telegrams: int

    @property
    def sweep(self) -> ResolvedSweep:
        return ResolvedSweep.model_validate(self.meta["sweep"])


def load_log(path: str | Path | BinaryIO, kinematics: dict[str, Any] | None = None) -> LoadedLog:
    """Read ``path`` (a file, or an open seekable binary stream) into a :class:`LoadedLog`
    (:class:`ReplayError` if it is no measurement log or its sweep never started).

    ``kinematics``: ``[kinematics]`` keys that replace the logged configuration's (a new rig
    calibration, :func:`kinematics_of_calibration`); the calibration the measurement logged is then
    not used (nor recorded in the result)."""
    status = mcaplog.LogReadStatus()
    meta: dict[str, Any] | None = None
    stored: dict[str, Any] | None = None
    t_start: int | None = None
    t_end: int | None = None
    recorder: SweepRecorder | None = None
    codec: CoLaConnection | None = None
    bad = 0
    for msg in mcaplog.iter_log(path, status):
        if msg.topic == mcaplog.TOPIC_MEASUREMENT:
            meta = msg.decode()
            if kinematics is not None:
                logged = meta["config"].get("kinematics", {})
                meta["config"] = {**meta["config"], "kinematics": {**logged, **kinematics}}
                meta["calibration"] = None
            cfg = parse_config(meta["config"], source=f"{path} (logged configuration)")
            calibration = logged_calibration(meta, path)
            recorder = SweepRecorder(rig_kinematics(cfg, calibration), None, meta["dialect"])
            codec = CoLaConnection(meta["dialect"], role="client")
        elif recorder is None or codec is None:
            continue
        elif msg.topic == mcaplog.TOPIC_TELEGRAM:
            codec.receive_data(msg.data)
            try:
                decoded = codec.next_message()
            except CoLaError:
                bad += 1
                continue
            if isinstance(decoded, ScanDataEvent | ScanDataReply):
                recorder.add_scan(decoded.scan, msg.log_time_ns, None)
        elif msg.topic == mcaplog.TOPIC_MOTOR:
            js = msg.decode()
            t_ns = js.timestamp.seconds * 1_000_000_000 + js.timestamp.nanos
            for j in js.joints:
                recorder.add_motor(t_ns, j.position, j.velocity)
        elif msg.topic == mcaplog.TOPIC_EVENT:
            ev = msg.decode()
            if ev.get("kind") in ("sweep_start", "sweep_end"):
                # {"sec", "nsec"}; logs written before that carry the integer "t_ns"
                t = mcaplog.time_ns_of(ev["time"] if "time" in ev else ev["t_ns"])
                if ev["kind"] == "sweep_start":
                    t_start = t
                else:
                    t_end = t
            elif ev.get("kind") == "motor_time_source":
                recorder.logged_motor_time_source = ev.get("source")
        elif msg.topic == mcaplog.TOPIC_RESULT:
            stored = msg.decode()
    if meta is None or recorder is None:
        raise ReplayError(f"{path} has no /lrms/measurement record: not a measurement log")
    if t_start is None:
        raise ReplayError(f"{path}: the sweep never started (log ends before the sweep_start event)")
    cfg = parse_config(meta["config"], source=f"{path} (logged configuration)")
    return LoadedLog(meta, cfg, logged_calibration(meta, path), recorder, t_start, t_end, stored, status.truncated, bad)


def replay(path: str | Path | BinaryIO, kinematics: dict[str, Any] | None = None) -> dict[str, Any]:
    """Replay ``path``; returns ``{"result", "stored", "truncated", "recovered", "bad_telegrams",
    "reproduced", "max_abs_diff"}`` (``recovered``: the recovery record of a log rebuilt on restart).

    ``path`` may be an open seekable binary file (a log fetched from an archive). ``kinematics``:
    ``[kinematics]`` keys that replace the logged configuration's (a new rig calibration, see
    :func:`kinematics_of_calibration`); the result is then a re-evaluation, not a reproduction.
    """
    from service.rig import finish_measurement

    log = load_log(path, kinematics)
    request = JobRequest.model_validate(log.meta["request"])
    _, result = finish_measurement(
        log.recorder, log.config, request, log.sweep, log.t_start, log.t_end, log.calibration
    )
    result = mcaplog.json_safe(result)
    stored, bad = log.stored, log.bad_telegrams
    recovered = mcaprecovery.recovery_info(path)
    out: dict[str, Any] = {
        "result": result,
        "stored": stored,
        "truncated": log.truncated or recovered is not None,
        "recovered": recovered,
        "bad_telegrams": bad,
        "reproduced": None,
        "max_abs_diff": None,
    }
    if stored is not None and stored.get("state") == "done" and kinematics is None:
        diff = max_abs_diff(stored["result"], result)
        out["max_abs_diff"] = diff
        scaled = max_abs_diff(stored["result"], result, relative=True)
        out["reproduced"] = scaled is not None and scaled <= REPRODUCED
    return out


@dataclass(frozen=True)
class LoggedReadings:
    """The raw readings of a logged sweep's valid beams (inside the sweep's constant-speed window
    and the fit's range limits): range ``l`` (m), scan angle ``alpha`` and plane angle ``beta``
    (rad, the rig's device conventions applied), the motor speed ``omega`` at each beam (rad/s),
    and the rig model the measurement mapped with; ``noise``: the rig's ``[noise]`` when it logged
    (:class:`lrms.covariance.NoiseModel`'s fields, SI: what the service's calibration sweep adjusts with)."""

    l: FloatArray
    alpha: FloatArray
    beta: FloatArray
    omega: FloatArray
    model: RigModel
    noise: dict[str, float] | None = None


def log_readings(path: str | Path) -> LoggedReadings:
    """The raw ``(l, alpha, beta, omega)`` of the sweep logged in ``path`` (a measurement's raw
    MCAP log), for a calibration (``lrms calibrate``). The motor speed at a beam is the drive's
    logged velocity interpolated at the beam's host time (where the drive logged none: the
    derivative of the logged positions)."""
    from service.rig import plan_from

    log = load_log(path)
    plan = plan_from(log.sweep)
    window = plan.beta_window() if plan.mode == "constant" else None
    cfg = log.config
    mapped = log.recorder.map(log.t_start, log.t_end, window, cfg.fit.min_range_m, cfg.fit.max_range_m)
    motor = log.recorder.motor
    t = np.asarray(motor.t_ns, dtype=np.int64)
    pos = np.asarray(motor.position, dtype=np.float64)
    vel = np.asarray(motor.velocity, dtype=np.float64)
    t, idx = np.unique(t, return_index=True)
    pos, vel = pos[idx], vel[idx]
    ts = (t - mapped.t_ref_ns) * 1e-9
    if t.size < 2:
        raise ReplayError(f"{path}: fewer than two motor samples")
    if not np.all(np.isfinite(vel)):
        vel = np.gradient(pos, ts)
    omega = np.interp(mapped.beam_time_s, ts, vel)
    return LoggedReadings(
        mapped.ranges, mapped.alpha, mapped.beta, omega, log.recorder.calibration.rig, dict(cfg.noise.si())
    )


def logged_calibration(meta: dict[str, Any], path: str | Path | BinaryIO) -> StoredCalibration | None:
    """The calibration the logged measurement used (its ``/lrms/measurement`` record), or None."""
    from lrms.calibration import CalibrationError
    from service.calstore import StoredCalibration

    data = meta.get("calibration")
    if data is None:
        return None
    try:
        return StoredCalibration.from_payload(data)
    except (CalibrationError, KeyError, TypeError) as exc:
        raise ReplayError(f"{path}: the logged calibration cannot be read: {exc}") from None


#: Result fields a replay cannot reproduce (wall time, the live client's counters, the id, when a
#: calibration sweep's calibration was computed).
NOT_REPLAYED = frozenset({"duration_s", "scanner_stats", "measurement_id", "created"})


#: A replay reproduces a result when every number agrees to this (absolutely, or relatively for
#: numbers beyond 1 in magnitude: a calibration's condition number of 2e4 differs by 4e-8 between
#: two processes' LAPACK, 2e-12 of it).
REPRODUCED = 1e-9


def max_abs_diff(a: Any, b: Any, relative: bool = False) -> float | None:
    """Largest absolute difference between two results' numbers (``relative``: each difference
    divided by the larger magnitude when that is beyond 1); ``None`` when their structure differs
    (a key present in one only, apart from :data:`NOT_REPLAYED`; lists of other lengths; values of
    other kinds), so a replay that loses or adds a field is not "reproduced"."""
    if isinstance(a, dict) and isinstance(b, dict):
        keys_a, keys_b = set(a) - NOT_REPLAYED, set(b) - NOT_REPLAYED
        if keys_a != keys_b:
            return None
        diffs = [max_abs_diff(a[k], b[k], relative) for k in keys_a]
        if any(d is None for d in diffs):
            return None
        return max((d for d in diffs if d is not None), default=0.0)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return None
        diffs = [max_abs_diff(x, y, relative) for x, y in zip(a, b, strict=True)]
        if any(d is None for d in diffs):
            return None
        return max((d for d in diffs if d is not None), default=0.0)
    if isinstance(a, bool) or isinstance(b, bool):
        return 0.0 if type(a) is type(b) and a == b else None
    if isinstance(a, int | float) and isinstance(b, int | float):
        d = abs(float(a) - float(b))
        return d / max(1.0, abs(float(a)), abs(float(b))) if relative else d
    return 0.0 if a == b else None


def kinematics_of_calibration(calibration: dict[str, Any]) -> dict[str, Any]:
    """The ``[kinematics]`` keys of a rig calibration (``lrms calibrate --out``'s JSON): ``p_m`` and
    :attr:`lrms.kinematics.RigCalibration.MODEL_KEYS` from its estimated rig model, in the
    table's units (the device conventions and ``world_from_rig`` stay the logged ones)."""
    from lrms.calibration import CalibrationResult
    from lrms.kinematics import RigCalibration

    model = CalibrationResult.from_dict(calibration).model
    out: dict[str, Any] = {"p_m": model.p}
    for key, (field, factor) in RigCalibration.MODEL_KEYS.items():
        out[key] = float(getattr(model, field)) / factor
    return out
