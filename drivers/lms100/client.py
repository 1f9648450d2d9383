"""TCP client for a SICK LMS100 (LMS1xx) speaking CoLa A (port 2111) or CoLa B (port 2112).

A thin transport around the sans-I/O codec (:class:`drivers.lms100.CoLaConnection`)::

    from drivers.lms100.client import ScannerClient

    with ScannerClient("192.168.0.1", dialect="b") as sc:
        print(sc.device_ident(), sc.serial_number())
        sc.login()                              # level 3, "client"
        sc.set_scan_config(25.0, 0.25)          # 25 Hz, 0.25 deg, -45..225 deg
        sc.start_measurement()
        sc.run()
        sc.start_streaming()                    # sEN LMDscandata 1
        for scan in sc.scans(count=100):
            ...                                 # drivers.lms100.Scan
        print(sc.stats)                         # received, lost, gaps, reconnects, ...

One background reader thread per connection feeds the codec, hands replies to the waiting
request (matched by command type and name, ``sFA`` to whoever is waiting) and puts streamed
scans into a bounded queue (full: the oldest scan is dropped and counted). Every request has a
timeout (:class:`~drivers.errors.DeviceTimeoutError`); an ``sFA`` reply raises
:class:`~drivers.lms100.errors.DeviceErrorReply` with the decoded message.

When the link drops (or a running stream stalls) and ``reconnect`` is on, a reconnect thread
retries with exponential back-off and then restores the session: log in, scan configuration,
scan data configuration, measurement start/stop, ``Run``, and the scan subscription. Lost scans
are found from scan-counter gaps, also across a reconnect, and are counted in :attr:`stats`
and logged (logger ``drivers.lms100.client``). See ``docs/lms100-client.md``.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any, TypeVar

from drivers.errors import DeviceConnectionError, DeviceTimeoutError, DeviceURLError, DriverError
from drivers.lms100.errors import CoLaError, DeviceErrorReply, TelegramError
from drivers.lms100.framing import Dialect, frame
from drivers.lms100.messages import (
    PASSWORD_HASHES,
    REPLY_KINDS,
    AccessLevel,
    DeviceIdent,
    DeviceReady,
    DeviceState,
    ErrorReply,
    FirmwareVersion,
    Message,
    PollScan,
    ReadDeviceIdent,
    ReadDeviceReady,
    ReadDeviceState,
    ReadFirmwareVersion,
    ReadScanConfig,
    ReadScanDataConfig,
    ReadSerialNumber,
    Reboot,
    Run,
    RunReply,
    ScanConfig,
    ScanDataConfig,
    ScanDataEvent,
    ScanDataReply,
    SerialNumber,
    SetAccessMode,
    SetAccessModeReply,
    SetScanConfig,
    SetScanConfigReply,
    StartMeasurement,
    StartMeasurementReply,
    StopMeasurement,
    StopMeasurementReply,
    SubscribeScanData,
    SubscribeScanDataReply,
    WriteScanDataConfig,
    WriteScanDataConfigReply,
    decode_payload,
    is_reply_to,
)
from drivers.lms100.protocol import CoLaConnection
from drivers.lms100.scan import Scan
from drivers.lms100.transport import Backoff, DroppingQueue, GapTracker, ScannerStats, StatsCounter
from drivers.url import DeviceURL

__all__ = [
    "DEFAULT_PORTS",
    "LMS1XX_SCAN_MODES",
    "Backoff",
    "LoginError",
    "MeasurementError",
    "ScanConfigError",
    "ScanRecord",
    "ScannerClient",
    "ScannerStateError",
    "ScannerStats",
    "open_url",
]

log = logging.getLogger("drivers.lms100.client")

DEFAULT_PORTS = {Dialect.A: 2111, Dialect.B: 2112}
"""The LMS1xx serves CoLa A on TCP 2111 and CoLa B on 2112."""

LMS1XX_SCAN_MODES = ((25.0, 0.25), (50.0, 0.5))
"""(scan frequency Hz, angular resolution deg) pairs an LMS1xx accepts in mLMPsetscancfg."""

R = TypeVar("R", bound=Message)

_PAUSES_STREAM = (SetAccessMode, StopMeasurement, SetScanConfig, Reboot)
"""Requests after which a real LMS1xx may send no scans for a while (login, stop, reconfigure, reboot)."""


class LoginError(CoLaError):
    """SetAccessMode was refused (wrong password hash for the level)."""


class ScanConfigError(CoLaError):
    """The device refused a scan configuration (mLMPsetscancfg status 1..5), or it is malformed."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class MeasurementError(CoLaError):
    """LMCstartmeas / LMCstopmeas / Run reported failure."""


