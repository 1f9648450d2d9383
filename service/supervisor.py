"""The rig process's supervisor, on the service's side: :class:`RigSupervisor` starts the rig
process (``python -m service.rigproc``, :mod:`service.rigproc`: the process and the messages
it and the service exchange), relays a measurement to it (:meth:`RigSupervisor.measure` is the
job runner's measurement function), keeps the latest device state for ``/healthz`` and
``GET /api/v1/rig``, and restarts the rig process when it dies: the running measurement fails
with the reason, its raw log stays as written, and the new rig process quick-stops a drive it
finds still enabled. A rig process that does not start raises :class:`RigProcessError` with the
reason it reported (:class:`service.rigproc.StartupFailed`).

Standard library only at load time (with :mod:`service.rigproc`), so ``lrms measure`` starts
the rig process before it loads the rig code, the API and the store.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from service.rigproc import (
    Boot,
    CancelCmd,
    Finished,
    Progress,
    Ready,
    ResetCmd,
    ResetDone,
    RigProcessError,
    ShutdownCmd,
    StartCmd,
    StartupFailed,
    Status,
)

if TYPE_CHECKING:
    from service.config import RigConfig
    from service.jobs import JobContext

__all__ = ["RigProcessError", "RigSupervisor"]

log = logging.getLogger(__name__)


@dataclass
class _Job:
    mid: str
    events: queue.Queue[object] = field(default_factory=queue.Queue)


@dataclass(frozen=True)
class _Died:
    how: str


def _exit_text(code: int | None) -> str:
    if code is None:
        return "did not exit"
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exit status {code}"


class RigSupervisor:
    """Starts and supervises the rig process and relays measurements to it (module docstring)."""

    def __init__(
        self,
        config: RigConfig,
        *,
        log_level: str = "warning",
        status_period_s: float = 0.25,
        start_timeout_s: float = 120.0,
        restart_delays_s: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0, 10.0, 30.0),
    ) -> None:
        self.config = config
        self.log_level = log_level
        self.status_period_s = status_period_s
        self.start_timeout_s = start_timeout_s
        self.restart_delays_s = restart_delays_s
        self.scanner_url: str | None = config.scanner.url
        self.motor_url: str | None = config.motor.url
        self.restarts = 0
        self.last_exit: str | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._conn: Connection | None = None
        self._alive = False
        self._send_lock = threading.Lock()
        self._lock = threading.Lock()
        self._job: _Job | None = None
        self._reset_waiter: queue.Queue[ResetDone] | None = None
        self._status: Status | None = None
        self._status_at = 0.0
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None

    # -- life cycle -----------------------------------------------------------------------
    def open(self) -> RigSupervisor:
        """Start the rig process and wait until its devices are open (a failure is raised)."""
        self._spawn(after_crash=False)
        self._thread = threading.Thread(target=self._supervise, name="lrms-rig-supervisor", daemon=True)
        self._thread.start()
        return self

    def _spawn(self, after_crash: bool) -> None:
        # a process of its own started with ``-m`` (not multiprocessing's spawn, which would import
        # the caller's main script again), its end of a socket pair passed as a file descriptor
        ours, theirs = socket.socketpair()
        argv = [sys.executable, "-m", "service.rigproc", str(theirs.fileno())]
        if self.config.sim is not None and self.config.sim.process:
            import json

            from service.simproc import sim_args

            argv.append(json.dumps(sim_args(self.config)))  # started first thing (main)
        proc = subprocess.Popen(
            argv,
            pass_fds=[theirs.fileno()],
            stdin=subprocess.DEVNULL,
        )
        theirs.close()  # else this process holds the child's end open and never sees it close
        parent = Connection(ours.detach())
        first: object = None
        try:
            parent.send(Boot(self.config, self.log_level, self.status_period_s, after_crash))
            first = parent.recv() if parent.poll(self.start_timeout_s) else None
        except (EOFError, OSError):
            pass
        except Exception as exc:  # the boot message did not pickle, or the answer did not unpickle
            first = StartupFailed(f"{type(exc).__name__}: {exc}")
        if not isinstance(first, Ready):
            parent.close()  # a rig process still waiting for its boot message sees the pipe close
            try:
                proc.wait(10.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5.0)
            why = first.reason if isinstance(first, StartupFailed) else _exit_text(proc.returncode)
            raise RigProcessError(f"the rig process did not start: {why}")
        self.scanner_url = first.info.get("scanner_url")
        self.motor_url = first.info.get("motor_url")
        with self._lock:
            self._proc, self._conn, self._alive = proc, parent, True
            self._status = None
        log.info("rig process %d ready (scanner %s, motor %s)", proc.pid, self.scanner_url, self.motor_url)

    def close(self) -> None:
        """Stop the rig process: a running sweep is cancelled (motor quick stop), devices closed."""
        self._closing.set()
        proc = self._proc
        if proc is None:
            return
        with contextlib.suppress(OSError, ValueError):
            self._send(ShutdownCmd())
        try:
            proc.wait(40.0)
        except subprocess.TimeoutExpired:
            log.error("the rig process did not stop in 40 s: killing it")
            proc.kill()
            proc.wait(5.0)
        if self._thread is not None:
            self._thread.join(5.0)
        with contextlib.suppress(OSError):
            if self._conn is not None:
                self._conn.close()
        self._alive = False

    def __enter__(self) -> RigSupervisor:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    def _send(self, msg: object) -> None:
        with self._send_lock:
            if self._conn is None or not self._alive:
                raise RigProcessError(f"the rig process is down ({self.last_exit or 'not started'})")
            self._conn.send(msg)

    # -- supervision ----------------------------------------------------------------------
    def _supervise(self) -> None:
        while True:
            conn = self._conn
            assert conn is not None
            self._read(conn)
            with contextlib.suppress(OSError):
                conn.close()
            proc = self._proc
            assert proc is not None
            try:
                proc.wait(10.0)
            except subprocess.TimeoutExpired:  # its pipe closed but it lives on: make sure it is gone
                proc.kill()
                proc.wait(5.0)
            how = _exit_text(proc.returncode)
            with self._lock:
                self._alive = False
                self.last_exit = how
                job = self._job
                waiter = self._reset_waiter
            if job is not None:
                job.events.put(_Died(how))
            if waiter is not None:
                waiter.put(ResetDone(False, f"the rig process died ({how})"))
            if self._closing.is_set():
                return
            log.error("the rig process %d died (%s): restarting it", proc.pid, how)
            for attempt in range(10**9):
                delay = self.restart_delays_s[min(attempt, len(self.restart_delays_s) - 1)]
                if self._closing.wait(delay):
                    return
                try:
                    self._spawn(after_crash=True)
                except Exception as exc:
                    log.error("restarting the rig process failed (attempt %d): %s", attempt + 1, exc)
                    with self._lock:
                        self.last_exit = f"{how}; restart failed: {exc}"
                    continue
                self.restarts += 1
                if self._closing.is_set():  # close() came while it started: stop this one too
                    with contextlib.suppress(OSError, ValueError):
                        self._send(ShutdownCmd())
                break

    def _read(self, conn: Connection) -> None:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return
            if isinstance(msg, Status):
                self._status, self._status_at = msg, time.monotonic()
            elif isinstance(msg, Progress | Finished):
                job = self._job
                if job is not None and job.mid == msg.mid:
                    job.events.put(msg)
            elif isinstance(msg, ResetDone):
                waiter = self._reset_waiter
                if waiter is not None:
                    waiter.put(msg)
            else:
                log.error("unexpected message from the rig process: %r", msg)

    # -- a measurement --------------------------------------------------------------------
    def measure(self, ctx: JobContext) -> dict[str, Any]:
        """The job runner's measurement function: run it in the rig process, relay its progress
        and cancellation; its outcome becomes this call's return value or exception."""
        mid = ctx.measurement.id
        job = _Job(mid)
        with self._lock:
            if not self._alive:
                raise RigProcessError(f"the rig process is down ({self.last_exit}); the measurement was not started")
            self._job = job
        try:
            self._send(StartCmd(ctx.measurement, str(ctx.raw_path), str(ctx.cloud_path), ctx.calibration))
            cancel_sent = False
            while True:
                if ctx.cancelled and not cancel_sent:
                    with contextlib.suppress(RigProcessError, OSError, ValueError):
                        self._send(CancelCmd(mid))
                    cancel_sent = True
                try:
                    ev = job.events.get(timeout=0.1)
                except queue.Empty:
                    continue
                if isinstance(ev, Progress):
                    ctx.progress(ev.fraction, ev.message)
                elif isinstance(ev, Finished):
                    return self._outcome(ctx, ev)
                elif isinstance(ev, _Died):
                    raise RigProcessError(
                        f"the rig process died during the measurement ({ev.how}); the motor stop could not be "
                        "commanded (a CANopen drive stops on its heartbeat watchdog); the rig process is restarted"
                    )
        finally:
            with self._lock:
                self._job = None

    @staticmethod
    def _outcome(ctx: JobContext, ev: Finished) -> dict[str, Any]:
        from service.jobs import Cancelled

        if ctx.metrics is not None:
            ctx.metrics.scans.inc(ev.scans_received)
            ctx.metrics.scans_missing.inc(ev.scans_missing)
        if ev.state == "done" and ev.result is not None:
            return ev.result
        if ev.partial_result is not None:
            ctx.info["partial_result"] = ev.partial_result
        if ev.state == "cancelled":
            raise Cancelled(ev.reason or "cancelled")
        raise RigProcessError(ev.reason or "failed")

    # -- state ----------------------------------------------------------------------------
    def reset(self, timeout: float = 10.0) -> dict[str, Any]:
        """Clear a drive fault (CiA 402 fault reset); ``{"ok", "error", "motor"}``."""
        waiter: queue.Queue[ResetDone] = queue.Queue()
        with self._lock:
            if self._reset_waiter is not None:
                raise RigProcessError("a reset is already in progress")
            self._reset_waiter = waiter
        try:
            self._send(ResetCmd())
            try:
                done = waiter.get(timeout=timeout)
            except queue.Empty:
                raise RigProcessError(f"the rig process did not answer the reset in {timeout:g} s") from None
        finally:
            with self._lock:
                self._reset_waiter = None
        return {"ok": done.ok, "error": done.error, "motor": done.motor}

    def process_info(self) -> dict[str, Any]:
        age = time.monotonic() - self._status_at if self._status is not None else None
        return {
            "alive": self._alive,
            "pid": self.pid,
            "restarts": self.restarts,
            "last_exit": self.last_exit,
            "state_age_s": None if age is None else round(age, 3),
        }

    def describe(self) -> dict[str, Any]:
        """For ``GET /api/v1/rig``: the rig process and the newest device state it reported."""
        st = self._status
        out: dict[str, Any] = dict(st.info) if st is not None and self._alive else {}
        out.setdefault("scanner", {"url": self.scanner_url})
        out.setdefault("motor", {"url": self.motor_url})
        out["rig_process"] = self.process_info()
        return out

    def health(self) -> dict[str, Any]:
        """For ``/healthz``: ``status`` ``ok`` only when the rig process is alive, reports its state,
        the drive is not faulted and the scanner is connected; else ``degraded`` with the reasons."""
        reasons: list[str] = []
        proc = self.process_info()
        st = self._status if self._alive else None
        drive: dict[str, Any] = {"state": None, "fault": None}
        scanner_connected = None
        if not self._alive:
            reasons.append(f"rig process down ({self.last_exit})")
        elif st is None or proc["state_age_s"] is None:
            reasons.append("no state from the rig process yet")
        else:
            if proc["state_age_s"] > max(5.0, 20 * self.status_period_s):
                reasons.append(f"no state from the rig process for {proc['state_age_s']:.1f} s")
            from service.rig import device_health

            device_reasons, drive, scanner_connected = device_health(st.info)
            reasons += device_reasons
        return {
            "status": "degraded" if reasons else "ok",
            "reasons": reasons,
            "rig_process": proc,
            "drive": drive,
            "scanner_connected": scanner_connected,
        }
