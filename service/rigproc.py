"""The rig process: the rig's real-time work in a process of its own, supervised by the service.

The API process (uvicorn, the job runner, the store, the scheduler) never touches a device. A
child process (``python -m service.rigproc``, talking over a socket pair wrapped in a
``multiprocessing`` connection) opens the :class:`service.rig.Rig`: the scanner
client's reader thread (scan ingest), the CANopen driver's SYNC and master-heartbeat thread, the
sweep's motion thread and loop, and the raw MCAP writer all run there, so nothing the API
process does (parsing a 40 MB request body, a flood of requests, a full garbage collection)
holds their interpreter lock. Mapping and the fit run in a worker process of the rig process
(:meth:`service.rig.Rig._finish`): they hold the interpreter lock for up to ~0.3 s at a time,
and the drive's heartbeat watchdog allows 0.5 s (measured: docs/service.md, "The rig process").

The interface is one duplex pipe of small pickled dataclasses:

* commands (API -> rig): :class:`StartCmd` (the measurement, its request and the raw log and
  cloud paths), :class:`CancelCmd`, :class:`ResetCmd` (clear a drive fault), :class:`ShutdownCmd`;
* events (rig -> API): :class:`Ready` / :class:`StartupFailed`, :class:`Status` (device state,
  pushed every ``status_period_s``), :class:`Progress`, :class:`Finished` (done with the result,
  failed or cancelled with the reason), :class:`ResetDone`.

The rig process sends through an outbox thread: progress and status reports replace their
unsent predecessors, so a stalled API process never blocks the sweep on a full pipe.

:class:`RigSupervisor` (API side) starts the rig process, relays a measurement
(:meth:`RigSupervisor.measure` is the job runner's measurement function), keeps the latest
device state for ``/healthz`` and ``GET /api/v1/rig``, and restarts the rig process when it
dies: the running measurement fails with the reason, its raw log stays as written (readable up
to the last complete chunk), and the new rig process quick-stops a drive it finds still enabled.
When the API process dies, the rig process sees its pipe close, cancels the sweep (motor quick
stop), closes the devices and exits.
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
from collections import deque
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.errors import ServiceError

if TYPE_CHECKING:  # imported where used: ``lrms measure`` starts this process before it loads them,
    # and this process starts the simulated rig before it loads the config models (pydantic): the
    # boot message's unpickling imports them
    from service.config import RigConfig
    from service.jobs import JobContext
    from service.simproc import SimProcess
    from service.store import Measurement

log = logging.getLogger(__name__)


# -- messages -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Boot:
    """The first message to a new rig process: what to open and how."""

    config: RigConfig
    log_level: str
    status_period_s: float
    after_crash: bool


@dataclass(frozen=True)
class StartCmd:
    measurement: Measurement
    raw_path: str
    cloud_path: str
    calibration: dict[str, Any] | None = None
    """The active calibration's payload (:attr:`service.jobs.JobContext.calibration`)."""


@dataclass(frozen=True)
class CancelCmd:
    mid: str


@dataclass(frozen=True)
class ResetCmd:
    pass


@dataclass(frozen=True)
class ShutdownCmd:
    pass


@dataclass(frozen=True)
class Ready:
    info: dict[str, Any]
    """pid, scanner_url, motor_url (what the devices were opened with)."""


@dataclass(frozen=True)
class StartupFailed:
    reason: str


@dataclass(frozen=True)
class Status:
    info: dict[str, Any]
    """:meth:`service.rig.Rig.describe`: scanner link and counters, motor state, position, fault."""
    busy: str | None


@dataclass(frozen=True)
class Progress:
    mid: str
    fraction: float
    message: str


@dataclass(frozen=True)
class Finished:
    mid: str
    state: str
    """``done``, ``failed`` or ``cancelled``."""
    result: dict[str, Any] | None = None
    reason: str | None = None
    partial_result: dict[str, Any] | None = None
    scans_received: int = 0
    scans_missing: int = 0


@dataclass(frozen=True)
class ResetDone:
    ok: bool
    error: str | None
    motor: dict[str, Any] = field(default_factory=dict)


class RigProcessError(ServiceError):
    """The rig process is down, died, or refused a command."""


# -- the rig process ------------------------------------------------------------------------