class ScannerStateError(DriverError):
    """The client is not in a state for this call (closed, not connected, not streaming)."""


@dataclass(frozen=True)
class ScanRecord:
    """A streamed scan with what the host knows about its arrival."""

    scan: Scan
    host_time_s: float
    """``time.monotonic()`` when the bytes completing the telegram were received."""
    raw: bytes | None
    """The telegram as framed on the wire (for raw logging), or None if ``keep_raw`` is off."""


@dataclass(frozen=True)
class _Session:
    """What the device must be told again after a reconnect."""

    login: SetAccessMode | None = None
    scan_config: SetScanConfig | None = None
    scan_data_config: WriteScanDataConfig | None = None
    measuring: bool | None = None  # True after LMCstartmeas, False after LMCstopmeas, None: untouched
    run_after_login: bool = False
    streaming: bool = False


class _Pending:
    def __init__(self, request: Message, link: _Link) -> None:
        self.request = request
        self.link = link
        self.done = threading.Event()
        self.reply: Message | None = None
        self.error: BaseException | None = None


class _Link:
    """One TCP connection with its codec and reader thread."""

    def __init__(self, sock: socket.socket, dialect: Dialect, number: int) -> None:
        self.sock = sock
        self.codec = CoLaConnection(dialect, role="client")
        self.number = number
        self.send_lock = threading.Lock()
        self.alive = True
        self.last_rx = time.monotonic()
        self.scans = 0
        self.thread: threading.Thread | None = None

    def send(self, msg: Message) -> None:
        with self.send_lock:
            data = self.codec.send(msg)
            self.sock.sendall(data)

    def close(self) -> None:
        self.alive = False
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self.sock.close()


