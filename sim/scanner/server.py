"""TCP server for the simulated LMS100 (the ``sim://`` scanner URL is served by :mod:`service.simdevices`).

:class:`ScannerServer` listens on 127.0.0.1 (port 0: an ephemeral port), serves several clients at
once (one reader thread each), and streams ``sSN LMDscandata`` events from one producer thread:

* real time (the device's clock follows the host clock, optionally scaled by ``time_scale``): each
  scan is sent at its time of transmission; a producer that falls behind skips scans, which the
  scan counter shows;
* fast (``realtime=False`` on the device): scans are made as fast as the subscribed clients read
  them (TCP back-pressure), and the virtual device clock advances by one scan period per scan.

Bytes are framed and parsed by the codec in :mod:`drivers.lms100` (``CoLaConnection`` in the
``device`` role, its framer, and ``decode_payload``).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from types import TracebackType
from typing import Any

from drivers.lms100 import (
    CoLaConnection,
    CoLaError,
    Dialect,
    ErrorReply,
    FramingError,
    Message,
    ScanDataEvent,
    TelegramError,
    decode_payload,
    is_modelled,
)
from sim.scanner.device import Session, SimulatedLMS100, SimulatorError
from sim.scanner.requests import (
    SFA_BUFFER_UNDERFLOW,
    SFA_COLA_A_INVALID_CHARACTER,
    SFA_INTERNAL,
    SFA_UNKNOWN_COLA_COMMAND,
)

log = logging.getLogger(__name__)

_REQUEST_KINDS = frozenset({"sRN", "sWN", "sMN", "sEN", "sRI", "sWI"})
#: A send that makes no progress for this long drops the client (s).
SEND_TIMEOUT_S = 30.0


class _Client:
    def __init__(self, sock: socket.socket, addr: Any, dialect: Dialect, session: Session) -> None:
        self.sock = sock
        self.addr = addr
        self.conn = CoLaConnection(dialect, role="device")
        self.session = session
        self.send_lock = threading.Lock()
        self.closed = False
        self.thread: threading.Thread | None = None

    def send(self, messages: list[Message]) -> None:
        data = b"".join(self.conn.send(m) for m in messages)
        with self.send_lock:
            self.sock.sendall(data)

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self.sock.close()


class ScannerServer:
    """A simulated LMS100 on a real TCP port. Use as a context manager or ``start()``/``stop()``."""

    def __init__(self, device: SimulatedLMS100, host: str = "127.0.0.1", port: int = 0, dialect: str = "b") -> None:
        if dialect not in ("a", "b", Dialect.A, Dialect.B):
            raise SimulatorError(f"dialect must be 'a' or 'b', got {dialect!r}")
        if not 0 <= port <= 65535:
            raise SimulatorError(f"port must be within 0..65535, got {port}")
        self.device = device
        self.host = host
        self.port = port
        self.dialect = Dialect(dialect)
        self._listener: socket.socket | None = None
        self._clients: list[_Client] = []
        self._clients_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.scans_sent = 0
        """Scan telegrams produced by the streaming thread (each counted once, whatever the clients)."""
        self.scans_skipped = 0
        """Scans the real-time streaming thread passed over because it fell behind (it goes on with
        the newest complete scan); the clients see them as scan counter gaps. A starved host makes
        these, not a client."""
        self.framing_errors = 0
        self.connections = 0

    # ------------------------------------------------------------------ life cycle
    @property
    def address(self) -> tuple[str, int]:
        if self._listener is None:
            raise SimulatorError("server is not started")
        host, port = self._listener.getsockname()[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        """``tcp://host:port?cola=a|b``: the URL a driver connects with."""
        host, port = self.address
        return f"tcp://{host}:{port}?cola={self.dialect.value}"

    @property
    def client_count(self) -> int:
        with self._clients_lock:
            return len(self._clients)

    def start(self) -> ScannerServer:
        if self._listener is not None:
            return self
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise SimulatorError(f"cannot listen on {self.host}:{self.port}: {exc}") from None
        sock.listen(8)
        sock.settimeout(0.2)
        self._listener = sock
        self._stop.clear()
        self.device.add_event_listener(self._push_event)
        for target, name in ((self._accept_loop, "accept"), (self._stream_loop, "stream")):
            t = threading.Thread(target=target, name=f"lms100-sim-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        self.device.remove_event_listener(self._push_event)
        with self.device.changed:
            self.device.changed.notify_all()
        if self._listener is not None:
            with contextlib.suppress(OSError):
                self._listener.close()
        self.drop_clients()
        for t in self._threads:
            t.join(timeout=5)
        self._threads.clear()
        self._listener = None

    def __enter__(self) -> ScannerServer:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def drop_clients(self) -> int:
        """Kill every client connection (as a cable pull or a device reboot would); returns how many."""
        with self._clients_lock:
            clients = list(self._clients)
        for c in clients:
            self._remove(c)
        return len(clients)

    def serve_forever(self) -> None:
        """Block until :meth:`stop` (or KeyboardInterrupt)."""
        self.start()
        while not self._stop.wait(0.5):
            pass

    # ------------------------------------------------------------------ connections
    def _remove(self, client: _Client) -> None:
        with self._clients_lock:
            if client in self._clients:
                self._clients.remove(client)
        client.close()
        self.device.close_session(client.session)

    def _accept_loop(self) -> None:
        listener = self._listener
        assert listener is not None
        while not self._stop.is_set():
            try:
                sock, addr = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(SEND_TIMEOUT_S)
            client = _Client(sock, addr, self.dialect, self.device.open_session())
            with self._clients_lock:
                self._clients.append(client)
                self.connections += 1
            t = threading.Thread(target=self._client_loop, args=(client,), name=f"lms100-sim-{addr}", daemon=True)
            client.thread = t
            t.start()

    def _client_loop(self, client: _Client) -> None:
        try:
            while not self._stop.is_set() and not client.closed:
                try:
                    data = client.sock.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not data:
                    break
                client.conn.receive_data(data)
                while True:
                    try:
                        payload = client.conn.framer.next_payload()
                    except FramingError as exc:
                        self.framing_errors += 1
                        log.debug("client %s: %s", client.addr, exc)
                        continue
                    if payload is None:
                        break
                    replies = self._answer(client.session, payload)
                    client.send(replies)
                    if self.device.reboot_requested:
                        self.device.reboot()  # before the connections drop: a reconnect sees the rebooted device
                        self.drop_clients()
                        return
        except (OSError, CoLaError) as exc:
            log.debug("client %s closed: %s", client.addr, exc)
        finally:
            self._remove(client)

    def _answer(self, session: Session, payload: bytes) -> list[Message]:
        try:
            msg = decode_payload(payload, self.dialect)
        except TelegramError as exc:
            reply = ErrorReply(self._decode_error_code(payload))
            self.device.log_rejection(payload, reply, f"cannot decode it: {exc}")
            return [reply]
        if msg.kind not in _REQUEST_KINDS:
            reply = ErrorReply(SFA_UNKNOWN_COLA_COMMAND)
            self.device.log_rejection(msg, reply, f"{msg.kind} is a reply/event type, not a request")
            return [reply]
        try:
            return self.device.handle(session, msg)
        except Exception:  # a bug or a failing motor_angle_at callback: the device reports an internal error
            log.exception("simulated LMS100 failed on %s %s", msg.kind, msg.name)
            return [ErrorReply(SFA_INTERNAL)]

    def _decode_error_code(self, payload: bytes) -> int:
        """sFA code for a telegram that could not be parsed (what an LMS1xx answers, as far as known)."""
        if self.dialect is Dialect.A and any(b < 0x20 or b > 0x7E for b in payload):
            return SFA_COLA_A_INVALID_CHARACTER
        head = payload.split(b" ", 2)
        if len(head) >= 2:
            key = (head[0].decode("latin-1"), head[1].decode("latin-1"))
            if key[0] in _REQUEST_KINDS and is_modelled(*key):
                return SFA_BUFFER_UNDERFLOW  # a known telegram with missing or malformed parameters
        return SFA_UNKNOWN_COLA_COMMAND

    def _push_event(self, session: Session, event: Message) -> None:
        """An I/O event (``sSN LIDoutputstate`` / ``LIDinputstate``) for the client of ``session``."""
        with self._clients_lock:
            clients = [c for c in self._clients if c.session is session and not c.closed]
        for client in clients:
            try:
                client.send([event])
            except (OSError, CoLaError):
                self._remove(client)

    # ------------------------------------------------------------------ streaming
    def _subscribed_clients(self) -> list[_Client]:
        with self._clients_lock:
            return [c for c in self._clients if c.session.subscribed and not c.closed]

    def _stream_loop(self) -> None:
        dev = self.device
        next_index: int | None = None
        while not self._stop.is_set():
            wait_until = send_at = 0.0
            with dev.changed:
                if not self._subscribed_clients() or not dev.streaming():
                    next_index = None
                    dev.changed.wait(0.05)
                    continue
                if dev.clock.realtime:
                    latest = dev.latest_complete_index()
                    index = latest + 1 if next_index is None else max(next_index, latest, dev.epoch_index)
                    while not dev.is_output_scan(index):
                        index += 1
                    if next_index is not None and next_index >= dev.epoch_index:
                        rate = max(1, dev.config.data.output_rate)  # output scans in [next_index, index)
                        self.scans_skipped += (index - 1) // rate - (next_index - 1) // rate
                    timing = dev.timing(index)
                    # Cast once the last beam has been fired (the motor's history is complete
                    # then), send at the scan's time of transmission.
                    wait_until = dev.clock.monotonic_at(timing.end_us)
                    send_at = dev.clock.monotonic_at(timing.transmit_us)
                else:
                    index = dev.next_virtual_index()
                    while not dev.is_output_scan(index):
                        index += 1
                    dev.clock.advance_to(dev.timing(index).transmit_us)
                    dev.mark_virtual_sent(index)
                epoch = dev.epoch_index
            delay = wait_until - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            with dev.lock:
                if dev.epoch_index != epoch or not dev.streaming():
                    next_index = None  # reconfigured or stopped meanwhile
                    continue
            try:
                scan = dev.stamp(dev.make_scan(index))
            except SimulatorError as exc:  # reconfigured between the check and the scan: not sent
                log.debug("scan %d not sent: %s", index, exc)
                next_index = None
                continue
            except Exception:  # keep serving; the scan counter will show the scans that were not sent
                log.exception("simulated scan %d failed", index)
                next_index = None
                self._stop.wait(0.1)
                continue
            delay = send_at - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            self.scans_sent += 1
            event: list[Message] = [ScanDataEvent(scan)]
            for client in self._subscribed_clients():
                try:
                    client.send(event)
                except (OSError, CoLaError):
                    self._remove(client)
            next_index = index + 1