class _Outbox:
    """Sends events on the pipe from one thread. Progress and status reports coalesce (only the
    newest unsent one of each is kept), other events queue in order; progress goes out before
    the events queued after it, so a ``Finished`` is never overtaken by its own progress."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self._cond = threading.Condition()
        self._events: deque[object] = deque()
        self._progress: Progress | None = None
        self._status: Status | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="lrms-rig-outbox", daemon=True)
        self._thread.start()

    def send(self, msg: object) -> None:
        with self._cond:
            if isinstance(msg, Progress):
                self._progress = msg
            elif isinstance(msg, Status):
                self._status = msg
            else:
                if self._progress is not None:  # keep the order: progress, then what followed it
                    self._events.append(self._progress)
                    self._progress = None
                self._events.append(msg)
            self._cond.notify()

    def close(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout)

    def _next(self) -> object | None:
        with self._cond:
            while not (self._events or self._progress or self._status or self._closed):
                self._cond.wait()
            if self._events:
                return self._events.popleft()
            if self._progress is not None:
                msg: object = self._progress
                self._progress = None
                return msg
            if self._status is not None:
                msg = self._status
                self._status = None
                return msg
            return None  # closed and drained

    def _run(self) -> None:
        while (msg := self._next()) is not None:
            try:
                self.conn.send(msg)
            except (OSError, ValueError):  # the API process is gone: nothing to tell
                return


class _Worker:
    """Runs one measurement at a time on a thread of the rig process."""

    def __init__(self, rig: Any, outbox: _Outbox) -> None:
        self.rig = rig
        self.outbox = outbox
        self._thread: threading.Thread | None = None
        self._mid: str | None = None
        self._cancel = threading.Event()

    @property
    def busy(self) -> str | None:
        return self._mid if self._thread is not None and self._thread.is_alive() else None

    def start(self, cmd: StartCmd) -> None:
        mid = cmd.measurement.id
        if self.busy is not None:
            self.outbox.send(Finished(mid, "failed", reason=f"the rig is busy with measurement {self.busy}"))
            return
        self._mid = mid
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(cmd, self._cancel), name="lrms-rig-measure")
        self._thread.start()

    def cancel(self, mid: str | None = None) -> None:
        if mid is None or mid == self._mid:
            self._cancel.set()

    def join(self, timeout: float) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self, cmd: StartCmd, cancel: threading.Event) -> None:
        from drivers.errors import DriverError
        from lrms.errors import LrmsError
        from service.jobs import Cancelled, JobContext
        from service.models import MeasurementRequest

        m = cmd.measurement
        ctx = JobContext(
            measurement=m,
            request=MeasurementRequest.model_validate(m.request),
            raw_path=Path(cmd.raw_path),
            cloud_path=Path(cmd.cloud_path),
            cancel_event=cancel,
            report=lambda f, msg: self.outbox.send(Progress(m.id, f, msg)),
            calibration=cmd.calibration,
        )
        try:
            result = self.rig.measure(ctx)
            out = Finished(m.id, "done", result=result)
        except Cancelled as exc:
            out = Finished(m.id, "cancelled", reason=str(exc))
        except (ServiceError, DriverError, LrmsError) as exc:
            out = Finished(m.id, "failed", reason=str(exc) or type(exc).__name__)
        except Exception as exc:  # a bug: the traceback in this process's log, the reason to the API
            log.exception("measurement %s crashed", m.id)
            out = Finished(m.id, "failed", reason=f"internal error: {type(exc).__name__}: {exc}")
        scans = ctx.info.get("scans", {})
        self.outbox.send(
            Finished(
                out.mid,
                out.state,
                out.result,
                out.reason,
                ctx.info.get("partial_result"),
                int(scans.get("received", 0)),
                int(scans.get("missing", 0)),
            )
        )


def _motor_state(rig: Any) -> dict[str, Any]:
    info: dict[str, Any] = rig.describe(max_age_s=0.0).get("motor", {})
    return info


def _stop_if_enabled(rig: Any) -> None:
    """After a crash of the previous rig process: a drive still enabled (no heartbeat watchdog, or
    it has not tripped yet) gets a quick stop, so the drive is left stopped."""
    from service.sweep import stop_motor

    state = _motor_state(rig).get("state")
    if state == "OPERATION_ENABLED":
        err = stop_motor(rig.motor)
        log.warning("the drive was still enabled after the rig process died: quick stop (%s)", err or "accepted")


def main(argv: list[str] | None = None) -> int:
    """``python -m service.rigproc FD [SIM_ARGS]``: the rig process (started by :class:`RigSupervisor`;
    FD is its end of the socket pair, and the first message on it is a :class:`Boot`). SIM_ARGS
    (JSON, :func:`service.simproc.sim_args`; a ``[sim]`` config with ``process = true``): the
    simulated rig to start first, before the boot message is read (its unpickling loads the
    config models) and the rig code is imported, so the simulated rig boots meanwhile.

    Whatever stops the start (the boot message not readable, e.g. an ``ImportError`` when the
    service and this process run different code; the simulated rig not starting; the rig not
    opening) closes the simulated rig and is reported as :class:`StartupFailed` with its reason;
    the exit status is then 1."""
    args = sys.argv[1:] if argv is None else argv
    conn = Connection(int(args[0]))
    outbox = _Outbox(conn)
    sim: SimProcess | None = None
    try:
        if len(args) > 1:
            import json

            from service.simproc import SimProcess

            sim = SimProcess(wait=False, args=json.loads(args[1]))
        boot = conn.recv()
        if not isinstance(boot, Boot):
            raise RigProcessError(f"the first message was a {type(boot).__name__}, not a Boot")
    except BaseException as exc:
        return _startup_failed(outbox, sim, exc)
    return child_main(conn, boot.config, boot.log_level, boot.status_period_s, boot.after_crash, sim, outbox=outbox)


def _startup_failed(outbox: _Outbox, sim: SimProcess | None, exc: BaseException) -> int:
    """Close the simulated rig, tell the service why the start failed (if it is still there to
    read it: the outbox drops what it cannot send) and give the exit status."""
    if sim is not None:
        sim.close()
    if isinstance(exc, EOFError):
        reason = "the service closed the rig process's pipe before its boot message"
    else:
        log.error("the rig did not open", exc_info=exc)
        reason = f"{type(exc).__name__}: {exc}"
    outbox.send(StartupFailed(reason))
    outbox.close()
    return 1


def child_main(
    conn: Connection,
    config: RigConfig,
    log_level: str,
    status_period_s: float,
    after_crash: bool,
    sim: SimProcess | None = None,
    *,
    outbox: _Outbox | None = None,
) -> int:
    """The rig process's work: open the rig, report, run commands until told to stop or the pipe
    closes; the exit status (1: the start failed, reported as :class:`StartupFailed`). ``sim``:
    the simulated rig's process, already started (by :func:`main`), closed with the rig, also
    when the start fails. ``outbox``: the pipe's sender, if already made."""
    import os

    if outbox is None:
        outbox = _Outbox(conn)
    try:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
        logging.basicConfig(
            level=log_level.upper(), format="%(asctime)s %(levelname)s rig[%(process)d] %(name)s: %(message)s"
        )
        # Ctrl-C in a terminal reaches the whole process group: the service stops this process
        # itself (ShutdownCmd, or its end of the pipe closing); SIGTERM (a service manager stopping
        # the whole group) is a clean stop too: sweep cancelled, motor stopped, devices closed
        signal.signal(signal.SIGINT, signal.SIG_IGN)

        def terminated(signum: int, frame: object) -> None:
            raise SystemExit(128 + signum)

        signal.signal(signal.SIGTERM, terminated)
        if sim is None and config.sim is not None and config.sim.process:
            from service.simproc import SimProcess

            sim = SimProcess(config, wait=False)  # the simulated rig boots while the rig code loads
        from service.rig import Rig

        rig = Rig(config, fit_process=True).open(sim)  # closes what it opened when it fails
    except BaseException as exc:
        return _startup_failed(outbox, sim, exc)
    worker = _Worker(rig, outbox)
    stop = threading.Event()

    def push_status() -> None:
        while not stop.wait(status_period_s):
            try:
                outbox.send(Status(rig.describe(max_age_s=0.0), worker.busy))
            except Exception:  # never let a state read end the status reports
                log.exception("reading the rig's state failed")

    try:
        if after_crash:
            _stop_if_enabled(rig)
        outbox.send(Ready({"pid": os.getpid(), "scanner_url": rig.scanner_url, "motor_url": rig.motor_url}))
        outbox.send(Status(rig.describe(max_age_s=0.0), None))
        threading.Thread(target=push_status, name="lrms-rig-status", daemon=True).start()
        while True:
            try:
                cmd = conn.recv()
            except (EOFError, OSError):  # the service is gone
                log.warning("the service closed the rig's pipe: stopping")
                break
            if isinstance(cmd, StartCmd):
                worker.start(cmd)
            elif isinstance(cmd, CancelCmd):
                worker.cancel(cmd.mid)
            elif isinstance(cmd, ResetCmd):
                outbox.send(ResetDone(**rig.reset()))  # refused while a measurement runs
            elif isinstance(cmd, ShutdownCmd):
                break
            else:
                log.error("unknown command %r", cmd)
    finally:
        stop.set()
        worker.cancel()
        worker.join(30.0)
        rig.close()
        outbox.close()
    return 0


# -- the API side ---------------------------------------------------------------------------


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


if __name__ == "__main__":
    # run the imported module's main, not this ``__main__`` copy's: the messages it pickles must
    # name their classes ``service.rigproc.*`` for the service to read them
    from service.rigproc import main as _main

    raise SystemExit(_main())