class ScannerClient:
    """A connection to one LMS1xx (see the module docstring).

    ``timeout_s`` bounds every request and the TCP connect. ``reconnect`` enables the automatic
    reconnect with ``backoff``. ``queue_size`` bounds the streamed-scan queue. ``stall_timeout_s``
    (default ``max(2 * timeout_s, 1 s)``): a stream that delivered scans and then goes silent for
    this long is treated as a dead link (half-open TCP) and reconnected. ``keep_raw``: keep each
    streamed telegram's bytes in its :class:`ScanRecord` (for raw logging).
    """

    def __init__(
        self,
        host: str,
        port: int | None = None,
        dialect: Dialect | str = Dialect.B,
        *,
        timeout_s: float = 5.0,
        reconnect: bool = True,
        backoff: Backoff | None = None,
        queue_size: int = 256,
        stall_timeout_s: float | None = None,
        keep_raw: bool = True,
    ) -> None:
        try:
            self.dialect = Dialect(dialect.lower() if isinstance(dialect, str) else dialect)
        except ValueError:
            raise ScannerStateError(f"unknown CoLa dialect {dialect!r} (expected 'a' or 'b')") from None
        if timeout_s <= 0:
            raise ScannerStateError(f"timeout_s must be > 0, got {timeout_s}")
        if queue_size < 1:
            raise ScannerStateError(f"queue_size must be >= 1, got {queue_size}")
        self.host = host
        self.port = DEFAULT_PORTS[self.dialect] if port is None else port
        self.timeout_s = timeout_s
        self.reconnect = reconnect
        self.backoff = backoff or Backoff()
        self.stall_timeout_s = max(2.0 * timeout_s, 1.0) if stall_timeout_s is None else stall_timeout_s
        self.keep_raw = keep_raw
        self._stats = StatsCounter()
        self._queue: DroppingQueue[ScanRecord] = DroppingQueue(queue_size)
        self._gaps = GapTracker()
        self._state = threading.Lock()  # guards _link, _pending, _session, _fatal, _reconnector
        self._req_lock = threading.Lock()  # one request in flight (the device serves one at a time)
        self._ready = threading.Event()  # set while a link is up and its session restored
        self._closing = threading.Event()
        self._shutting_down = False
        self._link: _Link | None = None
        self._links_opened = 0
        self._pending: _Pending | None = None
        self._session = _Session()
        self._fatal: BaseException | None = None
        self._reconnector: threading.Thread | None = None
        self._output_rate = 1
        self._drop_logged = 0

    # -- connection -----------------------------------------------------------------------------
    @property
    def address(self) -> str:
        return f"{self.host}:{self.port} (CoLa {self.dialect.value.upper()})"

    @property
    def connected(self) -> bool:
        """True while a link is up and its session is restored."""
        return self._ready.is_set()

    @property
    def stats(self) -> ScannerStats:
        """A snapshot of the counters (see :class:`~drivers.lms100.transport.ScannerStats`)."""
        return self._stats.snapshot()

    @property
    def streaming(self) -> bool:
        return self._session.streaming

    def connect(self) -> ScannerClient:
        """Open the TCP connection (no retries: a first connection that fails raises)."""
        if self._closing.is_set():
            raise ScannerStateError(f"scanner client {self.address} is closed")
        with self._state:
            if self._link is not None or self._reconnector is not None:
                return self
        link = self._open_link()
        with self._state:
            self._link = link
            # a fresh connection after a fatal loss: the device forgot our session
            self._fatal = None
            self._session = _Session()
        self._queue.fail(None)
        self._ready.set()
        log.info("connected to %s", self.address)
        return self

    def close(self) -> None:
        """Stop streaming (best effort), close the connection and stop all threads."""
        if self._closing.is_set():
            return
        self._shutting_down = True
        if self._session.streaming and self._ready.is_set():
            with contextlib.suppress(DriverError, OSError):
                self._request(SubscribeScanData(False), SubscribeScanDataReply, timeout=min(self.timeout_s, 0.5))
        self._closing.set()
        self._ready.clear()
        with self._state:
            link, self._link = self._link, None
            self._fail_pending(ScannerStateError(f"scanner client {self.address} closed"))
            reconnector = self._reconnector
        self._queue.fail(ScannerStateError(f"scanner client {self.address} is closed"))
        self._update_session(streaming=False)
        if link is not None:
            link.close()
            if link.thread is not None and link.thread is not threading.current_thread():
                link.thread.join(timeout=2.0)
        if reconnector is not None and reconnector is not threading.current_thread():
            reconnector.join(timeout=2.0)
        log.info("closed connection to %s; %s", self.address, self.stats)

    def __enter__(self) -> ScannerClient:
        return self.connect()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- commands -------------------------------------------------------------------------------
    def login(self, level: AccessLevel | int = AccessLevel.AUTHORIZED_CLIENT, password_hash: int | None = None) -> None:
        """SetAccessMode. Levels: 2 maintenance, 3 authorized client (needed for every write),
        4 service; ``password_hash`` defaults to the factory hash of the level.

        Logging in switches the laser off on a real LMS1xx: call :meth:`run` afterwards.
        """
        try:
            level_enum = AccessLevel(int(level))
        except ValueError:
            raise LoginError(f"unknown access level {level} (2 maintenance, 3 authorized client, 4 service)") from None
        pw = PASSWORD_HASHES[level_enum] if password_hash is None else password_hash
        if not 0 <= pw <= 0xFFFFFFFF:
            raise LoginError("password hash does not fit 32 bits")  # a secret: never in a message
        msg = SetAccessMode(int(level_enum), pw)
        self._check_login(self._request(msg, SetAccessModeReply), msg)
        self._update_session(login=msg, run_after_login=False)

    def device_ident(self) -> DeviceIdent:
        """``sRN DeviceIdent``: ``.device_name`` and ``.version``."""
        return self._request(ReadDeviceIdent(), DeviceIdent)

    def serial_number(self) -> str:
        return self._request(ReadSerialNumber(), SerialNumber).serial

    def firmware_version(self) -> str:
        """Firmware version with the device's trailing blanks removed (``"V1.80.2"``)."""
        return self._request(ReadFirmwareVersion(), FirmwareVersion).version.rstrip()

    def device_state(self) -> DeviceState:
        """``sRN STlms``: ``.status`` (7 = measuring, see ``.status_text``), temperature flag, clock."""
        return self._request(ReadDeviceState(), DeviceState)

    def device_ready(self) -> int:
        """``sRN SCdevicestate``: 0 busy, 1 ready, 2 error."""
        return self._request(ReadDeviceReady(), DeviceReady).state

    def scan_config(self) -> ScanConfig:
        """``sRN LMPscancfg`` (``.scan_frequency_hz``, ``.angular_resolution_deg``, start/stop deg)."""
        return self._request(ReadScanConfig(), ScanConfig)

    def set_scan_config(
        self, frequency_hz: float, resolution_deg: float, start_deg: float = -45.0, stop_deg: float = 225.0
    ) -> SetScanConfigReply:
        """``sMN mLMPsetscancfg``. An LMS1xx accepts 25 Hz with 0.25 deg and 50 Hz with 0.5 deg only,
        over at most -45..225 deg; a refusal raises :class:`ScanConfigError` with the device's
        status. Needs :meth:`login` first (else ``sFA`` access denied)."""
        if not (frequency_hz > 0 and resolution_deg > 0 and start_deg < stop_deg):
            raise ScanConfigError(
                f"malformed scan configuration: {frequency_hz} Hz, {resolution_deg} deg, {start_deg}..{stop_deg} deg"
            )
        msg = SetScanConfig.from_hz_deg(frequency_hz, resolution_deg, start_deg, stop_deg)
        reply = self._request(msg, SetScanConfigReply)
        if not reply.ok:
            modes = " or ".join(f"{f:g} Hz with {r:g} deg" for f, r in LMS1XX_SCAN_MODES)
            raise ScanConfigError(
                f"{self.address} refused mLMPsetscancfg {frequency_hz:g} Hz, {resolution_deg:g} deg, "
                f"{start_deg:g}..{stop_deg:g} deg: status {reply.status} ({reply.status_text}); "
                f"an LMS1xx accepts {modes} over -45..225 deg",
                reply.status,
            )
        self._update_session(scan_config=msg)
        return reply

    def scan_data_config(self) -> ScanDataConfig:
        """``sRN LMDscandatacfg``: what each scan telegram carries."""
        return self._request(ReadScanDataConfig(), ScanDataConfig)

    def set_scan_data_config(self, config: WriteScanDataConfig | None = None, **fields: Any) -> None:
        """``sWN LMDscandatacfg``; pass a :class:`WriteScanDataConfig` or its fields by name
        (``remission=True, time=True, output_rate=1``...). Needs :meth:`login` first."""
        try:
            cfg = replace(config or WriteScanDataConfig(), **fields)
        except TypeError as exc:
            raise ScanConfigError(f"bad LMDscandatacfg field: {exc}") from None
        if not 1 <= cfg.output_rate <= 50000:
            raise ScanConfigError(f"LMDscandatacfg output_rate must be 1..50000, got {cfg.output_rate}")
        self._request(cfg, WriteScanDataConfigReply)
        self._output_rate = cfg.output_rate
        self._update_session(scan_data_config=cfg)

    def start_measurement(self) -> None:
        """``sMN LMCstartmeas`` (needs :meth:`login`); status 1 (not allowed) raises."""
        reply = self._request(StartMeasurement(), StartMeasurementReply)
        if reply.status != 0:
            raise MeasurementError(f"{self.address} refused LMCstartmeas (status {reply.status}: not allowed)")
        # the counters may run on while measurement was stopped on purpose: no scans were lost then
        self._gaps.reset()
        self._update_session(measuring=True)

    def stop_measurement(self) -> None:
        """``sMN LMCstopmeas`` (needs :meth:`login`)."""
        reply = self._request(StopMeasurement(), StopMeasurementReply)
        if reply.status != 0:
            raise MeasurementError(f"{self.address} refused LMCstopmeas (status {reply.status}: not allowed)")
        self._update_session(measuring=False)

    def run(self) -> None:
        """``sMN Run``: apply settings and return to run level (needed after every log in)."""
        if not self._request(Run(), RunReply).success:
            raise MeasurementError(f"{self.address} answered 'sAN Run 0' (run level refused)")
        self._update_session(run_after_login=True)

    def wait_until_measuring(self, timeout_s: float | None = None, interval_s: float = 0.05) -> DeviceState:
        """Poll ``STlms`` until the device reports state 7 (measuring); DeviceTimeoutError otherwise."""
        limit = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + limit
        while True:
            state = self.device_state()
            if state.measuring:
                return state
            if time.monotonic() >= deadline:
                raise DeviceTimeoutError(
                    f"{self.address} not measuring after {limit:g} s (STlms state {state.status}: {state.status_text})"
                )
            time.sleep(interval_s)

    def ensure_measuring(self, timeout_s: float | None = None) -> DeviceState:
        """If the device is not measuring: log in, LMCstartmeas, Run, and wait for state 7."""
        state = self.device_state()
        if state.measuring:
            return state
        log.info("%s is %s; starting measurement", self.address, state.status_text)
        self.login()
        self.start_measurement()
        self.run()
        return self.wait_until_measuring(timeout_s)

    def poll(self) -> Scan:
        """``sRN LMDscandata``: the device's latest scan, once (not part of the stream's gap count)."""
        scan = self._request(PollScan(), ScanDataReply).scan
        self._stats.add("received")
        return scan

    # -- streaming ------------------------------------------------------------------------------
    def start_streaming(self) -> None:
        """``sEN LMDscandata 1``: scans then arrive in the queue; read them with :meth:`next_scan`."""
        if self._session.scan_data_config is None:
            # the output rate tells how far the scan counter advances per telegram
            try:
                self._output_rate = max(1, self.scan_data_config().output_rate)
            except CoLaError as exc:
                log.info("%s: cannot read LMDscandatacfg (%s); assuming every scan is sent", self.address, exc)
                self._output_rate = 1
        self._gaps.reset()
        reply = self._request(SubscribeScanData(True), SubscribeScanDataReply)
        if not reply.enable:
            raise MeasurementError(f"{self.address} answered 'sEA LMDscandata 0' to a subscription")
        self._update_session(streaming=True)

    def stop_streaming(self) -> None:
        """``sEN LMDscandata 0``. Scans already queued stay readable."""
        self._update_session(streaming=False)
        self._request(SubscribeScanData(False), SubscribeScanDataReply)

    def next_scan(self, timeout: float | None = None) -> Scan:
        """The next streamed scan (oldest first). Waits up to ``timeout`` s (default: the client's
        timeout) and raises :class:`DeviceTimeoutError` if none came; raises the connection error if
        the link is gone for good, and :class:`ScannerStateError` if nothing is queued and the
        client is not streaming."""
        return self.next_record(timeout).scan

    def next_record(self, timeout: float | None = None) -> ScanRecord:
        """Like :meth:`next_scan`, with the host receive time and the raw telegram."""
        wait = self.timeout_s if timeout is None else timeout
        if not self._session.streaming and len(self._queue) == 0:
            raise ScannerStateError(f"not streaming from {self.address}: call start_streaming() first")
        record = self._queue.get(wait)
        if record is None:
            raise DeviceTimeoutError(f"no scan from {self.address} within {wait:g} s")
        return record

    def scans(self, count: int | None = None, timeout: float | None = None) -> Iterator[Scan]:
        """Iterate over streamed scans (``count`` of them, or forever)."""
        n = 0
        while count is None or n < count:
            yield self.next_scan(timeout)
            n += 1

    def __iter__(self) -> Iterator[Scan]:
        return self.scans()

    # -- requests -------------------------------------------------------------------------------
    def request(self, msg: Message, reply_cls: type[R], timeout: float | None = None) -> R:
        """Send any request telegram of :mod:`drivers.lms100.messages` and return its reply as
        ``reply_cls`` (e.g. ``request(ReadOutputRange(), OutputRange)``); ``sFA`` raises
        :class:`DeviceErrorReply`, silence :class:`DeviceTimeoutError`. The session restore after a
        reconnect does not know about telegrams sent this way."""
        if not msg.is_request:
            raise CoLaError(f"{msg.kind} {msg.name} is not a request")
        return self._request(msg, reply_cls, timeout)

    def _request(self, msg: Message, reply_cls: type[R], timeout: float | None = None, link: _Link | None = None) -> R:
        """Send ``msg`` and wait for its reply. ``link`` is given by the session restore only."""
        limit = self.timeout_s if timeout is None else timeout
        deadline = time.monotonic() + limit
        what = f"{msg.kind} {msg.name}"
        while True:
            if link is None:
                self._wait_ready(deadline, what)
            if not self._req_lock.acquire(timeout=max(0.0, deadline - time.monotonic())):
                self._stats.add("timeouts")
                raise DeviceTimeoutError(f"{self.address}: {what} waited {limit:g} s for an earlier request")
            try:
                use = link if link is not None else (self._link if self._ready.is_set() else None)
                if use is None or not use.alive:
                    if link is not None:
                        raise DeviceConnectionError(f"{self.address}: connection lost before {what}")
                    continue  # lost between the wait and the lock: wait again
                return self._exchange(use, msg, reply_cls, deadline, limit)
            finally:
                self._req_lock.release()

    def _exchange(self, link: _Link, msg: Message, reply_cls: type[R], deadline: float, limit: float) -> R:
        what = f"{msg.kind} {msg.name}"
        pending = _Pending(msg, link)
        with self._state:
            self._pending = pending
        if isinstance(msg, _PAUSES_STREAM):
            link.scans = 0  # the stream may pause now (config mode, busy, stopped): not a dead link
        try:
            try:
                link.send(msg)
            except OSError as exc:
                self._link_lost(link, f"send failed: {exc}")
                raise DeviceConnectionError(f"{self.address}: cannot send {what}: {exc}") from None
            if not pending.done.wait(max(0.0, deadline - time.monotonic())):
                self._stats.add("timeouts")
                if self.reconnect and not self._shutting_down:
                    # a late answer could be taken for the answer to the next request: start afresh
                    self._link_lost(link, f"no answer to {what} within {limit:g} s")
                raise DeviceTimeoutError(f"{self.address} did not answer {what} within {limit:g} s")
        finally:
            with self._state:
                if self._pending is pending:
                    self._pending = None
        if pending.error is not None:
            raise pending.error
        reply = pending.reply
        assert reply is not None
        if isinstance(reply, ErrorReply):
            raise DeviceErrorReply(reply.code, f"{self.address}: {what}")
        if not isinstance(reply, reply_cls):
            raise CoLaError(f"{self.address}: expected {reply_cls.__name__} to {what}, got {reply.kind} {reply.name}")
        return reply

    def _wait_ready(self, deadline: float, what: str) -> None:
        while not self._ready.is_set():
            if self._closing.is_set():
                raise ScannerStateError(f"scanner client {self.address} is closed")
            with self._state:
                fatal = self._fatal
                never_connected = self._link is None and self._reconnector is None
            if fatal is not None:
                raise fatal
            if never_connected:
                raise ScannerStateError(f"not connected to {self.address}: call connect() first")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self._stats.add("timeouts")
                raise DeviceTimeoutError(f"{self.address}: {what} not sent: still reconnecting")
            self._ready.wait(min(remaining, 0.1))

    def _check_login(self, reply: SetAccessModeReply, msg: SetAccessMode) -> None:
        if not reply.success:
            # the hash is a secret: the message (logged, stored as a measurement's error) names the level only
            raise LoginError(f"{self.address} refused SetAccessMode level {msg.level}: wrong password hash")

    def _update_session(self, **changes: Any) -> None:
        with self._state:
            self._session = replace(self._session, **changes)

    # -- the reader thread ----------------------------------------------------------------------
    def _open_link(self) -> _Link:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except TimeoutError:
            raise DeviceTimeoutError(f"connecting to {self.address} timed out after {self.timeout_s:g} s") from None
        except OSError as exc:
            raise DeviceConnectionError(f"cannot connect to {self.address}: {exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(0.2)  # the reader wakes up to check for close and stalls
        self._links_opened += 1
        link = _Link(sock, self.dialect, self._links_opened)
        link.thread = threading.Thread(
            target=self._reader, args=(link,), name=f"lms100-reader-{self.host}:{self.port}#{link.number}", daemon=True
        )
        link.thread.start()
        return link

    def _reader(self, link: _Link) -> None:
        reason = "connection closed by the device"
        try:
            while link.alive and not self._closing.is_set():
                try:
                    data = link.sock.recv(65536)
                except TimeoutError:
                    if (
                        self._session.streaming
                        and link.scans > 0
                        and time.monotonic() - link.last_rx > self.stall_timeout_s
                    ):
                        reason = f"stream stalled: no data for {self.stall_timeout_s:g} s"
                        break
                    continue
                except OSError as exc:
                    reason = f"receive failed: {exc}"
                    break
                if not data:
                    break
                link.last_rx = time.monotonic()
                link.codec.receive_data(data)
                self._drain(link, link.last_rx)
        finally:
            if link.alive and not self._closing.is_set():
                self._link_lost(link, reason)

    def _drain(self, link: _Link, host_time_s: float) -> None:
        # the framer and decoder of the link's CoLaConnection, used directly to keep the payload
        framer = link.codec.framer
        while True:
            try:
                payload = framer.next_payload()
                if payload is None:
                    return
                msg = decode_payload(payload, self.dialect)
                if msg.kind not in REPLY_KINDS:
                    raise TelegramError(f"a device does not send {msg.kind} telegrams ({msg.kind} {msg.name})")
            except CoLaError as exc:  # FramingError / TelegramError: the telegram is skipped
                self._stats.add("bad_telegrams")
                log.warning("%s: bad telegram skipped: %s", self.address, exc)
                continue
            if isinstance(msg, ScanDataEvent):
                link.scans += 1
                raw = frame(payload, self.dialect) if self.keep_raw else None
                self._on_scan(ScanRecord(msg.scan, host_time_s, raw))
                continue
            with self._state:
                pending = self._pending
                if pending is not None and pending.link is link and is_reply_to(msg, pending.request):
                    if msg.kind == "sMA":  # method accepted; the sAN with the result follows
                        continue
                    pending.reply = msg
                    pending.done.set()
                    continue
            self._stats.add("unexpected")
            log.debug("%s: unexpected telegram %s %s skipped", self.address, msg.kind, msg.name)

    def _on_scan(self, record: ScanRecord) -> None:
        scan = record.scan
        self._stats.add("received")
        period_us = 1e8 / scan.scan_frequency if scan.scan_frequency > 0 else None
        report = self._gaps.update(scan.scan_counter, scan.time_since_startup_us, period_us, self._output_rate)
        if report.restart:
            self._stats.add("device_restarts")
            log.warning(
                "%s: scan counter or device clock reset (device restarted?); counting starts afresh", self.address
            )
        if report.duplicate:
            self._stats.add("duplicates")
            log.warning("%s: repeated scan (scan counter %d) skipped", self.address, scan.scan_counter)
            return
        if report.lost:
            self._stats.add("lost", report.lost)
            self._stats.add("gaps")
            log.warning(
                "%s: %d scan(s) lost before scan counter %d (telegram counter %d)",
                self.address,
                report.lost,
                scan.scan_counter,
                scan.telegram_counter,
            )
        if not self._queue.put(record):
            self._stats.add("queue_drops")
            self._drop_logged += 1
            if self._drop_logged == 1 or self._drop_logged % 100 == 0:
                log.warning(
                    "%s: scan queue full, oldest scan dropped (%d drops so far): the consumer is too slow",
                    self.address,
                    self._drop_logged,
                )

    # -- losing and restoring the link ----------------------------------------------------------
    def _fail_pending(self, error: BaseException) -> None:
        """Caller holds ``self._state``."""
        pending = self._pending
        if pending is not None and not pending.done.is_set():
            pending.error = error
            pending.done.set()

    def _link_lost(self, link: _Link, reason: str) -> None:
        reconnector: threading.Thread | None = None
        fatal: DeviceConnectionError | None = None
        with self._state:
            if not link.alive:
                return
            link.alive = False
            current = self._link is link
            if current:
                self._link = None
                self._ready.clear()
                # counted before a reconnect can start: no snapshot shows the reconnect without its loss
                self._stats.add("connection_losses")
            if self._pending is not None and self._pending.link is link:
                self._fail_pending(DeviceConnectionError(f"{self.address}: {reason}"))
            if current and not self._closing.is_set():
                if not self.reconnect:
                    fatal = DeviceConnectionError(f"{self.address}: {reason} (reconnect is off)")
                    self._fatal = fatal
                elif self._reconnector is None:
                    reconnector = threading.Thread(
                        target=self._reconnect_loop, name=f"lms100-reconnect-{self.host}:{self.port}", daemon=True
                    )
                    self._reconnector = reconnector
                    reconnector.start()  # under the lock: close() never sees it unstarted
        link.close()
        if not current:
            return
        log.warning("%s: link lost (%s)", self.address, reason)
        if fatal is not None:
            self._queue.fail(fatal)

    def _reconnect_loop(self) -> None:
        """Runs in its own thread until the session is back, the client closes, or it gives up.

        ``self._reconnector`` is cleared under the state lock in the same step that publishes the
        outcome, so a link lost right after a reconnect always starts a new reconnect thread.
        """
        attempt = 0
        for delay in self.backoff.delays():
            attempt += 1
            if self._closing.wait(delay):
                break
            try:
                link = self._open_link()
            except DriverError as exc:
                log.info("%s: reconnect attempt %d failed: %s", self.address, attempt, exc)
                continue
            with self._state:
                if self._closing.is_set():
                    link.close()
                    break
                self._link = link
            try:
                self._restore_session(link)
            except (DriverError, OSError) as exc:
                log.warning("%s: session restore after reconnect failed: %s", self.address, exc)
                self._link_lost(link, f"session restore failed: {exc}")
                continue
            with self._state:
                if not link.alive or self._link is not link:
                    continue
                # counted in the same step that publishes the link: once connected (or once close() finds
                # no reconnect thread to join) the stats include this reconnect
                self._stats.add("reconnects")
                self._reconnector = None
                self._ready.set()
            log.warning("%s: reconnected after %d attempt(s); session restored", self.address, attempt)
            return
        error = DeviceConnectionError(f"{self.address}: gave up reconnecting after {attempt} attempt(s)")
        with self._state:
            self._reconnector = None
            if self._closing.is_set():
                return
            self._fatal = error
        log.error("%s", error)
        self._queue.fail(error)

    def _restore_session(self, link: _Link) -> None:
        s = self._session
        if s.login is not None:
            self._check_login(self._request(s.login, SetAccessModeReply, link=link), s.login)
        if s.scan_config is not None:
            # an LMS1xx is busy for ~30 s after mLMPsetscancfg: only send it if the device lost it
            have = self._request(ReadScanConfig(), ScanConfig, link=link)
            want = s.scan_config
            fields = ("scan_frequency", "angular_resolution", "start_angle", "stop_angle")
            if any(getattr(have, f) != getattr(want, f) for f in fields):
                reply = self._request(want, SetScanConfigReply, link=link)
                if not reply.ok:
                    raise ScanConfigError(f"scan configuration refused on restore: {reply.status_text}", reply.status)
        if s.scan_data_config is not None:
            self._request(s.scan_data_config, WriteScanDataConfigReply, link=link)
        if s.measuring is True:
            if self._request(StartMeasurement(), StartMeasurementReply, link=link).status != 0:
                raise MeasurementError("LMCstartmeas refused on restore")
        elif s.measuring is False:
            self._request(StopMeasurement(), StopMeasurementReply, link=link)
        if s.login is not None and s.run_after_login and not self._request(Run(), RunReply, link=link).success:
            raise MeasurementError("Run refused on restore")
        if s.streaming:
            self._request(SubscribeScanData(True), SubscribeScanDataReply, link=link)


def open_url(url: DeviceURL, **kw: Any) -> ScannerClient:
    """Open ``tcp://HOST[:PORT]?cola=a|b[&timeout=S][&reconnect=0|1][&queue=N]
    [&backoff=S][&backoff_max=S][&retries=N][&stall_timeout=S]`` and connect.

    Without ``cola`` the dialect follows the port (2112: B, otherwise A); without a port it
    follows the dialect (A: 2111, B: 2112). Keyword arguments override the URL
    (``timeout_s``, ``reconnect``, ``backoff``, ``queue_size``, ``stall_timeout_s``), ``keep_raw``
    (default True) is passed on to :class:`ScannerClient`, and ``connect=False`` returns the client
    unconnected.
    """
    if url.scheme != "tcp":
        raise DeviceURLError(f"LMS100 client handles tcp:// URLs, not {url.scheme}:// ({url.raw!r})")
    if not url.host:
        raise DeviceURLError(f"scanner URL {url.raw!r} has no host (expected tcp://HOST:PORT?cola=a|b)")
    if url.path not in ("", "/"):
        raise DeviceURLError(f"scanner URL {url.raw!r} must not have a path ({url.path!r})")
    if url.has("cola"):
        dialect = Dialect(url.get_str("cola", choices=("a", "b")))
    else:
        dialect = Dialect.B if url.port == DEFAULT_PORTS[Dialect.B] else Dialect.A
    timeout_s = url.get_float("timeout", 5.0, lo=0.001, hi=3600.0)
    reconnect = url.get_bool("reconnect", True)
    queue_size = url.get_int("queue", 256, lo=1, hi=1_000_000)
    initial = url.get_float("backoff", 0.2, lo=0.0, hi=600.0)
    maximum = url.get_float("backoff_max", 5.0, lo=0.0, hi=3600.0)
    retries = url.get_int("retries", 0, lo=0, hi=1_000_000)
    stall = url.get_float("stall_timeout", max(2.0 * timeout_s, 1.0), lo=0.01, hi=3600.0)
    url.check_all_used()
    connect = bool(kw.pop("connect", True))
    options: dict[str, Any] = {
        "timeout_s": timeout_s,
        "reconnect": reconnect,
        "backoff": Backoff(initial_s=initial, max_s=max(initial, maximum), max_attempts=retries or None),
        "queue_size": queue_size,
        "stall_timeout_s": stall,
        "keep_raw": True,
    }
    unknown = set(kw) - set(options)
    if unknown:
        raise DeviceURLError(f"unknown keyword argument(s) for the LMS100 client: {', '.join(sorted(unknown))}")
    options.update(kw)
    client = ScannerClient(url.host, url.port, dialect, **options)
    return client.connect() if connect else client
