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

:class:`service.supervisor.RigSupervisor` (the API side) starts the rig process, relays a
measurement, keeps the latest device state, and restarts the rig process when it dies; the new
rig process quick-stops a drive it finds still enabled. A start that fails for any reason (the
boot message not unpickling, the devices not opening) closes the simulated rig this process
started and is reported as :class:`StartupFailed` with the reason. When the API process dies,
the rig process sees its pipe close, cancels the sweep (motor quick stop), closes the devices and
exits.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
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
        from service.models import JobRequest

        m = cmd.measurement
        ctx = JobContext(
            measurement=m,
            request=JobRequest.model_validate(m.request),
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
    """``python -m service.rigproc FD [SIM_ARGS]``: the rig process (started by
    :class:`service.supervisor.RigSupervisor`;
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


if __name__ == "__main__":
    # run the imported module's main, not this ``__main__`` copy's: the messages it pickles must
    # name their classes ``service.rigproc.*`` for the service to read them
    from service.rigproc import main as _main

    raise SystemExit(_main())
