"""A Modbus RTU slave that serves the simulated CiA 402 drive through the register map.

The drive is :class:`sim.drive.model.SimDrive`, the same model the CANopen node serves, so both
protocols show the same state machine, motion and faults. The register map is
:mod:`drivers.servo.modbus_map` (the default or a TOML file). Transports:

* a **pseudo-terminal pair** (``os.openpty``): the server holds the master side, a client opens the
  slave device (``/dev/pts/N``) with pyserial exactly as it would open ``/dev/ttyUSB0``; optionally
  a symlink with a stable name points at it (like socat's ``link=``);
* a **TCP byte stream on 127.0.0.1** carrying RTU frames unchanged (what pyserial's ``socket://``
  and serial device servers in "raw" mode speak), one master connection at a time.

The core, :meth:`ModbusDriveServer.handle_frame`, is sans-I/O: request frame in, reply frame (or
nothing) out. Frames are delimited by their length where the function code tells it, otherwise by
the silent interval; a frame with a bad CRC, or for another unit, is ignored as the spec requires;
a broadcast (unit 0) write is applied without a reply.

Register semantics: an unmapped register, or a range that cuts a 32-bit object in half, is
exception 02; a value the object's type or the drive refuses is 03 (or 02 for read-only
objects); a refusal because of the drive's state is 04. A multi-register write is validated as a
whole before anything is written, then applied object by object in address order.

Link faults for tests: ``drive.silent`` (the model's "heartbeat_loss" fault) or
:attr:`ModbusDriveServer.silent` make the slave stop answering; :attr:`corrupt_replies` sends that
many replies with a broken CRC.

``start_from_url`` starts a server in the background and returns it; ``serve_from_url`` (what
``lrms sim motor --motor URL`` calls) runs one until SIGINT / SIGTERM. URLs::

    modbus-rtu://                       pty, the client URL names /dev/pts/N
    modbus-rtu:///tmp/lrms-servo        pty plus a symlink /tmp/lrms-servo -> /dev/pts/N
    modbus-rtu://127.0.0.1:5020         TCP on loopback (port 0 = ephemeral); client URL the same form
    modbus-rtu+socket://127.0.0.1:5020  the same

with options ``unit`` (default 1), ``map`` (TOML), ``word_order``, ``baud`` (for the silent
interval; default 115200) and ``position`` (initial position, counts).
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import select
import signal
import socket
import sys
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.errors import DeviceConnectionError, DeviceURLError
from drivers.servo import cia402
from drivers.servo.modbus_map import ModbusMapError, RegisterEntry, RegisterMap, default_map, load_map
from drivers.servo.modbus_rtu import (
    BROADCAST,
    ExceptionCode,
    ModbusExceptionError,
    ModbusFrameError,
    ReadHoldingRegisters,
    ReadHoldingRegistersResponse,
    RtuTiming,
    WriteMultipleRegistersResponse,
    WriteSingleRegister,
    WriteSingleRegisterResponse,
    decode_request,
    encode_exception,
    encode_response,
    request_frame_length,
)
from drivers.url import DeviceURL
from sim.drive.model import ObjectAccessError, SimDrive

__all__ = ["ModbusDriveServer", "ServerStats", "serve_from_url", "start_from_url"]

_ADDRESS_ABORTS = {
    cia402.ABORT_NO_OBJECT,
    cia402.ABORT_NO_SUBINDEX,
    cia402.ABORT_READ_ONLY,
    cia402.ABORT_WRITE_ONLY,
    cia402.ABORT_UNSUPPORTED_ACCESS,
}
_VALUE_ABORTS = {
    cia402.ABORT_INVALID_VALUE,
    cia402.ABORT_VALUE_TOO_HIGH,
    cia402.ABORT_VALUE_TOO_LOW,
    cia402.ABORT_MAX_LESS_THAN_MIN,
    cia402.ABORT_TYPE_MISMATCH,
    cia402.ABORT_LENGTH_TOO_HIGH,
    cia402.ABORT_LENGTH_TOO_LOW,
}


def exception_for_abort(abort_code: int) -> ExceptionCode:
    """The Modbus exception code a CiA 301 abort code of the drive model becomes."""
    if abort_code in _ADDRESS_ABORTS:
        return ExceptionCode.ILLEGAL_DATA_ADDRESS
    if abort_code in _VALUE_ABORTS:
        return ExceptionCode.ILLEGAL_DATA_VALUE
    return ExceptionCode.SERVER_DEVICE_FAILURE


class _Refused(Exception):
    def __init__(self, code: ExceptionCode) -> None:
        self.code = code


@dataclass
class ServerStats:
    frames: int = 0
    replies: int = 0
    exceptions: int = 0
    crc_errors: int = 0
    other_unit: int = 0
    broadcasts: int = 0
    incomplete: int = 0
    ignored_silent: int = 0


class ModbusDriveServer:
    """Modbus RTU slave for one :class:`SimDrive` (see the module docstring)."""

    def __init__(
        self,
        drive: SimDrive,
        register_map: RegisterMap | None = None,
        *,
        unit: int = 1,
        baudrate: int = 115200,
        frame_gap: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 1 <= unit <= 247:
            raise DeviceURLError(f"Modbus unit must be 1..247, got {unit}")
        self.drive = drive
        self.map = register_map or default_map()
        self.unit = unit
        self.timing = RtuTiming(baudrate)
        self._frame_gap = frame_gap
        self.clock = clock
        self.stats = ServerStats()
        self.silent = False
        self.corrupt_replies = 0
        self.url = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cleanup: list[Callable[[], None]] = []

    # ------------------------------------------------------------------------------------------
    # sans-I/O core
    # ------------------------------------------------------------------------------------------
    def handle_frame(self, frame: bytes) -> bytes | None:
        """The reply to one request frame, or ``None`` when the slave must stay silent."""
        self.stats.frames += 1
        try:
            unit, request = decode_request(frame)
        except ModbusFrameError:
            self.stats.crc_errors += 1
            return None
        except ModbusExceptionError as exc:
            if exc.unit != self.unit:
                self.stats.other_unit += 1
                return None
            return self._exception(exc.function, ExceptionCode(exc.code))
        if unit not in (self.unit, BROADCAST):
            self.stats.other_unit += 1
            return None
        if self.silent or self.drive.silent:
            self.stats.ignored_silent += 1
            return None
        if unit == BROADCAST and isinstance(request, ReadHoldingRegisters):
            return None  # cannot happen: the codec refuses broadcast reads when encoding
        try:
            if isinstance(request, ReadHoldingRegisters):
                values = self._read(request.address, request.count)
                reply = encode_response(self.unit, ReadHoldingRegistersResponse(values))
            elif isinstance(request, WriteSingleRegister):
                self._write(request.address, (request.value,))
                reply = encode_response(self.unit, WriteSingleRegisterResponse(request.address, request.value))
            else:
                self._write(request.address, request.values)
                reply = encode_response(self.unit, WriteMultipleRegistersResponse(request.address, len(request.values)))
        except _Refused as refused:
            if unit == BROADCAST:
                return None
            return self._exception(request.function, refused.code)
        if unit == BROADCAST:
            self.stats.broadcasts += 1
            return None
        self.stats.replies += 1
        if self.corrupt_replies > 0:
            self.corrupt_replies -= 1
            reply = reply[:-1] + bytes([reply[-1] ^ 0xFF])
        return reply

    def _exception(self, function: int, code: ExceptionCode) -> bytes:
        self.stats.exceptions += 1
        return encode_exception(self.unit, function, code)

    def _covering(self, address: int, count: int) -> list[RegisterEntry]:
        try:
            return self.map.covering(address, count)
        except ModbusMapError:
            raise _Refused(ExceptionCode.ILLEGAL_DATA_ADDRESS) from None

    def _read(self, address: int, count: int) -> tuple[int, ...]:
        entries = self._covering(address, count)
        if not all(e.readable for e in entries):
            raise _Refused(ExceptionCode.ILLEGAL_DATA_ADDRESS)
        out: list[int] = []
        with self.drive.lock:  # one coherent snapshot of all objects in the range
            for e in entries:
                try:
                    value = self.drive.read(e.index, e.subindex)
                except ObjectAccessError as exc:
                    raise _Refused(exception_for_abort(exc.abort_code)) from None
                try:
                    out.extend(self.map.encode(e, value))
                except ModbusMapError:  # the map's type cannot carry the drive's value
                    raise _Refused(ExceptionCode.SERVER_DEVICE_FAILURE) from None
        return tuple(out)

    def _write(self, address: int, registers: tuple[int, ...]) -> None:
        entries = self._covering(address, len(registers))
        if not all(e.writable for e in entries):
            raise _Refused(ExceptionCode.ILLEGAL_DATA_ADDRESS)
        values: list[tuple[RegisterEntry, int]] = []
        pos = 0
        for e in entries:
            try:
                values.append((e, self.map.decode(e, registers[pos : pos + e.count])))
            except ModbusMapError:
                raise _Refused(ExceptionCode.ILLEGAL_DATA_VALUE) from None
            pos += e.count
        with self.drive.lock:
            for e, v in values:
                try:
                    self.drive.write(e.index, e.subindex, v)
                except ObjectAccessError as exc:
                    raise _Refused(exception_for_abort(exc.abort_code)) from None

    # ------------------------------------------------------------------------------------------
    # byte-stream framing shared by the transports
    # ------------------------------------------------------------------------------------------
    @property
    def frame_gap(self) -> float:
        """Silence after which an incomplete or unknown-length frame is closed. The spec's t3.5 is
        1.75 ms above 19200 baud; a host scheduler can stall a writer that long, so by default the
        server waits at least 20 ms before giving up on a frame whose length it knows."""
        if self._frame_gap is not None:
            return self._frame_gap
        return max(self.timing.t3_5, 0.02)

    def _serve_stream(self, recv: Callable[[float], bytes | None], send: Callable[[bytes], None]) -> None:
        """Serve one byte stream until ``recv`` returns None (closed) or the server stops."""
        buf = bytearray()
        last_rx = self.clock()
        while not self._stop.is_set():
            chunk = recv(self.frame_gap if buf else 0.1)
            if chunk is None:
                return
            now = self.clock()
            if chunk:
                buf += chunk
                last_rx = now
            silent_long = not chunk and now - last_rx >= self.frame_gap
            while buf:
                try:
                    n: int | None = request_frame_length(bytes(buf))
                    known = True
                except ModbusFrameError:
                    n, known = None, False
                if known and n is not None and len(buf) >= n:
                    frame = bytes(buf[:n])
                    del buf[:n]
                elif not known and silent_long:  # unknown function: the silence ends the frame
                    frame = bytes(buf)
                    buf.clear()
                else:
                    if known and silent_long:  # a frame that never completed
                        self.stats.incomplete += 1
                        buf.clear()
                    break
                reply = self.handle_frame(frame)  # a bad frame is dropped; what follows is parsed afresh
                if reply is not None:
                    send(reply)

    # ------------------------------------------------------------------------------------------
    # transports
    # ------------------------------------------------------------------------------------------
    def start_pty(self, link: str | Path | None = None) -> str:
        """Serve on a new pseudo-terminal pair; return the device a client opens (or ``link``)."""
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline, as on a real serial port
        name = os.ttyname(slave)
        path = name
        if link is not None:
            link_path = Path(link)
            if link_path.is_symlink():
                link_path.unlink()
            elif link_path.exists():
                os.close(master)
                os.close(slave)
                raise DeviceConnectionError(f"{link_path} exists and is not a symlink; not replacing it")
            link_path.symlink_to(name)
            path = str(link_path)
            self._cleanup.append(lambda: link_path.unlink(missing_ok=True))

        def recv(timeout: float) -> bytes | None:
            ready, _, _ = select.select([master], [], [], timeout)
            if not ready:
                return b""
            try:
                return os.read(master, 4096)
            except OSError:  # EIO: transient while no slave is open; keep serving
                time.sleep(timeout)
                return b""

        def send(data: bytes) -> None:
            os.write(master, data)

        def close() -> None:
            for fd in (master, slave):
                with contextlib.suppress(OSError):
                    os.close(fd)

        self._cleanup.append(close)
        self._start(lambda: self._serve_stream(recv, send))
        self.url = f"modbus-rtu://{path}?unit={self.unit}"
        return path

    def start_tcp(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Serve RTU frames over TCP on loopback; return (host, port)."""
        try:
            if not ipaddress.ip_address(host).is_loopback:
                raise DeviceURLError(f"the simulated drive binds loopback only, not {host}")
        except ValueError:
            if host != "localhost":
                raise DeviceURLError(f"the simulated drive binds loopback only, not {host!r}") from None
            host = "127.0.0.1"
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((host, port))
        except OSError as exc:
            listener.close()
            raise DeviceConnectionError(f"cannot listen on {host}:{port}: {exc}") from exc
        listener.listen(1)
        listener.settimeout(0.1)
        bound = listener.getsockname()

        def serve() -> None:
            while not self._stop.is_set():
                try:
                    conn, _ = listener.accept()
                except TimeoutError:
                    continue
                except OSError:
                    return
                with conn:
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

                    def recv(timeout: float, conn: socket.socket = conn) -> bytes | None:
                        conn.settimeout(timeout)
                        try:
                            data = conn.recv(4096)
                        except TimeoutError:
                            return b""
                        except OSError:
                            return None
                        return data or None  # b"" from recv means the peer closed

                    def send(data: bytes, conn: socket.socket = conn) -> None:
                        with contextlib.suppress(OSError):
                            conn.sendall(data)

                    self._serve_stream(recv, send)

        self._cleanup.append(listener.close)
        self._start(serve)
        self.url = f"modbus-rtu://{bound[0]}:{bound[1]}?unit={self.unit}"
        return bound[0], bound[1]

    def _start(self, target: Callable[[], None]) -> None:
        if self._thread is not None:
            raise DeviceConnectionError("this Modbus server is already serving")
        self._thread = threading.Thread(target=target, name=f"modbus-slave-{self.unit}", daemon=True)
        self._thread.start()

    def serve_forever(self) -> None:
        """Block until :meth:`close` (from another thread) or KeyboardInterrupt."""
        try:
            while not self._stop.wait(0.5):
                pass
        finally:
            self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        while self._cleanup:
            self._cleanup.pop()()

    def __enter__(self) -> ModbusDriveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_from_url(url: str | DeviceURL, *, drive: SimDrive | None = None, **kwargs: Any) -> ModbusDriveServer:
    """Start a simulated Modbus RTU drive described by ``url`` in a background thread and return it.

    ``server.url`` is the URL a client opens, ``server.drive`` the model (for fault injection),
    ``server.serve_forever()`` blocks, ``server.close()`` stops it.
    """
    if kwargs:
        raise DeviceURLError(f"start_from_url: unexpected keyword argument(s) {', '.join(sorted(kwargs))}")
    u = url if isinstance(url, DeviceURL) else DeviceURL.parse(url)
    unit = u.get_int("unit", 1, lo=1, hi=247)
    baud = u.get_int("baud", 115200, lo=300, hi=4_000_000)
    map_path = u.get_str("map", "")
    word_order = u.get_str("word_order", "", choices=("", "high_first", "low_first"))
    position = u.get_int("position", 0, lo=-(1 << 31), hi=(1 << 31) - 1)
    link: str | None = None
    tcp: tuple[str, int] | None = None
    if u.scheme == "modbus-rtu" and not u.host:
        link = u.path if u.path not in ("", "/") else None
    elif u.scheme in ("modbus-rtu", "modbus-rtu+socket"):
        if u.port is None or not u.host or u.path not in ("", "/"):
            raise DeviceURLError(f"{u.raw!r}: TCP needs 127.0.0.1:PORT (0 = ephemeral) and no path")
        tcp = (u.host, u.port)
    else:
        raise DeviceURLError(
            f"{u.raw!r}: the simulated Modbus drive serves modbus-rtu:// (pty) or modbus-rtu+socket://"
        )
    u.check_all_used()
    regmap = load_map(map_path) if map_path else default_map()
    if word_order:
        regmap = RegisterMap(regmap.entries, word_order, regmap.sample, regmap.source)  # type: ignore[arg-type]
    server = ModbusDriveServer(drive or SimDrive(position=position), regmap, unit=unit, baudrate=baud)
    if tcp is not None:
        server.start_tcp(*tcp)
    else:
        server.start_pty(link)
    return server


def serve_from_url(url: str | DeviceURL) -> int:
    """``lrms sim motor --motor modbus-rtu...``: serve until SIGINT / SIGTERM; returns the exit status.

    Prints ``serving <client URL>`` (flushed) once the port is up, like the CANopen simulator.
    """
    server = start_from_url(url)
    stop = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    try:
        print(f"serving {server.url}", flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            while not stop.wait(0.5):
                pass
        print("stopped", file=sys.stderr, flush=True)
    finally:
        server.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0
