"""The rig coordinator: devices from the config, one measurement = sweep + mapping + fit + log.

:class:`Rig` opens the scanner and the motor with :func:`drivers.url.open_device` (for a ``[sim]``
config it first starts :class:`sim.rig.SimulatedRig` and opens the URLs that one serves, so the
service talks to the simulated devices over the same TCP and CAN transports as to real ones).
:meth:`Rig.measure` is the job runner's measurement function.

Every scan's host receive time and its raw telegram are taken on the scanner client's reader
thread when the bytes completing the telegram arrive (``ScannerClient.next_record``), not when
the sweep loop gets to it, so queueing delays in this process do not enter the clock model.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from drivers.lms100.client import ScannerClient
from drivers.servo import cia402
from drivers.url import open_device, register
from lrms.errors import FitError, LrmsError
from lrms.kinematics import RigCalibration
from service import fitting, mcaplog
from service.config import RigConfig
from service.errors import ServiceError
from service.jobs import Cancelled, JobContext
from service.models import APPROACH_SPEED_DEG_S, MeasurementRequest, ResolvedSweep, resolve_sweep
from service.simproc import SimProcess
from service.sweep import MappedSweep, MotionLimits, SweepError, SweepPlan, SweepRecorder, run_sweep

if TYPE_CHECKING:  # imported where a calibration is applied: it loads lrms.calibration and scipy.optimize
    from service.calstore import StoredCalibration

log = logging.getLogger(__name__)

# the sim:// device URLs, by dotted path: the simulator's device code (the scene, the scanner's
# ray-caster) loads only where a sim:// URL is opened, not in every rig process (a [sim] rig with
# process = true opens the simulated rig's tcp:// and socketcand:// URLs)
register("scanner", "sim", "service.simdevices:open_sim_scanner")
register("motor", "sim", "service.simdevices:open_sim_motor")


def open_scanner(url: str, **kw: Any) -> ScannerClient:
    """The LMS100 client for ``url`` (its :meth:`ScannerClient.next_record` gives each scan's
    host receive time, stamped on the reader thread, and the raw framed telegram)."""
    client = open_device("scanner", url, **kw)
    if not isinstance(client, ScannerClient):
        raise ServiceError(f"scanner URL {url!r} did not give an LMS100 client")
    return client


def write_ply(path: Path, mapped: MappedSweep) -> None:
    """Binary little-endian PLY (``plyfile``): x y z (float32, world frame) plus range, alpha, beta
    and scan index; written to a side file first and renamed, so a reader never sees half a cloud."""
    from plyfile import PlyData, PlyElement

    n = mapped.points.shape[0]
    rec = np.empty(
        n,
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("range", "<f4"),
            ("alpha", "<f4"),
            ("beta", "<f4"),
            ("scan", "<i4"),
        ],
    )
    rec["x"], rec["y"], rec["z"] = mapped.points[:, 0], mapped.points[:, 1], mapped.points[:, 2]
    rec["range"], rec["alpha"], rec["beta"] = mapped.ranges, mapped.alpha, mapped.beta
    rec["scan"] = mapped.scan_index
    ply = PlyData(
        [PlyElement.describe(rec, "vertex")],
        text=False,
        byte_order="<",
        comments=["lrms sweep cloud, world frame (m, rad)"],
    )
    tmp = path.with_suffix(".ply.part")
    ply.write(str(tmp))
    tmp.replace(path)


def plan_from(sweep: ResolvedSweep, approach_speed_deg_s: float = APPROACH_SPEED_DEG_S) -> SweepPlan:
    return SweepPlan(
        start=math.radians(sweep.start_deg),
        stop=math.radians(sweep.stop_deg),
        speed=math.radians(sweep.speed_deg_s),
        acceleration=math.radians(sweep.acceleration_deg_s2),
        mode=sweep.mode,
        step=math.radians(sweep.step_deg),
        scans_per_step=sweep.scans_per_step,
        approach_speed=math.radians(approach_speed_deg_s),
    )


def motion_limits(config: RigConfig) -> MotionLimits:
    """The ``[motor]`` limits as :func:`service.sweep.run_sweep` checks them (rad, rad/s, rad/s^2)."""
    m = config.motor
    return MotionLimits(
        min_angle=math.radians(m.min_angle_deg),
        max_angle=math.radians(m.max_angle_deg),
        max_speed=math.radians(m.max_velocity_deg_s),
        max_acceleration=math.radians(m.max_acceleration_deg_s2),
    )


#: Configuration keys never written to a raw log (secrets): all of ``[auth]`` and the scanner's
#: login password hash. ``public_config`` leaves them out; the logged configuration still parses.
SECRET_KEYS: tuple[str, ...] = ("auth", "scanner.login_password_hash")


def redact_url(url: str | None) -> str | None:
    """``url`` without a password in its user part (``scheme://user:***@host``)."""
    if url is None:
        return None
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.netloc.rsplit("@", 1)[1]
    return urlunsplit(parts._replace(netloc=f"{parts.username or ''}:***@{host}"))


def public_config(config: RigConfig) -> dict[str, Any]:
    """The configuration as logged with a measurement: no secrets (:data:`SECRET_KEYS`; device URLs
    without a password) and no storage paths."""
    data: dict[str, Any] = config.model_dump(mode="json", exclude={"auth", "storage"})
    scanner = data.get("scanner", {})
    scanner.pop("login_password_hash", None)
    for device in ("scanner", "motor"):
        if isinstance(data.get(device), dict) and data[device].get("url") is not None:
            data[device]["url"] = redact_url(data[device]["url"])
    return data


def finish_measurement(
    recorder: SweepRecorder,
    config: RigConfig,
    request: MeasurementRequest,
    sweep: ResolvedSweep,
    t_start_ns: int,
    t_end_ns: int | None,
    calibration: StoredCalibration | None = None,
) -> tuple[MappedSweep, dict[str, Any]]:
    """Mapping and fit from recorded data: the same code live and in ``lrms replay``. The
    recorder maps with ``calibration``'s rig model when one is given (:func:`fitting.rig_kinematics`),
    and the fit uses it (:func:`fitting.fit`)."""
    plan = plan_from(sweep)
    window = plan.beta_window() if plan.mode == "constant" else None
    mapped = recorder.map(t_start_ns, t_end_ns, window, config.fit.min_range_m, config.fit.max_range_m)
    info = sweep_info(recorder, mapped, sweep)
    try:
        result = fitting.fit(mapped, request, config, calibration)
    except FitError as exc:
        err = FitError(f"{exc} ({mapped.points.shape[0]} points mapped)")
        err.partial_result = info  # type: ignore[attr-defined]
        raise err from exc
    except LrmsError as exc:  # a calibration sweep's adjustment refused the data: the sweep's counters too
        exc.partial_result = info  # type: ignore[attr-defined]
        raise
    result.update(info)
    return mapped, result


def sweep_info(recorder: SweepRecorder, mapped: MappedSweep, sweep: ResolvedSweep) -> dict[str, Any]:
    return {
        "sweep": {
            **sweep.model_dump(),
            "scans_received": recorder.gaps.received,
            "scans_missing": recorder.gaps.missing,
            "scan_gaps": [list(g) for g in recorder.gaps.gaps[:100]],
            "scans_in_sweep": int(np.unique(mapped.scan_index).size),
            "motor_samples": len(recorder.motor),
            "motor_timing_jitter_s": mapped.motor_timing_jitter_s,
            "motor_time_source": recorder.motor_time_source,
        },
        "mapping": mapped.stats(),
        "clock": {
            "drift_ppm": recorder.clock.drift * 1e6,
            "residual_jitter_s": recorder.clock.residual_std(),
            "resets": recorder.clock.resets,
        },
    }


def _exit_with_parent() -> None:
    """The fit worker's initializer: end the worker when the rig process ends, however it ends
    (a worker of a killed process would otherwise wait for work for ever)."""
    import multiprocessing
    import multiprocessing.connection
    import os

    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os._exit(0)

    threading.Thread(target=watch, name="lrms-fit-parent-watch", daemon=True).start()


def _warm_up_fits() -> None:
    import service.fitting  # noqa: F401  (and with it lrms, numpy, scipy)


def device_health(info: dict[str, Any]) -> tuple[list[str], dict[str, Any], bool | None]:
    """From :meth:`Rig.describe`'s output: what keeps the rig from measuring (a drive in FAULT or
    FAULT_REACTION_ACTIVE with its code, a drive not readable or without samples, a scanner not
    connected), the drive's ``{"state", "fault"}`` and whether the scanner is connected."""
    reasons: list[str] = []
    motor = info.get("motor", {})
    drive = {"state": motor.get("state"), "fault": motor.get("fault")}
    name = str(motor.get("state") or "UNKNOWN")
    if motor.get("error"):
        reasons.append(f"drive not readable: {motor['error']}")
    elif "FAULT" in name:
        fault = motor.get("fault") or {}
        code = fault.get("code")
        what = f"0x{code:04X}: {fault.get('reason')}" if isinstance(code, int) else "no fault code"
        reasons.append(f"drive {name} ({what})")
    elif name == "UNKNOWN":
        reasons.append("drive state unknown (no sample from the drive)")
    connected = info.get("scanner", {}).get("connected")
    if connected is False:
        reasons.append("scanner not connected")
    return reasons, drive, connected


class Rig:
    """Scanner + motor of one rig (see the module docstring)."""

    def __init__(self, config: RigConfig, fit_process: bool = False) -> None:
        self.config = config
        self.fit_process = fit_process
        """Map and fit in a worker process of this one (the rig process does: see :meth:`_finish`)."""
        self._fit_pool: Any = None
        self.sim: Any = None
        self.scanner: ScannerClient | None = None
        self.motor: Any = None
        self.scanner_url: str | None = config.scanner.url
        self.motor_url: str | None = config.motor.url
        self._lock = threading.Lock()
        self._describe_lock = threading.Lock()
        self._described: tuple[float, dict[str, Any]] | None = None

    # -- life cycle -----------------------------------------------------------------------
    def open(self, sim: SimProcess | None = None) -> Rig:
        """Open the devices (and the simulated rig of a ``[sim]`` config). ``sim``: the simulated
        rig's process, already started (:class:`SimProcess` with ``wait=False``); it is closed
        with the rig, also when opening fails."""
        cfg = self.config
        try:
            if cfg.sim is not None and cfg.sim.process:
                self.sim = sim if sim is not None else SimProcess(cfg, wait=False)
                self.sim.wait_ready()
                self.scanner_url, self.motor_url = self.sim.scanner_url, self.sim.motor_url
            elif cfg.sim is not None:
                from sim.rig import SimulatedRig
                from sim.scene import make_sensor

                sensor = make_sensor(cfg.sim.sensor, **cfg.noise.si())
                self.sim = SimulatedRig(
                    cfg.sim.scene,
                    RigCalibration.from_dict(cfg.sim_kinematics),  # the true rig: [kinematics] + [sim] rig_errors
                    sensor,
                    seed=cfg.sim.seed,
                    cola=cfg.sim.cola,
                    can=cfg.sim.can,
                    node=cfg.sim.node,
                )
                self.scanner_url, self.motor_url = self.sim.scanner_url, self.sim.motor_url
            assert self.scanner_url is not None and self.motor_url is not None
            self.scanner = open_scanner(self.scanner_url)
            # the [motor] limits go to the driver too: it refuses targets beyond them and writes
            # them to the drive (a CiA 402 drive's software position limits)
            self.motor = open_device("motor", self.motor_url, config=cfg.motor.drive_config())
            self._configure_scanner()
            if self.fit_process:
                self._start_fit_pool()
        except BaseException:
            self.close()
            raise
        return self

    def _configure_scanner(self) -> None:
        sc = self.scanner
        assert sc is not None
        want = self.config.scanner
        if want.login_password_hash is not None:
            sc.login(password_hash=want.login_password_hash)
        else:
            sc.login()
        current = sc.scan_config()
        if (current.scan_frequency, current.angular_resolution) != (
            round(want.scan_frequency_hz * 100),
            round(want.resolution_deg * 10000),
        ):
            sc.set_scan_config(float(want.scan_frequency_hz), float(want.resolution_deg))
        sc.start_measurement()
        sc.run()

    def close(self) -> None:
        if self._fit_pool is not None:
            self._fit_pool.shutdown(wait=False, cancel_futures=True)
            self._fit_pool = None
        for name in ("scanner", "motor", "sim"):
            dev = getattr(self, name)
            if dev is not None:
                try:
                    dev.close()
                except Exception:  # closing is best effort; keep closing the others
                    log.exception("closing the %s failed", name)
                setattr(self, name, None)

    def reset(self) -> dict[str, Any]:
        """Clear a drive fault (``POST /api/v1/rig/reset``): ``{"ok", "error", "motor"}``."""
        if self.motor is None:
            raise ServiceError("the rig is not open")
        if not self._lock.acquire(blocking=False):
            return {"ok": False, "error": "a measurement is running", "motor": self.describe(0.0).get("motor", {})}
        try:
            self.motor.reset_fault()
            error = None
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
        finally:
            self._lock.release()
        return {"ok": error is None, "error": error, "motor": self.describe(0.0).get("motor", {})}

    def __enter__(self) -> Rig:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state ----------------------------------------------------------------------------
    def describe(self, max_age_s: float = 0.5) -> dict[str, Any]:
        """Device state for ``GET /rig``: cached for ``max_age_s``, and built from what the drivers
        already know (no bus traffic unless the drive is faulted), so polling clients cannot load
        the CAN bus during a sweep."""
        with self._describe_lock:
            now = time.monotonic()
            if self._described is not None and now - self._described[0] < max_age_s:
                return self._described[1]
            out = self._describe()
            self._described = (now, out)
            return out

    def _describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"scanner": {"url": self.scanner_url}, "motor": {"url": self.motor_url}}
        sc = self.scanner
        if sc is not None:
            out["scanner"].update(connected=sc.connected, streaming=sc.streaming, stats=sc.stats.as_dict())
        m = self.motor
        if m is not None:
            try:
                sample = m.latest_sample()  # the newest sample's statusword: no bus traffic, no wait
                name = "UNKNOWN" if sample is None else cia402.decode_state(sample.statusword).name
                fault = m.fault() if "FAULT" in name else None
                out["motor"].update(
                    state=name,
                    position_deg=None if sample is None else math.degrees(sample.position_rad),
                    velocity_deg_s=None if sample is None else math.degrees(sample.velocity_rad_s),
                    fault=None if fault is None else {"code": fault.code, "reason": fault.reason},
                )
            except Exception as exc:  # report, do not fail GET /rig
                out["motor"]["error"] = str(exc)
        if self.sim is not None:
            out["sim"] = self.sim.describe()
        return out

    def health(self) -> dict[str, Any]:
        """``/healthz``'s rig part for a rig in this process (see :func:`device_health`)."""
        reasons, drive, connected = device_health(self.describe())
        return {
            "status": "degraded" if reasons else "ok",
            "reasons": reasons,
            "drive": drive,
            "scanner_connected": connected,
        }

    # -- a measurement --------------------------------------------------------------------
    def _finish(
        self,
        recorder: SweepRecorder,
        req: MeasurementRequest,
        sweep: ResolvedSweep,
        t0: int,
        t1: int | None,
        calibration: StoredCalibration | None = None,
    ) -> tuple[MappedSweep, dict[str, Any]]:
        """Mapping and fit (:func:`finish_measurement`). With ``fit_process`` in a worker process:
        the fit's numpy/scipy code holds the interpreter lock for up to ~0.3 s at a time (measured:
        docs/service.md), which would delay this process's heartbeat and SYNC threads; the worker
        has an interpreter of its own. The recorder goes there pickled, without its log."""
        if not self.fit_process:
            return finish_measurement(recorder, self.config, req, sweep, t0, t1, calibration)
        from concurrent.futures.process import BrokenProcessPool

        if self._fit_pool is None:
            self._start_fit_pool()
        log_ = recorder.log
        recorder.log = None  # the MCAP writer (a thread) stays here; the sweep no longer logs through it
        try:
            job = self._fit_pool.submit(finish_measurement, recorder, self.config, req, sweep, t0, t1, calibration)
            return job.result()  # type: ignore[no-any-return]
        except BrokenProcessPool as exc:
            self._fit_pool = None
            raise ServiceError(f"the fit process died: {exc}") from None
        finally:
            recorder.log = log_

    def _start_fit_pool(self) -> None:
        """The fit worker: spawned (a fork of this threaded process could inherit held locks) and
        warmed up (imports) at start-up, so the first measurement does not wait for it and its start-up
        does not compete with a sweep."""
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self._fit_pool = ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_exit_with_parent
        )
        self._fit_pool.submit(_warm_up_fits)

    def measure(self, ctx: JobContext) -> dict[str, Any]:
        with self._lock:
            return self._measure(ctx)

    def _measure(self, ctx: JobContext) -> dict[str, Any]:
        if self.scanner is None or self.motor is None:
            raise ServiceError("the rig is not open")
        cfg = self.config
        req = ctx.request
        try:
            sweep = resolve_sweep(req.sweep, cfg)
        except ValueError as exc:
            raise ServiceError(f"the request does not fit this rig: {exc}") from None
        fault = self.motor.fault()
        if fault is not None:
            raise SweepError(f"motor is faulted before the sweep: {fault.reason} (0x{fault.code:04X}); reset it first")
        plan = plan_from(sweep, min(APPROACH_SPEED_DEG_S, cfg.motor.max_velocity_deg_s))
        offset_ns = time.time_ns() - time.monotonic_ns()
        calibration = None
        if ctx.calibration is not None:
            from service.calstore import StoredCalibration

            calibration = StoredCalibration.from_payload(ctx.calibration)

        def clock_ns(t_monotonic: float) -> int:
            return round(t_monotonic * 1e9) + offset_ns

        def now_ns() -> int:
            return clock_ns(time.monotonic())

        dialect = self.scanner.dialect.value
        with mcaplog.McapLog(ctx.raw_path) as logf:
            logf.log_json(
                mcaplog.TOPIC_MEASUREMENT,
                now_ns(),
                {
                    "id": ctx.measurement.id,
                    "request": req.model_dump(mode="json"),
                    "sweep": sweep.model_dump(),
                    "config": public_config(cfg),
                    "scanner_url": redact_url(self.scanner_url),
                    "motor_url": redact_url(self.motor_url),
                    "redacted": list(SECRET_KEYS),
                    "dialect": dialect,
                    "time_base": "host CLOCK_MONOTONIC + epoch offset, ns",
                    "calibration": None if calibration is None else calibration.payload(),
                },
            )
            logf.log_world_pose(now_ns(), cfg.calibration.world_from_rig)
            recorder = SweepRecorder(fitting.rig_kinematics(cfg, calibration), logf, dialect)

            def on_event(kind: str, data: dict[str, Any]) -> None:
                logf.log_json(mcaplog.TOPIC_EVENT, now_ns(), {"kind": kind, **data})

            metrics = ctx.metrics
            scanner = self.scanner

            def read_scan(timeout: float) -> tuple[Any, float, bytes | None]:
                rec = scanner.next_record(timeout)
                if metrics is not None:
                    metrics.scans.inc()
                return rec.scan, rec.host_time_s, rec.raw

            ctx.progress(0.01, "approach")
            try:
                outcome = run_sweep(
                    scanner,
                    self.motor,
                    recorder,
                    plan,
                    clock_ns=clock_ns,
                    read_scan=read_scan,
                    progress=ctx.progress,
                    cancelled=lambda: ctx.cancelled,
                    on_event=on_event,
                    max_duration_s=cfg.sweep.max_duration_s,
                    limits=motion_limits(cfg),
                )
            except BaseException as exc:
                ctx.info["scans"] = {"received": recorder.gaps.received, "missing": recorder.gaps.missing}
                state = "cancelled" if isinstance(exc, Cancelled) else "failed"
                logf.log_json(
                    mcaplog.TOPIC_RESULT, now_ns(), {"state": state, "reason": str(exc) or type(exc).__name__}
                )
                if metrics is not None:
                    metrics.scans_missing.inc(recorder.gaps.missing)
                raise
            if metrics is not None:
                metrics.scans_missing.inc(recorder.gaps.missing)
            ctx.info["scans"] = {"received": recorder.gaps.received, "missing": recorder.gaps.missing}
            ctx.progress(0.86, "mapping")
            try:
                mapped, result = self._finish(recorder, req, sweep, outcome.t_start_ns, outcome.t_end_ns, calibration)
            except (LrmsError, SweepError) as exc:
                partial = getattr(exc, "partial_result", None)
                if partial is not None:  # the sweep's counters, so a failed fit still says what was measured
                    ctx.info["partial_result"] = mcaplog.json_safe(partial)
                logf.log_json(
                    mcaplog.TOPIC_RESULT, now_ns(), {"state": "failed", "reason": str(exc), "partial_result": partial}
                )
                raise
            logf.log_cloud(now_ns(), mapped.points)
            write_ply(ctx.cloud_path, mapped)
            result["scanner_stats"] = outcome.scanner_stats
            result["duration_s"] = outcome.duration_s
            result["measurement_id"] = ctx.measurement.id
            logf.log_json(mcaplog.TOPIC_RESULT, now_ns(), {"state": "done", "result": result})
        ctx.progress(1.0, "done")
        return mcaplog.json_safe(result)  # type: ignore[no-any-return]


def build_service(
    config: RigConfig, open_rig: bool = True, *, isolate: bool = True, log_level: str = "warning"
) -> tuple[Any, Any]:
    """The REST service for ``config`` with its rig (opened unless told otherwise).

    ``isolate`` (the default, and what ``lrms serve`` and ``lrms measure`` use): the rig runs in
    its own process (:func:`service.isolated.isolated_service`), and the service gets its
    measurement function, device state, health and drive reset from there. ``isolate=False``
    keeps a :class:`Rig` in this process (library use; no isolation from request handling).
    """
    if isolate:
        from service.isolated import isolated_service

        return isolated_service(config, open_rig, log_level=log_level)
    from service.api import Service

    rig = Rig(config)
    if open_rig:
        rig.open()
    return Service(config, rig.measure, rig_info=rig.describe, rig_health=rig.health, rig_reset=rig.reset), rig
