"""A simulated CAN bus behind a TCP server that speaks the socketcand protocol (raw mode).

The kernel here has no SocketCAN, so the cross-process CAN bus is this server: every process
joins with python-can's own ``socketcand`` interface
(``can.Bus(interface="socketcand", host="127.0.0.1", port=P, channel="can0")``). It listens on
127.0.0.1 only.

Protocol (the subset python-can's client uses, as in socketcand's documentation):

* on connect the server sends ``< hi >``;
* ``< open CHANNEL >`` -> ``< ok >`` (or ``< error ... >`` for an unknown channel);
* ``< rawmode >`` -> ``< ok >``; from then on the client receives every frame other clients
  send on its channel as ``< frame ID SECONDS.MICROS DATA >`` (ID 3 hex digits for standard,
  8 for extended identifiers, DATA the payload as hex digits);
* ``< send ID DLC B0 B1 ... >`` transmits a frame (bytes in hex); like a CAN controller, the
  sender does not receive its own frame back;
* ``< echo >`` -> ``< echo >``; anything else -> ``< error unknown command >``.

python-can's client reads the greeting and each ``< ok >`` with a bare ``recv`` and compares
the whole string, so frames for a client that just entered raw mode are queued and delivered
:attr:`SocketcandServer.join_delay_s` later (they would otherwise arrive glued to its ``< ok >``).
Each client has its own writer thread and queue, so a slow reader never stalls the bus.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import socket
import threading
import time
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


class SocketcandError(Exception):
    """A malformed socketcand command."""


@dataclass(eq=False)
class _Client:
    sock: socket.socket
    addr: tuple[str, int]
    channel: str | None = None
    raw_since: float | None = None  # monotonic time raw mode began (frames are queued from then)
    ok_time: float = 0.0  # monotonic time its "< ok >" was sent
    lock: threading.Lock = field(default_factory=threading.Lock)
    frames: queue.SimpleQueue[str | None] = field(default_factory=queue.SimpleQueue)
    ok_sent: threading.Event = field(default_factory=threading.Event)  # raw mode's "< ok >" is out

    def send(self, text: str) -> None:
        data = text.encode("ascii")
        with self.lock:
            self.sock.sendall(data)

    def writer(self, delay_s: float) -> None:
        """Deliver queued frames, the first ones no earlier than ``delay_s`` after raw mode began."""
        first = True
        while True:
            text = self.frames.get()
            if text is None:
                return
            if first:
                self.ok_sent.wait()
                wait = self.ok_time + delay_s - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                first = False
            try:
                self.send(text)
            except OSError:
                return


def parse_send(command: str) -> tuple[int, bool, bytes]:
    """``< send ID DLC B0 .. >`` -> (arbitration id, extended, data). Raises :class:`SocketcandError`."""
    parts = command[1:-1].split()
    if len(parts) < 3 or parts[0] != "send":
        raise SocketcandError(f"not a send command: {command!r}")
    try:
        id_text = parts[1]
        can_id = int(id_text, 16)
        dlc = int(parts[2], 16)
        data = bytes(int(b, 16) for b in parts[3:])
    except ValueError:
        raise SocketcandError(f"bad number in {command!r}") from None
    extended = len(id_text) > 3
    if not 0 <= dlc <= 8 or len(data) != dlc:
        raise SocketcandError(f"DLC {dlc} does not match {len(data)} data bytes in {command!r}")
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise SocketcandError(f"identifier out of range in {command!r}")
    return can_id, extended, data


def format_frame(can_id: int, extended: bool, data: bytes, timestamp: float) -> str:
    ident = f"{can_id:08X}" if extended else f"{can_id:03X}"
    return f"< frame {ident} {timestamp:.6f} {data.hex().upper()} >"


class SocketcandServer:
    """A socketcand-protocol TCP server on 127.0.0.1 hosting simulated CAN channels."""

    join_delay_s = 0.05

    def __init__(self, host: str = "127.0.0.1", port: int = 0, channels: tuple[str, ...] = ("can0",)) -> None:
        if host not in ("127.0.0.1", "localhost"):
            raise ValueError(f"the simulated CAN bus binds 127.0.0.1 only, not {host!r}")
        self.channels = channels
        self._listener = socket.create_server(("127.0.0.1", port))
        self.host, self.port = self._listener.getsockname()[:2]
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.frames = 0

    def start(self) -> SocketcandServer:
        t = threading.Thread(target=self._accept_loop, name="socketcand-accept", daemon=True)
        t.start()
        self._threads.append(t)
        return self

    def url(self, channel: str = "can0", node: int = 1) -> str:
        return f"canopen+socketcand://{self.host}:{self.port}/{channel}?node={node}"

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self._listener.close()
        with self._lock:
            clients, self._clients = self._clients, []
        for c in clients:
            c.frames.put(None)
            c.ok_sent.set()
            _close_socket(c.sock)
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)

    def __enter__(self) -> SocketcandServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    # ------------------------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        self._listener.settimeout(0.2)
        while not self._stop.is_set():
            try:
                sock, addr = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, addr)
            with self._lock:
                self._clients.append(client)
            t = threading.Thread(target=self._client_loop, args=(client,), name=f"socketcand-{addr[1]}", daemon=True)
            t.start()
            self._threads = [x for x in self._threads if x.is_alive()] + [t]

    def _client_loop(self, client: _Client) -> None:
        buffer = ""
        try:
            client.send("< hi >")
            while not self._stop.is_set():
                try:
                    chunk = client.sock.recv(4096)
                except OSError:
                    break
                if not chunk:
                    break
                buffer += chunk.decode("ascii", errors="replace")
                while True:
                    start = buffer.find("<")
                    if start < 0:
                        buffer = ""
                        break
                    end = buffer.find(">", start)
                    if end < 0:
                        buffer = buffer[start:]
                        if len(buffer) > 512:
                            buffer = ""  # garbage without an end
                        break
                    command = buffer[start : end + 1]
                    buffer = buffer[end + 1 :]
                    self._handle(client, command)
        except OSError:
            pass
        finally:
            with self._lock:
                if client in self._clients:
                    self._clients.remove(client)
            client.frames.put(None)
            client.ok_sent.set()
            _close_socket(client.sock)

    def _handle(self, client: _Client, command: str) -> None:
        words = command[1:-1].split()
        if not words:
            client.send("< error empty command >")
            return
        verb = words[0]
        if verb == "open":
            if len(words) == 2 and words[1] in self.channels and client.channel is None:
                client.channel = words[1]
                client.send("< ok >")
            else:
                client.send("< error could not open bus >")
        elif verb == "rawmode":
            if client.channel is None:
                client.send("< error no bus open >")
            else:
                # in raw mode before the client hears "ok": frames sent by others from the moment
                # it returns are queued for it (and held back join_delay_s, after the "ok")
                client.raw_since = time.monotonic()
                threading.Thread(
                    target=client.writer, args=(self.join_delay_s,), name=f"socketcand-w{client.addr[1]}", daemon=True
                ).start()
                client.send("< ok >")
                client.ok_time = time.monotonic()
                client.ok_sent.set()
        elif verb == "send":
            if client.raw_since is None:
                client.send("< error not in raw mode >")
                return
            try:
                can_id, extended, data = parse_send(command)
            except SocketcandError as exc:
                log.info("socketcand: %s", exc)
                client.send("< error malformed send >")
                return
            self._broadcast(client, format_frame(can_id, extended, data, time.time()))
        elif verb == "echo":
            client.send("< echo >")
        else:
            client.send("< error unknown command >")

    def _broadcast(self, sender: _Client, text: str) -> None:
        self.frames += 1
        with self._lock:
            targets = [
                c for c in self._clients if c is not sender and c.channel == sender.channel and c.raw_since is not None
            ]
        for c in targets:
            c.frames.put(text)


def _close_socket(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    sock.close()


class SimulatedCanDrive:
    """A socketcand server on 127.0.0.1 with a simulated CiA 402 node on its bus.

    ``url`` is the motor URL other processes open (``canopen+socketcand://127.0.0.1:P/can0?node=N``);
    ``drive`` is the :class:`~sim.drive.model.SimDrive` (inject faults there); ``close()`` stops both.
    """

    def __init__(
        self,
        port: int = 0,
        node: int = 1,
        channel: str = "can0",
        *,
        host: str = "127.0.0.1",
        drive: object | None = None,
    ) -> None:
        import can

        from sim.drive.can_node import SimCanNode
        from sim.drive.model import SimDrive

        self.server = SocketcandServer(host, port, channels=(channel,)).start()
        try:
            bus = can.Bus(
                interface="socketcand", host="127.0.0.1", port=self.server.port, channel=channel, tcp_tune=True
            )
        except BaseException:
            self.server.close()
            raise
        sim_drive = drive if isinstance(drive, SimDrive) else SimDrive(node)
        self.node = SimCanNode(bus, sim_drive).start()
        self.drive = sim_drive
        self.channel = channel

    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def url(self) -> str:
        return self.server.url(self.channel, self.drive.node_id)

    def close(self) -> None:
        self.node.stop()
        self.node.bus.shutdown()
        self.server.close()

    def __enter__(self) -> SimulatedCanDrive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
